//! [`StencilGrid`]: the stencil layout of a [`super::TermBlock`]'s force loop. The particles a
//! block touches are copied onto a dense local grid (the bounding box of their lattice cells,
//! structure of arrays), so that neighbour `k` of the particle in grid cell `i` is the cell
//! `i + off_k` for a constant `off_k`, and four owners adjacent along x are one vector: their
//! four neighbours `k` are four consecutive cells, loaded and stored without any index.
//!
//! **Why it is exact.** On the lattice every per-pair rest quantity depends on the stencil
//! offset only: the uncorrected weight `w_k` ([`ParticleCloud::pair_weight`]), the rest
//! offset `X_k` and the hourglass stiffness `c_k`. The corrected gradient is
//! `g_ik = A_i^-T w_k` (Bonet-Lok, [`super::cloud`]), so with `F~_i = sum_k d_ik (x) w_k`
//! (`d_ik = x_j - x_i`, over present neighbours):
//! - `F_i = F~_i A_i^-1` (seed: `F_i = F~_i`, `A_i^-1 = I`);
//! - the hourglass matrix `H_i = sum_k c_k e_ik (x) X_k`, `e_ik = F_i X_k - d_ik`, is
//!   `F_i Q_i - D_i` with the rest constant `Q_i = sum_k c_k X_k X_k^T` and
//!   `D_i = sum_k d_ik (x) c_k X_k`, summed in the same pass as `F~_i`;
//! - the force on neighbour `k` is minus `grad_ik = N_i w_k - F_i u_k + c_k d_ik`, with
//!   `N_i = (V P_i + H_i) A_i^-T` and `u_k = c_k X_k`, and the owner's is
//!   `sum_k grad_ik = N_i S_i - F_i U_i + sum_k c_k d_ik` with the rest sums `S_i = sum_k w_k`,
//!   `U_i = sum_k u_k` over present neighbours.
//!
//! These are the formulas of [`super::block`] regrouped, so the forces agree with the general
//! loop to round-off (unit test in `block.rs`). Per term only a few 3x3 matrices are stored
//! (no per-pair data at all); a missing neighbour is a zero in the occupancy array, which masks
//! `d_ik` in the first pass; in the second pass its `grad_ik` is written into the empty cell,
//! whose force nobody reads. Lanes of a group that own no term (tied particles, empty cells)
//! have `N = F = 0` and masked `d`, so they add nothing.
//!
//! **The 26-cell cube.** Both passes run over pairs `(k, -k)` (`w_-k = -w_k`, same class),
//! so pass 2 forms each pair's `(N - beta F) w_k` once for both entries. When the stencil is
//! the whole cube (the usual `h = spacing`), `w_k` is a class constant times the lattice
//! offset, so the loops are written out for its 13 pairs with every zero and sign known at
//! compile time: sums and differences of positions and of matrix columns, one product per
//! class, instead of a product per weight component. The general stencil keeps the pair
//! loops; a unit test in `block.rs` checks both, along every vector axis.
//!
//! **When it is used.** When the bounding box of the touched particles fits the grid's
//! capacity (sized at construction: no allocation at run time); otherwise (active regions far
//! apart) the block falls back to its general loop.
//!
//! Neighbours: built and driven by [`super::block::TermBlock`]; rest data from
//! [`super::cloud::ParticleCloud`].

use glam::{DMat3, DVec3};

use super::MeshfreeVariant;
use super::cloud::{ParticleCloud, outer};
use crate::material::MaterialParams;
use crate::simd::{Avx2Fma, Plain4};

mod group;
use group::cube_force_at;

/// Most pairs `(k, -k)` of a stencil of reach one (the 26-cell cube).
const MAX_PAIRS: usize = 13;

/// The 26-cell cube's pairs `(k, -k)` by the `k` whose first nonzero offset is positive, in
/// grid axes (the vector axis first), by class: faces, edges, corners.
const CUBE: [[i32; 3]; MAX_PAIRS] = [
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 1, 0],
    [1, -1, 0],
    [1, 0, 1],
    [1, 0, -1],
    [0, 1, 1],
    [0, 1, -1],
    [1, 1, 1],
    [1, 1, -1],
    [1, -1, 1],
    [1, -1, -1],
];

/// Class (0 faces, 1 edges, 2 corners) of each of [`CUBE`]'s pairs.
const CUBE_CLASS: [usize; MAX_PAIRS] = [0, 0, 0, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2];

/// Rest data of one lane of a group (module documentation); all zero for a padding lane.
#[derive(Debug, Clone, Copy)]
struct LaneRest {
    /// 1 for the owner of a term, 0 for a padding lane.
    own: f64,
    /// The moment matrix `A_i = sum_k X_k (x) w_k` over present neighbours (`F~` at rest).
    a: DMat3,
    /// `C_i = sum_k c_k` over present neighbours, N/m (corrected).
    c: f64,
    /// `A_i^-1` (corrected; identity for the seed variant).
    a_inv: DMat3,
    /// `Q_i` (corrected) or the rest strain (seed).
    q: DMat3,
    /// `S_i = sum_k w_k` over present neighbours, 1/m.
    s: DVec3,
    /// `U_i = sum_k c_k X_k` over present neighbours, N (corrected).
    u: DVec3,
}

/// The rest data of a group, lane-wise (structure of arrays, the fields of [`LaneRest`]), for
/// the vectorised St. Venant-Kirchhoff stress; in the order the loop reads them (one group
/// is 832 B, streamed from memory once per evaluation).
#[derive(Debug, Clone, Copy, Default)]
struct GroupRest {
    own: [f64; 4],
    s: [[f64; 4]; 3],
    /// `A` (seed) or `A^-1` (corrected; zero on padding lanes, so that their `F - I` and `N`
    /// vanish): the one the variant reads.
    a: [[f64; 4]; 9],
    /// `Q` (corrected) or the rest strain (seed).
    q: [[f64; 4]; 9],
    u: [[f64; 4]; 3],
    c: [f64; 4],
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
/// fastest (the vector axis): four cells of margin along it and a row length that is a
/// multiple of four, so that every group of four owners and every chunk a group writes is
/// aligned to four cells (chunks of different groups never partially overlap), and `reach`
/// cells of margin along the others.
#[derive(Debug, Clone, Copy, Default)]
struct GridLayout {
    perm: [usize; 3],
    origin: [i64; 3],
    dims: [usize; 3],
    cells: usize,
}

impl GridLayout {
    /// The layout over cells `lo..=hi` (lattice coordinates), `None` beyond `capacity` cells.
    fn new(
        perm: [usize; 3],
        lo: [i64; 3],
        hi: [i64; 3],
        reach: i64,
        capacity: usize,
    ) -> Option<Self> {
        let mut origin = [0i64; 3];
        let mut dims = [0usize; 3];
        for (a, &ax) in perm.iter().enumerate() {
            let margin = if a == 0 { 4 } else { reach };
            origin[a] = lo[ax] - margin;
            let span = hi[ax] - origin[a] + 1 + margin;
            dims[a] = if a == 0 {
                ((span + 3) / 4 * 4) as usize
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

/// The stencil layout of a term block (module documentation), sized once.
#[derive(Debug, Clone)]
pub(crate) struct StencilGrid {
    /// The AVX2 + FMA token where the CPU has them.
    #[cfg(target_arch = "x86_64")]
    isa: Option<Avx2Fma>,
    seed: bool,
    volume_m3: f64,
    /// Stencil offsets (lattice cells) and, per offset, `w_k` (1/m), `X_k` (m), `c_k` (N/m)
    /// and `u_k = c_k X_k` (N).
    dirs: Vec<[i32; 3]>,
    w: Vec<[f64; 3]>,
    x: Vec<DVec3>,
    c: Vec<f64>,
    u: Vec<[f64; 3]>,
    /// Largest component of a stencil offset (the stencil loop needs 1: the 26-cell cube or
    /// part of it).
    reach: i64,
    /// The stencil by rows along the vector axis: per row the grid offset of its centre and
    /// the stencil entries of offsets -1, 0, +1 along the axis (`usize::MAX`: absent; the
    /// centre row's 0 is the owner). At most nine rows.
    rows: Vec<(isize, [usize; 3])>,
    /// Grid-index offset of each stencil entry for the current grid.
    off: Vec<isize>,
    /// Half the stencil, one entry `k` of each pair `(k, -k)`, with the grid offset of `k`;
    /// ordered by class.
    pairs: Vec<(usize, isize)>,
    /// Classes of stencil entries of equal length: `beta = c_k / phi_k` (`c_k X_k = beta
    /// w_k`), `c_k`, and their range in `pairs`.
    classes: Vec<(f64, f64, std::ops::Range<usize>)>,
    /// Class of each stencil entry.
    class_of: Vec<usize>,
    /// Per stencil entry `k`, its pair in `pairs` and whether `k` is the pair's negative
    /// (`w_k = -w_pair`): pass 2 computes `(N - beta F) w` once per pair.
    half_of: Vec<(usize, bool)>,
    /// The stencil is the whole 26-cell cube: the loops run [`CUBE`]'s pairs with their
    /// weights' zeros and signs known at compile time.
    cube: bool,
    /// Grid-index offset of each of [`CUBE`]'s pairs for the current grid (cube only).
    cube_off: [isize; MAX_PAIRS],
    /// The nonzero components' magnitude `|w_k|_max` of each class (faces, edges, corners),
    /// 1/m: `w_k = scale * (the lattice offset)` exactly (cube only).
    cube_scale: [f64; 3],
    /// Grid-index offset of the centre of each row along the vector axis, at
    /// `(a + 1) + 3 (b + 1)` for offsets `a`, `b` along the other two grid axes (cube only).
    cube_rows: [isize; 9],
    /// Grid dimensions and the lattice cell of grid cell (0, 0, 0).
    layout: GridLayout,
    cells: usize,
    capacity_cells: usize,
    /// Positions and occupancy (1 where a touched particle sits) per grid cell.
    px: Vec<f64>,
    py: Vec<f64>,
    pz: Vec<f64>,
    occ: Vec<f64>,
    /// Forces (x, y, z components) by offset `dx` along the vector axis, stored at their
    /// owner's cell (the cube loop: no shift across lanes; the pair loops write offset 0
    /// only, shifted) and interleaved by chunk of four cells: chunk `c` holds `fm`, `f0`, `fp`
    /// of its four cells at `12 c + 4 (dx + 1)`; the force on cell `i` is
    /// `f0[i] + fm[i + 1] + fp[i - 1]` ([`cube_force_at`]).
    fc: [Vec<f64>; 3],
    /// First cell of every chunk of four cells the group loop writes forces into, ascending
    /// (zeroed before each evaluation; the other chunks stay zero from the build), and a
    /// mark per chunk for building the list.
    write_chunks: Vec<u32>,
    chunk_mark: Vec<bool>,
    /// Grid cell of each local particle of the block.
    cell_of_local: Vec<u32>,
    /// (global particle, grid cell) of every touched particle, sorted by grid cell: the
    /// gather and the write-back walk the grid's arrays in memory order.
    by_particle: Vec<(u32, u32)>,
    /// Rest position of each entry of `by_particle`, m (read in order by the gather).
    rest_of: Vec<DVec3>,
    /// First grid cell of each group of four owners along x, and the lanes' rest data.
    groups: Vec<u32>,
    lanes: Vec<LaneRest>,
    /// The lanes' rest data by group, lane-wise.
    group_rest: Vec<GroupRest>,
    /// (grid cell, term) of every term, sorted when the grid is built.
    order: Vec<(u32, u32)>,
    /// The vector axis forced by a test (every permutation of the cube's loops tested).
    #[cfg(test)]
    fast_axis: Option<usize>,
}

impl StencilGrid {
    /// A grid for blocks of up to `terms` terms touching up to `touched` particles of `cloud`,
    /// holding at most `capacity_cells` grid cells.
    pub(crate) fn new(
        cloud: &ParticleCloud,
        terms: usize,
        touched: usize,
        capacity_cells: usize,
    ) -> Self {
        let s = cloud.lattice().spacing_m();
        // By x offset first, so that the second pass's partially overlapping read-modify-writes
        // of one row (offsets -1, 0, +1 along x) are a third of the stencil apart.
        let mut dirs: Vec<[i32; 3]> = cloud.lattice().stencil().to_vec();
        dirs.sort_by_key(|d| (d[0], d[2], d[1]));
        let x: Vec<DVec3> = dirs
            .iter()
            .map(|d| DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64) * s)
            .collect();
        let w: Vec<[f64; 3]> = x.iter().map(|&o| cloud.pair_weight(o).to_array()).collect();
        let c: Vec<f64> = x.iter().map(|&o| cloud.hourglass_stiffness(o)).collect();
        let u = x
            .iter()
            .zip(&c)
            .map(|(o, c)| (*o * *c).to_array())
            .collect();
        let reach = dirs
            .iter()
            .flat_map(|d| d.iter().map(|v| v.unsigned_abs() as i64))
            .max()
            .unwrap_or(0);
        // Pairs (k, -k) by class of length; w_-k = -w_k exactly (the weight is odd).
        let mut half: Vec<usize> = (0..dirs.len())
            .filter(|&k| {
                let d = dirs[k];
                let first = d.iter().copied().find(|&v| v != 0).unwrap_or(0);
                first > 0 && dirs.contains(&[-d[0], -d[1], -d[2]])
            })
            .collect();
        let len2 = |k: usize| dirs[k].iter().map(|v| v * v).sum::<i32>();
        half.sort_by_key(|&k| len2(k));
        let mut classes: Vec<(f64, f64, std::ops::Range<usize>)> = Vec::new();
        for (j, &k) in half.iter().enumerate() {
            if classes
                .last()
                .is_some_and(|cl| len2(half[cl.2.start]) == len2(k))
            {
                classes.last_mut().expect("a class").2.end = j + 1;
            } else {
                let phi = DVec3::from_array(w[k]).length() / x[k].length();
                classes.push((c[k] / phi, c[k], j..j + 1));
            }
        }
        let mut class_of = vec![0usize; dirs.len()];
        for (ci, cl) in classes.iter().enumerate() {
            for &k in &half[cl.2.clone()] {
                let d = dirs[k];
                class_of[k] = ci;
                if let Some(m) = dirs.iter().position(|e| *e == [-d[0], -d[1], -d[2]]) {
                    class_of[m] = ci;
                }
            }
        }
        let mut half_of = vec![(usize::MAX, false); dirs.len()];
        for (j, &k) in half.iter().enumerate() {
            let d = dirs[k];
            half_of[k] = (j, false);
            if let Some(m) = dirs.iter().position(|e| *e == [-d[0], -d[1], -d[2]]) {
                half_of[m] = (j, true);
            }
        }
        let pairs = half.iter().map(|&k| (k, 0isize)).collect();
        // The 26-cell cube: three classes (faces, edges, corners, by length).
        let cube = dirs.len() == 26 && reach == 1 && classes.len() == 3;
        let mut cube_scale = [0.0; 3];
        for (sc, cl) in cube_scale.iter_mut().zip(&classes) {
            *sc = w[half[cl.2.start]]
                .iter()
                .fold(0.0f64, |a, v| a.max(v.abs()));
        }
        Self {
            #[cfg(target_arch = "x86_64")]
            isa: Avx2Fma::detect(),
            seed: cloud.params().variant == MeshfreeVariant::Seed,
            volume_m3: cloud.volume_m3(),
            off: vec![0; dirs.len()],
            dirs,
            w,
            x,
            c,
            u,
            reach,
            rows: Vec::with_capacity(9),
            pairs,
            classes,
            class_of,
            half_of,
            cube,
            cube_off: [0; MAX_PAIRS],
            cube_scale,
            cube_rows: [0; 9],
            layout: GridLayout::default(),
            cells: 0,
            capacity_cells,
            px: vec![0.0; capacity_cells],
            py: vec![0.0; capacity_cells],
            pz: vec![0.0; capacity_cells],
            occ: vec![0.0; capacity_cells],
            fc: [
                vec![0.0; 3 * capacity_cells],
                vec![0.0; 3 * capacity_cells],
                vec![0.0; 3 * capacity_cells],
            ],
            write_chunks: Vec::with_capacity(capacity_cells / 4 + 1),
            chunk_mark: vec![false; capacity_cells / 4 + 1],
            cell_of_local: vec![0; touched],
            by_particle: Vec::with_capacity(touched),
            rest_of: Vec::with_capacity(touched),
            groups: Vec::with_capacity(terms),
            lanes: Vec::with_capacity(4 * terms),
            group_rest: Vec::with_capacity(terms),
            order: Vec::with_capacity(terms),
            #[cfg(test)]
            fast_axis: None,
        }
    }

    /// Runs the plain lanes from now on even where the CPU has AVX2 (tests of both builds).
    #[cfg(test)]
    pub(crate) fn plain_lanes_only(&mut self) {
        #[cfg(target_arch = "x86_64")]
        {
            self.isa = None;
        }
    }

    /// Runs the general stencil's pair loops from now on even for the 26-cell cube (tests of
    /// both).
    #[cfg(test)]
    pub(crate) fn pair_loops_only(&mut self) {
        self.cube = false;
    }

    /// Vectorises along lattice axis `axis` from the next layout on (tests of every axis
    /// permutation).
    #[cfg(test)]
    pub(crate) fn force_vector_axis(&mut self, axis: usize) {
        self.fast_axis = Some(axis);
    }

    /// Grid cells in use and groups of four lanes (for studies of the lane occupancy).
    pub(crate) fn size(&self) -> (usize, usize) {
        (self.cells, self.groups.len())
    }

    /// Lays out the block: `particles` (global index of each local particle), the local index
    /// of each term's owner and each term's rest strain (seed). Allocation-free. Returns false
    /// (grid not usable) when the bounding box exceeds the capacity.
    pub(crate) fn build(
        &mut self,
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
        if self.reach != 1 || self.half_of.iter().any(|h| h.0 == usize::MAX) {
            return false;
        }
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for &p in particles {
            let c = cloud.cell_of(p);
            for a in 0..3 {
                lo[a] = lo[a].min(c[a] as i64);
                hi[a] = hi[a].max(c[a] as i64);
            }
        }
        // The vector axis: the one whose groups of four hold the most owners (fewest groups).
        let mut best: Option<(usize, [usize; 3])> = None;
        for fast in 0..3 {
            #[cfg(test)]
            if self.fast_axis.is_some_and(|f| f != fast) {
                continue;
            }
            let perm = [fast, (fast + 1) % 3, (fast + 2) % 3];
            let Some(layout) = GridLayout::new(perm, lo, hi, self.reach, self.capacity_cells)
            else {
                continue;
            };
            self.order.clear();
            for &own in owner_local {
                let i = layout.index(cloud.cell_of(particles[own as usize]));
                self.order.push(((i & !3) as u32, 0));
            }
            self.order.sort_unstable();
            let mut groups = 0;
            let mut last = None;
            for &(b, _) in &self.order {
                if last != Some(b) {
                    groups += 1;
                    last = Some(b);
                }
            }
            if best.is_none_or(|(g, _)| groups < g) {
                best = Some((groups, perm));
            }
        }
        self.order.clear();
        let Some((_, perm)) = best else {
            return false;
        };
        let layout = GridLayout::new(perm, lo, hi, self.reach, self.capacity_cells)
            .expect("the layout fitted above");
        let cells = layout.cells;
        self.layout = layout;
        self.cells = cells;
        for a in [&mut self.px, &mut self.py, &mut self.pz, &mut self.occ] {
            a[..cells].fill(0.0);
        }
        for a in &mut self.fc {
            a[..3 * cells].fill(0.0);
        }
        for (l, &p) in particles.iter().enumerate() {
            let i = layout.index(cloud.cell_of(p));
            self.cell_of_local[l] = i as u32;
            self.occ[i] = 1.0;
            self.by_particle.push((p, i as u32));
        }
        self.by_particle.sort_unstable_by_key(|&(p, i)| (i, p));
        self.rest_of.clear();
        for &(p, _) in &self.by_particle {
            self.rest_of.push(cloud.rest_m()[p as usize]);
        }
        for (o, d) in self.off.iter_mut().zip(&self.dirs) {
            *o = layout.offset(d);
        }
        for (k, o) in &mut self.pairs {
            *o = self.off[*k];
        }
        if self.cube {
            // CUBE is in grid axes: lattice offset d has d[perm[a]] = e[a].
            for (j, e) in CUBE.iter().enumerate() {
                let mut d = [0i32; 3];
                for a in 0..3 {
                    d[perm[a]] = e[a];
                }
                if let Some(k) = self.dirs.iter().position(|dk| *dk == d) {
                    self.cube_off[j] = self.off[k];
                }
            }
            for (r, o) in self.cube_rows.iter_mut().enumerate() {
                let mut d = [0i32; 3];
                d[perm[1]] = r as i32 % 3 - 1;
                d[perm[2]] = r as i32 / 3 - 1;
                *o = layout.offset(&d);
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
                for (k, d) in self.dirs.iter().enumerate() {
                    if d[perm[1]] == a && d[perm[2]] == b {
                        e[(d[perm[0]] + 1) as usize] = k;
                    }
                }
                if e != [usize::MAX; 3] || (a, b) == (0, 0) {
                    self.rows.push((layout.offset(&centre), e));
                }
            }
        }
        for (t, &own) in owner_local.iter().enumerate() {
            self.order
                .push((self.cell_of_local[own as usize], t as u32));
        }
        self.order.sort_unstable();
        for &(i, t) in &self.order {
            let i = i as usize;
            let lane = i & 3;
            let base = (i - lane) as u32;
            if self.groups.last() != Some(&base) {
                self.groups.push(base);
                self.lanes.extend_from_slice(&[PADDING; 4]);
            }
            let mut a = DMat3::ZERO;
            let mut q = DMat3::ZERO;
            let mut s = DVec3::ZERO;
            let mut u = DVec3::ZERO;
            let mut csum = 0.0;
            for k in 0..self.dirs.len() {
                if self.occ[(i as isize + self.off[k]) as usize] == 0.0 {
                    continue;
                }
                let w = DVec3::from_array(self.w[k]);
                let x = self.x[k];
                a += outer(x, w);
                q += outer(x, x * self.c[k]);
                s += w;
                u += DVec3::from_array(self.u[k]);
                csum += self.c[k];
            }
            let slot = self.lanes.len() - 4 + lane;
            self.lanes[slot] = if self.seed {
                LaneRest {
                    own: 1.0,
                    a,
                    c: 0.0,
                    a_inv: DMat3::IDENTITY,
                    q: rest_strain[t as usize],
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
            };
        }
        // The chunks written: each group's rows (the cube loop at the row's chunk only, in
        // all three offsets; the pair loops also the chunks before and after, offset 0).
        let reach: &[isize] = if self.cube { &[0] } else { &[-4, 0, 4] };
        for &g in &self.groups {
            for &(ro, _) in &self.rows {
                for &d in reach {
                    let c = (g as isize + ro + d) as usize / 4;
                    if !self.chunk_mark[c] {
                        self.chunk_mark[c] = true;
                        self.write_chunks.push(4 * c as u32);
                    }
                }
            }
        }
        for &c in &self.write_chunks {
            self.chunk_mark[c as usize / 4] = false;
        }
        self.write_chunks.sort_unstable();
        for lanes in self.lanes.chunks_exact(4) {
            let mut gr = GroupRest::default();
            for (l, lr) in lanes.iter().enumerate() {
                // Corrected: a zero A^-1 makes a padding lane's F - I and N zero.
                let a = if self.seed {
                    lr.a
                } else if lr.own == 0.0 {
                    DMat3::ZERO
                } else {
                    lr.a_inv
                };
                let (a, q) = (a.to_cols_array(), lr.q.to_cols_array());
                for e in 0..9 {
                    gr.a[e][l] = a[e];
                    gr.q[e][l] = q[e];
                }
                for r in 0..3 {
                    gr.s[r][l] = lr.s[r];
                    gr.u[r][l] = lr.u[r];
                }
                gr.c[l] = lr.c;
                gr.own[l] = lr.own;
            }
            self.group_rest.push(gr);
        }
        true
    }

    /// The terms' forces (N) at positions `x` (m, by global particle) written (`add`: added)
    /// into `f` (by global particle) for every touched particle, in the AVX2 + FMA build
    /// where the CPU has it. The grid holds displacements from the rest positions of the
    /// cloud the grid was built with (zero in empty cells).
    pub(crate) fn forces(&mut self, mat: &MaterialParams, x: &[DVec3], f: &mut [DVec3], add: bool) {
        for (&(p, i), r) in self.by_particle.iter().zip(&self.rest_of) {
            let (i, xp) = (i as usize, x[p as usize] - *r);
            self.px[i] = xp.x;
            self.py[i] = xp.y;
            self.pz[i] = xp.z;
        }
        let [f0, f1, f2] = &mut self.fc;
        for &c in &self.write_chunks {
            let c = 3 * c as usize;
            for a in [&mut *f0, &mut *f1, &mut *f2] {
                a[c..c + 12].fill(0.0);
            }
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = self.isa {
            // SAFETY: the token.
            unsafe { self.group_loop_avx2(isa, mat) };
        } else {
            self.group_loop::<Plain4>((), mat);
        }
        #[cfg(not(target_arch = "x86_64"))]
        self.group_loop::<Plain4>((), mat);
        for &(p, i) in &self.by_particle {
            let i = i as usize;
            let fc = &self.fc;
            let fi = DVec3::new(
                cube_force_at(&fc[0], i),
                cube_force_at(&fc[1], i),
                cube_force_at(&fc[2], i),
            );
            if add {
                f[p as usize] += fi;
            } else {
                f[p as usize] = fi;
            }
        }
    }
}
