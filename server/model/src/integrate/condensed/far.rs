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
    /// Returns `false`, touching nothing, when `self` has no such map (not built to follow).
    /// Costs `3 g` multiply-adds per such node (`g` interface
    /// components of `self`); allocation-free.
    ///
    /// # Panics
    /// If `x`, `v` are shorter than the body's node count or `next` is of another body.
    pub fn hand_over(&mut self, next: &CondensedSolver, x: &mut [DVec3], v: &mut [DVec3]) -> bool {
        let (sys, scratch) = (&self.system, &mut self.scratch);
        let node_active = &sys.node_active;
        let taken = |d: usize| !node_active[d / 3];
        let missing = next
            .system
            .eq_dof
            .iter()
            .any(|&d| taken(d) && sys.map_row.get(d).is_none_or(|&r| r == u32::MAX));
        if missing {
            return false;
        }
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
        let g = sys.gamma_dof.len();
        for &d in &next.system.eq_dof {
            if taken(d) {
                let r = sys.map_row[d] as usize;
                let u = dot_half(sys.f16c, &sys.map[r * g..(r + 1) * g], &scratch.u_gamma32);
                x[d / 3][d % 3] = rest[d / 3][d % 3] + u;
                v[d / 3][d % 3] = 0.0;
            }
        }
        // Nodes `next` condenses become quasi-static: their kinetic energy is dropped (never
        // injected), and the probe's coupling sees them at rest.
        for &d in &sys.eq_dof {
            if !next.system.node_active[d / 3] {
                v[d / 3][d % 3] = 0.0;
            }
        }
        true
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
