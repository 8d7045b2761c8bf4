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
//! **Two options not in the seed** ([`ScaledMotion`](super::ScaledMotion), [`CoreStep`](super::CoreStep)): with `scaled_motion =
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
//! the core, so their inertia is the core's), times the core's mass scale ([`CoreMassScale`](super::CoreMassScale):
//! `mass_scale` by default, a uniform slow-down; 1, the body's real inertia, the sub-steps
//! then set by the core's critical step; `auto`, the smallest scale that adds no sub-step to
//! the particles' count, so the body is as close to its real inertia as the particle step
//! allows).
//!
//! **Several tools** (issue 50, [`HybridBody::set_tools`]). Each tool slot has its own proxy
//! on the same particles, all adding their penalties in the same sub-steps; the active regions
//! are the union of those under each device, and no tool's activation evicts the regions under
//! another. A tool that leaves while another stays is withdrawn by a ghost device over
//! [`RELEASE_FADE_TICKS`] ticks and its regions stay until no tool is connected, so the other
//! tool's force stays continuous (`docs/decisions.md`, "Several tools in one implicit step").
//!
//! **Surface.** Each outer vertex shows the core's interpolation at the vertex plus the
//! deviation of its nearest particle from the core's interpolation at that particle (zero for
//! inactive particles), so the surface is continuous at activation and release.
//!
//! Neighbours: data from [`mod@super::prepare`]; forces from [`crate::meshfree::block`] and
//! [`crate::element::FemModel`].

use std::sync::Arc;

use glam::DVec3;

use super::implicit::ImplicitCore;
use super::layer::LayerElements;
use super::prepare::{HybridModel, Tie, TieNodes};
use super::proxy::{ParticleProxy, ProxyContact};
use crate::ModelError;
use crate::body::{
    BodyInfo, BodyStats, MAX_TOOLS, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput,
    TickOutput, check_tool_inputs, validate_point_load,
};
use crate::contact::probe::ProbeParams;
use crate::element::FemModel;
use crate::meshfree::TermBlock;
use crate::pool::TickPool;
use step::NO_CONTACT;

mod diagnostics;
mod regions;
mod setup;
mod step;

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

/// The hybrid body (module documentation): the preprocessed model and the core's elements,
/// the parameters fixed at build (`HybridSetup`), what a tick changes (`HybridState`), the
/// active regions and particles (`RegionSet`), the caches rebuilt when they change
/// (`HybridPipeline`), per-step work arrays and counters, as separate parts.
#[derive(Debug)]
pub struct HybridBody {
    model: Box<HybridModel>,
    fem: FemModel,
    setup: HybridSetup,
    state: HybridState,
    regions: RegionSet,
    pipeline: HybridPipeline,
    scratch: HybridScratch,
    stats: HybridStats,
}

/// The parameters fixed at build ([`HybridBody::override_substeps`] is the one writer).
#[derive(Debug)]
struct HybridSetup {
    name: String,
    probe: ProbeParams,
    /// The scene's named tools by slot ([`SoftBody::tool_slot`]).
    tool_ids: Vec<String>,
    tick_s: f64,
    substeps: u32,
    core_substeps: u32,
    dt_s: f64,
    critical_dt_s: f64,
    particle_mass_kg: f64,
    core_mass_scale: f64,
    /// `scaled_motion = "deviation"` ([`ScaledMotion::Deviation`](super::ScaledMotion)): the
    /// active particles' state is their deviation from the core's interpolation (`xd`, and
    /// `vp` its rate), and their forces also drive the core nodes.
    deviation: bool,
}

/// Ticks over which a leaving tool's force on the body fades while another tool stays
/// ([`HybridBody::tick_tools`]).
pub const RELEASE_FADE_TICKS: u32 = 20;

/// A tool slot's device of the last tick, where it last touched nothing, and after it left
/// while touching, its ghost's path (from, to, m) with the ticks it still presses.
#[derive(Debug, Clone, Copy, Default)]
struct ReleaseFade {
    last_device_m: Option<DVec3>,
    clear_m: Option<DVec3>,
    ghost: Option<(DVec3, DVec3, u32)>,
}

/// A tool slot past the first: its proxy and force limit (N).
#[derive(Debug)]
struct ExtraTool {
    proxy: ParticleProxy,
    max_force_n: f64,
}

/// What a tick changes.
#[derive(Debug)]
struct HybridState {
    xc: Vec<DVec3>,
    vc: Vec<DVec3>,
    xp: Vec<DVec3>,
    vp: Vec<DVec3>,
    /// Deviations of the active particles from the core's interpolation, m (deviation mode).
    xd: Vec<DVec3>,
    /// Deviation mode: the active particles' `xp` are `interpolate(xc) + xd` of the current
    /// `xc` and `xd` (set by the particle step, which writes them; cleared by anything else
    /// that writes `xc`, `xd` or `xp`), so the next force evaluation need not interpolate
    /// them again (issue 48 section 3: they were interpolated twice per sub-step).
    xp_fresh: bool,
    /// The probe: the proxy sphere on the active particles and the virtual coupling (tool
    /// slot 0).
    proxy: ParticleProxy,
    /// Tool slots 1.. (issue 50, [`HybridBody::set_tools`]).
    tools: Vec<ExtraTool>,
    /// Per tool slot: the release fade ([`RELEASE_FADE_TICKS`]).
    fades: [ReleaseFade; MAX_TOOLS],
    /// Per tool slot: where its tool left while another stayed (m; `release_far` keeps the
    /// folds there), until no tool is connected.
    departed: [Option<DVec3>; MAX_TOOLS],
    /// Points whose regions an activation may not evict (m; the other tools during one tool's
    /// activation).
    evict_guard: [Option<DVec3>; MAX_TOOLS],
    loads: [PointLoad; MAX_POINT_LOADS],
    load_count: usize,
    time_s: f64,
    diverged_at_s: Option<f64>,
    last_force_n: DVec3,
}

/// The active regions and particles (contact-local activation, `regions.rs`).
#[derive(Debug)]
struct RegionSet {
    active: Vec<bool>,
    in_block: Vec<bool>,
    active_list: Vec<u32>,
    tied_list: Vec<u32>,
    region_active: Vec<bool>,
    active_regions: Vec<u32>,
    /// Outer-vertex adjacency (CSR over `outer_triangles`), for the implicit core's regions
    /// (built once; empty with an explicit core).
    vertex_adj_start: Vec<u32>,
    vertex_adj: Vec<u32>,
    /// The active set changed: the terms are refilled before the next force evaluation.
    changed: bool,
    /// [`HybridBody::hold_regions`]: no release.
    hold: bool,
    /// The activation scan's bound ([`HybridBody::activate_near`]).
    vertex_bounds: regions::VertexBounds,
}

/// Caches rebuilt when the active set changes.
#[derive(Debug)]
struct HybridPipeline {
    block: TermBlock,
    /// `inactive_layer = "elements"`: the elements' shares of the wall's energy.
    layer: Option<LayerElements>,
    /// `core_step = "implicit"`: the core's factor and its margin.
    implicit: Option<(ImplicitCore, f64)>,
    /// The core nodes and tie weights of each particle of `tied_list`, copied when the terms
    /// are refilled: the per-sub-step gather and scatter read them in order instead of
    /// looking up the particle's tie and its tetrahedron.
    tied_ties: Vec<TieNodes>,
    /// The core nodes and tie weights of each particle of `active_list`, copied when the terms
    /// are refilled (deviation mode).
    active_ties: Vec<TieNodes>,
    /// The positions `k` in `active_list` (and `active_ties`) by ascending particle index
    /// (deviation mode): the particle step walks the particle arrays forwards (issue 48; the
    /// list itself keeps its order, which the proxy's and the ties' sums follow).
    active_order: Vec<u32>,
    /// The session's tick pool ([`SoftBody::set_tick_pool`]): the terms' stencil loop runs in
    /// its parts (issue 48). `None`: one part, the one-core tick.
    pool: Option<Arc<TickPool>>,
}

/// Work arrays, sized at build and overwritten.
#[derive(Debug)]
struct HybridScratch {
    fc: Vec<DVec3>,
    fp: Vec<DVec3>,
    /// Forces of the tied particles and point loads on the core nodes, held over a particle
    /// step, N.
    fcoup: Vec<DVec3>,
    /// The FEM's elastic forces at the core's positions, computed on a pool worker beside the
    /// proxy and the ties (two threads, implicit core); `ffem_ready` until
    /// [`HybridBody::update`] has used them.
    ffem: Vec<DVec3>,
    /// The layer's replaced shares taken out of zero (`inactive_layer = "elements"`), computed
    /// on the caller after the proxy and the ties while the worker computes `ffem`; zero
    /// without a layer.
    flayer: Vec<DVec3>,
    ffem_ready: bool,
    /// The regions whose condensed stiffness the implicit core's matrix holds: the active ones
    /// and their neighbours (`region_mark` flags them).
    matrix_regions: Vec<u32>,
    region_mark: Vec<bool>,
    /// Regions to activate this tick with their squared distance to the probe, m^2 (one slot
    /// per outer vertex).
    candidates: Vec<(f64, u32)>,
}

/// Counters since set-up.
#[derive(Debug, Default)]
struct HybridStats {
    /// Refactorings of the implicit core's matrix.
    implicit_refactors: u64,
    refused_activations: u64,
    released_for_room: u64,
}

impl HybridBody {
    /// The preprocessed model.
    pub fn model(&self) -> &HybridModel {
        &self.model
    }

    /// Particle sub-steps per tick, the particle step (s) and core steps per particle step.
    pub fn substeps(&self) -> (u32, f64, u32) {
        (
            self.setup.substeps,
            self.setup.dt_s,
            self.setup.core_substeps,
        )
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
        self.setup.substeps = substeps;
        self.setup.dt_s = self.setup.tick_s / substeps as f64;
        self.rebuild_implicit()
    }

    /// The critical step the sub-steps come from, s: the smaller of the particles' (Gershgorin
    /// bound, mass-scaled, with the probe penalty) and the core's.
    pub fn critical_step_bound_s(&self) -> f64 {
        self.setup.critical_dt_s
    }

    /// Keeps every active region active (no release) while `hold` is true: for tests and
    /// studies of a fixed active set.
    pub fn hold_regions(&mut self, hold: bool) {
        self.regions.hold = hold;
    }

    /// Activations refused because `max_active_particles` (or the term capacity) was reached.
    pub fn refused_activations(&self) -> u64 {
        self.stats.refused_activations
    }

    /// Regions released unsettled to make room under `max_active_particles` for regions
    /// nearer the probe ([`Self::activate_near`]).
    pub fn released_for_room(&self) -> u64 {
        self.stats.released_for_room
    }

    /// Proxy solves that stopped at their iteration cap since set-up
    /// ([`ParticleProxy::unconverged_solves`]).
    pub fn unconverged_proxy_solves(&self) -> u64 {
        self.state.proxy.unconverged_solves()
    }

    /// Refactorings of the implicit core's matrix since set-up (when an active region was not
    /// in it).
    pub fn implicit_refactors(&self) -> u64 {
        self.stats.implicit_refactors
    }

    /// Heap bytes of the implicit core's matrix and factor (0 with an explicit core).
    pub fn implicit_core_memory_bytes(&self) -> usize {
        self.pipeline
            .implicit
            .as_ref()
            .map_or(0, |(c, _)| c.memory_bytes())
    }

    /// Energy terms and tied particles of the current active set (the per-sub-step work).
    pub fn work_counts(&self) -> (usize, usize) {
        (self.pipeline.block.len(), self.regions.tied_list.len())
    }

    /// The term block's stencil layout in use (grid cells, groups of four owners), `None`
    /// when its general loop runs ([`TermBlock::stencil_layout`]).
    pub fn stencil_layout(&self) -> Option<(usize, usize)> {
        self.pipeline.block.stencil_layout()
    }

    /// Chooses the term block's force loop ([`TermBlock::set_stencil_loop`]), for benchmarks.
    pub fn set_stencil_loop(&mut self, on: bool) {
        self.pipeline.block.set_stencil_loop(on);
    }

    /// Currently active particles.
    pub fn active_particles(&self) -> &[u32] {
        &self.regions.active_list
    }

    /// Core positions and velocities (m, m/s), for tests and studies.
    pub fn core_state_mut(&mut self) -> (&mut [DVec3], &mut [DVec3]) {
        self.state.xp_fresh = false;
        (&mut self.state.xc, &mut self.state.vc)
    }

    /// Particle positions and velocities (m, m/s, indexed by particle; only active particles'
    /// entries are state, the others are overwritten from the core), for tests and studies.
    /// With `scaled_motion = "deviation"` the velocities are the deviations' rates and the
    /// positions are recomputed from the core and the deviations at every sub-step.
    pub fn particle_state_mut(&mut self) -> (&mut [DVec3], &mut [DVec3]) {
        self.state.xp_fresh = false;
        (&mut self.state.xp, &mut self.state.vp)
    }

    /// Lumped masses of the core nodes, kg (the core's and the particle layer's, times
    /// `core_mass_scale`). Length: core nodes.
    pub fn core_lumped_mass_kg(&self) -> &[f64] {
        self.fem.lumped_mass_kg()
    }

    /// The core's mass multiplier in use ([`CoreMassScale`](super::CoreMassScale): the value set, `mass_scale`, or
    /// the one chosen for `auto`).
    pub fn core_mass_scale(&self) -> f64 {
        self.setup.core_mass_scale
    }

    /// Mass of one particle, kg.
    pub fn particle_mass_kg(&self) -> f64 {
        self.setup.particle_mass_kg
    }
}

impl HybridBody {
    /// Tools leaving while another stays (issue 50): a slot whose device left while its proxy
    /// touched is withdrawn by a ghost device over [`RELEASE_FADE_TICKS`] ticks, linearly from
    /// its last point back to where it last touched nothing, so its force on the body fades
    /// instead of vanishing in one tick (which stepped the other tool's force by 6.9 % on
    /// `lv-hybrid`, `tests/tools.rs`). `devices[k]` becomes the ghost. Never with one slot, or
    /// with no other device connected (the one-tool tick is unchanged).
    fn fade_released(&mut self, devices: &mut [Option<DVec3>]) {
        let connected = devices.iter().filter(|d| d.is_some()).count();
        if connected == 0 {
            self.state.departed = [None; MAX_TOOLS];
        }
        for (k, device) in devices.iter_mut().enumerate() {
            let touching = match k {
                0 => self.state.proxy.state().1,
                _ => self.state.tools[k - 1].proxy.state().1,
            };
            let fade = &mut self.state.fades[k];
            if let Some(d) = *device {
                if !touching {
                    fade.clear_m = Some(d);
                }
                fade.last_device_m = Some(d);
                fade.ghost = None;
                self.state.departed[k] = None;
                continue;
            }
            if let (Some(last), true, true) = (fade.last_device_m, touching, connected > 0) {
                let clear = fade.clear_m.unwrap_or(last);
                fade.ghost = Some((last, clear, RELEASE_FADE_TICKS));
                self.state.departed[k] = Some(last);
            }
            fade.last_device_m = None;
            fade.clear_m = None;
            if let Some((last, clear, left)) = fade.ghost {
                let s = f64::from(left) / f64::from(RELEASE_FADE_TICKS + 1);
                *device = Some(clear + (last - clear) * s);
                fade.ghost = (left > 1).then_some((last, clear, left - 1));
            }
        }
    }

    /// Point loads age by the tick; expired ones leave the table.
    fn age_point_loads(&mut self) {
        let mut k = 0;
        while k < self.state.load_count {
            self.state.loads[k].remaining_s -= self.setup.tick_s;
            if self.state.loads[k].remaining_s <= 0.0 {
                self.state.loads[k] = self.state.loads[self.state.load_count - 1];
                self.state.load_count -= 1;
            } else {
                k += 1;
            }
        }
    }
}

/// The tick output of a proxy's `contact` at `time_s` (s), its force clamped to
/// `max_force_n` (N; the stiffness scaled with it).
fn clamped_output(contact: &ProxyContact, max_force_n: f64, time_s: f64) -> TickOutput {
    let (mut force, mut stiffness) = (contact.force_on_device_n, contact.stiffness_n_per_m);
    let mag = force.length();
    if mag > max_force_n {
        let s = max_force_n / mag;
        force *= s;
        stiffness.iter_mut().for_each(|v| *v *= s);
    }
    TickOutput {
        force_on_device_n: force,
        in_contact: contact.in_contact,
        proxy_position_m: contact.proxy_m,
        contact_stiffness_n_per_m: stiffness,
        sim_time_s: time_s,
    }
}

impl SoftBody for HybridBody {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        let mut out = [TickOutput::default()];
        self.tick_tools(std::slice::from_ref(input), &mut out)?;
        Ok(out[0])
    }

    /// The scene's `probe.max_tools`.
    fn max_tools(&self) -> usize {
        1 + self.state.tools.len()
    }

    /// The index of `tool_id` among the scene's `[[probe.tool]]`.
    fn tool_slot(&self, tool_id: &str) -> Option<usize> {
        self.setup.tool_ids.iter().position(|id| id == tool_id)
    }

    /// Every slot's proxy on the same particles: the active regions are the union of those
    /// under each device; each proxy adds its penalty forces to the particles in the same
    /// sub-steps. One slot is [`SoftBody::tick`] bit for bit.
    fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        check_tool_inputs(inputs, outputs.len(), self.max_tools())?;
        if let Some(time_s) = self.state.diverged_at_s {
            return Err(ModelError::Diverged { time_s });
        }
        // The workers stay awake through the tick (no wake-up on the tick's jobs).
        let pool = self.pipeline.pool.clone();
        let _hot = pool.as_deref().map(TickPool::hot);
        let mut devices = [None; MAX_TOOLS];
        for (d, input) in devices.iter_mut().zip(inputs) {
            *d = input.device_position_m;
        }
        let connected = devices;
        self.fade_released(&mut devices[..inputs.len()]);
        let devices = &devices[..inputs.len()];
        // A slot past the first without a device (or a fading one) forgets its contact.
        for (k, tool) in self.state.tools.iter_mut().enumerate() {
            if devices.get(k + 1).copied().flatten().is_none() {
                tool.proxy.reset();
            }
        }
        // 1. Release, then activation (which may release unsettled far regions for room).
        if !self.regions.hold {
            self.release_far(devices);
        }
        // Ghosts activate nothing (a region activated under a leaving tool moved the other's
        // force by 15 % in one tick).
        for (k, c) in connected[..inputs.len()].iter().enumerate() {
            let Some(c) = *c else { continue };
            // Each tool's activation evicts none of the regions under the others.
            for (j, g) in self.state.evict_guard.iter_mut().enumerate() {
                *g = match j {
                    _ if j == k || j >= devices.len() => None,
                    _ => devices[j].or(self.state.departed[j]),
                };
            }
            self.activate_near(c, self.model.params.activation_radius_m);
        }
        self.state.evict_guard = [None; MAX_TOOLS];
        // 2. Sub-steps.
        let mut contacts = [NO_CONTACT; MAX_TOOLS];
        for (c, d) in contacts.iter_mut().zip(devices) {
            c.proxy_m = d.unwrap_or(DVec3::ZERO);
        }
        let contacts = &mut contacts[..devices.len()];
        for _ in 0..self.setup.substeps {
            self.particle_forces_tools(devices, contacts);
            let v2 = self.update(self.setup.dt_s);
            if !(v2 <= MAX_SPEED_M_PER_S * MAX_SPEED_M_PER_S) {
                self.state.diverged_at_s = Some(self.state.time_s);
                return Err(ModelError::Diverged {
                    time_s: self.state.time_s,
                });
            }
        }
        // 3. The device force at the end of the tick: the proxy solved again against the
        // particles the sub-steps moved. (The force of the last sub-step's start lags the body
        // by a tick: through the coupling that reads `k_c v h` too high while the device moves,
        // 3 mN at 10 mm/s, and drops by as much in the tick it stops.)
        for (k, (device, contact)) in devices.iter().zip(contacts.iter_mut()).enumerate() {
            let Some(device) = *device else { continue };
            let proxy = match k {
                0 => &mut self.state.proxy,
                _ => &mut self.state.tools[k - 1].proxy,
            };
            *contact = proxy.update(device, &self.state.xp, &self.regions.active_list, None);
        }
        self.state.time_s += self.setup.tick_s;
        self.age_point_loads();
        // 4. Device forces, clamped.
        for (k, (contact, out)) in contacts.iter().zip(outputs.iter_mut()).enumerate() {
            let max_force_n = match k {
                0 => self.setup.probe.max_force_n,
                _ => self.state.tools[k - 1].max_force_n,
            };
            *out = match connected[k] {
                Some(_) => clamped_output(contact, max_force_n, self.state.time_s),
                // A fading slot's device is gone: nobody feels its force.
                None => clamped_output(&NO_CONTACT, max_force_n, self.state.time_s),
            };
        }
        self.state.last_force_n = outputs[0].force_on_device_n;
        Ok(())
    }

    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        validate_point_load(point_m, force_n, duration_s)?;
        if self.state.load_count == MAX_POINT_LOADS {
            return Err(ModelError::LoadTableFull(MAX_POINT_LOADS));
        }
        let m = &self.model;
        let mut best = (f64::INFINITY, 0usize);
        for v in 0..m.outer_rest_m.len() {
            let x = m.interpolate(&m.vertex_tie[v], &self.state.xc);
            let d = (x - point_m).length_squared();
            if d < best.0 {
                best = (d, v);
            }
        }
        self.state.loads[self.state.load_count] = PointLoad {
            tie: m.vertex_tie[best.1],
            force_n,
            remaining_s: duration_s,
        };
        self.state.load_count += 1;
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
            let mut x = m.interpolate(&m.vertex_tie[v], &self.state.xc);
            let p = m.vertex_particle[v];
            if p != u32::MAX && self.regions.active[p as usize] {
                let p = p as usize;
                x += self.state.xp[p] - m.interpolate(&m.particle_tie[p], &self.state.xc);
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
            .state
            .xc
            .iter()
            .zip(&self.model.core_mesh.nodes)
            .fold(0.0f64, |a, (x, r)| a.max((*x - *r).length()));
        BodyStats {
            nodes: self.state.xc.len(),
            elements: self.model.core_mesh.tets.len(),
            active_elements: self.model.core_mesh.tets.len(),
            particles: self.model.layer_count,
            active_particles: self.regions.active_list.len(),
            active_point_loads: self.state.load_count,
            surface_vertices: self.model.outer_rest_m.len(),
            topology_version: 1,
            sim_time_s: self.state.time_s,
            max_displacement_m,
            ..BodyStats::default()
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "hybrid",
            scene: self.setup.name.clone(),
            tick_s: self.setup.tick_s,
            substeps: self.setup.substeps,
            critical_dt_s: self.setup.critical_dt_s,
            probe_radius_m: self.setup.probe.radius_m,
            point_loads: crate::body::PointLoadZone::Anywhere,
        }
    }

    /// Two: the terms' stencil loop, the largest share of the tick (docs/benchmarks.md), runs
    /// in two parts.
    fn wants_threads(&self) -> usize {
        2
    }

    /// Cuts the terms' stencil loop into `pool.threads()` parts, and the implicit core's
    /// sweep in two where its elimination tree forks in balanced halves.
    fn set_tick_pool(&mut self, pool: Arc<TickPool>) {
        self.pipeline.block.set_parts(pool.threads());
        if let Some((core, _)) = &mut self.pipeline.implicit {
            core.set_parts(pool.threads());
        }
        self.pipeline.pool = Some(pool);
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
