//! [`StencilLayout`]: where a block's touched particles and terms sit on the dense grid of
//! [`super::StencilGrid`], rebuilt by [`StencilLayout::build`] when the touched set changes:
//! the bounding box, the vector axis and where its groups start along it (the fewest
//! groups), the cell of each particle, the stencil's grid offsets, the groups of eight owners
//! with their lanes' rest data, and the chunks the loop writes.

use glam::{DMat3, DVec3};

use super::offsets::Stencil;
use super::{CUBE, GridBuffers, LANES, MAX_PAIRS};
use crate::meshfree::cloud::{ParticleCloud, outer};

/// Rest data of one lane of a group (module documentation); all zero for a padding lane.
#[derive(Debug, Clone, Copy)]
pub(super) struct LaneRest {
    /// 1 for the owner of a term, 0 for a padding lane.
    pub(super) own: f64,
    /// The moment matrix `A_i = sum_k X_k (x) w_k` over present neighbours (`F~` at rest).
    pub(super) a: DMat3,
    /// `C_i = sum_k c_k` over present neighbours, N/m (corrected).
    pub(super) c: f64,
    /// `A_i^-1` (corrected; identity for the seed variant).
    pub(super) a_inv: DMat3,
    /// `Q_i` (corrected) or the rest strain (seed).
    pub(super) q: DMat3,
    /// `S_i = sum_k w_k` over present neighbours, 1/m.
    pub(super) s: DVec3,
    /// `U_i = sum_k c_k X_k` over present neighbours, N (corrected).
    pub(super) u: DVec3,
}

/// The rest data of a group, lane-wise (structure of arrays, the fields of [`LaneRest`] in
/// single precision), for the vectorised stress; in the order the loop reads them (one group
/// is 832 B, streamed from memory once per evaluation).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct GroupRest {
    pub(super) own: [f32; LANES],
    pub(super) s: [[f32; LANES]; 3],
    /// `A` (seed) or `A^-1` (corrected; zero on padding lanes, so that their `F - I` and `N`
    /// vanish): the one the variant reads.
    pub(super) a: [[f32; LANES]; 9],
    /// `Q` (corrected) or the rest strain (seed).
    pub(super) q: [[f32; LANES]; 9],
    pub(super) u: [[f32; LANES]; 3],
    pub(super) c: [f32; LANES],
}

/// One lane of a [`GroupRest`], read back for the per-lane stress (which streams the packed
/// group instead of the eight [`LaneRest`]s).
#[derive(Debug, Clone, Copy)]
pub(super) struct Lane {
    /// `A` (seed) or `A^-1` (corrected), as [`GroupRest::a`].
    pub(super) a: DMat3,
    pub(super) q: DMat3,
    pub(super) s: DVec3,
    pub(super) u: DVec3,
    pub(super) c: f64,
}

impl GroupRest {
    /// Lane `l`'s rest data (the same values as its [`LaneRest`], `a` as in [`Self::a`]).
    #[inline(always)]
    pub(super) fn lane(&self, l: usize) -> Lane {
        let col = |m: &[[f32; LANES]; 9]| {
            DMat3::from_cols_array(&std::array::from_fn(|e| f64::from(m[e][l])))
        };
        let vec =
            |v: &[[f32; LANES]; 3]| DVec3::new(v[0][l].into(), v[1][l].into(), v[2][l].into());
        Lane {
            a: col(&self.a),
            q: col(&self.q),
            s: vec(&self.s),
            u: vec(&self.u),
            c: self.c[l].into(),
        }
    }
}

const PADDING: LaneRest = LaneRest {
    own: 0.0,
    a: DMat3::IDENTITY,
    c: 0.0,
    a_inv: DMat3::IDENTITY,
    q: DMat3::ZERO,
    s: DVec3::ZERO,
    u: DVec3::ZERO,
};

/// A dense grid over a box of lattice cells with the axes permuted so that `perm[0]` is the
/// fastest (the vector axis): [`LANES`] cells of margin along it (and `shift` more, which
/// moves where the groups of [`LANES`] cells start) and a row length that is a
/// multiple of [`LANES`], so that every group of [`LANES`] owners and every chunk a group
/// writes is aligned to [`LANES`] cells (chunks of different groups never partially
/// overlap), and `reach` cells of margin along the others.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct GridLayout {
    pub(super) perm: [usize; 3],
    origin: [i64; 3],
    dims: [usize; 3],
    cells: usize,
}

impl GridLayout {
    /// The layout over cells `lo..=hi` (lattice coordinates) with `shift` (less than
    /// [`LANES`]) more cells of margin before `lo` along the vector axis, `None` beyond
    /// `capacity` cells.
    fn new(
        perm: [usize; 3],
        shift: usize,
        lo: [i64; 3],
        hi: [i64; 3],
        reach: i64,
        capacity: usize,
    ) -> Option<Self> {
        let mut origin = [0i64; 3];
        let mut dims = [0usize; 3];
        for (a, &ax) in perm.iter().enumerate() {
            let margin = if a == 0 { LANES as i64 } else { reach };
            let before = if a == 0 {
                margin + shift as i64
            } else {
                margin
            };
            origin[a] = lo[ax] - before;
            let span = hi[ax] - origin[a] + 1 + margin;
            dims[a] = if a == 0 {
                (span as usize).div_ceil(LANES) * LANES
            } else {
                span as usize
            };
        }
        let cells = dims[0].checked_mul(dims[1])?.checked_mul(dims[2])?;
        (cells <= capacity && cells <= u32::MAX as usize).then_some(Self {
            perm,
            origin,
            dims,
            cells,
        })
    }

    /// Grid index of lattice cell `c` (inside the box).
    #[inline]
    fn index(&self, c: [usize; 3]) -> usize {
        let g = |a: usize| (c[self.perm[a]] as i64 - self.origin[a]) as usize;
        g(0) + self.dims[0] * (g(1) + self.dims[1] * g(2))
    }

    /// Grid-index offset of lattice offset `d`.
    #[inline]
    fn offset(&self, d: &[i32; 3]) -> isize {
        let g = |a: usize| d[self.perm[a]] as isize;
        g(0) + self.dims[0] as isize * (g(1) + self.dims[1] as isize * g(2))
    }
}

/// The number of groups of [`LANES`] cells the owners at grid indices `sorted` (ascending;
/// a repeat adds nothing) fill when the groups start `s` cells earlier along the vector
/// axis, for every shift `s < LANES`. Shifted by `s`, the owner at index `i` falls in group
/// `(i + s) / LANES`: rows are whole groups long and owners keep [`LANES`] cells of margin
/// at both ends of a row, so no group spans two rows. Two owners adjacent in grid order, `d`
/// cells apart, start a new group for every shift when `d >= LANES`, else for the `d` shifts
/// that carry the first past a multiple of [`LANES`].
fn groups_by_shift(sorted: impl Iterator<Item = usize>) -> [usize; LANES] {
    let mut groups = [0usize; LANES];
    let mut last = None;
    for i in sorted {
        match last.map(|p: usize| (i - p, p % LANES)) {
            Some((d, r)) if d < LANES => {
                for t in LANES - d..LANES {
                    groups[(t + LANES - r) % LANES] += 1;
                }
            }
            _ => groups.iter_mut().for_each(|g| *g += 1),
        }
        last = Some(i);
    }
    groups
}

/// The layout of a block's terms on the grid (module documentation), sized once.
#[derive(Debug, Clone)]
pub(super) struct StencilLayout {
    /// Grid dimensions and the lattice cell of grid cell (0, 0, 0).
    pub(super) grid: GridLayout,
    pub(super) cells: usize,
    capacity_cells: usize,
    /// Grid-index offset of each stencil entry for the current grid.
    pub(super) off: Vec<isize>,
    /// One entry `k` of each pair `(k, -k)` ([`Stencil`]'s `half`), with the grid offset of
    /// `k`; ordered by class.
    pub(super) pairs: Vec<(usize, isize)>,
    /// The stencil by rows along the vector axis: per row the grid offset of its centre and
    /// the stencil entries of offsets -1, 0, +1 along the axis (`usize::MAX`: absent; the
    /// centre row's 0 is the owner). At most nine rows.
    pub(super) rows: Vec<(isize, [usize; 3])>,
    /// Grid-index offset of each of [`CUBE`]'s pairs for the current grid (cube only).
    pub(super) cube_off: [isize; MAX_PAIRS],
    /// Grid-index offset of the centre of each row along the vector axis, at
    /// `(a + 1) + 3 (b + 1)` for offsets `a`, `b` along the other two grid axes (cube only).
    pub(super) cube_rows: [isize; 9],
    /// First cell of every chunk of [`LANES`] cells the group loop writes forces into, ascending
    /// (zeroed before each evaluation; the other chunks stay zero from the build), and a
    /// mark per chunk for building the list.
    pub(super) write_chunks: Vec<u32>,
    chunk_mark: Vec<bool>,
    /// Grid cell of each local particle of the block.
    cell_of_local: Vec<u32>,
    /// (global particle, grid cell) of every touched particle, sorted by grid cell: the
    /// gather and the write-back walk the grid's arrays in memory order.
    pub(super) by_particle: Vec<(u32, u32)>,
    /// Rest position of each entry of `by_particle`, m (read in order by the gather).
    pub(super) rest_of: Vec<DVec3>,
    /// First grid cell of each group of [`LANES`] owners along x, and the lanes' rest data.
    pub(super) groups: Vec<u32>,
    pub(super) lanes: Vec<LaneRest>,
    /// The lanes' rest data by group, lane-wise.
    pub(super) group_rest: Vec<GroupRest>,
    /// (grid cell, term) of every term, sorted when the grid is built.
    order: Vec<(u32, u32)>,
    /// The vector axis and the groups' shift along it forced by a test (every permutation of
    /// the cube's loops tested, and several shifts).
    #[cfg(test)]
    pub(super) fast_axis: Option<(usize, usize)>,
}

impl StencilLayout {
    /// An empty layout of `stencil` for blocks of up to `terms` terms touching up to
    /// `touched` particles, on at most `capacity_cells` grid cells.
    pub(super) fn new(
        stencil: &Stencil,
        terms: usize,
        touched: usize,
        capacity_cells: usize,
    ) -> Self {
        Self {
            grid: GridLayout::default(),
            cells: 0,
            capacity_cells,
            off: vec![0; stencil.dirs.len()],
            pairs: stencil.half.iter().map(|&k| (k, 0isize)).collect(),
            rows: Vec::with_capacity(9),
            cube_off: [0; MAX_PAIRS],
            cube_rows: [0; 9],
            write_chunks: Vec::with_capacity(capacity_cells / LANES + 1),
            chunk_mark: vec![false; capacity_cells / LANES + 1],
            cell_of_local: vec![0; touched],
            by_particle: Vec::with_capacity(touched),
            rest_of: Vec::with_capacity(touched),
            groups: Vec::with_capacity(terms),
            lanes: Vec::with_capacity(LANES * terms),
            group_rest: Vec::with_capacity(terms),
            order: Vec::with_capacity(terms),
            #[cfg(test)]
            fast_axis: None,
        }
    }

    /// Lays out the block ([`super::StencilGrid::build`]), clearing `buf`'s cells in use.
    /// Allocation-free. Returns false (grid not usable) when the bounding box exceeds the
    /// capacity.
    pub(super) fn build(
        &mut self,
        st: &Stencil,
        buf: &mut GridBuffers,
        cloud: &ParticleCloud,
        particles: &[u32],
        owner_local: &[u32],
        rest_strain: &[DMat3],
    ) -> bool {
        self.groups.clear();
        self.by_particle.clear();
        self.lanes.clear();
        self.group_rest.clear();
        self.order.clear();
        self.write_chunks.clear();
        self.cells = 0;
        if particles.is_empty() {
            return true;
        }
        // Reach one, and every entry paired with its negative (pass 1 sums over pairs).
        if st.reach != 1 || st.half_of.iter().any(|h| h.0 == usize::MAX) {
            return false;
        }
        let (lo, hi) = bounding_box(cloud, particles);
        let Some((perm, shift)) = self.vector_axis(st, cloud, particles, owner_local, lo, hi)
        else {
            return false;
        };
        let grid = GridLayout::new(perm, shift, lo, hi, st.reach, self.capacity_cells)
            .expect("the layout fitted above");
        self.place(buf, cloud, particles, grid);
        self.set_offsets(st, perm);
        self.lane_rests(st, &buf.occ, owner_local, rest_strain);
        self.mark_chunks(st);
        self.pack_group_rest(st.seed);
        true
    }

    /// The permutation of the grid axes and the shift of the groups along the vector axis
    /// (first) that make the fewest groups of [`LANES`] owners, among those that fit the
    /// capacity (`None`: none fits). Per axis the owners are sorted once by grid index (row,
    /// then position along the row) and one pass counts the groups of every shift.
    fn vector_axis(
        &mut self,
        st: &Stencil,
        cloud: &ParticleCloud,
        particles: &[u32],
        owner_local: &[u32],
        lo: [i64; 3],
        hi: [i64; 3],
    ) -> Option<([usize; 3], usize)> {
        let mut best: Option<(usize, [usize; 3], usize)> = None;
        for fast in 0..3 {
            #[cfg(test)]
            if self.fast_axis.is_some_and(|(f, _)| f != fast) {
                continue;
            }
            let perm = [fast, (fast + 1) % 3, (fast + 2) % 3];
            let Some(layout) = GridLayout::new(perm, 0, lo, hi, st.reach, self.capacity_cells)
            else {
                continue;
            };
            self.order.clear();
            for &own in owner_local {
                let i = layout.index(cloud.cell_of(particles[own as usize]));
                self.order.push((i as u32, 0));
            }
            self.order.sort_unstable();
            let groups = groups_by_shift(self.order.iter().map(|&(i, _)| i as usize));
            for (shift, &groups) in groups.iter().enumerate() {
                #[cfg(test)]
                if self.fast_axis.is_some_and(|(_, s)| s != shift) {
                    continue;
                }
                if GridLayout::new(perm, shift, lo, hi, st.reach, self.capacity_cells).is_none() {
                    continue;
                }
                if best.is_none_or(|(g, ..)| groups < g) {
                    best = Some((groups, perm, shift));
                }
            }
        }
        self.order.clear();
        best.map(|(_, perm, shift)| (perm, shift))
    }

    /// Takes `grid`, clears `buf`'s cells in use and puts every particle into its cell
    /// (occupancy, the cell of each local particle, the particles by cell and their rest
    /// positions).
    fn place(
        &mut self,
        buf: &mut GridBuffers,
        cloud: &ParticleCloud,
        particles: &[u32],
        grid: GridLayout,
    ) {
        let cells = grid.cells;
        self.grid = grid;
        self.cells = cells;
        for a in [&mut buf.px, &mut buf.py, &mut buf.pz, &mut buf.occ] {
            a[..cells].fill(0.0);
        }
        for a in buf.fc.iter_mut().flatten() {
            a[..3 * cells].fill(0.0);
        }
        for (l, &p) in particles.iter().enumerate() {
            let i = grid.index(cloud.cell_of(p));
            self.cell_of_local[l] = i as u32;
            buf.occ[i] = 1.0;
            self.by_particle.push((p, i as u32));
        }
        self.by_particle.sort_unstable_by_key(|&(p, i)| (i, p));
        self.rest_of.clear();
        for &(p, _) in &self.by_particle {
            self.rest_of.push(cloud.rest_m()[p as usize]);
        }
    }

    /// The grid offsets of the stencil's entries, pairs, [`CUBE`]'s pairs and rows (cube) and
    /// the rows along the vector axis, for the grid axes `perm`.
    fn set_offsets(&mut self, st: &Stencil, perm: [usize; 3]) {
        let grid = self.grid;
        for (o, d) in self.off.iter_mut().zip(&st.dirs) {
            *o = grid.offset(d);
        }
        for (k, o) in &mut self.pairs {
            *o = self.off[*k];
        }
        if st.cube {
            // CUBE is in grid axes: lattice offset d has d[perm[a]] = e[a].
            for (j, e) in CUBE.iter().enumerate() {
                let mut d = [0i32; 3];
                for a in 0..3 {
                    d[perm[a]] = e[a];
                }
                if let Some(k) = st.dirs.iter().position(|dk| *dk == d) {
                    self.cube_off[j] = self.off[k];
                }
            }
            for (r, o) in self.cube_rows.iter_mut().enumerate() {
                let mut d = [0i32; 3];
                d[perm[1]] = r as i32 % 3 - 1;
                d[perm[2]] = r as i32 / 3 - 1;
                *o = grid.offset(&d);
            }
        }
        // Rows along the vector axis: offsets -1, 0, +1 along it of each (other two) offset.
        self.rows.clear();
        for b in -1..=1 {
            for a in -1..=1 {
                let mut centre = [0i32; 3];
                centre[perm[1]] = a;
                centre[perm[2]] = b;
                let mut e = [usize::MAX; 3];
                for (k, d) in st.dirs.iter().enumerate() {
                    if d[perm[1]] == a && d[perm[2]] == b {
                        e[(d[perm[0]] + 1) as usize] = k;
                    }
                }
                if e != [usize::MAX; 3] || (a, b) == (0, 0) {
                    self.rows.push((grid.offset(&centre), e));
                }
            }
        }
    }

    /// The terms by grid cell, their groups of [`LANES`] lanes and each owner lane's rest data
    /// (`occ`: the occupancy of the grid cells).
    fn lane_rests(
        &mut self,
        st: &Stencil,
        occ: &[f32],
        owner_local: &[u32],
        rest_strain: &[DMat3],
    ) {
        for (t, &own) in owner_local.iter().enumerate() {
            self.order
                .push((self.cell_of_local[own as usize], t as u32));
        }
        self.order.sort_unstable();
        for &(i, t) in &self.order {
            let i = i as usize;
            let lane = i & (LANES - 1);
            let base = (i - lane) as u32;
            if self.groups.last() != Some(&base) {
                self.groups.push(base);
                self.lanes.extend_from_slice(&[PADDING; LANES]);
            }
            let slot = self.lanes.len() - LANES + lane;
            self.lanes[slot] = lane_rest(st, occ, &self.off, i, rest_strain, t as usize);
        }
    }

    /// The chunks written: each group's rows (the cube loop at the row's chunk only, in all
    /// three offsets; the pair loops also the chunks before and after, offset 0).
    fn mark_chunks(&mut self, st: &Stencil) {
        let w = LANES as isize;
        let reach: &[isize] = if st.cube { &[0] } else { &[-w, 0, w] };
        for &g in &self.groups {
            for &(ro, _) in &self.rows {
                for &d in reach {
                    let c = (g as isize + ro + d) as usize / LANES;
                    if !self.chunk_mark[c] {
                        self.chunk_mark[c] = true;
                        self.write_chunks.push((LANES * c) as u32);
                    }
                }
            }
        }
        for &c in &self.write_chunks {
            self.chunk_mark[c as usize / LANES] = false;
        }
        self.write_chunks.sort_unstable();
    }

    /// The lanes' rest data by group, lane-wise ([`GroupRest`]).
    fn pack_group_rest(&mut self, seed: bool) {
        for lanes in self.lanes.chunks_exact(LANES) {
            let mut gr = GroupRest::default();
            for (l, lr) in lanes.iter().enumerate() {
                // Corrected: a zero A^-1 makes a padding lane's F - I and N zero.
                let a = if seed {
                    lr.a
                } else if lr.own == 0.0 {
                    DMat3::ZERO
                } else {
                    lr.a_inv
                };
                let (a, q) = (a.to_cols_array(), lr.q.to_cols_array());
                for e in 0..9 {
                    gr.a[e][l] = a[e] as f32;
                    gr.q[e][l] = q[e] as f32;
                }
                for r in 0..3 {
                    gr.s[r][l] = lr.s[r] as f32;
                    gr.u[r][l] = lr.u[r] as f32;
                }
                gr.c[l] = lr.c as f32;
                gr.own[l] = lr.own as f32;
            }
            self.group_rest.push(gr);
        }
    }
}

/// The lattice cells `lo..=hi` holding `particles`.
fn bounding_box(cloud: &ParticleCloud, particles: &[u32]) -> ([i64; 3], [i64; 3]) {
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    for &p in particles {
        let c = cloud.cell_of(p);
        for a in 0..3 {
            lo[a] = lo[a].min(c[a] as i64);
            hi[a] = hi[a].max(c[a] as i64);
        }
    }
    (lo, hi)
}

/// The rest data of the owner of term `t` in grid cell `i`: the sums over its present
/// neighbours (`occ` nonzero at `i + off_k`) and, seed, its rest strain `rest_strain[t]`.
fn lane_rest(
    st: &Stencil,
    occ: &[f32],
    off: &[isize],
    i: usize,
    rest_strain: &[DMat3],
    t: usize,
) -> LaneRest {
    let mut a = DMat3::ZERO;
    let mut q = DMat3::ZERO;
    let mut s = DVec3::ZERO;
    let mut u = DVec3::ZERO;
    let mut csum = 0.0;
    for k in 0..st.dirs.len() {
        if occ[(i as isize + off[k]) as usize] == 0.0 {
            continue;
        }
        let w = DVec3::from_array(st.w[k]);
        let x = st.x[k];
        a += outer(x, w);
        q += outer(x, x * st.c[k]);
        s += w;
        u += DVec3::from_array(st.u[k]);
        csum += st.c[k];
    }
    if st.seed {
        LaneRest {
            own: 1.0,
            a,
            c: 0.0,
            a_inv: DMat3::IDENTITY,
            q: rest_strain[t],
            s,
            u: DVec3::ZERO,
        }
    } else {
        LaneRest {
            own: 1.0,
            a,
            c: csum,
            a_inv: a.inverse(),
            q,
            s,
            u,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_by_shift_counts_what_grouping_each_shift_makes() {
        // Pseudo-random ascending owner indices in rows of 48 cells, owners 8..40 of each (the
        // margins), gaps of 1 to 12: every shift's count against the groups themselves.
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = |m: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % m) as usize
        };
        for _ in 0..200 {
            let mut cells = Vec::new();
            for row in 0..6 {
                let mut g = LANES + next(6);
                while g < 48 - LANES {
                    cells.push(48 * row + g);
                    g += 1 + next(12);
                }
            }
            let counts = groups_by_shift(cells.iter().copied());
            for (s, &count) in counts.iter().enumerate() {
                let mut distinct: Vec<(usize, usize)> = cells
                    .iter()
                    .map(|&i| (i / 48, (i % 48 + s) / LANES))
                    .collect();
                distinct.dedup();
                assert_eq!(count, distinct.len(), "shift {s}, owners {cells:?}");
            }
        }
    }
}
