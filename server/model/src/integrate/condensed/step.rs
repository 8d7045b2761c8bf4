use super::*;

impl CondensedSolver {
    /// One backward Euler step (module documentation). `f` (N, one per body node) holds the
    /// active elements' elastic force at `x` (from [`Self::active_model`]), external loads on
    /// active nodes and the coupling's explicit part; the far field's `-S u_G` is added here.
    /// Updates `x`, `v` of the active nodes and the positions of a slice of the far boundary
    /// nodes (all of them every [`Self::surface_refresh_ticks`] ticks); other far nodes keep
    /// their values (see [`Self::recover_far_field`]). Returns the largest squared nodal speed
    /// (m^2/s^2; NaN if any value is not finite). Allocation-free.
    ///
    /// # Panics
    /// If the slices are shorter than the body's node count.
    pub fn step(
        &mut self,
        f: &[DVec3],
        coupling: Option<ContactCoupling<'_>>,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        self.step_in(None, None, f, coupling, x, v)
    }

    /// [`Self::step`] with the pieces [`Self::set_parts`] cut run as parts jobs of `pool`
    /// (on the caller and a free worker; both on the caller when none is free, with the same
    /// sums), and `beside` (other work of the tick, run once: a following region's coarse
    /// companion) on a worker of `pool` beside the solve, the tick's longest serial piece
    /// ([`TickPool::join`]; after the solve without a pool). Without a cut it is
    /// [`Self::step`] bit for bit. Allocation-free (`beside` aside).
    ///
    /// # Panics
    /// As [`Self::step`]; with `beside`'s panic.
    pub fn step_in(
        &mut self,
        pool: Option<&TickPool>,
        beside: Option<&mut (dyn FnMut() + Send)>,
        f: &[DVec3],
        coupling: Option<ContactCoupling<'_>>,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        // Without an entry factor there is nothing to tell apart.
        if self.system.entry.is_none() {
            return self.step_solved(pool, beside, f, coupling, x, v);
        }
        // A node entering the probe's rows: the step with the unscaled rest stiffness.
        let entering = coupling.is_some_and(|c| {
            c.nodes.len() > ENTRY_TRACKED_NODES
                || c.nodes.iter().any(|i| !self.state.last_contact.contains(i))
        });
        self.state.last_contact.clear();
        if let Some(c) = coupling {
            let k = c.nodes.len().min(ENTRY_TRACKED_NODES);
            self.state.last_contact.extend_from_slice(&c.nodes[..k]);
        }
        let entry = if entering {
            self.system.entry.take()
        } else {
            None
        };
        let Some(mut entry) = entry else {
            return self.step_solved(pool, beside, f, coupling, x, v);
        };
        // The entry factor and its columns stand in for this tick (swapped, not copied).
        self.swap_entry(&mut entry);
        let r = self.step_solved(pool, beside, f, coupling, x, v);
        self.swap_entry(&mut entry);
        self.system.entry = Some(entry);
        r
    }

    /// Swaps the tick factor, its half-precision copy and the contact columns with the entry
    /// factor's (allocation-free).
    fn swap_entry(&mut self, entry: &mut EntryFactor) {
        std::mem::swap(&mut self.system.factor, &mut entry.factor);
        std::mem::swap(&mut self.system.half, &mut entry.half);
        std::mem::swap(&mut self.contact.z, &mut entry.contact_z);
    }

    /// [`Self::step_in`] with the factor in `factor` (and its columns in `contact_z`).
    fn step_solved(
        &mut self,
        pool: Option<&TickPool>,
        beside: Option<&mut (dyn FnMut() + Send)>,
        f: &[DVec3],
        coupling: Option<ContactCoupling<'_>>,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        // Component `d` of a node array is entry `d` of its flat view.
        let x: &mut [f64] = bytemuck::cast_slice_mut(x);
        let v: &mut [f64] = bytemuck::cast_slice_mut(v);
        let f: &[f64] = bytemuck::cast_slice(f);
        self.gather_interface(x);
        let far_cut = match pool {
            Some(pool) if self.scratch.far_cut.is_some() => {
                self.far_products_in(pool, x);
                true
            }
            _ => {
                self.refresh_surface_rows(x);
                false
            }
        };
        self.right_hand_side(f, v, far_cut);
        match (pool, beside) {
            (Some(pool), Some(beside)) => {
                pool.join(|| self.solve_with_probe(coupling), beside);
            }
            (None, Some(beside)) => {
                self.solve_with_probe(coupling);
                beside();
            }
            (_, None) => self.solve_with_probe(coupling),
        }
        let alpha = self.relax(v);
        self.scatter(alpha, x, v)
    }

    /// The interface displacement `u_G` from `x` (flat), in double and single precision.
    fn gather_interface(&mut self, x: &[f64]) {
        let rest: &[f64] = bytemuck::cast_slice(self.system.active.rest());
        for ((u, u32), &d) in self
            .scratch
            .u_gamma
            .iter_mut()
            .zip(&mut self.scratch.u_gamma32)
            .zip(&self.system.gamma_dof)
        {
            *u = x[d] - rest[d];
            *u32 = *u as f32;
        }
    }

    /// Far boundary nodes: a slice of rows per tick, so the surface is at most
    /// `surface_refresh_ticks` ticks behind the interface.
    fn refresh_surface_rows(&mut self, x: &mut [f64]) {
        let rest: &[f64] = bytemuck::cast_slice(self.system.active.rest());
        let g = self.system.gamma_dof.len();
        let rows = self.surface_rows_now();
        for &r in &self.system.surface_rows[rows.clone()] {
            let r = r as usize;
            let d = self.system.map_dofs[r];
            let u = dot_half(
                self.system.f16c,
                &self.system.map[r * g..(r + 1) * g],
                &self.scratch.u_gamma32,
            );
            x[d] = rest[d] + u;
        }
        self.advance_surface_cursor(rows.end);
    }

    /// This tick's slice of `surface_rows` (empty without far surface).
    fn surface_rows_now(&self) -> std::ops::Range<usize> {
        let (start, rows) = (self.state.surface_cursor, self.system.surface_rows.len());
        start..(start + self.surface_rows_per_tick()).min(rows).max(start)
    }

    /// The next tick refreshes the rows from `end` (from the first after the last).
    fn advance_surface_cursor(&mut self, end: usize) {
        let rows = self.system.surface_rows.len();
        self.state.surface_cursor = if end >= rows { 0 } else { end };
    }

    /// The far products of a tick cut in two ([`Self::set_parts`]) as a parts job of
    /// `pool`: `S u_G` into `su` (the first part's packed rows `0..row` there, the second's
    /// rows `row..` into the cut's own sums, added after) and this tick's slice of far
    /// surface rows (each part half of it, written to `x` after).
    fn far_products_in(&mut self, pool: &TickPool, x: &mut [f64]) {
        /// One part: packed rows of `S` and its sums, surface rows and their values.
        struct Part<'a> {
            rows: std::ops::Range<usize>,
            su: &'a mut [f64],
            surface: &'a [u32],
            surface_u: &'a mut [f64],
        }
        let g = self.system.gamma_dof.len();
        let now = self.surface_rows_now();
        let Some(cut) = self.scratch.far_cut.as_mut() else {
            return;
        };
        let slice = &self.system.surface_rows[now.clone()];
        let half_rows = slice.len() / 2;
        let (u_first, u_second) = cut.surface_u[..slice.len()].split_at_mut(half_rows);
        let mut parts = [
            Part {
                rows: 0..cut.row,
                su: &mut self.scratch.su,
                surface: &slice[..half_rows],
                surface_u: u_first,
            },
            Part {
                rows: cut.row..g,
                su: &mut cut.su,
                surface: &slice[half_rows..],
                surface_u: u_second,
            },
        ];
        let (sys, u, u32s) = (
            &self.system,
            &self.scratch.u_gamma[..],
            &self.scratch.u_gamma32[..],
        );
        pool.for_each_mut(&mut parts, &|_, p: &mut Part<'_>| {
            schur_rows(sys, p.rows.clone(), u, p.su);
            for (value, &r) in p.surface_u.iter_mut().zip(p.surface) {
                let r = r as usize;
                *value = dot_half(sys.f16c, &sys.map[r * g..(r + 1) * g], u32s);
            }
        });
        for (s, &t) in self.scratch.su[cut.row..]
            .iter_mut()
            .zip(&cut.su[cut.row..])
        {
            *s += t;
        }
        let rest: &[f64] = bytemuck::cast_slice(self.system.active.rest());
        for (&r, &u) in slice.iter().zip(&cut.surface_u) {
            let d = self.system.map_dofs[r as usize];
            x[d] = rest[d] + u;
        }
        self.advance_surface_cursor(now.end);
    }

    /// `b = M v + h (f - S u_G)`, into the first right-hand-side column (the second is
    /// filled where it is used); `S u_G` is in `su` already when `su_ready`
    /// ([`Self::far_products_in`]).
    fn right_hand_side(&mut self, f: &[f64], v: &[f64], su_ready: bool) {
        let h = self.params.h;
        let g = self.system.gamma_dof.len();
        if g > 0 && !su_ready {
            self.schur_product();
        }
        let rhs0 = self.scratch.rhs.col_as_slice_mut(0);
        if g == 0 {
            for ((r, &d), &m) in rhs0
                .iter_mut()
                .zip(&self.system.eq_dof)
                .zip(&self.system.mass)
            {
                *r = (m * v[d] + h * f[d]) as f32;
            }
        } else {
            for ((b, &d), &m) in self
                .scratch
                .b
                .iter_mut()
                .zip(&self.system.eq_dof)
                .zip(&self.system.mass)
            {
                *b = m * v[d] + h * f[d];
            }
            for (&da, &su) in self.system.gamma_dof.iter().zip(&self.scratch.su) {
                self.scratch.b[self.system.eq[da]] -= h * su;
            }
            for (r, b) in rhs0.iter_mut().zip(&self.scratch.b) {
                *r = *b as f32;
            }
        }
    }

    /// `su = S u_G` on the caller (the uncut tick) from the packed upper triangle: row `a`
    /// adds its dot product to entry `a` and its entries times `u_a` to the entries after it.
    fn schur_product(&mut self) {
        let g = self.system.gamma_dof.len();
        schur_rows(
            &self.system,
            0..g,
            &self.scratch.u_gamma,
            &mut self.scratch.su,
        );
    }

    /// The solve of the tick: `z0 = A^-1 b` into the first right-hand-side column, with the
    /// probe's term `h^2 A^T C A` by Woodbury on the factor:
    /// `v' = z0 - A^-1 A^T W^-1 A z0`, `z0 = A^-1 b`, `W = C^-1 / h^2 + A A^-1 A^T`, with the
    /// columns `A^-1 e` prepared for the contact nodes ([`Self::prepare_contact`]); a row
    /// with a node not prepared falls back to one more solve per row. `z1` receives the
    /// correction `A^-1 A^T W^-1 A z0` (zero without one).
    fn solve_with_probe(&mut self, coupling: Option<ContactCoupling<'_>>) {
        self.scratch.z1.iter_mut().for_each(|z| *z = 0.0);
        let paired = self.paired_sweep_row(coupling);
        if let Some(c) = coupling.filter(|_| !paired) {
            self.woodbury_rows(c);
        }
    }

    /// One row `a` (the kernel patch) over many nodes through the half-precision sweep:
    /// both forward sweeps in one pass over the factor, `W = C^-1 / h^2 + a A^-1 a`,
    /// `s = a z0 / W`, then one backward sweep of `b - s a`: `v' = A^-1 (b - s a)`, without
    /// the prepared columns ([`PAIRED_SWEEP_MIN_RATIO`]). Otherwise the plain solve
    /// `z0 = A^-1 b`; returns whether the paired sweep ran.
    fn paired_sweep_row(&mut self, coupling: Option<ContactCoupling<'_>>) -> bool {
        let h = self.params.h;
        let m = self.system.eq_dof.len();
        let factor_len = self
            .system
            .sweep
            .as_ref()
            .map_or(usize::MAX, SupernodalSolve::factor_len);
        let one_row = coupling.filter(|c| {
            c.rows() == 1
                && (3 * c.nodes.len() * m) as f64 >= PAIRED_SWEEP_MIN_RATIO * factor_len as f64
        });
        if let (Some(c), Some(sweep), Some(half)) =
            (one_row, &mut self.system.sweep, &self.system.half)
        {
            self.scratch.a_row.iter_mut().for_each(|a| *a = 0.0);
            add_row(&self.system.eq, c, 0, 1.0, &mut self.scratch.a_row);
            let (aa, ab) =
                sweep.forward_pair(half, self.scratch.rhs.col_as_slice(0), &self.scratch.a_row);
            let w = c.compliance[0] / (h * h) + aa;
            // A capacitance that is not positive: no correction, as for several rows.
            let s = if w > 0.0 { ab / w } else { 0.0 };
            sweep.backward_combined(half, s as f32, self.scratch.rhs.col_as_slice_mut(0));
            true
        } else {
            self.solve_column(0);
            false
        }
    }

    /// The Woodbury correction of the probe's rows `c` into `z1` ([`Self::solve_with_probe`]),
    /// from the prepared columns when every node has them.
    fn woodbury_rows(&mut self, c: ContactCoupling<'_>) {
        let nf = c.rows();
        let prepared = c
            .nodes
            .iter()
            .all(|&i| self.contact.col[i as usize] != u32::MAX);
        // t = A z0.
        let mut t = [0.0; MAX_MERGED_ROWS];
        for (f, tf) in t.iter_mut().enumerate().take(nf) {
            for (i, u) in c.row(f) {
                for k in 0..3 {
                    let e = self.system.eq[3 * i as usize + k];
                    if e != usize::MAX {
                        *tf += u[k] * f64::from(self.scratch.rhs[(e, 0)]);
                    }
                }
            }
        }
        // One row (the kernel patch: every patch node in it): `z1 = A^-1 a^T` from the
        // prepared columns first, then `W += a z1`.
        let single_row = prepared && nf == 1;
        self.capacitance_of(c, prepared, single_row);
        let w = &mut self.scratch.capacitance[..nf * nf];
        if cholesky_in_place(w, nf) {
            cholesky_solve(w, nf, &mut t[..nf]);
            self.correction(c, &t[..nf], prepared, single_row);
        } else if single_row {
            // No correction, as for several rows.
            self.scratch.z1.iter_mut().for_each(|z| *z = 0.0);
        }
    }

    /// The capacitance `W = C^-1 / h^2 + A A^-1 A^T` of the probe's rows `c` into
    /// `capacitance`; with `single_row`, `z1 = A^-1 a^T` on the way.
    fn capacitance_of(&mut self, c: ContactCoupling<'_>, prepared: bool, single_row: bool) {
        let h = self.params.h;
        let m = self.system.eq_dof.len();
        let nf = c.rows();
        let w = &mut self.scratch.capacitance[..nf * nf];
        for f in 0..nf {
            for g in 0..nf {
                w[f * nf + g] = c.compliance[f * nf + g] / (h * h);
            }
        }
        // The pair loop below reads `3 N^2` scattered entries of the columns for a row of
        // `N` nodes, about a fifth of the tick on a 0.5 mm mesh: one row goes through `z1`.
        if single_row {
            for (l, u) in c.row(0) {
                let base = self.contact.col[l as usize] as usize * 3 * m;
                axpy3(
                    self.system.avx2,
                    &mut self.scratch.z1,
                    u.to_array(),
                    &self.contact.z[base..base + 3 * m],
                );
            }
            let mut s = 0.0;
            for (j, u) in c.row(0) {
                for a in 0..3 {
                    let e = self.system.eq[3 * j as usize + a];
                    if e != usize::MAX {
                        s += u[a] * self.scratch.z1[e];
                    }
                }
            }
            w[0] += s;
        } else if prepared {
            for f in 0..nf {
                for g in 0..=f {
                    let mut s = 0.0;
                    for (j, u) in c.row(f) {
                        for (l, wv) in c.row(g) {
                            let base = self.contact.col[l as usize] as usize * 3 * m;
                            for a in 0..3 {
                                let e = self.system.eq[3 * j as usize + a];
                                if e == usize::MAX {
                                    continue;
                                }
                                let z = &self.contact.z[base + e..];
                                s += u[a]
                                    * (wv.x * f64::from(z[0])
                                        + wv.y * f64::from(z[m])
                                        + wv.z * f64::from(z[2 * m]));
                            }
                        }
                    }
                    w[f * nf + g] += s;
                    if g != f {
                        w[g * nf + f] += s;
                    }
                }
            }
        } else {
            for g in 0..nf {
                self.solve_row(c, g);
                for f in 0..nf {
                    let mut s = 0.0;
                    for (i, u) in c.row(f) {
                        for k in 0..3 {
                            let e = self.system.eq[3 * i as usize + k];
                            if e != usize::MAX {
                                s += u[k] * f64::from(self.scratch.rhs[(e, 1)]);
                            }
                        }
                    }
                    self.scratch.capacitance[f * nf + g] += s;
                }
            }
        }
    }

    /// `z1 = A^-1 A^T s` for the solved multipliers `s` of the probe's rows `c`.
    fn correction(&mut self, c: ContactCoupling<'_>, t: &[f64], prepared: bool, single_row: bool) {
        let m = self.system.eq_dof.len();
        if single_row {
            let s = t[0];
            self.scratch.z1.iter_mut().for_each(|z| *z *= s);
        } else if prepared {
            for (f, &tf) in t.iter().enumerate() {
                for (l, u) in c.row(f) {
                    let base = self.contact.col[l as usize] as usize * 3 * m;
                    axpy3(
                        self.system.avx2,
                        &mut self.scratch.z1,
                        (u * tf).to_array(),
                        &self.contact.z[base..base + 3 * m],
                    );
                }
            }
        } else {
            self.scratch.rhs.col_mut(1).fill(0.0);
            for (f, &tf) in t.iter().enumerate() {
                add_row(
                    &self.system.eq,
                    c,
                    f,
                    tf,
                    self.scratch.rhs.col_as_slice_mut(1),
                );
            }
            self.solve_column(1);
            for (k, z) in self.scratch.z1.iter_mut().enumerate() {
                *z = f64::from(self.scratch.rhs[(k, 1)]);
            }
        }
    }

    /// Under-relaxation of the modified Newton step (module documentation, "Relaxation"):
    /// a velocity field that reverses from one tick to the next is the frozen matrix's
    /// overshoot, never the body's motion. A velocity component that grows SNAP_GROWTH-fold
    /// in one tick past SNAP_MIN_SPEED is the same overshoot in one direction (an inverted
    /// element snapping back). `z1` becomes the solved (unrelaxed) velocity; returns the
    /// factor on it.
    fn relax(&mut self, v: &[f64]) -> f64 {
        let (mut dot_old_new, mut old2, mut new2) = (0.0, 0.0, 0.0);
        let (mut new_max2, mut old_max2) = (0.0f64, 0.0f64);
        let z0 = self.scratch.rhs.col_as_slice(0);
        for ((z, &d), &z0) in self.scratch.z1.iter_mut().zip(&self.system.eq_dof).zip(z0) {
            let vn = f64::from(z0) - *z;
            *z = vn;
            let vo = v[d];
            dot_old_new += vo * vn;
            old2 += vo * vo;
            new2 += vn * vn;
            new_max2 = new_max2.max(vn * vn);
            old_max2 = old_max2.max(vo * vo);
        }
        let reversed = dot_old_new < REVERSAL_COSINE * (old2 * new2).sqrt()
            && new_max2 > REVERSAL_MIN_SPEED_M_PER_S * REVERSAL_MIN_SPEED_M_PER_S;
        let snapped = new_max2 > SNAP_GROWTH * SNAP_GROWTH * old_max2
            && new_max2 > SNAP_MIN_SPEED_M_PER_S * SNAP_MIN_SPEED_M_PER_S;
        self.state.relaxation = if reversed || snapped {
            self.stats.relaxed_ticks += 1;
            (self.state.relaxation * 0.5).max(MIN_RELAXATION)
        } else {
            (self.state.relaxation * RELAXATION_RECOVERY).min(1.0)
        };
        self.state.relaxation
    }

    /// `v = alpha z1`, `x += h v` on the equations; returns the largest squared nodal speed
    /// (NaN if any value is not finite).
    fn scatter(&self, alpha: f64, x: &mut [f64], v: &mut [f64]) -> f64 {
        let h = self.params.h;
        for (&d, &vn) in self.system.eq_dof.iter().zip(&self.scratch.z1) {
            let vi = alpha * vn;
            v[d] = vi;
            x[d] += vi * h;
        }
        let mut max_v2: f64 = 0.0;
        let mut non_finite = false;
        let mut last = usize::MAX;
        for &d in &self.system.eq_dof {
            let i = d / 3;
            if i != last {
                last = i;
                let s =
                    v[3 * i] * v[3 * i] + v[3 * i + 1] * v[3 * i + 1] + v[3 * i + 2] * v[3 * i + 2];
                non_finite |= !s.is_finite();
                max_v2 = max_v2.max(s);
            }
        }
        if non_finite { f64::NAN } else { max_v2 }
    }

    /// `A^-1 a_g` for row `g` of the probe's term into the second right-hand-side column (the
    /// fallback for nodes without prepared columns).
    fn solve_row(&mut self, c: ContactCoupling<'_>, g: usize) {
        self.scratch.rhs.col_mut(1).fill(0.0);
        add_row(
            &self.system.eq,
            c,
            g,
            1.0,
            self.scratch.rhs.col_as_slice_mut(1),
        );
        self.solve_column(1);
    }

    /// `A^-1` applied in place to column `col` of `rhs` (allocation-free).
    fn solve_column(&mut self, col: usize) {
        if let (Some(sweep), Some(half)) = (&mut self.system.sweep, &self.system.half) {
            sweep.solve_in_place(half, self.scratch.rhs.col_as_slice_mut(col));
            return;
        }
        LltRef::<usize, f32>::new(&self.system.symbolic, &self.system.factor)
            .solve_in_place_with_conj(
                Conj::No,
                self.scratch.rhs.as_mut().subcols_mut(col, 1),
                Par::Seq,
                MemStack::new(&mut self.scratch.stack.buffer),
            );
    }
}

/// `su = ` the sums of the packed rows `rows` of `S` times `u` (`u_G`; length `g`): row `a`
/// adds its dot product with `u[a..]` to entry `a` and its entries times `u[a]` to the entries
/// after it, so all rows give `S u`; entries no row of `rows` reaches stay zero.
fn schur_rows(sys: &CondensedSystem, rows: std::ops::Range<usize>, u: &[f64], su: &mut [f64]) {
    let g = u.len();
    su.iter_mut().for_each(|s| *s = 0.0);
    for a in rows {
        let start = packed_row_start(a, g);
        let row = &sys.schur[start..start + g - a];
        let (head, tail) = su.split_at_mut(a + 1);
        let s = sym_row(sys.avx2, &row[1..], &u[a + 1..], tail, u[a]);
        head[a] += f64::from(row[0]) * u[a] + s;
    }
}
