//! The raw (serde) form of a scene file and its validation into a [`Scene`]: every field is
//! checked for presence, finiteness and range, and errors name it by its dotted path.

use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Deserialize;

use super::builtin::builtin_calibration;
use super::{HybridScene, MassSpringScene, ModelFamily, OrganScene, Scene, TableState};
use crate::ModelError;
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

// ----- validation helpers -----

/// A finite value satisfying `ok`, described by `expect` in the error.
fn checked(field: &str, v: f64, ok: impl Fn(f64) -> bool, expect: &str) -> Result<f64, ModelError> {
    if !v.is_finite() {
        return Err(ModelError::field(
            field,
            format!("must be a finite number, got {v}"),
        ));
    }
    if !ok(v) {
        return Err(ModelError::field(
            field,
            format!("must be {expect}, got {v}"),
        ));
    }
    Ok(v)
}

fn required<T>(field: &str, v: Option<T>) -> Result<T, ModelError> {
    v.ok_or_else(|| ModelError::field(field, "is required but missing"))
}

fn positive(field: &str, v: f64) -> Result<f64, ModelError> {
    checked(field, v, |x| x > 0.0, "> 0")
}

fn non_negative(field: &str, v: f64) -> Result<f64, ModelError> {
    checked(field, v, |x| x >= 0.0, ">= 0")
}

fn positive_vec(field: &str, v: [f64; 3], unit: f64) -> Result<DVec3, ModelError> {
    for x in v {
        positive(field, x)?;
    }
    Ok(DVec3::from_array(v) * unit)
}

fn int_in(field: &str, v: i64, lo: i64, hi: i64) -> Result<usize, ModelError> {
    if v < lo || v > hi {
        return Err(ModelError::field(
            field,
            format!("must be an integer in {lo}..={hi}, got {v}"),
        ));
    }
    Ok(v as usize)
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

/// The coarse whole-body companion of a following region (`active_region.fallback_target_tets`,
/// [`Scene::fallback`]): the scene `text` again, on the built-in mesh `builtin` at about `tets`
/// quadratic tetrahedra (in place of the scene's mesh) without strain smoothing, backward Euler
/// on the whole-body rest factor with the region's stiffness margin, double-precision forces,
/// no active region. Parsed by [`parse_scene`], so every check applies; an error names the
/// fallback's field.
fn fallback_scene(
    text: &str,
    base_dir: &Path,
    name: &str,
    origin: Origin,
    (builtin, tets): (&str, usize),
    stiffness_margin: f64,
) -> Result<Scene, ModelError> {
    let field = "active_region.fallback_target_tets";
    let bad = |e: String| ModelError::field(field, format!("the coarse companion: {e}"));
    let mut doc: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| bad(e.to_string()))?;
    doc.remove("active_region");
    fn table<'a>(doc: &'a mut toml::Table, key: &str) -> Option<&'a mut toml::Table> {
        doc.entry(key)
            .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            .as_table_mut()
    }
    let mesh = table(&mut doc, "mesh").ok_or_else(|| bad("[mesh] is not a table".into()))?;
    if mesh.remove("file").is_some() {
        // The file's parameters are not the built-in's (its length unit names the outputs').
        mesh.retain(|k, _| k == "length_unit");
    }
    mesh.insert("builtin".into(), builtin.into());
    mesh.insert("target_tets".into(), toml::Value::Integer(tets as i64));
    mesh.insert("order".into(), toml::Value::Integer(2));
    mesh.remove("strain_smoothing");
    let integrator =
        table(&mut doc, "integrator").ok_or_else(|| bad("[integrator] is not a table".into()))?;
    integrator.insert("linear_solver".into(), "rest-cholesky".into());
    integrator.insert("stiffness_margin".into(), stiffness_margin.into());
    integrator.remove("force_precision");
    let text = toml::to_string(&doc).map_err(|e| bad(e.to_string()))?;
    parse_scene(&text, base_dir, name, origin).map_err(|e| bad(e.to_string()))
}

/// Refuses a companion whose mesh is not the scene mesh's shape: their bounding boxes (m) must
/// agree to 2 % of the scene mesh's diagonal (a mesh file of another geometry, or in another
/// unit, would be answered by a body the probe is not touching).
fn check_same_shape(mesh: &TetMesh, coarse: &TetMesh) -> Result<(), ModelError> {
    let ((lo, hi), (clo, chi)) = (mesh.bounding_box(), coarse.bounding_box());
    let off = (lo - clo).abs().max((hi - chi).abs()).max_element();
    let size = (hi - lo).length();
    if off > 0.02 * size {
        return Err(ModelError::field(
            "active_region.fallback_builtin",
            format!(
                "the companion's geometry does not match the mesh: bounding boxes differ by {:.3} mm (the mesh spans {:.1} mm)",
                off * 1e3,
                size * 1e3
            ),
        ));
    }
    Ok(())
}

// ----- hybrid section -----

fn build_hybrid(h: &RawHybrid, mesh: &RawMesh, unit_m: f64) -> Result<HybridScene, ModelError> {
    let mm = 1e-3;
    let geometry = match mesh.builtin.as_deref() {
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
    let d = HybridParams::default();
    let inactive_layer = h
        .inactive_layer
        .as_deref()
        .map_or(Ok(d.inactive_layer), InactiveLayer::parse)?;
    let core_order = match mesh.order.unwrap_or(1) {
        o @ (1 | 2) => o as u8,
        o => {
            return Err(ModelError::field(
                "mesh.order",
                format!("must be 1 or 2, got {o}"),
            ));
        }
    };
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
    let opt_int = |field: &str, v: Option<i64>, default: usize, lo: i64, hi: i64| {
        v.map_or(Ok(default), |v| int_in(field, v, lo, hi))
    };
    let params = HybridParams {
        meshfree: MeshfreeParams {
            variant,
            kernel,
            spacing_m,
            smoothing_ratio: h.smoothing_ratio.unwrap_or(d.meshfree.smoothing_ratio),
            hourglass_coefficient: h
                .hourglass_coefficient
                .unwrap_or(d.meshfree.hourglass_coefficient),
        },
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
    let core_target_tets = mesh
        .target_tets
        .map_or(Ok(200), |t| int_in("mesh.target_tets", t, 100, 500_000))?;
    Ok(HybridScene {
        geometry,
        params,
        core_target_tets,
    })
}

// ----- mass-spring section -----

/// The mesh of a spring surface cut from `mesh`: its nodes (in the surface's order), no
/// tetrahedra, its triangles as the surface `name`, and `mesh`'s node groups restricted to it.
fn surface_mesh(mesh: &TetMesh, surface: &SpringSurface, name: &str) -> TetMesh {
    let mut local = vec![u32::MAX; mesh.node_count()];
    for i in 0..surface.node_count() as u32 {
        local[surface.source_node(i) as usize] = i;
    }
    TetMesh {
        nodes: surface.rest().to_vec(),
        tets: Vec::new(),
        tet_edge_nodes: Vec::new(),
        surfaces: vec![crate::mesh::SurfaceGroup {
            name: name.to_string(),
            triangles: surface.triangles().to_vec(),
        }],
        node_groups: mesh
            .node_groups
            .iter()
            .map(|g| crate::mesh::NodeGroup {
                name: g.name.clone(),
                nodes: g
                    .nodes
                    .iter()
                    .filter_map(|&i| local.get(i as usize).copied().filter(|&l| l != u32::MAX))
                    .collect(),
            })
            .filter(|g| !g.nodes.is_empty())
            .collect(),
    }
}

#[allow(clippy::too_many_arguments)]
fn build_mass_spring(
    m: &RawMassSpring,
    mesh: &TetMesh,
    touchable: &[[u32; 3]],
    clamped: &[u32],
    probe: ProbeParams,
    scene_name: &str,
    base_dir: &Path,
    origin: Origin,
) -> Result<MassSpringScene, ModelError> {
    let req = |field: &str, v: Option<f64>| required(&format!("mass_spring.{field}"), v);
    let km = req("mesh_spring_n_per_m", m.mesh_spring_n_per_m)?;
    let kh = req("home_spring_n_per_m", m.home_spring_n_per_m)?;
    let rings = match m.rings {
        None => 1,
        Some(r) => int_in("mass_spring.rings", r, 0, i64::from(MAX_RINGS))? as u32,
    };
    let springs = match m.springs.as_deref() {
        None => SpringRule::Calibrated,
        Some(n) => SpringRule::from_name(n).ok_or_else(|| {
            ModelError::field(
                "mass_spring.springs",
                format!("unknown rule `{n}` (expected \"calibrated\", \"unchanged\" or \"area\")"),
            )
        })?,
    };
    let vertex_rule = match m.vertex_rule.as_deref() {
        None => VertexRule::Keep,
        Some(n) => VertexRule::from_name(n).ok_or_else(|| {
            ModelError::field(
                "mass_spring.vertex_rule",
                format!("unknown rule `{n}` (expected \"keep\" or \"loop\")"),
            )
        })?,
    };
    let params = MassSpringParams {
        mesh_spring_n_per_m: km,
        home_spring_n_per_m: kh,
        damping_n_s_per_m: m.damping_n_s_per_m.unwrap_or(0.0),
        node_mass_kg: req("node_mass_kg", m.node_mass_kg)?,
        subdivision: SubdivisionParams {
            rings,
            springs,
            km_over_kh_after: m.km_over_kh_after.unwrap_or(km / kh),
            vertex_rule,
            coarsen_delay_s: m.coarsen_delay_s.unwrap_or(0.2),
        },
    };
    params.validate()?;
    let surface = SpringSurface::from_mesh(&mesh.nodes, touchable, clamped).map_err(|e| {
        ModelError::field(
            "boundary.touchable",
            format!("the touchable triangles are not a valid spring surface: {e}"),
        )
    })?;
    let file = m
        .calibration_file
        .clone()
        .unwrap_or_else(|| format!("{scene_name}.calibration.csv"));
    let needed = rings > 0 && springs == SpringRule::Calibrated;
    let shape = ContactShape::Probe(probe);
    let key = calibration_key(&surface, &params, shape);
    let path = match origin {
        Origin::Builtin => None,
        Origin::File => Some(base_dir.join(&file)),
    };
    let table = if !needed {
        TableState::NotNeeded
    } else {
        let text = match &path {
            None => builtin_calibration(&file)
                .map(str::to_string)
                .ok_or_else(|| format!("no built-in calibration table `{file}`")),
            Some(p) => std::fs::read_to_string(p).map_err(|e| format!("cannot be read ({e})")),
        };
        let shown = file.clone();
        match text.and_then(|t| CalibrationTable::parse(&t, &shown).map_err(|e| e.to_string())) {
            Err(why) => TableState::Unusable(why),
            Ok(t) if t.key() != key => TableState::Unusable(format!(
                "is stale: computed for key {:016x}, this scene needs {key:016x} (the surface, springs, rings, vertex rule or probe radius changed)",
                t.key()
            )),
            Ok(t) if t.node_count() != surface.node_count() => TableState::Unusable(format!(
                "covers {} nodes, the surface has {}",
                t.node_count(),
                surface.node_count()
            )),
            Ok(t) => TableState::Ready(t),
        }
    };
    let organ = match &m.reference_file {
        None => {
            for (field, given) in [
                ("mass_spring.organ_file", m.organ_file.is_some()),
                ("mass_spring.reference_axis", m.reference_axis.is_some()),
            ] {
                if given {
                    return Err(ModelError::field(
                        field,
                        "needs mass_spring.reference_file (the organ's reference)",
                    ));
                }
            }
            None
        }
        Some(reference) => Some(build_organ(
            m, reference, &surface, &params, &probe, scene_name, base_dir, origin,
        )?),
    };
    Ok(MassSpringScene {
        params,
        surface,
        contact: shape,
        key,
        calibration_file: file,
        calibration_path: path,
        table,
        organ,
    })
}

/// The organ part of a mass-spring scene: the reference (read now: a scene whose reference
/// cannot be read or parsed is refused), its axis, and the organ table (missing, malformed or
/// stale: recorded, refused when a body is started).
#[allow(clippy::too_many_arguments)]
fn build_organ(
    m: &RawMassSpring,
    reference_file: &str,
    surface: &SpringSurface,
    params: &MassSpringParams,
    probe: &ProbeParams,
    scene_name: &str,
    base_dir: &Path,
    origin: Origin,
) -> Result<OrganScene, ModelError> {
    let field = "mass_spring.reference_file";
    let read = |file: &str| -> Result<(String, Option<PathBuf>), String> {
        match origin {
            Origin::Builtin => builtin_calibration(file)
                .map(|t| (t.to_string(), None))
                .ok_or_else(|| format!("no built-in file `{file}`")),
            Origin::File => {
                let p = base_dir.join(file);
                // Named as the scene names it, not where it resolved (issue 47).
                std::fs::read_to_string(&p)
                    .map(|t| (t, Some(p.clone())))
                    .map_err(|e| format!("`{file}` cannot be read ({e})"))
            }
        }
    };
    let (text, _) = read(reference_file).map_err(|e| ModelError::field(field, e))?;
    let reference = OrganReference::parse(&text, reference_file)
        .map_err(|e| ModelError::field(field, e.to_string()))?;
    let axis = DVec3::from_array(m.reference_axis.unwrap_or([0.0, 0.0, 1.0]));
    if !(axis.is_finite() && axis.length() > 0.0) {
        return Err(ModelError::field(
            "mass_spring.reference_axis",
            "must be a finite non-zero vector",
        ));
    }
    let axis = axis.normalize();
    let file = m
        .organ_file
        .clone()
        .unwrap_or_else(|| format!("{scene_name}.organ.csv"));
    let key = organ_key(surface, params, probe, &reference, axis);
    let path = match origin {
        Origin::Builtin => None,
        Origin::File => Some(base_dir.join(&file)),
    };
    let table = read(&file)
        // As the scene names it, not where it resolved (issue 47).
        .and_then(|(t, _)| OrganTable::parse(&t, &file).map_err(|e| e.to_string()))
        .and_then(|t| {
            if t.key() != key {
                Err(format!(
                    "is stale: computed for key {:016x}, this scene needs {key:016x} (the surface, springs, probe, reference or axis changed)",
                    t.key()
                ))
            } else if (t.node_count(), t.edge_count())
                != (surface.node_count(), surface.edge_count())
            {
                Err(format!(
                    "covers {} nodes and {} edges, the surface has {} and {}",
                    t.node_count(),
                    t.edge_count(),
                    surface.node_count(),
                    surface.edge_count()
                ))
            } else {
                Ok(t)
            }
        });
    Ok(OrganScene {
        reference,
        axis,
        key,
        file,
        path,
        table,
    })
}

// ----- loads section -----

/// A finite vector with every component checked and a bounded magnitude.
fn bounded_vec(field: &str, v: [f64; 3], max: f64) -> Result<DVec3, ModelError> {
    for x in v {
        checked(field, x, |_| true, "finite")?;
    }
    let d = DVec3::from_array(v);
    if d.length() > max {
        return Err(ModelError::field(
            field,
            format!("magnitude {:.3e} exceeds the {max:.0e} limit", d.length()),
        ));
    }
    Ok(d)
}

fn build_loads(l: &RawLoads, mesh: &TetMesh, clamped: &[u32]) -> Result<SceneLoads, ModelError> {
    let gravity_m_per_s2 = match l.gravity_m_per_s2 {
        Some(g) => bounded_vec("loads.gravity_m_per_s2", g, MAX_GRAVITY_M_PER_S2)?,
        None => DVec3::ZERO,
    };
    let mut pressure = Vec::new();
    for (k, p) in l.pressure.iter().flatten().enumerate() {
        let field = |name: &str| format!("loads.pressure[{k}].{name}");
        let surfaces = required(&field("surfaces"), p.surfaces.clone())?;
        if surfaces.is_empty() {
            return Err(ModelError::field(field("surfaces"), "names no surface"));
        }
        let mut triangles: Vec<[u32; 3]> = Vec::new();
        for name in &surfaces {
            let Some(s) = mesh.surface(name) else {
                let known: Vec<&str> = mesh.surfaces.iter().map(|s| s.name.as_str()).collect();
                return Err(ModelError::field(
                    field("surfaces"),
                    format!(
                        "no surface named `{name}` (mesh surfaces: {})",
                        known.join(", ")
                    ),
                ));
            };
            triangles.extend(s.triangles.iter().copied());
        }
        let mut seen = std::collections::HashSet::new();
        triangles.retain(|t| {
            let mut key = *t;
            key.sort_unstable();
            seen.insert(key)
        });
        let pressure_pa = checked(
            &field("pressure_pa"),
            required(&field("pressure_pa"), p.pressure_pa)?,
            |x| x.abs() <= MAX_PRESSURE_PA,
            "at most 1e9 Pa in magnitude",
        )?;
        let quadratic = mesh.is_quadratic() && crate::loads::is_quadratic_split(&triangles);
        pressure.push(PressureLoad {
            surfaces,
            triangles,
            pressure_pa,
            follower: p.follower.unwrap_or(false),
            quadratic,
        });
    }
    let mut point = Vec::new();
    if l.point.as_ref().is_some_and(|p| !p.is_empty()) {
        let surface: Vec<[u32; 3]> = mesh
            .boundary_triangles()
            .into_iter()
            .filter(|t| !t.iter().all(|i| clamped.binary_search(i).is_ok()))
            .collect();
        let (lo, hi) = mesh.bounding_box();
        let size = (hi - lo).length();
        for (k, p) in l.point.iter().flatten().enumerate() {
            let field = |name: &str| format!("loads.point[{k}].{name}");
            let at = required(&field("point_m"), p.point_m)?;
            for x in at {
                checked(&field("point_m"), x, |_| true, "finite")?;
            }
            let point_m = DVec3::from_array(at);
            let force_n = bounded_vec(
                &field("force_n"),
                required(&field("force_n"), p.force_n)?,
                MAX_SCENE_POINT_FORCE_N,
            )?;
            let best = surface
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| mesh.nodes[i as usize]);
                    let (q, bary) = crate::contact::closest_point_on_triangle(point_m, a, b, c);
                    (*t, bary, (q - point_m).length())
                })
                .min_by(|a, b| a.2.total_cmp(&b.2));
            let Some((nodes, bary, dist)) = best else {
                return Err(ModelError::field(
                    field("point_m"),
                    "the body has no free boundary surface to load",
                ));
            };
            if dist > size {
                return Err(ModelError::field(
                    field("point_m"),
                    format!(
                        "is {dist:.3e} m from the body's surface, farther than the body's size {size:.3e} m"
                    ),
                ));
            }
            point.push(PointForce {
                point_m,
                force_n,
                nodes,
                bary,
            });
        }
    }
    Ok(SceneLoads {
        gravity_m_per_s2,
        pressure,
        point,
    })
}

/// Length unit name to metres.
fn unit_m(field: &str, name: &str) -> Result<f64, ModelError> {
    match name {
        "m" => Ok(1.0),
        "cm" => Ok(1e-2),
        "mm" => Ok(1e-3),
        "um" => Ok(1e-6),
        _ => Err(ModelError::field(
            field,
            format!("unknown unit `{name}` (expected m, cm, mm or um)"),
        )),
    }
}

fn build_mesh(m: &RawMesh, base_dir: &Path) -> Result<(TetMesh, f64), ModelError> {
    let unit = unit_m("mesh.length_unit", m.length_unit.as_deref().unwrap_or("m"))?;
    // Parameters that only some builtins accept.
    let params: [(&str, bool, &[&str]); 8] = [
        (
            "mesh.target_tets",
            m.target_tets.is_some(),
            &["lv", "ellipsoids", "sphere"],
        ),
        ("mesh.inner_radius", m.inner_radius.is_some(), &["sphere"]),
        (
            "mesh.outer_radius",
            m.outer_radius.is_some(),
            &["sphere", "hemisphere"],
        ),
        ("mesh.edge_length", m.edge_length.is_some(), &["hemisphere"]),
        (
            "mesh.inner_semi_axes",
            m.inner_semi_axes.is_some(),
            &["ellipsoids"],
        ),
        (
            "mesh.outer_semi_axes",
            m.outer_semi_axes.is_some(),
            &["ellipsoids"],
        ),
        ("mesh.size", m.size.is_some(), &["box"]),
        ("mesh.cells", m.cells.is_some(), &["box"]),
    ];
    let builtin = m.builtin.as_deref().unwrap_or("");
    for (field, given, allowed) in params {
        if given && !allowed.contains(&builtin) {
            return Err(ModelError::field(
                field,
                format!(
                    "only applies to mesh.builtin = {}",
                    allowed
                        .iter()
                        .map(|b| format!("\"{b}\""))
                        .collect::<Vec<_>>()
                        .join(" or ")
                ),
            ));
        }
    }
    let target = |default: usize| -> Result<usize, ModelError> {
        m.target_tets
            .map_or(Ok(default), |t| int_in("mesh.target_tets", t, 100, 500_000))
    };
    let quadratic = match m.order.unwrap_or(1) {
        1 => false,
        2 => true,
        other => {
            return Err(ModelError::field(
                "mesh.order",
                format!("must be 1 (linear) or 2 (quadratic), got {other}"),
            ));
        }
    };
    let mesh = match (&m.file, &m.builtin) {
        (Some(_), Some(_)) => {
            return Err(ModelError::field(
                "mesh.builtin",
                "give either mesh.file or mesh.builtin, not both",
            ));
        }
        (None, None) => {
            return Err(ModelError::field(
                "mesh.file",
                "is required (or mesh.builtin)",
            ));
        }
        (Some(file), None) => {
            // Errors name the file as the scene wrote it (issue 47).
            let mut mesh = crate::mesh::gmsh::load_msh_named(&base_dir.join(file), file)?;
            mesh.scale(unit);
            mesh
        }
        (None, Some(b)) => match b.as_str() {
            // Built-in shells get curved quadratic elements (mid-edge nodes on the surfaces).
            "lv" if quadratic => crate::mesh::generate::lv_shell_quadratic(target(2000)?),
            "lv" => crate::mesh::generate::lv_shell(target(2000)?),
            "ellipsoids" => {
                let inner = m
                    .inner_semi_axes
                    .map_or(Ok(DVec3::new(6e-3, 6e-3, 12e-3)), |v| {
                        positive_vec("mesh.inner_semi_axes", v, unit)
                    })?;
                let outer = m
                    .outer_semi_axes
                    .map_or(Ok(DVec3::new(10e-3, 10e-3, 16e-3)), |v| {
                        positive_vec("mesh.outer_semi_axes", v, unit)
                    })?;
                if !inner.cmplt(outer).all() {
                    return Err(ModelError::field(
                        "mesh.outer_semi_axes",
                        "every outer semi-axis must exceed the inner one",
                    ));
                }
                if quadratic {
                    crate::mesh::generate::ellipsoid_shell_quadratic(inner, outer, target(188)?)
                } else {
                    crate::mesh::generate::ellipsoid_shell(inner, outer, target(188)?)
                }
            }
            "sphere" => {
                let ri = positive(
                    "mesh.inner_radius",
                    required("mesh.inner_radius", m.inner_radius)?,
                )? * unit;
                let ro = positive(
                    "mesh.outer_radius",
                    required("mesh.outer_radius", m.outer_radius)?,
                )? * unit;
                if ro <= ri {
                    return Err(ModelError::field(
                        "mesh.outer_radius",
                        "must exceed mesh.inner_radius",
                    ));
                }
                if quadratic {
                    crate::mesh::generate::sphere_shell_quadratic(ri, ro, target(5000)?)
                } else {
                    crate::mesh::generate::sphere_shell(ri, ro, target(5000)?)
                }
            }
            "hemisphere" => {
                let radius = positive(
                    "mesh.outer_radius",
                    required("mesh.outer_radius", m.outer_radius)?,
                )? * unit;
                let edge = positive(
                    "mesh.edge_length",
                    required("mesh.edge_length", m.edge_length)?,
                )? * unit;
                if edge > radius || edge < radius / 200.0 {
                    return Err(ModelError::field(
                        "mesh.edge_length",
                        "must be between outer_radius / 200 and outer_radius",
                    ));
                }
                if quadratic {
                    return Err(ModelError::field(
                        "mesh.order",
                        "the hemisphere is a triangle surface: order = 1 only",
                    ));
                }
                crate::mesh::generate::hemisphere_surface(radius, edge)
            }
            "box" => {
                let size = positive_vec("mesh.size", required("mesh.size", m.size)?, unit)?;
                let c = required("mesh.cells", m.cells)?;
                let mut cells = [0usize; 3];
                for k in 0..3 {
                    cells[k] = int_in("mesh.cells", c[k], 1, 200)?;
                }
                if cells.iter().product::<usize>() > 100_000 {
                    return Err(ModelError::field("mesh.cells", "more than 100000 cells"));
                }
                crate::mesh::generate::box_mesh(size, cells)
            }
            other => {
                return Err(ModelError::field(
                    "mesh.builtin",
                    format!(
                        "unknown builtin mesh `{other}` (expected lv, ellipsoids, sphere, box or hemisphere)"
                    ),
                ));
            }
        },
    };
    let mesh = if quadratic && !mesh.is_quadratic() {
        mesh.to_quadratic()
    } else {
        mesh
    };
    Ok((mesh, unit))
}

/// The Guccione keys of `[material]` (`model = "guccione"`); refused with other models.
fn build_guccione(m: &RawMaterial, density: f64) -> Result<MaterialParams, ModelError> {
    let guccione = m.model.as_deref() == Some("guccione");
    let given: [(&str, bool); 6] = [
        ("material.guccione_c_pa", m.guccione_c_pa.is_some()),
        ("material.b_f", m.b_f.is_some()),
        ("material.b_t", m.b_t.is_some()),
        ("material.b_fs", m.b_fs.is_some()),
        ("material.bulk_modulus_pa", m.bulk_modulus_pa.is_some()),
        ("material.volumetric", m.volumetric.is_some()),
    ];
    if !guccione {
        if let Some((field, _)) = given.iter().find(|g| g.1) {
            return Err(ModelError::field(
                *field,
                "only applies to material.model = \"guccione\"",
            ));
        }
        return Err(ModelError::field(
            "material.model",
            "internal: not guccione",
        ));
    }
    for (field, present) in [
        ("material.youngs_modulus_pa", m.youngs_modulus_pa.is_some()),
        ("material.poisson_ratio", m.poisson_ratio.is_some()),
        ("material.lambda_pa", m.lambda_pa.is_some()),
        ("material.mu_pa", m.mu_pa.is_some()),
    ] {
        if present {
            return Err(ModelError::field(
                field,
                "does not apply to material.model = \"guccione\" (give guccione_c_pa, b_f, b_t, b_fs, bulk_modulus_pa)",
            ));
        }
    }
    let c = positive(
        "material.guccione_c_pa",
        required("material.guccione_c_pa", m.guccione_c_pa)?,
    )?;
    let b = |field: &str, v: Option<f64>| positive(field, required(field, v)?);
    let mean_dilatation = match m.volumetric.as_deref() {
        None | Some("mean-dilatation") => true,
        Some("point") => false,
        Some(other) => {
            return Err(ModelError::field(
                "material.volumetric",
                format!(
                    "unknown volumetric treatment `{other}` (expected \"mean-dilatation\" or \"point\")"
                ),
            ));
        }
    };
    let g = crate::material::GuccioneParams {
        c_pa: c,
        b_f: b("material.b_f", m.b_f)?,
        b_t: b("material.b_t", m.b_t)?,
        b_fs: b("material.b_fs", m.b_fs)?,
        bulk_modulus_pa: positive(
            "material.bulk_modulus_pa",
            required("material.bulk_modulus_pa", m.bulk_modulus_pa)?,
        )?,
        mean_dilatation,
    };
    Ok(MaterialParams::with_guccione(g, density))
}

/// The fibre rule of `[material.fibres]`: `(endo surface, epi surface, rule)`; `None` when the
/// material needs no frame (not an anisotropic Guccione law) and the section is absent.
fn build_fibres(
    m: &RawMaterial,
    mat: &MaterialParams,
    mesh: &TetMesh,
) -> Result<Option<super::FibreSpec>, ModelError> {
    if m.fibres.is_some() && mat.model != MaterialModel::Guccione {
        return Err(ModelError::field(
            "material.fibres",
            "only applies to material.model = \"guccione\"",
        ));
    }
    if m.fibres.is_none() && !mat.is_anisotropic() {
        return Ok(None);
    }
    let f = m.fibres.as_ref();
    let endo = f
        .and_then(|f| f.endo.clone())
        .unwrap_or_else(|| "ENDO".into());
    let epi = f
        .and_then(|f| f.epi.clone())
        .unwrap_or_else(|| "EPI".into());
    for (field, name) in [
        ("material.fibres.endo", &endo),
        ("material.fibres.epi", &epi),
    ] {
        if mesh.surface(name).is_none() {
            let known: Vec<&str> = mesh.surfaces.iter().map(|s| s.name.as_str()).collect();
            return Err(ModelError::field(
                field,
                format!(
                    "no surface named `{name}` for the fibre rule (mesh surfaces: {})",
                    known.join(", ")
                ),
            ));
        }
    }
    let d = crate::element::FibreRule::default();
    let angle = |field: &str, v: Option<f64>, default: f64| {
        checked(
            field,
            v.unwrap_or(default),
            |x| x.abs() <= 180.0,
            "in [-180, 180] degrees",
        )
    };
    let axis = match f.and_then(|f| f.long_axis) {
        Some(a) => {
            let v = bounded_vec("material.fibres.long_axis", a, 1e9)?;
            if v.length() == 0.0 {
                return Err(ModelError::field(
                    "material.fibres.long_axis",
                    "must not be zero",
                ));
            }
            v.normalize()
        }
        None => d.long_axis,
    };
    Ok(Some(super::FibreSpec {
        endo_surface: endo,
        epi_surface: epi,
        rule: crate::element::FibreRule {
            helix_endo_deg: angle(
                "material.fibres.helix_endo_deg",
                f.and_then(|f| f.helix_endo_deg),
                d.helix_endo_deg,
            )?,
            helix_epi_deg: angle(
                "material.fibres.helix_epi_deg",
                f.and_then(|f| f.helix_epi_deg),
                d.helix_epi_deg,
            )?,
            long_axis: axis,
        },
    }))
}

fn build_material(m: &RawMaterial) -> Result<MaterialParams, ModelError> {
    const E: &str = "material.youngs_modulus_pa";
    const NU: &str = "material.poisson_ratio";
    const LAMBDA: &str = "material.lambda_pa";
    const MU: &str = "material.mu_pa";
    let density = required("material.density_kg_per_m3", m.density_kg_per_m3)?;
    let density = positive("material.density_kg_per_m3", density)?;
    if m.model.as_deref() == Some("guccione")
        || m.guccione_c_pa.is_some()
        || m.b_f.is_some()
        || m.b_t.is_some()
        || m.b_fs.is_some()
        || m.bulk_modulus_pa.is_some()
        || m.volumetric.is_some()
    {
        let mut mat = build_guccione(m, density)?;
        mat.phi_pa_s = non_negative("material.phi_pa_s", m.phi_pa_s.unwrap_or(0.0))?;
        mat.psi_pa_s = non_negative("material.psi_pa_s", m.psi_pa_s.unwrap_or(0.0))?;
        mat.mass_damping_per_s = non_negative(
            "material.mass_damping_per_s",
            m.mass_damping_per_s.unwrap_or(0.0),
        )?;
        mat.validate()?;
        return Ok(mat);
    }
    let engineering = m.youngs_modulus_pa.is_some() || m.poisson_ratio.is_some();
    let lame = m.lambda_pa.is_some() || m.mu_pa.is_some();
    let mut mat = match (engineering, lame) {
        (true, true) => {
            let field = if m.lambda_pa.is_some() { LAMBDA } else { MU };
            return Err(ModelError::field(
                field,
                "give exactly one pair: youngs_modulus_pa + poisson_ratio, or lambda_pa + mu_pa",
            ));
        }
        (false, false) => {
            return Err(ModelError::field(
                E,
                "is required (with poisson_ratio), or give lambda_pa + mu_pa",
            ));
        }
        (true, false) => {
            let e = positive(E, required(E, m.youngs_modulus_pa)?)?;
            let nu = checked(
                NU,
                required(NU, m.poisson_ratio)?,
                |x| x > -1.0 && x < 0.5,
                "in (-1, 0.5)",
            )?;
            let mat = MaterialParams::from_youngs(e, nu, density);
            if mat.lambda_pa < 0.0 {
                return Err(ModelError::field(
                    NU,
                    format!("{nu} gives lambda < 0, which the model does not support"),
                ));
            }
            mat
        }
        (false, true) => {
            let lambda = non_negative(LAMBDA, required(LAMBDA, m.lambda_pa)?)?;
            let mu = positive(MU, required(MU, m.mu_pa)?)?;
            MaterialParams {
                model: Default::default(),
                lambda_pa: lambda,
                mu_pa: mu,
                density_kg_per_m3: density,
                ..MaterialParams::from_youngs(1.0, 0.0, 1.0)
            }
        }
    };
    if let Some(name) = &m.model {
        mat.model = MaterialModel::from_scene_name(name).ok_or_else(|| {
            ModelError::field(
                "material.model",
                format!(
                    "unknown material model `{name}` (expected \"stvk\", \"corotational\", \"stable-neo-hookean\" or \"guccione\")"
                ),
            )
        })?;
    }
    mat.phi_pa_s = non_negative("material.phi_pa_s", m.phi_pa_s.unwrap_or(0.0))?;
    mat.psi_pa_s = non_negative("material.psi_pa_s", m.psi_pa_s.unwrap_or(0.0))?;
    mat.mass_damping_per_s = non_negative(
        "material.mass_damping_per_s",
        m.mass_damping_per_s.unwrap_or(0.0),
    )?;
    mat.validate()?;
    Ok(mat)
}

fn build_integrator(i: &RawIntegrator) -> Result<IntegratorParams, ModelError> {
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
    let substeps = match &i.substeps {
        None => None,
        Some(toml::Value::String(s)) if s == "auto" => None,
        Some(toml::Value::Integer(n)) => {
            Some(int_in("integrator.substeps", *n, 1, i64::from(max_substeps))? as u32)
        }
        Some(other) => {
            return Err(ModelError::field(
                "integrator.substeps",
                format!("must be \"auto\" or an integer in 1..={max_substeps}, got {other}"),
            ));
        }
    };
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
    let linear_solver = match i.linear_solver.as_deref() {
        None => d.linear_solver,
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

/// The probe section (every integrator carries every contact model:
/// [`crate::integrate::resolve_contact_model`]).
fn build_probe(p: &RawProbe) -> Result<ProbeParams, ModelError> {
    let d = ProbeParams::default();
    let contact = match p.contact.as_deref() {
        None => d.contact,
        Some(name) => ContactModel::from_name(name).ok_or_else(|| {
            ModelError::field(
                "probe.contact",
                format!(
                    "unknown contact model {:?}: expected \"auto\", \"sphere\", \"patch\", \"patch-hertz\" or \"patch-local\"",
                    name.chars().take(40).collect::<String>()
                ),
            )
        })?,
    };
    let params = ProbeParams {
        contact,
        radius_m: positive("probe.radius_m", p.radius_m.unwrap_or(d.radius_m))?,
        coupling_stiffness_n_per_m: positive(
            "probe.coupling_stiffness_n_per_m",
            p.coupling_stiffness_n_per_m
                .unwrap_or(d.coupling_stiffness_n_per_m),
        )?,
        coupling_damping_n_s_per_m: non_negative(
            "probe.coupling_damping_n_s_per_m",
            p.coupling_damping_n_s_per_m
                .unwrap_or(d.coupling_damping_n_s_per_m),
        )?,
        max_force_n: positive("probe.max_force_n", p.max_force_n.unwrap_or(d.max_force_n))?,
        friction_coefficient: checked(
            "probe.friction_coefficient",
            p.friction_coefficient.unwrap_or(d.friction_coefficient),
            |mu| (0.0..=10.0).contains(&mu),
            "in [0, 10]",
        )?,
        hertz_modulus_pa: d.hertz_modulus_pa,
    };
    Ok(params)
}
