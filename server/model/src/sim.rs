//! [`Simulation`]: one deformable body driven by a haptic probe and point loads, advanced one
//! servo tick at a time.
//!
//! Layout follows state / scratch / parameters: [`SimState`] holds positions, velocities and
//! time; the force buffer and the point-load table are scratch sized at construction; the
//! [`FemModel`], [`StepPlan`] and probe parameters are fixed. [`Simulation::tick`] allocates
//! nothing, takes no lock and does no I/O, so the server can call it on its servo thread.
//!
//! The scene's loads ([`crate::scene::SceneLoads`]) act in every sub-step of every integrator:
//! gravity, dead pressure and point forces are summed once at construction into a constant
//! nodal force; follower pressure is recomputed from the current positions each sub-step.
//! [`static_external_forces`] gives the same forces for static solves.
//!
//! Neighbours: built from a [`crate::scene::Scene`]; uses [`crate::fem`],
//! [`crate::integrator`], [`crate::contact`].

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::condensed::CondensedSolver;
use crate::contact::{ContactState, ContactSurface, MAX_PATCH_NODES, PATCH_RADIUS_FACTOR, Probe};
use crate::fem::{CLAMPED, FemModel};
use crate::integrator::{self, CgStats, ImplicitSolver, IntegratorKind, StepPlan};
use crate::scene::Scene;

/// Largest number of point loads active at once (the table is preallocated).
pub const MAX_POINT_LOADS: usize = 32;
/// Largest accepted point-load magnitude, N. Anything larger is rejected as absurd for a
/// haptic scene (the strongest device we drive renders 100 N).
pub const MAX_POINT_FORCE_N: f64 = 100.0;
/// Largest accepted point-load duration, s.
pub const MAX_POINT_LOAD_DURATION_S: f64 = 3600.0;
/// Largest accepted distance between a device point and the rest bounding box, m: device
/// points farther away than this are absurd (a unit error or a broken sensor).
pub const MAX_DEVICE_DISTANCE_M: f64 = 10.0;
/// A nodal speed above this (m/s) is treated as divergence.
pub const DIVERGENCE_SPEED_M_PER_S: f64 = 100.0;

/// Dynamic state of the body.
#[derive(Debug, Clone)]
pub struct SimState {
    /// Node positions, m.
    pub x: Vec<DVec3>,
    /// Node velocities, m/s.
    pub v: Vec<DVec3>,
    /// Simulated time, s.
    pub time_s: f64,
}

/// What the device reports for one servo tick.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TickInput {
    /// Haptic interaction point, m, scene frame; `None` when no device is connected.
    pub device_position_m: Option<DVec3>,
    /// Device velocity, m/s.
    pub device_velocity_m_per_s: DVec3,
}

/// What one servo tick returns to the device.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TickOutput {
    /// Force the device must render, N (the virtual coupling force at the end of the tick).
    pub force_on_device_n: DVec3,
    /// Whether the probe touches the surface.
    pub in_contact: bool,
    /// Proxy (god-object) position, m.
    pub proxy_position_m: DVec3,
    /// Local contact stiffness, 3x3 row-major, N/m.
    pub contact_stiffness_n_per_m: [f64; 9],
    /// Simulated time after the tick, s.
    pub sim_time_s: f64,
}

/// A point load: a force on a surface point, spread over the surface nodes around it with the
/// probe's kernel weights (`nodes[..len]`, `weights[..len]`, sum 1), see
/// [`Simulation::add_point_load`].
#[derive(Debug, Clone, Copy, PartialEq)]
struct PointLoad {
    nodes: [u32; MAX_PATCH_NODES],
    weights: [f64; MAX_PATCH_NODES],
    len: usize,
    force_n: DVec3,
    remaining_s: f64,
}

/// Whether a simulation is still meaningful, with the quantities that say so
/// ([`Simulation::stability`]).
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

/// A deformable body with its probe, loads, integrator and sub-stepping.
#[derive(Debug, Clone)]
pub struct Simulation {
    fem: FemModel,
    kind: IntegratorKind,
    plan: StepPlan,
    tick_s: f64,
    /// Seed eq. 34 per-node matrices `A_i^-1` (semi-implicit only; empty otherwise).
    a_inv: Vec<DMat3>,
    /// Backward Euler solver and its scratch (backward Euler only).
    implicit: Option<ImplicitSolver>,
    /// Backward Euler on the scene's active region with the rest condensed (scenes with
    /// `[active_region]`; then `implicit` is `None`).
    condensed: Option<CondensedSolver>,
    /// Scene loads that do not depend on the state (gravity, dead pressure, point forces), N
    /// per node; empty when there are none.
    constant_load: Vec<DVec3>,
    /// Follower pressures: (triangles, Pa).
    follower: Vec<(Vec<[u32; 3]>, f64)>,
    /// Set when a tick diverged; later ticks refuse to run.
    diverged_at_s: Option<f64>,
    state: SimState,
    /// Scratch: total nodal forces of the current sub-step.
    force: Vec<DVec3>,
    probe: Probe,
    /// Surface used to place point loads (all boundary triangles not entirely clamped).
    load_surface: ContactSurface,
    loads: Vec<PointLoad>,
    /// Scratch for the patch of a new point load (capacity [`MAX_PATCH_NODES`]).
    load_nodes: Vec<u32>,
    load_weights: Vec<f64>,
    /// Extra force on the probe's contact patch (N) and its remaining time (s), see
    /// [`Simulation::add_probe_load`].
    probe_load_n: DVec3,
    probe_load_remaining_s: f64,
    /// Surface for viewers: distinct boundary nodes and triangles indexing into them.
    surface_nodes: Vec<u32>,
    surface_triangles: Vec<[u32; 3]>,
    scene_name: String,
    last_output: TickOutput,
}

impl Simulation {
    /// Builds the simulation of `scene`: precomputes the FEM data, the critical time step and the
    /// sub-step plan, and the semi-implicit per-node matrices.
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] / [`ModelError::SceneField`] for a bad mesh or material;
    /// [`ModelError::Unstable`] when the integrator cannot be stable within `max_substeps`.
    pub fn new(scene: &Scene) -> Result<Self, ModelError> {
        let mut fem =
            FemModel::with_smoothing(&scene.mesh, scene.material, scene.strain_smoothing)?;
        fem.clamp_nodes(&scene.clamped_nodes);
        Self::from_fem(fem, scene)
    }

    /// Like [`Simulation::new`] but with a prepared [`FemModel`] (e.g. with roller constraints).
    ///
    /// # Errors
    /// As [`Simulation::new`].
    pub fn from_fem(fem: FemModel, scene: &Scene) -> Result<Self, ModelError> {
        let p = scene.integrator;
        if !(p.tick_s > 0.0 && p.tick_s.is_finite()) {
            return Err(ModelError::field(
                "integrator.tick_s",
                "must be a positive number",
            ));
        }
        let critical = integrator::critical_time_step(&fem, p.kind);
        let plan = integrator::plan_steps(&p, critical)?;
        let a_inv = match p.kind {
            IntegratorKind::SemiImplicit => integrator::semi_implicit_inverses(&fem, plan.sub_dt_s),
            IntegratorKind::SymplecticEuler | IntegratorKind::BackwardEuler => Vec::new(),
        };
        let condensed = match scene.active_region {
            Some(region) => Some(CondensedSolver::new(
                &fem,
                &scene.mesh,
                region,
                plan.sub_dt_s,
            )?),
            None => None,
        };
        let implicit = (p.kind == IntegratorKind::BackwardEuler && condensed.is_none())
            .then(|| ImplicitSolver::new(&fem, plan.sub_dt_s, &p));
        let constant_load = constant_external_forces(scene, &fem.rest, &fem.lumped_mass_kg);
        // A condensed model sees loads and contact on its active nodes only.
        let active = |t: &[u32; 3]| condensed.as_ref().is_none_or(|c| c.is_active_triangle(t));
        if let Some(c) = &condensed {
            let far_load = constant_load
                .iter()
                .enumerate()
                .any(|(i, f)| *f != DVec3::ZERO && !c.is_active_node(i as u32));
            let far_follower = scene
                .loads
                .pressure
                .iter()
                .filter(|l| l.follower)
                .any(|l| !l.triangles.iter().all(|t| c.is_active_triangle(t)));
            if far_load || far_follower {
                return Err(ModelError::field(
                    "active_region",
                    "a scene load acts outside the active region (condensed elements are unloaded): enlarge the region or remove the load",
                ));
            }
        }
        let touchable: Vec<[u32; 3]> = scene.touchable.iter().copied().filter(active).collect();
        let contact_nodes: Vec<u32> = touchable.iter().flatten().copied().collect();
        if touchable.is_empty() {
            return Err(ModelError::field(
                "active_region",
                "no touchable triangle lies inside the active region",
            ));
        }
        let follower = scene
            .loads
            .pressure
            .iter()
            .filter(|l| l.follower)
            .map(|l| (l.triangles.clone(), l.pressure_pa))
            .collect();
        let n = fem.node_count();
        let boundary = scene.mesh.boundary_triangles();
        let load_tris: Vec<[u32; 3]> = boundary
            .iter()
            .copied()
            .filter(|t| t.iter().any(|&i| fem.constraint[i as usize] != CLAMPED))
            .filter(active)
            .collect();
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
        let probe = Probe::new(scene.probe, touchable, &fem.rest);
        let mut condensed = condensed;
        if let Some(c) = &mut condensed {
            c.prepare_contact(&contact_nodes);
        }
        Ok(Self {
            kind: p.kind,
            plan,
            tick_s: p.tick_s,
            a_inv,
            implicit,
            condensed,
            constant_load,
            follower,
            diverged_at_s: None,
            state: SimState {
                x: fem.rest.clone(),
                v: vec![DVec3::ZERO; n],
                time_s: 0.0,
            },
            force: vec![DVec3::ZERO; n],
            probe,
            load_surface: ContactSurface::new(load_tris, n),
            loads: Vec::with_capacity(MAX_POINT_LOADS),
            load_nodes: Vec::with_capacity(MAX_PATCH_NODES),
            load_weights: Vec::with_capacity(MAX_PATCH_NODES),
            probe_load_n: DVec3::ZERO,
            probe_load_remaining_s: 0.0,
            surface_nodes,
            surface_triangles,
            scene_name: scene.name.clone(),
            last_output: TickOutput::default(),
            fem,
        })
    }

    /// Advances one servo tick (`plan().substeps` model steps) with the device input, and
    /// returns the force for the device.
    ///
    /// # Errors
    /// [`ModelError::InvalidDevice`] for a non-finite or absurd device input (the state is not
    /// touched); [`ModelError::Diverged`] when the state became non-finite or diverged (the
    /// caller must quarantine the session: the state is no longer meaningful). Neither
    /// allocates.
    pub fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        self.check_device(input)?;
        if let Some(time_s) = self.diverged_at_s {
            return Err(ModelError::Diverged { time_s });
        }
        let h = self.plan.sub_dt_s;
        let mut contact = ContactState::default();
        for _ in 0..self.plan.substeps {
            self.force.iter_mut().for_each(|f| *f = DVec3::ZERO);
            // Backward Euler treats the viscous force implicitly inside its solve.
            let v_for_force = match self.kind {
                IntegratorKind::BackwardEuler => None,
                _ => Some(self.state.v.as_slice()),
            };
            self.condensed
                .as_ref()
                .map_or(&self.fem, CondensedSolver::active_model)
                .add_internal_forces(&self.state.x, v_for_force, &mut self.force);
            self.add_external_forces();
            contact = match input.device_position_m {
                Some(p) => {
                    let c = self
                        .probe
                        .update(&self.state.x, p, input.device_velocity_m_per_s);
                    self.probe.add_reaction(&mut self.force);
                    if self.probe_load_remaining_s > 0.0 {
                        let (nodes, weights) = self.probe.patch();
                        for (&i, &w) in nodes.iter().zip(weights) {
                            self.force[i as usize] += self.probe_load_n * w;
                        }
                    }
                    c
                }
                None => {
                    self.probe.state = ContactState::default();
                    ContactState::default()
                }
            };
            let max_v2 = if let Some(solver) = &mut self.condensed {
                let coupling = self.probe.rank_one(h);
                let max_v2 =
                    solver.step(&self.force, coupling, &mut self.state.x, &mut self.state.v);
                if contact.in_contact {
                    self.probe.finish_solved(h, &self.state.v);
                    contact = self.probe.state;
                }
                max_v2
            } else if let Some(solver) = &mut self.implicit {
                let coupling = self.probe.rank_one(h);
                let max_v2 = solver.step(
                    &self.fem,
                    &self.force,
                    coupling,
                    &mut self.state.x,
                    &mut self.state.v,
                );
                if contact.in_contact {
                    self.probe.finish_solved(h, &self.state.v);
                    contact = self.probe.state;
                }
                max_v2
            } else {
                let mut max_v2 = integrator::integrate_nodes(
                    self.kind,
                    &self.fem,
                    &self.a_inv,
                    h,
                    &self.force,
                    &mut self.state.x,
                    &mut self.state.v,
                );
                if contact.in_contact {
                    let (kind, fem, a_inv) = (self.kind, &self.fem, &self.a_inv);
                    self.probe
                        .finish_implicit(h, &mut self.state.x, &mut self.state.v, |i, w| {
                            integrator::apply_inverse(kind, fem, a_inv, h, i, w)
                        });
                    contact = self.probe.state;
                    for &i in self.probe.patch().0 {
                        let s = self.state.v[i as usize].length_squared();
                        if !s.is_finite() || s > max_v2 {
                            max_v2 = if s.is_finite() { s } else { f64::NAN };
                        }
                    }
                }
                max_v2
            };
            if !(max_v2 <= DIVERGENCE_SPEED_M_PER_S * DIVERGENCE_SPEED_M_PER_S) {
                self.diverged_at_s = Some(self.state.time_s);
                return Err(ModelError::Diverged {
                    time_s: self.state.time_s,
                });
            }
        }
        self.state.time_s += self.tick_s;
        let dt = self.tick_s;
        self.loads.retain_mut(|l| {
            l.remaining_s -= dt;
            l.remaining_s > 1e-12
        });
        if self.probe_load_remaining_s > 0.0 {
            self.probe_load_remaining_s -= dt;
            if self.probe_load_remaining_s <= 1e-12 {
                self.probe_load_remaining_s = 0.0;
            }
        }
        let out = TickOutput {
            force_on_device_n: contact.force_on_device_n,
            in_contact: contact.in_contact,
            proxy_position_m: if contact.in_contact {
                contact.proxy_m
            } else {
                input.device_position_m.unwrap_or(DVec3::ZERO)
            },
            contact_stiffness_n_per_m: self.probe.contact_stiffness(),
            sim_time_s: self.state.time_s,
        };
        self.last_output = out;
        Ok(out)
    }

    /// Adds the scene loads and the active point loads to the force buffer. Allocation-free.
    fn add_external_forces(&mut self) {
        if !self.constant_load.is_empty() {
            for (f, l) in self.force.iter_mut().zip(&self.constant_load) {
                *f += *l;
            }
        }
        for (tris, p) in &self.follower {
            crate::statics::add_pressure_forces(tris, &self.state.x, *p, &mut self.force);
        }
        for l in &self.loads {
            for (&i, &w) in l.nodes[..l.len].iter().zip(&l.weights[..l.len]) {
                self.force[i as usize] += l.force_n * w;
            }
        }
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
        let (elastic_energy_j, volume_change) = match &self.condensed {
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
            stable: finite && self.diverged_at_s.is_none(),
            diverged_at_s: self.diverged_at_s,
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
    /// some integration point.
    /// With an active region, of the active elements (the far ones are linear).
    pub fn inverted_elements(&self) -> usize {
        self.condensed
            .as_ref()
            .map_or(&self.fem, CondensedSolver::active_model)
            .inverted_elements(&self.state.x)
    }

    /// Conjugate-gradient statistics of the last backward Euler step (default for the other
    /// integrators).
    pub fn cg_stats(&self) -> CgStats {
        self.implicit
            .as_ref()
            .map(ImplicitSolver::stats)
            .unwrap_or_default()
    }

    fn check_device(&self, input: &TickInput) -> Result<(), ModelError> {
        if let Some(p) = input.device_position_m {
            if !p.is_finite() || !input.device_velocity_m_per_s.is_finite() {
                return Err(ModelError::InvalidDevice(
                    "device position or velocity is not finite",
                ));
            }
            if p.abs().max_element() > MAX_DEVICE_DISTANCE_M {
                return Err(ModelError::InvalidDevice(
                    "device position is farther than 10 m from the origin",
                ));
            }
        }
        Ok(())
    }

    /// Applies `force_n` (N) at the surface point closest to `point_m` (m) for `duration_s` of
    /// simulated time, spread as a probe of the scene's radius `r` touching there spreads its
    /// reaction: over the free boundary nodes within `2 r` of the point `r` outside the surface
    /// (the probe's centre) with the contact kernel weights `(1 - d^2 / (2r)^2)^2` (sum 1, see
    /// [`ContactSurface::gather_kernel_patch`]; a disc of radius `sqrt(3) r` on the surface),
    /// fixed to those nodes when the load is added. When no node lies that close (a triangle
    /// much larger than the probe) it falls back to the closest triangle's barycentric
    /// weights.
    ///
    /// A force on the three nodes of one triangle is a point load in the continuum sense: its
    /// local displacement grows without bound as the mesh is refined (0.05 N on one sub-triangle
    /// of the default quadratic `lv` moved the surface 9.9 mm in the demo); spread over the
    /// probe's footprint it converges with the mesh (7.6 mm on 474, 7.4 mm on 948 quadratic
    /// elements). It is more than the 3 mm of a probe held against the surface with the same
    /// force, because the probe's patch widens as the surface wraps around the sphere, while
    /// this one stays on the nodes it was given.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] (state untouched) for non-finite values, a force above
    /// [`MAX_POINT_FORCE_N`], a duration outside `(0, MAX_POINT_LOAD_DURATION_S]`, a point farther
    /// than [`MAX_DEVICE_DISTANCE_M`]; [`ModelError::LoadTableFull`] when [`MAX_POINT_LOADS`] loads
    /// are already active (this path does not allocate, so the servo tick may call it).
    pub fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        validate_point_load(point_m, force_n, duration_s)?;
        if self.loads.len() >= MAX_POINT_LOADS {
            return Err(ModelError::LoadTableFull(MAX_POINT_LOADS));
        }
        let sp = self
            .load_surface
            .closest_global(&self.state.x, point_m)
            .ok_or(ModelError::InvalidDevice(
                "the body has no free surface to load",
            ))?;
        let mut load = PointLoad {
            nodes: [0; MAX_PATCH_NODES],
            weights: [0.0; MAX_PATCH_NODES],
            len: 0,
            force_n,
            remaining_s: duration_s,
        };
        // The kernel centre sits one probe radius outside the surface, where a probe touching
        // there has its centre, so the weights are the probe's.
        let r = self.probe.params.radius_m;
        let centre = sp.point + self.load_surface.normal(sp.triangle, &self.state.x) * r;
        self.load_surface.gather_kernel_patch(
            &self.state.x,
            centre,
            sp.triangle,
            PATCH_RADIUS_FACTOR * r,
            &mut self.load_nodes,
            &mut self.load_weights,
        );
        if self.load_nodes.is_empty() {
            let tri = self.load_surface.triangles[sp.triangle as usize];
            load.nodes[..3].copy_from_slice(&tri);
            load.weights[..3].copy_from_slice(&sp.bary);
            load.len = 3;
        } else {
            load.len = self.load_nodes.len();
            load.nodes[..load.len].copy_from_slice(&self.load_nodes);
            load.weights[..load.len].copy_from_slice(&self.load_weights);
        }
        self.loads.push(load);
        Ok(())
    }

    /// Applies `force_n` (N) to the body at the probe for `duration_s` of simulated time: in every
    /// sub-step in contact it is spread over the probe's contact patch with the same kernel
    /// weights as the coupling reaction (the nodes within 2 r of the device point, see
    /// [`crate::contact`]), so it follows the probe and never concentrates on one triangle. Out of
    /// contact it does not act (its time still runs). The device is not told about it: this is an
    /// external disturbance at the probe (the stability suite's 10-fold impulse), not a change of
    /// the coupling. A new call replaces an active probe load. Allocation-free.
    ///
    /// Unlike [`Simulation::add_point_load`] (one surface triangle), the load is spread over the
    /// probe's footprint: a force concentrated on the three nodes of a small triangle is a point
    /// load in the continuum sense, whose local displacement grows without bound as the mesh is
    /// refined.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] (state untouched) for a non-finite force, a force above
    /// [`MAX_POINT_FORCE_N`] or a duration outside `(0, MAX_POINT_LOAD_DURATION_S]`.
    pub fn add_probe_load(&mut self, force_n: DVec3, duration_s: f64) -> Result<(), ModelError> {
        validate_point_load(DVec3::ZERO, force_n, duration_s)?;
        self.probe_load_n = force_n;
        self.probe_load_remaining_s = duration_s;
        Ok(())
    }

    /// Remaining time of the probe load of [`Simulation::add_probe_load`], s (0 when none).
    pub fn probe_load_remaining_s(&self) -> f64 {
        self.probe_load_remaining_s
    }

    /// Number of point loads still active.
    pub fn active_point_loads(&self) -> usize {
        self.loads.len()
    }

    /// Writes the surface vertex positions (xyz interleaved, f32, m) into `out` (length
    /// `3 * surface_node_indices().len()`) and returns the largest displacement from rest among
    /// them, m.
    ///
    /// # Panics
    /// If `out` has the wrong length.
    pub fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        assert_eq!(
            out.len(),
            3 * self.surface_nodes.len(),
            "surface buffer length"
        );
        let mut max_d2: f64 = 0.0;
        for (k, &i) in self.surface_nodes.iter().enumerate() {
            let p = self.state.x[i as usize];
            out[3 * k] = p.x as f32;
            out[3 * k + 1] = p.y as f32;
            out[3 * k + 2] = p.z as f32;
            max_d2 = max_d2.max((p - self.fem.rest[i as usize]).length_squared());
        }
        max_d2.sqrt()
    }

    /// Largest nodal displacement from rest over the whole body, m.
    pub fn max_displacement_m(&self) -> f64 {
        self.state
            .x
            .iter()
            .zip(&self.fem.rest)
            .map(|(x, r)| (*x - *r).length_squared())
            .fold(0.0, f64::max)
            .sqrt()
    }

    /// Kinetic energy `sum m v^2 / 2`, J.
    pub fn kinetic_energy_j(&self) -> f64 {
        self.state
            .v
            .iter()
            .zip(&self.fem.lumped_mass_kg)
            .map(|(v, m)| 0.5 * m * v.length_squared())
            .sum()
    }

    /// Boundary nodes shown to viewers (indices into the body's nodes), sorted.
    pub fn surface_node_indices(&self) -> &[u32] {
        &self.surface_nodes
    }

    /// Boundary triangles indexing into [`Simulation::surface_node_indices`], outward oriented.
    pub fn surface_triangles(&self) -> &[[u32; 3]] {
        &self.surface_triangles
    }

    /// The FEM data.
    pub fn fem(&self) -> &FemModel {
        &self.fem
    }

    /// The condensed solver of a scene with `[active_region]`.
    pub fn condensed(&self) -> Option<&CondensedSolver> {
        self.condensed.as_ref()
    }

    /// With an active region: moves the condensed (far) nodes to the static response of the
    /// far body to the interface, which the tick leaves at their last recovered positions (one
    /// sparse solve, allocates: not for the servo tick). No-op otherwise.
    pub fn recover_far_field(&mut self) {
        if let Some(c) = &self.condensed {
            c.recover_far_field(&mut self.state.x);
        }
    }

    /// The dynamic state.
    pub fn state(&self) -> &SimState {
        &self.state
    }

    /// Mutable state, for tests and set-ups (e.g. imposing an initial deformation). Forgets
    /// the backward Euler warm start and a recorded divergence.
    pub fn state_mut(&mut self) -> &mut SimState {
        if let Some(s) = &mut self.implicit {
            s.reset_warm_start();
        }
        self.diverged_at_s = None;
        &mut self.state
    }

    /// Sub-step plan.
    pub fn plan(&self) -> StepPlan {
        self.plan
    }

    /// Integrator in use.
    pub fn integrator(&self) -> IntegratorKind {
        self.kind
    }

    /// Servo tick, s.
    pub fn tick_s(&self) -> f64 {
        self.tick_s
    }

    /// Probe radius, m.
    pub fn probe_radius_m(&self) -> f64 {
        self.probe.params.radius_m
    }

    /// Scene name.
    pub fn scene_name(&self) -> &str {
        &self.scene_name
    }

    /// The output of the last successful tick.
    pub fn last_output(&self) -> TickOutput {
        self.last_output
    }
}

/// Checks a point load's numbers (see [`Simulation::add_point_load`]).
///
/// # Errors
/// [`ModelError::InvalidInput`] saying which value is wrong.
pub fn validate_point_load(
    point_m: DVec3,
    force_n: DVec3,
    duration_s: f64,
) -> Result<(), ModelError> {
    if !point_m.is_finite() {
        return Err(ModelError::InvalidInput("point_m is not finite".into()));
    }
    if !force_n.is_finite() {
        return Err(ModelError::InvalidInput("force_n is not finite".into()));
    }
    if !duration_s.is_finite() || duration_s <= 0.0 || duration_s > MAX_POINT_LOAD_DURATION_S {
        return Err(ModelError::InvalidInput(format!(
            "duration_s = {duration_s} must be in (0, {MAX_POINT_LOAD_DURATION_S}] s"
        )));
    }
    if force_n.length() > MAX_POINT_FORCE_N {
        return Err(ModelError::InvalidInput(format!(
            "|force_n| = {:.3} N exceeds the {MAX_POINT_FORCE_N} N limit",
            force_n.length()
        )));
    }
    if point_m.abs().max_element() > MAX_DEVICE_DISTANCE_M {
        return Err(ModelError::InvalidInput(format!(
            "point_m {point_m} is absurdly far from the scene"
        )));
    }
    Ok(())
}

/// The state-independent part of the scene loads on nodes with rest positions `rest` and
/// lumped masses `mass_kg`: gravity, dead pressure (rest geometry) and point forces. Empty
/// when the scene has none of them.
fn constant_external_forces(scene: &Scene, rest: &[DVec3], mass_kg: &[f64]) -> Vec<DVec3> {
    let l = &scene.loads;
    if l.gravity_m_per_s2 == DVec3::ZERO
        && l.point.is_empty()
        && l.pressure.iter().all(|p| p.follower)
    {
        return Vec::new();
    }
    let mut f: Vec<DVec3> = mass_kg.iter().map(|m| l.gravity_m_per_s2 * *m).collect();
    for p in l.pressure.iter().filter(|p| !p.follower) {
        crate::statics::add_pressure_forces(&p.triangles, rest, p.pressure_pa, &mut f);
    }
    for p in &l.point {
        for k in 0..3 {
            f[p.nodes[k] as usize] += p.force_n * p.bary[k];
        }
    }
    f
}

/// External nodal forces (N, one per mesh node) of the scene's loads at positions `x` (m), for
/// static solves: gravity on the lumped masses, dead pressure on the rest geometry, follower
/// pressure on `x`, point forces. The same forces [`Simulation::tick`] applies.
///
/// # Panics
/// If `x` is shorter than the mesh's node count.
pub fn static_external_forces(scene: &Scene, x: &[DVec3]) -> Vec<DVec3> {
    let mesh = &scene.mesh;
    let mass = crate::fem::lumped_masses(mesh, scene.material.density_kg_per_m3);
    let mut f = constant_external_forces(scene, &mesh.nodes, &mass);
    if f.is_empty() {
        f = vec![DVec3::ZERO; mesh.nodes.len()];
    }
    for p in scene.loads.pressure.iter().filter(|p| p.follower) {
        crate::statics::add_pressure_forces(&p.triangles, x, p.pressure_pa, &mut f);
    }
    f
}
