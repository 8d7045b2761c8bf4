//! The raw (serde) form of a scene file and its validation into a [`Scene`]: every field is
//! checked for presence, finiteness and range, and errors name it by its dotted path.

use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Deserialize;

use super::builtin::builtin_calibration;
use super::{HybridScene, MassSpringScene, ModelFamily, OrganScene, Scene, TableState};
use crate::ModelError;
use crate::check::{bounded_vec, checked, int_in, non_negative, positive, positive_vec, required};
use crate::contact::{ContactModel, ProbeParams};
use crate::element::StrainSmoothing;
use crate::hybrid::{
    CoreMassScale, CoreStep, HybridParams, InactiveLayer, ScaledMotion, ShellGeometry,
};
use crate::integrate::condensed::{ActiveRegion, DEFAULT_STIFFNESS_MARGIN};
use crate::integrate::{IntegratorKind, IntegratorParams, LinearSolver};
use crate::loads::{PointForce, PressureLoad, SceneLoads};
use crate::mass_spring::calibration::{CalibrationTable, ContactShape, calibration_key};
use crate::mass_spring::organ::{OrganReference, OrganTable, organ_key};
use crate::mass_spring::{
    MAX_RINGS, MassSpringParams, SpringRule, SpringSurface, SubdivisionParams, VertexRule,
};
use crate::material::{MaterialModel, MaterialParams};
use crate::mesh::TetMesh;
use crate::meshfree::{KernelKind, MeshfreeParams, MeshfreeVariant};

mod fallback;
mod hybrid;
mod integrator;
mod loads;
mod mass_spring;
mod material;
mod mesh;
mod probe;

use fallback::*;
use hybrid::*;
use integrator::*;
use loads::*;
use mass_spring::*;
use material::*;
use mesh::*;
use probe::*;

/// Largest accepted gravitational acceleration magnitude in a scene, m/s^2.
pub const MAX_GRAVITY_M_PER_S2: f64 = 1e4;
/// Largest accepted surface pressure magnitude in a scene, Pa.
pub const MAX_PRESSURE_PA: f64 = 1e9;
/// Largest accepted scene point-force magnitude, N.
pub const MAX_SCENE_POINT_FORCE_N: f64 = 1e9;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScene {
    name: Option<String>,
    description: Option<String>,
    model: Option<RawModel>,
    mesh: Option<RawMesh>,
    material: Option<RawMaterial>,
    boundary: Option<RawBoundary>,
    integrator: Option<RawIntegrator>,
    probe: Option<RawProbe>,
    loads: Option<RawLoads>,
    active_region: Option<RawActiveRegion>,
    mass_spring: Option<RawMassSpring>,
    hybrid: Option<RawHybrid>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHybrid {
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

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMassSpring {
    mesh_spring_n_per_m: Option<f64>,
    home_spring_n_per_m: Option<f64>,
    damping_n_s_per_m: Option<f64>,
    node_mass_kg: Option<f64>,
    rings: Option<i64>,
    springs: Option<String>,
    km_over_kh_after: Option<f64>,
    vertex_rule: Option<String>,
    coarsen_delay_s: Option<f64>,
    calibration_file: Option<String>,
    reference_file: Option<String>,
    reference_axis: Option<[f64; 3]>,
    organ_file: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawModel {
    family: Option<String>,
    realtime: Option<bool>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawActiveRegion {
    centre_m: Option<[f64; 3]>,
    radius_m: Option<f64>,
    stiffness_margin: Option<f64>,
    follow: Option<bool>,
    fallback_target_tets: Option<i64>,
    fallback_builtin: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLoads {
    gravity_m_per_s2: Option<[f64; 3]>,
    pressure: Option<Vec<RawPressure>>,
    point: Option<Vec<RawPoint>>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPressure {
    surfaces: Option<Vec<String>>,
    pressure_pa: Option<f64>,
    follower: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPoint {
    point_m: Option<[f64; 3]>,
    force_n: Option<[f64; 3]>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMesh {
    file: Option<String>,
    builtin: Option<String>,
    length_unit: Option<String>,
    target_tets: Option<i64>,
    inner_radius: Option<f64>,
    outer_radius: Option<f64>,
    inner_semi_axes: Option<[f64; 3]>,
    outer_semi_axes: Option<[f64; 3]>,
    size: Option<[f64; 3]>,
    cells: Option<[i64; 3]>,
    edge_length: Option<f64>,
    order: Option<i64>,
    strain_smoothing: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMaterial {
    model: Option<String>,
    youngs_modulus_pa: Option<f64>,
    poisson_ratio: Option<f64>,
    lambda_pa: Option<f64>,
    mu_pa: Option<f64>,
    phi_pa_s: Option<f64>,
    psi_pa_s: Option<f64>,
    density_kg_per_m3: Option<f64>,
    mass_damping_per_s: Option<f64>,
    guccione_c_pa: Option<f64>,
    b_f: Option<f64>,
    b_t: Option<f64>,
    b_fs: Option<f64>,
    bulk_modulus_pa: Option<f64>,
    volumetric: Option<String>,
    fibres: Option<RawFibres>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFibres {
    endo: Option<String>,
    epi: Option<String>,
    helix_endo_deg: Option<f64>,
    helix_epi_deg: Option<f64>,
    long_axis: Option<[f64; 3]>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBoundary {
    clamped: Option<Vec<String>>,
    touchable: Option<Vec<String>>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIntegrator {
    kind: Option<String>,
    tick_s: Option<f64>,
    substeps: Option<toml::Value>,
    max_substeps: Option<i64>,
    safety_factor: Option<f64>,
    cg_max_iterations: Option<i64>,
    cg_tolerance: Option<f64>,
    linear_solver: Option<String>,
    stiffness_margin: Option<f64>,
    force_precision: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawProbe {
    contact: Option<String>,
    radius_m: Option<f64>,
    coupling_stiffness_n_per_m: Option<f64>,
    coupling_damping_n_s_per_m: Option<f64>,
    max_force_n: Option<f64>,
    friction_coefficient: Option<f64>,
}

/// Where a scene's text comes from: a built-in scene reads its calibration table from the
/// library, any other from its directory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Origin {
    Builtin,
    File,
}

pub(super) fn parse_scene(
    text: &str,
    base_dir: &Path,
    default_name: &str,
    origin: Origin,
) -> Result<Scene, ModelError> {
    let raw: RawScene = super::toml_errors::deserialize(text)?;
    let model = raw.model.unwrap_or_default();
    let realtime = model.realtime.unwrap_or(true);
    let family = match model.family.as_deref() {
        None => ModelFamily::Fem,
        Some(name) => ModelFamily::from_name(name).ok_or_else(|| {
            let known: Vec<&str> = ModelFamily::ALL.iter().map(|f| f.name()).collect();
            ModelError::field(
                "model.family",
                format!(
                    "unknown model family `{name}` (known: {})",
                    known.join(", ")
                ),
            )
        })?,
    };
    let springs = family == ModelFamily::MassSpring;
    let mesh_raw = required("mesh", raw.mesh)?;
    let (mesh, length_unit_m) = build_mesh(&mesh_raw, base_dir)?;
    if !springs && mesh.tets.is_empty() {
        let field = if mesh_raw.builtin.is_some() {
            "mesh.builtin"
        } else {
            "mesh.file"
        };
        return Err(ModelError::field(
            field,
            "the mesh has no tetrahedra: a surface mesh is for model.family = \"mass-spring\"",
        ));
    }
    let strain_smoothing = match mesh_raw.strain_smoothing.as_deref() {
        None => StrainSmoothing::None,
        Some(name) => StrainSmoothing::from_name(name).ok_or_else(|| {
            ModelError::field(
                "mesh.strain_smoothing",
                format!("unknown strain smoothing `{name}` (expected none or edge)"),
            )
        })?,
    };
    if strain_smoothing != StrainSmoothing::None && mesh.is_quadratic() {
        return Err(ModelError::field(
            "mesh.strain_smoothing",
            "strain smoothing is for linear tetrahedra (order = 1)",
        ));
    }
    let (material, fibres) = if springs {
        if raw.material.is_some() {
            return Err(ModelError::field(
                "material",
                "the mass-spring family takes its constants from [mass_spring]: remove [material]",
            ));
        }
        (MaterialParams::default(), None)
    } else {
        let raw_material = required("material", raw.material)?;
        let material = build_material(&raw_material)?;
        let fibres = build_fibres(&raw_material, &material, &mesh)?;
        (material, fibres)
    };
    let boundary = raw.boundary.unwrap_or_default();
    let clamped_nodes = match &boundary.clamped {
        Some(names) => mesh.nodes_of_surfaces(names, "boundary.clamped")?,
        None => Vec::new(),
    };
    let touchable = match &boundary.touchable {
        Some(names) => {
            let mut tris = Vec::new();
            for name in names {
                let Some(s) = mesh.surface(name) else {
                    let known: Vec<&str> = mesh.surfaces.iter().map(|s| s.name.as_str()).collect();
                    return Err(ModelError::field(
                        "boundary.touchable",
                        format!(
                            "no surface named `{name}` (mesh surfaces: {})",
                            known.join(", ")
                        ),
                    ));
                };
                tris.extend(s.triangles.iter().copied());
            }
            let mut seen = std::collections::HashSet::new();
            tris.retain(|t| {
                let mut k = *t;
                k.sort_unstable();
                seen.insert(k)
            });
            tris
        }
        None if mesh.tets.is_empty() => {
            let mut tris: Vec<[u32; 3]> = mesh
                .surfaces
                .iter()
                .flat_map(|s| s.triangles.iter().copied())
                .collect();
            let mut seen = std::collections::HashSet::new();
            tris.retain(|t| {
                let mut k = *t;
                k.sort_unstable();
                seen.insert(k)
            });
            tris
        }
        None => mesh
            .boundary_triangles()
            .into_iter()
            .filter(|t| !t.iter().all(|i| clamped_nodes.binary_search(i).is_ok()))
            .collect(),
    };
    if touchable.is_empty() {
        return Err(ModelError::field(
            "boundary.touchable",
            "no touchable triangle is left",
        ));
    }
    let raw_integrator = raw.integrator.unwrap_or_default();
    let mut integrator = build_integrator(&raw_integrator)?;
    if springs {
        match raw_integrator.kind {
            None => integrator.kind = IntegratorKind::SymplecticEuler,
            Some(_) if integrator.kind == IntegratorKind::SymplecticEuler => {}
            Some(k) => {
                return Err(ModelError::field(
                    "integrator.kind",
                    format!(
                        "the mass-spring family integrates with \"symplectic-euler\" only, got `{k}`"
                    ),
                ));
            }
        }
        if raw.loads.is_some() {
            return Err(ModelError::field(
                "loads",
                "scene loads are not supported by the mass-spring family (clients can still apply point forces)",
            ));
        }
        if raw.active_region.is_some() {
            return Err(ModelError::field(
                "active_region",
                "is for the FEM family with backward Euler",
            ));
        }
    } else if raw.mass_spring.is_some() {
        return Err(ModelError::field(
            "mass_spring",
            "is only for model.family = \"mass-spring\"",
        ));
    }
    let hybrid = if family == ModelFamily::Hybrid {
        let section = required("hybrid", raw.hybrid.as_ref())?;
        Some(build_hybrid(section, &mesh_raw, length_unit_m)?)
    } else if raw.hybrid.is_some() {
        return Err(ModelError::field(
            "hybrid",
            "is only for model.family = \"hybrid\"",
        ));
    } else {
        None
    };
    let probe = build_probe(&raw.probe.unwrap_or_default())?;
    let loads = build_loads(&raw.loads.unwrap_or_default(), &mesh, &clamped_nodes)?;
    let active_region = match &raw.active_region {
        None => None,
        Some(a) => {
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
            Some(ActiveRegion {
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
            })
        }
    };
    let name = raw.name.unwrap_or_else(|| default_name.to_string());
    let fallback = match (&raw.active_region, &active_region) {
        (Some(a), Some(region)) => match a.fallback_target_tets {
            None if a.fallback_builtin.is_some() => {
                return Err(ModelError::field(
                    "active_region.fallback_builtin",
                    "needs active_region.fallback_target_tets",
                ));
            }
            None => None,
            Some(tets) => {
                let field = "active_region.fallback_target_tets";
                if !region.follow {
                    return Err(ModelError::field(
                        field,
                        "needs active_region.follow = true",
                    ));
                }
                let tets = int_in(field, tets, 100, 20_000)?;
                // The companion's geometry: the scene's own built-in, or the one named for a
                // mesh file of the same shape.
                let builtin = match (&a.fallback_builtin, &mesh_raw.builtin) {
                    (Some(b), _) | (None, Some(b)) => b.as_str(),
                    (None, None) => {
                        return Err(ModelError::field(
                            "active_region.fallback_builtin",
                            "is required with a mesh file: the built-in geometry the file meshes (\"lv\", \"ellipsoids\" or \"sphere\")",
                        ));
                    }
                };
                if !matches!(builtin, "lv" | "ellipsoids" | "sphere") {
                    let field = if a.fallback_builtin.is_some() {
                        "active_region.fallback_builtin"
                    } else {
                        field
                    };
                    return Err(ModelError::field(
                        field,
                        format!(
                            "the companion is a built-in \"lv\", \"ellipsoids\" or \"sphere\", not \"{builtin}\""
                        ),
                    ));
                }
                let margin = region.stiffness_margin;
                let coarse =
                    fallback_scene(text, base_dir, &name, origin, (builtin, tets), margin)?;
                check_same_shape(&mesh, &coarse.mesh)?;
                Some(Box::new(coarse))
            }
        },
        _ => None,
    };
    let (mut mesh, mut touchable, mut clamped_nodes) = (mesh, touchable, clamped_nodes);
    let mass_spring = if springs {
        let section = required("mass_spring", raw.mass_spring)?;
        let mut ms = build_mass_spring(
            &section,
            &mesh,
            &touchable,
            &clamped_nodes,
            probe,
            &name,
            base_dir,
            origin,
        )?;
        // The scene's mesh becomes the surface the body simulates (listings and outputs then
        // count its nodes): the spring surface's nodes, no tetrahedra, the touchable triangles
        // as one surface named after the touchable surfaces, node groups restricted to it.
        let names = boundary
            .touchable
            .clone()
            .unwrap_or_else(|| mesh.surfaces.iter().map(|s| s.name.clone()).collect());
        mesh = surface_mesh(&mesh, &ms.surface, &names.join("+"));
        touchable = ms.surface.triangles().to_vec();
        clamped_nodes = (0..ms.surface.node_count() as u32)
            .filter(|&i| ms.surface.is_fixed(i))
            .collect();
        // The same surface, numbered as the new mesh (its key is unchanged).
        let fixed = (0..ms.surface.node_count() as u32)
            .map(|i| ms.surface.is_fixed(i))
            .collect();
        ms.surface = SpringSurface::new(mesh.nodes.clone(), touchable.clone(), fixed)?;
        Some(ms)
    } else {
        None
    };
    if integrator.single_precision_forces
        && (mesh.is_quadratic()
            || crate::element::SingleElastic::of(&material).is_none()
            || family != ModelFamily::Fem)
    {
        return Err(ModelError::field(
            "integrator.force_precision",
            "\"single\" is for linear St Venant-Kirchhoff or stable Neo-Hookean tetrahedra \
             (FEM family)",
        ));
    }
    Ok(Scene {
        name,
        fibres,
        mass_spring,
        hybrid,
        description: raw.description.unwrap_or_default(),
        family,
        realtime,
        mesh,
        strain_smoothing,
        material,
        integrator,
        probe,
        clamped_nodes,
        touchable,
        length_unit_m,
        loads,
        active_region,
        fallback,
    })
}
