//! A subdivision event: new labels, the mesh edited where they changed, the state carried
//! over without adding energy (module documentation of [`super`]).

use super::MassSpringBody;
use crate::body::MAX_TOOLS;
use crate::mass_spring::VertexRule;
use crate::mass_spring::refine::NO_OWNER;
use glam::DVec3;

impl MassSpringBody {
    /// Recomputes the refinement's labels for the current centres, edits the mesh where they
    /// changed and carries the state over (module documentation). O(areas before and after),
    /// allocation-free.
    pub(super) fn event(&mut self, added: bool, removed: bool) {
        // 1. The labels before, then the new ones.
        self.relabel();
        // 2. Where the event can change the energy, and the energy there before.
        self.collect_region();
        let energy_before = self.region_energy_j();
        let mut contact_triangles = [None; MAX_TOOLS];
        for (t, tool) in contact_triangles.iter_mut().zip(&self.state.tools) {
            *t = tool.probe.state.in_contact.then(|| {
                self.state
                    .mesh
                    .coarse_triangle_of(tool.probe.state.triangle)
            });
        }
        // 3. The nodes of the areas before and after: masses, rest positions, velocities.
        self.carry_state();
        // 4. The mesh.
        self.edit_mesh();
        self.state.version += 1;
        self.update_area_constants();
        // 5. No energy from the event.
        let excess = self.region_energy_j() - energy_before;
        self.drain_excess(excess);
        // 6. Each probe's contact triangle index refers to the old triangles: walk from a piece
        // of the coarse triangle it was in (over the new slots' contact positions).
        self.update_contact_positions();
        for (tool, t) in self.state.tools.iter_mut().zip(contact_triangles) {
            if let Some(t) = t {
                let st = tool.probe.state;
                let point = st.proxy_m - st.normal * tool.probe.params.radius_m;
                let sp = tool
                    .probe
                    .surface
                    .closest_local(&self.scratch.cx, point, t, 16);
                tool.probe.state.triangle = sp.triangle;
            }
        }
        // 7. The device forces blend from this tick's to the simulated ones.
        self.state.blend.pending = true;
        self.stats.events += 1;
        self.stats.subdivisions += u64::from(added);
        self.stats.coarsenings += u64::from(removed);
    }

    /// Keeps the labels before the event (region, split edges, type-1 nodes) and labels the
    /// current centres' rings anew.
    fn relabel(&mut self) {
        let (event, refinement) = (&mut self.event, &mut self.state.refinement);
        event.old_region.clear();
        event.old_region.extend_from_slice(refinement.region());
        event.old_edges.clear();
        event.old_edges.extend_from_slice(refinement.active_edges());
        event.old_type1.clear();
        event.old_type1.extend_from_slice(refinement.type1_nodes());
        refinement.begin();
        let rings = self.setup.params.subdivision.rings;
        for (k, centre) in self.state.centres[..self.state.centre_count]
            .iter()
            .enumerate()
        {
            refinement.request_ring(&self.model.surface, centre.node, rings, k as u8);
        }
        refinement.finish(&self.model.surface);
    }

    /// The mesh edits of an event: triangles and edges whose state changed, then the rest
    /// lengths and owners of every spring in the region (the Loop rule moves rest positions).
    /// What the last event appended (triangles, then edges) is visited in reverse first, so that
    /// removing an area removes from the ends of the lists (nothing to move into the holes).
    fn edit_mesh(&mut self) {
        let surface = &self.model.surface;
        let (event, state) = (&self.event, &mut self.state);
        state.mesh.begin();
        for &e in event.old_edges.iter().rev() {
            state.mesh.update_edge(surface, &state.refinement, e);
        }
        for &t in event
            .old_region
            .iter()
            .rev()
            .chain(state.refinement.region())
        {
            state.mesh.update_triangle(
                surface,
                &state.refinement,
                &mut state.tools[0].probe.surface,
                t,
            );
        }
        for &e in state.refinement.active_edges() {
            state.mesh.update_edge(surface, &state.refinement, e);
        }
        for &t in &event.region_tris {
            state
                .mesh
                .refresh_triangle(&state.refinement, t, &state.rest, &state.owner);
        }
        for &e in &event.region_edges {
            state.mesh.refresh_edge(e, &state.rest, &state.owner);
        }
        state.mesh.finish(surface, &state.tools[0].probe.surface);
        // The other tools' probes see the same surface.
        if let Some((first, others)) = state.tools.split_first_mut() {
            for tool in others {
                tool.probe.surface.copy_from(&first.probe.surface);
            }
        }
    }

    /// No energy from an event: drains the touched nodes' kinetic energy by the `excess` (J)
    /// the event added, counts what it could not cover, and clears the touched marks.
    fn drain_excess(&mut self, excess: f64) {
        let (event, state) = (&mut self.event, &mut self.state);
        if excess > 0.0 {
            let ke: f64 = event
                .touched_list
                .iter()
                .map(|&s| 0.5 * state.mass[s as usize] * state.v[s as usize].length_squared())
                .sum();
            let drained = excess.min(ke);
            if ke > 0.0 {
                let scale = ((ke - drained) / ke).max(0.0).sqrt();
                for &s in &event.touched_list {
                    state.v[s as usize] *= scale;
                }
            }
            self.stats.drained_energy_j += drained;
            let injected = excess - drained;
            if injected > 0.0 {
                self.stats.injected_energy_j += injected;
                self.stats.max_injected_energy_j = self.stats.max_injected_energy_j.max(injected);
            }
        }
        for &s in &event.touched_list {
            event.touched[s as usize] = false;
        }
        event.touched_list.clear();
    }

    /// The region an event can change: the split and cut triangles before and after it, their
    /// coarse nodes (type-1 nodes, crack-filling ends) and edges; with [`VertexRule::Loop`]
    /// (which moves the rest positions of type-1 nodes) also every coarse triangle around those
    /// nodes. Every mesh spring and node whose energy the event changes is in it.
    fn collect_region(&mut self) {
        self.event.stamp = self.event.stamp.wrapping_add(1);
        if self.event.stamp == 0 {
            self.event.node_stamp.fill(0);
            self.event.tri_stamp.fill(0);
            self.event.edge_stamp.fill(0);
            self.event.stamp = 1;
        }
        let stamp = self.event.stamp;
        self.event.region_nodes.clear();
        self.event.region_tris.clear();
        self.event.region_edges.clear();
        let surface = &self.model.surface;
        for &t in self
            .event
            .old_region
            .iter()
            .chain(self.state.refinement.region())
        {
            if self.event.tri_stamp[t as usize] == stamp {
                continue;
            }
            self.event.tri_stamp[t as usize] = stamp;
            self.event.region_tris.push(t);
            for &i in &surface.triangles()[t as usize] {
                if self.event.node_stamp[i as usize] != stamp {
                    self.event.node_stamp[i as usize] = stamp;
                    self.event.region_nodes.push(i);
                }
            }
        }
        if self.setup.params.subdivision.vertex_rule == VertexRule::Loop {
            for &i in &self.event.region_nodes {
                for &t in surface.triangles_at(i) {
                    if self.event.tri_stamp[t as usize] != stamp {
                        self.event.tri_stamp[t as usize] = stamp;
                        self.event.region_tris.push(t);
                    }
                }
            }
        }
        for &t in &self.event.region_tris {
            for e in surface.triangle_edges(t) {
                if self.event.edge_stamp[e as usize] != stamp {
                    self.event.edge_stamp[e as usize] = stamp;
                    self.event.region_edges.push(e);
                }
            }
        }
    }

    /// Total energy (as [`MassSpringBody::energy_j`]) of the region's nodes and springs, J:
    /// what an event changes of the total.
    fn region_energy_j(&self) -> f64 {
        let nc = self.model.surface.node_count() as u32;
        let mut e = 0.0;
        for &i in &self.event.region_nodes {
            e += self.node_energy_j(i);
        }
        for &edge in &self.event.region_edges {
            if self.state.mesh.is_edge_split(edge) {
                e += self.node_energy_j(nc + edge);
            }
            self.state
                .mesh
                .edge_springs(edge, |k| e += self.spring_energy_j(k));
        }
        for &t in &self.event.region_tris {
            self.state
                .mesh
                .triangle_springs(t, |k| e += self.spring_energy_j(k));
        }
        e
    }

    /// Carries the state of the nodes of the areas before and after the event over to the new
    /// labels (module documentation): masses (eq. 3), damping, rest positions of the original
    /// nodes, velocities; new type-2 nodes interpolated; the owners. Marks what it changed in
    /// `touched`.
    fn carry_state(&mut self) {
        let (model, event, state) = (&self.model, &mut self.event, &mut self.state);
        let nc = model.surface.node_count() as u32;
        let m = self.setup.params.node_mass_kg;
        let (n1, n2) = (
            state.refinement.type1_count(),
            state.refinement.type2_count(),
        );
        let m_area = if n1 + n2 > 0 {
            m * n1 as f64 / (n1 + n2) as f64
        } else {
            m
        };
        let kd_per_kg = self.setup.params.damping_n_s_per_m / m;
        let loop_rule = self.setup.params.subdivision.vertex_rule == VertexRule::Loop;
        // Original nodes first (a new type-2 node interpolates its ends' new state). A node in
        // both lists is carried once: the second visit finds nothing to change.
        for &i in event.old_type1.iter().chain(state.refinement.type1_nodes()) {
            let i = i as usize;
            let area = state.refinement.node_owner(i as u32) != NO_OWNER;
            let mass = if area { m_area } else { m };
            let mut touched = false;
            if loop_rule {
                let new_rest = if area && !model.fixed[i] {
                    model.loop_vertex_rest[i]
                } else {
                    model.surface.rest()[i]
                };
                if new_rest != state.rest[i] {
                    state.x[i] += new_rest - state.rest[i];
                    state.rest[i] = new_rest;
                    touched = true;
                }
            }
            if mass != state.mass[i] {
                state.v[i] *= (state.mass[i] / mass).min(1.0);
                state.mass[i] = mass;
                state.damping[i] = kd_per_kg * mass;
                touched = true;
            }
            if touched && !event.touched[i] {
                event.touched[i] = true;
                event.touched_list.push(i as u32);
            }
        }
        // Type-2 nodes: new ones interpolated, persisting ones keep their state.
        for &e in event
            .old_edges
            .iter()
            .chain(state.refinement.active_edges())
        {
            let s = (nc + e) as usize;
            let now = state.refinement.is_edge_split(e);
            let was = state.mesh.is_edge_split(e);
            let mass = if now { m_area } else { m };
            let mut touched = false;
            if now && !was && !event.touched[s] {
                let [a, b] = model.surface.edges()[e as usize].map(|i| i as usize);
                let u = 0.5 * ((state.x[a] - state.rest[a]) + (state.x[b] - state.rest[b]));
                if model.fixed[s] {
                    state.x[s] = state.rest[s];
                    state.v[s] = DVec3::ZERO;
                } else {
                    state.x[s] = state.rest[s] + u;
                    state.v[s] = 0.5 * (state.v[a] + state.v[b]);
                }
                touched = true;
            } else if now && was && mass != state.mass[s] {
                state.v[s] *= (state.mass[s] / mass).min(1.0);
                touched = true;
            } else if !now {
                state.v[s] = DVec3::ZERO;
            }
            state.mass[s] = mass;
            state.damping[s] = kd_per_kg * mass;
            if touched && !event.touched[s] {
                event.touched[s] = true;
                event.touched_list.push(s as u32);
            }
        }
        // Owners, as labelled.
        for &i in event.old_type1.iter().chain(state.refinement.type1_nodes()) {
            state.owner[i as usize] = state.refinement.node_owner(i);
        }
        for &e in event
            .old_edges
            .iter()
            .chain(state.refinement.active_edges())
        {
            state.owner[(nc + e) as usize] = state.refinement.node_owner(nc + e);
        }
    }
}
