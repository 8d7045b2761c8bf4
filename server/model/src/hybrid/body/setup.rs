//! Building a [`HybridBody`]: masses, the sub-steps and their set-up check against the coupled
//! system's limit, the implicit core's factor (module documentation of [`super`]).

use super::CORE_COUPLING_MARGIN;
use super::COUPLED_STEP_HEADROOM;
use super::MAX_POINT_LOADS;
use super::PointLoad;
use super::STEP_CHECK_POINTS;
use super::{
    ExtraTool, HybridBody, HybridPipeline, HybridScratch, HybridSetup, HybridState, HybridStats,
    RegionSet,
};
use crate::ModelError;
use crate::body::MAX_TOOLS;
use crate::contact::probe::ProbeParams;
use crate::element::FemModel;
use crate::hybrid::CoreMassScale;
use crate::hybrid::CoreStep;
use crate::hybrid::InactiveLayer;
use crate::hybrid::ScaledMotion;
use crate::hybrid::implicit::CondensedLayer;
use crate::hybrid::implicit::ImplicitCore;
use crate::hybrid::layer::LayerElements;
use crate::hybrid::prepare::HybridModel;
use crate::hybrid::proxy::ParticleProxy;
use crate::integrate::damped_critical_step_s;
use crate::integrate::damped_max_omega2_per_s2;
use crate::integrate::viscous_beta_s;
use crate::meshfree::TermBlock;
use glam::DVec3;

impl HybridBody {
    /// Gives the body tool slots 1.. (issue 50; slot 0 is the probe of [`Self::new`]): one
    /// proxy per entry of `probes` (each with its radius, coupling stiffness and force limit),
    /// and the named tools' ids by slot (`tool_ids[k]` names slot `k`). Set-up, not a tick:
    /// allocates.
    pub fn set_tools(&mut self, probes: &[ProbeParams], tool_ids: &[String]) {
        let params = self.model.params;
        let skin = self.model.contact_skin_m();
        let most_active = params.max_active_particles + self.model.largest_region;
        self.state.tools = probes
            .iter()
            .take(MAX_TOOLS - 1)
            .map(|p| ExtraTool {
                proxy: ParticleProxy::new(
                    p,
                    params.meshfree.spacing_m,
                    params.contact_stiffness_n_per_m,
                    &skin,
                    most_active,
                ),
                max_force_n: p.max_force_n,
            })
            .collect();
        self.setup.tool_ids = tool_ids.to_vec();
    }
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
        // The core carries its own mass and the particle layer's (the inactive particles
        // follow it), both times the core's mass scale (`CoreMassScale`).
        let mut fem = FemModel::new(&model.core_mesh, *model.cloud.material())?;
        if params.inactive_layer == InactiveLayer::Tied {
            fem.add_lumped_mass(&model.layer_mass_on_core_kg());
        }
        fem.clamp_nodes(clamped);
        let setup = HybridSetup::new(&model, &mut fem, probe, tick_s, name)?;
        let n = model.cloud.len();
        let nc = model.core_mesh.nodes.len();
        let nv = model.outer_rest_m.len();
        let capacity = 4 * params.max_active_particles + 4 * model.largest_region + 64;
        let most_active = params.max_active_particles + model.largest_region;
        let mut body = Self {
            state: HybridState {
                xc: model.core_mesh.nodes.clone(),
                vc: vec![DVec3::ZERO; nc],
                xp: model.cloud.rest_m().to_vec(),
                vp: vec![DVec3::ZERO; n],
                xd: vec![DVec3::ZERO; n],
                xp_fresh: false,
                proxy: ParticleProxy::new(
                    &probe,
                    params.meshfree.spacing_m,
                    params.particle_contact_stiffness_n_per_m(),
                    &model.contact_skin_m(),
                    most_active,
                ),
                loads: [PointLoad::default(); MAX_POINT_LOADS],
                load_count: 0,
                time_s: 0.0,
                diverged_at_s: None,
                last_force_n: DVec3::ZERO,
                tools: Vec::new(),
                fades: Default::default(),
                departed: [None; MAX_TOOLS],
                evict_guard: [None; MAX_TOOLS],
            },
            regions: RegionSet {
                active: vec![false; n],
                in_block: vec![false; n],
                active_list: Vec::with_capacity(most_active),
                tied_list: Vec::with_capacity(3 * capacity),
                region_active: vec![false; nv],
                active_regions: Vec::with_capacity(nv),
                vertex_adj_start: Vec::new(),
                vertex_adj: Vec::new(),
                changed: false,
                hold: false,
                vertex_bounds: super::regions::VertexBounds::new(&model, fem.rest()),
            },
            pipeline: HybridPipeline {
                block: TermBlock::new(&model.cloud, capacity),
                layer: (params.inactive_layer == InactiveLayer::Elements)
                    .then(|| LayerElements::new(&model, &fem)),
                implicit: None,
                tied_ties: Vec::with_capacity(3 * capacity),
                active_ties: Vec::with_capacity(most_active),
                active_order: Vec::with_capacity(most_active),
                pool: None,
            },
            scratch: HybridScratch {
                fc: vec![DVec3::ZERO; nc],
                fp: vec![DVec3::ZERO; n],
                fcoup: vec![DVec3::ZERO; nc],
                ffem: vec![DVec3::ZERO; nc],
                flayer: vec![DVec3::ZERO; nc],
                ffem_ready: false,
                matrix_regions: Vec::with_capacity(nv),
                region_mark: vec![false; nv],
                candidates: Vec::with_capacity(nv),
            },
            stats: HybridStats::default(),
            setup,
            fem,
            model: Box::new(model),
        };
        // The check holds the core when it steps implicitly (not part of the explicit system).
        body.verify_coupled_step()?;
        if let CoreStep::Implicit { margin } = params.core_step {
            (body.regions.vertex_adj_start, body.regions.vertex_adj) =
                vertex_adjacency(&body.model.outer_triangles, nv);
            let layer = match params.inactive_layer {
                InactiveLayer::Tied => Some(CondensedLayer::new(&body.model)?),
                InactiveLayer::Elements => None,
            };
            let core = ImplicitCore::new(&body.fem, layer.as_ref(), body.setup.dt_s, margin)?;
            body.pipeline.implicit = Some((core, margin));
        }
        Ok(body)
    }

    /// Rebuilds the implicit core's matrix when the sub-step changed (studies; condenses the
    /// layer again, about 0.8 s on `lv-hybrid`).
    pub(super) fn rebuild_implicit(&mut self) -> Result<(), ModelError> {
        if let Some((core, margin)) = self.pipeline.implicit.take() {
            let mut core = if core.h_s() == self.setup.dt_s {
                core
            } else {
                let layer = match self.model.params.inactive_layer {
                    InactiveLayer::Tied => Some(CondensedLayer::new(&self.model)?),
                    InactiveLayer::Elements => None,
                };
                ImplicitCore::new(&self.fem, layer.as_ref(), self.setup.dt_s, margin)?
            };
            core.refactor(&self.scratch.matrix_regions)?;
            self.pipeline.implicit = Some((core, margin));
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
    pub(super) fn verify_coupled_step(&mut self) -> Result<(), ModelError> {
        let params = self.model.params;
        let beta = viscous_beta_s(self.fem.material());
        let k_over_m = params.particle_contact_stiffness_n_per_m() / self.setup.particle_mass_kg;
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
        self.regions.hold = true;
        for point in points {
            let mut r = 0.5 * params.meshfree.spacing_m;
            while self.regions.active_list.len() < params.max_active_particles && r < 0.05 {
                self.activate_near(point, r);
                r += 0.5 * params.meshfree.spacing_m;
            }
            let estimate = self.max_eigenvalue_estimate(1000, 1e-3);
            while let Some(k) = self.regions.active_regions.len().checked_sub(1) {
                self.deactivate_region(k);
            }
            self.regions.active_list.clear();
            let e = estimate?;
            limit_s = limit_s.min(damped_critical_step_s(e.lambda_per_s2 + k_over_m, beta));
        }
        self.regions.hold = false;
        self.stats.refused_activations = 0;
        self.rebuild_terms();
        let needed = (self.setup.tick_s / (COUPLED_STEP_HEADROOM * limit_s)).ceil() as u32;
        if needed > self.setup.substeps {
            if needed > params.max_substeps {
                return Err(ModelError::field(
                    "hybrid.max_substeps",
                    format!(
                        "the coupled system's critical step ({limit_s:.3e} s, power iteration at {STEP_CHECK_POINTS} points) needs {needed} sub-steps per {} s tick; raise max_substeps or mass_scale, or use a coarser core",
                        self.setup.tick_s
                    ),
                ));
            }
            self.setup.substeps = needed;
            self.setup.dt_s = self.setup.tick_s / needed as f64;
        }
        Ok(())
    }
}

impl HybridSetup {
    /// The masses and sub-steps: the particles' critical step (Gershgorin bound with the probe
    /// penalty), the core's mass scale ([`CoreMassScale`]; adds the scaled mass to `fem`) and
    /// its critical step times [`CORE_COUPLING_MARGIN`] for an explicit core.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.max_substeps` when the steps need more
    /// sub-steps per tick.
    fn new(
        model: &HybridModel,
        fem: &mut FemModel,
        probe: ProbeParams,
        tick_s: f64,
        name: &str,
    ) -> Result<Self, ModelError> {
        let params = model.params;
        let particle_mass_kg = model.cloud.mass_kg() * params.mass_scale;
        // Elastic part scales with 1/mass; the probe penalty adds k / m to the eigenvalue bound.
        let lambda_el = (2.0 / model.particle_dt_s).powi(2) / params.mass_scale;
        let lambda = lambda_el + params.particle_contact_stiffness_n_per_m() / particle_mass_kg;
        let particle_dt = 2.0 / lambda.sqrt();
        let substeps_for = |dt_s: f64| (tick_s / (params.safety_factor * dt_s)).ceil().max(1.0);
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
        Ok(Self {
            name: name.to_string(),
            probe,
            tool_ids: Vec::new(),
            tick_s,
            substeps,
            core_substeps,
            dt_s: tick_s / substeps as f64,
            critical_dt_s,
            particle_mass_kg,
            core_mass_scale,
            deviation: params.scaled_motion == ScaledMotion::Deviation,
        })
    }
}

/// The outer vertices' adjacency over `triangles` as CSR (`start`, `adjacent`): vertex `v`'s
/// neighbours are `adjacent[start[v]..start[v + 1]]`, in first-seen order.
fn vertex_adjacency(triangles: &[[u32; 3]], nv: usize) -> (Vec<u32>, Vec<u32>) {
    let mut adj: Vec<Vec<u32>> = vec![Vec::new(); nv];
    for t in triangles {
        for a in 0..3 {
            for b in 0..3 {
                if a != b && !adj[t[a] as usize].contains(&t[b]) {
                    adj[t[a] as usize].push(t[b]);
                }
            }
        }
    }
    let start = std::iter::once(0)
        .chain(adj.iter().scan(0u32, |acc, a| {
            *acc += a.len() as u32;
            Some(*acc)
        }))
        .collect();
    (start, adj.concat())
}
