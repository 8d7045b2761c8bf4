//! The `[active_region]` section: the FEM family's condensed region (backward Euler only).

use super::*;

/// The active region of `a` (absent: `None`): needs backward Euler on the region's rest factor
/// (no `integrator.linear_solver = "cg"`, no `integrator.stiffness_margin`).
pub(super) fn region_section(
    a: Option<&RawActiveRegion>,
    integrator: &IntegratorParams,
    raw_integrator: &RawIntegrator,
) -> Result<Option<ActiveRegion>, ModelError> {
    let Some(a) = a else {
        return Ok(None);
    };
    if integrator.kind != IntegratorKind::BackwardEuler {
        return Err(ModelError::field(
            "active_region",
            "needs integrator.kind = \"backward-euler\"",
        ));
    }
    if raw_integrator.linear_solver.as_deref() == Some("cg") {
        return Err(ModelError::field(
            "integrator.linear_solver",
            "a scene with [active_region] solves with the region's rest factor: remove linear_solver or set \"rest-cholesky\"",
        ));
    }
    if raw_integrator.stiffness_margin.is_some() {
        return Err(ModelError::field(
            "integrator.stiffness_margin",
            "a scene with [active_region] takes active_region.stiffness_margin",
        ));
    }
    let centre = required("active_region.centre_m", a.centre_m)?;
    Ok(Some(ActiveRegion {
        centre_m: bounded_vec("active_region.centre_m", centre, 1e3)?,
        radius_m: positive(
            "active_region.radius_m",
            required("active_region.radius_m", a.radius_m)?,
        )?,
        stiffness_margin: checked(
            "active_region.stiffness_margin",
            a.stiffness_margin.unwrap_or(DEFAULT_STIFFNESS_MARGIN),
            |c| (1.0..=100.0).contains(&c),
            "in [1, 100]",
        )?,
        follow: a.follow.unwrap_or(false),
    }))
}
