//! [`MassSpringBody`]: the mass-spring surface with run-time haptic subdivision, behind the
//! [`SoftBody`] interface the servo drives.
//!
//! A tick is `substeps` steps of symplectic Euler on eq. 1-2 with the damping `K_d` implicit
//! (`v' = (m v + dt f) / (m + dt K_d)`, `x' = x + dt v'`), the probe's virtual coupling
//! completed implicitly ([`Probe::finish_implicit`], the same probe as the FEM's), and the
//! subdivided area's spring constants looked up in the calibrated table at the current
//! displacement of its contact node once per step (section 3.2.4). After the steps, the
//! contact node (the coarse node nearest the contact point) becomes a *centre*; an area is
//! kept subdivided while its centre was touched within `coarsen_delay_s`, and until it has
//! come back to rest (within [`QUIET_DISPLACEMENT_OVER_L`]). When the set of
//! centres changes, an **event** recomputes the refinement's labels ([`super::refine`]), edits
//! the mixed-level mesh where they changed (`super::mixed`) and carries the state over:
//!
//! - original nodes keep position and velocity (with [`VertexRule::Loop`](super::VertexRule::Loop) they keep their
//!   displacement from their moved rest position); a node whose mass changes keeps its
//!   velocity when it gets lighter and its momentum when it gets heavier, so no node gains
//!   kinetic energy;
//! - a new type-2 node takes Loop's edge rule for its rest position and the mean displacement
//!   and velocity of its edge's end points (the deformed surface under the probe stays where
//!   it was);
//! - masses follow eq. 3 (`m' = m N / N'` over the subdivided area), damping `K_d m' / m`;
//! - if the event still raised the total energy (the subdivided area can store more elastic
//!   energy in the same shape), the velocities of the nodes it touched are scaled down by the
//!   excess; what kinetic energy cannot cover is counted in [`EventStats::injected_energy_j`];
//! - the device force is rendered blended from the force at the event to the simulated one
//!   over [`EVENT_BLEND_TICKS`]: the carried state is not the subdivided network's equilibrium
//!   under a pressed probe, and its first sub-steps kick the surface under the probe (a
//!   rendering filter over 30 ms; the simulated state is not changed).
//!
//! Everything an event touches is sized at construction for the whole surface subdivided, so
//! neither a tick nor an event allocates, locks or does I/O. Events run on the servo thread
//! (preparing them on another thread would need a hand-off the servo does not have): an event
//! visits only the subdivided areas before and after it and the coarse triangles around them
//! (labels, mesh edits, the energy balance over that region, the contact triangle found again
//! by a local walk), so it costs O(areas), independent of the surface size;
//! `docs/benchmarks.md` has the numbers. The
//! sub-step is fixed at construction from a Gershgorin bound that covers every configuration
//! the events can produce (lightest masses `m/4`, stiffest table entry, most springs per node),
//! so an event never makes the integration unstable.
//!
//! **Several tools** (issue 50; [`MassSpringBody::tick_tools`], file `tools`). The body keeps
//! one [`Probe`] per tool slot (`probe.max_tools`, each with its named tool's radius and force
//! limit) on the same contact surface. Each sub-step every connected slot's probe updates and
//! adds its explicit reaction; the couplings of the tools in contact are then completed
//! together (`finish_couplings`: Woodbury over their rank-one terms, exact
//! where patches share nodes, so two tools on one spot count the surface once), and each slot
//! gets its own force. After the steps every tool's contact node becomes a centre, so the
//! surface is subdivided under each tool. The organ table's contact factor is read per tool,
//! and each node's springs take the factor of the tool in contact nearest it. A tool that
//! leaves while another touches is withdrawn over [`WITHDRAW_S`] so the other's force
//! stays continuous. Slot 0 alone is the one-tool tick bit for bit.

use glam::DVec3;

use super::MassSpringParams;
use super::calibration::CalibrationTable;
use super::mixed::MixedMesh;
use super::network::{Spring, critical_time_step_s, gershgorin_bound_per_s2};
use super::organ::OrganTable;
use super::refine::{NO_OWNER, Refinement};
use super::surface::SpringSurface;
use crate::ModelError;
use crate::body::{
    BodyInfo, BodyStats, MAX_TOOLS, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput,
    TickOutput, check_tool_inputs,
};
use crate::contact::Probe;
use crate::integrate::{IntegratorParams, StepPlan, plan_steps};
use crate::loads::BodyLoads;

mod centres;
mod contact;
mod event;
mod setup;
mod tools;

pub use tools::WITHDRAW_S;

use tools::ToolContact;

/// Most centres (subdivided areas) at a time: every tool's contact node (at most
/// [`MAX_TOOLS`]) and former contact nodes still within their coarsening delay. A new centre
/// beyond it replaces the one touched longest ago; being above `MAX_TOOLS`, that one is never
/// a centre a tool touches in the same tick (each tool keeps its area), and with every slot in
/// use `MAX_CENTRES - MAX_TOOLS` = 8 former contact nodes stay subdivided, as many as the one
/// tool had before several (7 delayed plus its own). Owners are `u8` (below `NO_OWNER`).
pub const MAX_CENTRES: usize = MAX_TOOLS + 8;

/// An area is coarsened only once every node of it is back within this fraction of the
/// element size L of its rest position: coarsening restores the coarse constants, stiffer than
/// the calibrated ones, so a displaced area would gain elastic energy (at most
/// `N' K_h (1e-3 L)^2 / 2` this way, 1e-8 J on the hemisphere).
pub const QUIET_DISPLACEMENT_OVER_L: f64 = 1e-3;

/// A nodal speed above this (m/s) is treated as divergence (as for the FEM).
pub const DIVERGENCE_SPEED_M_PER_S: f64 = 100.0;

/// A subdivided area's contact node and when it was last touched.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Centre {
    node: u32,
    last_contact_s: f64,
}

/// Counters of the subdivision events of a body.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EventStats {
    /// Events (changes of the set of subdivided areas).
    pub events: u64,
    /// Events that added a subdivided area.
    pub subdivisions: u64,
    /// Events that removed one.
    pub coarsenings: u64,
    /// Kinetic energy removed to keep events from raising the total energy, J.
    pub drained_energy_j: f64,
    /// Energy events added that kinetic energy could not cover, J (see the module
    /// documentation).
    pub injected_energy_j: f64,
    /// The largest single-event excess that was injected, J.
    pub max_injected_energy_j: f64,
}

/// The mass-spring body (module documentation): what the build fixes (`MassSpringModel`),
/// the parameters (`MassSpringSetup`), what a tick changes (`MassSpringState`), the
/// per-tick and per-event work arrays and the event counters, as separate parts.
#[derive(Debug, Clone)]
pub struct MassSpringBody {
    model: MassSpringModel,
    setup: MassSpringSetup,
    state: MassSpringState,
    scratch: MassSpringScratch,
    event: EventScratch,
    stats: EventStats,
}

/// What the build fixes and no tick changes.
#[derive(Debug, Clone)]
struct MassSpringModel {
    /// The coarse surface.
    surface: SpringSurface,
    /// The calibrated lookup table of the subdivided areas (section 3.2.4), if subdividing
    /// with calibrated springs.
    table: Option<CalibrationTable>,
    /// The organ table ([`super::organ`]), if any.
    organ: Option<OrganTable>,
    /// Loop rest positions per coarse node (type-1; a type-2 node's, Loop's edge rule, is its
    /// slot's entry of the rest positions).
    loop_vertex_rest: Vec<DVec3>,
    /// Where the probe meets each slot at rest ([`super::contact_rest`]); at run time the probe
    /// sees `cx = x + contact_rest - rest`.
    contact_rest: Vec<DVec3>,
    /// Per coarse edge, the height of the organ's surface over the chord's midpoint, m: the
    /// circular arc of [`super::contact_rest::arc_midpoint`] (positive on a convex surface).
    edge_arc_m: Vec<f64>,
    /// Per slot: clamped (never moves).
    fixed: Vec<bool>,
    scene_name: String,
    /// The scene's named tools by slot ([`SoftBody::tool_slot`]).
    tool_ids: Vec<String>,
}

/// The parameters: the scene's and what the build derived from them.
#[derive(Debug, Clone)]
struct MassSpringSetup {
    params: MassSpringParams,
    integrator: IntegratorParams,
    /// The sub-step plan, from the worst-case Gershgorin bound (times the organ table's
    /// largest factor).
    plan: StepPlan,
    coarse_critical_dt_s: f64,
    /// The worst-case Gershgorin bound with constant springs (1/s^2) and the integrator
    /// settings: the plan is recomputed with the organ table's largest factor.
    worst_lambda_per_s2: f64,
    tick_s: f64,
}

/// What a tick (and an event) changes.
#[derive(Debug, Clone)]
struct MassSpringState {
    /// The labels (levels, owners) for the current centres.
    refinement: Refinement,
    /// The springs, triangles and active nodes for those labels (the probe's contact surface
    /// holds the triangles over slots).
    mesh: MixedMesh,
    // Per slot (coarse nodes, then one per coarse edge).
    rest: Vec<DVec3>,
    x: Vec<DVec3>,
    v: Vec<DVec3>,
    mass: Vec<f64>,
    damping: Vec<f64>,
    /// The centre slot whose area each slot belongs to ([`NO_OWNER`]: none), as built: equal
    /// to the refinement's labels except inside an event.
    owner: Vec<u8>,
    centres: [Centre; MAX_CENTRES],
    centre_count: usize,
    /// Per centre: `K'_h` and `K'_m` now, N/m.
    kh_area: [f64; MAX_CENTRES],
    km_area: [f64; MAX_CENTRES],
    /// One per tool slot (issue 50), slot 0 first: its probe and where the organ table reads
    /// it. Slot 0's probe surface is the one events edit; the others copy it.
    tools: Vec<ToolContact>,
    /// Per slot: the tool whose contact factor its springs take (a mesh spring its first
    /// node's): the nearest tool in contact at the end of the last tick with one, by rest
    /// position ([`MassSpringBody::update_factor_tools`]).
    factor_tool: Vec<u8>,
    /// `Some(k)` while every slot's `factor_tool` is `k` (no relabelling while one tool
    /// touches).
    factor_all: Option<u8>,
    loads: BodyLoads,
    time_s: f64,
    diverged_at_s: Option<f64>,
    version: u64,
    /// The device forces' blend after an event ([`EVENT_BLEND_TICKS`]).
    blend: ForceBlend,
}

/// Ticks over which the device force blends from the force rendered at an event to the
/// simulated one (30 ms). An event rescales the springs of the area under a pressed probe and
/// starts its new nodes from the coarse surface's displacement, away from the subdivided
/// network's equilibrium: the first sub-steps push the nodes under the probe out, and
/// unblended a 20 mm/s stroke across `lv-surface-springs` read 60 mN within the tick after a
/// subdivision (held 22 mN; 74 % of the hold from one tick to the next, then 17.6 mN).
/// The blend renders `F_sim + w (F_event - F_sim)`, `w` falling linearly from 1 to 0, so the
/// user feels the surface settle instead of the kick; out of contact the force is zero as
/// always.
pub const EVENT_BLEND_TICKS: u32 = 30;

/// The device forces' blend after an event: the force each tool was rendered at the event
/// (N), the ticks left, and whether an event of this tick starts a new blend.
#[derive(Debug, Clone, Copy, Default)]
struct ForceBlend {
    from_n: [DVec3; MAX_TOOLS],
    ticks_left: u32,
    pending: bool,
}

impl ForceBlend {
    /// The force to render for tool `k` whose simulated force is `sim_n` (N): the simulated
    /// one out of contact, and for a tool that rendered no force at the event (it was not in
    /// contact: a touch soon after the event is not ramped in).
    fn render(&self, k: usize, sim_n: DVec3, in_contact: bool) -> DVec3 {
        if self.ticks_left == 0 || !in_contact || self.from_n[k] == DVec3::ZERO {
            return sim_n;
        }
        let w = f64::from(self.ticks_left) / f64::from(EVENT_BLEND_TICKS);
        sim_n + (self.from_n[k] - sim_n) * w
    }

    /// After a tick's outputs `rendered` (N): starts the blend of this tick's event from
    /// them, or counts the tick.
    fn advance(&mut self, rendered: impl Iterator<Item = DVec3>) {
        if self.pending {
            for (from, f) in self.from_n.iter_mut().zip(rendered) {
                *from = f;
            }
            self.ticks_left = EVENT_BLEND_TICKS;
            self.pending = false;
        } else {
            self.ticks_left = self.ticks_left.saturating_sub(1);
        }
    }
}

/// Overwritten every tick: the forces and the contact positions per slot.
#[derive(Debug, Clone)]
struct MassSpringScratch {
    f: Vec<DVec3>,
    /// `x + contact_rest - rest` over the active slots (what the probe sees).
    cx: Vec<DVec3>,
    /// Per slot, zero between uses: one tool's patch weights over `m + dt K_d`, to join the
    /// couplings of several tools ([`MassSpringBody::finish_couplings`]).
    tool_weight: Vec<f64>,
}

/// One subdivision event's work arrays, sized at build: the labels before the event, the
/// region it can change (coarse nodes, triangles and edges, with stamps against repeats), the
/// nodes whose state it changed, and the Gershgorin and ring scratch.
#[derive(Debug, Clone)]
struct EventScratch {
    old_region: Vec<u32>,
    old_edges: Vec<u32>,
    old_type1: Vec<u32>,
    region_nodes: Vec<u32>,
    region_tris: Vec<u32>,
    region_edges: Vec<u32>,
    node_stamp: Vec<u32>,
    tri_stamp: Vec<u32>,
    edge_stamp: Vec<u32>,
    stamp: u32,
    touched: Vec<bool>,
    touched_list: Vec<u32>,
    scratch_home: Vec<f64>,
    ring: Vec<(u32, u32)>,
    ring_dist: Vec<u32>,
    scratch_a: Vec<f64>,
    scratch_b: Vec<f64>,
}

impl MassSpringBody {
    /// The body with the organ table `table` ([`super::organ`]): every spring constant is then
    /// multiplied by the contact factor the table gives at the probe's sphere depth and contact
    /// point. The sub-step plan is recomputed with the table's largest factor.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`mass_spring.organ_file`) for a table of another node, edge
    /// or triangle count;
    /// [`ModelError::Unstable`] when the stiffest factor needs more than
    /// `integrator.max_substeps`.
    pub fn with_organ_table(mut self, table: OrganTable) -> Result<Self, ModelError> {
        if let Some(why) = table.mismatch(&self.model.surface) {
            return Err(ModelError::field(
                "mass_spring.organ_file",
                format!("the organ table {why}"),
            ));
        }
        let beta_max = table.max_factor().max(1.0);
        self.setup.plan = plan_steps(
            &self.setup.integrator,
            critical_time_step_s(self.setup.worst_lambda_per_s2 * beta_max),
        )?;
        self.model.organ = Some(table);
        Ok(self)
    }

    /// The organ table, if any.
    pub fn organ_table(&self) -> Option<&OrganTable> {
        self.model.organ.as_ref()
    }

    /// The probe's sphere depth, m, at the last sub-step in contact (the key of the organ
    /// table, [`super::organ`]): when the probe has a foot ([`super::organ::foot`]) on a
    /// coarse rest triangle (since session 13 on the coarse surface too), the sphere's depth below that flat
    /// triangle along the line through the proxy along the contact normal, plus the organ's
    /// height over the flat triangle there (the arcs over its edges, quadratic over the
    /// triangle: the depth below the surface the reference is pressed on); without a foot the travel
    /// of the probe's kernel plane from its rest position, `sum w_i (rest_i - x_i) . n` over
    /// its patch.
    /// Slot 0's ([`MassSpringBody::tool_contact_depth_m`]).
    pub fn contact_depth_m(&self) -> f64 {
        self.state.tools[0].contact_depth_m
    }

    /// The contact factor of slot 0's tool ([`super::organ`]), which every spring constant is
    /// multiplied by while one tool touches; with several, each slot takes its nearest
    /// tool's ([`MassSpringBody::tool_contact_factor`]).
    pub fn contact_factor(&self) -> f64 {
        self.state.tools[0].contact_factor
    }

    /// The contact factor of slot `s`'s springs now.
    #[inline]
    fn factor_of(&self, s: u32) -> f64 {
        self.state.tools[self.state.factor_tool[s as usize] as usize].contact_factor
    }

    #[inline]
    fn home_constant(&self, s: u32) -> f64 {
        self.home_constant_at(self.factor_of(s), s)
    }

    /// The factor all slots take while one tool keeps every slot (`factor_all`), read once
    /// for a sub-step's force loops instead of per slot.
    #[inline]
    fn uniform_factor(&self) -> Option<f64> {
        self.state
            .factor_all
            .map(|k| self.state.tools[k as usize].contact_factor)
    }

    /// The home-spring constant of slot `s` with the contact factor `beta`, N/m.
    #[inline]
    fn home_constant_at(&self, beta: f64, s: u32) -> f64 {
        beta * match self.state.owner[s as usize] {
            NO_OWNER => self.setup.params.home_spring_n_per_m,
            o => self.state.kh_area[o as usize],
        }
    }

    /// The constant of a mesh spring from slot `i` owned by `owner`, N/m.
    #[inline]
    fn spring_constant(&self, i: u32, owner: u8) -> f64 {
        self.spring_constant_at(self.factor_of(i), owner)
    }

    /// The constant of a mesh spring owned by `owner` with the contact factor `beta`, N/m.
    #[inline]
    fn spring_constant_at(&self, beta: f64, owner: u8) -> f64 {
        beta * match owner {
            NO_OWNER => self.setup.params.mesh_spring_n_per_m,
            o => self.state.km_area[o as usize],
        }
    }

    /// Total energy, J: kinetic `sum m v^2 / 2` plus elastic (home and mesh springs, eq. 2)
    /// over the current mesh with the current constants. Allocation-free.
    pub fn energy_j(&self) -> f64 {
        let mut e = 0.0;
        for &s in self.state.mesh.active() {
            e += self.node_energy_j(s);
        }
        for k in 0..self.state.mesh.springs().len() {
            e += self.spring_energy_j(k);
        }
        e
    }

    /// Kinetic and home-spring energy of slot `s`, J.
    #[inline]
    fn node_energy_j(&self, s: u32) -> f64 {
        let i = s as usize;
        0.5 * self.state.mass[i] * self.state.v[i].length_squared()
            + 0.5 * self.home_constant(s) * (self.state.x[i] - self.state.rest[i]).length_squared()
    }

    /// Elastic energy of mesh spring `k`, J.
    #[inline]
    fn spring_energy_j(&self, k: usize) -> f64 {
        let sp = &self.state.mesh.springs()[k];
        let stretch =
            (self.state.x[sp.j as usize] - self.state.x[sp.i as usize]).length() - sp.rest_length_m;
        0.5 * self.spring_constant(sp.i, sp.owner) * stretch * stretch
    }

    /// Kinetic energy over the active nodes, J.
    pub fn kinetic_energy_j(&self) -> f64 {
        self.state
            .mesh
            .active()
            .iter()
            .map(|&s| 0.5 * self.state.mass[s as usize] * self.state.v[s as usize].length_squared())
            .sum()
    }

    /// Total mass of the active nodes, kg (eq. 3 keeps it constant).
    pub fn total_mass_kg(&self) -> f64 {
        self.state
            .mesh
            .active()
            .iter()
            .map(|&s| self.state.mass[s as usize])
            .sum()
    }

    /// The coarse surface.
    pub fn surface(&self) -> &SpringSurface {
        &self.model.surface
    }

    /// The current refinement: levels and owners (its [`Refinement::mesh`] lists what
    /// [`MassSpringBody::triangles`] and [`MassSpringBody::springs`] hold).
    pub fn refinement(&self) -> &Refinement {
        &self.state.refinement
    }

    /// The parameters.
    pub fn params(&self) -> &MassSpringParams {
        &self.setup.params
    }

    /// Active slots (the coarse nodes, then the active type-2 nodes in the order they
    /// appeared): the viewer's vertices.
    pub fn active_nodes(&self) -> &[u32] {
        self.state.mesh.active()
    }

    /// Triangles of the current mesh over slots, outward oriented: the probe's contact
    /// surface (the pieces of a coarse triangle are not consecutive; as a set they are
    /// [`Refinement::mesh`]'s).
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.state.tools[0].probe.surface.triangles
    }

    /// Mesh springs of the current mesh with their rest lengths and current constants (as a
    /// set, [`Refinement::mesh`]'s springs).
    pub fn springs(&self) -> impl Iterator<Item = Spring> + '_ {
        self.state.mesh.springs().iter().map(|sp| Spring {
            i: sp.i,
            j: sp.j,
            rest_length_m: sp.rest_length_m,
            stiffness_n_per_m: self.spring_constant(sp.i, sp.owner),
        })
    }

    /// Positions per slot, m (inactive slots hold stale values).
    pub fn positions(&self) -> &[DVec3] {
        &self.state.x
    }

    /// Velocities per slot, m/s.
    pub fn velocities(&self) -> &[DVec3] {
        &self.state.v
    }

    /// Rest positions per slot, m.
    pub fn rest_positions(&self) -> &[DVec3] {
        &self.state.rest
    }

    /// Masses per slot, kg.
    pub fn masses(&self) -> &[f64] {
        &self.state.mass
    }

    /// Positions and velocities per slot, to set a state (tests, experiments). Fixed nodes
    /// must stay at rest with zero velocity.
    pub fn state_mut(&mut self) -> (&mut [DVec3], &mut [DVec3]) {
        self.state.diverged_at_s = None;
        (&mut self.state.x, &mut self.state.v)
    }

    /// Event counters.
    pub fn event_stats(&self) -> EventStats {
        self.stats
    }

    /// The sub-step plan (from the worst-case Gershgorin bound).
    pub fn plan(&self) -> StepPlan {
        self.setup.plan
    }

    /// Critical time step of the coarse mesh (Gershgorin bound), s.
    pub fn coarse_critical_dt_s(&self) -> f64 {
        self.setup.coarse_critical_dt_s
    }

    /// The current `K'_h` of each centre's area (N/m), in centre order, with the centres'
    /// nodes: for tests and tools.
    pub fn area_home_constants(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        (0..self.state.centre_count).map(|k| (self.state.centres[k].node, self.state.kh_area[k]))
    }

    /// Slot 0's probe ([`MassSpringBody::tool_probe`]).
    pub fn probe(&self) -> &Probe {
        &self.state.tools[0].probe
    }

    /// Sets slot 0's contact factor to `beta` (positive), which every spring then takes, and
    /// the sub-step plan for it (for `beta` above 1): the organ calibration presses a body
    /// without an organ table at the run time's factor ([`super::organ`]), whose factor stays
    /// as set. Not for the servo tick.
    ///
    /// # Errors
    /// [`ModelError::Unstable`] when `beta` needs more than `integrator.max_substeps`.
    pub fn set_contact_factor(&mut self, beta: f64) -> Result<(), ModelError> {
        self.setup.plan = plan_steps(
            &self.setup.integrator,
            critical_time_step_s(self.setup.worst_lambda_per_s2 * beta.max(1.0)),
        )?;
        self.state.tools[0].contact_factor = beta;
        Ok(())
    }

    /// Advances one servo tick (module documentation) with slot 0's device alone; the other
    /// slots are released ([`MassSpringBody::tick_tools`]).
    ///
    /// # Errors
    /// [`ModelError::InvalidDevice`] for a non-finite or absurd device input (state
    /// untouched); [`ModelError::Diverged`] when the state diverged (then every later tick
    /// too). Allocation-free, also when the tick runs a subdivision event.
    pub fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        let mut out = [TickOutput::default()];
        self.tick_tools(std::slice::from_ref(input), &mut out)?;
        Ok(out[0])
    }

    /// [`Self::tick`] with every tool slot's input (issue 50; [`SoftBody::tick_tools`]):
    /// `inputs[k]` drives slot `k`'s probe and `outputs[k]` receives its force; slots past
    /// `inputs.len()` are released. All the probes' reactions act in the same sub-steps, their
    /// couplings are completed together (Woodbury over their rank-one terms) and every tool's contact
    /// node becomes a centre. Slot 0 alone is the one-tool tick of before, bit for bit.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for slot counts [`crate::body::check_tool_slots`] refuses; otherwise as
    /// [`Self::tick`] (any slot's invalid input refuses the tick, state untouched).
    /// Allocation-free.
    pub fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        check_tool_inputs(inputs, outputs.len(), self.state.tools.len())?;
        if let Some(time_s) = self.state.diverged_at_s {
            return Err(ModelError::Diverged { time_s });
        }
        // A tool that leaves while another touches is withdrawn over `WITHDRAW_S`.
        let mut acting = [TickInput::default(); MAX_TOOLS];
        self.acting_inputs(inputs, &mut acting);
        let acting = &acting[..self.state.tools.len()];
        for _ in 0..self.setup.plan.substeps {
            self.substep(acting)?;
        }
        self.state.time_s += self.setup.tick_s;
        self.state.loads.advance(self.setup.tick_s);
        self.update_contact_positions();
        for tool in &mut self.state.tools {
            if !tool.probe.state.in_contact {
                tool.foot = None;
            }
            tool.foot_searched = false;
        }
        self.update_factor_tools();
        // 4. Subdivision around each tool's contact node, coarsening of areas left.
        self.update_centres();
        // 5. Output (a slot without a device: no contact, also while it is withdrawn).
        let blend = self.state.blend;
        for (k, ((tool, input), out)) in self
            .state
            .tools
            .iter()
            .zip(inputs)
            .zip(outputs.iter_mut())
            .enumerate()
        {
            let contact = tool.probe.state;
            *out = match input.device_position_m {
                Some(device_m) => TickOutput {
                    force_on_device_n: blend.render(
                        k,
                        contact.force_on_device_n,
                        contact.in_contact,
                    ),
                    in_contact: contact.in_contact,
                    proxy_position_m: if contact.in_contact {
                        contact.proxy_m
                    } else {
                        device_m
                    },
                    contact_stiffness_n_per_m: tool.probe.contact_stiffness(),
                    sim_time_s: self.state.time_s,
                },
                None => TickOutput {
                    sim_time_s: self.state.time_s,
                    ..TickOutput::default()
                },
            };
        }
        let rendered = outputs.iter().map(|o| o.force_on_device_n);
        self.state.blend.advance(rendered);
        Ok(())
    }

    /// One sub-step of [`Self::tick_tools`].
    ///
    /// # Errors
    /// [`ModelError::Diverged`] (and the body remembers it).
    fn substep(&mut self, inputs: &[TickInput]) -> Result<(), ModelError> {
        let dt = self.setup.plan.sub_dt_s;
        self.update_area_constants();
        let uniform = self.uniform_factor();
        // 1. Forces of eq. 2: home springs, mesh springs, point loads.
        for &s in self.state.mesh.active() {
            let i = s as usize;
            let beta = uniform.unwrap_or_else(|| self.factor_of(s));
            self.scratch.f[i] =
                (self.state.rest[i] - self.state.x[i]) * self.home_constant_at(beta, s);
        }
        for sp in self.state.mesh.springs() {
            let d = self.state.x[sp.j as usize] - self.state.x[sp.i as usize];
            let len = d.length();
            if len > 0.0 {
                let beta = uniform.unwrap_or_else(|| self.factor_of(sp.i));
                let k = self.spring_constant_at(beta, sp.owner);
                let fs = d * (k * (len - sp.rest_length_m) / len);
                self.scratch.f[sp.i as usize] += fs;
                self.scratch.f[sp.j as usize] -= fs;
            }
        }
        self.state.loads.add_to(&self.state.x, &mut self.scratch.f);
        // 2. Contact: every tool's proxy and the explicit part of its coupling's reaction, on
        // the contact positions.
        self.update_probes(inputs);
        // 3. Symplectic Euler with implicit damping, then the implicit couplings.
        let mut max_v2: f64 = 0.0;
        for &s in self.state.mesh.active() {
            let i = s as usize;
            if self.model.fixed[i] {
                continue;
            }
            let denom = self.state.mass[i] + dt * self.state.damping[i];
            self.state.v[i] =
                (self.state.v[i] * self.state.mass[i] + self.scratch.f[i] * dt) / denom;
            self.state.x[i] += self.state.v[i] * dt;
            max_v2 = max_v2.max(self.state.v[i].length_squared());
        }
        max_v2 = max_v2.max(self.finish_couplings(dt));
        if !(max_v2 <= DIVERGENCE_SPEED_M_PER_S * DIVERGENCE_SPEED_M_PER_S) {
            self.state.diverged_at_s = Some(self.state.time_s);
            return Err(ModelError::Diverged {
                time_s: self.state.time_s,
            });
        }
        Ok(())
    }

    /// The probe's view of the active slots: `cx = x + contact_rest - rest`. O(active),
    /// allocation-free.
    fn update_contact_positions(&mut self) {
        for &s in self.state.mesh.active() {
            let i = s as usize;
            self.scratch.cx[i] =
                self.state.x[i] + (self.model.contact_rest[i] - self.state.rest[i]);
        }
    }

    /// Contact positions per slot (where the probe meets the surface, m; inactive slots hold
    /// stale values): the positions plus the offsets of [`super::contact_rest`].
    pub fn contact_positions(&self) -> &[DVec3] {
        &self.scratch.cx
    }

    /// Largest displacement from rest over the active nodes, m.
    pub fn max_displacement_m(&self) -> f64 {
        self.state
            .mesh
            .active()
            .iter()
            .map(|&s| (self.state.x[s as usize] - self.state.rest[s as usize]).length_squared())
            .fold(0.0, f64::max)
            .sqrt()
    }

    /// The Gershgorin bound on `M^-1 K` (1/s^2) of the current mesh with the current
    /// constants (the tick's sub-step respects the worst case over all meshes, see
    /// [`MassSpringBody::plan`]). Allocation-free.
    pub fn current_stiffness_bound_per_s2(&mut self) -> f64 {
        let n = self.state.mass.len();
        let mut home = std::mem::take(&mut self.event.scratch_home);
        for (s, h) in home.iter_mut().enumerate().take(n) {
            *h = if !self.state.mesh.is_active(s as u32) {
                0.0
            } else {
                self.home_constant(s as u32)
            };
        }
        let mut diag = std::mem::take(&mut self.event.scratch_a);
        let mut off = std::mem::take(&mut self.event.scratch_b);
        let lambda = gershgorin_bound_per_s2(
            &home,
            &self.state.mass,
            &self.model.fixed,
            self.state
                .mesh
                .springs()
                .iter()
                .map(|sp| (sp.i, sp.j, self.spring_constant(sp.i, sp.owner))),
            &mut diag,
            &mut off,
        );
        self.event.scratch_home = home;
        self.event.scratch_a = diag;
        self.event.scratch_b = off;
        lambda
    }
}

impl SoftBody for MassSpringBody {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        MassSpringBody::tick(self, input)
    }

    /// The scene's `probe.max_tools`.
    fn max_tools(&self) -> usize {
        self.state.tools.len()
    }

    /// The index of `tool_id` among the scene's `[[probe.tool]]`.
    fn tool_slot(&self, tool_id: &str) -> Option<usize> {
        self.model.tool_ids.iter().position(|id| id == tool_id)
    }

    fn tick_tools(
        &mut self,
        inputs: &[TickInput],
        outputs: &mut [TickOutput],
    ) -> Result<(), ModelError> {
        MassSpringBody::tick_tools(self, inputs, outputs)
    }

    /// Point loads act on the coarse nodes around the point (they survive every event).
    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        self.state.loads.add_point_load(
            &self.state.x,
            self.state.tools[0].probe.params.radius_m,
            point_m,
            force_n,
            duration_s,
        )
    }

    fn surface_topology(&self) -> SurfaceTopology<'_> {
        SurfaceTopology {
            version: self.state.version,
            vertex_count: self.state.mesh.active().len(),
            triangles: self.state.mesh.view_triangles(),
        }
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        SurfaceCapacity {
            vertices: self.state.mass.len(),
            triangles: 4 * self.model.surface.triangle_count(),
        }
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        assert_eq!(
            out.len(),
            3 * self.state.mesh.active().len(),
            "surface buffer length"
        );
        let mut max_d2: f64 = 0.0;
        for (k, &s) in self.state.mesh.active().iter().enumerate() {
            let p = self.state.x[s as usize];
            out[3 * k] = p.x as f32;
            out[3 * k + 1] = p.y as f32;
            out[3 * k + 2] = p.z as f32;
            max_d2 = max_d2.max((p - self.state.rest[s as usize]).length_squared());
        }
        max_d2.sqrt()
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        assert_eq!(
            out.len(),
            3 * self.state.mesh.active().len(),
            "surface buffer length"
        );
        for (k, &s) in self.state.mesh.active().iter().enumerate() {
            let p = self.state.rest[s as usize];
            out[3 * k] = p.x as f32;
            out[3 * k + 1] = p.y as f32;
            out[3 * k + 2] = p.z as f32;
        }
    }

    /// Nodes and surface vertices are the current (subdivided) node count; elements are the
    /// mesh springs, all of them simulated.
    fn stats(&self) -> BodyStats {
        BodyStats {
            nodes: self.state.mesh.active().len(),
            elements: self.state.mesh.springs().len(),
            active_elements: self.state.mesh.springs().len(),
            particles: 0,
            active_particles: 0,
            active_point_loads: self.state.loads.active_point_loads(),
            surface_vertices: self.state.mesh.active().len(),
            topology_version: self.state.version,
            sim_time_s: self.state.time_s,
            max_displacement_m: self.max_displacement_m(),
            ..BodyStats::default()
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "mass-spring",
            scene: self.model.scene_name.clone(),
            tick_s: self.setup.tick_s,
            substeps: self.setup.plan.substeps,
            critical_dt_s: self.setup.plan.critical_dt_s,
            probe_radius_m: self.state.tools[0].probe.params.radius_m,
            point_loads: crate::body::PointLoadZone::Anywhere,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blend of an event in contact: the event's tick renders the simulated force, the
    /// next one the force at the event, then a linear approach; out of contact, after the
    /// blend, and for a tool that rendered nothing at the event: the simulated force.
    #[test]
    fn an_event_blends_the_rendered_force_linearly_in_contact_only() {
        let (event, sim) = (DVec3::new(0.0, 0.0, 0.02), DVec3::new(0.0, 0.0, 0.05));
        let mut blend = ForceBlend {
            pending: true,
            ..ForceBlend::default()
        };
        assert_eq!(blend.render(0, event, true), event);
        blend.advance([event, DVec3::ZERO].into_iter());
        assert_eq!(blend.render(0, sim, true), event);
        assert_eq!(blend.render(0, sim, false), sim);
        assert_eq!(blend.render(1, sim, true), sim, "no force at the event");
        for _ in 0..EVENT_BLEND_TICKS / 2 {
            blend.advance(std::iter::empty());
        }
        let half = blend.render(0, sim, true);
        assert!((half - 0.5 * (event + sim)).length() < 1e-15, "{half}");
        for _ in 0..EVENT_BLEND_TICKS / 2 {
            blend.advance(std::iter::empty());
        }
        assert_eq!(blend.render(0, sim, true), sim);
    }
}
