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
//! - original nodes keep position and velocity (with [`VertexRule::Loop`] they keep their
//!   displacement from their moved rest position); a node whose mass changes keeps its
//!   velocity when it gets lighter and its momentum when it gets heavier, so no node gains
//!   kinetic energy;
//! - a new type-2 node takes Loop's edge rule for its rest position and the mean displacement
//!   and velocity of its edge's end points (the deformed surface under the probe stays where
//!   it was);
//! - masses follow eq. 3 (`m' = m N / N'` over the subdivided area), damping `K_d m' / m`;
//! - if the event still raised the total energy (the subdivided area can store more elastic
//!   energy in the same shape), the velocities of the nodes it touched are scaled down by the
//!   excess; what kinetic energy cannot cover is counted in [`EventStats::injected_energy_j`].
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

use glam::DVec3;

use super::calibration::CalibrationTable;
use super::contact_rest::contact_rest_positions;
use super::loop_rules::loop_rest_positions;
use super::mixed::MixedMesh;
use super::network::{Spring, critical_time_step_s, gershgorin_bound_per_s2};
use super::organ::OrganTable;
use super::organ::foot::{RestFoot, foot_depth_m, rest_foot};
use super::refine::{NO_OWNER, Refinement};
use super::surface::SpringSurface;
use super::{MassSpringParams, SpringRule, VertexRule, prefaulted};
use crate::ModelError;
use crate::body::{
    BodyInfo, BodyStats, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput, TickOutput,
};
use crate::contact::{ContactModel, Probe, ProbeParams};
use crate::integrate::{IntegratorKind, IntegratorParams, StepPlan, plan_steps};
use crate::loads::{BodyLoads, SceneLoads};

/// Most centres (subdivided areas) at a time: the contact node and former contact nodes still
/// within their coarsening delay. A new centre beyond it replaces the oldest.
pub const MAX_CENTRES: usize = 8;

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

/// The mass-spring body (module documentation).
#[derive(Debug, Clone)]
pub struct MassSpringBody {
    surface: SpringSurface,
    params: MassSpringParams,
    table: Option<CalibrationTable>,
    /// The labels (levels, owners) for the current centres.
    refinement: Refinement,
    /// The springs, triangles and active nodes for those labels (the probe's contact surface
    /// holds the triangles over slots).
    mesh: MixedMesh,
    /// Loop rest positions per coarse node (type-1; a type-2 node's, Loop's edge rule, is its
    /// slot's entry of `rest`).
    loop_vertex_rest: Vec<DVec3>,
    // Per slot (coarse nodes, then one per coarse edge).
    rest: Vec<DVec3>,
    /// Where the probe meets each slot at rest ([`super::contact_rest`]); at run time the probe
    /// sees `cx = x + contact_rest - rest`.
    contact_rest: Vec<DVec3>,
    cx: Vec<DVec3>,
    x: Vec<DVec3>,
    v: Vec<DVec3>,
    f: Vec<DVec3>,
    mass: Vec<f64>,
    damping: Vec<f64>,
    fixed: Vec<bool>,
    /// The centre slot whose area each slot belongs to ([`NO_OWNER`]: none), as built: equal
    /// to the refinement's labels except inside an event.
    owner: Vec<u8>,
    centres: [Centre; MAX_CENTRES],
    centre_count: usize,
    /// Per centre: `K'_h` and `K'_m` now, N/m.
    kh_area: [f64; MAX_CENTRES],
    km_area: [f64; MAX_CENTRES],
    probe: Probe,
    /// The organ table ([`super::organ`]) and the contact factor `beta` every spring constant
    /// is multiplied by now (1 without a table; kept when the probe leaves).
    organ: Option<OrganTable>,
    contact_factor: f64,
    /// The probe's sphere depth at the last sub-step in contact, m (see
    /// [`MassSpringBody::contact_depth_m`]).
    contact_depth_m: f64,
    /// The probe's foot on the coarse rest surface ([`super::organ::foot`]), where the organ
    /// table is read; `None` out of contact, without a table or off the surface.
    foot: Option<RestFoot>,
    /// Whether a sub-step of this tick already searched the foot (at most one search per
    /// tick besides the end-of-tick update).
    foot_searched: bool,
    /// The worst-case Gershgorin bound with constant springs (1/s^2) and the integrator
    /// settings: the plan is recomputed with the organ table's largest factor.
    worst_lambda_per_s2: f64,
    integrator: IntegratorParams,
    loads: BodyLoads,
    plan: StepPlan,
    coarse_critical_dt_s: f64,
    tick_s: f64,
    time_s: f64,
    diverged_at_s: Option<f64>,
    version: u64,
    stats: EventStats,
    // Event scratch: the labels before the event, the region it can change (coarse nodes,
    // triangles and edges, with stamps against repeats), the nodes whose state it changed.
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
    scene_name: String,
}

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
        let sub = params.subdivision;
        let needs_table = sub.rings > 0 && sub.springs == SpringRule::Calibrated;
        let table = if needs_table {
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
            Some(t)
        } else {
            None
        };
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
        let m = params.node_mass_kg;
        let mut fixed: Vec<bool> = (0..nc as u32).map(|i| surface.is_fixed(i)).collect();
        fixed.extend(
            surface
                .edges()
                .iter()
                .map(|&[a, b]| surface.is_fixed(a) && surface.is_fixed(b)),
        );
        let refinement = Refinement::new(&surface);
        let mut probe = Probe::new(probe, surface.triangles().to_vec(), &rest);
        let (mesh, contact_surface) = MixedMesh::new(&surface, &rest);
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
        // Stability: the coarse bound, and the worst case over every refinement.
        let kh = params.home_spring_n_per_m;
        let km = params.mesh_spring_n_per_m;
        let mut diag = vec![0.0; ns];
        let mut off = vec![0.0; ns];
        let coarse_lambda = gershgorin_bound_per_s2(
            &vec![kh; nc],
            &vec![m; nc],
            &fixed[..nc],
            surface.edges().iter().map(|&[a, b]| (a, b, km)),
            &mut diag,
            &mut off,
        );
        let coarse_critical_dt_s = critical_time_step_s(coarse_lambda);
        let worst_lambda = if sub.rings == 0 {
            coarse_lambda
        } else {
            let a_max = table.as_ref().map_or(1.0, |t| t.max_scale());
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
                .map(|i| {
                    node_bound(f64::from(surface.valence(i)) + surface.triangles_at(i).len() as f64)
                })
                .fold(0.0, f64::max);
            coarse_worst.max(node_bound(6.0)).max(coarse_lambda)
        };
        let worst_dt = critical_time_step_s(worst_lambda);
        let plan = plan_steps(integrator, worst_dt)?;
        Ok(Self {
            loop_vertex_rest,
            x: rest.clone(),
            cx: contact_rest.clone(),
            contact_rest,
            v: vec![DVec3::ZERO; ns],
            f: vec![DVec3::ZERO; ns],
            mass: vec![m; ns],
            damping: prefaulted(params.damping_n_s_per_m, ns),
            fixed,
            owner: vec![NO_OWNER; ns],
            centres: [Centre {
                node: 0,
                last_contact_s: 0.0,
            }; MAX_CENTRES],
            centre_count: 0,
            kh_area: [kh; MAX_CENTRES],
            km_area: [km; MAX_CENTRES],
            probe,
            organ: None,
            contact_factor: 1.0,
            contact_depth_m: 0.0,
            foot: None,
            foot_searched: false,
            worst_lambda_per_s2: worst_lambda,
            integrator: *integrator,
            loads,
            plan,
            coarse_critical_dt_s,
            tick_s: integrator.tick_s,
            time_s: 0.0,
            diverged_at_s: None,
            version: 0,
            stats: EventStats::default(),
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
            scratch_a: diag,
            scratch_b: off,
            scene_name: scene_name.to_string(),
            rest,
            refinement,
            mesh,
            table,
            params: *params,
            surface,
        })
    }

    /// The body with the organ table `table` ([`super::organ`]): every spring constant is then
    /// multiplied by the contact factor the table gives at the probe's sphere depth and contact
    /// point. The sub-step plan is recomputed with the table's largest factor.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`mass_spring.organ_file`) for a table of another node count;
    /// [`ModelError::Unstable`] when the stiffest factor needs more than
    /// `integrator.max_substeps`.
    pub fn with_organ_table(mut self, table: OrganTable) -> Result<Self, ModelError> {
        if (table.node_count(), table.edge_count())
            != (self.surface.node_count(), self.surface.edge_count())
        {
            return Err(ModelError::field(
                "mass_spring.organ_file",
                format!(
                    "the organ table covers {} nodes and {} edges, the surface has {} and {}",
                    table.node_count(),
                    table.edge_count(),
                    self.surface.node_count(),
                    self.surface.edge_count()
                ),
            ));
        }
        let beta_max = table.max_factor().max(1.0);
        self.plan = plan_steps(
            &self.integrator,
            critical_time_step_s(self.worst_lambda_per_s2 * beta_max),
        )?;
        self.organ = Some(table);
        Ok(self)
    }

    /// The organ table, if any.
    pub fn organ_table(&self) -> Option<&OrganTable> {
        self.organ.as_ref()
    }

    /// The probe's sphere depth, m, at the last sub-step in contact (the key of the organ
    /// table, [`super::organ`]): when the probe's foot ([`super::organ::foot`]) lies on a
    /// rest triangle with a corner in a subdivided area, the sphere's depth below that flat
    /// triangle along the line through the proxy along the contact normal; elsewhere the travel
    /// of the probe's kernel plane from its rest position, `sum w_i (rest_i - x_i) . n` over
    /// its patch.
    pub fn contact_depth_m(&self) -> f64 {
        self.contact_depth_m
    }

    /// The contact factor every spring constant is multiplied by now ([`super::organ`]).
    pub fn contact_factor(&self) -> f64 {
        self.contact_factor
    }

    /// The probe's sphere depth ([`MassSpringBody::contact_depth_m`]: below the flat rest
    /// triangle at the foot in a subdivided area, the kernel plane's travel elsewhere) and the
    /// contact factor at its current contact: the organ table at that depth, interpolated on the
    /// coarse surface at the foot of the kernel patch's centroid
    /// ([`MassSpringBody::patch_foot`]), in a subdivided area at the probe's foot on the coarse
    /// rest surface ([`super::organ::foot`]: where the calibration pressed, so a press along a
    /// site's normal reads that site's row at any depth), over its coarse
    /// triangle's four Loop children (corners: nodes and edge midpoints, the table's sites);
    /// each site's coarse factor, or its subdivided one when it lies in a subdivided area. Off
    /// the rest surface (no foot), at the contact point of the deformed surface (the probe's
    /// triangle). Unchanged out of contact; the factor
    /// unchanged without a table. Allocation-free.
    fn update_contact_factor(&mut self) {
        let st = self.probe.state;
        if !st.in_contact {
            return;
        }
        self.update_foot();
        // In a subdivided area the depth below the flat rest triangle at the foot (the
        // subdivided patch's kernel plane sits lower at rest than the coarse one's); elsewhere
        // the kernel plane's travel (which follows the organ's surface between nodes).
        let foot_in_area = self.foot.filter(|f| {
            self.surface.triangles()[f.triangle as usize]
                .iter()
                .any(|&s| self.owner[s as usize] != NO_OWNER)
        });
        let depth = match &foot_in_area {
            Some(foot) => foot_depth_m(foot, self.probe.params.radius_m),
            None => {
                let (nodes, weights) = self.probe.patch();
                nodes
                    .iter()
                    .zip(weights)
                    .map(|(&i, &w)| w * (self.rest[i as usize] - self.x[i as usize]).dot(st.normal))
                    .sum()
            }
        };
        self.contact_depth_m = depth;
        let Some(table) = &self.organ else {
            return;
        };
        // On the coarse surface at the patch's centroid ([`MassSpringBody::patch_foot`]); in a
        // subdivided area at the proxy's foot.
        let at = match foot_in_area {
            Some(_) => self.foot,
            None => self.patch_foot().or(self.foot),
        };
        let (tri, b) = match at {
            Some(foot) => (self.surface.triangles()[foot.triangle as usize], foot.bary),
            None => match self.probe.surface.triangles.get(st.triangle as usize) {
                Some(&tri) => (tri, st.bary),
                None => return,
            },
        };
        let nc = self.surface.node_count() as u32;
        // A site of a subdivided area takes the subdivided configuration's factor.
        let site = |s: u32| table.factor(s, depth, self.owner[s as usize] != NO_OWNER);
        let beta = if tri.iter().all(|&s| s < nc) {
            // A coarse triangle: linear over its four Loop children (corner i's child where
            // b_i >= 1/2, else the middle one), whose corners are nodes and edge midpoints.
            let edge = |i: usize| {
                self.surface
                    .edge_between(tri[i], tri[(i + 1) % 3])
                    .map_or(0.5 * (site(tri[i]) + site(tri[(i + 1) % 3])), |e| {
                        site(nc + e)
                    })
            };
            // m[i]: the factor at the midpoint of side (i, i + 1).
            let m = [edge(0), edge(1), edge(2)];
            match (0..3).find(|&i| b[i] >= 0.5) {
                Some(i) => {
                    let (j, k) = ((i + 1) % 3, (i + 2) % 3);
                    (2.0 * b[i] - 1.0) * site(tri[i]) + 2.0 * b[j] * m[i] + 2.0 * b[k] * m[k]
                }
                None => {
                    (1.0 - 2.0 * b[2]) * m[0]
                        + (1.0 - 2.0 * b[0]) * m[1]
                        + (1.0 - 2.0 * b[1]) * m[2]
                }
            }
        } else {
            tri.iter().zip(&b).map(|(&s, &w)| w * site(s)).sum()
        };
        if beta.is_finite() && beta > 0.0 {
            self.contact_factor = beta;
        }
    }

    /// Where the organ table is read ([`super::organ::foot`], session 6): the foot on the coarse
    /// rest surface of the probe's patch centroid at rest, `sum w_j rest_j` over the patch's
    /// slots, along the contact normal. The patch carries the force: on `hemisphere-springs`
    /// (8 mm edges under a 4 mm sphere) a press between nodes bears on the nearest node almost
    /// alone (3 mm from node 13 at the point `h1`: its weight 0.987), as a press on that node
    /// does, and reads that node's row, not the mean of its edges' (about half a node's) that
    /// the proxy's foot gave; on a node, an edge's midpoint (equal weights on its ends) and a
    /// symmetric patch it is the proxy's foot, as the calibration pressed. Continuous as the
    /// weights are. `None` without a foot (then the proxy's foot or the contact triangle).
    /// Allocation-free.
    fn patch_foot(&self) -> Option<RestFoot> {
        let hint = self.foot?.triangle;
        let (nodes, weights) = self.probe.patch();
        if nodes.is_empty() {
            return None;
        }
        let centre: DVec3 = nodes
            .iter()
            .zip(weights)
            .map(|(&i, &w)| self.rest[i as usize] * w)
            .sum();
        let m = self.probe.state.normal;
        let r = self.probe.params.radius_m;
        rest_foot(&self.surface, centre + m * r, m, r, r, Some(hint))
            .filter(|h| h.miss_m <= r)
            .map(|h| h.foot)
    }

    /// The probe's foot on the coarse rest surface ([`super::organ::foot`]) from its state now:
    /// searched around the last foot's triangles, over the whole surface at a first contact (at
    /// most once a tick while none is found); `None` when the line through the proxy along the
    /// normal meets no rest triangle within a probe radius of where the centre should be.
    /// Allocation-free.
    fn update_foot(&mut self) {
        let hint = self.foot.map(|f| f.triangle);
        if hint.is_none() {
            if self.foot_searched {
                return;
            }
            self.foot_searched = true;
        }
        let st = self.probe.state;
        let r = self.probe.params.radius_m;
        let expected = if hint.is_some() {
            r - self.contact_depth_m
        } else {
            r
        };
        self.foot = rest_foot(&self.surface, st.proxy_m, st.normal, expected, r, hint)
            .filter(|f| f.miss_m <= r)
            .map(|f| f.foot);
    }

    /// `K'_h` and `K'_m` of each centre's area at the current state (section 3.2.4: the table
    /// at the centre's displacement over L; the coarse constants with
    /// [`SpringRule::Unchanged`]; eq. 5 with [`SpringRule::Area`]).
    fn update_area_constants(&mut self) {
        let kh = self.params.home_spring_n_per_m;
        let ratio = match self.params.subdivision.springs {
            SpringRule::Calibrated => self.params.subdivision.km_over_kh_after,
            SpringRule::Unchanged => self.params.mesh_spring_n_per_m / kh,
            SpringRule::Area => {
                // Eq. 5 over the areas (as the masses of eq. 3), the mesh springs unchanged.
                let (n1, n2) = (self.refinement.type1_count(), self.refinement.type2_count());
                let n_ratio = if n1 + n2 > 0 {
                    n1 as f64 / (n1 + n2) as f64
                } else {
                    1.0
                };
                for k in 0..self.centre_count {
                    self.kh_area[k] = kh * n_ratio;
                    self.km_area[k] = self.params.mesh_spring_n_per_m;
                }
                return;
            }
        };
        for k in 0..self.centre_count {
            let c = self.centres[k].node;
            let a = match &self.table {
                Some(t) => {
                    let u = (self.x[c as usize] - self.rest[c as usize]).length();
                    t.scale(c, u / self.surface.element_size_m(c))
                }
                None => 1.0,
            };
            self.kh_area[k] = a * kh;
            self.km_area[k] = ratio * a * kh;
        }
    }

    #[inline]
    fn home_constant(&self, s: u32) -> f64 {
        self.contact_factor
            * match self.owner[s as usize] {
                NO_OWNER => self.params.home_spring_n_per_m,
                o => self.kh_area[o as usize],
            }
    }

    #[inline]
    fn spring_constant(&self, owner: u8) -> f64 {
        self.contact_factor
            * match owner {
                NO_OWNER => self.params.mesh_spring_n_per_m,
                o => self.km_area[o as usize],
            }
    }

    /// Total energy, J: kinetic `sum m v^2 / 2` plus elastic (home and mesh springs, eq. 2)
    /// over the current mesh with the current constants. Allocation-free.
    pub fn energy_j(&self) -> f64 {
        let mut e = 0.0;
        for &s in self.mesh.active() {
            e += self.node_energy_j(s);
        }
        for k in 0..self.mesh.springs().len() {
            e += self.spring_energy_j(k);
        }
        e
    }

    /// Kinetic and home-spring energy of slot `s`, J.
    #[inline]
    fn node_energy_j(&self, s: u32) -> f64 {
        let i = s as usize;
        0.5 * self.mass[i] * self.v[i].length_squared()
            + 0.5 * self.home_constant(s) * (self.x[i] - self.rest[i]).length_squared()
    }

    /// Elastic energy of mesh spring `k`, J.
    #[inline]
    fn spring_energy_j(&self, k: usize) -> f64 {
        let sp = &self.mesh.springs()[k];
        let stretch = (self.x[sp.j as usize] - self.x[sp.i as usize]).length() - sp.rest_length_m;
        0.5 * self.spring_constant(sp.owner) * stretch * stretch
    }

    /// Kinetic energy over the active nodes, J.
    pub fn kinetic_energy_j(&self) -> f64 {
        self.mesh
            .active()
            .iter()
            .map(|&s| 0.5 * self.mass[s as usize] * self.v[s as usize].length_squared())
            .sum()
    }

    /// Total mass of the active nodes, kg (eq. 3 keeps it constant).
    pub fn total_mass_kg(&self) -> f64 {
        self.mesh
            .active()
            .iter()
            .map(|&s| self.mass[s as usize])
            .sum()
    }

    /// Recomputes the refinement's labels for the current centres, edits the mesh where they
    /// changed and carries the state over (module documentation). O(areas before and after),
    /// allocation-free.
    fn event(&mut self, added: bool, removed: bool) {
        // 1. The labels before, then the new ones.
        self.old_region.clear();
        self.old_region.extend_from_slice(self.refinement.region());
        self.old_edges.clear();
        self.old_edges
            .extend_from_slice(self.refinement.active_edges());
        self.old_type1.clear();
        self.old_type1
            .extend_from_slice(self.refinement.type1_nodes());
        self.refinement.begin();
        let rings = self.params.subdivision.rings;
        for k in 0..self.centre_count {
            self.refinement
                .request_ring(&self.surface, self.centres[k].node, rings, k as u8);
        }
        self.refinement.finish(&self.surface);
        // 2. Where the event can change the energy, and the energy there before.
        self.collect_region();
        let energy_before = self.region_energy_j();
        let contact_triangle = self
            .probe
            .state
            .in_contact
            .then(|| self.mesh.coarse_triangle_of(self.probe.state.triangle));
        // 3. The nodes of the areas before and after: masses, rest positions, velocities.
        self.carry_state();
        // 4. The mesh: triangles and edges whose state changed, then the rest lengths and owners
        // of every spring in the region (the Loop rule moves rest positions). What the last
        // event appended (triangles, then edges) is visited in reverse first, so that removing
        // an area removes from the ends of the lists (nothing to move into the holes).
        self.mesh.begin();
        for &e in self.old_edges.iter().rev() {
            self.mesh.update_edge(&self.surface, &self.refinement, e);
        }
        for &t in self.old_region.iter().rev().chain(self.refinement.region()) {
            self.mesh
                .update_triangle(&self.surface, &self.refinement, &mut self.probe.surface, t);
        }
        for &e in self.refinement.active_edges() {
            self.mesh.update_edge(&self.surface, &self.refinement, e);
        }
        for &t in &self.region_tris {
            self.mesh
                .refresh_triangle(&self.refinement, t, &self.rest, &self.owner);
        }
        for &e in &self.region_edges {
            self.mesh.refresh_edge(e, &self.rest, &self.owner);
        }
        self.mesh.finish(&self.surface, &self.probe.surface);
        self.version += 1;
        self.update_area_constants();
        // 5. No energy from the event: drain the touched nodes' kinetic energy by the excess.
        let energy_after = self.region_energy_j();
        let excess = energy_after - energy_before;
        if excess > 0.0 {
            let ke: f64 = self
                .touched_list
                .iter()
                .map(|&s| 0.5 * self.mass[s as usize] * self.v[s as usize].length_squared())
                .sum();
            let drained = excess.min(ke);
            if ke > 0.0 {
                let scale = ((ke - drained) / ke).max(0.0).sqrt();
                for &s in &self.touched_list {
                    self.v[s as usize] *= scale;
                }
            }
            self.stats.drained_energy_j += drained;
            let injected = excess - drained;
            if injected > 0.0 {
                self.stats.injected_energy_j += injected;
                self.stats.max_injected_energy_j = self.stats.max_injected_energy_j.max(injected);
            }
        }
        for &s in &self.touched_list {
            self.touched[s as usize] = false;
        }
        self.touched_list.clear();
        // 6. The probe's contact triangle index refers to the old triangles: walk from a piece
        // of the coarse triangle it was in (over the new slots' contact positions).
        self.update_contact_positions();
        if let Some(t) = contact_triangle {
            let st = self.probe.state;
            let point = st.proxy_m - st.normal * self.probe.params.radius_m;
            let sp = self.probe.surface.closest_local(&self.cx, point, t, 16);
            self.probe.state.triangle = sp.triangle;
        }
        self.stats.events += 1;
        self.stats.subdivisions += u64::from(added);
        self.stats.coarsenings += u64::from(removed);
    }

    /// The region an event can change: the split and cut triangles before and after it, their
    /// coarse nodes (type-1 nodes, crack-filling ends) and edges; with [`VertexRule::Loop`]
    /// (which moves the rest positions of type-1 nodes) also every coarse triangle around those
    /// nodes. Every mesh spring and node whose energy the event changes is in it.
    fn collect_region(&mut self) {
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.node_stamp.fill(0);
            self.tri_stamp.fill(0);
            self.edge_stamp.fill(0);
            self.stamp = 1;
        }
        let stamp = self.stamp;
        self.region_nodes.clear();
        self.region_tris.clear();
        self.region_edges.clear();
        let surface = &self.surface;
        for &t in self.old_region.iter().chain(self.refinement.region()) {
            if self.tri_stamp[t as usize] == stamp {
                continue;
            }
            self.tri_stamp[t as usize] = stamp;
            self.region_tris.push(t);
            for &i in &surface.triangles()[t as usize] {
                if self.node_stamp[i as usize] != stamp {
                    self.node_stamp[i as usize] = stamp;
                    self.region_nodes.push(i);
                }
            }
        }
        if self.params.subdivision.vertex_rule == VertexRule::Loop {
            for &i in &self.region_nodes {
                for &t in surface.triangles_at(i) {
                    if self.tri_stamp[t as usize] != stamp {
                        self.tri_stamp[t as usize] = stamp;
                        self.region_tris.push(t);
                    }
                }
            }
        }
        for &t in &self.region_tris {
            for e in surface.triangle_edges(t) {
                if self.edge_stamp[e as usize] != stamp {
                    self.edge_stamp[e as usize] = stamp;
                    self.region_edges.push(e);
                }
            }
        }
    }

    /// Total energy (as [`MassSpringBody::energy_j`]) of the region's nodes and springs, J:
    /// what an event changes of the total.
    fn region_energy_j(&self) -> f64 {
        let nc = self.surface.node_count() as u32;
        let mut e = 0.0;
        for &i in &self.region_nodes {
            e += self.node_energy_j(i);
        }
        for &edge in &self.region_edges {
            if self.mesh.is_edge_split(edge) {
                e += self.node_energy_j(nc + edge);
            }
            self.mesh
                .edge_springs(edge, |k| e += self.spring_energy_j(k));
        }
        for &t in &self.region_tris {
            self.mesh
                .triangle_springs(t, |k| e += self.spring_energy_j(k));
        }
        e
    }

    /// Carries the state of the nodes of the areas before and after the event over to the new
    /// labels (module documentation): masses (eq. 3), damping, rest positions of the original
    /// nodes, velocities; new type-2 nodes interpolated; the owners. Marks what it changed in
    /// `touched`.
    fn carry_state(&mut self) {
        let nc = self.surface.node_count() as u32;
        let m = self.params.node_mass_kg;
        let (n1, n2) = (self.refinement.type1_count(), self.refinement.type2_count());
        let m_area = if n1 + n2 > 0 {
            m * n1 as f64 / (n1 + n2) as f64
        } else {
            m
        };
        let kd_per_kg = self.params.damping_n_s_per_m / m;
        let loop_rule = self.params.subdivision.vertex_rule == VertexRule::Loop;
        // Original nodes first (a new type-2 node interpolates its ends' new state). A node in
        // both lists is carried once: the second visit finds nothing to change.
        for &i in self.old_type1.iter().chain(self.refinement.type1_nodes()) {
            let i = i as usize;
            let area = self.refinement.node_owner(i as u32) != NO_OWNER;
            let mass = if area { m_area } else { m };
            let mut touched = false;
            if loop_rule {
                let new_rest = if area && !self.fixed[i] {
                    self.loop_vertex_rest[i]
                } else {
                    self.surface.rest()[i]
                };
                if new_rest != self.rest[i] {
                    self.x[i] += new_rest - self.rest[i];
                    self.rest[i] = new_rest;
                    touched = true;
                }
            }
            if mass != self.mass[i] {
                self.v[i] *= (self.mass[i] / mass).min(1.0);
                self.mass[i] = mass;
                self.damping[i] = kd_per_kg * mass;
                touched = true;
            }
            if touched && !self.touched[i] {
                self.touched[i] = true;
                self.touched_list.push(i as u32);
            }
        }
        // Type-2 nodes: new ones interpolated, persisting ones keep their state.
        for &e in self.old_edges.iter().chain(self.refinement.active_edges()) {
            let s = (nc + e) as usize;
            let now = self.refinement.is_edge_split(e);
            let was = self.mesh.is_edge_split(e);
            let mass = if now { m_area } else { m };
            let mut touched = false;
            if now && !was && !self.touched[s] {
                let [a, b] = self.surface.edges()[e as usize].map(|i| i as usize);
                let u = 0.5 * ((self.x[a] - self.rest[a]) + (self.x[b] - self.rest[b]));
                if self.fixed[s] {
                    self.x[s] = self.rest[s];
                    self.v[s] = DVec3::ZERO;
                } else {
                    self.x[s] = self.rest[s] + u;
                    self.v[s] = 0.5 * (self.v[a] + self.v[b]);
                }
                touched = true;
            } else if now && was && mass != self.mass[s] {
                self.v[s] *= (self.mass[s] / mass).min(1.0);
                touched = true;
            } else if !now {
                self.v[s] = DVec3::ZERO;
            }
            self.mass[s] = mass;
            self.damping[s] = kd_per_kg * mass;
            if touched && !self.touched[s] {
                self.touched[s] = true;
                self.touched_list.push(s as u32);
            }
        }
        // Owners, as labelled.
        for &i in self.old_type1.iter().chain(self.refinement.type1_nodes()) {
            self.owner[i as usize] = self.refinement.node_owner(i);
        }
        for &e in self.old_edges.iter().chain(self.refinement.active_edges()) {
            self.owner[(nc + e) as usize] = self.refinement.node_owner(nc + e);
        }
    }

    /// The coarse node nearest the probe's contact point among the coarse vertices of the
    /// triangle it touches (the contact node C of the paper), if it is free.
    fn contact_node(&self) -> Option<u32> {
        let st = self.probe.state;
        if !st.in_contact {
            return None;
        }
        let point = st.proxy_m - st.normal * self.probe.params.radius_m;
        let nc = self.surface.node_count() as u32;
        let tri = *self.probe.surface.triangles.get(st.triangle as usize)?;
        let mut best: Option<(f64, u32)> = None;
        for s in tri {
            let parents = if s < nc {
                [s, s]
            } else {
                self.surface.edges()[(s - nc) as usize]
            };
            for p in parents {
                if self.fixed[p as usize] {
                    continue;
                }
                let d = (self.cx[p as usize] - point).length_squared();
                if best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, p));
                }
            }
        }
        best.map(|b| b.1)
    }

    /// Updates the centres from the contact (touched now: refreshed or added; untouched for
    /// longer than the delay: removed) and runs an event when they changed.
    fn update_centres(&mut self) {
        if self.params.subdivision.rings == 0 {
            return;
        }
        let now = self.time_s;
        let mut added = false;
        if let Some(c) = self.contact_node() {
            match self.centres[..self.centre_count]
                .iter_mut()
                .find(|k| k.node == c)
            {
                Some(k) => k.last_contact_s = k.last_contact_s.max(now),
                None => {
                    if self.centre_count == MAX_CENTRES {
                        // Replace the one touched longest ago.
                        let oldest = (0..MAX_CENTRES)
                            .min_by(|&a, &b| {
                                self.centres[a]
                                    .last_contact_s
                                    .total_cmp(&self.centres[b].last_contact_s)
                            })
                            .unwrap_or(0);
                        self.centres[oldest] = Centre {
                            node: c,
                            last_contact_s: now,
                        };
                    } else {
                        self.centres[self.centre_count] = Centre {
                            node: c,
                            last_contact_s: now,
                        };
                        self.centre_count += 1;
                    }
                    added = true;
                }
            }
        }
        let delay = self.params.subdivision.coarsen_delay_s;
        let before = self.centre_count;
        let mut k = 0;
        while k < self.centre_count {
            if now - self.centres[k].last_contact_s > delay && self.area_is_quiet(k) {
                self.centre_count -= 1;
                self.centres[k] = self.centres[self.centre_count];
            } else {
                k += 1;
            }
        }
        let removed = self.centre_count < before;
        if added || removed {
            self.event(added, removed);
        }
    }

    /// Whether every node of centre `k`'s area (its rings' coarse nodes and their type-2
    /// nodes) is within [`QUIET_DISPLACEMENT_OVER_L`] of its rest position. O(area),
    /// allocation-free.
    fn area_is_quiet(&mut self, k: usize) -> bool {
        let c = self.centres[k].node;
        let limit = QUIET_DISPLACEMENT_OVER_L * self.surface.element_size_m(c);
        let limit2 = limit * limit;
        let rings = self.params.subdivision.rings;
        let mut ring = std::mem::take(&mut self.ring);
        self.surface.ring(c, rings, &mut self.ring_dist, &mut ring);
        let nc = self.surface.node_count() as u32;
        let moved = |s: u32| (self.x[s as usize] - self.rest[s as usize]).length_squared() > limit2;
        let quiet = ring.iter().all(|&(i, _)| {
            !moved(i)
                && self
                    .surface
                    .incident_edges(i)
                    .iter()
                    .all(|&e| !self.refinement.is_edge_split(e) || !moved(nc + e))
        });
        self.ring = ring;
        quiet
    }

    /// Subdivides around the coarse nodes `nodes` (replacing every current area; they stay
    /// subdivided until [`MassSpringBody::coarsen`]): a subdivision event, for tests, tools and
    /// the calibration experiment. At most [`MAX_CENTRES`] nodes are taken; fixed ones and
    /// nodes out of range are skipped. Allocation-free.
    pub fn subdivide_around(&mut self, nodes: &[u32]) {
        self.centre_count = 0;
        for &c in nodes.iter().take(MAX_CENTRES) {
            if (c as usize) < self.surface.node_count() && !self.surface.is_fixed(c) {
                self.centres[self.centre_count] = Centre {
                    node: c,
                    last_contact_s: f64::INFINITY,
                };
                self.centre_count += 1;
            }
        }
        self.event(true, false);
    }

    /// Coarsens every subdivided area: back to the coarse mesh (an event). Allocation-free.
    pub fn coarsen(&mut self) {
        self.centre_count = 0;
        self.event(false, true);
    }

    /// The coarse surface.
    pub fn surface(&self) -> &SpringSurface {
        &self.surface
    }

    /// The current refinement: levels and owners (its [`Refinement::mesh`] lists what
    /// [`MassSpringBody::triangles`] and [`MassSpringBody::springs`] hold).
    pub fn refinement(&self) -> &Refinement {
        &self.refinement
    }

    /// The parameters.
    pub fn params(&self) -> &MassSpringParams {
        &self.params
    }

    /// Active slots (the coarse nodes, then the active type-2 nodes in the order they
    /// appeared): the viewer's vertices.
    pub fn active_nodes(&self) -> &[u32] {
        self.mesh.active()
    }

    /// Triangles of the current mesh over slots, outward oriented: the probe's contact
    /// surface (the pieces of a coarse triangle are not consecutive; as a set they are
    /// [`Refinement::mesh`]'s).
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.probe.surface.triangles
    }

    /// Mesh springs of the current mesh with their rest lengths and current constants (as a
    /// set, [`Refinement::mesh`]'s springs).
    pub fn springs(&self) -> impl Iterator<Item = Spring> + '_ {
        self.mesh.springs().iter().map(|sp| Spring {
            i: sp.i,
            j: sp.j,
            rest_length_m: sp.rest_length_m,
            stiffness_n_per_m: self.spring_constant(sp.owner),
        })
    }

    /// Positions per slot, m (inactive slots hold stale values).
    pub fn positions(&self) -> &[DVec3] {
        &self.x
    }

    /// Velocities per slot, m/s.
    pub fn velocities(&self) -> &[DVec3] {
        &self.v
    }

    /// Rest positions per slot, m.
    pub fn rest_positions(&self) -> &[DVec3] {
        &self.rest
    }

    /// Masses per slot, kg.
    pub fn masses(&self) -> &[f64] {
        &self.mass
    }

    /// Positions and velocities per slot, to set a state (tests, experiments). Fixed nodes
    /// must stay at rest with zero velocity.
    pub fn state_mut(&mut self) -> (&mut [DVec3], &mut [DVec3]) {
        self.diverged_at_s = None;
        (&mut self.x, &mut self.v)
    }

    /// Event counters.
    pub fn event_stats(&self) -> EventStats {
        self.stats
    }

    /// The sub-step plan (from the worst-case Gershgorin bound).
    pub fn plan(&self) -> StepPlan {
        self.plan
    }

    /// Critical time step of the coarse mesh (Gershgorin bound), s.
    pub fn coarse_critical_dt_s(&self) -> f64 {
        self.coarse_critical_dt_s
    }

    /// The current `K'_h` of each centre's area (N/m), in centre order, with the centres'
    /// nodes: for tests and tools.
    pub fn area_home_constants(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        (0..self.centre_count).map(|k| (self.centres[k].node, self.kh_area[k]))
    }

    /// The probe.
    pub fn probe(&self) -> &Probe {
        &self.probe
    }

    /// Advances one servo tick (module documentation).
    ///
    /// # Errors
    /// [`ModelError::InvalidDevice`] for a non-finite or absurd device input (state
    /// untouched); [`ModelError::Diverged`] when the state diverged (then every later tick
    /// too). Allocation-free, also when the tick runs a subdivision event.
    pub fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        input.validate()?;
        if let Some(time_s) = self.diverged_at_s {
            return Err(ModelError::Diverged { time_s });
        }
        let dt = self.plan.sub_dt_s;
        for _ in 0..self.plan.substeps {
            self.update_area_constants();
            // 1. Forces of eq. 2: home springs, mesh springs, point loads.
            for &s in self.mesh.active() {
                let i = s as usize;
                self.f[i] = (self.rest[i] - self.x[i]) * self.home_constant(s);
            }
            for sp in self.mesh.springs() {
                let d = self.x[sp.j as usize] - self.x[sp.i as usize];
                let len = d.length();
                if len > 0.0 {
                    let k = self.spring_constant(sp.owner);
                    let fs = d * (k * (len - sp.rest_length_m) / len);
                    self.f[sp.i as usize] += fs;
                    self.f[sp.j as usize] -= fs;
                }
            }
            self.loads.add_to(&self.x, &mut self.f);
            // 2. Contact: proxy and the explicit part of the coupling's reaction, on the
            // contact positions.
            match input.device_position_m {
                Some(p) => {
                    self.update_contact_positions();
                    self.probe
                        .update(&self.cx, p, input.device_velocity_m_per_s);
                    self.probe.add_reaction(&mut self.f);
                    self.update_contact_factor();
                }
                None => self.probe.release(),
            }
            // 3. Symplectic Euler with implicit damping, then the implicit coupling.
            let mut max_v2: f64 = 0.0;
            for &s in self.mesh.active() {
                let i = s as usize;
                if self.fixed[i] {
                    continue;
                }
                let denom = self.mass[i] + dt * self.damping[i];
                self.v[i] = (self.v[i] * self.mass[i] + self.f[i] * dt) / denom;
                self.x[i] += self.v[i] * dt;
                max_v2 = max_v2.max(self.v[i].length_squared());
            }
            if self.probe.state.in_contact {
                let (mass, damping, fixed) = (&self.mass, &self.damping, &self.fixed);
                self.probe
                    .finish_implicit(dt, &mut self.x, &mut self.v, |i, w| {
                        if fixed[i] {
                            DVec3::ZERO
                        } else {
                            w / (mass[i] + dt * damping[i])
                        }
                    });
                for &i in self.probe.patch().0 {
                    max_v2 = max_v2.max(self.v[i as usize].length_squared());
                }
            }
            if !(max_v2 <= DIVERGENCE_SPEED_M_PER_S * DIVERGENCE_SPEED_M_PER_S) {
                self.diverged_at_s = Some(self.time_s);
                return Err(ModelError::Diverged {
                    time_s: self.time_s,
                });
            }
        }
        self.time_s += self.tick_s;
        self.loads.advance(self.tick_s);
        self.update_contact_positions();
        if !self.probe.state.in_contact {
            self.foot = None;
        }
        self.foot_searched = false;
        // 4. Subdivision around the contact node, coarsening of areas left.
        self.update_centres();
        // 5. Output.
        let contact = self.probe.state;
        Ok(TickOutput {
            force_on_device_n: contact.force_on_device_n,
            in_contact: contact.in_contact,
            proxy_position_m: if contact.in_contact {
                contact.proxy_m
            } else {
                input.device_position_m.unwrap_or(DVec3::ZERO)
            },
            contact_stiffness_n_per_m: self.probe.contact_stiffness(),
            sim_time_s: self.time_s,
        })
    }

    /// The probe's view of the active slots: `cx = x + contact_rest - rest`. O(active),
    /// allocation-free.
    fn update_contact_positions(&mut self) {
        for &s in self.mesh.active() {
            let i = s as usize;
            self.cx[i] = self.x[i] + (self.contact_rest[i] - self.rest[i]);
        }
    }

    /// Contact positions per slot (where the probe meets the surface, m; inactive slots hold
    /// stale values): the positions plus the offsets of [`super::contact_rest`].
    pub fn contact_positions(&self) -> &[DVec3] {
        &self.cx
    }

    /// Largest displacement from rest over the active nodes, m.
    pub fn max_displacement_m(&self) -> f64 {
        self.mesh
            .active()
            .iter()
            .map(|&s| (self.x[s as usize] - self.rest[s as usize]).length_squared())
            .fold(0.0, f64::max)
            .sqrt()
    }

    /// The Gershgorin bound on `M^-1 K` (1/s^2) of the current mesh with the current
    /// constants (the tick's sub-step respects the worst case over all meshes, see
    /// [`MassSpringBody::plan`]). Allocation-free.
    pub fn current_stiffness_bound_per_s2(&mut self) -> f64 {
        let n = self.mass.len();
        let mut home = std::mem::take(&mut self.scratch_home);
        for (s, h) in home.iter_mut().enumerate().take(n) {
            *h = if !self.mesh.is_active(s as u32) {
                0.0
            } else {
                self.home_constant(s as u32)
            };
        }
        let mut diag = std::mem::take(&mut self.scratch_a);
        let mut off = std::mem::take(&mut self.scratch_b);
        let lambda = gershgorin_bound_per_s2(
            &home,
            &self.mass,
            &self.fixed,
            self.mesh
                .springs()
                .iter()
                .map(|sp| (sp.i, sp.j, self.spring_constant(sp.owner))),
            &mut diag,
            &mut off,
        );
        self.scratch_home = home;
        self.scratch_a = diag;
        self.scratch_b = off;
        lambda
    }
}

impl SoftBody for MassSpringBody {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        MassSpringBody::tick(self, input)
    }

    /// Point loads act on the coarse nodes around the point (they survive every event).
    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        self.loads.add_point_load(
            &self.x,
            self.probe.params.radius_m,
            point_m,
            force_n,
            duration_s,
        )
    }

    fn surface_topology(&self) -> SurfaceTopology<'_> {
        SurfaceTopology {
            version: self.version,
            vertex_count: self.mesh.active().len(),
            triangles: self.mesh.view_triangles(),
        }
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        SurfaceCapacity {
            vertices: self.mass.len(),
            triangles: 4 * self.surface.triangle_count(),
        }
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        assert_eq!(
            out.len(),
            3 * self.mesh.active().len(),
            "surface buffer length"
        );
        let mut max_d2: f64 = 0.0;
        for (k, &s) in self.mesh.active().iter().enumerate() {
            let p = self.x[s as usize];
            out[3 * k] = p.x as f32;
            out[3 * k + 1] = p.y as f32;
            out[3 * k + 2] = p.z as f32;
            max_d2 = max_d2.max((p - self.rest[s as usize]).length_squared());
        }
        max_d2.sqrt()
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        assert_eq!(
            out.len(),
            3 * self.mesh.active().len(),
            "surface buffer length"
        );
        for (k, &s) in self.mesh.active().iter().enumerate() {
            let p = self.rest[s as usize];
            out[3 * k] = p.x as f32;
            out[3 * k + 1] = p.y as f32;
            out[3 * k + 2] = p.z as f32;
        }
    }

    /// Nodes and surface vertices are the current (subdivided) node count; elements are the
    /// mesh springs, all of them simulated.
    fn stats(&self) -> BodyStats {
        BodyStats {
            nodes: self.mesh.active().len(),
            elements: self.mesh.springs().len(),
            active_elements: self.mesh.springs().len(),
            particles: 0,
            active_particles: 0,
            active_point_loads: self.loads.active_point_loads(),
            surface_vertices: self.mesh.active().len(),
            topology_version: self.version,
            sim_time_s: self.time_s,
            max_displacement_m: self.max_displacement_m(),
            ..BodyStats::default()
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "mass-spring",
            scene: self.scene_name.clone(),
            tick_s: self.tick_s,
            substeps: self.plan.substeps,
            critical_dt_s: self.plan.critical_dt_s,
            probe_radius_m: self.probe.params.radius_m,
            point_loads: crate::body::PointLoadZone::Anywhere,
        }
    }
}
