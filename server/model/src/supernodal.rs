//! One right-hand side through a single-precision supernodal Cholesky factor of faer, for the
//! servo tick: `A x = b` with `A = L L^T` solved in place, allocation-free.
//!
//! faer's `LltRef::solve_in_place_with_conj` is general (many right-hand sides, any scalar,
//! parallelism); for one column it pays a dense triangular solve and a matrix product call per
//! supernode. The LV meshes' factors have many small supernodes (the tick matrix of the default
//! `lv`, 2 727 equations and 485 000 entries, has about one per node), so on that factor the
//! calls took most of the solve. Here each supernode's block is swept as it lies in faer's
//! storage (column-major, the diagonal block on top, then the rows of its pattern): forward,
//! `y = L^-1 b` one column at a time with a contiguous update below the diagonal; backward,
//! `x = L^-T y` with a contiguous dot product per column. The arithmetic is faer's own (the
//! same single-precision products of the same values), so the results agree to round-off
//! (test below); only the loop structure differs (docs/decisions.md, "The whole-body rest
//! factor").
//!
//! Owns: the sweep. May use: [`crate::cpu`].

use faer::sparse::linalg::cholesky::{SymbolicCholesky, SymbolicCholeskyRaw};

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
    /// Whether the AVX2 + FMA build of the sweep runs on this CPU.
    avx2: bool,
}

impl SupernodalSolve {
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
            y: vec![0.0; widest],
            avx2: crate::cpu::has_avx2_fma(),
        })
    }

    /// Number of equations.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// Whether there is no equation.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Solves `L L^T x = b` in place: `b` (length [`Self::len`], original numbering) becomes
    /// `x`. `values` are the factor's (faer's supernodal layout, from
    /// `factorize_numeric_llt::<f32>` on the same symbolic factor). Allocation-free.
    ///
    /// # Panics
    /// If `b` or `values` have the wrong length.
    pub fn solve_in_place(&mut self, values: &[f32], b: &mut [f32]) {
        assert_eq!(b.len(), self.x.len(), "right-hand side length");
        assert_eq!(values.len(), self.len_val, "factor length");
        for (xk, &f) in self.x.iter_mut().zip(&self.forward) {
            *xk = b[f as usize];
        }
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` comes from `crate::cpu::has_avx2_fma` on this CPU.
            unsafe { sweep_avx2(&self.nodes, &self.rows, values, &mut self.x, &mut self.y) };
        } else {
            sweep::<false>(&self.nodes, &self.rows, values, &mut self.x, &mut self.y);
        }
        #[cfg(not(target_arch = "x86_64"))]
        sweep::<false>(&self.nodes, &self.rows, values, &mut self.x, &mut self.y);
        for (&xk, &f) in self.x.iter().zip(&self.forward) {
            b[f as usize] = xk;
        }
    }
}

/// [`sweep`] compiled for AVX2 + FMA.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn sweep_avx2(
    nodes: &[[u32; 5]],
    rows: &[u32],
    values: &[f32],
    x: &mut [f32],
    y: &mut [f32],
) {
    sweep::<true>(nodes, rows, values, x, y);
}

/// `a . b` (`b` at least as long as `a`) with AVX2 + FMA intrinsics: two accumulators of
/// eight lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dot_avx2(a: &[f32], b: &[f32]) -> f32 {
    use std::arch::x86_64::*;
    let n = a.len();
    let b = &b[..n];
    let mut k = 0;
    let mut s0 = _mm256_setzero_ps();
    let mut s1 = _mm256_setzero_ps();
    // SAFETY: every load reads 8 floats at `k` or `k + 8` with `k + 16 <= n` (or `k + 8 <= n`)
    // of slices of length `n`.
    unsafe {
        while k + 16 <= n {
            s0 = _mm256_fmadd_ps(
                _mm256_loadu_ps(a.as_ptr().add(k)),
                _mm256_loadu_ps(b.as_ptr().add(k)),
                s0,
            );
            s1 = _mm256_fmadd_ps(
                _mm256_loadu_ps(a.as_ptr().add(k + 8)),
                _mm256_loadu_ps(b.as_ptr().add(k + 8)),
                s1,
            );
            k += 16;
        }
        if k + 8 <= n {
            s0 = _mm256_fmadd_ps(
                _mm256_loadu_ps(a.as_ptr().add(k)),
                _mm256_loadu_ps(b.as_ptr().add(k)),
                s0,
            );
            k += 8;
        }
    }
    let v = _mm256_add_ps(s0, s1);
    let q = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let q = _mm_add_ps(q, _mm_movehl_ps(q, q));
    let q = _mm_add_ss(q, _mm_movehdup_ps(q));
    let mut s = _mm_cvtss_f32(q);
    for i in k..n {
        s = a[i].mul_add(b[i], s);
    }
    s
}

/// A supernode's first column, column count, start of its values and pattern rows.
#[inline(always)]
fn supernode(node: [u32; 5], rows: &[u32]) -> (usize, usize, usize, &[u32]) {
    let [c0, nc, r0, nr, v0] = node.map(|v| v as usize);
    (c0, nc, v0, &rows[r0..r0 + nr])
}

/// Forward `L y = b` then backward `L^T x = y` over the supernodes (module docs); `x` holds
/// `b` in the permuted numbering and receives `x`.
#[inline(always)]
fn sweep<const AVX2: bool>(
    nodes: &[[u32; 5]],
    rows: &[u32],
    values: &[f32],
    x: &mut [f32],
    y: &mut [f32],
) {
    for &node in nodes {
        let (c0, nc, v0, pattern) = supernode(node, rows);
        let h = nc + pattern.len();
        let y = &mut y[..h];
        y[..nc].copy_from_slice(&x[c0..c0 + nc]);
        y[nc..].fill(0.0);
        for j in 0..nc {
            let col = &values[v0 + j * h..v0 + (j + 1) * h];
            let yj = y[j] / col[j];
            y[j] = yj;
            for (yi, &l) in y[j + 1..].iter_mut().zip(&col[j + 1..]) {
                *yi = l.mul_add(-yj, *yi);
            }
        }
        x[c0..c0 + nc].copy_from_slice(&y[..nc]);
        // `y[nc..]` started at zero and holds minus the update.
        for (&r, &yr) in pattern.iter().zip(&y[nc..]) {
            x[r as usize] += yr;
        }
    }
    for &node in nodes.iter().rev() {
        let (c0, nc, v0, pattern) = supernode(node, rows);
        let h = nc + pattern.len();
        let y = &mut y[..h];
        y[..nc].copy_from_slice(&x[c0..c0 + nc]);
        for (yr, &r) in y[nc..].iter_mut().zip(pattern) {
            *yr = x[r as usize];
        }
        for j in (0..nc).rev() {
            let col = &values[v0 + j * h..v0 + (j + 1) * h];
            let (head, tail) = y.split_at_mut(j + 1);
            let d = if AVX2 {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `AVX2` is set only by `sweep_avx2`, which runs on AVX2 + FMA CPUs.
                unsafe {
                    dot_avx2(&col[j + 1..], tail)
                }
                #[cfg(not(target_arch = "x86_64"))]
                dot8(&col[j + 1..], tail)
            } else {
                dot8(&col[j + 1..], tail)
            };
            head[j] = (head[j] - d) / col[j];
        }
        x[c0..c0 + nc].copy_from_slice(&y[..nc]);
    }
}

/// `a . b` with eight partial sums (so that it vectorises).
#[inline(always)]
fn dot8(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ac, ar) = a.as_chunks::<8>();
    let (bc, br) = b[..a.len()].as_chunks::<8>();
    for (u, v) in ac.iter().zip(bc) {
        for k in 0..8 {
            acc[k] = u[k].mul_add(v[k], acc[k]);
        }
    }
    let mut s = ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (&u, &v) in ar.iter().zip(br) {
        s = u.mul_add(v, s);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::sparse::SparseColMat;
    use faer::sparse::linalg::cholesky::{LltRef, factorize_symbolic_cholesky};
    use faer::{Conj, Mat, Par, Side};

    /// A 3-D Laplacian-like SPD matrix on an `n^3` grid with 3 components per node (block
    /// coupling), large enough for faer to choose a supernodal factor.
    fn grid_matrix(n: usize) -> SparseColMat<usize, f32> {
        let id = |i: usize, j: usize, k: usize| (i * n + j) * n + k;
        let mut t = Vec::new();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let a = id(i, j, k);
                    for c in 0..3 {
                        t.push(faer::sparse::Triplet::new(
                            3 * a + c,
                            3 * a + c,
                            7.0 + c as f32,
                        ));
                        if c > 0 {
                            t.push(faer::sparse::Triplet::new(3 * a + c, 3 * a, 0.5));
                        }
                    }
                    for (di, dj, dk) in [(1, 0, 0), (0, 1, 0), (0, 0, 1)] {
                        let (p, q, r) = (i + di, j + dj, k + dk);
                        if p < n && q < n && r < n {
                            let b = id(p, q, r);
                            for c in 0..3 {
                                t.push(faer::sparse::Triplet::new(3 * b + c, 3 * a + c, -1.0));
                            }
                        }
                    }
                }
            }
        }
        SparseColMat::try_new_from_triplets(3 * n * n * n, 3 * n * n * n, &t).unwrap()
    }

    #[test]
    fn the_sweep_agrees_with_faers_solve_and_solves_the_system() {
        let a = grid_matrix(9);
        let m = a.nrows();
        let symbolic = factorize_symbolic_cholesky(
            a.symbolic(),
            Side::Lower,
            faer::sparse::linalg::cholesky::SymmetricOrdering::Amd,
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
        let mut sweep = SupernodalSolve::new(&symbolic).expect("a supernodal factor");
        assert_eq!(sweep.len(), m);
        let b: Vec<f32> = (0..m)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 17.0)
            .collect();
        let mut ours = b.clone();
        sweep.solve_in_place(&values, &mut ours);
        let mut theirs = Mat::<f32>::from_fn(m, 1, |i, _| b[i]);
        let mut mem = MemBuffer::new(symbolic.solve_in_place_scratch::<f32>(1, Par::Seq));
        LltRef::<usize, f32>::new(&symbolic, &values).solve_in_place_with_conj(
            Conj::No,
            theirs.as_mut(),
            Par::Seq,
            MemStack::new(&mut mem),
        );
        // The portable build of the sweep gives the same solution (on AVX2 machines the test
        // above ran the AVX2 build).
        let mut plain = sweep.clone();
        plain.avx2 = false;
        let mut portable = b.clone();
        plain.solve_in_place(&values, &mut portable);
        let scale = ours.iter().fold(0.0f32, |s, v| s.max(v.abs()));
        for (p, o) in portable.iter().zip(&ours) {
            assert!((p - o).abs() <= 1e-5 * scale, "portable {p} vs {o}");
        }
        for i in 0..m {
            assert!(
                (ours[i] - theirs[(i, 0)]).abs() <= 1e-5 * scale,
                "row {i}: {} vs faer {}",
                ours[i],
                theirs[(i, 0)]
            );
        }
        // And it solves A x = b (the lower triangle is stored: apply both).
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
        for i in 0..m {
            assert!(
                (ax[i] - f64::from(b[i])).abs() < 1e-4,
                "residual at {i}: {} vs {}",
                ax[i],
                b[i]
            );
        }
    }
}
