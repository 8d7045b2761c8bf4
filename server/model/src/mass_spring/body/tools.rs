//! Several tools on the mass-spring surface (issue 50): one [`Probe`] per tool slot, their
//! couplings completed together, and which tool's organ-table factor each slot's springs take.

use glam::DVec3;

use super::MassSpringBody;
use crate::ModelError;
use crate::body::{MAX_TOOLS, TickInput};
use crate::contact::{ContactModel, Probe, ProbeParams};
use crate::mass_spring::contact_rest::contact_rest_positions;
use crate::mass_spring::mixed::MixedMesh;
use crate::mass_spring::organ::foot::RestFoot;

/// One tool slot's contact: its probe and where the organ table reads it.
#[derive(Debug, Clone)]
pub(super) struct ToolContact {
    pub(super) probe: Probe,
    /// The contact factor `beta` of this tool's contact (1 without an organ table; kept when
    /// the tool leaves).
    pub(super) contact_factor: f64,
    /// The probe's sphere depth at the last sub-step in contact, m (see
    /// [`MassSpringBody::contact_depth_m`]).
    pub(super) contact_depth_m: f64,
    /// The probe's foot on the coarse rest surface ([`crate::mass_spring::organ::foot`]), where
    /// the organ table is read; `None` out of contact, without a table or off the surface.
    pub(super) foot: Option<RestFoot>,
    /// Whether a sub-step of this tick already searched the foot (at most one search per
    /// tick besides the end-of-tick update).
    pub(super) foot_searched: bool,
    /// The device position of the last tick with one, m.
    pub(super) last_device_m: Option<DVec3>,
    /// While the tool is withdrawn ([`WITHDRAW_S`]): where its device was, its whole travel
    /// (m, along the contact normal) and the time since it left, s.
    pub(super) withdrawal: Option<(DVec3, DVec3, f64)>,
}

/// A tool whose stream ends while it touches the surface and another tool touches it too is
/// withdrawn along its contact normal over this time, s, instead of vanishing (a C1
/// smoothstep over its coupling's stretch plus the surface's depth under it). An abrupt
/// release is a step of its load on the surface: with the other tool 4 mm away on
/// `hemisphere-springs` (1 mm presses, the patches sharing nodes) the surface springing back
/// raised that tool's force by 19 % of it in one tick (the JND is 7 %); withdrawn over 100 ms
/// the largest change is 3.8 % (`lv-surface-springs`: 3.7 %; `tests/tools_mass_spring.rs`).
/// Alone, a tool is released at once, as before several tools (no other device feels it).
pub const WITHDRAW_S: f64 = 0.1;

/// A withdrawal ends after at most this many [`WITHDRAW_S`] even if the contact persists
/// (the surface moving out with the device).
const WITHDRAW_LIMIT: f64 = 2.0;

/// How far beyond the proxy a withdrawn device goes, m: out of contact with a margin.
const WITHDRAW_MARGIN_M: f64 = 1e-4;

impl ToolContact {
    /// A tool at rest out of contact with `probe`.
    pub(super) fn new(probe: Probe) -> Self {
        Self {
            probe,
            contact_factor: 1.0,
            contact_depth_m: 0.0,
            foot: None,
            foot_searched: false,
            last_device_m: None,
            withdrawal: None,
        }
    }
}

impl MassSpringBody {
    /// The body with one tool slot per entry of `probes` (slot `k` with `probes[k]`'s radius,
    /// force limit, coupling) and the named tools `ids` in the first slots
    /// ([`crate::body::SoftBody::tool_slot`]); [`MassSpringBody::new`] makes one slot. Where
    /// the probe meets each slot at rest ([`crate::mass_spring::contact_rest`]) follows slot 0's
    /// radius. Before the first tick (allocates).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for no probe, more than [`MAX_TOOLS`], or more ids than
    /// probes; [`ModelError::SceneField`] (`probe.contact`) for a patch law taking an FEM
    /// material.
    pub fn with_tools(
        mut self,
        probes: &[ProbeParams],
        ids: &[String],
    ) -> Result<Self, ModelError> {
        if probes.is_empty() || probes.len() > MAX_TOOLS || ids.len() > probes.len() {
            return Err(ModelError::InvalidInput(format!(
                "mass-spring tools: {} probes and {} ids (1..={MAX_TOOLS} probes, at most one id each)",
                probes.len(),
                ids.len()
            )));
        }
        for p in probes {
            if matches!(
                p.contact,
                ContactModel::PatchHertz | ContactModel::PatchLocal
            ) {
                return Err(ModelError::field(
                    "probe.contact",
                    "\"patch-hertz\" and \"patch-local\" take the law of an FEM material; a mass-spring surface has none (use \"auto\" or \"patch\")",
                ));
            }
        }
        let surface = &self.model.surface;
        let current = &self.state.tools[0].probe.surface;
        let tools = probes
            .iter()
            .map(|&params| {
                let mut probe = Probe::new(params, surface.triangles().to_vec(), &self.state.rest);
                // Built as slot 0's (same capacities), then made equal to the current one.
                let (_, mut contact) = MixedMesh::new(surface, &self.state.rest);
                contact.copy_from(current);
                probe.replace_surface(contact);
                ToolContact::new(probe)
            })
            .collect();
        self.state.tools = tools;
        self.model.contact_rest = contact_rest_positions(surface, probes[0]).positions;
        self.scratch.cx.clone_from(&self.model.contact_rest);
        self.model.tool_ids = ids.to_vec();
        Ok(self)
    }

    /// Slot `slot`'s probe; `None` past [`crate::body::SoftBody::max_tools`].
    pub fn tool_probe(&self, slot: usize) -> Option<&Probe> {
        self.state.tools.get(slot).map(|t| &t.probe)
    }

    /// Slot `slot`'s sphere depth at its last sub-step in contact, m
    /// ([`MassSpringBody::contact_depth_m`]); `None` past the slots.
    pub fn tool_contact_depth_m(&self, slot: usize) -> Option<f64> {
        self.state.tools.get(slot).map(|t| t.contact_depth_m)
    }

    /// Slot `slot`'s contact factor ([`crate::mass_spring::organ`]): the springs of the slots
    /// nearest this tool take it; `None` past the slots.
    pub fn tool_contact_factor(&self, slot: usize) -> Option<f64> {
        self.state.tools.get(slot).map(|t| t.contact_factor)
    }

    /// The inputs the probes act with this tick (`acting[k]` for slot `k`): `inputs`, except
    /// that a slot whose device left while its probe touches and another slot's device is
    /// present is withdrawn along its contact normal, out of contact within [`WITHDRAW_S`]
    /// (or released after [`WITHDRAW_LIMIT`] of it, or when it no longer touches). Without
    /// another device a slot is released at once (the one-tool tick of before). The outputs
    /// still follow `inputs`. Allocation-free.
    pub(super) fn acting_inputs(&mut self, inputs: &[TickInput], acting: &mut [TickInput]) {
        let tick_s = self.setup.tick_s;
        let others = inputs
            .iter()
            .filter(|i| i.device_position_m.is_some())
            .count();
        for (k, tool) in self.state.tools.iter_mut().enumerate() {
            let input = inputs.get(k).copied().unwrap_or_default();
            if let Some(p) = input.device_position_m {
                tool.last_device_m = Some(p);
                tool.withdrawal = None;
                acting[k] = input;
                continue;
            }
            let st = tool.probe.state;
            if let (None, Some(last), true, true) = (
                tool.withdrawal,
                tool.last_device_m,
                st.in_contact,
                others > 0,
            ) {
                // The coupling's stretch and the surface's depth under the tool: out of contact
                // even if the surface comes back to rest.
                let travel = (st.proxy_m - last).dot(st.normal).max(0.0)
                    + tool.contact_depth_m.max(0.0)
                    + WITHDRAW_MARGIN_M;
                tool.withdrawal = Some((last, st.normal * travel, 0.0));
            }
            tool.last_device_m = None;
            acting[k] = TickInput::default();
            if let Some((from, travel, elapsed)) = tool.withdrawal {
                let elapsed = elapsed + tick_s;
                if !st.in_contact || others == 0 || elapsed > WITHDRAW_LIMIT * WITHDRAW_S {
                    tool.withdrawal = None;
                    continue;
                }
                tool.withdrawal = Some((from, travel, elapsed));
                // A C1 smoothstep: the load's rate starts and ends at zero (no jolt).
                let u = (elapsed / WITHDRAW_S).min(1.0);
                acting[k] = TickInput {
                    device_position_m: Some(from + travel * (u * u * (3.0 - 2.0 * u))),
                    device_velocity_m_per_s: travel * (6.0 * u * (1.0 - u) / WITHDRAW_S),
                };
            }
        }
    }

    /// Contact of one sub-step: each slot's probe at its device (released without one, and past
    /// `inputs`) on the contact positions, its explicit reaction into the forces, its contact
    /// factor. Allocation-free.
    pub(super) fn update_probes(&mut self, inputs: &[TickInput]) {
        if inputs.iter().any(|i| i.device_position_m.is_some()) {
            self.update_contact_positions();
        }
        for k in 0..self.state.tools.len() {
            let input = inputs.get(k).copied().unwrap_or_default();
            let probe = &mut self.state.tools[k].probe;
            match input.device_position_m {
                Some(p) => {
                    probe.update(&self.scratch.cx, p, input.device_velocity_m_per_s);
                    probe.add_reaction(&mut self.scratch.f);
                    self.update_contact_factor(k);
                }
                None => probe.release(),
            }
        }
    }

    /// Completes the sub-step's couplings implicitly, after the nodes moved with the explicit
    /// parts, and returns the largest squared speed over the patches (m^2/s^2). One tool in
    /// contact: [`Probe::finish_implicit`] (Sherman-Morrison). Several: their rank-one terms
    /// `gamma_k u_k u_k^T` (`u_k = (w_ki n_k)`, [`Probe::coupling_gamma`]) solved together by
    /// Woodbury, `v' = y - B^-1 U (G^-1 + U^T B^-1 U)^-1 U^T y` with the per-node
    /// `B_i = m_i + dt K_d,i` (fixed nodes: `B^-1 = 0`): exact where patches share nodes, so
    /// two tools on one spot count the surface once (a sequential completion would let the
    /// second tool see the first's correction as motion). Positions move by `dt (v' - y)`; each
    /// tool's force follows from its `u_k^T v'` ([`Probe::finish_solved`]). Allocation-free.
    pub(super) fn finish_couplings(&mut self, dt: f64) -> f64 {
        let mut active = [0usize; MAX_TOOLS];
        let mut m = 0;
        for (k, tool) in self.state.tools.iter().enumerate() {
            if tool.probe.state.in_contact {
                active[m] = k;
                m += 1;
            }
        }
        if m == 0 {
            return 0.0;
        }
        if m == 1 {
            let (mass, damping, fixed) = (&self.state.mass, &self.state.damping, &self.model.fixed);
            let probe = &mut self.state.tools[active[0]].probe;
            probe.finish_implicit(dt, &mut self.state.x, &mut self.state.v, |i, w| {
                if fixed[i] {
                    DVec3::ZERO
                } else {
                    w / (mass[i] + dt * damping[i])
                }
            });
            return patch_max_v2(probe, &self.state.v);
        }
        let delta = self.coupling_multipliers(&active[..m], dt);
        let (mass, damping, fixed) = (&self.state.mass, &self.state.damping, &self.model.fixed);
        let inv = |i: usize| {
            if fixed[i] {
                0.0
            } else {
                1.0 / (mass[i] + dt * damping[i])
            }
        };
        for (a, &k) in active[..m].iter().enumerate() {
            let probe = &self.state.tools[k].probe;
            let n = probe.state.normal;
            let (nodes, weights) = probe.patch();
            for (&i, &w) in nodes.iter().zip(weights) {
                let dv = n * (w * inv(i as usize) * delta[a]);
                self.state.v[i as usize] -= dv;
                self.state.x[i as usize] -= dv * dt;
            }
        }
        let mut max_v2: f64 = 0.0;
        for &k in &active[..m] {
            let probe = &mut self.state.tools[k].probe;
            probe.finish_solved(dt, &self.state.v);
            max_v2 = max_v2.max(patch_max_v2(probe, &self.state.v));
        }
        max_v2
    }

    /// The multipliers `delta = (G^-1 + U^T B^-1 U)^-1 U^T y` of the tools `active` (in contact,
    /// 2 to [`MAX_TOOLS`]) at the velocities `y` the explicit part left
    /// ([`Self::finish_couplings`]); `S = U^T B^-1 U` is symmetric positive semi-definite and
    /// `G^-1` positive, so the elimination needs no pivoting. Allocation-free.
    fn coupling_multipliers(&mut self, active: &[usize], dt: f64) -> [f64; MAX_TOOLS] {
        let m = active.len();
        let mut s = [[0.0; MAX_TOOLS]; MAX_TOOLS];
        let mut r = [0.0; MAX_TOOLS];
        let (mass, damping, fixed) = (&self.state.mass, &self.state.damping, &self.model.fixed);
        let scatter = &mut self.scratch.tool_weight;
        for (a, &ka) in active.iter().enumerate() {
            let pa = &self.state.tools[ka].probe;
            let na = pa.state.normal;
            let (nodes_a, weights_a) = pa.patch();
            for (&i, &w) in nodes_a.iter().zip(weights_a) {
                let i = i as usize;
                if !fixed[i] {
                    scatter[i] += w / (mass[i] + dt * damping[i]);
                }
                r[a] += w * na.dot(self.state.v[i]);
            }
            for (b, &kb) in active.iter().enumerate() {
                let pb = &self.state.tools[kb].probe;
                let (nodes_b, weights_b) = pb.patch();
                let overlap: f64 = nodes_b
                    .iter()
                    .zip(weights_b)
                    .map(|(&i, &w)| w * scatter[i as usize])
                    .sum();
                s[a][b] = overlap * na.dot(pb.state.normal);
            }
            for &i in nodes_a {
                scatter[i as usize] = 0.0;
            }
            s[a][a] += 1.0 / pa.coupling_gamma(dt);
        }
        solve_small(&mut s, &mut r, m);
        r
    }

    /// Which tool's contact factor each slot's springs take: with tools in contact, the one
    /// whose contact point (`proxy - r n`) lies nearest the slot's rest position (the organ
    /// table describes the tissue under each tool; far from all of them displacements are
    /// small and the choice matters little). Unchanged with no tool in contact, and while one
    /// tool keeps every slot. O(slots x tools) when it relabels, allocation-free.
    pub(super) fn update_factor_tools(&mut self) {
        let mut points = [DVec3::ZERO; MAX_TOOLS];
        let mut ids = [0u8; MAX_TOOLS];
        let mut m = 0;
        for (k, tool) in self.state.tools.iter().enumerate() {
            let st = tool.probe.state;
            if st.in_contact {
                points[m] = st.proxy_m - st.normal * tool.probe.params.radius_m;
                ids[m] = k as u8;
                m += 1;
            }
        }
        if m == 0 || (m == 1 && self.state.factor_all == Some(ids[0])) {
            return;
        }
        for (label, rest) in self.state.factor_tool.iter_mut().zip(&self.state.rest) {
            let mut best = (f64::INFINITY, ids[0]);
            for (p, &id) in points[..m].iter().zip(&ids[..m]) {
                let d2 = (*rest - *p).length_squared();
                if d2 < best.0 {
                    best = (d2, id);
                }
            }
            *label = best.1;
        }
        self.state.factor_all = (m == 1).then_some(ids[0]);
    }
}

/// The largest squared speed (m^2/s^2) over `probe`'s patch.
fn patch_max_v2(probe: &Probe, v: &[DVec3]) -> f64 {
    probe
        .patch()
        .0
        .iter()
        .map(|&i| v[i as usize].length_squared())
        .fold(0.0, f64::max)
}

/// Solves the `m x m` symmetric positive definite system `s x = r` in place (`r` becomes `x`)
/// by Gaussian elimination without pivoting.
fn solve_small(s: &mut [[f64; MAX_TOOLS]; MAX_TOOLS], r: &mut [f64; MAX_TOOLS], m: usize) {
    for c in 0..m {
        let pivot = s[c];
        for row in c + 1..m {
            let f = s[row][c] / pivot[c];
            for (x, p) in s[row][c..m].iter_mut().zip(&pivot[c..m]) {
                *x -= f * p;
            }
            r[row] -= f * r[c];
        }
    }
    for c in (0..m).rev() {
        let mut acc = r[c];
        for col in c + 1..m {
            acc -= s[c][col] * r[col];
        }
        r[c] = acc / s[c][c];
    }
}
