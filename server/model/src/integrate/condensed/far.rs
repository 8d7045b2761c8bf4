use super::*;

impl CondensedSolver {
    /// Hands the state over from `self` (the region in use) to `next` at a tick boundary:
    /// every node `next` simulates that `self` condenses gets the displacement the far field
    /// of `self` gives it for the current interface displacement (`u = -K_FF^-1 K_FG u_G`,
    /// from the map of every far component kept when `self` was built with
    /// [`ActiveRegion::follow`]) and zero
    /// velocity (the far field is quasi-static); nodes both simulate keep their state, and
    /// nodes only `self` simulates keep their positions (`next` refreshes its far surface
    /// from its own map) with zero velocity.
    ///
    /// A tile maps only the far components of its ring (`build::tile_ring`): a component
    /// `next` simulates outside it starts at rest (counted in
    /// [`Self::unmapped_hand_over`]; a neighbouring tile never has one), and a
    /// component `self` maps or simulates that `next` neither maps nor simulates is put at
    /// rest, so that a far node is either refreshed by the region in use or at rest.
    /// Returns `false`, touching nothing, when `self` has no such map (not built to follow).
    /// Costs `3 g` multiply-adds per such node (`g` interface
    /// components of `self`); allocation-free.
    ///
    /// # Panics
    /// If `x`, `v` are shorter than the body's node count or `next` is of another body.
    pub fn hand_over(&mut self, next: &CondensedSolver, x: &mut [DVec3], v: &mut [DVec3]) -> bool {
        if !self.start_hand_over(next, x) {
            return false;
        }
        let sys = &self.system;
        for &d in &next.system.eq_dof {
            if !sys.node_active[d / 3] {
                let u = self.far_displacement_or_rest(d);
                x[d / 3][d % 3] = sys.active.rest()[d / 3][d % 3] + u;
                v[d / 3][d % 3] = 0.0;
            }
        }
        self.finish_hand_over(next, x, v);
        true
    }

    /// [`Self::hand_over`] with the map's rows cut into two parts of `pool`'s join (the
    /// servo's swap tick is its longest): each part writes its displacements into `next`'s
    /// right-hand side (free until `next`'s first step), then they are copied into `x`. The
    /// same values bit for bit, whatever the thread count; serial as [`Self::hand_over`]
    /// without a worker. Allocation-free.
    ///
    /// # Panics
    /// As [`Self::hand_over`].
    pub fn hand_over_in(
        &mut self,
        pool: &TickPool,
        next: &mut CondensedSolver,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> bool {
        let eq = &next.system.eq_dof;
        if pool.threads() < 2 || next.scratch.b.len() < eq.len() {
            return self.hand_over(next, x, v);
        }
        if !self.start_hand_over(next, x) {
            return false;
        }
        let this = &*self;
        let taken = |d: usize| !this.system.node_active[d / 3];
        // Cut where half of the taken components lie before.
        let total = eq.iter().filter(|&&d| taken(d)).count();
        let mut seen = 0;
        let mid = eq
            .iter()
            .position(|&d| {
                seen += usize::from(taken(d));
                2 * seen > total
            })
            .unwrap_or(eq.len());
        let values = &mut next.scratch.b[..eq.len()];
        let (eq_a, eq_b) = eq.split_at(mid);
        let (out_a, out_b) = values.split_at_mut(mid);
        let part = |eqs: &[usize], out: &mut [f64]| {
            for (o, &d) in out.iter_mut().zip(eqs) {
                if taken(d) {
                    *o = this.far_displacement_or_rest(d);
                }
            }
        };
        pool.join(|| part(eq_a, out_a), || part(eq_b, out_b));
        let rest = this.system.active.rest();
        for (&d, &u) in eq.iter().zip(&next.scratch.b[..eq.len()]) {
            if taken(d) {
                x[d / 3][d % 3] = rest[d / 3][d % 3] + u;
                v[d / 3][d % 3] = 0.0;
            }
        }
        self.finish_hand_over(next, x, v);
        true
    }

    /// The hand-over's check and set-up: `false` when this region keeps no map for a
    /// successor (not built to follow); else `u_G` from `x` into the scratch (double and
    /// single precision) and the count of components `next` takes over without a row.
    fn start_hand_over(&mut self, next: &CondensedSolver, x: &[DVec3]) -> bool {
        let (sys, scratch) = (&self.system, &mut self.scratch);
        if sys.map_row.is_empty() {
            return false;
        }
        let node_active = &sys.node_active;
        self.stats.unmapped_hand_over = next
            .system
            .eq_dof
            .iter()
            .filter(|&&d| !node_active[d / 3] && sys.map_row[d] == u32::MAX)
            .count();
        let rest = sys.active.rest();
        for ((u, u32), &d) in scratch
            .u_gamma
            .iter_mut()
            .zip(&mut scratch.u_gamma32)
            .zip(&sys.gamma_dof)
        {
            *u = x[d / 3][d % 3] - rest[d / 3][d % 3];
            *u32 = *u as f32;
        }
        true
    }

    /// The far field's displacement of condensed component `d` for the interface
    /// displacement in the scratch ([`Self::start_hand_over`]): its map row times `u_G`, or
    /// zero (rest) without a row.
    fn far_displacement_or_rest(&self, d: usize) -> f64 {
        let sys = &self.system;
        let g = sys.gamma_dof.len();
        let r = sys.map_row[d];
        if r == u32::MAX {
            return 0.0;
        }
        let r = r as usize;
        dot_half(
            sys.f16c,
            &sys.map[r * g..(r + 1) * g],
            &self.scratch.u_gamma32,
        )
    }

    /// Nodes `next` condenses become quasi-static: their kinetic energy is dropped (never
    /// injected), and the probe's coupling sees them at rest. Components `next` neither
    /// simulates nor maps (beyond a tile's ring) go to rest.
    fn finish_hand_over(&self, next: &CondensedSolver, x: &mut [DVec3], v: &mut [DVec3]) {
        let (sys, to) = (&self.system, &next.system);
        let rest = sys.active.rest();
        // A region that maps every far component (not a tile) leaves nothing at rest; the
        // swap tick then skips the old map's rows (55 830 on the 100 000-tet LV).
        let maps_all = to.map_dofs.len() == to.far.dofs.len();
        let unmapped = |d: usize| !maps_all && to.map_row.get(d).is_some_and(|&r| r == u32::MAX);
        for &d in &sys.eq_dof {
            if !to.node_active[d / 3] {
                v[d / 3][d % 3] = 0.0;
                if unmapped(d) {
                    x[d / 3][d % 3] = rest[d / 3][d % 3];
                }
            }
        }
        if maps_all {
            return;
        }
        for &d in &sys.map_dofs {
            if !to.node_active[d / 3] && unmapped(d) {
                x[d / 3][d % 3] = rest[d / 3][d % 3];
            }
        }
    }

    /// Components the last hand-over from this region ([`Self::hand_over`]) started at rest
    /// because its map has no row for them (outside a tile's ring); 0 before any.
    pub fn unmapped_hand_over(&self) -> usize {
        self.stats.unmapped_hand_over
    }

    /// Elastic energy of the condensed far part for the interface displacement in `x`,
    /// `u_G^T S u_G / 2`, J (exact for its linear elements).
    pub fn far_energy_j(&self, x: &[DVec3]) -> f64 {
        let sys = &self.system;
        let g = sys.gamma_dof.len();
        let u = |a: usize| {
            let d = sys.gamma_dof[a];
            x[d / 3][d % 3] - sys.active.rest()[d / 3][d % 3]
        };
        // Packed upper triangle: the off-diagonal entries count twice.
        (0..g)
            .map(|a| {
                let start = packed_row_start(a, g);
                let row = &sys.schur[start..start + g - a];
                let off: f64 = (a + 1..g).map(|b| f64::from(row[b - a]) * u(b)).sum();
                u(a) * (0.5 * f64::from(row[0]) * u(a) + off)
            })
            .sum::<f64>()
    }

    /// Sets the far-only nodes of `x` to the static linear response of the far body to the
    /// interface displacement, `u_F = -K_FF^-1 K_FG u_G` (one sparse solve; allocates). Far
    /// velocities are left as they are (zero for a quasi-static far field).
    /// A following region ([`ActiveRegion::follow`]) keeps no far factor: it sets the far
    /// nodes from its map of every far component instead.
    pub fn recover_far_field(&self, x: &mut [DVec3]) {
        let sys = &self.system;
        let Some(llt) = &sys.far.llt else {
            let g = sys.gamma_dof.len();
            let rest = sys.active.rest();
            let u_gamma: Vec<f32> = sys
                .gamma_dof
                .iter()
                .map(|&d| (x[d / 3][d % 3] - rest[d / 3][d % 3]) as f32)
                .collect();
            for (r, &d) in sys.map_dofs.iter().enumerate() {
                x[d / 3][d % 3] =
                    rest[d / 3][d % 3] + dot_half(sys.f16c, &sys.map[r * g..(r + 1) * g], &u_gamma);
            }
            return;
        };
        let mut b = Mat::<f64>::zeros(sys.far.dofs.len(), 1);
        for &(fr, gc, v) in &sys.far.kfg {
            let d = sys.gamma_dof[gc];
            b[(fr, 0)] -= v * (x[d / 3][d % 3] - sys.active.rest()[d / 3][d % 3]);
        }
        llt.solve_in_place(b.as_mut());
        for (k, &d) in sys.far.dofs.iter().enumerate() {
            x[d / 3][d % 3] = sys.active.rest()[d / 3][d % 3] + b[(k, 0)];
        }
    }
}
