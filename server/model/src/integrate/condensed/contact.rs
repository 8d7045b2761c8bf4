use super::*;

impl CondensedSolver {
    /// Adds the entry factor: the same region's tick matrix with the rest stiffness unscaled
    /// (`c = 1`), stepped instead on ticks where a node enters the probe's rows. With the
    /// implicit sphere a face entering the contact while sliding otherwise takes its load
    /// against a body `c` times too stiff in its first tick, and the force turns at once (a
    /// 20 mm/s stroke on the default LV: 9.0 % between ticks with `c = 2`, 6.1 % with the
    /// entry factor; docs/decisions.md, "The whole-body rest factor"). Only those ticks use
    /// it, so `c` still guards every other tick against the stiffening tangent. Costs a second
    /// numeric factorisation on the same analysis, its memory and that of a second set of
    /// prepared contact columns (both sets share [`PREPARED_CONTACT_MAX_BYTES`]); a margin of
    /// 1 needs none. Meant for whole-body solvers (a following region's successors are
    /// prepared without it).
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] when the matrix is not positive definite.
    pub fn add_entry_factor(&mut self) -> Result<(), ModelError> {
        if self.params.region.stiffness_margin <= 1.0 {
            return Ok(());
        }
        let schur = unpack_symmetric(&self.system.schur, self.system.gamma_dof.len());
        let parts = self.tick_matrix_parts(&schur);
        let a_lower = parts.lower(1.0)?;
        let mut factor = factorize(&self.system.symbolic, &a_lower)?;
        let half = half_of(self.system.sweep.as_mut(), &mut factor, &a_lower);
        // Columns already prepared: the same nodes through the new factor.
        let mut list: Vec<(u32, u32)> = self
            .contact
            .col
            .iter()
            .enumerate()
            .filter(|(_, c)| **c != u32::MAX)
            .map(|(i, &c)| (c, i as u32))
            .collect();
        list.sort_unstable();
        let nodes: Vec<u32> = list.iter().map(|&(_, i)| i).collect();
        let contact_z = if nodes.is_empty() {
            Vec::new()
        } else {
            self.contact_columns(&factor, &nodes)
        };
        self.system.entry = Some(EntryFactor {
            factor,
            half: half.map(Arc::new),
            contact_z: contact_z.into(),
        });
        Ok(())
    }

    /// Precomputes `A^-1 e` for the three components of each of `nodes` (the nodes a probe
    /// patch can hold: the active touchable surface), so that a tick in contact needs one
    /// right-hand side instead of two. Nodes outside the region are skipped; a patch with a
    /// node not prepared falls back to the second right-hand side. Costs `3 |nodes|` solves
    /// and `12 m |nodes|` bytes (`m` equations), at most [`PREPARED_CONTACT_MAX_BYTES`]:
    /// beyond it nothing is prepared (a client's large whole-body scene must not take
    /// gigabytes and minutes of solves) and the result is `false`.
    pub fn prepare_contact(&mut self, nodes: &[u32]) -> bool {
        self.prepare_contact_within(nodes, PREPARED_CONTACT_MAX_BYTES)
    }

    /// [`Self::prepare_contact`] with the memory limit `max_bytes`; `false` (nothing
    /// prepared, the columns of an earlier call dropped) when the columns would exceed it or
    /// the tick factor was dropped ([`Self::trim_for_tiles`]).
    pub fn prepare_contact_within(&mut self, nodes: &[u32], max_bytes: usize) -> bool {
        let m = self.system.eq_dof.len();
        let mut list: Vec<u32> = nodes
            .iter()
            .copied()
            .filter(|&i| {
                self.system
                    .node_active
                    .get(i as usize)
                    .copied()
                    .unwrap_or(false)
            })
            .collect();
        list.sort_unstable();
        list.dedup();
        self.contact.col.iter_mut().for_each(|c| *c = u32::MAX);
        let factors = if self.system.entry.is_some() { 2 } else { 1 };
        if 12usize
            .saturating_mul(m)
            .saturating_mul(list.len())
            .saturating_mul(factors)
            > max_bytes
            || self.system.factor.is_empty()
        {
            self.contact.z = Vec::new().into();
            if let Some(e) = self.system.entry.as_mut() {
                e.contact_z = Vec::new().into();
            }
            return false;
        }
        for (c, &i) in list.iter().enumerate() {
            self.contact.col[i as usize] = c as u32;
        }
        self.contact.z = self.contact_columns(&self.system.factor, &list).into();
        if let Some(e) = &self.system.entry {
            let z = self.contact_columns(&e.factor, &list);
            if let Some(e) = self.system.entry.as_mut() {
                e.contact_z = z.into();
            }
        }
        true
    }

    /// `A^-1 e` through `factor` (of this solver's analysis) for the three components of each
    /// node of `list`: per node its three columns of `m` values one after the other.
    fn contact_columns(&self, factor: &[f32], list: &[u32]) -> Vec<f32> {
        let m = self.system.eq_dof.len();
        let mut z = vec![0.0; 3 * m * list.len()];
        const BLOCK: usize = 16;
        let mut mem = MemBuffer::new(
            self.system
                .symbolic
                .solve_in_place_scratch::<f32>(3 * BLOCK, Par::Seq),
        );
        for (b, chunk) in list.chunks(BLOCK).enumerate() {
            let mut e = Mat::<f32>::zeros(m, 3 * chunk.len());
            for (j, &i) in chunk.iter().enumerate() {
                for k in 0..3 {
                    let q = self.system.eq[3 * i as usize + k];
                    if q != usize::MAX {
                        e[(q, 3 * j + k)] = 1.0;
                    }
                }
            }
            LltRef::<usize, f32>::new(&self.system.symbolic, factor).solve_in_place_with_conj(
                Conj::No,
                e.as_mut(),
                Par::Seq,
                MemStack::new(&mut mem),
            );
            for j in 0..chunk.len() {
                let c = b * BLOCK + j;
                // A constrained component has a zero column (its e was zero).
                for (k, dst) in z[3 * c * m..3 * (c + 1) * m]
                    .chunks_exact_mut(m)
                    .enumerate()
                {
                    dst.copy_from_slice(e.col_as_slice(3 * j + k));
                }
            }
        }
        z
    }
}
