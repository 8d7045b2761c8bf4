//! The `[active_region]` section: the FEM family's condensed region (backward Euler only).

use serde::Deserialize;

use super::condensed::{ActiveRegion, DEFAULT_STIFFNESS_MARGIN};
use super::{IntegratorKind, IntegratorParams};
use crate::ModelError;
use crate::check::{bounded_vec, checked, positive, required};

/// The `[active_region]` section as written (`crate::scene` reads the `fallback_*` keys: the
/// coarse companion is a second scene).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawActiveRegion {
    centre_m: Option<[f64; 3]>,
    radius_m: Option<f64>,
    stiffness_margin: Option<f64>,
    follow: Option<bool>,
    pub(crate) fallback_target_tets: Option<i64>,
    pub(crate) fallback_builtin: Option<String>,
}

/// The active region of `a` (absent: `None`): needs backward Euler on the region's rest factor
/// (no `integrator.linear_solver = "cg"`, no `integrator.stiffness_margin`): `linear_solver` is
/// the scene's `integrator.linear_solver` as written, `stiffness_margin_given` whether the scene
/// sets `integrator.stiffness_margin`.
pub(crate) fn region_section(
    a: Option<&RawActiveRegion>,
    integrator: &IntegratorParams,
    linear_solver: Option<&str>,
    stiffness_margin_given: bool,
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
    if linear_solver == Some("cg") {
        return Err(ModelError::field(
            "integrator.linear_solver",
            "a scene with [active_region] solves with the region's rest factor: remove linear_solver or set \"rest-cholesky\"",
        ));
    }
    if stiffness_margin_given {
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
