//! The sweeps' supernodes of a single panel (at most `PANEL` columns; on a 3-D mesh most
//! supernodes are one node's three) with AVX2 + FMA + F16C, the rows below fused with their
//! scatter (forward) or gather (backward) instead of passing through the column block `y`.
//!
//! They do the same fused operations in the same order per entry as the panel path of
//! [`super::forward`] and [`super::backward`] (`panel::panel_update_avx2`,
//! `panel::panel_dots_w`), so the results are the same bits (test
//! `the_fused_single_panels_sweep_bit_for_bit_like_the_panels`). What they save is the block's
//! zero fill, its store and reload, and the scalar scatter of row blocks whose eight rows are
//! consecutive (a vector add into `x`), and on the way back the scalar gather (a hardware
//! gather, or a load for consecutive rows).

#[cfg(target_arch = "x86_64")]
use super::{HALF_PAD, PANEL, PanelKernel};
use super::{HalfFactor, single_panel};
#[cfg(target_arch = "x86_64")]
use crate::simd::Avx2FmaF16c;

/// A supernode of a single panel with rows below it, as the fused sweeps read it: its first
/// column `c0`, its pattern rows, the panel's blocks of [`super::HALF_PAD`] rows below it
/// (`inv.len()` columns of eight each, zero-padded past the pattern), its strictly lower
/// triangle (row by row) and its reciprocal diagonal.
#[derive(Clone, Copy)]
pub(super) struct Narrow<'a> {
    c0: usize,
    pattern: &'a [u32],
    vals: &'a [u16],
    tri: &'a [f32],
    inv: &'a [f32],
}

impl<'a> Narrow<'a> {
    /// The supernode of columns `c0..c0 + nc` with rows `pattern`, whose values and triangle
    /// start at `[v, e]` in `factor`, when it is a single panel with rows below it.
    #[inline(always)]
    pub(super) fn of(
        factor: &'a HalfFactor,
        (c0, nc, pattern): (usize, usize, &'a [u32]),
        [v, e]: [usize; 2],
    ) -> Option<Self> {
        let panel = single_panel(nc, nc + pattern.len())?;
        Some(Self {
            c0,
            pattern,
            vals: &factor.values[v..][..panel.values_len],
            tri: &factor.triangles[e..][..panel.triangle_len],
            inv: &factor.inv_diag[c0..c0 + nc],
        })
    }

    /// Its row blocks, checking that the entries are those of a supernode of `w` columns.
    ///
    /// # Panics
    /// When they are not.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn blocks(&self, w: usize) -> usize {
        let blocks = self.pattern.len().div_ceil(HALF_PAD);
        assert!(w <= PANEL && self.vals.len() == blocks * w * HALF_PAD);
        assert!(self.tri.len() == w * (w - 1) / 2 && self.inv.len() == w);
        blocks
    }
}

/// One supernode of `W` columns `c0..c0 + W` for the forward sweep: its own triangle
/// (`tri`, strictly lower, row by row; `inv` the reciprocal diagonal), then
/// `x_k[r] -= sum_t L_rt y_t` for the rows `r` of `pattern`, whose blocks of [`HALF_PAD`] rows
/// are `vals` (`W` columns of eight each, zero-padded past the pattern).
///
/// # Safety
/// The CPU has AVX2, FMA and F16C (the token); every row of `pattern` and `c0 + W` are at
/// most `x[k].len()`. `vals`, `tri` and `inv` hold the supernode's entries (asserted).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
pub(super) unsafe fn forward_single<const W: usize, const K: usize>(
    _: Avx2FmaF16c,
    node: Narrow<'_>,
    mut x: [&mut [f32]; K],
) {
    use std::arch::x86_64::*;
    let (c0, pattern, vals, tri, inv) = (node.c0, node.pattern, node.vals, node.tri, node.inv);
    let blocks = node.blocks(W);
    let mut coef = [[_mm256_setzero_ps(); W]; K];
    for (x, coef) in x.iter_mut().zip(&mut coef) {
        let y = &mut x[c0..c0 + W];
        let mut row = 0;
        for i in 0..W {
            let mut yi = y[i];
            for t in 0..i {
                yi = (-tri[row + t]).mul_add(y[t], yi);
            }
            row += i;
            yi *= inv[i];
            y[i] = yi;
            coef[i] = _mm256_set1_ps(yi);
        }
    }
    for b in 0..blocks {
        let block_rows = &pattern[HALF_PAD * b..pattern.len().min(HALF_PAD * (b + 1))];
        // SAFETY: block `b` of `vals` holds `W * 8` entries (asserted); the rows index `x`
        // (the caller's contract), eight consecutive ones from the first when the block is
        // full and spans seven.
        unsafe {
            let mut acc = [_mm256_setzero_ps(); K];
            let block = vals.as_ptr().add(b * W * HALF_PAD);
            for t in 0..W {
                let c = _mm256_cvtph_ps(_mm_loadu_si128(block.add(HALF_PAD * t).cast()));
                for (a, cf) in acc.iter_mut().zip(&coef) {
                    *a = _mm256_fnmadd_ps(c, cf[t], *a);
                }
            }
            let first = block_rows[0] as usize;
            if block_rows.len() == HALF_PAD && block_rows[HALF_PAD - 1] as usize == first + 7 {
                for (a, x) in acc.iter().zip(x.iter_mut()) {
                    let p = x.as_mut_ptr().add(first);
                    _mm256_storeu_ps(p, _mm256_add_ps(_mm256_loadu_ps(p), *a));
                }
            } else {
                for (a, x) in acc.iter().zip(x.iter_mut()) {
                    let mut lanes = [0.0f32; HALF_PAD];
                    _mm256_storeu_ps(lanes.as_mut_ptr(), *a);
                    for (&r, &d) in block_rows.iter().zip(&lanes) {
                        *x.get_unchecked_mut(r as usize) += d;
                    }
                }
            }
        }
    }
}

/// One supernode of `W` columns `c0..c0 + W` for the backward sweep:
/// `d_t = sum_r L_rt x_r` over the rows of `pattern` (blocks `vals` as in
/// [`forward_single`]), then its own columns last first,
/// `x_t = (x_t - d_t - sum_(i>t) L_it x_i) / L_tt`.
///
/// # Safety
/// As [`forward_single`]; also every row of `pattern` is below `i32::MAX` (the gather's
/// indices).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
pub(super) unsafe fn backward_single<const W: usize>(
    _: Avx2FmaF16c,
    node: Narrow<'_>,
    x: &mut [f32],
) {
    use std::arch::x86_64::*;
    let (c0, pattern, vals, tri, inv) = (node.c0, node.pattern, node.vals, node.tri, node.inv);
    let blocks = node.blocks(W);
    let mut acc = [_mm256_setzero_ps(); W];
    let mut acc2 = [_mm256_setzero_ps(); W];
    let mut b = 0;
    // SAFETY: block `b < blocks` of `vals` holds `W * 8` entries (asserted); the rows index
    // `x` (the caller's contract): eight consecutive ones from the first when the block is
    // full and spans seven, otherwise gathered under a mask of the block's rows (the other
    // lanes read as zero, as the block's padding does). The same accumulators in the same
    // order as `panel_dots_w`. (Macros, not closures: closures do not inherit
    // `target_feature`.)
    unsafe {
        macro_rules! rows_of {
            ($b:expr) => {{
                let b = $b;
                let block_rows = &pattern[HALF_PAD * b..pattern.len().min(HALF_PAD * (b + 1))];
                let first = block_rows[0] as usize;
                if block_rows.len() == HALF_PAD && block_rows[HALF_PAD - 1] as usize == first + 7 {
                    _mm256_loadu_ps(x.as_ptr().add(first))
                } else {
                    let mut index = [0i32; HALF_PAD];
                    let mut mask = [0i32; HALF_PAD];
                    for (l, &r) in block_rows.iter().enumerate() {
                        index[l] = r as i32;
                        mask[l] = -1;
                    }
                    _mm256_mask_i32gather_ps::<4>(
                        _mm256_setzero_ps(),
                        x.as_ptr(),
                        _mm256_loadu_si256(index.as_ptr().cast()),
                        _mm256_castsi256_ps(_mm256_loadu_si256(mask.as_ptr().cast())),
                    )
                }
            }};
        }
        macro_rules! column {
            ($b:expr, $t:expr) => {
                _mm256_cvtph_ps(_mm_loadu_si128(
                    vals.as_ptr().add(($b * W + $t) * HALF_PAD).cast(),
                ))
            };
        }
        if W <= 4 {
            while b + 2 <= blocks {
                let (v, v2) = (rows_of!(b), rows_of!(b + 1));
                for (t, (a, a2)) in acc.iter_mut().zip(&mut acc2).enumerate() {
                    *a = _mm256_fmadd_ps(column!(b, t), v, *a);
                    *a2 = _mm256_fmadd_ps(column!(b + 1, t), v2, *a2);
                }
                b += 2;
            }
        }
        while b < blocks {
            let v = rows_of!(b);
            for (t, a) in acc.iter_mut().enumerate() {
                *a = _mm256_fmadd_ps(column!(b, t), v, *a);
            }
            b += 1;
        }
    }
    let y = &mut x[c0..c0 + W];
    for t in (0..W).rev() {
        let v = _mm256_add_ps(acc[t], acc2[t]);
        let q = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
        let q = _mm_add_ps(q, _mm_movehl_ps(q, q));
        let q = _mm_add_ss(q, _mm_movehdup_ps(q));
        let mut s = y[t] - _mm_cvtss_f32(q);
        for i in t + 1..W {
            s = (-tri[i * (i - 1) / 2 + t]).mul_add(y[i], s);
        }
        y[t] = s * inv[t];
    }
}

/// The AVX2 + FMA + F16C build, with the single-panel supernodes fused (this module) when
/// `fused`, else through the panels.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub(super) struct Fused {
    pub(super) isa: Avx2FmaF16c,
    pub(super) fused: bool,
}

/// `$f::<W, ..>(args)` for the width `$w` (1 to [`PANEL`]) as a constant.
#[cfg(target_arch = "x86_64")]
macro_rules! by_width {
    ($w:expr, $f:ident, [$($k:tt)*], $($arg:expr),*) => {
        match $w {
            1 => $f::<1 $($k)*>($($arg),*),
            2 => $f::<2 $($k)*>($($arg),*),
            3 => $f::<3 $($k)*>($($arg),*),
            4 => $f::<4 $($k)*>($($arg),*),
            5 => $f::<5 $($k)*>($($arg),*),
            6 => $f::<6 $($k)*>($($arg),*),
            7 => $f::<7 $($k)*>($($arg),*),
            _ => $f::<8 $($k)*>($($arg),*),
        }
    };
}

#[cfg(target_arch = "x86_64")]
impl PanelKernel for Fused {
    #[inline(always)]
    fn update<const K: usize>(
        self,
        vals: &[u16],
        w: usize,
        a: &[[f32; PANEL]; K],
        y: [&mut [f32]; K],
    ) {
        self.isa.update(vals, w, a, y);
    }

    #[inline(always)]
    fn dots(self, vals: &[u16], w: usize, y: &[f32]) -> [f32; PANEL] {
        self.isa.dots(vals, w, y)
    }

    #[inline(always)]
    fn forward_single<const K: usize>(self, node: Narrow<'_>, x: [&mut [f32]; K]) -> bool {
        if !self.fused {
            return false;
        }
        // SAFETY: the token proves AVX2, FMA and F16C; the rows and columns index `x`
        // (checked by `SupernodalSolve::new`, the only maker of the structure).
        unsafe { by_width!(node.inv.len(), forward_single, [, K], self.isa, node, x) };
        true
    }

    #[inline(always)]
    fn backward_single(self, node: Narrow<'_>, x: &mut [f32]) -> bool {
        if !self.fused {
            return false;
        }
        // SAFETY: as in the forward sweep; `fused` is set only when every row fits an `i32`.
        unsafe { by_width!(node.inv.len(), backward_single, [], self.isa, node, x) };
        true
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{grid_matrix, node_order, plane, scaled, supernodal_factor};
    use super::super::{HALF_PAD, SupernodalSolve, single_panel, supernode};
    use crate::pool::TickPool;
    use faer::sparse::linalg::cholesky::SymmetricOrdering;

    /// The fused single-panel supernodes ([`single`]) give the panel path's solution bit for
    /// bit: whole, and the paired forward sweep with the combined backward one, on the grid
    /// matrix in AMD order, scaled and wildly scaled; and cut on a 2-thread pool in a nested
    /// dissection order whose halves are scrambled. Each case has narrow supernodes whose row
    /// blocks are eight consecutive rows and others.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_fused_single_panels_sweep_bit_for_bit_like_the_panels() {
        let n = 9;
        let a = grid_matrix(n);
        let m = a.nrows();
        let wild: Vec<f32> = (0..m).map(|i| 10f32.powi((i % 13) as i32 - 6)).collect();
        // Each half's nodes scrambled (narrow supernodes), then the plane `i = 4`.
        let half_nodes = 4 * n * n;
        let scramble = |v: usize| v * 97 % half_nodes;
        let sides = (0..half_nodes)
            .map(scramble)
            .chain((0..half_nodes).map(|v| half_nodes + n * n + scramble(v)));
        let (forward, inverse) = node_order(sides.chain(plane(n, 4)));
        let nested = faer::perm::PermRef::new_checked(&forward, &inverse, m);
        let pool = TickPool::new(1, std::sync::Arc::new(|_| {})).expect("pool");
        let b: Vec<f32> = (0..m)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) / 17.0)
            .collect();
        let a_row: Vec<f32> = (0..m).map(|i| (i % 5) as f32 - 2.0).collect();
        let cases = [
            (SymmetricOrdering::Amd, vec![1.0f32; m]),
            (SymmetricOrdering::Amd, wild.clone()),
            (SymmetricOrdering::Custom(nested), wild),
        ];
        for (case, (ordering, d)) in cases.into_iter().enumerate() {
            let a = scaled(&a, &d);
            let (symbolic, mut values) = supernodal_factor(&a, ordering);
            let mut fused = SupernodalSolve::new(&symbolic).expect("a supernodal factor");
            assert!(
                fused.f16c.is_some() && fused.fused,
                "needs AVX2 + FMA + F16C, as every machine the project runs on"
            );
            let (mut consecutive, mut scattered) = (0, 0);
            for node in &fused.nodes {
                let (_, nc, _, pattern) = supernode(*node, &fused.rows);
                if single_panel(nc, nc + pattern.len()).is_some() {
                    for block in pattern.chunks(HALF_PAD) {
                        let span = block[block.len() - 1] - block[0];
                        match block.len() == HALF_PAD && span == 7 {
                            true => consecutive += 1,
                            false => scattered += 1,
                        }
                    }
                }
            }
            assert!(
                consecutive > 0 && scattered > 0,
                "case {case}: {consecutive} / {scattered}"
            );
            let half = fused.half_factor(&mut values).expect("32-bit offsets");
            let mut panels = fused.clone();
            panels.fused = false;
            let cut = case == 2;
            let mut solutions = Vec::new();
            for solver in [&mut fused, &mut panels] {
                let (b, a_row): (Vec<f32>, Vec<f32>) = b
                    .iter()
                    .zip(&a_row)
                    .zip(&d)
                    .map(|((b, a), d)| (b * d, a * d))
                    .unzip();
                let mut x = b.clone();
                if cut {
                    assert!(solver.set_parts(2), "no fork found");
                    solver.solve_in_place_in(Some(&pool), &half, &mut x);
                } else {
                    solver.solve_in_place(&half, &mut x);
                }
                let pair = solver.forward_pair(&half, &b, &a_row);
                let mut combined = vec![0.0f32; m];
                solver.backward_combined(&half, 0.25, &mut combined);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                solutions.push((bits(&x), pair, bits(&combined)));
            }
            assert!(
                solutions[0] == solutions[1],
                "case {case}: the fused sweep differs"
            );
        }
    }
}
