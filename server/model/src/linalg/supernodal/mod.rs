//! One right-hand side through a supernodal Cholesky factor of faer stored in half precision,
//! for the servo tick: `A x = b` with `A = L L^T` solved in place, allocation-free.
//!
//! faer's `LltRef::solve_in_place_with_conj` is general (many right-hand sides, any scalar,
//! parallelism); for one column it pays a dense triangular solve and a matrix product call per
//! supernode. The LV meshes' factors have many small supernodes (the tick matrix of the default
//! `lv`, 2 727 equations and 485 000 entries, has about one per node), so on that factor the
//! calls took most of the solve. Here each supernode's block is swept in faer's order, eight
//! columns (a panel) at a time ([`HalfFactor`] stores the factor in that order): forward,
//! `y = L^-1 b` solves the panel's triangle, then updates the rows below it eight at a time,
//! each held in a register across the panel's columns; backward, `x = L^-T y` takes the
//! panel's dot products with the rows below, eight rows per load, then its triangle. So the
//! right-hand side is read and written once per panel, not once per column
//! (docs/benchmarks.md, "Panel sweeps"). For the probe's one-row Woodbury term the forward
//! sweep also takes a second right-hand side in the same pass
//! ([`SupernodalSolve::forward_pair`], [`SupernodalSolve::backward_combined`]).
//!
//! **Half precision.** One tick streams the whole factor twice, and that stream bounds the
//! sweep. [`HalfFactor`] holds `S L`, the factor of the diagonally scaled `S A S` with
//! `S = diag(A_rr^-1/2)`: its rows have unit norm, so every entry lies in `[-1, 1]` and
//! IEEE half precision (11 significant bits, `half::f16`, converted by the F16C instructions)
//! holds it to `2^-11` of itself. The diagonal is kept inverted in single precision and the
//! arithmetic is single precision. The sweep solves with the rounded factor's matrix exactly
//! (to single-precision round-off): [`SupernodalSolve::half_factor`] also rounds the caller's
//! single-precision factor to it, so faer's solves through that factor agree with the sweep
//! (test below). How far the rounding moves the step is checked where the factor is used
//! (`integrate::condensed`); docs/decisions.md, "The whole-body rest factor".
//!
//! Owns: the sweep. May use: `crate::simd`.

use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};

use crate::pool::TickPool;
use crate::simd::Avx2FmaF16c;
use std::ops::Range;

mod panel;
mod parts;
mod single;
mod split;
use panel::{PanelKernel, Portable};
pub use parts::{HalfFactorParts, touch_words};
#[cfg(target_arch = "x86_64")]
use single::Fused;
use single::Narrow;
use split::{Phases, TreeSplit, phases, tree_split};

/// The supernodal structure of a factor in the form the sweep reads, with its workspace.
#[derive(Debug, Clone)]
pub struct SupernodalSolve {
    /// Per supernode: first column, column count, start of its pattern in `rows`, pattern
    /// length, start of its values.
    nodes: Vec<[u32; 5]>,
    /// Row indices of the off-diagonal rows of every supernode (permuted numbering).
    rows: Vec<u32>,
    /// Fill-reducing permutation: `forward[k]` is the original index of equation `k`.
    forward: Vec<u32>,
    /// Number of stored factor values.
    len_val: usize,
    /// Permuted right-hand side / solution.
    x: Vec<f32>,
    /// One supernode's column block of the right-hand side.
    y: Vec<f32>,
    /// The second right-hand side of [`Self::forward_pair`] (permuted, scaled).
    x2: Vec<f32>,
    /// Its column block.
    y2: Vec<f32>,
    /// The AVX2 + FMA + F16C token when the CPU has them (the sweep runs that build then).
    f16c: Option<Avx2FmaF16c>,
    /// Whether that build takes supernodes of a single panel through [`single`] (the same
    /// bits; off only in tests, to compare, and for more than `i32::MAX` equations).
    fused: bool,
    /// The elimination tree cut in two for [`Self::solve_in_place_in`] ([`Self::set_parts`]).
    split: Option<TreeSplit>,
}

/// Rows per block of a [`HalfFactor`] panel (one AVX2 register of `f32`), and columns per
/// panel: the sweeps read and write the right-hand side eight rows at a time, once per panel.
const HALF_PAD: usize = 8;
const PANEL: usize = 8;

/// A factor in the sweep's structure, stored in IEEE half precision: the factor `S L` of the
/// diagonally scaled matrix `S A S`, `S = diag(A_rr^-1/2)` (so every entry lies in `[-1, 1]`
/// and the half-precision range holds it), with its diagonal inverted in single precision.
///
/// Layout: each supernode's columns are cut into panels of up to `PANEL` consecutive
/// columns `p0..p0 + w`. A panel keeps the strict lower triangle among its own columns
/// (single precision, the half-precision values converted; row-major packed) and, for the
/// rows below it (`p0 + w..` of the supernode's block), blocks of `HALF_PAD` rows: block
/// `b` holds, for each column `t` of the panel in turn, its eight entries of rows
/// `p0 + w + 8 b ..` (zero past the block's height). So a sweep loads or stores each eight
/// rows of the right-hand side once per panel instead of once per column, and reads the
/// factor in order. Built by [`SupernodalSolve::half_factor`], solved by
/// [`SupernodalSolve::solve_in_place`].
#[derive(Debug, Clone)]
pub struct HalfFactor {
    /// Per permuted equation `r`: `s_r = A_rr^-1/2`.
    scale: Vec<f32>,
    /// Per permuted column: the inverse of its diagonal entry in `S L`.
    inv_diag: Vec<f32>,
    /// Per supernode, and one past the last: where its panels start in `values` and in
    /// `triangles`.
    node_start: Vec<[u32; 2]>,
    /// The panels' strict lower triangles (entry `(i, t)`, `t < i`, at `i (i - 1) / 2 + t`).
    triangles: Vec<f32>,
    /// The panels' row blocks (half-precision bits).
    values: Vec<u16>,
}

impl HalfFactor {
    /// Bytes of the factor's arrays.
    pub fn memory_bytes(&self) -> usize {
        2 * self.values.len()
            + 4 * (self.scale.len()
                + self.inv_diag.len()
                + 2 * self.node_start.len()
                + self.triangles.len())
    }
}

/// One panel of a supernode: columns `p0..p0 + w` of its block, `blocks` blocks of
/// [`HALF_PAD`] rows below them, and how many entries it keeps in [`HalfFactor`]'s `values`
/// and `triangles`.
#[derive(Clone, Copy)]
struct Panel {
    p0: usize,
    w: usize,
    blocks: usize,
    values_len: usize,
    triangle_len: usize,
}

/// The one panel of a supernode of `nc` columns and block height `h` when it has one and rows
/// below it ([`single`]).
#[inline(always)]
fn single_panel(nc: usize, h: usize) -> Option<Panel> {
    (nc <= PANEL && h > nc)
        .then(|| panels(nc, h).next())
        .flatten()
}

/// The panels of a supernode of `nc` columns and block height `h`, in column order.
#[inline(always)]
fn panels(nc: usize, h: usize) -> impl DoubleEndedIterator<Item = Panel> {
    (0..nc.div_ceil(PANEL)).map(move |p| {
        let p0 = p * PANEL;
        let w = PANEL.min(nc - p0);
        let blocks = (h - p0 - w).div_ceil(HALF_PAD);
        Panel {
            p0,
            w,
            blocks,
            values_len: blocks * w * HALF_PAD,
            triangle_len: w * (w - 1) / 2,
        }
    })
}

impl SupernodalSolve {
    /// Bytes of the sweep's arrays (pattern, permutation, right-hand side blocks, cut).
    pub fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        let split = self.split.as_ref().map_or(0, |s| {
            let p = &s.phases;
            b(&s.xb)
                + b(&s.yb)
                + b(&p.one[0])
                + b(&p.one[1])
                + b(&p.two[0])
                + b(&p.two[1])
                + b(&p.waiting_cols)
                + b(&p.second_cols)
        });
        b(&self.nodes)
            + b(&self.rows)
            + b(&self.forward)
            + b(&self.x)
            + b(&self.y)
            + b(&self.x2)
            + b(&self.y2)
            + split
    }

    /// The sweep for the factors of `symbolic`, or `None` when faer chose a simplicial factor
    /// (small or very sparse matrices: solve those with faer) or the sizes exceed 32 bits.
    pub fn new(symbolic: &SymbolicCholesky<usize>) -> Option<Self> {
        let SymbolicCholeskyRaw::Supernodal(s) = symbolic.raw() else {
            return None;
        };
        let n = s.nrows();
        let to32 = |v: usize| u32::try_from(v).ok();
        to32(s.len_val())?;
        let (begin, end) = (s.supernode_begin(), s.supernode_end());
        let row_ptr = s.col_ptr_for_row_idx();
        let val_ptr = s.col_ptr_for_val();
        let mut nodes = Vec::with_capacity(s.n_supernodes());
        let mut rows = Vec::new();
        let mut widest = 0;
        for k in 0..s.n_supernodes() {
            let ncols = end[k] - begin[k];
            // A supernode's block is `(ncols + pattern) x ncols`, column-major.
            let height = (val_ptr[k + 1] - val_ptr[k]) / ncols.max(1);
            let pattern = &s.row_idx()[row_ptr[k]..][..height - ncols];
            nodes.push([
                to32(begin[k])?,
                to32(ncols)?,
                to32(rows.len())?,
                to32(pattern.len())?,
                to32(val_ptr[k])?,
            ]);
            widest = widest.max(ncols + pattern.len());
            for &r in pattern {
                rows.push(to32(r)?);
            }
        }
        // The sweeps index `x` by these rows without checks.
        if rows.iter().any(|&r| r as usize >= n) {
            return None;
        }
        let forward = match symbolic.perm() {
            Some(p) => p
                .arrays()
                .0
                .iter()
                .map(|&i| to32(i))
                .collect::<Option<_>>()?,
            None => (0..n).map(to32).collect::<Option<_>>()?,
        };
        Some(Self {
            nodes,
            rows,
            forward,
            len_val: s.len_val(),
            x: vec![0.0; n],
            y: vec![0.0; widest + HALF_PAD],
            x2: vec![0.0; n],
            y2: vec![0.0; widest + HALF_PAD],
            f16c: Avx2FmaF16c::detect(),
            fused: i32::try_from(n).is_ok(),
            split: None,
        })
    }

    /// Cuts later [`Self::solve_in_place_in`] sweeps into two groups of subtrees when `parts`
    /// is at least 2 and the elimination tree has a fork whose two sides each hold at least
    /// a quarter of the factor, the rest at most a third (found from the heaviest root down
    /// through children holding more than two thirds of their parent); otherwise (or with
    /// `parts` 1) the sweep stays whole. When it balances the threads better, the sweeps also
    /// run in two phases (`split::Phases`). Set-up, not a tick: allocates.
    /// Returns whether the sweep is cut.
    pub fn set_parts(&mut self, parts: usize) -> bool {
        self.split = if parts >= 2 {
            tree_split(&self.nodes, &self.rows, self.len_val).map(|(b_start, top_start)| {
                let col = |k: usize| self.nodes[k][0] as usize;
                let (col_b, col_top) = (col(b_start), col(top_start));
                let (nodes, rows) = (&self.nodes, &self.rows);
                TreeSplit {
                    top_start,
                    col_top,
                    xb: vec![0.0; self.x.len()],
                    yb: vec![0.0; self.y.len()],
                    phases: phases(nodes, rows, self.len_val, b_start, top_start)
                        .unwrap_or_else(|| Phases::plain(b_start, top_start, col_b, col_top)),
                }
            })
        } else {
            None
        };
        self.split.is_some()
    }

    /// The sweeps' build ([`Build`]).
    fn build(&self) -> Build {
        Build {
            isa: self.f16c,
            fused: self.fused,
        }
    }

    /// Number of stored factor values (faer's supernodal layout).
    pub fn factor_len(&self) -> usize {
        self.len_val
    }

    /// Number of equations.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// Whether there is no equation.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// The half-precision form of the factor `values` (faer's supernodal layout on this
    /// structure), and `values` rounded to what it holds: afterwards `values` is the factor of
    /// exactly the matrix the half-precision sweep solves with (to single-precision
    /// round-off), so faer's solves through `values` (prepared right-hand sides, Woodbury
    /// columns) and [`Self::solve_in_place`] agree. Rounding the scaled entries to half
    /// precision perturbs each by at most `2^-11` of itself.
    ///
    /// `None` when the padded half-precision factor exceeds 32-bit offsets (`values` is then
    /// partly rounded: pass a copy).
    ///
    /// # Panics
    /// If `values` has the wrong length.
    pub fn half_factor(&self, values: &mut [f32]) -> Option<HalfFactor> {
        use half::f16;
        assert_eq!(values.len(), self.len_val, "factor length");
        let n = self.x.len();
        // `A_rr` is the squared norm of row r of L.
        let mut row_norm2 = vec![0.0f64; n];
        for &node in &self.nodes {
            let (c0, nc, v0, pattern) = supernode(node, &self.rows);
            let h = nc + pattern.len();
            for j in 0..nc {
                let col = &values[v0 + j * h..v0 + (j + 1) * h];
                for (i, &l) in col.iter().enumerate().skip(j) {
                    let r = if i < nc {
                        c0 + i
                    } else {
                        pattern[i - nc] as usize
                    };
                    row_norm2[r] += f64::from(l) * f64::from(l);
                }
            }
        }
        let scale: Vec<f32> = row_norm2.iter().map(|&a| (1.0 / a.sqrt()) as f32).collect();
        let mut inv_diag = vec![0.0f32; n];
        let mut node_start = Vec::with_capacity(self.nodes.len());
        let mut triangles = Vec::new();
        let mut half = Vec::new();
        for &node in &self.nodes {
            let (c0, nc, v0, pattern) = supernode(node, &self.rows);
            let h = nc + pattern.len();
            node_start.push([
                u32::try_from(half.len()).ok()?,
                u32::try_from(triangles.len()).ok()?,
            ]);
            for j in 0..nc {
                inv_diag[c0 + j] = 1.0 / (values[v0 + j * h + j] * scale[c0 + j]);
            }
            let row_scale = |i: usize| {
                scale[if i < nc {
                    c0 + i
                } else {
                    pattern[i - nc] as usize
                }]
            };
            // Entry (row i, column j) of the block, rounded in place to what the half
            // factor holds; its scaled half-precision value.
            let mut round = |i: usize, j: usize| {
                let l = &mut values[v0 + j * h + i];
                let s = row_scale(i);
                let q = f16::from_f32(*l * s);
                *l = q.to_f32() / s;
                q
            };
            for Panel { p0, w, blocks, .. } in panels(nc, h) {
                for i in 1..w {
                    for t in 0..i {
                        triangles.push(round(p0 + i, p0 + t).to_f32());
                    }
                }
                for b in 0..blocks {
                    for t in 0..w {
                        for lane in 0..HALF_PAD {
                            let i = p0 + w + HALF_PAD * b + lane;
                            half.push(if i < h { round(i, p0 + t).to_bits() } else { 0 });
                        }
                    }
                }
            }
        }
        node_start.push([
            u32::try_from(half.len()).ok()?,
            u32::try_from(triangles.len()).ok()?,
        ]);
        Some(HalfFactor {
            scale,
            inv_diag,
            node_start,
            triangles,
            values: half,
        })
    }

    /// Solves `A x = b` in place through the half-precision factor `factor` (from
    /// [`Self::half_factor`] on this structure): `b` (length [`Self::len`], original
    /// numbering) becomes `x`; `(S L)(S L)^T y = S b`, `x = S y`, in single-precision
    /// arithmetic. Allocation-free.
    ///
    /// # Panics
    /// If `b` has the wrong length or `factor` another structure.
    pub fn solve_in_place(&mut self, factor: &HalfFactor, b: &mut [f32]) {
        self.solve_in_place_in(None, factor, b);
    }

    /// [`Self::solve_in_place`] with the sweeps' two groups of subtrees (when
    /// [`Self::set_parts`] cut them) on the caller and a worker of `pool` (serially without
    /// one); the common ancestors before (backward) or after (forward) them on the caller.
    /// Uncut, or without a pool, it is [`Self::solve_in_place`] bit for bit; cut, the top's
    /// rows sum the second group's updates separately (single-precision round-off apart).
    /// Allocation-free.
    ///
    /// # Panics
    /// As [`Self::solve_in_place`].
    pub fn solve_in_place_in(
        &mut self,
        pool: Option<&TickPool>,
        factor: &HalfFactor,
        b: &mut [f32],
    ) {
        let n = self.x.len();
        assert_eq!(b.len(), n, "right-hand side length");
        assert_eq!(factor.scale.len(), n, "half factor of another structure");
        for ((xk, &f), &s) in self.x.iter_mut().zip(&self.forward).zip(&factor.scale) {
            *xk = b[f as usize] * s;
        }
        let Self {
            nodes,
            rows,
            x,
            y,
            split,
            f16c,
            fused,
            ..
        } = self;
        let isa = Build {
            isa: *f16c,
            fused: *fused,
        };
        let (nodes, rows) = (&nodes[..], &rows[..]);
        let (Some(pool), Some(sp)) = (pool, split.as_mut()) else {
            forward_sweep(isa, nodes, 0, rows, factor, [x], [y]);
            return self.backward_into(factor, b);
        };
        cut_sweeps(pool, isa, (nodes, rows, factor), sp, x, y);
        for ((&xk, &f), &s) in self.x.iter().zip(&self.forward).zip(&factor.scale) {
            b[f as usize] = xk * s;
        }
    }

    /// The backward sweep of `self.x` with the CPU's build, then `out = S x` in the original
    /// numbering.
    fn backward_into(&mut self, factor: &HalfFactor, out: &mut [f32]) {
        let (nodes, rows) = (&self.nodes, &self.rows);
        let build = self.build();
        backward_sweep(build, nodes, 0, rows, factor, &mut self.x, &mut self.y);
        for ((&xk, &f), &s) in self.x.iter().zip(&self.forward).zip(&factor.scale) {
            out[f as usize] = xk * s;
        }
    }

    /// The forward half of two solves in one pass over the factor, for a rank-one update of
    /// the solve (Woodbury with one row `a`): with `(S L)(S L)^T = S A S` ([`HalfFactor`]),
    /// keeps `y_b = (S L)^-1 S b` and `y_a = (S L)^-1 S a` (permuted) for
    /// [`Self::backward_combined`] and returns `(y_a . y_a, y_a . y_b)`, which are
    /// `a^T A^-1 a` and `a^T A^-1 b`, summed in double precision. `b`, `a`: length
    /// [`Self::len`], original numbering. The factor is streamed once for both (a tick on a
    /// large factor is bound by that stream). Allocation-free.
    ///
    /// # Panics
    /// If `b` or `a` has the wrong length or `factor` another structure.
    pub fn forward_pair(&mut self, factor: &HalfFactor, b: &[f32], a: &[f32]) -> (f64, f64) {
        let n = self.x.len();
        assert!(b.len() == n && a.len() == n, "right-hand side length");
        assert_eq!(factor.scale.len(), n, "half factor of another structure");
        for (((xk, x2k), &f), &s) in self
            .x
            .iter_mut()
            .zip(&mut self.x2)
            .zip(&self.forward)
            .zip(&factor.scale)
        {
            *xk = b[f as usize] * s;
            *x2k = a[f as usize] * s;
        }
        forward_sweep(
            self.build(),
            &self.nodes,
            0,
            &self.rows,
            factor,
            [&mut self.x, &mut self.x2],
            [&mut self.y, &mut self.y2],
        );
        let (mut aa, mut ab) = (0.0f64, 0.0f64);
        for (&yb, &ya) in self.x.iter().zip(&self.x2) {
            aa += f64::from(ya) * f64::from(ya);
            ab += f64::from(ya) * f64::from(yb);
        }
        (aa, ab)
    }

    /// The backward half after [`Self::forward_pair`]: `out = A^-1 (b - s a)` (original
    /// numbering, length [`Self::len`]) through the same `factor`. Allocation-free.
    ///
    /// # Panics
    /// If `out` has the wrong length or `factor` another structure.
    pub fn backward_combined(&mut self, factor: &HalfFactor, s: f32, out: &mut [f32]) {
        let n = self.x.len();
        assert_eq!(out.len(), n, "solution length");
        assert_eq!(factor.scale.len(), n, "half factor of another structure");
        for (xb, &xa) in self.x.iter_mut().zip(&self.x2) {
            *xb = (-s).mul_add(xa, *xb);
        }
        self.backward_into(factor, out);
    }
}

/// The forward and backward sweeps of `x` cut as `sp` says ([`TreeSplit`], [`Phases`]): the
/// groups' phases on the caller (`x`, `y`) and a worker of `pool` (`sp.xb`, `sp.yb`), the top
/// on the caller. `x` ends as the solution.
fn cut_sweeps(
    pool: &TickPool,
    isa: Build,
    (nodes, rows, factor): (&[[u32; 5]], &[u32], &HalfFactor),
    sp: &mut TreeSplit,
    x: &mut [f32],
    y: &mut [f32],
) {
    let (t0, ct, ph) = (sp.top_start, sp.col_top, &sp.phases);
    let lent = ph.lent_cols.clone();
    sp.xb[lent.clone()].copy_from_slice(&x[lent.clone()]);
    sp.xb[ct..].fill(0.0);
    // The first thread's sums into the waiting supernodes' columns start from zero (their
    // right-hand side is in the second's copy).
    for c in &ph.waiting_cols {
        x[c.clone()].fill(0.0);
    }
    let sweep_forward = |list: &[Range<usize>], x: &mut [f32], y: &mut [f32]| {
        for r in list {
            forward_sweep(isa, &nodes[r.clone()], r.start, rows, factor, [x], [y]);
        }
    };
    for (phase, last) in [(&ph.one, false), (&ph.two, true)] {
        if last {
            if phase.iter().all(Vec::is_empty) {
                break;
            }
            for c in &ph.waiting_cols {
                for (d, &s) in sp.xb[c.clone()].iter_mut().zip(&x[c.clone()]) {
                    *d += s;
                }
            }
        }
        let worker = (&mut sp.xb[..], &mut sp.yb[..]);
        join_phase(pool, phase, &sweep_forward, (x, y), worker);
    }
    for c in &ph.second_cols {
        x[c.clone()].copy_from_slice(&sp.xb[c.clone()]);
    }
    for (xk, &d) in x[ct..].iter_mut().zip(&sp.xb[ct..]) {
        *xk += d;
    }
    forward_sweep(
        isa,
        &nodes[t0..],
        t0,
        rows,
        factor,
        [&mut x[..]],
        [&mut y[..]],
    );
    backward_sweep(isa, &nodes[t0..], t0, rows, factor, x, y);
    sp.xb[ct..].copy_from_slice(&x[ct..]);
    sp.xb[lent.clone()].copy_from_slice(&x[lent]);
    let sweep_backward = |list: &[Range<usize>], x: &mut [f32], y: &mut [f32]| {
        for r in list.iter().rev() {
            backward_sweep(isa, &nodes[r.clone()], r.start, rows, factor, x, y);
        }
    };
    for (phase, second) in [(&ph.two, true), (&ph.one, false)] {
        if phase.iter().all(Vec::is_empty) {
            continue;
        }
        let worker = (&mut sp.xb[..], &mut sp.yb[..]);
        join_phase(pool, phase, &sweep_backward, (x, y), worker);
        // After phase two: the waiting supernodes' solution, for the stolen ones below them.
        for c in ph.waiting_cols.iter().filter(|_| second) {
            x[c.clone()].copy_from_slice(&sp.xb[c.clone()]);
        }
    }
    for c in &ph.second_cols {
        x[c.clone()].copy_from_slice(&sp.xb[c.clone()]);
    }
}

/// A sweep of a list of supernode ranges on a right-hand side and column block.
type SweepList<'a> = dyn Fn(&[Range<usize>], &mut [f32], &mut [f32]) + Sync + 'a;

/// The sweeps of a phase's two lists ([`Phases`]): the first on the caller's `(x, y)` beside
/// the second on a worker's `(xb, yb)`.
fn join_phase(
    pool: &TickPool,
    phase: &[Vec<Range<usize>>; 2],
    sweep: &SweepList<'_>,
    (x, y): (&mut [f32], &mut [f32]),
    (xb, yb): (&mut [f32], &mut [f32]),
) {
    pool.join(|| sweep(&phase[0], x, y), || sweep(&phase[1], xb, yb));
}

/// The sweeps' build: the AVX2 + FMA + F16C token when the CPU has them, and whether that
/// build fuses the single-panel supernodes ([`SupernodalSolve`]'s `fused`).
#[derive(Clone, Copy)]
struct Build {
    isa: Option<Avx2FmaF16c>,
    fused: bool,
}

/// A supernode's first column, column count, start of its values (in faer's layout) and
/// pattern rows.
#[inline(always)]
fn supernode(node: [u32; 5], rows: &[u32]) -> (usize, usize, usize, &[u32]) {
    let [c0, nc, r0, nr, v0] = node.map(|v| v as usize);
    (c0, nc, v0, &rows[r0..r0 + nr])
}

/// [`forward`] of `K` right-hand sides with the CPU's build: AVX2 + FMA + F16C with the token.
#[inline(always)]
fn forward_sweep<const K: usize>(
    build: Build,
    nodes: &[[u32; 5]],
    first: usize,
    rows: &[u32],
    factor: &HalfFactor,
    x: [&mut [f32]; K],
    y: [&mut [f32]; K],
) {
    let starts = &factor.node_start[first..first + nodes.len()];
    #[cfg(target_arch = "x86_64")]
    if let Some(isa) = build.isa {
        // SAFETY: the token proves AVX2, FMA and F16C on this CPU.
        unsafe { forward_avx2::<K>(isa, build.fused, nodes, starts, rows, factor, x, y) };
        return;
    }
    forward::<Portable, K>(Portable, nodes, starts, rows, factor, x, y);
}

/// [`backward`] of the supernodes `nodes` (the structure's from index `first` on) with the
/// CPU's build: AVX2 + FMA + F16C with the token.
#[inline(always)]
fn backward_sweep(
    build: Build,
    nodes: &[[u32; 5]],
    first: usize,
    rows: &[u32],
    factor: &HalfFactor,
    x: &mut [f32],
    y: &mut [f32],
) {
    let starts = &factor.node_start[first..=first + nodes.len()];
    #[cfg(target_arch = "x86_64")]
    if let Some(isa) = build.isa {
        // SAFETY: the token proves AVX2, FMA and F16C on this CPU.
        unsafe { backward_avx2(isa, build.fused, nodes, starts, rows, factor, x, y) };
        return;
    }
    backward(Portable, nodes, starts, rows, factor, x, y);
}

/// [`forward`] compiled for AVX2 + FMA + F16C (the token).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
#[allow(clippy::too_many_arguments)]
fn forward_avx2<const K: usize>(
    isa: Avx2FmaF16c,
    fused: bool,
    nodes: &[[u32; 5]],
    starts: &[[u32; 2]],
    rows: &[u32],
    factor: &HalfFactor,
    x: [&mut [f32]; K],
    y: [&mut [f32]; K],
) {
    // One build for both (two would not inline the panel kernels).
    forward::<Fused, K>(Fused { isa, fused }, nodes, starts, rows, factor, x, y);
}

/// [`backward`] compiled for AVX2 + FMA + F16C (the token).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
#[allow(clippy::too_many_arguments)]
fn backward_avx2(
    isa: Avx2FmaF16c,
    fused: bool,
    nodes: &[[u32; 5]],
    starts: &[[u32; 2]],
    rows: &[u32],
    factor: &HalfFactor,
    x: &mut [f32],
    y: &mut [f32],
) {
    backward(Fused { isa, fused }, nodes, starts, rows, factor, x, y);
}

/// The forward sweep `L y = b` over the supernodes of a [`HalfFactor`] (module docs) for `K`
/// right-hand sides `x[k]` (`S b` in the permuted numbering) at once, each panel of the
/// factor read once for all of them; `y[k]` are their column blocks.
#[inline(always)]
fn forward<P: PanelKernel, const K: usize>(
    kernel: P,
    nodes: &[[u32; 5]],
    starts: &[[u32; 2]],
    rows: &[u32],
    factor: &HalfFactor,
    mut x: [&mut [f32]; K],
    mut y: [&mut [f32]; K],
) {
    for (&node, &[v_start, t_start]) in nodes.iter().zip(starts) {
        let (c0, nc, _, pattern) = supernode(node, rows);
        let h = nc + pattern.len();
        let (v, e) = (v_start as usize, t_start as usize);
        if let Some(node) = Narrow::of(factor, (c0, nc, pattern), [v, e])
            && kernel.forward_single(node, x.each_mut().map(|x| &mut **x))
        {
            continue;
        }
        for k in 0..K {
            let y = &mut y[k][..h + HALF_PAD];
            y[..nc].copy_from_slice(&x[k][c0..c0 + nc]);
            y[nc..].fill(0.0);
        }
        let (mut v, mut e) = (v, e);
        for panel in panels(nc, h) {
            let Panel { p0, w, blocks, .. } = panel;
            let tri = &factor.triangles[e..e + panel.triangle_len];
            let inv = &factor.inv_diag[c0 + p0..c0 + p0 + w];
            // The panel's own columns: `y_i = (y_i - sum_(t<i) L_it y_t) / L_ii`.
            let mut a = [[0.0f32; PANEL]; K];
            for (y, a) in y.iter_mut().zip(&mut a) {
                let mut row = 0;
                for i in 0..w {
                    let mut yi = y[p0 + i];
                    for t in 0..i {
                        yi = (-tri[row + t]).mul_add(y[p0 + t], yi);
                    }
                    row += i;
                    yi *= inv[i];
                    y[p0 + i] = yi;
                    a[i] = yi;
                }
            }
            // The rows below: `y_r -= sum_t L_rt y_t`, eight rows at a time.
            let vals = &factor.values[v..v + panel.values_len];
            let below = p0 + w;
            let tails = y
                .each_mut()
                .map(|y| &mut y[below..below + blocks * HALF_PAD]);
            kernel.update(vals, w, &a, tails);
            v += panel.values_len;
            e += panel.triangle_len;
        }
        for k in 0..K {
            let (x, y) = (&mut *x[k], &*y[k]);
            x[c0..c0 + nc].copy_from_slice(&y[..nc]);
            for (&r, &yr) in pattern.iter().zip(&y[nc..h]) {
                // SAFETY: every pattern row is below `x.len()` (checked by
                // `SupernodalSolve::new`, the only maker of `nodes` and `rows`, whose `x` and
                // `x2` are passed here).
                unsafe { *x.get_unchecked_mut(r as usize) += yr };
            }
        }
    }
}

/// The backward sweep `L^T x = y` after [`forward`]; `x` receives `S^-1 x`. `y` has
/// [`HALF_PAD`] rows of slack past the widest supernode, zeroed before the blocks read them.
#[inline(always)]
fn backward<P: PanelKernel>(
    kernel: P,
    nodes: &[[u32; 5]],
    starts: &[[u32; 2]],
    rows: &[u32],
    factor: &HalfFactor,
    x: &mut [f32],
    y: &mut [f32],
) {
    for (ni, &node) in nodes.iter().enumerate().rev() {
        let (c0, nc, _, pattern) = supernode(node, rows);
        let h = nc + pattern.len();
        let start = starts[ni].map(|o| o as usize);
        if let Some(node) = Narrow::of(factor, (c0, nc, pattern), start)
            && kernel.backward_single(node, x)
        {
            continue;
        }
        let y = &mut y[..h + HALF_PAD];
        y[..nc].copy_from_slice(&x[c0..c0 + nc]);
        for (yr, &r) in y[nc..h].iter_mut().zip(pattern) {
            // SAFETY: as in the forward sweep.
            *yr = unsafe { *x.get_unchecked(r as usize) };
        }
        y[h..].fill(0.0);
        let [mut v, mut e] = starts[ni + 1].map(|o| o as usize);
        for panel in panels(nc, h).rev() {
            let Panel { p0, w, blocks, .. } = panel;
            v -= panel.values_len;
            e -= panel.triangle_len;
            let vals = &factor.values[v..v + panel.values_len];
            let below = p0 + w;
            let tail = &y[below..below + blocks * HALF_PAD];
            // `d_t = sum_r L_rt x_r` over the rows below the panel.
            let d = kernel.dots(vals, w, tail);
            // The panel's own columns, last first: `x_t = (y_t - d_t - sum_(i>t) L_it x_i) / L_tt`.
            let tri = &factor.triangles[e..e + panel.triangle_len];
            let inv = &factor.inv_diag[c0 + p0..c0 + p0 + w];
            for t in (0..w).rev() {
                let mut s = y[p0 + t] - d[t];
                for i in t + 1..w {
                    s = (-tri[i * (i - 1) / 2 + t]).mul_add(y[p0 + i], s);
                }
                y[p0 + t] = s * inv[t];
            }
        }
        x[c0..c0 + nc].copy_from_slice(&y[..nc]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::sparse::SparseColMat;
    use faer::sparse::linalg::cholesky::{LltRef, SymmetricOrdering, factorize_symbolic_cholesky};
    use faer::{Conj, Mat, Par, Side};
    use std::sync::Arc;

    /// [`crate::linalg::grid_matrix`] in single precision (its entries are exact in both).
    pub(super) fn grid_matrix(n: usize) -> SparseColMat<usize, f32> {
        let a = crate::linalg::grid_matrix(n);
        let values = a.val().iter().map(|&v| v as f32).collect();
        SparseColMat::new(a.symbolic().to_owned().expect("a pattern"), values)
    }

    /// The supernodal symbolic factor of `a` (lower triangle) in `ordering` and its
    /// single-precision numeric factor.
    pub(super) fn supernodal_factor(
        a: &SparseColMat<usize, f32>,
        ordering: SymmetricOrdering<'_, usize>,
    ) -> (SymbolicCholesky<usize>, Vec<f32>) {
        let symbolic = factorize_symbolic_cholesky(
            a.symbolic(),
            Side::Lower,
            ordering,
            faer::sparse::linalg::cholesky::CholeskySymbolicParams {
                supernodal_flop_ratio_threshold:
                    faer::sparse::linalg::SupernodalThreshold::FORCE_SUPERNODAL,
                ..Default::default()
            },
        )
        .unwrap();
        let mut values = vec![0.0f32; symbolic.len_val()];
        let mut mem = MemBuffer::new(
            symbolic.factorize_numeric_llt_scratch::<f32>(Par::Seq, Default::default()),
        );
        symbolic
            .factorize_numeric_llt::<f32>(
                &mut values,
                a.as_ref(),
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .unwrap();
        (symbolic, values)
    }

    /// The equations of the grid nodes in the order `nodes` (each node's three together) and
    /// the inverse order, for `faer::perm::PermRef::new_checked`.
    pub(super) fn node_order(nodes: impl Iterator<Item = usize>) -> (Vec<usize>, Vec<usize>) {
        let forward: Vec<usize> = nodes.flat_map(|v| [3 * v, 3 * v + 1, 3 * v + 2]).collect();
        let mut inverse = vec![0; forward.len()];
        for (k, &i) in forward.iter().enumerate() {
            inverse[i] = k;
        }
        (forward, inverse)
    }

    /// The nodes of plane `i` of the `n`-grid.
    pub(super) fn plane(n: usize, i: usize) -> std::ops::Range<usize> {
        i * n * n..(i + 1) * n * n
    }

    /// `D A D` for the diagonal `d` (lower triangle of `a`).
    pub(super) fn scaled(a: &SparseColMat<usize, f32>, d: &[f32]) -> SparseColMat<usize, f32> {
        let mut t = Vec::new();
        for j in 0..a.ncols() {
            for (i, v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                t.push(faer::sparse::Triplet::new(i, j, d[i] * v * d[j]));
            }
        }
        SparseColMat::try_new_from_triplets(a.nrows(), a.ncols(), &t).unwrap()
    }

    /// On the grid matrix and on `D A D` with row scales from 1e-6 to 1e6 (whose entries no
    /// half-precision number could hold unscaled): the half-precision sweep agrees with faer's
    /// solve through the rounded single-precision factor (the same matrix), with the portable
    /// build, the rounding stays within `2^-11` of each entry, and the solution solves the
    /// original system to the half-precision rounding (relative residual below 1e-2, where the
    /// rounded system is solved to single precision).
    #[test]
    fn the_sweep_agrees_with_faers_solve_and_solves_the_system() {
        let a = grid_matrix(9);
        let m = a.nrows();
        let unit = vec![1.0f32; m];
        let wild: Vec<f32> = (0..m).map(|i| 10f32.powi((i % 13) as i32 - 6)).collect();
        for d in [unit, wild] {
            let a = scaled(&a, &d);
            let (symbolic, mut values) = supernodal_factor(&a, SymmetricOrdering::Amd);
            let mut sweep = SupernodalSolve::new(&symbolic).expect("a supernodal factor");
            assert_eq!(sweep.len(), m);
            // The factor has wide supernodes (several panels, a narrower last one, several
            // row blocks below) and narrow ones (one panel narrower than `PANEL`).
            let ncols = |n: &[u32; 5]| n[1] as usize;
            assert!(sweep.nodes.iter().any(|n| {
                ncols(n) > 2 * PANEL && ncols(n) % PANEL != 0 && n[3] as usize > 2 * HALF_PAD
            }));
            assert!(sweep.nodes.iter().any(|n| ncols(n) < PANEL && n[3] > 0));
            let original = values.clone();
            let half = sweep.half_factor(&mut values).expect("32-bit offsets");
            // Every entry of the factor (row scales as D's) rounded by at most 2^-11 of itself
            // (plus the half-precision subnormal spacing of its row for tiny ones).
            let largest = original.iter().fold(0.0f32, |s, v| s.max(v.abs()));
            let mut moved = 0;
            for (o, r) in original.iter().zip(&values) {
                let tiny = 1e-7 * largest;
                assert!(
                    (o - r).abs() <= (1.0 / 2048.0) * o.abs() * 1.0001 + tiny,
                    "{o} rounded to {r}"
                );
                moved += usize::from(o != r);
            }
            assert!(moved > values.len() / 2, "rounding changed {moved} entries");
            let b: Vec<f32> = (0..m)
                .map(|i| (((i * 37 % 101) as f32 - 50.0) / 17.0) * d[i])
                .collect();
            let mut ours = b.clone();
            sweep.solve_in_place(&half, &mut ours);
            let mut theirs = Mat::<f32>::from_fn(m, 1, |i, _| b[i]);
            let mut mem = MemBuffer::new(symbolic.solve_in_place_scratch::<f32>(1, Par::Seq));
            LltRef::<usize, f32>::new(&symbolic, &values).solve_in_place_with_conj(
                Conj::No,
                theirs.as_mut(),
                Par::Seq,
                MemStack::new(&mut mem),
            );
            // The portable build of the sweep gives the same solution (on AVX2 machines the
            // solve above ran the AVX2 build). Compared as `D x`, of order one.
            let mut plain = sweep.clone();
            plain.f16c = None;
            let mut portable = b.clone();
            plain.solve_in_place(&half, &mut portable);
            let scale = ours
                .iter()
                .zip(&d)
                .fold(0.0f32, |s, (v, di)| s.max((v * di).abs()));
            for i in 0..m {
                let (o, t, p) = (ours[i] * d[i], theirs[(i, 0)] * d[i], portable[i] * d[i]);
                assert!(
                    (p - o).abs() <= 1e-5 * scale,
                    "row {i}: portable {p} vs {o}"
                );
                assert!((o - t).abs() <= 1e-5 * scale, "row {i}: {o} vs faer {t}");
            }
            // And it solves the original A x = b to the rounding (the lower triangle is
            // stored: apply both halves), relative to D^-1 b.
            let mut ax = vec![0.0f64; m];
            for j in 0..m {
                for (i, v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                    let v = f64::from(*v);
                    ax[i] += v * f64::from(ours[j]);
                    if i != j {
                        ax[j] += v * f64::from(ours[i]);
                    }
                }
            }
            let rel = (0..m)
                .map(|i| ((ax[i] - f64::from(b[i])) / f64::from(d[i])).abs())
                .fold(0.0, f64::max)
                / (50.0 / 17.0);
            assert!(rel < 1e-2, "relative residual {rel:.2e}");
            println!("relative residual against the unrounded matrix: {rel:.2e}");
            // The paired forward sweep and the combined backward one (both builds) are the
            // one-column solves: `a^T A^-1 a`, `a^T A^-1 b` and `A^-1 (b - s a)`.
            let a_row: Vec<f32> = (0..m)
                .map(|i| if i % 7 == 0 { (i % 5) as f32 - 2.0 } else { 0.0 } * d[i])
                .collect();
            let mut za = a_row.clone();
            sweep.solve_in_place(&half, &mut za);
            let dot = |p: &[f32], q: &[f32]| -> f64 {
                p.iter()
                    .zip(q)
                    .map(|(p, q)| f64::from(*p) * f64::from(*q))
                    .sum()
            };
            let (aa_ref, ab_ref) = (dot(&a_row, &za), dot(&a_row, &ours));
            assert!(aa_ref > 0.0);
            let s = (ab_ref / aa_ref) as f32;
            let mut combined_ref: Vec<f32> = b.iter().zip(&a_row).map(|(b, a)| b - s * a).collect();
            sweep.solve_in_place(&half, &mut combined_ref);
            for solver in [&mut sweep, &mut plain] {
                let (aa, ab) = solver.forward_pair(&half, &b, &a_row);
                assert!(
                    (aa - aa_ref).abs() <= 1e-5 * aa_ref,
                    "a A^-1 a {aa} vs {aa_ref}"
                );
                assert!(
                    (ab - ab_ref).abs() <= 1e-5 * (aa_ref * dot(&b, &ours).abs()).sqrt(),
                    "a A^-1 b {ab} vs {ab_ref}"
                );
                let mut out = vec![0.0f32; m];
                solver.backward_combined(&half, s, &mut out);
                for i in 0..m {
                    let (o, r) = (out[i] * d[i], combined_ref[i] * d[i]);
                    assert!((o - r).abs() <= 1e-5 * scale, "row {i}: {o} vs {r}");
                }
            }
        }
    }

    /// Without a pool `cut` solves as `whole` bit for bit; on a 2-thread pool (returned, for its
    /// statistics) to single-precision round-off (1e-5 of the largest entry), 50 times.
    fn assert_cut_agrees(
        whole: &mut SupernodalSolve,
        cut: &mut SupernodalSolve,
        half: &HalfFactor,
    ) -> Arc<TickPool> {
        let b: Vec<f32> = (0..whole.len())
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 17.0)
            .collect();
        let mut x_whole = b.clone();
        whole.solve_in_place(half, &mut x_whole);
        let mut x_serial = b.clone();
        cut.solve_in_place_in(None, half, &mut x_serial);
        assert_eq!(
            x_serial, x_whole,
            "without a pool the cut sweep is not the whole one"
        );
        let pool = TickPool::new(1, Arc::new(|_| {})).expect("pool");
        let largest = x_whole.iter().fold(0.0f32, |s, v| s.max(v.abs()));
        for _ in 0..50 {
            let mut x_cut = b.clone();
            cut.solve_in_place_in(Some(&pool), half, &mut x_cut);
            let worst = x_whole
                .iter()
                .zip(&x_cut)
                .fold(0.0f32, |s, (p, q)| s.max((p - q).abs()));
            assert!(worst <= 1e-5 * largest, "{worst} against {largest}");
        }
        pool
    }

    /// The sweep cut in two at a fork of the elimination tree (issue 48): on the grid matrix
    /// ordered by one level of nested dissection by hand (the halves `i < 4` and `i > 4`, then
    /// the plane `i = 4`), [`SupernodalSolve::set_parts`] finds the fork; the cut solve on a
    /// 2-thread pool agrees with the whole sweep to single-precision round-off (1e-5 of the
    /// largest entry), and without a pool it is the whole sweep bit for bit. One part never
    /// cuts.
    #[test]
    fn the_sweep_cut_at_a_fork_agrees_with_the_whole_sweep() {
        let n = 9;
        let a = grid_matrix(n);
        let m = a.nrows();
        let planes = (0..n)
            .filter(|&i| i < 4)
            .chain((0..n).filter(|&i| i > 4))
            .chain([4]);
        let (forward, inverse) = node_order(planes.flat_map(|i| plane(n, i)));
        let perm = faer::perm::PermRef::new_checked(&forward, &inverse, m);
        let (symbolic, mut values) = supernodal_factor(&a, SymmetricOrdering::Custom(perm));
        let mut whole = SupernodalSolve::new(&symbolic).expect("a supernodal factor");
        let half = whole.half_factor(&mut values).expect("32-bit offsets");
        let mut cut = whole.clone();
        assert!(!whole.set_parts(1), "one part cut the sweep");
        assert!(cut.set_parts(2), "no fork found");
        let sp = cut.split.as_ref().expect("cut");
        eprintln!(
            "{} supernodes: top from {} (column {} of {m}); {:?}",
            cut.nodes.len(),
            sp.top_start,
            sp.col_top,
            sp.phases
        );
        let pool = assert_cut_agrees(&mut whole, &mut cut, &half);
        // Which thread ran the second half is the scheduler's business (both orders agree).
        eprintln!("pool {:?}", pool.stats());
    }

    /// The sweep cut with two phases ([`split::phases`]): on the grid matrix ordered by hand
    /// into a first side of three planes, a second of five (itself cut by a plane into two and
    /// two) and the plane between them on top, the cut alone leaves the second thread with
    /// most of the work, so the first takes one of the second's subtrees. The phased solve on
    /// a 2-thread pool agrees with the whole sweep to single-precision round-off (1e-5 of the
    /// largest entry), and without a pool it is the whole sweep bit for bit.
    #[test]
    fn the_sweep_in_two_phases_agrees_with_the_whole_sweep() {
        let n = 11;
        let a = grid_matrix(n);
        let m = a.nrows();
        let planes = [0, 1, 2, 3, 5, 6, 8, 9, 10, 7, 4];
        let (forward, inverse) = node_order(planes.into_iter().flat_map(|i| plane(n, i)));
        let perm = faer::perm::PermRef::new_checked(&forward, &inverse, m);
        let (symbolic, mut values) = supernodal_factor(&a, SymmetricOrdering::Custom(perm));
        let mut whole = SupernodalSolve::new(&symbolic).expect("a supernodal factor");
        let half = whole.half_factor(&mut values).expect("32-bit offsets");
        let mut cut = whole.clone();
        assert!(cut.set_parts(2), "no fork found");
        let ph = &cut.split.as_ref().expect("cut").phases;
        eprintln!("{ph:?}");
        assert!(
            !ph.two[0].is_empty() && !ph.two[1].is_empty() && ph.one[0].len() > 1,
            "no second phase: {ph:?}"
        );
        assert_cut_agrees(&mut whole, &mut cut, &half);
    }
}
