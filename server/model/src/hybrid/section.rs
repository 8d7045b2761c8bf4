//! The `[hybrid]` section of a scene: the family parses and validates its own parameters; the
//! scene hands it the mesh facts it reads ([`HybridMesh`]).

use glam::DVec3;
use serde::Deserialize;

use super::{CoreMassScale, CoreStep, HybridParams, InactiveLayer, ScaledMotion, ShellGeometry};
use crate::ModelError;
use crate::check::{int_in, positive, positive_vec, required};
use crate::meshfree::{KernelKind, MeshfreeParams, MeshfreeVariant};

/// The hybrid part of a scene (`[hybrid]`, with the wall geometry of the built-in mesh).
#[derive(Debug, Clone)]
pub struct HybridScene {
    /// The wall between two ellipsoids (`mesh.builtin` = `"lv"` or `"ellipsoids"`).
    pub geometry: ShellGeometry,
    /// Parameters.
    pub params: HybridParams,
    /// Wanted tetrahedra of the FEM core (`mesh.target_tets`).
    pub core_target_tets: usize,
}

/// The `[mesh]` keys the hybrid section reads, as the scene gives them (lengths in the scene's
/// length unit `unit_m`, metres per unit).
#[derive(Debug, Clone, Copy)]
pub(crate) struct HybridMesh<'a> {
    /// `mesh.builtin`.
    pub(crate) builtin: Option<&'a str>,
    /// `mesh.inner_semi_axes`.
    pub(crate) inner_semi_axes: Option<[f64; 3]>,
    /// `mesh.outer_semi_axes`.
    pub(crate) outer_semi_axes: Option<[f64; 3]>,
    /// `mesh.order`.
    pub(crate) order: Option<i64>,
    /// `mesh.target_tets`.
    pub(crate) target_tets: Option<i64>,
    /// Metres per length unit (`mesh.length_unit`).
    pub(crate) unit_m: f64,
}

/// The `[hybrid]` section as written.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawHybrid {
    variant: Option<String>,
    kernel: Option<String>,
    spacing_m: Option<f64>,
    smoothing_ratio: Option<f64>,
    hourglass_coefficient: Option<f64>,
    core_fraction: Option<f64>,
    surface_target_tets: Option<i64>,
    activation_radius_m: Option<f64>,
    release_radius_m: Option<f64>,
    release_tolerance_m: Option<f64>,
    max_active_particles: Option<i64>,
    contact_stiffness_n_per_m: Option<f64>,
    contact_stiffness_pa_per_m: Option<f64>,
    mass_scale: Option<f64>,
    core_mass_scale: Option<RawCoreMassScale>,
    scaled_motion: Option<String>,
    core_step: Option<String>,
    core_stiffness_margin: Option<f64>,
    inactive_layer: Option<String>,
    safety_factor: Option<f64>,
    max_substeps: Option<i64>,
}

/// `hybrid.core_mass_scale`: a number or a name (`CoreMassScale::parse`).
#[derive(Debug)]
enum RawCoreMassScale {
    Number(f64),
    Name(String),
}

impl<'de> Deserialize<'de> for RawCoreMassScale {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl serde::de::Visitor<'_> for Visitor {
            type Value = RawCoreMassScale;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a number, \"auto\" or \"uniform\"")
            }
            fn visit_f64<E>(self, v: f64) -> Result<Self::Value, E> {
                Ok(RawCoreMassScale::Number(v))
            }
            fn visit_i64<E>(self, v: i64) -> Result<Self::Value, E> {
                Ok(RawCoreMassScale::Number(v as f64))
            }
            fn visit_u64<E>(self, v: u64) -> Result<Self::Value, E> {
                Ok(RawCoreMassScale::Number(v as f64))
            }
            fn visit_str<E>(self, v: &str) -> Result<Self::Value, E> {
                Ok(RawCoreMassScale::Name(v.to_string()))
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// The wall of the hybrid family: `mesh.builtin` "lv" (fixed semi-axes, cut at z = 5 mm) or
/// "ellipsoids" (`mesh.inner_semi_axes`, `mesh.outer_semi_axes`).
fn shell_geometry(mesh: &HybridMesh) -> Result<ShellGeometry, ModelError> {
    let unit_m = mesh.unit_m;
    let mm = 1e-3;
    let geometry = match mesh.builtin {
        Some("lv") => ShellGeometry {
            inner_m: DVec3::new(7.0, 7.0, 17.0) * mm,
            outer_m: DVec3::new(10.0, 10.0, 20.0) * mm,
            z_cut_m: Some(5.0 * mm),
        },
        Some("ellipsoids") => ShellGeometry {
            inner_m: mesh
                .inner_semi_axes
                .map_or(Ok(DVec3::new(6e-3, 6e-3, 12e-3)), |v| {
                    positive_vec("mesh.inner_semi_axes", v, unit_m)
                })?,
            outer_m: mesh
                .outer_semi_axes
                .map_or(Ok(DVec3::new(10e-3, 10e-3, 16e-3)), |v| {
                    positive_vec("mesh.outer_semi_axes", v, unit_m)
                })?,
            z_cut_m: None,
        },
        _ => {
            return Err(ModelError::field(
                "mesh.builtin",
                "model.family = \"hybrid\" needs mesh.builtin = \"lv\" or \"ellipsoids\" (a wall between two ellipsoids)",
            ));
        }
    };
    Ok(geometry)
}

/// The element order of the core (`mesh.order`: 1 or 2, default 1).
fn core_order(mesh: &HybridMesh) -> Result<u8, ModelError> {
    match mesh.order.unwrap_or(1) {
        o @ (1 | 2) => Ok(o as u8),
        o => Err(ModelError::field(
            "mesh.order",
            format!("must be 1 or 2, got {o}"),
        )),
    }
}

/// The meshfree part of `[hybrid]`: variant, kernel, spacing, smoothing, hourglass control.
fn meshfree_params(h: &RawHybrid, d: &MeshfreeParams) -> Result<MeshfreeParams, ModelError> {
    let variant = match h.variant.as_deref() {
        None => MeshfreeVariant::default(),
        Some(v) => MeshfreeVariant::from_name(v).ok_or_else(|| {
            ModelError::field(
                "hybrid.variant",
                format!("unknown variant `{v}` (expected seed or corrected)"),
            )
        })?,
    };
    let kernel = match h.kernel.as_deref() {
        None => KernelKind::default_for(variant),
        Some(k) => KernelKind::from_name(k).ok_or_else(|| {
            ModelError::field(
                "hybrid.kernel",
                format!("unknown kernel `{k}` (expected seed-linear or wendland-c2)"),
            )
        })?,
    };
    let spacing_m = positive(
        "hybrid.spacing_m",
        required("hybrid.spacing_m", h.spacing_m)?,
    )?;
    Ok(MeshfreeParams {
        variant,
        kernel,
        spacing_m,
        smoothing_ratio: h.smoothing_ratio.unwrap_or(d.smoothing_ratio),
        hourglass_coefficient: h.hourglass_coefficient.unwrap_or(d.hourglass_coefficient),
    })
}

/// The parameters of `[hybrid]` (validated), with the core order of `mesh`.
fn hybrid_params(h: &RawHybrid, mesh: &HybridMesh) -> Result<HybridParams, ModelError> {
    let d = HybridParams::default();
    let inactive_layer = h
        .inactive_layer
        .as_deref()
        .map_or(Ok(d.inactive_layer), InactiveLayer::parse)?;
    let core_order = core_order(mesh)?;
    let meshfree = meshfree_params(h, &d.meshfree)?;
    if h.contact_stiffness_n_per_m.is_some() && h.contact_stiffness_pa_per_m.is_some() {
        return Err(ModelError::field(
            "hybrid.contact_stiffness_pa_per_m",
            "give the probe's penalty either per particle (contact_stiffness_n_per_m) or per area (contact_stiffness_pa_per_m), not both",
        ));
    }
    let opt_int = |field: &str, v: Option<i64>, default: usize, lo: i64, hi: i64| {
        v.map_or(Ok(default), |v| int_in(field, v, lo, hi))
    };
    let params = HybridParams {
        meshfree,
        core_fraction: h.core_fraction.unwrap_or(d.core_fraction),
        surface_target_tets: opt_int(
            "hybrid.surface_target_tets",
            h.surface_target_tets,
            d.surface_target_tets,
            100,
            200_000,
        )?,
        activation_radius_m: h.activation_radius_m.unwrap_or(d.activation_radius_m),
        release_radius_m: h.release_radius_m.unwrap_or(d.release_radius_m),
        release_tolerance_m: h.release_tolerance_m.unwrap_or(d.release_tolerance_m),
        max_active_particles: opt_int(
            "hybrid.max_active_particles",
            h.max_active_particles,
            d.max_active_particles,
            1,
            1_000_000,
        )?,
        contact_stiffness_n_per_m: h
            .contact_stiffness_n_per_m
            .unwrap_or(d.contact_stiffness_n_per_m),
        contact_stiffness_pa_per_m: h.contact_stiffness_pa_per_m,
        mass_scale: h.mass_scale.unwrap_or(d.mass_scale),
        core_mass_scale: match &h.core_mass_scale {
            None => CoreMassScale::Uniform,
            Some(RawCoreMassScale::Number(v)) => CoreMassScale::Fixed(*v),
            Some(RawCoreMassScale::Name(t)) => CoreMassScale::parse(t)?,
        },
        scaled_motion: h
            .scaled_motion
            .as_deref()
            .map_or(Ok(d.scaled_motion), ScaledMotion::parse)?,
        core_step: CoreStep::parse(
            h.core_step.as_deref().unwrap_or("explicit"),
            h.core_stiffness_margin,
        )?,
        inactive_layer,
        core_order,
        safety_factor: h.safety_factor.unwrap_or(d.safety_factor),
        max_substeps: opt_int(
            "hybrid.max_substeps",
            h.max_substeps,
            d.max_substeps as usize,
            1,
            10_000,
        )? as u32,
    };
    params.validate()?;
    Ok(params)
}

/// The hybrid part of a scene: section `h` on the mesh facts `mesh`.
fn build_hybrid(h: &RawHybrid, mesh: &HybridMesh) -> Result<HybridScene, ModelError> {
    let geometry = shell_geometry(mesh)?;
    let params = hybrid_params(h, mesh)?;
    let core_target_tets = mesh
        .target_tets
        .map_or(Ok(200), |t| int_in("mesh.target_tets", t, 100, 500_000))?;
    Ok(HybridScene {
        geometry,
        params,
        core_target_tets,
    })
}

/// The `[hybrid]` section: required when the scene's family is hybrid (`wanted`), refused for
/// the others.
pub(crate) fn hybrid_section(
    wanted: bool,
    section: Option<&RawHybrid>,
    mesh: &HybridMesh,
) -> Result<Option<HybridScene>, ModelError> {
    if wanted {
        let section = required("hybrid", section)?;
        Ok(Some(build_hybrid(section, mesh)?))
    } else if section.is_some() {
        Err(ModelError::field(
            "hybrid",
            "is only for model.family = \"hybrid\"",
        ))
    } else {
        Ok(None)
    }
}
