//! [`FemBody`]: the FEM family of [`crate::body::SoftBody`]: one tetrahedral body driven
//! by a haptic probe and loads, advanced one servo tick at a time.
//!
//! Layout follows state / scratch / parameters: [`FemState`] holds positions, velocities and
//! time; the force buffer is scratch sized at construction; the [`FemModel`], the
//! [`Stepper`] (which owns its solver workspace), the [`BodyLoads`] and the probe parameters are
//! fixed at construction. [`FemBody::tick`] allocates nothing, takes no lock and does no
//! I/O, so the server can call it on its servo thread. A tick is, per sub-step: internal forces,
//! loads, contact update (the probe's explicit reaction), one step of the [`Stepper`] (which
//! completes the coupling), and a divergence check; then the output.
//!
//! **Several tools** (issue 50). The body keeps one [`Probe`] per tool slot (`probe.max_tools`); [`FemBody::tick_tools`] updates every connected slot's probe
//! and adds its reaction in each sub-step, and the stepper solves all their couplings in the
//! same step ([`Stepper::step_tools`]: backward Euler joins their rows in one low-rank term).
//! [`FemBody::tick`] is slot 0 alone, the other slots released. A following region covers
//! every connected tool (a union of balls, [`crate::integrate::follow`], "Several tools").
//!
//! **The coarse companion.** A following active region (`[active_region] follow`) holds only
//! the elements near its centre; a new one takes seconds to prepare on a large mesh
//! ([`crate::integrate::follow`]), and a probe that leaves the region meanwhile rests on the
//! condensed far surface, which does not yield. With `fallback_target_tets` the scene carries
//! a coarse whole-body companion ([`Scene::fallback`]: the same built-in geometry, quadratic,
//! backward Euler on its rest factor) that ticks with the same device input every tick, on a
//! worker of the session's [`TickPool`] beside the region's solve when it has one (the two
//! share no state; the region's forces and far products are cut into the pool's parts
//! before it, so two threads differ from one by round-off and two 2-thread runs not at all).
//! The companion ticks every tool slot; where a tool's contact patch reaches a node the region
//! does not simulate, the companion answers for that tool: its output force (and contact
//! stiffness) is `(1 - w) f_region + w f_companion`, with the tool's own weight `w`
//! moving towards 1 by at most `1 / FALLBACK_BLEND_TICKS` per tick; it moves back towards 0
//! only after the region has held the whole patch for `FALLBACK_SETTLE_TICKS` ticks (a region
//! swapped in under a deep probe starts undeformed and needs that long to settle). Viewers
//! still see the fine body; point loads act on it only.
//!
//! Owns: the FEM body. May use: [`crate::element`], [`crate::integrate`], [`crate::contact`],
//! [`crate::loads`], [`crate::scene`] (to build from), [`crate::body`] (the interface it
//! implements).

use std::sync::Arc;

use glam::DVec3;

use crate::body::{
    BodyInfo, BodyStats, MAX_TOOLS, PointLoadZone, SoftBody, SurfaceCapacity, SurfaceTopology,
    check_tool_inputs,
};
use crate::contact::coupling::{MAX_COUPLED_PROBES, MAX_COUPLING_ROWS};
use crate::contact::{ContactModel, CouplingMerge, LocalLaw, MAX_PATCH_NODES, Probe, ProbeParams};
use crate::element::{CLAMPED, FemModel, ForceScratch};
use crate::integrate::condensed::{ActiveRegion, CondensedSolver, MAX_REGION_BALLS};
use crate::integrate::follow::{FollowStats, RegionFollower};
use crate::integrate::implicit::CgStats;
use crate::integrate::{self, IntegratorKind, IntegratorParams, StepPlan, Stepper};
use crate::loads::BodyLoads;
use crate::pool::TickPool;
use crate::scene::Scene;
use crate::{BodyOptions, ModelError};

pub use crate::body::{TickInput, TickOutput};
pub use crate::integrate::FemState;
pub use fallback::FallbackStats;

mod fallback;

use fallback::Fallback;

// The probes' joined implicit term holds every tool slot's rows.
const _: () = assert!(MAX_TOOLS <= MAX_COUPLED_PROBES);
// A following region has a ball per tool slot.
const _: () = assert!(MAX_TOOLS <= MAX_REGION_BALLS);

/// A nodal speed above this (m/s) is treated as divergence.
pub const DIVERGENCE_SPEED_M_PER_S: f64 = 100.0;

/// Ticks over which the coarse companion's weight goes from 0 to 1 or back (module
/// documentation, "The coarse companion").
pub const FALLBACK_BLEND_TICKS: u32 = 20;

/// Ticks the region must hold the whole contact patch before the coarse companion hands the
/// probe back to it.
pub const FALLBACK_SETTLE_TICKS: u32 = 100;

/// Whether a simulation is still meaningful, with the quantities that say so
/// ([`FemBody::stability`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StabilityReport {
    /// The state is finite and no tick diverged.
    pub stable: bool,
    /// Simulated time of the tick that diverged ([`ModelError::Diverged`]), s.
    pub diverged_at_s: Option<f64>,
    /// Every position and velocity is finite.
    pub finite: bool,
    /// Largest nodal speed, m/s.
    pub max_speed_m_per_s: f64,
    /// Kinetic energy, J.
    pub kinetic_energy_j: f64,
    /// Elastic energy of the material, J.
    pub elastic_energy_j: f64,
    /// Largest nodal displacement from rest, m.
    pub max_displacement_m: f64,
    /// Elements with `det F <= 0`.
    pub inverted_elements: usize,
    /// Relative change of the total (signed) volume, `(V - V0) / V0`.
    pub volume_change: f64,
    /// Conjugate-gradient statistics of the last backward Euler step (default otherwise).
    pub cg: CgStats,
}

/// A tetrahedral FEM body with its probe, loads, stepper and sub-stepping (module
/// documentation).
#[derive(Debug, Clone)]
pub struct FemBody {
    fem: FemModel,
    stepper: Stepper,
    setup: FemSetup,
    state: FemState,
    /// One probe per tool slot (issue 50), slot 0 first: [`FemBody::tick`] drives slot 0
    /// alone; [`FemBody::tick_tools`] every slot.
    probes: Vec<Probe>,
    /// The joined implicit term of the probes in contact ([`Stepper::step_tools`]).
    merge: CouplingMerge,
    loads: BodyLoads,
    scratch: FemScratch,
    status: TickStatus,
    /// A following active region's worker ([`RegionFollower`]).
    follow: FollowSlot,
    /// The coarse companion of a following region (`active_region.fallback_target_tets`).
    fallback: Option<Box<Fallback>>,
    /// The session's worker pool ([`SoftBody::set_tick_pool`]; serial until one is given): the
    /// forces and every probe's contact beside each other, the far products in parts, the
    /// companion beside the region's solve.
    pool: Arc<TickPool>,
}

/// What a [`FemBody`] fixes at set-up: its sub-stepping, tick and the surface it shows.
#[derive(Debug, Clone)]
struct FemSetup {
    plan: StepPlan,
    /// Servo tick, s.
    tick_s: f64,
    scene_name: String,
    /// Surface for viewers: distinct boundary nodes and triangles indexing into them.
    surface_nodes: Vec<u32>,
    surface_triangles: Vec<[u32; 3]>,
    /// The scene's named tools by slot ([`SoftBody::tool_slot`]).
    tool_ids: Vec<String>,
}

/// Work arrays of one sub-step, overwritten every time.
#[derive(Debug, Clone)]
struct FemScratch {
    /// Total nodal forces of the current sub-step, N.
    force: Vec<DVec3>,
    /// Work arrays of the single-precision force kernel (empty when it is off).
    kernel: ForceScratch,
}

/// What the ticks so far left: the last output and whether one diverged.
#[derive(Debug, Clone, Copy, Default)]
struct TickStatus {
    /// Set when a tick diverged; later ticks refuse to run.
    diverged_at_s: Option<f64>,
    last_output: TickOutput,
}

/// Holds the [`RegionFollower`] of a following active region. A clone of the simulation does
/// not follow: it keeps the region it has (the worker thread is not cloned).
#[derive(Debug, Default)]
struct FollowSlot(Option<RegionFollower>);

impl Clone for FollowSlot {
    fn clone(&self) -> Self {
        Self(None)
    }
}

impl FemBody {
    /// Builds the simulation of `scene`: precomputes the FEM data, the critical time step, the
    /// sub-step plan and the stepper (the semi-implicit per-node matrices, the backward Euler
    /// preconditioner, or the condensed factorisation).
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] / [`ModelError::SceneField`] for a bad mesh, material or
    /// active region; [`ModelError::Unstable`] when the integrator cannot be stable within
    /// `max_substeps`.
    pub fn new(scene: &Scene) -> Result<Self, ModelError> {
        Self::new_with_progress(scene, &mut |_, _| {})
    }

    /// [`FemBody::new`] reporting its stages, `progress(stage, fraction)` with the fraction
    /// done in `[0, 1]`: the FEM data, then (a contact-local active region) the condensation
    /// ([`crate::integrate::condensed::CondensedSolver::new_with_progress`]), which takes
    /// seconds on large meshes.
    ///
    /// # Errors
    /// As [`FemBody::new`].
    pub fn new_with_progress(
        scene: &Scene,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        Self::new_with_options(scene, &BodyOptions::default(), progress)
    }

    /// [`FemBody::new_with_progress`] with the host's `options` ([`BodyOptions`]: where a
    /// following region keeps its tiles between sessions).
    ///
    /// # Errors
    /// As [`FemBody::new`].
    pub fn new_with_options(
        scene: &Scene,
        options: &BodyOptions,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        progress("FEM data", 0.0);
        let fem = scene.fem_model()?;
        Self::from_fem_with_progress(fem, scene, options, &mut |stage, f| {
            progress(stage, 0.1 + 0.9 * f)
        })
    }

    /// Like [`FemBody::new`] but with a prepared [`FemModel`] (e.g. with roller constraints).
    ///
    /// # Errors
    /// As [`FemBody::new`].
    pub fn from_fem(fem: FemModel, scene: &Scene) -> Result<Self, ModelError> {
        Self::from_fem_with_progress(fem, scene, &BodyOptions::default(), &mut |_, _| {})
    }

    fn from_fem_with_progress(
        fem: FemModel,
        scene: &Scene,
        options: &BodyOptions,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        let p = scene.integrator;
        if !(p.tick_s > 0.0 && p.tick_s.is_finite()) {
            return Err(ModelError::field(
                "integrator.tick_s",
                "must be a positive number",
            ));
        }
        // Before the critical step: an explicit integrator on a condensed scene would
        // otherwise report the tick as unstable rather than the combination as unsupported.
        if scene.active_region.is_some() && p.kind != IntegratorKind::BackwardEuler {
            return Err(ModelError::field(
                "active_region",
                "needs integrator.kind = \"backward-euler\"",
            ));
        }
        let critical = integrate::critical_time_step(&fem, p.kind);
        let plan = integrate::plan_steps(&p, critical)?;
        let mut stepper = stepper_of(&fem, scene, &p, &plan, progress)?;
        let n = fem.node_count();
        let boundary = scene.mesh.boundary_triangles();
        let load_surface: Vec<[u32; 3]> = boundary
            .iter()
            .copied()
            .filter(|t| t.iter().any(|&i| fem.constraints()[i as usize] != CLAMPED))
            .collect();
        let mut loads = BodyLoads::new(
            &scene.loads,
            fem.rest(),
            fem.lumped_mass_kg(),
            load_surface.clone(),
        );
        let mut touchable = scene.touchable.clone();
        let follows = scene.active_region.is_some_and(|r| r.follow);
        if follows && loads.acts_outside(|_| false) {
            return Err(ModelError::field(
                "active_region.follow",
                "a following region takes no scene loads (they would act on condensed elements as the region moves): remove [loads] or fix the region",
            ));
        }
        if let Some(c) = stepper.condensed().filter(|_| !follows) {
            (loads, touchable) =
                confine_to_region(c, scene, &fem, &loads, &load_surface, touchable)?;
        }
        let mut follow = FollowSlot(None);
        if let Stepper::Condensed(c) = &mut stepper {
            let contact_nodes: Vec<u32> = touchable.iter().flatten().copied().collect();
            c.prepare_contact(&contact_nodes);
            if follows {
                follow.0 = Some(follower(&fem, scene, &contact_nodes, c, options)?);
            }
        }
        let (surface_nodes, surface_triangles) = surface_map(&boundary, n);
        let implicit_dt_s = (p.kind == IntegratorKind::BackwardEuler).then_some(plan.sub_dt_s);
        let probes = tool_probes(scene, &touchable, fem.rest(), implicit_dt_s);
        let fallback = companion(scene, follows, progress)?;
        Ok(Self {
            stepper,
            setup: FemSetup {
                plan,
                tick_s: p.tick_s,
                scene_name: scene.name.clone(),
                surface_nodes,
                surface_triangles,
                tool_ids: scene.tools.named.iter().map(|t| t.id.clone()).collect(),
            },
            loads,
            state: FemState {
                x: fem.rest().to_vec(),
                v: vec![DVec3::ZERO; n],
                time_s: 0.0,
            },
            scratch: FemScratch {
                force: vec![DVec3::ZERO; n],
                kernel: ForceScratch::new(n),
            },
            merge: CouplingMerge::with_capacity(
                probes.len(),
                MAX_PATCH_NODES.max(3 * MAX_COUPLING_ROWS),
            ),
            probes,
            status: TickStatus::default(),
            follow,
            fallback,
            pool: TickPool::serial(),
            fem,
        })
    }

    /// Advances one servo tick (`plan().substeps` model steps) with the device input, and
    /// returns the force for the device. Per sub-step: internal forces, loads, contact update,
    /// one [`Stepper::step`], divergence check.
    ///
    /// # Errors
    /// [`ModelError::InvalidDevice`] for a non-finite or absurd device input (the state is not
    /// touched); [`ModelError::Diverged`] when the state became non-finite or diverged (the
    /// caller must quarantine the session: the state is no longer meaningful). Neither
    /// allocates.
    pub fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        let mut out = [TickOutput::default()];
        self.tick_tools(std::slice::from_ref(input), &mut out)?;
        Ok(out[0])
    }

    /// [`Self::tick`] with every tool slot's input (issue 50; [`SoftBody::tick_tools`]):
    /// `inputs[k]` drives the probe of slot `k` and `outputs[k]` receives its force; slots past
    /// `inputs.len()` are released. All the probes' reactions act in the same sub-steps and
    /// backward Euler solves their couplings together ([`Stepper::step_tools`]). One slot is
    /// [`Self::tick`] bit for bit.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for slot counts [`crate::body::check_tool_slots`] refuses; otherwise as
    /// [`Self::tick`] (any slot's invalid input refuses the tick, state untouched). Neither
    /// allocates.
    pub fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        check_tool_inputs(inputs, outputs.len(), self.probes.len())?;
        if let Some(time_s) = self.status.diverged_at_s {
            return Err(ModelError::Diverged { time_s });
        }
        // The workers stay awake through the tick (no wake-up on the tick's jobs).
        let pool = Arc::clone(&self.pool);
        let _hot = pool.hot();
        let outputs = &mut outputs[..inputs.len()];
        match self.fallback.take() {
            None => self.tick_model(inputs, outputs, None)?,
            Some(mut fb) => {
                let ticked = self.tick_with_companion(inputs, outputs, &mut fb);
                self.fallback = Some(fb);
                ticked?;
            }
        }
        self.status.last_output = outputs[0];
        Ok(())
    }

    /// [`Self::tick_tools`] of a following region with its coarse companion `fb` (taken out
    /// of `self.fallback` meanwhile): the region on this thread, the companion's tick of every
    /// slot on a pool worker beside the region's solve (its longest serial piece:
    /// [`Stepper::step_tools`]'s `beside`; the forces before it and the far products get the
    /// worker too), then each slot's blend (module documentation, "The coarse companion").
    /// The two share nothing but `inputs`, so the companion's outputs do not depend on the
    /// thread count. Both tick even when the region fails (its error is returned first; a
    /// diverged region quarantines the session anyway).
    fn tick_with_companion(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
        fb: &mut Fallback,
    ) -> Result<(), ModelError> {
        let swaps_before = self.follow.0.as_ref().map_or(0, RegionFollower::swaps);
        let n = inputs.len();
        let mut fine = [TickOutput::default(); MAX_TOOLS];
        let mut coarse = [TickOutput::default(); MAX_TOOLS];
        let mut companion = None;
        let ticked = {
            let mut beside = || companion = Some(fb.tick_companion(inputs, &mut coarse[..n]));
            self.tick_model(inputs, &mut fine[..n], Some(&mut beside))
        };
        // A region that failed before its step did not run the companion.
        let companion = companion.unwrap_or_else(|| fb.tick_companion(inputs, &mut coarse[..n]));
        ticked?;
        companion?;
        let swapped = self.follow.0.as_ref().map_or(0, RegionFollower::swaps) != swaps_before;
        let mut outside = [false; MAX_TOOLS];
        if let Some(c) = self.stepper.condensed() {
            for (o, probe) in outside.iter_mut().zip(&self.probes) {
                *o = probe.patch().0.iter().any(|&i| !c.is_active_node(i));
            }
        }
        fb.blend(&fine[..n], &coarse[..n], &outside[..n], swapped, outputs);
        Ok(())
    }

    /// The tick of this body's own model (the region when one follows), without the companion:
    /// [`Self::tick_tools`] after its checks; `beside` runs once, beside the first sub-step's
    /// solve ([`Stepper::step_tools`]), unless the tick fails before it.
    fn tick_model(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
        mut beside: Option<&mut (dyn FnMut() + Send)>,
    ) -> Result<(), ModelError> {
        if let (Some(f), Stepper::Condensed(solver)) = (&mut self.follow.0, &mut self.stepper) {
            let mut devices = [None; MAX_TOOLS];
            for (d, input) in devices.iter_mut().zip(inputs) {
                *d = input
                    .device_position_m
                    .map(|p| (p, input.device_velocity_m_per_s));
            }
            let patches: [&[u32]; MAX_TOOLS] =
                std::array::from_fn(|k| self.probes.get(k).map_or(&[][..], |p| p.patch().0));
            let slots = self.probes.len().min(MAX_TOOLS);
            f.before_tick(
                solver,
                Some(&*self.pool),
                &devices[..inputs.len().min(MAX_TOOLS)],
                &patches[..slots],
                &mut self.state.x,
                &mut self.state.v,
            );
        }
        for _ in 0..self.setup.plan.substeps {
            // 1. Forces, internal and external, and every probe's contact (its proxy and
            // patch) beside them on a pool worker (serially without one: the one-core path);
            // the forces cut into the pool's parts, which the worker joins when the contact
            // is done (one part without a pool, bit for bit).
            self.scratch.force.iter_mut().for_each(|f| *f = DVec3::ZERO);
            let pool = Arc::clone(&self.pool);
            let (stepper, fem, state) = (&self.stepper, &self.fem, &self.state);
            let (scratch, probes) = (&mut self.scratch, &mut self.probes);
            pool.join(
                || {
                    stepper.add_internal_forces_in(
                        &*pool,
                        fem,
                        (&state.x, &state.v),
                        &mut scratch.force,
                        &mut scratch.kernel,
                    );
                },
                || update_probes(probes, inputs, &state.x),
            );
            self.loads.add_to(&self.state.x, &mut self.scratch.force);
            // 2. The explicit part of every probe's reaction.
            self.add_probe_reactions(inputs);
            // 3. Step, completing the couplings.
            let report = self.stepper.step_tools(
                Some(&*self.pool),
                beside.take(),
                &self.fem,
                &self.scratch.force,
                &mut self.probes,
                &mut self.merge,
                &mut self.state,
            );
            let max_v2 = report.max_speed2_m2_per_s2;
            if !(max_v2 <= DIVERGENCE_SPEED_M_PER_S * DIVERGENCE_SPEED_M_PER_S) {
                self.status.diverged_at_s = Some(self.state.time_s);
                return Err(ModelError::Diverged {
                    time_s: self.state.time_s,
                });
            }
        }
        self.state.time_s += self.setup.tick_s;
        self.loads.advance(self.setup.tick_s);
        // 4. Output.
        for ((probe, input), out) in self.probes.iter().zip(inputs).zip(outputs.iter_mut()) {
            let contact = probe.state;
            *out = TickOutput {
                force_on_device_n: contact.force_on_device_n,
                in_contact: contact.in_contact,
                proxy_position_m: if contact.in_contact {
                    contact.proxy_m
                } else {
                    input.device_position_m.unwrap_or(DVec3::ZERO)
                },
                contact_stiffness_n_per_m: probe.contact_stiffness(),
                sim_time_s: self.state.time_s,
            };
        }
        Ok(())
    }

    /// Contact of one sub-step: each slot's probe at its device (released without one, and
    /// past `inputs`), its explicit reaction into the force; the probe load acts at slot 0.
    /// Adds the explicit part of the reaction of every probe with a device (updated by
    /// [`update_probes`]) to the forces, and the probe load's share on the first one's patch.
    fn add_probe_reactions(&mut self, inputs: &[TickInput]) {
        for (k, probe) in self.probes.iter_mut().enumerate() {
            if inputs.get(k).is_some_and(|i| i.device_position_m.is_some()) {
                probe.add_reaction(&mut self.scratch.force);
                if k == 0 && self.loads.probe_load_remaining_s() > 0.0 {
                    let patch = probe.load_patch(&self.state.x);
                    self.loads.add_probe_load_to(patch, &mut self.scratch.force);
                }
            }
        }
    }

    /// What the coarse companion of a following region did (module documentation, "The coarse
    /// companion"); `None` without one.
    pub fn fallback_stats(&self) -> Option<FallbackStats> {
        self.fallback.as_deref().map(Fallback::stats)
    }

    /// Stability of the current state: finite or not, divergence, energies, inverted elements,
    /// volume change, last CG statistics. O(nodes + elements); allocation-free.
    pub fn stability(&self) -> StabilityReport {
        let x = &self.state.x;
        let v = &self.state.v;
        let finite = x.iter().chain(v).all(|a| a.is_finite());
        let max_speed = v
            .iter()
            .map(|a| a.length_squared())
            .fold(0.0, f64::max)
            .sqrt();
        // Condensed: the far elements' nodes are not all current (the tick moves the far
        // boundary only), so energy and volume come from the active elements plus the far
        // part's exact linear energy `u_G^T S u_G / 2`, and its volume change is not tracked.
        let (elastic_energy_j, volume_change) = match self.stepper.condensed() {
            Some(c) => {
                let a = c.active_model();
                (
                    a.elastic_energy(x) + c.far_energy_j(x),
                    (a.deformed_volume_m3(x) - a.total_volume_m3()) / self.fem.total_volume_m3(),
                )
            }
            None => {
                let v0 = self.fem.total_volume_m3();
                (
                    self.fem.elastic_energy(x),
                    (self.fem.deformed_volume_m3(x) - v0) / v0,
                )
            }
        };
        StabilityReport {
            stable: finite && self.status.diverged_at_s.is_none(),
            diverged_at_s: self.status.diverged_at_s,
            finite,
            max_speed_m_per_s: max_speed,
            kinetic_energy_j: self.kinetic_energy_j(),
            elastic_energy_j,
            max_displacement_m: self.max_displacement_m(),
            inverted_elements: self.inverted_elements(),
            volume_change,
            cg: self.cg_stats(),
        }
    }

    /// Number of elements whose deformation gradient has `det F <= 0` (inverted or flat) at
    /// some integration point. With an active region, of the active elements (the far ones are
    /// linear).
    pub fn inverted_elements(&self) -> usize {
        self.stepper
            .force_model(&self.fem)
            .inverted_elements(&self.state.x)
    }

    /// Conjugate-gradient statistics of the last backward Euler step (default for the other
    /// integrators).
    pub fn cg_stats(&self) -> CgStats {
        self.stepper.cg_stats()
    }

    /// Applies `force_n` (N) at the surface point closest to `point_m` (m) for `duration_s` of
    /// simulated time, spread over the free boundary around it as a probe of the scene's radius
    /// touching there would spread its reaction (see [`BodyLoads::add_point_load`]; with an
    /// active region, on the active part of the boundary).
    ///
    /// # Errors
    /// As [`BodyLoads::add_point_load`]: [`ModelError::InvalidInput`] (state untouched) for
    /// non-finite or absurd values, or a point outside [`FemBody::point_load_zone`] (a
    /// fixed active region's ball; none for a following region);
    /// [`ModelError::LoadTableFull`] when the table is full.
    /// Allocation-free, so the servo tick may call it.
    pub fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        self.point_load_zone().check(point_m)?;
        self.loads.add_point_load(
            &self.state.x,
            self.probes[0].params.radius_m,
            point_m,
            force_n,
            duration_s,
        )
    }

    /// Applies `force_n` (N) to the body at the probe for `duration_s` of simulated time: in every
    /// sub-step in contact it is spread over the probe's contact patch with the same kernel
    /// weights as the coupling reaction (the nodes within 2 r of the device point, see
    /// [`crate::contact`]), so it follows the probe. Out of contact it does not act (its time
    /// still runs). The device is not told about it: this is an external disturbance at the
    /// probe (the stability suite's 10-fold impulse), not a change of the coupling. A new call
    /// replaces an active probe load. Allocation-free.
    ///
    /// Unlike [`FemBody::add_point_load`], whose patch is fixed to the nodes around the
    /// point when the load is added, this load moves with the probe.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] (state untouched) for a non-finite force, a force above
    /// [`crate::loads::MAX_POINT_FORCE_N`] or a duration outside
    /// `(0, MAX_POINT_LOAD_DURATION_S]`.
    pub fn add_probe_load(&mut self, force_n: DVec3, duration_s: f64) -> Result<(), ModelError> {
        self.loads.set_probe_load(force_n, duration_s)
    }

    /// Where point loads may act: anywhere on the whole body; within a fixed active region's
    /// ball (its condensed elements take no load); nowhere with a following region (a load
    /// would end up on condensed elements as the region moves on with the probe, and two
    /// contacts far apart would need two regions: refused, issue 20).
    pub fn point_load_zone(&self) -> PointLoadZone {
        match (&self.stepper, self.follow.0.is_some()) {
            (_, true) => PointLoadZone::Refused(
                "this scene's active region follows the probe (active_region.follow) and takes no point loads: a load away from the probe would act on condensed elements; use the probe, or a scene with a fixed region or none",
            ),
            (Stepper::Condensed(c), false) if !c.is_whole_body() => {
                let r = c.region();
                PointLoadZone::Ball {
                    centre_m: r.centre_m,
                    radius_m: r.radius_m,
                }
            }
            _ => PointLoadZone::Anywhere,
        }
    }

    /// Remaining time of the probe load of [`FemBody::add_probe_load`], s (0 when none).
    pub fn probe_load_remaining_s(&self) -> f64 {
        self.loads.probe_load_remaining_s()
    }

    /// Number of point loads still active.
    pub fn active_point_loads(&self) -> usize {
        self.loads.active_point_loads()
    }

    /// Writes the surface vertex positions (xyz interleaved, f32, m) into `out` (length
    /// `3 * surface_node_indices().len()`) and returns the largest displacement from rest among
    /// them, m.
    ///
    /// # Panics
    /// If `out` has the wrong length.
    pub fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        write_positions(
            &self.setup.surface_nodes,
            &self.state.x,
            Some(self.fem.rest()),
            out,
        )
    }

    /// Largest nodal displacement from rest over the whole body, m.
    pub fn max_displacement_m(&self) -> f64 {
        self.state
            .x
            .iter()
            .zip(self.fem.rest())
            .map(|(x, r)| (*x - *r).length_squared())
            .fold(0.0, f64::max)
            .sqrt()
    }

    /// Kinetic energy `sum m v^2 / 2`, J.
    pub fn kinetic_energy_j(&self) -> f64 {
        self.state
            .v
            .iter()
            .zip(self.fem.lumped_mass_kg())
            .map(|(v, m)| 0.5 * m * v.length_squared())
            .sum()
    }

    /// Boundary nodes shown to viewers (indices into the body's nodes), sorted.
    pub fn surface_node_indices(&self) -> &[u32] {
        &self.setup.surface_nodes
    }

    /// Boundary triangles indexing into [`FemBody::surface_node_indices`], outward oriented.
    pub fn surface_triangles(&self) -> &[[u32; 3]] {
        &self.setup.surface_triangles
    }

    /// The FEM data.
    pub fn fem(&self) -> &FemModel {
        &self.fem
    }

    /// The time stepper.
    pub fn stepper(&self) -> &Stepper {
        &self.stepper
    }

    /// Counters of a following active region (`active_region.follow`), `None` otherwise.
    pub fn follow_stats(&self) -> Option<FollowStats> {
        self.follow.0.as_ref().map(RegionFollower::stats)
    }

    /// The threads a following region's worker prepares regions with from now on (at most
    /// [`crate::integrate::condensed::MAX_PREPARATION_THREADS`]; the regions it sends are cut
    /// for as many parts, [`RegionFollower::set_parts`]), for a host that fills the region
    /// cache without a tick pool. No effect without one.
    pub fn set_region_preparation_threads(&self, threads: usize) {
        if let Some(f) = &self.follow.0 {
            f.set_parts(threads);
        }
    }

    /// Pauses (or resumes) a following region's background builds of tiles
    /// ([`RegionFollower::set_paused`]). No effect without one.
    pub fn set_region_preparation_paused(&self, on: bool) {
        if let Some(f) = &self.follow.0 {
            f.set_paused(on);
        }
    }

    /// Centres a following region's background tile work on `point_m`, m
    /// ([`RegionFollower::focus_tiles`]). No effect without one.
    pub fn focus_region_tiles(&self, point_m: DVec3) {
        if let Some(f) = &self.follow.0 {
            f.focus_tiles(point_m);
        }
    }

    /// Makes a following region's ticks wait for each region they request (deterministic
    /// swaps, for tests and studies; a servo must not). No effect without one.
    pub fn set_blocking_region_preparation(&mut self, on: bool) {
        if let Some(f) = &mut self.follow.0 {
            f.set_blocking(on);
        }
    }

    /// The condensed solver of a scene with `[active_region]`.
    pub fn condensed(&self) -> Option<&CondensedSolver> {
        self.stepper.condensed()
    }

    /// With an active region: moves the condensed (far) nodes to the static response of the
    /// far body to the interface, which the tick leaves at their last recovered positions (one
    /// sparse solve, allocates: not for the servo tick). No-op otherwise.
    pub fn recover_far_field(&mut self) {
        if let Some(c) = self.stepper.condensed() {
            c.recover_far_field(&mut self.state.x);
        }
    }

    /// The dynamic state.
    pub fn state(&self) -> &FemState {
        &self.state
    }

    /// Mutable state, for tests and set-ups (e.g. imposing an initial deformation). Forgets
    /// the backward Euler warm start and a recorded divergence.
    pub fn state_mut(&mut self) -> &mut FemState {
        self.stepper.reset();
        self.status.diverged_at_s = None;
        &mut self.state
    }

    /// Sub-step plan.
    pub fn plan(&self) -> StepPlan {
        self.setup.plan
    }

    /// Integrator in use.
    pub fn integrator(&self) -> IntegratorKind {
        self.stepper.kind()
    }

    /// Servo tick, s.
    pub fn tick_s(&self) -> f64 {
        self.setup.tick_s
    }

    /// Probe radius, m.
    pub fn probe_radius_m(&self) -> f64 {
        self.probes[0].params.radius_m
    }

    /// Scene name.
    pub fn scene_name(&self) -> &str {
        &self.setup.scene_name
    }

    /// The output of the last successful tick.
    pub fn last_output(&self) -> TickOutput {
        self.status.last_output
    }
}

/// Writes `x[nodes[k]]` (f32, xyz interleaved) into `out` and returns the largest distance to
/// `rest[nodes[k]]` (0 without `rest`).
///
/// # Panics
/// If `out.len() != 3 * nodes.len()`.
fn write_positions(nodes: &[u32], x: &[DVec3], rest: Option<&[DVec3]>, out: &mut [f32]) -> f64 {
    assert_eq!(out.len(), 3 * nodes.len(), "surface buffer length");
    let mut max_d2: f64 = 0.0;
    for (k, &i) in nodes.iter().enumerate() {
        let p = x[i as usize];
        out[3 * k] = p.x as f32;
        out[3 * k + 1] = p.y as f32;
        out[3 * k + 2] = p.z as f32;
        if let Some(r) = rest {
            max_d2 = max_d2.max((p - r[i as usize]).length_squared());
        }
    }
    max_d2.sqrt()
}

/// One probe per tool slot of `scene` over `touchable` of a
/// body at rest `rest`, each with its tool's parameters ([`Scene::tool_probe`]), the local law
/// of its radius, and the implicit sphere for a backward Euler sub-step `implicit_dt_s`. Slots
/// with the same parameters share one set-up ([`Probe::clone_for_slot`]).
fn tool_probes(
    scene: &Scene,
    touchable: &[[u32; 3]],
    rest: &[DVec3],
    implicit_dt_s: Option<f64>,
) -> Vec<Probe> {
    let slots = scene.tools.max_tools.max(1);
    let mut probes: Vec<Probe> = Vec::with_capacity(slots);
    for slot in 0..slots {
        let params = probe_params_of(scene, slot);
        if let Some(same) = probes.iter().find(|p| p.params == params) {
            probes.push(same.clone_for_slot());
            continue;
        }
        let mut probe = Probe::new(params, touchable.to_vec(), rest);
        if params.contact == ContactModel::PatchLocal {
            probe.set_local_law(LocalLaw::for_material(&scene.material, params.radius_m));
        }
        if let Some(h) = implicit_dt_s {
            probe.use_implicit_sphere(h);
        }
        probes.push(probe);
    }
    probes
}

/// The probe's parameters of tool slot `slot` of `scene`: its contact model resolved (`auto`) and the plane-strain
/// modulus `E / (1 - nu^2)` of its material for the Hertz laws.
fn probe_params_of(scene: &Scene, slot: usize) -> ProbeParams {
    let mut probe_params = scene.tool_probe(slot);
    probe_params.contact = integrate::resolve_contact_model(probe_params.contact);
    let (e, nu) = (
        scene.material.youngs_modulus_pa(),
        scene.material.poisson_ratio(),
    );
    probe_params.hertz_modulus_pa = e / (1.0 - nu * nu);
    probe_params
}

/// The stepper of `scene`'s integrator `p` with sub-step `plan`: backward Euler with the rest
/// factor on the whole body is the condensed solver on a region holding every element.
fn stepper_of(
    fem: &FemModel,
    scene: &Scene,
    p: &IntegratorParams,
    plan: &StepPlan,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Stepper, ModelError> {
    // Backward Euler with the rest factor on the whole body is the condensed solver on a
    // region holding every element.
    let region = scene.active_region.or_else(|| {
        (p.kind == IntegratorKind::BackwardEuler
            && p.linear_solver == integrate::LinearSolver::RestCholesky)
            .then(|| ActiveRegion::whole_body(fem.rest(), p.stiffness_margin))
    });
    let mut stepper = Stepper::new_with_progress(fem, &scene.mesh, p, plan, region, progress)?;
    // The exact sphere on the whole-body rest factor: a second factor for the ticks where
    // a face enters the contact ([`CondensedSolver::add_entry_factor`]).
    if let Stepper::Condensed(c) = &mut stepper
        && c.is_whole_body()
        && integrate::resolve_contact_model(scene.probe.contact) == ContactModel::Sphere
    {
        c.add_entry_factor()?;
    }
    Ok(stepper)
}

/// The worker of a following region `c` over `fem`, its tiles in the host's region cache
/// (`options`), requests led for the scene's tick.
fn follower(
    fem: &FemModel,
    scene: &Scene,
    contact_nodes: &[u32],
    c: &CondensedSolver,
    options: &BodyOptions,
) -> Result<RegionFollower, ModelError> {
    let mut f = RegionFollower::spawn_with_cache(
        fem,
        &scene.mesh,
        contact_nodes,
        c,
        options.region_cache.as_ref(),
        options.region_cache_report.clone(),
        options.region_cache_fill_only,
    )?;
    f.set_tick_s(scene.integrator.tick_s);
    Ok(f)
}

/// A condensed model (not following) sees loads and contact on its active nodes only: the
/// touchable triangles and the loads on the load surface inside the region; refused when one
/// of the whole surface's `loads` acts outside it or no touchable triangle lies inside.
fn confine_to_region(
    c: &CondensedSolver,
    scene: &Scene,
    fem: &FemModel,
    loads: &BodyLoads,
    load_surface: &[[u32; 3]],
    mut touchable: Vec<[u32; 3]>,
) -> Result<(BodyLoads, Vec<[u32; 3]>), ModelError> {
    if loads.acts_outside(|i| c.is_active_node(i)) {
        return Err(ModelError::field(
            "active_region",
            "a scene load acts outside the active region (condensed elements are unloaded): enlarge the region or remove the load",
        ));
    }
    touchable.retain(|t| c.is_active_triangle(t));
    if touchable.is_empty() {
        return Err(ModelError::field(
            "active_region",
            "no touchable triangle lies inside the active region",
        ));
    }
    let load_surface: Vec<[u32; 3]> = load_surface
        .iter()
        .copied()
        .filter(|t| c.is_active_triangle(t))
        .collect();
    let loads = BodyLoads::new(&scene.loads, fem.rest(), fem.lumped_mass_kg(), load_surface);
    Ok((loads, touchable))
}

/// The boundary's nodes (sorted) and its triangles over their local numbers, for `n` nodes.
fn surface_map(boundary: &[[u32; 3]], n: usize) -> (Vec<u32>, Vec<[u32; 3]>) {
    let mut surface_nodes: Vec<u32> = boundary.iter().flatten().copied().collect();
    surface_nodes.sort_unstable();
    surface_nodes.dedup();
    let mut local = vec![u32::MAX; n];
    for (k, &i) in surface_nodes.iter().enumerate() {
        local[i as usize] = k as u32;
    }
    let surface_triangles = boundary
        .iter()
        .map(|t| t.map(|i| local[i as usize]))
        .collect();
    (surface_nodes, surface_triangles)
}

/// The following region's coarse companion, built from the scene's `fallback` (only when the
/// region follows the probe) with the scene's tool slots (it ticks every slot).
fn companion(
    scene: &Scene,
    follows: bool,
    progress: &mut dyn FnMut(&str, f64),
) -> Result<Option<Box<Fallback>>, ModelError> {
    Ok(match (&scene.fallback, follows) {
        (Some(coarse), true) => {
            progress("coarse companion", 1.0);
            let coarse = Scene {
                tools: scene.tools.clone(),
                ..(**coarse).clone()
            };
            let sim = FemBody::new(&coarse).map_err(|e| {
                ModelError::field(
                    "active_region.fallback_target_tets",
                    format!("the coarse companion: {e}"),
                )
            })?;
            Some(Box::new(Fallback::new(sim)))
        }
        _ => None,
    })
}

impl SoftBody for FemBody {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        FemBody::tick(self, input)
    }

    /// The scene's `probe.max_tools`.
    fn max_tools(&self) -> usize {
        self.probes.len()
    }

    /// The index of `tool_id` among the scene's `[[probe.tool]]`.
    fn tool_slot(&self, tool_id: &str) -> Option<usize> {
        self.setup.tool_ids.iter().position(|id| id == tool_id)
    }

    fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        FemBody::tick_tools(self, inputs, outputs)
    }

    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        FemBody::add_point_load(self, point_m, force_n, duration_s)
    }

    /// The boundary of the mesh; it never changes (version 0).
    fn surface_topology(&self) -> SurfaceTopology<'_> {
        SurfaceTopology {
            version: 0,
            vertex_count: self.setup.surface_nodes.len(),
            triangles: &self.setup.surface_triangles,
        }
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        SurfaceCapacity {
            vertices: self.setup.surface_nodes.len(),
            triangles: self.setup.surface_triangles.len(),
        }
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        FemBody::write_surface_positions(self, out)
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        write_positions(&self.setup.surface_nodes, self.fem.rest(), None, out);
    }

    fn stats(&self) -> BodyStats {
        BodyStats {
            nodes: self.fem.node_count(),
            elements: self.fem.element_count(),
            active_elements: self.stepper.force_model(&self.fem).element_count(),
            particles: 0,
            active_particles: 0,
            active_point_loads: self.loads.active_point_loads(),
            surface_vertices: self.setup.surface_nodes.len(),
            topology_version: 0,
            sim_time_s: self.state.time_s,
            max_displacement_m: self.max_displacement_m(),
            region_swaps: self.follow_stats().map_or(0, |f| f.swaps),
            region_preparation_s: self.follow_stats().map_or(0.0, |f| f.last_prepare_s),
            region_tiles: self.follow_stats().map_or(0, |f| f.tiles),
            region_tiles_ready: self
                .follow_stats()
                .map_or(0, |f| f.tiles_ready().min(f.tiles)),
            region_tiles_loaded: self.follow_stats().map_or(0, |f| f.tiles_loaded),
            region_tiles_refused: self.follow_stats().map_or(0, |f| f.tiles_refused),
            region_tile_memory_bytes: self.follow_stats().map_or(0, |f| f.tile_cache_bytes),
            region_tiles_dropped: self.follow_stats().map_or(0, |f| f.tiles_dropped),
            region_tiles_reloaded: self.follow_stats().map_or(0, |f| f.tiles_reloaded),
            region_tile_misses: self.follow_stats().map_or(0, |f| f.tile_misses),
            region_unmapped_swaps: self.follow_stats().map_or(0, |f| f.unmapped_swaps),
            companion_ticks: self
                .fallback_stats()
                .map_or(0, |s| s.contact_ticks_answered),
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "fem",
            scene: self.setup.scene_name.clone(),
            tick_s: self.setup.tick_s,
            substeps: self.setup.plan.substeps,
            critical_dt_s: self.setup.plan.critical_dt_s,
            probe_radius_m: self.probes[0].params.radius_m,
            point_loads: self.point_load_zone(),
        }
    }

    /// 2 with a coarse companion (it ticks beside the region), else 1.
    fn wants_threads(&self) -> usize {
        if self.fallback.is_some() { 2 } else { 1 }
    }

    /// 1 while a following region builds its tiles
    /// ([`crate::integrate::condensed::TileMode::Background`]: a worker busy
    /// from the session's start until every tile is built or read), and from the first tile
    /// dropped to keep the cache under its memory limit on (the worker then reads tiles back
    /// as the probe moves), else 0 (a region worker that prepares on request only idles
    /// between requests).
    fn background_threads(&self) -> usize {
        self.follow_stats().map_or(0, |f| {
            usize::from(f.tiles_ready() < f.tiles || f.tiles_dropped > 0)
        })
    }

    /// Keeps `pool` for the element forces in parts (the kernels' per-part arrays are sized
    /// here), a condensed region's far products in two parts
    /// ([`CondensedSolver::set_parts`], now and on every region prepared later) and the
    /// coarse companion's tick beside the region's solve ([`FemBody::tick`]): the worker is
    /// free for the forces' and the far products' parts first. The companion itself gets
    /// none.
    fn set_tick_pool(&mut self, pool: Arc<TickPool>) {
        self.scratch
            .kernel
            .ensure(self.fem.node_count(), pool.threads());
        if let Some(solver) = self.stepper.condensed_mut() {
            solver.set_parts(pool.threads());
        }
        if let Some(f) = &self.follow.0 {
            f.set_parts(pool.threads());
        }
        self.pool = pool;
    }
}

/// Every probe's contact at positions `x`: slot `k` follows `inputs[k]`'s device, or is
/// released without one (or past `inputs`). Reads nothing else of the body, so it runs beside
/// the force evaluation ([`FemBody::tick_tools`]).
fn update_probes(probes: &mut [Probe], inputs: &[TickInput], x: &[DVec3]) {
    for (k, probe) in probes.iter_mut().enumerate() {
        let input = inputs.get(k).copied().unwrap_or_default();
        match input.device_position_m {
            Some(p) => {
                probe.update(x, p, input.device_velocity_m_per_s);
            }
            None => probe.release(),
        }
    }
}
