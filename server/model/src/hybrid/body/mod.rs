//! [`HybridBody`]: the hybrid family's [`SoftBody`] (seed 000 sections 5-6): the FEM core
//! (symplectic Euler with mass damping), the active particles (Verlet, seed eq. 33, in its
//! velocity form `v += F/m dt; x += v dt`, which gives the same positions), the ties of
//! everything else to the core, contact-local activation and release, and the probe.
//!
//! **A tick.** (1) Release and activation: a region whose vertex is farther than
//! `release_radius_m` from the probe and whose particles are back within `release_tolerance_m`
//! of the core's interpolation (or at rest: speeds below that tolerance per 0.1 s) is switched
//! off (its particles follow the core again, at no cost); then the particle region of every
//! outer vertex within `activation_radius_m` of the probe centre is switched on, nearest
//! first (its particles start on the core's interpolation, with the core's interpolated
//! velocity). When a region does not fit under `max_active_particles`, the regions farthest
//! from the probe (farther than it by half of `release_radius_m - activation_radius_m`) are
//! switched off, settled or not, so a sliding probe keeps simulated particles under it. When
//! the active set changed, the energy terms are refilled (active particles and their tied
//! neighbours, allocation-free). (2) Particle steps at the particles' critical step: tied
//! particles take the core's interpolated positions, term forces, probe penalty on active
//! particles, tied particles' forces back to the core with the tie weights; then the core
//! and the active particles update (one rate: the smaller critical step; the core-step loop
//! inside a particle step is there for a multi-rate scheme, which diverged on lv-hybrid
//! because the tied particles' terms stiffen the core nodes). (3) The device force is minus the probe's penalty forces of the last
//! sub-step, with their stiffness `sum k n n^T`.
//!
//! **Two options not in the seed** ([`ScaledMotion`], [`CoreStep`]): with `scaled_motion =
//! "deviation"` an active particle's state is its deviation from the core's interpolation
//! (`x_p = sum_k w_pk x_k + d_p`), only `d_p` carries the scaled mass, and every active
//! particle's force drives the core nodes too; with `core_step = "implicit"` the core takes the
//! linearly implicit step of [`ImplicitCore`] once per sub-step (its matrix frozen at rest,
//! with the layer's stiffness condensed on the core), and the sub-steps follow the particles'
//! critical step alone. Together they give the press the core's real inertia at one sub-step
//! per tick on `lv-hybrid` (`docs/accuracy.md`, "Deviation mass and an implicit core").
//!
//! **The sub-step** comes from the particles' Gershgorin bound and the core's own critical step
//! times `CORE_COUPLING_MARGIN` (0.65), and is then checked at set-up against the coupled system's
//! limit estimated by power iteration ([`HybridBody::new`], `verify_coupled_step`).
//!
//! **Masses.** Each active particle has `rho s^3` times `mass_scale`. The core's nodes carry
//! the core's lumped mass and the whole particle layer's (each layer particle's mass spread
//! over its tie's nodes, [`HybridModel::layer_mass_on_core_kg`]: the inactive particles follow
//! the core, so their inertia is the core's), times the core's mass scale ([`CoreMassScale`]:
//! `mass_scale` by default, a uniform slow-down; 1, the body's real inertia, the sub-steps
//! then set by the core's critical step; `auto`, the smallest scale that adds no sub-step to
//! the particles' count, so the body is as close to its real inertia as the particle step
//! allows).
//!
//! **Surface.** Each outer vertex shows the core's interpolation at the vertex plus the
//! deviation of its nearest particle from the core's interpolation at that particle (zero for
//! inactive particles), so the surface is continuous at activation and release.
//!
//! Neighbours: data from [`mod@super::prepare`]; forces from [`crate::meshfree::block`] and
//! [`crate::element::FemModel`].

use glam::DVec3;

use super::implicit::{CondensedLayer, ImplicitCore};
use super::layer::LayerElements;
use super::prepare::{HybridModel, Tie, TieNodes};
use super::proxy::{ParticleProxy, ProxyContact};
use super::{CoreMassScale, CoreStep, InactiveLayer, ScaledMotion};
use crate::ModelError;
use crate::body::{
    BodyInfo, BodyStats, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput, TickOutput,
    validate_point_load,
};
use crate::contact::probe::ProbeParams;
use crate::element::FemModel;
use crate::integrate::explicit::integrate_nodes;
use crate::integrate::{
    IntegratorKind, damped_critical_step_s, damped_max_omega2_per_s2, viscous_beta_s,
};
use crate::meshfree::TermBlock;

/// Point loads a body holds at once.
pub const MAX_POINT_LOADS: usize = 16;

/// Speed above which the body counts as diverged, m/s.
const MAX_SPEED_M_PER_S: f64 = 100.0;

/// Share of the core's own critical step (power iteration on the core alone) the sub-steps may
/// use: the tied particles' terms stiffen the core nodes, so the coupled system's limit is
/// shorter. Measured by power iteration on the coupled system (`HybridBody::
/// max_eigenvalue_estimate`) on lv-hybrid with about 2 000 active particles: 0.80-0.98 of the
/// core's step with a real-inertia core (`core_mass_scale = 1`, `mass_scale = 300`), 0.70-0.79
/// with `mass_scale = 1000` and a core scaled by 18. The tests
/// `a_real_inertia_core_steps_within_the_coupled_limit` and
/// `the_chosen_core_mass_scale_is_the_least_that_keeps_the_particles_substeps` check the step
/// against that estimate at several points of the surface. (With a uniform mass scale the
/// core's step is several times the particles' and this does not bind.)
const CORE_COUPLING_MARGIN: f64 = 0.65;

/// Outer vertices at which [`HybridBody::verify_coupled_step`] estimates the coupled limit.
const STEP_CHECK_POINTS: usize = 6;

/// The largest share of the coupled system's estimated critical step (power iteration, a
/// slight overestimate of the step) a sub-step may take: the check is there to catch core
/// meshes on which [`CORE_COUPLING_MARGIN`] fails, not to replace the bound's safety factor.
const COUPLED_STEP_HEADROOM: f64 = 0.95;

#[derive(Debug, Clone, Copy, Default)]
struct PointLoad {
    tie: Tie,
    force_n: DVec3,
    remaining_s: f64,
}

/// The hybrid body (module documentation).
#[derive(Debug)]
pub struct HybridBody {
    model: Box<HybridModel>,
    fem: FemModel,
    name: String,
    probe: ProbeParams,
    tick_s: f64,
    substeps: u32,
    core_substeps: u32,
    dt_s: f64,
    /// Forces of the tied particles and point loads on the core nodes, held over a particle
    /// step, N.
    fcoup: Vec<DVec3>,
    critical_dt_s: f64,
    particle_mass_kg: f64,
    core_mass_scale: f64,
    xc: Vec<DVec3>,
    vc: Vec<DVec3>,
    fc: Vec<DVec3>,
    xp: Vec<DVec3>,
    vp: Vec<DVec3>,
    fp: Vec<DVec3>,
    active: Vec<bool>,
    in_block: Vec<bool>,
    active_list: Vec<u32>,
    tied_list: Vec<u32>,
    /// The core nodes and tie weights of each particle of `tied_list`, copied when the terms
    /// are refilled: the per-sub-step gather and scatter read them in order instead of
    /// looking up the particle's tie and its tetrahedron.
    tied_ties: Vec<TieNodes>,
    /// `scaled_motion = "deviation"` ([`ScaledMotion::Deviation`]): the active particles'
    /// state is their deviation from the core's interpolation (`xd`, and `vp` its rate), and
    /// their forces also drive the core nodes.
    deviation: bool,
    /// Deviations of the active particles from the core's interpolation, m (deviation mode).
    xd: Vec<DVec3>,
    /// The core nodes and tie weights of each particle of `active_list`, copied when the terms
    /// are refilled (deviation mode).
    active_ties: Vec<TieNodes>,
    block: TermBlock,
    /// The probe: the proxy sphere on the active particles and the virtual coupling.
    proxy: ParticleProxy,
    /// `inactive_layer = "elements"`: the elements' shares of the wall's energy.
    layer: Option<LayerElements>,
    /// `core_step = "implicit"`: the core's factor and its margin.
    implicit: Option<(ImplicitCore, f64)>,
    /// Outer-vertex adjacency (CSR over `outer_triangles`), for the implicit core's regions.
    vertex_adj_start: Vec<u32>,
    vertex_adj: Vec<u32>,
    /// The regions whose condensed stiffness the implicit core's matrix holds: the active ones
    /// and their neighbours (scratch; `region_mark` flags them).
    matrix_regions: Vec<u32>,
    region_mark: Vec<bool>,
    /// Refactorings of the implicit core's matrix since set-up.
    implicit_refactors: u64,
    region_active: Vec<bool>,
    active_regions: Vec<u32>,
    /// Regions to activate this tick with their squared distance to the probe, m^2 (scratch
    /// of [`Self::activate_near`], one slot per outer vertex).
    candidates: Vec<(f64, u32)>,
    changed: bool,
    hold: bool,
    refused_activations: u64,
    released_for_room: u64,
    loads: [PointLoad; MAX_POINT_LOADS],
    load_count: usize,
    time_s: f64,
    diverged_at_s: Option<f64>,
    last_force_n: DVec3,
}

impl HybridBody {
    /// A body at rest from a preprocessed model. `clamped`: core nodes fixed at rest;
    /// `tick_s`: servo period, s.
    ///
    /// The sub-steps come from the critical step bound, then the set-up check of the coupled
    /// system's limit (`verify_coupled_step`: power iteration at six outer vertices, about
    /// 0.2 s on `lv-hybrid`) may raise them.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.max_substeps` when the critical step or the
    /// check needs more sub-steps per tick; [`ModelError::NoConvergence`] when a power
    /// iteration of the check does not settle; the errors of [`FemModel::new`].
    pub fn new(
        model: HybridModel,
        clamped: &[u32],
        probe: ProbeParams,
        tick_s: f64,
        name: &str,
    ) -> Result<Self, ModelError> {
        let params = model.params;
        let particle_mass_kg = model.cloud.mass_kg() * params.mass_scale;
        // Elastic part scales with 1/mass; the probe penalty adds k / m to the eigenvalue bound.
        let lambda_el = (2.0 / model.particle_dt_s).powi(2) / params.mass_scale;
        let lambda = lambda_el + params.contact_stiffness_n_per_m / particle_mass_kg;
        let particle_dt = 2.0 / lambda.sqrt();
        let substeps_for = |dt_s: f64| (tick_s / (params.safety_factor * dt_s)).ceil().max(1.0);
        // The core carries its own mass and the particle layer's (the inactive particles
        // follow it), both times the core's mass scale (`CoreMassScale`).
        let mut fem = FemModel::new(&model.core_mesh, *model.cloud.material())?;
        if params.inactive_layer == InactiveLayer::Tied {
            fem.add_lumped_mass(&model.layer_mass_on_core_kg());
        }
        fem.clamp_nodes(clamped);
        // The largest eigenvalue of M^-1 K at the real masses; a uniform mass scale divides it.
        let omega2_real = fem.max_eigenvalue(0.0, 300);
        let beta = viscous_beta_s(fem.material());
        let core_mass_scale = match params.core_mass_scale {
            CoreMassScale::Fixed(scale) => scale,
            CoreMassScale::Uniform => params.mass_scale,
            // The implicit core has no critical step: its real inertia costs nothing.
            CoreMassScale::Auto if params.core_step != CoreStep::Explicit => 1.0,
            CoreMassScale::Auto => {
                let want_dt = tick_s / (params.safety_factor * substeps_for(particle_dt));
                let omega2_max = damped_max_omega2_per_s2(want_dt / CORE_COUPLING_MARGIN, beta);
                (omega2_real / omega2_max * (1.0 + 1e-9)).clamp(1.0, params.mass_scale)
            }
        };
        if core_mass_scale != 1.0 {
            let extra: Vec<f64> = fem
                .lumped_mass_kg()
                .iter()
                .map(|m| m * (core_mass_scale - 1.0))
                .collect();
            fem.add_lumped_mass(&extra);
        }
        let core_dt_s = damped_critical_step_s(omega2_real / core_mass_scale, beta);
        let critical_dt_s = match params.core_step {
            CoreStep::Explicit => particle_dt.min(CORE_COUPLING_MARGIN * core_dt_s),
            CoreStep::Implicit { .. } => particle_dt,
        };
        // One rate for both: the particle terms of tied particles stiffen the core nodes, so a
        // core held through a longer particle step (multi-rate, tried, also with a real-inertia
        // core) diverges on lv-hybrid. `core_substeps` stays 1.
        let substeps = substeps_for(critical_dt_s) as u32;
        let core_substeps = 1u32;
        if substeps.max(core_substeps) > params.max_substeps {
            return Err(ModelError::field(
                "hybrid.max_substeps",
                format!(
                    "the critical steps (particles {particle_dt:.3e} s, core {:.3e} s) need {substeps} particle sub-steps per {tick_s} s tick and {core_substeps} core steps per particle step; raise max_substeps or mass_scale, or use a larger spacing_m",
                    core_dt_s
                ),
            ));
        }
        let n = model.cloud.len();
        let nc = model.core_mesh.nodes.len();
        let capacity = 4 * params.max_active_particles + 4 * model.largest_region + 64;
        let block = TermBlock::new(&model.cloud, capacity);
        let nv = model.outer_rest_m.len();
        let layer = (params.inactive_layer == InactiveLayer::Elements)
            .then(|| LayerElements::new(&model, &fem));
        let mut body = Self {
            fem,
            name: name.to_string(),
            probe,
            tick_s,
            substeps,
            core_substeps,
            dt_s: tick_s / substeps as f64,
            fcoup: vec![DVec3::ZERO; nc],
            critical_dt_s,
            particle_mass_kg,
            core_mass_scale,
            xc: model.core_mesh.nodes.clone(),
            vc: vec![DVec3::ZERO; nc],
            fc: vec![DVec3::ZERO; nc],
            xp: model.cloud.rest_m().to_vec(),
            vp: vec![DVec3::ZERO; n],
            fp: vec![DVec3::ZERO; n],
            active: vec![false; n],
            in_block: vec![false; n],
            active_list: Vec::with_capacity(params.max_active_particles + model.largest_region),
            tied_list: Vec::with_capacity(3 * capacity),
            tied_ties: Vec::with_capacity(3 * capacity),
            deviation: params.scaled_motion == ScaledMotion::Deviation,
            xd: vec![DVec3::ZERO; n],
            active_ties: Vec::with_capacity(params.max_active_particles + model.largest_region),
            block,
            layer,
            proxy: ParticleProxy::new(
                &probe,
                params.meshfree.spacing_m,
                params.contact_stiffness_n_per_m,
                &model.contact_skin_m(),
                params.max_active_particles + model.largest_region,
            ),
            implicit: None,
            vertex_adj_start: Vec::new(),
            vertex_adj: Vec::new(),
            matrix_regions: Vec::with_capacity(nv),
            region_mark: vec![false; nv],
            implicit_refactors: 0,
            region_active: vec![false; nv],
            active_regions: Vec::with_capacity(nv),
            candidates: Vec::with_capacity(nv),
            changed: false,
            hold: false,
            refused_activations: 0,
            released_for_room: 0,
            loads: [PointLoad::default(); MAX_POINT_LOADS],
            load_count: 0,
            time_s: 0.0,
            diverged_at_s: None,
            last_force_n: DVec3::ZERO,
            model: Box::new(model),
        };
        // The check holds the core when it steps implicitly (not part of the explicit system).
        body.verify_coupled_step()?;
        if let CoreStep::Implicit { margin } = params.core_step {
            let mut adj: Vec<Vec<u32>> = vec![Vec::new(); nv];
            for t in &body.model.outer_triangles {
                for a in 0..3 {
                    for b in 0..3 {
                        if a != b && !adj[t[a] as usize].contains(&t[b]) {
                            adj[t[a] as usize].push(t[b]);
                        }
                    }
                }
            }
            body.vertex_adj_start = std::iter::once(0)
                .chain(adj.iter().scan(0u32, |acc, a| {
                    *acc += a.len() as u32;
                    Some(*acc)
                }))
                .collect();
            body.vertex_adj = adj.concat();
            let layer = match params.inactive_layer {
                InactiveLayer::Tied => Some(CondensedLayer::new(&body.model)?),
                InactiveLayer::Elements => None,
            };
            let core = ImplicitCore::new(&body.fem, layer.as_ref(), body.dt_s, margin)?;
            body.implicit = Some((core, margin));
        }
        Ok(body)
    }

    /// Rebuilds the implicit core's matrix when the sub-step changed (studies; condenses the
    /// layer again, about 0.8 s on `lv-hybrid`).
    fn rebuild_implicit(&mut self) -> Result<(), ModelError> {
        if let Some((core, margin)) = self.implicit.take() {
            let mut core = if core.h_s() == self.dt_s {
                core
            } else {
                let layer = match self.model.params.inactive_layer {
                    InactiveLayer::Tied => Some(CondensedLayer::new(&self.model)?),
                    InactiveLayer::Elements => None,
                };
                ImplicitCore::new(&self.fem, layer.as_ref(), self.dt_s, margin)?
            };
            core.refactor(&self.matrix_regions)?;
            self.implicit = Some((core, margin));
        }
        Ok(())
    }

    /// The set-up check of the sub-step against the coupled system's own limit. The core's
    /// share of the step ([`CORE_COUPLING_MARGIN`]) was measured on one core mesh (lv-hybrid's
    /// 519 tetrahedra); with finer cores the coupled limit fell to 0.84-0.96 of the step bound
    /// and an instant 1 mm press diverged. At [`STEP_CHECK_POINTS`] outer vertices (the
    /// extremes of x, y and z) the regions nearest the vertex are activated up to
    /// `max_active_particles`, the largest eigenvalue of the coupled system (free core nodes
    /// and active particles, tied particles following the core) is estimated by power
    /// iteration, the probe penalty's `k / m` added, and the damped limit
    /// ([`damped_critical_step_s`]) taken; when the sub-step exceeds
    /// [`COUPLED_STEP_HEADROOM`] of the smallest, the sub-steps are raised. Stepped explicitly,
    /// lv-hybrid (519 tetrahedra, 2 000 active) has its step at 0.90 of the smallest (at the
    /// -x vertex), which stays; with 999 tetrahedra it was 1.10 and the check gives 3
    /// sub-steps. With `core_step = "implicit"` the core is held (not part of the explicit
    /// system) and the check covers the particles alone. The body is left at rest with no
    /// active region. About 10 ms per point with 2 000 active particles.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.max_substeps` when the raised count exceeds
    /// it; [`ModelError::NoConvergence`] when a power iteration does not settle.
    fn verify_coupled_step(&mut self) -> Result<(), ModelError> {
        let params = self.model.params;
        let beta = viscous_beta_s(self.fem.material());
        let k_over_m = params.contact_stiffness_n_per_m / self.particle_mass_kg;
        let outer = &self.model.outer_rest_m;
        let extreme = |key: &dyn Fn(DVec3) -> f64| {
            (0..outer.len()).max_by(|&a, &b| key(outer[a]).total_cmp(&key(outer[b])))
        };
        let points: Vec<DVec3> = [
            extreme(&|x| x.x),
            extreme(&|x| -x.x),
            extreme(&|x| x.y),
            extreme(&|x| -x.y),
            extreme(&|x| x.z),
            extreme(&|x| -x.z),
        ]
        .into_iter()
        .flatten()
        .map(|v| outer[v])
        .collect();
        debug_assert_eq!(points.len(), STEP_CHECK_POINTS);
        let mut limit_s = f64::INFINITY;
        self.hold = true;
        for point in points {
            let mut r = 0.5 * params.meshfree.spacing_m;
            while self.active_list.len() < params.max_active_particles && r < 0.05 {
                self.activate_near(point, r);
                r += 0.5 * params.meshfree.spacing_m;
            }
            let estimate = self.max_eigenvalue_estimate(1000, 1e-3);
            while let Some(k) = self.active_regions.len().checked_sub(1) {
                self.deactivate_region(k);
            }
            self.active_list.clear();
            let e = estimate?;
            limit_s = limit_s.min(damped_critical_step_s(e.lambda_per_s2 + k_over_m, beta));
        }
        self.hold = false;
        self.refused_activations = 0;
        self.rebuild_terms();
        let needed = (self.tick_s / (COUPLED_STEP_HEADROOM * limit_s)).ceil() as u32;
        if needed > self.substeps {
            if needed > params.max_substeps {
                return Err(ModelError::field(
                    "hybrid.max_substeps",
                    format!(
                        "the coupled system's critical step ({limit_s:.3e} s, power iteration at {STEP_CHECK_POINTS} points) needs {needed} sub-steps per {} s tick; raise max_substeps or mass_scale, or use a coarser core",
                        self.tick_s
                    ),
                ));
            }
            self.substeps = needed;
            self.dt_s = self.tick_s / needed as f64;
        }
        Ok(())
    }

    /// The preprocessed model.
    pub fn model(&self) -> &HybridModel {
        &self.model
    }

    /// Particle sub-steps per tick, the particle step (s) and core steps per particle step.
    pub fn substeps(&self) -> (u32, f64, u32) {
        (self.substeps, self.dt_s, self.core_substeps)
    }

    /// Sets the particle sub-steps per tick, overriding the count derived from the critical
    /// step bound (for studies of the explicit step, with
    /// [`Self::max_eigenvalue_estimate`]; stability is then the caller's responsibility).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when `substeps` is zero or above `hybrid.max_substeps`.
    pub fn override_substeps(&mut self, substeps: u32) -> Result<(), ModelError> {
        if substeps == 0 || substeps > self.model.params.max_substeps {
            return Err(ModelError::InvalidInput(format!(
                "{substeps} sub-steps per tick: must be 1 to {}",
                self.model.params.max_substeps
            )));
        }
        self.substeps = substeps;
        self.dt_s = self.tick_s / substeps as f64;
        self.rebuild_implicit()
    }

    /// The critical step the sub-steps come from, s: the smaller of the particles' (Gershgorin
    /// bound, mass-scaled, with the probe penalty) and the core's.
    pub fn critical_step_bound_s(&self) -> f64 {
        self.critical_dt_s
    }

    /// Keeps every active region active (no release) while `hold` is true: for tests and
    /// studies of a fixed active set.
    pub fn hold_regions(&mut self, hold: bool) {
        self.hold = hold;
    }

    /// Activations refused because `max_active_particles` (or the term capacity) was reached.
    pub fn refused_activations(&self) -> u64 {
        self.refused_activations
    }

    /// Regions released unsettled to make room under `max_active_particles` for regions
    /// nearer the probe ([`Self::activate_near`]).
    pub fn released_for_room(&self) -> u64 {
        self.released_for_room
    }

    /// Proxy solves that stopped at their iteration cap since set-up
    /// ([`ParticleProxy::unconverged_solves`]).
    pub fn unconverged_proxy_solves(&self) -> u64 {
        self.proxy.unconverged_solves()
    }

    /// Refactorings of the implicit core's matrix since set-up (when an active region was not
    /// in it).
    pub fn implicit_refactors(&self) -> u64 {
        self.implicit_refactors
    }

    /// Heap bytes of the implicit core's matrix and factor (0 with an explicit core).
    pub fn implicit_core_memory_bytes(&self) -> usize {
        self.implicit.as_ref().map_or(0, |(c, _)| c.memory_bytes())
    }

    /// Energy terms and tied particles of the current active set (the per-sub-step work).
    pub fn work_counts(&self) -> (usize, usize) {
        (self.block.len(), self.tied_list.len())
    }

    /// The term block's stencil layout in use (grid cells, groups of four owners), `None`
    /// when its general loop runs ([`TermBlock::stencil_layout`]).
    pub fn stencil_layout(&self) -> Option<(usize, usize)> {
        self.block.stencil_layout()
    }

    /// Chooses the term block's force loop ([`TermBlock::set_stencil_loop`]), for benchmarks.
    pub fn set_stencil_loop(&mut self, on: bool) {
        self.block.set_stencil_loop(on);
    }

    /// Currently active particles.
    pub fn active_particles(&self) -> &[u32] {
        &self.active_list
    }

    /// Core positions and velocities (m, m/s), for tests and studies.
    pub fn core_state_mut(&mut self) -> (&mut [DVec3], &mut [DVec3]) {
        (&mut self.xc, &mut self.vc)
    }

    /// Particle positions and velocities (m, m/s, indexed by particle; only active particles'
    /// entries are state, the others are overwritten from the core), for tests and studies.
    /// With `scaled_motion = "deviation"` the velocities are the deviations' rates and the
    /// positions are recomputed from the core and the deviations at every sub-step.
    pub fn particle_state_mut(&mut self) -> (&mut [DVec3], &mut [DVec3]) {
        (&mut self.xp, &mut self.vp)
    }

    /// Lumped masses of the core nodes, kg (the core's and the particle layer's, times
    /// `core_mass_scale`). Length: core nodes.
    pub fn core_lumped_mass_kg(&self) -> &[f64] {
        self.fem.lumped_mass_kg()
    }

    /// The core's mass multiplier in use ([`CoreMassScale`]: the value set, `mass_scale`, or
    /// the one chosen for `auto`).
    pub fn core_mass_scale(&self) -> f64 {
        self.core_mass_scale
    }

    /// Mass of one particle, kg.
    pub fn particle_mass_kg(&self) -> f64 {
        self.particle_mass_kg
    }

    /// Total linear momentum of the simulated degrees of freedom (core nodes and active
    /// particles; with `scaled_motion = "deviation"` the core nodes' alone, the momentum
    /// conjugate to a translation), kg m/s.
    pub fn linear_momentum(&self) -> DVec3 {
        let mut p = DVec3::ZERO;
        for (v, m) in self.vc.iter().zip(self.fem.lumped_mass_kg()) {
            p += *v * *m;
        }
        if !self.deviation {
            for &q in &self.active_list {
                p += self.vp[q as usize] * self.particle_mass_kg;
            }
        }
        p
    }

    /// Kinetic and elastic energy (J) of the simulated degrees of freedom (the terms of the
    /// active set at the current tied positions; with `scaled_motion = "deviation"` the
    /// particles' kinetic part is their deviations').
    pub fn energy(&self) -> (f64, f64) {
        let mut kin = 0.0;
        for (v, m) in self.vc.iter().zip(self.fem.lumped_mass_kg()) {
            kin += 0.5 * m * v.length_squared();
        }
        for &q in &self.active_list {
            kin += 0.5 * self.particle_mass_kg * self.vp[q as usize].length_squared();
        }
        let replaced = self
            .layer
            .as_ref()
            .map_or(0.0, |l| l.replaced_energy(&self.fem, &self.xc));
        let elastic = self.fem.elastic_energy(&self.xc) - replaced
            + self.block.energy(&self.model.cloud, &self.xp);
        (kin, elastic)
    }

    /// Activates the regions of the outer vertices within `radius_m` of `point_m` (m, at
    /// their current positions), nearest first. When a region does not fit under
    /// `max_active_particles`, active regions whose vertex is farther from `point_m` than the
    /// region's by half of `release_radius_m - radius_m` are released, farthest first, settled
    /// or not, to make room (not while
    /// [`Self::hold_regions`] holds them): the probe keeps simulated particles under it as it
    /// slides. Allocation-free; the terms are refilled at the next tick or
    /// [`Self::evaluate_forces`].
    pub fn activate_near(&mut self, point_m: DVec3, radius_m: f64) {
        let r2 = radius_m * radius_m;
        // Nearest first: when the cap binds, the regions under the probe get in.
        self.candidates.clear();
        for v in 0..self.model.outer_rest_m.len() {
            if self.region_active[v] {
                continue;
            }
            let x = self.model.interpolate(&self.model.vertex_tie[v], &self.xc);
            let d2 = (x - point_m).length_squared();
            if d2 < r2 {
                self.candidates.push((d2, v as u32));
            }
        }
        self.candidates.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        for k in 0..self.candidates.len() {
            let (d2, v) = self.candidates[k];
            let v = v as usize;
            if !self.fits(v) && !self.hold {
                // Regions farther than the candidate by half the release band give way: a
                // region near the activation radius's edge is not evicted and re-activated
                // tick after tick, and one coming under the probe gets in first.
                let p = &self.model.params;
                let band_m = 0.5 * (p.release_radius_m - radius_m).max(0.0);
                self.evict_far(point_m, d2.sqrt() + band_m, v);
            }
            if self.fits(v) {
                self.activate_region(v);
            } else {
                self.refused_activations += 1;
            }
        }
    }

    /// Whether the region of vertex `v` fits under `max_active_particles`.
    fn fits(&self, v: usize) -> bool {
        let m = &self.model;
        let len = (m.region_start[v + 1] - m.region_start[v]) as usize;
        self.active_list.len() + len <= m.params.max_active_particles
    }

    /// Releases active regions whose vertex is farther than `radius_m` from `probe_m`,
    /// farthest first, until the region of vertex `v` fits or none is left.
    fn evict_far(&mut self, probe_m: DVec3, radius_m: f64, v: usize) {
        let r2 = radius_m * radius_m;
        while !self.fits(v) {
            let m = &self.model;
            let mut farthest = None;
            let mut d2_max = r2;
            for (k, &u) in self.active_regions.iter().enumerate() {
                let x = m.interpolate(&m.vertex_tie[u as usize], &self.xc);
                let d2 = (x - probe_m).length_squared();
                if d2 > d2_max {
                    d2_max = d2;
                    farthest = Some(k);
                }
            }
            let Some(k) = farthest else {
                return;
            };
            self.deactivate_region(k);
            self.released_for_room += 1;
            let active = &self.active;
            self.active_list.retain(|&p| active[p as usize]);
        }
    }

    /// Switches off the `k`-th active region (its particles follow the core again, and may be
    /// tied to it as neighbours of the next active set); the caller prunes `active_list`.
    fn deactivate_region(&mut self, k: usize) {
        let m = &self.model;
        let v = self.active_regions[k] as usize;
        for &p in &m.region_particles[m.region_start[v] as usize..m.region_start[v + 1] as usize] {
            self.active[p as usize] = false;
            // `rebuild_terms` clears the marks of the pruned `active_list` only.
            self.in_block[p as usize] = false;
        }
        self.region_active[v] = false;
        self.active_regions.swap_remove(k);
        self.changed = true;
    }

    fn activate_region(&mut self, v: usize) {
        let m = &self.model;
        let range = m.region_start[v] as usize..m.region_start[v + 1] as usize;
        for k in range {
            let p = m.region_particles[k] as usize;
            if m.degenerate[p] {
                continue;
            }
            let tie = &m.particle_tie[p];
            self.xp[p] = m.interpolate(tie, &self.xc);
            if self.deviation {
                // On the core's interpolation, moving with it: no deviation.
                self.xd[p] = DVec3::ZERO;
                self.vp[p] = DVec3::ZERO;
            } else {
                self.vp[p] = m.interpolate(tie, &self.vc);
            }
            self.active[p] = true;
            self.active_list.push(p as u32);
        }
        self.region_active[v] = true;
        self.active_regions.push(v as u32);
        self.changed = true;
    }

    /// Releases the settled regions whose vertex is farther than `release_radius_m` from the
    /// probe (`None`: no probe, every settled region).
    fn release_far(&mut self, probe_m: Option<DVec3>) {
        let p = &self.model.params;
        let r2 = p.release_radius_m * p.release_radius_m;
        let tol2 = p.release_tolerance_m * p.release_tolerance_m;
        let mut released = false;
        let mut k = 0;
        while k < self.active_regions.len() {
            let m = &self.model;
            let v = self.active_regions[k] as usize;
            let near = probe_m.is_some_and(|c| {
                (m.interpolate(&m.vertex_tie[v], &self.xc) - c).length_squared() < r2
            });
            let region =
                &m.region_particles[m.region_start[v] as usize..m.region_start[v + 1] as usize];
            // Settled: back on the core's interpolation, or at rest (speeds below the tolerance
            // per 0.1 s) in a state the layer cannot leave by itself (a fold pressed in by the
            // probe), which the release then removes.
            let settled = !near
                && (region.iter().all(|&p| {
                    let p = p as usize;
                    !self.active[p]
                        || (self.xp[p] - m.interpolate(&m.particle_tie[p], &self.xc))
                            .length_squared()
                            < tol2
                }) || region.iter().all(|&p| {
                    !self.active[p as usize] || self.vp[p as usize].length_squared() * 0.01 < tol2
                }));
            if settled {
                self.deactivate_region(k);
                released = true;
            } else {
                k += 1;
            }
        }
        if released {
            let active = &self.active;
            self.active_list.retain(|&p| active[p as usize]);
        }
    }

    /// Refills the energy terms for the current active set (allocation-free): terms of the
    /// active particles and of their inactive neighbours (ring 1); the tied list holds ring 1
    /// and the inactive neighbours of ring 1 (ring 2), whose positions those terms read and
    /// whose forces go to the core.
    fn rebuild_terms(&mut self) {
        for &q in &self.tied_list {
            self.in_block[q as usize] = false;
        }
        for &q in &self.active_list {
            self.in_block[q as usize] = false;
        }
        self.tied_list.clear();
        self.block.clear();
        if let Some(layer) = &mut self.layer {
            layer.clear();
        }
        let cloud = &self.model.cloud;
        let ties = &self.model.particle_tie;
        let mut nbr = [0u32; crate::meshfree::cloud::MAX_STENCIL];
        for &p in &self.active_list {
            self.in_block[p as usize] = true;
            if matches!(self.block.push(cloud, p), Ok(true)) {
                if let Some(layer) = &mut self.layer {
                    layer.count_term(ties[p as usize].tet);
                }
            } else {
                self.refused_activations += 1;
            }
        }
        for ring in 0..2 {
            let to = if ring == 0 {
                self.active_list.len()
            } else {
                self.tied_list.len()
            };
            for a in 0..to {
                let p = if ring == 0 {
                    self.active_list[a]
                } else {
                    self.tied_list[a]
                };
                let k = cloud.neighbours(p, &mut nbr);
                for &q in &nbr[..k] {
                    if self.in_block[q as usize]
                        || self.tied_list.len() == self.tied_list.capacity()
                    {
                        continue;
                    }
                    self.in_block[q as usize] = true;
                    self.tied_list.push(q);
                    if ring == 0 && !self.model.degenerate[q as usize] {
                        if matches!(self.block.push(cloud, q), Ok(true)) {
                            if let Some(layer) = &mut self.layer {
                                layer.count_term(ties[q as usize].tet);
                            }
                        } else {
                            self.refused_activations += 1;
                        }
                    }
                }
            }
        }
        // In memory order: the tie gathers and scatters of every sub-step walk the particle
        // arrays forwards.
        self.tied_list.sort_unstable();
        if let Some(layer) = &mut self.layer {
            layer.finish();
        }
        let m = &self.model;
        self.tied_ties.clear();
        for &q in &self.tied_list {
            self.tied_ties
                .push(m.tie_nodes(&m.particle_tie[q as usize]));
        }
        // The implicit core's matrix holds the active regions and their neighbours (which stand
        // for the terms of inactive particles next to the active ones, which the block also
        // holds). It is refactored only when an active region is not in it: a region released,
        // or activated next to the active ones (already a neighbour), leaves a matrix that
        // still dominates the tangent, with a little more damping where it has too much.
        let refactor = self.implicit.is_some()
            && self.layer.is_none()
            && !self
                .active_regions
                .iter()
                .all(|&v| self.region_mark[v as usize]);
        if refactor {
            for &v in &self.matrix_regions {
                self.region_mark[v as usize] = false;
            }
            self.matrix_regions.clear();
            for &v in &self.active_regions {
                let (a, b) = (
                    self.vertex_adj_start[v as usize] as usize,
                    self.vertex_adj_start[v as usize + 1] as usize,
                );
                for &w in std::iter::once(&v).chain(&self.vertex_adj[a..b]) {
                    if !self.region_mark[w as usize] {
                        self.region_mark[w as usize] = true;
                        self.matrix_regions.push(w);
                    }
                }
            }
        }
        if let Some((core, _)) = &mut self.implicit
            && refactor
        {
            self.implicit_refactors += 1;
            if core.refactor(&self.matrix_regions).is_err() {
                // Positive definite by construction; a failure is a non-finite state.
                self.diverged_at_s = Some(self.time_s);
            }
        }
        self.active_ties.clear();
        if self.deviation {
            for &p in &self.active_list {
                self.active_ties
                    .push(m.tie_nodes(&m.particle_tie[p as usize]));
            }
        }
        self.changed = false;
    }

    /// Particle forces of the current state (no update): tied positions from the core, terms,
    /// the probe at `probe_m` (returns the force on the device, N, and its stiffness
    /// `sum k n n^T`, N/m); the tied particles' forces and the point loads go to the core
    /// nodes' coupling buffer with the tie weights.
    fn particle_forces(&mut self, probe_m: Option<DVec3>) -> ProxyContact {
        if self.changed {
            self.rebuild_terms();
        }
        let m = &self.model;
        let xc = &self.xc;
        for (&q, t) in self.tied_list.iter().zip(&self.tied_ties) {
            self.xp[q as usize] = t.interpolate(xc);
        }
        if self.deviation {
            for (&p, t) in self.active_list.iter().zip(&self.active_ties) {
                self.xp[p as usize] = t.interpolate(xc) + self.xd[p as usize];
            }
        }
        self.block.write_forces(&m.cloud, &self.xp, &mut self.fp);
        let contact = match probe_m {
            Some(device) => {
                self.proxy
                    .update(device, &self.xp, &self.active_list, Some(&mut self.fp))
            }
            None => ProxyContact {
                force_on_device_n: DVec3::ZERO,
                stiffness_n_per_m: [0.0; 9],
                proxy_m: DVec3::ZERO,
                in_contact: false,
            },
        };
        self.fcoup.iter_mut().for_each(|f| *f = DVec3::ZERO);
        for (&q, t) in self.tied_list.iter().zip(&self.tied_ties) {
            let f = self.fp[q as usize];
            for k in 0..t.len {
                self.fcoup[t.nodes[k] as usize] += f * t.w[k];
            }
        }
        if self.deviation {
            // `d x_p / d x_k = w_pk`: the active particles' forces drive the core too.
            for (&p, t) in self.active_list.iter().zip(&self.active_ties) {
                let f = self.fp[p as usize];
                for k in 0..t.len {
                    self.fcoup[t.nodes[k] as usize] += f * t.w[k];
                }
            }
        }
        for l in &self.loads[..self.load_count] {
            let t = m.tie_nodes(&l.tie);
            for k in 0..t.len {
                self.fcoup[t.nodes[k] as usize] += l.force_n * t.w[k];
            }
        }
        contact
    }

    /// Core forces: the coupling buffer plus the FEM's internal (elastic and viscous) forces.
    fn core_forces(&mut self) {
        self.fc.copy_from_slice(&self.fcoup);
        self.add_fem_forces(true);
    }

    /// Adds the FEM's internal forces at the core's positions to `fc` (with the viscous stress
    /// at its velocities when `viscous`), less the shares the particles' terms replace
    /// (`inactive_layer = "elements"`, [`LayerElements`]).
    fn add_fem_forces(&mut self, viscous: bool) {
        let v = viscous.then_some(self.vc.as_slice());
        self.fem.add_internal_forces(&self.xc, v, &mut self.fc);
        if let Some(layer) = &self.layer {
            layer.subtract_forces(&self.fem, &self.xc, v, &mut self.fc);
        }
    }

    /// Computes the forces of the current state without advancing it and returns the core
    /// nodes' forces and the particles' forces (N; particle entries are meaningful for active
    /// and tied particles). For tests: constant strain, momentum.
    pub fn evaluate_forces(&mut self) -> (&[DVec3], &[DVec3]) {
        self.particle_forces(None);
        self.core_forces();
        (&self.fc, &self.fp)
    }

    /// One particle step of length `dt` from the forces in the buffers, during which the core
    /// takes `core_substeps` steps with the coupling forces held (multi-rate: the impulses
    /// exchanged through the ties are equal and opposite, so momentum stays exact); returns the
    /// largest squared speed (NaN when non-finite).
    fn update(&mut self, dt: f64) -> f64 {
        let dt_c = dt / self.core_substeps as f64;
        let mut max_v2: f64 = 0.0;
        let mut non_finite = false;
        if self.implicit.is_some() {
            // Elastic and coupling forces; the viscous operator is in the frozen matrix.
            self.fc.copy_from_slice(&self.fcoup);
            self.add_fem_forces(false);
            let Some((core, _)) = &mut self.implicit else {
                unreachable!("checked above")
            };
            let v2 = core.step(
                self.fem.lumped_mass_kg(),
                &self.fc,
                &mut self.xc,
                &mut self.vc,
            );
            non_finite |= !v2.is_finite();
            max_v2 = max_v2.max(v2);
        }
        let explicit_core_steps = if self.implicit.is_some() {
            0
        } else {
            self.core_substeps
        };
        for _ in 0..explicit_core_steps {
            self.core_forces();
            let v2 = integrate_nodes(
                IntegratorKind::SymplecticEuler,
                &self.fem,
                &[],
                dt_c,
                &self.fc,
                &mut self.xc,
                &mut self.vc,
            );
            non_finite |= !v2.is_finite();
            max_v2 = max_v2.max(v2);
        }
        let damp = 1.0 / (1.0 + self.fem.material().mass_damping_per_s * dt);
        let inv_m = dt / self.particle_mass_kg;
        if self.deviation {
            let xc = &self.xc;
            for (&p, t) in self.active_list.iter().zip(&self.active_ties) {
                let p = p as usize;
                let v = (self.vp[p] + self.fp[p] * inv_m) * damp;
                self.vp[p] = v;
                self.xd[p] += v * dt;
                // The absolute position, for the surface and the release test between ticks.
                self.xp[p] = t.interpolate(xc) + self.xd[p];
                let s = v.length_squared();
                non_finite |= !s.is_finite();
                max_v2 = max_v2.max(s);
            }
        } else {
            for &p in &self.active_list {
                let p = p as usize;
                let v = (self.vp[p] + self.fp[p] * inv_m) * damp;
                self.vp[p] = v;
                self.xp[p] += v * dt;
                let s = v.length_squared();
                non_finite |= !s.is_finite();
                max_v2 = max_v2.max(s);
            }
        }
        if non_finite { f64::NAN } else { max_v2 }
    }

    /// Advances `ticks` servo periods without a device (for tests and studies).
    ///
    /// # Errors
    /// As [`SoftBody::tick`].
    pub fn run_free(&mut self, ticks: usize) -> Result<(), ModelError> {
        for _ in 0..ticks {
            self.tick(&TickInput::default())?;
        }
        Ok(())
    }
}

impl SoftBody for HybridBody {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        input.validate()?;
        if let Some(time_s) = self.diverged_at_s {
            return Err(ModelError::Diverged { time_s });
        }
        // 1. Release, then activation (which may release unsettled far regions for room).
        let probe = input.device_position_m;
        if !self.hold {
            self.release_far(probe);
        }
        if let Some(c) = probe {
            self.activate_near(c, self.model.params.activation_radius_m);
        }
        // 2. Sub-steps.
        let mut out = ProxyContact {
            force_on_device_n: DVec3::ZERO,
            stiffness_n_per_m: [0.0; 9],
            proxy_m: probe.unwrap_or(DVec3::ZERO),
            in_contact: false,
        };
        for _ in 0..self.substeps {
            out = self.particle_forces(probe);
            let v2 = self.update(self.dt_s);
            if !(v2 <= MAX_SPEED_M_PER_S * MAX_SPEED_M_PER_S) {
                self.diverged_at_s = Some(self.time_s);
                return Err(ModelError::Diverged {
                    time_s: self.time_s,
                });
            }
        }
        // 3. The device force at the end of the tick: the proxy solved again against the
        // particles the sub-steps moved. (The force of the last sub-step's start lags the body
        // by a tick: through the coupling that reads `k_c v h` too high while the device moves,
        // 3 mN at 10 mm/s, and drops by as much in the tick it stops.)
        if let Some(device) = probe {
            out = self.proxy.update(device, &self.xp, &self.active_list, None);
        }
        self.time_s += self.tick_s;
        // Point loads age by the tick.
        let mut k = 0;
        while k < self.load_count {
            self.loads[k].remaining_s -= self.tick_s;
            if self.loads[k].remaining_s <= 0.0 {
                self.loads[k] = self.loads[self.load_count - 1];
                self.load_count -= 1;
            } else {
                k += 1;
            }
        }
        // 4. Device force, clamped.
        let (mut force, mut stiffness) = (out.force_on_device_n, out.stiffness_n_per_m);
        let mag = force.length();
        if mag > self.probe.max_force_n {
            let s = self.probe.max_force_n / mag;
            force *= s;
            stiffness.iter_mut().for_each(|v| *v *= s);
        }
        self.last_force_n = force;
        Ok(TickOutput {
            force_on_device_n: force,
            in_contact: out.in_contact,
            proxy_position_m: out.proxy_m,
            contact_stiffness_n_per_m: stiffness,
            sim_time_s: self.time_s,
        })
    }

    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        validate_point_load(point_m, force_n, duration_s)?;
        if self.load_count == MAX_POINT_LOADS {
            return Err(ModelError::LoadTableFull(MAX_POINT_LOADS));
        }
        let m = &self.model;
        let mut best = (f64::INFINITY, 0usize);
        for v in 0..m.outer_rest_m.len() {
            let x = m.interpolate(&m.vertex_tie[v], &self.xc);
            let d = (x - point_m).length_squared();
            if d < best.0 {
                best = (d, v);
            }
        }
        self.loads[self.load_count] = PointLoad {
            tie: m.vertex_tie[best.1],
            force_n,
            remaining_s: duration_s,
        };
        self.load_count += 1;
        Ok(())
    }

    fn surface_topology(&self) -> SurfaceTopology<'_> {
        SurfaceTopology {
            version: 1,
            vertex_count: self.model.outer_rest_m.len(),
            triangles: &self.model.outer_triangles,
        }
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        SurfaceCapacity {
            vertices: self.model.outer_rest_m.len(),
            triangles: self.model.outer_triangles.len(),
        }
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        let m = &self.model;
        assert_eq!(out.len(), 3 * m.outer_rest_m.len(), "surface buffer length");
        let mut max_d2: f64 = 0.0;
        for v in 0..m.outer_rest_m.len() {
            let mut x = m.interpolate(&m.vertex_tie[v], &self.xc);
            let p = m.vertex_particle[v];
            if p != u32::MAX && self.active[p as usize] {
                let p = p as usize;
                x += self.xp[p] - m.interpolate(&m.particle_tie[p], &self.xc);
            }
            out[3 * v] = x.x as f32;
            out[3 * v + 1] = x.y as f32;
            out[3 * v + 2] = x.z as f32;
            max_d2 = max_d2.max((x - m.outer_rest_m[v]).length_squared());
        }
        max_d2.sqrt()
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        let m = &self.model;
        assert_eq!(out.len(), 3 * m.outer_rest_m.len(), "surface buffer length");
        for (v, x) in m.outer_rest_m.iter().enumerate() {
            out[3 * v] = x.x as f32;
            out[3 * v + 1] = x.y as f32;
            out[3 * v + 2] = x.z as f32;
        }
    }

    fn stats(&self) -> BodyStats {
        let max_displacement_m = self
            .xc
            .iter()
            .zip(&self.model.core_mesh.nodes)
            .fold(0.0f64, |a, (x, r)| a.max((*x - *r).length()));
        BodyStats {
            nodes: self.xc.len(),
            elements: self.model.core_mesh.tets.len(),
            active_elements: self.model.core_mesh.tets.len(),
            particles: self.model.layer_count,
            active_particles: self.active_list.len(),
            active_point_loads: self.load_count,
            surface_vertices: self.model.outer_rest_m.len(),
            topology_version: 1,
            sim_time_s: self.time_s,
            max_displacement_m,
            ..BodyStats::default()
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "hybrid",
            scene: self.name.clone(),
            tick_s: self.tick_s,
            substeps: self.substeps,
            critical_dt_s: self.critical_dt_s,
            probe_radius_m: self.probe.radius_m,
            point_loads: crate::body::PointLoadZone::Anywhere,
        }
    }
}

/// Result of [`HybridBody::max_eigenvalue_estimate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EigenEstimate {
    /// Rayleigh quotient of the last iterate, 1/s^2 (a lower bound of `lambda_max`).
    pub lambda_per_s2: f64,
    /// Relative change of the quotient over the last ten iterations.
    pub relative_change: f64,
    /// Iterations run.
    pub iterations: usize,
    /// The critical step `2 / sqrt(lambda)`, s, of the central-difference scheme.
    pub critical_step_s: f64,
}

impl HybridBody {
    /// Estimates the largest eigenvalue of `M^-1 K` of the current simulated system (free core
    /// nodes and active particles, tied particles following the core; `K` linearised at the
    /// current positions by forward differences of the forces, velocities held at zero, no
    /// probe) by power iteration on `M^-1/2 K M^-1/2`, stopping when the Rayleigh quotient
    /// changes by less than `tolerance` (relative) over ten iterations or after
    /// `max_iterations`. A diagnostic for studies of the explicit step (the body's own
    /// sub-steps use the Gershgorin bound of [`crate::meshfree::critical_time_step`]); the
    /// state is restored afterwards. Allocates.
    ///
    /// # Errors
    /// [`ModelError::NoConvergence`] when the quotient has not settled to `tolerance` after
    /// `max_iterations` (the message gives the last change).
    pub fn max_eigenvalue_estimate(
        &mut self,
        max_iterations: usize,
        tolerance: f64,
    ) -> Result<EigenEstimate, ModelError> {
        let x0c = self.xc.clone();
        let x0p = self.xp.clone();
        // Deviation mode: the active particles' coordinates are their deviations.
        let x0d = self.xd.clone();
        let v0c = std::mem::replace(&mut self.vc, vec![DVec3::ZERO; x0c.len()]);
        // The implicit core is not part of the explicit system: held.
        let free: Vec<bool> = self
            .fem
            .constraints()
            .iter()
            .map(|c| *c == 0 && self.model.params.core_step == CoreStep::Explicit)
            .collect();
        let inv_sqrt_mc: Vec<f64> = self
            .fem
            .lumped_mass_kg()
            .iter()
            .map(|m| 1.0 / m.sqrt())
            .collect();
        let inv_sqrt_mp = 1.0 / self.particle_mass_kg.sqrt();
        let active = self.active_list.clone();
        self.particle_forces(None);
        self.core_forces();
        let (f0c, f0p) = (self.fc.clone(), self.fp.clone());
        // Step length: 1e-7 of the particle spacing for a unit mass-weighted vector.
        let eps = 1e-7 * self.model.params.meshfree.spacing_m / inv_sqrt_mp;
        // A deterministic start with every component present.
        let start = |i: usize| {
            let h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            DVec3::new(
                (h >> 40) as f64 / (1u64 << 24) as f64 - 0.5,
                ((h >> 20) & 0xF_FFFF) as f64 / (1u64 << 20) as f64 - 0.5,
                (h & 0xF_FFFF) as f64 / (1u64 << 20) as f64 - 0.5,
            )
        };
        let mut uc: Vec<DVec3> = (0..x0c.len())
            .map(|i| if free[i] { start(i) } else { DVec3::ZERO })
            .collect();
        let mut up = vec![DVec3::ZERO; x0p.len()];
        for &p in &active {
            up[p as usize] = start(x0c.len() + p as usize);
        }
        let mut history = Vec::with_capacity(max_iterations);
        let mut result = None;
        for it in 0..max_iterations {
            let norm = (uc.iter().map(|u| u.length_squared()).sum::<f64>()
                + active
                    .iter()
                    .map(|&p| up[p as usize].length_squared())
                    .sum::<f64>())
            .sqrt();
            for (i, u) in uc.iter_mut().enumerate() {
                *u /= norm;
                self.xc[i] = x0c[i] + *u * (eps * inv_sqrt_mc[i]);
            }
            for &p in &active {
                let p = p as usize;
                up[p] /= norm;
                if self.deviation {
                    self.xd[p] = x0d[p] + up[p] * (eps * inv_sqrt_mp);
                } else {
                    self.xp[p] = x0p[p] + up[p] * (eps * inv_sqrt_mp);
                }
            }
            self.particle_forces(None);
            self.core_forces();
            // w = M^-1/2 K M^-1/2 u, with K u ~ -(f(x0 + eps M^-1/2 u) - f(x0)) / eps.
            let mut rayleigh = 0.0;
            for (i, u) in uc.iter_mut().enumerate() {
                let w = if free[i] {
                    -(self.fc[i] - f0c[i]) * (inv_sqrt_mc[i] / eps)
                } else {
                    DVec3::ZERO
                };
                rayleigh += w.dot(*u);
                *u = w;
            }
            for &p in &active {
                let p = p as usize;
                let w = -(self.fp[p] - f0p[p]) * (inv_sqrt_mp / eps);
                rayleigh += w.dot(up[p]);
                up[p] = w;
            }
            history.push(rayleigh);
            if it >= 10 {
                let change = (rayleigh - history[it - 10]).abs() / rayleigh.abs();
                if change < tolerance {
                    result = Some(EigenEstimate {
                        lambda_per_s2: rayleigh,
                        relative_change: change,
                        iterations: it + 1,
                        critical_step_s: 2.0 / rayleigh.sqrt(),
                    });
                    break;
                }
            }
        }
        self.xc.copy_from_slice(&x0c);
        self.xp.copy_from_slice(&x0p);
        self.xd.copy_from_slice(&x0d);
        self.vc = v0c;
        self.particle_forces(None);
        result.ok_or_else(|| {
            let n = history.len();
            let change = if n > 10 {
                (history[n - 1] - history[n - 11]).abs() / history[n - 1].abs()
            } else {
                f64::NAN
            };
            ModelError::NoConvergence(format!(
                "power iteration for lambda_max: relative change {change:.2e} after {n} iterations (tolerance {tolerance:.1e})"
            ))
        })
    }
}
