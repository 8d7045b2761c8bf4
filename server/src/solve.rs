//! Static solutions of scene files for reference and inspection (`haptic-solve`): the scene's
//! loads applied in increments, Newton at each increment ([`haptic_model::statics`]), follower
//! pressures by a fixed point on the load checked against the true residual, results written as `nodes.csv` and a ParaView `.vtu`
//! in the scene's length unit.

use std::path::Path;

use haptic_model::scene::Scene;
use haptic_model::statics::{StaticParams, free_residual_norm, solve_static};
use haptic_model::{DVec3, ModelError};

/// What a static solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveReport {
    /// Load increments.
    pub load_steps: usize,
    /// Newton iterations over all increments.
    pub newton_iterations: usize,
    /// Newton solves with a frozen load over all increments (one per increment without
    /// follower pressure).
    pub load_passes: usize,
    /// Final free residual `|f_int(x) + f_ext(x)|` with the loads evaluated at the final
    /// configuration (follower pressure included), N.
    pub residual_n: f64,
    /// `residual_n` relative to the norm of the final external load.
    pub relative_residual: f64,
    /// Largest nodal displacement, m.
    pub max_displacement_m: f64,
}

/// Settings of [`solve_scene`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveParams {
    /// Load increments (>= 1).
    pub load_steps: usize,
    /// Largest number of frozen-load Newton solves per increment when a follower pressure
    /// moves the load with the body (default 100: the fixed point converges linearly, slowly
    /// when the pressure is of the order of the stiffness; measured in `docs/decisions.md`).
    pub max_follower_passes: usize,
    /// Relative residual the solve must reach (against the external load norm).
    pub rel_tol: f64,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            load_steps: 1,
            max_follower_passes: 100,
            rel_tol: 1e-9,
        }
    }
}

/// Solves the scene's static equilibrium under its `[loads]`, applied in `params.load_steps`
/// equal increments. In each increment Newton solves with the load frozen at the current
/// shape; with a follower pressure the load is then re-evaluated at the new shape and the
/// solve repeated (a fixed point on the load) until the true residual, with the load at the
/// final shape, is below `params.rel_tol` of the load. Returns the node positions, m.
///
/// # Errors
/// [`ModelError::InvalidInput`] when the scene has no loads; [`ModelError::NoConvergence`]
/// when Newton fails at some increment, or when the follower load has not settled after
/// `max_follower_passes` passes (the message names the increment and the true residual).
pub fn solve_scene(
    scene: &Scene,
    params: &SolveParams,
) -> Result<(Vec<DVec3>, SolveReport), ModelError> {
    if scene.loads.is_empty() {
        return Err(ModelError::InvalidInput(
            "the scene has no [loads] (gravity, pressure or point forces): nothing to solve".into(),
        ));
    }
    let fem = scene.fem_model()?;
    let follower = scene.loads.pressure.iter().any(|p| p.follower);
    let steps = params.load_steps.max(1);
    let mut x = scene.mesh.nodes.clone();
    let mut report = SolveReport {
        load_steps: steps,
        newton_iterations: 0,
        load_passes: 0,
        residual_n: 0.0,
        relative_residual: 0.0,
        max_displacement_m: 0.0,
    };
    let newton = StaticParams {
        rel_tol: params.rel_tol,
        ..StaticParams::default()
    };
    let load_at = |x: &[DVec3], scale: f64| -> Vec<DVec3> {
        scene
            .external_forces(x)
            .into_iter()
            .map(|v| v * scale)
            .collect()
    };
    let norm = |f: &[DVec3]| f.iter().map(|a| a.length_squared()).sum::<f64>().sqrt();
    for k in 1..=steps {
        let scale = k as f64 / steps as f64;
        let mut f = load_at(&x, scale);
        for pass in 1.. {
            let r = solve_static(&fem, &f, &mut x, &newton).map_err(|e| {
                ModelError::NoConvergence(format!("load increment {k}/{steps}: {e}"))
            })?;
            report.newton_iterations += r.iterations;
            report.load_passes += 1;
            if follower {
                f = load_at(&x, scale);
            }
            // The true residual: the load at the shape just found.
            let residual = free_residual_norm(&fem, &f, &x);
            let tol = (params.rel_tol * norm(&f)).max(newton.abs_tol_n);
            report.residual_n = residual;
            report.relative_residual = residual / norm(&f).max(f64::MIN_POSITIVE);
            if residual <= tol {
                break;
            }
            if pass >= params.max_follower_passes {
                return Err(ModelError::NoConvergence(format!(
                    "load increment {k}/{steps}: the follower pressure did not settle in {pass} \
                     passes (residual {residual:.3e} N with the load at the final shape, {:.1e} \
                     of the load; tolerance {tol:.3e} N): use more load steps",
                    report.relative_residual
                )));
            }
        }
    }
    report.max_displacement_m = x
        .iter()
        .zip(&scene.mesh.nodes)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    Ok((x, report))
}

/// Writes `nodes.csv` and `solution.vtu` into `dir` (created if needed), in the scene's length
/// unit.
///
/// # Errors
/// [`ModelError::Io`] when a file cannot be written.
pub fn write_solution(dir: &Path, scene: &Scene, x: &[DVec3]) -> Result<(), ModelError> {
    std::fs::create_dir_all(dir).map_err(|e| ModelError::Io {
        path: dir.display().to_string(),
        source: e,
    })?;
    haptic_model::mesh::export::write_nodes_csv(
        &dir.join("nodes.csv"),
        &scene.mesh.nodes,
        x,
        scene.length_unit_m,
    )?;
    haptic_model::mesh::export::write_vtu(
        &dir.join("solution.vtu"),
        &scene.mesh,
        x,
        scene.length_unit_m,
    )
}
