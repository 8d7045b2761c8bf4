//! Building a [`MassSpringBody`]: checks, rest positions, masses and damping, the
//! worst-case sub-step plan (module documentation of [`super`]).

use glam::DVec3;

use super::{
    Centre, EventScratch, EventStats, ForceBlend, MAX_CENTRES, MassSpringBody, MassSpringModel,
    MassSpringScratch, MassSpringSetup, MassSpringState, ToolContact,
};
use crate::ModelError;
use crate::contact::{ContactModel, Probe, ProbeParams};
use crate::integrate::{IntegratorKind, IntegratorParams, plan_steps};
use crate::loads::{BodyLoads, SceneLoads};
use crate::mass_spring::calibration::CalibrationTable;
use crate::mass_spring::contact_rest::{arc_midpoint, contact_rest_positions};
use crate::mass_spring::loop_rules::loop_rest_positions;
use crate::mass_spring::mixed::MixedMesh;
use crate::mass_spring::network::{critical_time_step_s, gershgorin_bound_per_s2};
use crate::mass_spring::refine::{NO_OWNER, Refinement};
use crate::mass_spring::surface::SpringSurface;
use crate::mass_spring::{MassSpringParams, SpringRule, prefaulted};

impl MassSpringBody {
    /// Builds the body on `surface` with `params`; `table` is the calibrated lookup table
    /// (required when `params.subdivision` subdivides with [`SpringRule::Calibrated`]); the
    /// probe and the servo tick settings as for the FEM (`integrator.kind` must be
    /// symplectic Euler, the only scheme of this family).
    ///
    /// # Errors
    /// [`ModelError::SceneField`] for invalid parameters (naming the field), a missing table
    /// (`mass_spring.calibration_file`) or one for another node count, another integrator
    /// kind; [`ModelError::Unstable`] when the sub-steps needed by the worst-case Gershgorin
    /// bound exceed `integrator.max_substeps` (or a fixed `integrator.substeps` is too few).
    pub fn new(
        surface: SpringSurface,
        params: &MassSpringParams,
        table: Option<CalibrationTable>,
        probe: ProbeParams,
        integrator: &IntegratorParams,
        scene_name: &str,
    ) -> Result<Self, ModelError> {
        check_settings(params, &probe, integrator)?;
        let table = take_table(params, table, &surface)?;
        let (nc, ne, nt) = (
            surface.node_count(),
            surface.edge_count(),
            surface.triangle_count(),
        );
        let ns = nc + ne;
        let (edge_rest, loop_vertex_rest) = loop_rest_positions(&surface);
        let mut rest = surface.rest().to_vec();
        rest.extend_from_slice(&edge_rest);
        let contact_rest = contact_rest_positions(&surface, probe).positions;
        let edge_arc_m = surface
            .edges()
            .iter()
            .map(|&[a, b]| {
                let (ra, rb) = (surface.rest()[a as usize], surface.rest()[b as usize]);
                let (arc, n) = arc_midpoint(ra, rb, surface.rest_normal(a), surface.rest_normal(b));
                (arc - 0.5 * (ra + rb)).dot(n)
            })
            .collect();
        let mut fixed: Vec<bool> = (0..nc as u32).map(|i| surface.is_fixed(i)).collect();
        fixed.extend(
            surface
                .edges()
                .iter()
                .map(|&[a, b]| surface.is_fixed(a) && surface.is_fixed(b)),
        );
        let mut event = EventScratch::new(nc, ne, nt);
        // Stability: the coarse bound, and the worst case over every refinement.
        let (coarse_lambda, worst_lambda) = stability_bounds(
            &surface,
            params,
            table.as_ref(),
            &fixed,
            &mut event.scratch_a,
            &mut event.scratch_b,
        );
        let setup = MassSpringSetup {
            params: *params,
            integrator: *integrator,
            plan: plan_steps(integrator, critical_time_step_s(worst_lambda))?,
            coarse_critical_dt_s: critical_time_step_s(coarse_lambda),
            worst_lambda_per_s2: worst_lambda,
            tick_s: integrator.tick_s,
        };
        let state = MassSpringState::new(&surface, params, probe, rest);
        Ok(Self {
            scratch: MassSpringScratch {
                f: vec![DVec3::ZERO; ns],
                cx: contact_rest.clone(),
                tool_weight: prefaulted(0.0, ns),
            },
            model: MassSpringModel {
                surface,
                table,
                organ: None,
                loop_vertex_rest,
                contact_rest,
                edge_arc_m,
                fixed,
                scene_name: scene_name.to_string(),
                tool_ids: Vec::new(),
            },
            setup,
            state,
            event,
            stats: EventStats::default(),
        })
    }
}

/// The checks `MassSpringBody::new` makes before building anything: the parameters, the
/// contact law (a mass-spring surface has no FEM material for the patch laws), the integrator.
fn check_settings(
    params: &MassSpringParams,
    probe: &ProbeParams,
    integrator: &IntegratorParams,
) -> Result<(), ModelError> {
    params.validate()?;
    if matches!(
        probe.contact,
        ContactModel::PatchHertz | ContactModel::PatchLocal
    ) {
        return Err(ModelError::field(
            "probe.contact",
            "\"patch-hertz\" and \"patch-local\" take the law of an FEM material; a mass-spring surface has none (use \"auto\" or \"patch\")",
        ));
    }
    if integrator.kind != IntegratorKind::SymplecticEuler {
        return Err(ModelError::field(
            "integrator.kind",
            "the mass-spring family integrates with \"symplectic-euler\" only",
        ));
    }
    Ok(())
}

/// The calibration table when the subdivision needs one (calibrated springs, `rings > 0`),
/// checked against the surface; `None` otherwise (a table given then is dropped).
fn take_table(
    params: &MassSpringParams,
    table: Option<CalibrationTable>,
    surface: &SpringSurface,
) -> Result<Option<CalibrationTable>, ModelError> {
    let sub = params.subdivision;
    if !(sub.rings > 0 && sub.springs == SpringRule::Calibrated) {
        return Ok(None);
    }
    let t = table.ok_or_else(|| {
        ModelError::field(
            "mass_spring.calibration_file",
            "subdividing with springs = \"calibrated\" needs the calibration table (run `haptic-calibrate SCENE`)",
        )
    })?;
    if t.node_count() != surface.node_count() {
        return Err(ModelError::field(
            "mass_spring.calibration_file",
            format!(
                "the table covers {} nodes, the surface has {}",
                t.node_count(),
                surface.node_count()
            ),
        ));
    }
    Ok(Some(t))
}

/// The Gershgorin bounds on `M^-1 K` (1/s^2): of the coarse mesh, and the worst case over every
/// refinement the events can produce (lightest masses `m / 4`, stiffest table entry, most
/// springs per node). `diag` and `off` are work arrays of one entry per slot.
fn stability_bounds(
    surface: &SpringSurface,
    params: &MassSpringParams,
    table: Option<&CalibrationTable>,
    fixed: &[bool],
    diag: &mut [f64],
    off: &mut [f64],
) -> (f64, f64) {
    let sub = params.subdivision;
    let nc = surface.node_count();
    let m = params.node_mass_kg;
    let kh = params.home_spring_n_per_m;
    let km = params.mesh_spring_n_per_m;
    let coarse_lambda = gershgorin_bound_per_s2(
        &vec![kh; nc],
        &vec![m; nc],
        &fixed[..nc],
        surface.edges().iter().map(|&[a, b]| (a, b, km)),
        diag,
        off,
    );
    if sub.rings == 0 {
        return (coarse_lambda, coarse_lambda);
    }
    let a_max = table.map_or(1.0, |t| t.max_scale());
    let (kh_max, k_max) = match sub.springs {
        SpringRule::Calibrated => (
            kh * a_max.max(1.0),
            km.max(sub.km_over_kh_after * a_max * kh),
        ),
        SpringRule::Unchanged | SpringRule::Area => (kh, km),
    };
    // N' < 4 N for any area of a surface of genus 0, so m' > m / 4.
    let m_min = m / 4.0;
    let node_bound = |springs: f64| (kh_max + 2.0 * springs * k_max) / m_min;
    let coarse_worst = (0..nc as u32)
        .filter(|&i| !surface.is_fixed(i))
        .map(|i| node_bound(f64::from(surface.valence(i)) + surface.triangles_at(i).len() as f64))
        .fold(0.0, f64::max);
    (
        coarse_lambda,
        coarse_worst.max(node_bound(6.0)).max(coarse_lambda),
    )
}

impl MassSpringState {
    /// The state at rest on the coarse mesh: uniform masses and damping, no centre, the probe
    /// on the coarse triangles, no load.
    fn new(
        surface: &SpringSurface,
        params: &MassSpringParams,
        probe: ProbeParams,
        rest: Vec<DVec3>,
    ) -> Self {
        let nc = surface.node_count();
        let ns = rest.len();
        let m = params.node_mass_kg;
        let mut probe = Probe::new(probe, surface.triangles().to_vec(), &rest);
        let (mesh, contact_surface) = MixedMesh::new(surface, &rest);
        probe.replace_surface(contact_surface);
        let load_surface: Vec<[u32; 3]> = surface
            .triangles()
            .iter()
            .copied()
            .filter(|t| !t.iter().all(|&i| surface.is_fixed(i)))
            .collect();
        let loads = BodyLoads::new(
            &SceneLoads::default(),
            surface.rest(),
            &vec![m; nc],
            load_surface,
        );
        Self {
            refinement: Refinement::new(surface),
            mesh,
            x: rest.clone(),
            rest,
            v: vec![DVec3::ZERO; ns],
            mass: vec![m; ns],
            damping: prefaulted(params.damping_n_s_per_m, ns),
            owner: vec![NO_OWNER; ns],
            centres: [Centre {
                node: 0,
                last_contact_s: 0.0,
            }; MAX_CENTRES],
            centre_count: 0,
            kh_area: [params.home_spring_n_per_m; MAX_CENTRES],
            km_area: [params.mesh_spring_n_per_m; MAX_CENTRES],
            tools: vec![ToolContact::new(probe)],
            factor_tool: prefaulted(0, ns),
            factor_all: Some(0),
            loads,
            time_s: 0.0,
            diverged_at_s: None,
            version: 0,
            blend: ForceBlend::default(),
        }
    }
}

impl EventScratch {
    /// Work arrays for `nc` coarse nodes, `ne` edges and `nt` triangles (slots `nc + ne`),
    /// sized for the whole surface subdivided.
    fn new(nc: usize, ne: usize, nt: usize) -> Self {
        let ns = nc + ne;
        Self {
            old_region: Vec::with_capacity(nt),
            old_edges: Vec::with_capacity(ne),
            old_type1: Vec::with_capacity(nc),
            region_nodes: Vec::with_capacity(nc),
            region_tris: Vec::with_capacity(nt),
            region_edges: Vec::with_capacity(ne),
            node_stamp: prefaulted(0, nc),
            tri_stamp: prefaulted(0, nt),
            edge_stamp: prefaulted(0, ne),
            stamp: 0,
            touched: prefaulted(false, ns),
            touched_list: Vec::with_capacity(ns),
            scratch_home: vec![0.0; ns],
            ring: Vec::with_capacity(nc),
            ring_dist: vec![u32::MAX; nc],
            scratch_a: vec![0.0; ns],
            scratch_b: vec![0.0; ns],
        }
    }
}
