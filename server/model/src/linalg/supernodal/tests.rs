//! Tests of the supernodal sweep and its half-precision factor.

use super::*;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::SparseColMat;
use faer::sparse::linalg::cholesky::{LltRef, SymmetricOrdering, factorize_symbolic_cholesky};
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

/// The supernodal symbolic factor of `a` (lower triangle) in `ordering` and its
/// single-precision numeric factor.
fn supernodal_factor(
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
    let mut mem =
        MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f32>(Par::Seq, Default::default()));
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

/// `D A D` for the diagonal `d` (lower triangle of `a`).
fn scaled(a: &SparseColMat<usize, f32>, d: &[f32]) -> SparseColMat<usize, f32> {
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
    let forward: Vec<usize> = planes
        .flat_map(|i| (0..n * n).map(move |jk| i * n * n + jk))
        .flat_map(|v| [3 * v, 3 * v + 1, 3 * v + 2])
        .collect();
    let mut inverse = vec![0; m];
    for (k, &i) in forward.iter().enumerate() {
        inverse[i] = k;
    }
    let perm = faer::perm::PermRef::new_checked(&forward, &inverse, m);
    let (symbolic, mut values) = supernodal_factor(&a, SymmetricOrdering::Custom(perm));
    let mut whole = SupernodalSolve::new(&symbolic).expect("a supernodal factor");
    let half = whole.half_factor(&mut values).expect("32-bit offsets");
    let mut cut = whole.clone();
    assert!(!whole.set_parts(1), "one part cut the sweep");
    assert!(cut.set_parts(2), "no fork found");
    let sp = cut.split.as_ref().expect("cut");
    eprintln!(
        "{} supernodes: second side from {}, top from {} (columns {} and {} of {m})",
        cut.nodes.len(),
        sp.b_start,
        sp.top_start,
        sp.col_b,
        sp.col_top
    );
    let b: Vec<f32> = (0..m)
        .map(|i| ((i * 37 % 101) as f32 - 50.0) / 17.0)
        .collect();
    let mut x_whole = b.clone();
    whole.solve_in_place(&half, &mut x_whole);
    let mut x_serial = b.clone();
    cut.solve_in_place_in(None, &half, &mut x_serial);
    assert_eq!(
        x_serial, x_whole,
        "without a pool the cut sweep is not the whole one"
    );
    let pool = TickPool::new(1, std::sync::Arc::new(|_| {})).expect("pool");
    for _ in 0..50 {
        let mut x_cut = b.clone();
        cut.solve_in_place_in(Some(&pool), &half, &mut x_cut);
        let largest = x_whole.iter().fold(0.0f32, |s, v| s.max(v.abs()));
        let worst = x_whole
            .iter()
            .zip(&x_cut)
            .fold(0.0f32, |s, (p, q)| s.max((p - q).abs()));
        assert!(worst <= 1e-5 * largest, "{worst} against {largest}");
    }
    // Which thread ran the second half is the scheduler's business (both orders agree).
    eprintln!("pool {:?}", pool.stats());
}
