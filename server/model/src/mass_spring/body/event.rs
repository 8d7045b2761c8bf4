//! A subdivision event: new labels, the mesh edited where they changed, the state carried
//! over without adding energy (module documentation of [`super`]).

use super::MassSpringBody;
use crate::mass_spring::VertexRule;
use crate::mass_spring::refine::NO_OWNER;
use glam::DVec3;

impl MassSpringBody {
    /// Recomputes the refinement's labels for the current centres, edits the mesh where they
    /// changed and carries the state over (module documentation). O(areas before and after),
    /// allocation-free.
    pub(super) fn event(&mut self, added: bool, removed: bool) {
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
}
