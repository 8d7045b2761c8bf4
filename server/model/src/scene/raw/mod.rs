//! The raw (serde) form of a scene file and its validation into a [`Scene`]: every field is
//! checked for presence, finiteness and range, and errors name it by its dotted path.

use std::path::Path;

use glam::DVec3;
use serde::Deserialize;

use super::builtin::builtin_calibration;
use super::{
    BUILTIN_MESHES, DEFAULT_MAX_TOOLS, MAX_TOOL_ID_CHARS, ModelFamily, NamedTool, Scene, ToolSpec,
};
use crate::ModelError;
use crate::body::MAX_TOOLS;
use crate::check::{bounded_vec, checked, int_in, non_negative, positive, positive_vec, required};
use crate::contact::{ContactModel, ProbeParams};
use crate::element::StrainSmoothing;
use crate::hybrid::section::{RawHybrid, hybrid_section};
use crate::integrate::condensed::ActiveRegion;
use crate::integrate::region_section::{RawActiveRegion, region_section};
use crate::integrate::{IntegratorKind, IntegratorParams, LinearSolver};
use crate::loads::{PointForce, PressureLoad, SceneLoads};
use crate::mass_spring::section::{
    RawMassSpring, TableSource, build_mass_spring, into_spring_mesh,
};
use crate::material::{MaterialModel, MaterialParams};
use crate::mesh::TetMesh;

mod boundary;
mod fallback;
mod family;
mod integrator;
mod loads;
mod material;
mod mesh;
mod probe;

use boundary::*;
use fallback::*;
use family::*;
use integrator::*;
use loads::*;
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
struct RawModel {
    family: Option<String>,
    realtime: Option<bool>,
    offline: Option<String>,
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
    max_tools: Option<i64>,
    tool: Option<Vec<RawTool>>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTool {
    id: Option<String>,
    radius_m: Option<f64>,
    max_force_n: Option<f64>,
}

/// Where a scene's text comes from: a built-in scene reads its calibration table from the
/// library, any other from its directory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Origin {
    Builtin,
    File,
}

impl Origin {
    /// Where a scene of this origin in `base_dir` reads its calibration tables.
    fn table_source(self, base_dir: &Path) -> TableSource<'_> {
        match self {
            Origin::Builtin => TableSource::Builtin(builtin_calibration),
            Origin::File => TableSource::Dir(base_dir),
        }
    }
}

pub(super) fn parse_scene(
    text: &str,
    base_dir: &Path,
    default_name: &str,
    origin: Origin,
) -> Result<Scene, ModelError> {
    let raw: RawScene = super::toml_errors::deserialize(text)?;
    let model = raw.model.unwrap_or_default();
    let family = model_family(model.family.as_deref())?;
    let springs = family == ModelFamily::MassSpring;
    let mesh_raw = required("mesh", raw.mesh)?;
    let (mut mesh, length_unit_m) = build_mesh(&mesh_raw, base_dir)?;
    let strain_smoothing = mesh_rules(&mesh_raw, &mesh, springs)?;
    let (material, fibres) = material_section(raw.material, &mesh, springs)?;
    let boundary = raw.boundary.unwrap_or_default();
    let (mut clamped_nodes, mut touchable) = build_boundary(&boundary, &mesh)?;
    let raw_integrator = raw.integrator.unwrap_or_default();
    let mut integrator = build_integrator(&raw_integrator)?;
    let present = Present {
        loads: raw.loads.is_some(),
        active_region: raw.active_region.is_some(),
        mass_spring: raw.mass_spring.is_some(),
    };
    family_rules(
        springs,
        raw_integrator.kind.as_deref(),
        &mut integrator,
        &present,
    )?;
    let hybrid_mesh = hybrid_mesh(&mesh_raw, length_unit_m);
    let hybrid = hybrid_section(
        family == ModelFamily::Hybrid,
        raw.hybrid.as_ref(),
        &hybrid_mesh,
    )?;
    let (raw_probe, probe) = probe_section(raw.probe)?;
    let loads = build_loads(&raw.loads.unwrap_or_default(), &mesh, &clamped_nodes)?;
    let raw_region = raw.active_region.as_ref();
    let active_region = region_section(
        raw_region,
        &integrator,
        raw_integrator.linear_solver.as_deref(),
        raw_integrator.stiffness_margin.is_some(),
        probe.radius_m,
    )?;
    let name = raw.name.unwrap_or_else(|| default_name.to_string());
    let fallback = match (raw_region, &active_region) {
        (Some(a), Some(region)) => {
            let source = Source {
                text,
                base_dir,
                name: &name,
                origin,
            };
            companion(a, region, &mesh_raw, &mesh, source)?
        }
        _ => None,
    };
    let mass_spring = if springs {
        let section = required("mass_spring", raw.mass_spring)?;
        let source = origin.table_source(base_dir);
        let mut ms = build_mass_spring(
            &section,
            &mesh,
            &touchable,
            &clamped_nodes,
            probe,
            &name,
            source,
        )?;
        (mesh, touchable, clamped_nodes) =
            into_spring_mesh(&mut ms, boundary.touchable.as_deref(), &mesh)?;
        Some(ms)
    } else {
        None
    };
    single_precision_rule(&integrator, &mesh, &material, family)?;
    Ok(Scene {
        name,
        fibres,
        mass_spring,
        hybrid,
        description: raw.description.unwrap_or_default(),
        family,
        realtime: model.realtime.unwrap_or(true),
        offline: offline_reason(model.offline)?,
        mesh,
        strain_smoothing,
        material,
        integrator,
        probe,
        tools: build_tools(&raw_probe, probe, one_tool_reason(family))?,
        clamped_nodes,
        touchable,
        length_unit_m,
        loads,
        active_region,
        fallback,
    })
}

/// The longest `[model] offline` reason, bytes: a sentence or two for an operator, not a file.
const MAX_OFFLINE_REASON_BYTES: usize = 500;

/// `[model] offline`: why the scene is not for the haptic loop, trimmed; refused empty or
/// longer than [`MAX_OFFLINE_REASON_BYTES`].
fn offline_reason(raw: Option<String>) -> Result<Option<String>, ModelError> {
    let Some(reason) = raw else { return Ok(None) };
    let reason = reason.trim();
    if reason.is_empty() {
        return Err(ModelError::field(
            "model.offline",
            "is empty: say why the scene cannot run in the 1 kHz loop and what to use instead",
        ));
    }
    if reason.len() > MAX_OFFLINE_REASON_BYTES {
        return Err(ModelError::field(
            "model.offline",
            format!(
                "is {} bytes; at most {MAX_OFFLINE_REASON_BYTES}",
                reason.len()
            ),
        ));
    }
    Ok(Some(reason.to_string()))
}
