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
use super::cloud::{MAX_STENCIL, ParticleCloud, outer};
use crate::material::stvk::{green_strain, stvk_stress};
use crate::material::{MaterialModel, MaterialParams, first_piola};
#[cfg(target_arch = "x86_64")]
use crate::simd::Ymm;
use crate::simd::{Avx2Fma, Lanes4, Plain4};

/// Nine lane vectors of a column-major 3x3 matrix per lane.
#[inline(always)]
fn lane_mat<V: Lanes4>(isa: V::Isa, a: &[[f64; 4]; 9]) -> [V; 9] {
    // A loop, not `array::from_fn`: closures do not inherit the caller's target features.
    let mut m = [V::zero(isa); 9];
    for (m, a) in m.iter_mut().zip(a) {
        *m = V::from_array(isa, *a);
    }
    m
}

/// `N - beta_c (F - I)` for each class `c` of stencil length from `f` = `F - I` (at most
/// three; `N` when `seed`): with `c_k X_k = beta_c w_k`, the part `N w_k - F c_k X_k + c_k X_k`
/// of `grad_ik` (module documentation) is `(N - beta_c (F - I)) w_k`.
#[inline(always)]
fn class_matrices<V: Lanes4>(
    n: &[V; 9],
    f: &[V; 9],
    classes: &[(f64, f64, std::ops::Range<usize>)],
    seed: bool,
    isa: V::Isa,
) -> [[V; 9]; 3] {
    let mut out = [*n; 3];
    if !seed {
        for (o, cl) in out.iter_mut().zip(classes) {
            let beta = V::splat(isa, cl.0);
            for e in 0..9 {
                o[e] = V::nmadd(f[e], beta, n[e]);
            }
        }
    }
    out
}

/// `a b` lane-wise (column-major).
#[inline(always)]
fn mat_mul<V: Lanes4>(a: &[V; 9], b: &[V; 9]) -> [V; 9] {
    let mut out = *a;
    for c in 0..3 {
        for r in 0..3 {
            let mut acc = a[r].mul(b[3 * c]);
            acc = V::madd(a[3 + r], b[3 * c + 1], acc);
            acc = V::madd(a[6 + r], b[3 * c + 2], acc);
            out[3 * c + r] = acc;
        }
    }
    out
}

/// `a v` lane-wise (column-major `a`).
#[inline(always)]
fn mat_vec<V: Lanes4>(a: &[V; 9], v: &[V; 3]) -> [V; 3] {
    let mut out = *v;
    for (r, o) in out.iter_mut().enumerate() {
        let mut acc = a[r].mul(v[0]);
        acc = V::madd(a[3 + r], v[1], acc);
        acc = V::madd(a[6 + r], v[2], acc);
        *o = acc;
    }
    out
}

/// The column-major 3x3 matrix of each lane of nine lane vectors.
#[inline(always)]
fn lane_matrices<V: Lanes4>(a: &[V; 9]) -> [[f64; 9]; 4] {
    let c: [[f64; 4]; 9] = [
        a[0].to_array(),
        a[1].to_array(),
        a[2].to_array(),
        a[3].to_array(),
        a[4].to_array(),
        a[5].to_array(),
        a[6].to_array(),
        a[7].to_array(),
        a[8].to_array(),
    ];
    let mut out = [[0.0; 9]; 4];
    for (l, m) in out.iter_mut().enumerate() {
        for (e, v) in m.iter_mut().enumerate() {
            *v = c[e][l];
        }
    }
    out
}

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

    /// [`Self::group_loop`] on AVX2 + FMA lanes, compiled for them (the token proves the CPU
    /// has them).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn group_loop_avx2(&mut self, isa: Avx2Fma, mat: &MaterialParams) {
        self.group_loop::<Ymm>(isa, mat);
    }

    /// Every group's forces from the grid positions into the grid forces (module
    /// documentation for the formulas).
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // one index into several 3x3 lane matrices
    fn group_loop<V: Lanes4>(&mut self, isa: V::Isa, mat: &MaterialParams) {
        let Self {
            seed,
            volume_m3: v,
            w: ws,
            c: cs,
            u: us,
            off,
            rows,
            pairs,
            classes,
            class_of,
            half_of,
            cube,
            cube_off,
            cube_scale,
            cube_rows,
            layout,
            px,
            py,
            pz,
            fc,
            groups,
            lanes,
            group_rest,
            ..
        } = self;
        let stvk = mat.model == MaterialModel::StVenantKirchhoff;
        let (seed, v) = (*seed, *v);
        let nk = off.len();
        assert!(nk <= MAX_STENCIL && ws.len() == nk && cs.len() == nk && us.len() == nk);
        let (cube, perm) = (*cube, layout.perm);
        let zero = V::zero(isa);
        // Pass 2's `(N - beta F) w_k` of each pair, written before it is read.
        assert!(pairs.len() <= MAX_PAIRS);
        let mut ah = [[zero; 3]; MAX_PAIRS];
        for (g, &base) in groups.iter().enumerate() {
            let b = base as usize;
            let lanes = &lanes[4 * g..4 * g + 4];
            let own = V::from_array(isa, group_rest[g].own);
            let ui = [
                V::load(isa, px, b),
                V::load(isa, py, b),
                V::load(isa, pz, b),
            ];
            // Pass 1, over pairs (k, -k) (w_-k = -w_k): G = sum_k u_(i+k) (x) w_k, and
            // (corrected) Gb = sum_k beta_k u_(i+k) (x) w_k = sum_k u_(i+k) (x) c_k X_k and
            // sum_k c_k u_(i+k), class by class (beta and c depend on |k| only).
            let mut ga = [zero; 9];
            let mut gb = [zero; 9];
            let mut cu = [zero; 3];
            if cube {
                // The same sums with w_k = scale_c e_k: per class the signed sums of the
                // u_(i+k) - u_(i-k) by grid axis (columns perm[a]), scaled once.
                let (gl, sl) = pass_one_cube::<V>(isa, b, cube_off, px, py, pz, seed);
                for (c, &(beta, ck, _)) in classes.iter().enumerate() {
                    let scale = V::splat(isa, cube_scale[c]);
                    for a in 0..3 {
                        for r in 0..3 {
                            let e = 3 * perm[a] + r;
                            if seed {
                                ga[e] = V::madd(gl[c][3 * a + r], scale, ga[e]);
                            } else {
                                let gc = gl[c][3 * a + r].mul(scale);
                                ga[e] = ga[e].add(gc);
                                gb[e] = V::madd(gc, V::splat(isa, beta), gb[e]);
                            }
                        }
                    }
                    if !seed {
                        let cv = V::splat(isa, ck);
                        for r in 0..3 {
                            cu[r] = V::madd(sl[c][r], cv, cu[r]);
                        }
                    }
                }
            }
            for &(beta, ck, ref range) in classes.iter().filter(|_| !cube) {
                let mut gc = [zero; 9];
                let mut sc = [zero; 3];
                for &(k, o) in &pairs[range.clone()] {
                    let (hi, lo) = ((b as isize + o) as usize, (b as isize - o) as usize);
                    let a = [
                        V::load(isa, px, hi),
                        V::load(isa, py, hi),
                        V::load(isa, pz, hi),
                    ];
                    let m = [
                        V::load(isa, px, lo),
                        V::load(isa, py, lo),
                        V::load(isa, pz, lo),
                    ];
                    let w = ws[k];
                    for r in 0..3 {
                        let d = a[r].sub(m[r]);
                        for c in 0..3 {
                            gc[3 * c + r] = V::madd(d, V::splat(isa, w[c]), gc[3 * c + r]);
                        }
                        if !seed {
                            sc[r] = sc[r].add(a[r].add(m[r]));
                        }
                    }
                }
                if seed {
                    for e in 0..9 {
                        ga[e] = ga[e].add(gc[e]);
                    }
                } else {
                    let (bv, cv) = (V::splat(isa, beta), V::splat(isa, ck));
                    for e in 0..9 {
                        ga[e] = ga[e].add(gc[e]);
                        gb[e] = V::madd(gc[e], bv, gb[e]);
                    }
                    for r in 0..3 {
                        cu[r] = V::madd(sc[r], cv, cu[r]);
                    }
                }
            }
            let (nm, fm, ov) = if seed || stvk {
                // St. Venant-Kirchhoff lane-wise (the seed variant's law always).
                // Seed: F = F~ = A + G - u_i (x) S, E = (F^T F - I) / 2 - E0, N = V F S(E).
                // Corrected: F - I = (F~ - A) A^-1 = (G - u_i (x) S) A^-1 (A A^-1 = I; zero on
                // padding lanes, whose A^-1 is stored as zero), E = ((F - I) + (F - I)^T +
                // (F - I)^T (F - I)) / 2, M = V F S(E) + (F - I) Q - Gb + u_i (x) U,
                // N = M A^-T (zero on padding lanes).
                let gq = &group_rest[g];
                let ld = |a: &[f64; 4]| V::from_array(isa, *a);
                let mut ft = [zero; 9];
                for c in 0..3 {
                    let sc = ld(&gq.s[c]);
                    for r in 0..3 {
                        let base = if seed {
                            ld(&gq.a[3 * c + r]).add(ga[3 * c + r])
                        } else {
                            ga[3 * c + r]
                        };
                        ft[3 * c + r] = V::nmadd(ui[r], sc, base);
                    }
                }
                // Seed: `fmi` unused.
                let fmi = if seed {
                    ft
                } else {
                    mat_mul(&ft, &lane_mat(isa, &gq.a))
                };
                let f = if seed {
                    ft
                } else {
                    let mut f = fmi;
                    for i in [0, 4, 8] {
                        f[i] = f[i].add(V::splat(isa, 1.0));
                    }
                    f
                };
                let half = V::splat(isa, 0.5);
                let mut e = [zero; 9];
                for c in 0..3 {
                    for d in c..3 {
                        let ecd = if seed {
                            let mut ctd = f[3 * c].mul(f[3 * d]);
                            ctd = V::madd(f[3 * c + 1], f[3 * d + 1], ctd);
                            ctd = V::madd(f[3 * c + 2], f[3 * d + 2], ctd);
                            let id = if c == d { 1.0 } else { 0.0 };
                            ctd.sub(V::splat(isa, id))
                                .mul(half)
                                .sub(ld(&gq.q[3 * d + c]))
                        } else {
                            let mut ctd = fmi[3 * d + c].add(fmi[3 * c + d]);
                            ctd = V::madd(fmi[3 * c], fmi[3 * d], ctd);
                            ctd = V::madd(fmi[3 * c + 1], fmi[3 * d + 1], ctd);
                            ctd = V::madd(fmi[3 * c + 2], fmi[3 * d + 2], ctd);
                            ctd.mul(half)
                        };
                        e[3 * d + c] = ecd;
                        e[3 * c + d] = ecd;
                    }
                }
                let lv = V::splat(isa, mat.lambda_pa * v);
                let mv = V::splat(isa, 2.0 * mat.mu_pa * v);
                let tr = lv.mul(e[0].add(e[4]).add(e[8]));
                let mut sv = [zero; 9];
                for i in 0..9 {
                    sv[i] = mv.mul(e[i]);
                }
                for i in [0, 4, 8] {
                    sv[i] = sv[i].add(tr);
                }
                let own_v = own;
                let mut m = mat_mul(&f, &sv);
                let s3 = [ld(&gq.s[0]), ld(&gq.s[1]), ld(&gq.s[2])];
                let (nmv, fmv, ov) = if seed {
                    for x in &mut m {
                        *x = x.mul(own_v);
                    }
                    let ov = mat_vec(&m, &s3);
                    (m, [zero; 9], ov)
                } else {
                    let h = mat_mul(&fmi, &lane_mat(isa, &gq.q));
                    let u3 = [ld(&gq.u[0]), ld(&gq.u[1]), ld(&gq.u[2])];
                    for c in 0..3 {
                        for r in 0..3 {
                            let i = 3 * c + r;
                            m[i] = V::madd(ui[r], u3[c], m[i].add(h[i]).sub(gb[i]));
                        }
                    }
                    let a_inv = lane_mat(isa, &gq.a);
                    let mut n = [zero; 9];
                    // N = M A^-T: N[r][c] = sum_d M[r][d] A^-1[c][d].
                    for c in 0..3 {
                        for r in 0..3 {
                            let mut acc = m[r].mul(a_inv[c]);
                            acc = V::madd(m[3 + r], a_inv[3 + c], acc);
                            acc = V::madd(m[6 + r], a_inv[6 + c], acc);
                            n[3 * c + r] = acc;
                        }
                    }
                    // owner = N S - F U + sum_k c_k u_(i+k) - C u_i + U (U = 0 on padding
                    // lanes).
                    let ns = mat_vec(&n, &s3);
                    let fu = mat_vec(&f, &u3);
                    let cv = ld(&gq.c);
                    let mut ov = [zero; 3];
                    for r in 0..3 {
                        let sdl = V::nmadd(cv, ui[r], cu[r]).add(u3[r]).mul(own_v);
                        ov[r] = ns[r].sub(fu[r]).add(sdl);
                    }
                    (n, fmi, ov)
                };
                (nmv, fmv, ov)
            } else {
                // Per lane: F~ = A + G - u_i (x) S; stress, N, F (corrected: F - I) and the
                // owner's force.
                let gas = lane_matrices(&ga);
                let gbs = if seed {
                    [[0.0; 9]; 4]
                } else {
                    lane_matrices(&gb)
                };
                let uis = [ui[0].to_array(), ui[1].to_array(), ui[2].to_array()];
                let cus = [cu[0].to_array(), cu[1].to_array(), cu[2].to_array()];
                let mut nl = [[0.0; 4]; 9];
                let mut fl = [[0.0; 4]; 9];
                let mut ol = [[0.0; 4]; 3];
                for (l, lr) in lanes.iter().enumerate() {
                    if lr.own == 0.0 {
                        continue;
                    }
                    let u_i = DVec3::new(uis[0][l], uis[1][l], uis[2][l]);
                    let g_us = DMat3::from_cols_array(&gas[l]) - outer(u_i, lr.s);
                    let (n, f, owner) = if seed {
                        let ft = lr.a + g_us;
                        let e = green_strain(&ft) - lr.q;
                        let n = (ft * stvk_stress(&e, mat.lambda_pa, mat.mu_pa)) * v;
                        (n, DMat3::ZERO, n * lr.s)
                    } else {
                        // F - I = (F~ - A) A^-1.
                        let fmi = g_us * lr.a_inv;
                        let f = fmi + DMat3::IDENTITY;
                        // D = sum_k c_k d_ik (x) X_k = Gb - u_i (x) U + Q; H = F Q - D.
                        let h = fmi * lr.q - DMat3::from_cols_array(&gbs[l]) + outer(u_i, lr.u);
                        let m = first_piola(mat, &f) * v + h;
                        let n = m * lr.a_inv.transpose();
                        // sum_k c_k d_ik = sum_k c_k u_(i+k) - C u_i + U.
                        let sdl = DVec3::new(cus[0][l], cus[1][l], cus[2][l]) - u_i * lr.c + lr.u;
                        (n, fmi, n * lr.s - f * lr.u + sdl)
                    };
                    let (na, fa_) = (n.to_cols_array(), f.to_cols_array());
                    for e in 0..9 {
                        nl[e][l] = na[e];
                        fl[e][l] = fa_[e];
                    }
                    for r in 0..3 {
                        ol[r][l] = owner[r];
                    }
                }
                let nm = lane_mat::<V>(isa, &nl);
                let fm = lane_mat::<V>(isa, &fl);
                let ov = [
                    V::from_array(isa, ol[0]),
                    V::from_array(isa, ol[1]),
                    V::from_array(isa, ol[2]),
                ];
                (nm, fm, ov)
            };
            let ncl = class_matrices(&nm, &fm, classes, seed, isa);
            if cube {
                let m = cube_columns(isa, &ncl, cube_scale, perm);
                let cko = cube_hourglass(isa, classes, own);
                // c_k u_i per class and component (corrected).
                let mut cui = [[zero; 3]; 3];
                if !seed {
                    for (cu, ck) in cui.iter_mut().zip(&cko) {
                        for r in 0..3 {
                            cu[r] = ck.mul(ui[r]);
                        }
                    }
                }
                pass_two_cube::<V>(
                    isa,
                    b,
                    cube_rows,
                    &m,
                    &cui,
                    &cko,
                    [px, py, pz],
                    fc.each_mut().map(|a| &mut a[..]),
                    seed,
                    ov,
                );
            } else {
                pair_grads(isa, &ncl, ws, class_of, pairs, &mut ah);
                pass_two::<V>(
                    isa,
                    b,
                    rows,
                    cs,
                    off,
                    px,
                    py,
                    pz,
                    fc.each_mut().map(|a| &mut a[..]),
                    seed,
                    own,
                    ui,
                    half_of,
                    &ah,
                    ov,
                );
            }
        }
    }
}

/// `N w_k - F c_k X_k + c_k X_k = (N - beta_k (F - I)) w_k` of each pair `(k, -k)` (one
/// matrix `ncl` per class of length, [`class_matrices`]; odd in `k`: `w_-k = -w_k`, same
/// class) into `ah`, in `pairs` order.
#[inline(always)]
fn pair_grads<V: Lanes4>(
    isa: V::Isa,
    ncl: &[[V; 9]; 3],
    ws: &[[f64; 3]],
    class_of: &[usize],
    pairs: &[(usize, isize)],
    ah: &mut [[V; 3]; MAX_PAIRS],
) {
    for (a, &(k, _)) in ah.iter_mut().zip(pairs) {
        let w = ws[k];
        let (w0, w1, w2) = (
            V::splat(isa, w[0]),
            V::splat(isa, w[1]),
            V::splat(isa, w[2]),
        );
        let nc = &ncl[class_of[k]];
        for r in 0..3 {
            a[r] = V::madd(nc[r], w0, V::madd(nc[3 + r], w1, nc[6 + r].mul(w2)));
        }
    }
}

/// The columns of `scale_c (N - beta_c F)` by grid axis: `m[c][3 a + r]` is row `r` of
/// column `perm[a]` (26-cell cube: `w_k = scale_c e_k` with `e_k` in grid axes, so
/// `(N - beta_c F) w_k` is a signed sum of these columns).
#[inline(always)]
fn cube_columns<V: Lanes4>(
    isa: V::Isa,
    ncl: &[[V; 9]; 3],
    scale: &[f64; 3],
    perm: [usize; 3],
) -> [[V; 9]; 3] {
    let mut m = [[V::zero(isa); 9]; 3];
    for c in 0..3 {
        let sv = V::splat(isa, scale[c]);
        for a in 0..3 {
            for r in 0..3 {
                m[c][3 * a + r] = ncl[c][3 * perm[a] + r].mul(sv);
            }
        }
    }
    m
}

/// `c_k` of each class (faces, edges, corners) on the owner lanes, zero on padding lanes.
#[inline(always)]
fn cube_hourglass<V: Lanes4>(
    isa: V::Isa,
    classes: &[(f64, f64, std::ops::Range<usize>)],
    own: V,
) -> [V; 3] {
    // A loop, not `array::from_fn`: closures do not inherit the caller's target features.
    let mut cko = [V::zero(isa); 3];
    for (c, cl) in cko.iter_mut().zip(classes) {
        *c = V::splat(isa, cl.1).mul(own);
    }
    cko
}

/// The pair of [`CUBE`] holding grid-axis offset `e`, and whether `e` is its negative.
///
/// # Panics
/// If `e` is not an offset of the cube (at compile time where it is used).
const fn cube_pair_of(e: [i32; 3]) -> (usize, bool) {
    let mut j = 0;
    while j < MAX_PAIRS {
        let c = CUBE[j];
        if c[0] == e[0] && c[1] == e[1] && c[2] == e[2] {
            return (j, false);
        }
        if c[0] == -e[0] && c[1] == -e[1] && c[2] == -e[2] {
            return (j, true);
        }
        j += 1;
    }
    panic!("not an offset of the 26-cell cube");
}

/// Row `r` of `sum_a e[a] m[:, a]` for a constant `e` of entries -1, 0, 1 whose first
/// nonzero is 1 (the additions only, once inlined).
#[inline(always)]
fn cube_column_sum<V: Lanes4>(m: &[V; 9], e: [i32; 3], r: usize) -> V {
    let mut acc: Option<V> = None;
    for (a, &ea) in e.iter().enumerate() {
        let col = m[3 * a + r];
        acc = match (ea, acc) {
            (0, acc) => acc,
            (1, None) => Some(col),
            (1, Some(x)) => Some(x.add(col)),
            (_, Some(x)) => Some(x.sub(col)),
            (_, None) => Some(col.neg()),
        };
    }
    acc.expect("a nonzero offset")
}

/// [`pass_two`] for the 26-cell cube: the rows `(a, b)` and `(-a, -b)` together, so that each
/// pair's `(N - beta (F - I)) w_k` is summed once from the class columns `m`
/// ([`cube_columns`]) and serves both its entries (`w_-k = -w_k`); every offset, sign and
/// zero of the stencil is known at compile time. `cko`: `c_k` per class on owner lanes
/// ([`cube_hourglass`]); `cui`: `c_k u_i` per class and component (corrected). Each entry
/// of offset `dx` along the vector axis is subtracted at its row's chunk of four cells in the
/// forces of that offset (interleaved in `f`, [`StencilGrid`]'s `fc`): aligned whole-chunk
/// read-modify-writes, no shift across lanes.
#[inline(always)]
#[allow(clippy::too_many_arguments)] // the loop's state, split out of one function
fn pass_two_cube<V: Lanes4>(
    isa: V::Isa,
    b: usize,
    rows: &[isize; 9],
    m: &[[V; 9]; 3],
    cui: &[[V; 3]; 3],
    cko: &[V; 3],
    p: [&[f64]; 3],
    f: [&mut [f64]; 3],
    seed: bool,
    ol: [V; 3],
) {
    // `grad` subtracted (`neg`: added) at chunk `o` of the forces of offset `dx`, component
    // `r` (interleaved: at `3 o + 4 (dx + 1)`; a macro, not a closure: closures do not
    // inherit the caller's target features).
    macro_rules! put {
        ($dx:expr, $o:expr, $r:expr, $grad:expr, $neg:expr) => {{
            let (a, i) = (&mut *f[$r], 3 * $o + 4 * ($dx + 1) as usize);
            let old = V::load(isa, a, i);
            if $neg { old.add($grad) } else { old.sub($grad) }.store(a, i);
        }};
    }
    // The entry `(dx, a, b)` of row one and its negative in row two (owners' chunks `o1` and
    // `o2`, neighbours at `o1 + dx` and `o2 - dx`), component `r`: pair `j`, sign, the
    // hourglass part `c_k (u_(i+k) - u_i)` (corrected; its `c_k X_k` is in `m`).
    macro_rules! entry {
        ($dx:expr, $a:expr, $b:expr, $r:ident, $o1:ident, $o2:ident) => {{
            const JN: (usize, bool) = cube_pair_of([$dx, $a, $b]);
            let (j, neg) = JN;
            let g = cube_column_sum(&m[CUBE_CLASS[j]], CUBE[j], $r);
            if seed {
                put!($dx, $o1, $r, g, neg);
                put!(-$dx, $o2, $r, g, !neg);
            } else {
                // grad_k = (N - beta (F - I)) w_k + c_k u_(i+k) - c_k u_i: the entry `g` or
                // `-g`, its negative the other.
                let (ck, cu) = (cko[CUBE_CLASS[j]], cui[CUBE_CLASS[j]][$r]);
                let (gm, gp) = (g.sub(cu), g.add(cu));
                let u1 = V::load(isa, p[$r], ($o1 as isize + $dx) as usize);
                let u2 = V::load(isa, p[$r], ($o2 as isize - $dx) as usize);
                let (d1, d2) = if neg {
                    (V::msub(u1, ck, gp), V::madd(u2, ck, gm))
                } else {
                    (V::madd(u1, ck, gm), V::msub(u2, ck, gp))
                };
                put!($dx, $o1, $r, d1, false);
                put!(-$dx, $o2, $r, d2, false);
            }
        }};
    }
    macro_rules! row_pair {
        ($a:expr, $b:expr) => {{
            let o1 = (b as isize + rows[(($a + 1) + 3 * ($b + 1)) as usize]) as usize;
            let o2 = (b as isize + rows[((1 - $a) + 3 * (1 - $b)) as usize]) as usize;
            for r in 0..3 {
                entry!(-1, $a, $b, r, o1, o2);
                entry!(0, $a, $b, r, o1, o2);
                entry!(1, $a, $b, r, o1, o2);
            }
        }};
    }
    // The centre row: the owner's force and the pair (1, 0, 0) at both ends (its row two is
    // itself).
    for r in 0..3 {
        let o = b;
        put!(0, o, r, ol[r], true);
        entry!(1, 0, 0, r, o, o);
    }
    row_pair!(-1, -1);
    row_pair!(0, -1);
    row_pair!(1, -1);
    row_pair!(-1, 0);
}

/// The force on cell `i` from the cube loop's interleaved forces `fc` (one component):
/// `f0[i] + fm[i + 1] + fp[i - 1]`, chunk `c` holding `fm`, `f0`, `fp` at `12 c`, `12 c + 4`,
/// `12 c + 8`.
#[inline]
fn cube_force_at(fc: &[f64], i: usize) -> f64 {
    let at = |j: usize, d: usize| fc[3 * (j & !3) + 4 * d + (j & 3)];
    at(i, 1) + at(i + 1, 0) + at(i - 1, 2)
}

/// Pass 1 for the 26-cell cube: per class (faces, edges, corners) the grid-axis columns
/// `sum_k e_k[a] (u_(i+k) - u_(i-k))` (at `3 a + r`) and (corrected, `!seed`) the sums
/// `sum_k (u_(i+k) + u_(i-k))`, over [`CUBE`]'s pairs at grid offsets `off`.
#[inline(always)]
#[allow(clippy::type_complexity)] // two small per-class arrays
fn pass_one_cube<V: Lanes4>(
    isa: V::Isa,
    b: usize,
    off: &[isize; MAX_PAIRS],
    px: &[f64],
    py: &[f64],
    pz: &[f64],
    seed: bool,
) -> ([[V; 9]; 3], [[V; 3]; 3]) {
    let zero = V::zero(isa);
    let mut g = [[zero; 9]; 3];
    let mut s = [[zero; 3]; 3];
    macro_rules! pair {
        ($($j:literal),*) => {$(
            let (c, e, o) = (CUBE_CLASS[$j], CUBE[$j], off[$j]);
            let (hi, lo) = ((b as isize + o) as usize, (b as isize - o) as usize);
            let a = [V::load(isa, px, hi), V::load(isa, py, hi), V::load(isa, pz, hi)];
            let m = [V::load(isa, px, lo), V::load(isa, py, lo), V::load(isa, pz, lo)];
            for r in 0..3 {
                let d = a[r].sub(m[r]);
                for (ax, &ea) in e.iter().enumerate() {
                    let x = &mut g[c][3 * ax + r];
                    match ea {
                        0 => {}
                        1 => *x = x.add(d),
                        _ => *x = x.sub(d),
                    }
                }
                if !seed {
                    s[c][r] = s[c][r].add(a[r].add(m[r]));
                }
            }
        )*};
    }
    pair!(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12);
    (g, s)
}

/// Pass 2 of a group (module documentation): `grad_k = N w_k (- F u_k + c_k d_k)`, from
/// `ah` ([`pair_grads`], which holds `c_k X_k`) plus `c_k (u_(i+k) - u_i)` (corrected),
/// subtracted at the neighbour, the owner's force `ol` added at the owner; the three offsets
/// of a row along the vector axis are combined into whole aligned chunks of four cells first
/// (a store that a later load overlaps only partly stalls the core), written into the forces
/// of offset 0 in `f` (interleaved, [`StencilGrid`]'s `fc`).
#[inline(always)]
#[allow(clippy::too_many_arguments)] // the loop's state, split out of one function
fn pass_two<V: Lanes4>(
    isa: V::Isa,
    b: usize,
    rows: &[(isize, [usize; 3])],
    cs: &[f64],
    off: &[isize],
    px: &[f64],
    py: &[f64],
    pz: &[f64],
    mut f: [&mut [f64]; 3],
    seed: bool,
    own: V,
    ui: [V; 3],
    half_of: &[(usize, bool)],
    ah: &[[V; 3]; MAX_PAIRS],
    ol: [V; 3],
) {
    let zero = V::zero(isa);
    for &(ro, entries) in rows.iter() {
        let o = (b as isize + ro) as usize;
        let mut centre = if ro == 0 { ol } else { [zero; 3] };
        let mut before = [zero; 3];
        let mut after = [zero; 3];
        for (dx, &k) in entries.iter().enumerate() {
            if k == usize::MAX {
                continue;
            }
            let (j, negative) = half_of[k];
            let mut gr = ah[j];
            if negative {
                gr = [gr[0].neg(), gr[1].neg(), gr[2].neg()];
            }
            if !seed {
                // c_k (u_(i+k) - u_i) for an owner lane (padding lanes: zero); an empty
                // neighbour cell receives a value nobody reads.
                let ck = V::splat(isa, cs[k]).mul(own);
                let o = (b as isize + off[k]) as usize;
                let uj = [
                    V::load(isa, px, o),
                    V::load(isa, py, o),
                    V::load(isa, pz, o),
                ];
                for r in 0..3 {
                    let d = uj[r].sub(ui[r]);
                    gr[r] = V::madd(d, ck, gr[r]);
                }
            }
            for r in 0..3 {
                match dx {
                    0 => {
                        let (c, lo) = gr[r].shift_down();
                        centre[r] = centre[r].sub(c);
                        before[r] = before[r].sub(lo);
                    }
                    1 => centre[r] = centre[r].sub(gr[r]),
                    _ => {
                        let (c, hi) = gr[r].shift_up();
                        centre[r] = centre[r].sub(c);
                        after[r] = after[r].sub(hi);
                    }
                }
            }
        }
        // Chunk `q` (a multiple of four) of the forces of offset 0 is at `3 q + 4` in `f`.
        for (a, (c, (lo, hi))) in f
            .iter_mut()
            .map(|a| &mut **a)
            .zip(centre.iter().zip(before.iter().zip(&after)))
        {
            let i = 3 * o + 4;
            if entries[0] != usize::MAX {
                V::load(isa, a, i - 12).add(*lo).store(a, i - 12);
            }
            V::load(isa, a, i).add(*c).store(a, i);
            if entries[2] != usize::MAX {
                V::load(isa, a, i + 12).add(*hi).store(a, i + 12);
            }
        }
    }
}
