//! The `[integrator]` section.

use super::*;

/// `integrator.substeps`: "auto" (absent: `None`) or an integer in `1..=max_substeps`.
fn substeps(value: Option<&toml::Value>, max_substeps: u32) -> Result<Option<u32>, ModelError> {
    match value {
        None => Ok(None),
        Some(toml::Value::String(s)) if s == "auto" => Ok(None),
        Some(toml::Value::Integer(n)) => {
            Ok(Some(
                int_in("integrator.substeps", *n, 1, i64::from(max_substeps))? as u32,
            ))
        }
        Some(other) => Err(ModelError::field(
            "integrator.substeps",
            format!("must be \"auto\" or an integer in 1..={max_substeps}, got {other}"),
        )),
    }
}

/// `integrator.linear_solver` (absent: `default`); "rest-cholesky" needs backward Euler (`kind`).
fn linear_solver(
    name: Option<&str>,
    default: LinearSolver,
    kind: IntegratorKind,
) -> Result<LinearSolver, ModelError> {
    let linear_solver = match name {
        None => default,
        Some(name) => LinearSolver::from_name(name).ok_or_else(|| {
            ModelError::field(
                "integrator.linear_solver",
                format!("unknown linear solver `{name}` (expected \"cg\" or \"rest-cholesky\")"),
            )
        })?,
    };
    if linear_solver == LinearSolver::RestCholesky && kind != IntegratorKind::BackwardEuler {
        return Err(ModelError::field(
            "integrator.linear_solver",
            "\"rest-cholesky\" needs integrator.kind = \"backward-euler\"",
        ));
    }
    Ok(linear_solver)
}

/// The `[integrator]` section (absent keys: [`IntegratorParams::default`]).
pub(super) fn build_integrator(i: &RawIntegrator) -> Result<IntegratorParams, ModelError> {
    let d = IntegratorParams::default();
    let kind = match i.kind.as_deref() {
        None => d.kind,
        Some(name) => IntegratorKind::from_name(name).ok_or_else(|| {
            ModelError::field(
                "integrator.kind",
                format!(
                    "unknown integrator `{name}` (expected \"semi-implicit\", \"symplectic-euler\" or \"backward-euler\")"
                ),
            )
        })?,
    };
    let tick_s = checked(
        "integrator.tick_s",
        i.tick_s.unwrap_or(d.tick_s),
        |x| x > 0.0 && x <= 0.1,
        "in (0, 0.1]",
    )?;
    let max_substeps = match i.max_substeps {
        None => d.max_substeps,
        Some(v) => int_in("integrator.max_substeps", v, 1, 100_000)? as u32,
    };
    let substeps = substeps(i.substeps.as_ref(), max_substeps)?;
    let safety_factor = checked(
        "integrator.safety_factor",
        i.safety_factor.unwrap_or(d.safety_factor),
        |x| x > 0.0 && x <= 1.0,
        "in (0, 1]",
    )?;
    let cg_max_iterations = match i.cg_max_iterations {
        None => d.cg_max_iterations,
        Some(v) => int_in("integrator.cg_max_iterations", v, 1, 10_000)? as u32,
    };
    let cg_tolerance = checked(
        "integrator.cg_tolerance",
        i.cg_tolerance.unwrap_or(d.cg_tolerance),
        |x| x > 0.0 && x < 1.0,
        "in (0, 1)",
    )?;
    let linear_solver = linear_solver(i.linear_solver.as_deref(), d.linear_solver, kind)?;
    if i.stiffness_margin.is_some() && linear_solver != LinearSolver::RestCholesky {
        return Err(ModelError::field(
            "integrator.stiffness_margin",
            "applies to integrator.linear_solver = \"rest-cholesky\" only",
        ));
    }
    let stiffness_margin = checked(
        "integrator.stiffness_margin",
        i.stiffness_margin.unwrap_or(d.stiffness_margin),
        |c| (1.0..=100.0).contains(&c),
        "in [1, 100]",
    )?;
    let single_precision_forces = match i.force_precision.as_deref() {
        None | Some("double") => false,
        Some("single") => true,
        Some(other) => {
            return Err(ModelError::field(
                "integrator.force_precision",
                format!("unknown precision `{other}` (expected \"double\" or \"single\")"),
            ));
        }
    };
    Ok(IntegratorParams {
        kind,
        tick_s,
        substeps,
        max_substeps,
        safety_factor,
        cg_max_iterations,
        cg_tolerance,
        linear_solver,
        stiffness_margin,
        check_critical_step: true,
        single_precision_forces,
    })
}
