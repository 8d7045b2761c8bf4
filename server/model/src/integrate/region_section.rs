//! The `[active_region]` section: the FEM family's condensed region (backward Euler only).

use serde::Deserialize;

use super::condensed::{ActiveRegion, DEFAULT_STIFFNESS_MARGIN, MIN_TILE_COVER_M, TileMode};
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
    tiles: Option<String>,
    tile_cover_m: Option<f64>,
    pub(crate) fallback_target_tets: Option<i64>,
    pub(crate) fallback_builtin: Option<String>,
}

/// The active region of `a` (absent: `None`): needs backward Euler on the region's rest factor
/// (no `integrator.linear_solver = "cg"`, no `integrator.stiffness_margin`): `linear_solver` is
/// the scene's `integrator.linear_solver` as written, `stiffness_margin_given` whether the scene
/// sets `integrator.stiffness_margin`, `probe_radius_m` the probe's radius (the default tile
/// cover is `radius_m - sqrt(3) probe_radius_m`, the margin a region keeps around the probe's
/// patch).
pub(crate) fn region_section(
    a: Option<&RawActiveRegion>,
    integrator: &IntegratorParams,
    linear_solver: Option<&str>,
    stiffness_margin_given: bool,
    probe_radius_m: f64,
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
    let radius_m = positive(
        "active_region.radius_m",
        required("active_region.radius_m", a.radius_m)?,
    )?;
    let follow = a.follow.unwrap_or(false);
    Ok(Some(ActiveRegion {
        centre_m: bounded_vec("active_region.centre_m", centre, 1e3)?,
        radius_m,
        stiffness_margin: checked(
            "active_region.stiffness_margin",
            a.stiffness_margin.unwrap_or(DEFAULT_STIFFNESS_MARGIN),
            |c| (1.0..=100.0).contains(&c),
            "in [1, 100]",
        )?,
        follow,
        tiles: tile_mode(a, radius_m, follow, probe_radius_m)?,
    }))
}

/// `active_region.tiles` and `active_region.tile_cover_m` ([`TileMode`]).
fn tile_mode(
    a: &RawActiveRegion,
    radius_m: f64,
    follow: bool,
    probe_radius_m: f64,
) -> Result<TileMode, ModelError> {
    match a.tiles.as_deref() {
        None | Some("off") => {
            if a.tile_cover_m.is_some() {
                return Err(ModelError::field(
                    "active_region.tile_cover_m",
                    "needs active_region.tiles = \"background\"",
                ));
            }
            Ok(TileMode::Off)
        }
        Some("background") => {
            if !follow {
                return Err(ModelError::field(
                    "active_region.tiles",
                    "needs active_region.follow = true (tiles are regions a following region swaps in)",
                ));
            }
            let mm = 1e3;
            let cover_m = match a.tile_cover_m {
                Some(c) => checked(
                    "active_region.tile_cover_m",
                    c,
                    |c| c >= MIN_TILE_COVER_M && c <= radius_m,
                    &format!(
                        "at least {:.3} mm ({MIN_TILE_COVER_M} m) and at most radius_m ({radius_m} m)",
                        MIN_TILE_COVER_M * mm,
                    ),
                )?,
                None => {
                    let c = radius_m - 3f64.sqrt() * probe_radius_m;
                    if !(c >= MIN_TILE_COVER_M) {
                        return Err(ModelError::field(
                            "active_region.tile_cover_m",
                            format!(
                                "the default radius_m - sqrt(3) probe.radius_m = {:.3} mm - sqrt(3) x {:.3} mm = {:.3} mm is below {:.3} mm: set tile_cover_m or a larger radius_m",
                                radius_m * mm,
                                probe_radius_m * mm,
                                c * mm,
                                MIN_TILE_COVER_M * mm
                            ),
                        ));
                    }
                    c
                }
            };
            Ok(TileMode::Background { cover_m })
        }
        Some(other) => Err(ModelError::field(
            "active_region.tiles",
            format!("\"{other}\" is not one of \"off\", \"background\""),
        )),
    }
}
