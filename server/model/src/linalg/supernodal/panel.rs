//! The two panel kernels of the sweeps ([`PanelKernel`]): a panel's update of the rows below it
//! (forward) and its dot products with them (backward), portable or with AVX2 + FMA + F16C.

use super::single::Narrow;
use super::{HALF_PAD, PANEL};
use crate::simd::Avx2FmaF16c;

/// The two panel kernels of the sweeps, [`panel_update`] and [`panel_dots`]: the portable
/// build ([`Portable`]) or the AVX2 + FMA + F16C one (the token [`Avx2FmaF16c`]), with the
/// same fused operations in the same order per entry.
pub(super) trait PanelKernel: Copy {
    /// [`panel_update`].
    fn update<const K: usize>(
        self,
        vals: &[u16],
        w: usize,
        a: &[[f32; PANEL]; K],
        y: [&mut [f32]; K],
    );
    /// [`panel_dots`].
    fn dots(self, vals: &[u16], w: usize, y: &[f32]) -> [f32; PANEL];
    /// [`super::single::forward_single`] for a supernode of one panel with rows below it,
    /// when this build fuses; returns whether it did (else the panel path).
    #[inline(always)]
    fn forward_single<const K: usize>(self, _node: Narrow<'_>, _x: [&mut [f32]; K]) -> bool {
        false
    }
    /// [`super::single::backward_single`], as [`Self::forward_single`].
    #[inline(always)]
    fn backward_single(self, _node: Narrow<'_>, _x: &mut [f32]) -> bool {
        false
    }
}

/// The portable panel kernels.
#[derive(Clone, Copy)]
pub(super) struct Portable;

impl PanelKernel for Portable {
    #[inline(always)]
    fn update<const K: usize>(
        self,
        vals: &[u16],
        w: usize,
        a: &[[f32; PANEL]; K],
        y: [&mut [f32]; K],
    ) {
        panel_update(vals, w, a, y);
    }

    #[inline(always)]
    fn dots(self, vals: &[u16], w: usize, y: &[f32]) -> [f32; PANEL] {
        panel_dots(vals, w, y)
    }
}

#[cfg(target_arch = "x86_64")]
impl PanelKernel for Avx2FmaF16c {
    #[inline(always)]
    fn update<const K: usize>(
        self,
        vals: &[u16],
        w: usize,
        a: &[[f32; PANEL]; K],
        y: [&mut [f32]; K],
    ) {
        // SAFETY: the token proves AVX2, FMA and F16C on this CPU.
        unsafe { panel_update_avx2(self, vals, w, a, y) };
    }

    #[inline(always)]
    fn dots(self, vals: &[u16], w: usize, y: &[f32]) -> [f32; PANEL] {
        // SAFETY: the token proves AVX2, FMA and F16C on this CPU.
        unsafe { panel_dots_avx2(self, vals, w, y) }
    }
}

/// `y_k[8 b + l] -= sum_t vals[(b w + t) 8 + l] a_k[t]` for a panel of `w` columns whose row
/// blocks are `vals` and the `K` right-hand sides' rows below it `y` (portable).
fn panel_update<const K: usize>(
    vals: &[u16],
    w: usize,
    a: &[[f32; PANEL]; K],
    mut y: [&mut [f32]; K],
) {
    for (b, block) in vals.chunks_exact(w * HALF_PAD).enumerate() {
        for (t, col) in block.chunks_exact(HALF_PAD).enumerate() {
            for (y, a) in y.iter_mut().zip(a) {
                for (yl, &l) in y[HALF_PAD * b..HALF_PAD * (b + 1)].iter_mut().zip(col) {
                    *yl = half::f16::from_bits(l).to_f32().mul_add(-a[t], *yl);
                }
            }
        }
    }
}

/// [`panel_update`] with AVX2 + FMA + F16C: the rows of four blocks of every right-hand side
/// held in registers across the panel's columns, each column's coefficient broadcast once for
/// the four (the same fused operations in the same order per entry).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
fn panel_update_avx2<const K: usize>(
    _: Avx2FmaF16c,
    vals: &[u16],
    w: usize,
    a: &[[f32; PANEL]; K],
    mut y: [&mut [f32]; K],
) {
    use std::arch::x86_64::*;
    const U: usize = 4;
    let blocks = vals.len() / (w * HALF_PAD).max(1);
    assert!(w <= PANEL && vals.len() == blocks * w * HALF_PAD);
    assert!(y.iter().all(|y| y.len() == blocks * HALF_PAD));
    let mut b = 0;
    while b < blocks {
        let u = U.min(blocks - b);
        // SAFETY: blocks `b..b + u` of `vals` hold `w * 8` entries each and of each `y` eight,
        // by the asserts; `t < w <= PANEL` indexes `a`.
        unsafe {
            let mut acc = [[_mm256_setzero_ps(); K]; U];
            for (j, acc) in acc.iter_mut().enumerate().take(u) {
                for (a, y) in acc.iter_mut().zip(&y) {
                    *a = _mm256_loadu_ps(y.as_ptr().add(HALF_PAD * (b + j)));
                }
            }
            let block = vals.as_ptr().add(b * w * HALF_PAD);
            for t in 0..w {
                let mut coef = [_mm256_setzero_ps(); K];
                for (c, a) in coef.iter_mut().zip(a) {
                    *c = _mm256_set1_ps(*a.get_unchecked(t));
                }
                // Four blocks unrolled (the usual case), or the last few.
                macro_rules! update {
                    ($n:expr) => {
                        for (j, acc) in acc.iter_mut().enumerate().take($n) {
                            let c = _mm256_cvtph_ps(_mm_loadu_si128(
                                block.add(HALF_PAD * (j * w + t)).cast(),
                            ));
                            for (a, cf) in acc.iter_mut().zip(&coef) {
                                *a = _mm256_fnmadd_ps(c, *cf, *a);
                            }
                        }
                    };
                }
                if u == U {
                    update!(U);
                } else {
                    update!(u);
                }
            }
            for (j, acc) in acc.iter().enumerate().take(u) {
                for (a, y) in acc.iter().zip(y.iter_mut()) {
                    _mm256_storeu_ps(y.as_mut_ptr().add(HALF_PAD * (b + j)), *a);
                }
            }
        }
        b += u;
    }
}

/// `d[t] = sum_(b, l) vals[(b w + t) 8 + l] y[8 b + l]` for a panel of `w` columns (portable).
fn panel_dots(vals: &[u16], w: usize, y: &[f32]) -> [f32; PANEL] {
    let mut d = [0.0f32; PANEL];
    for (block, yb) in vals
        .chunks_exact(w * HALF_PAD)
        .zip(y.chunks_exact(HALF_PAD))
    {
        for (d, col) in d.iter_mut().zip(block.chunks_exact(HALF_PAD)) {
            for (&l, &v) in col.iter().zip(yb) {
                *d = half::f16::from_bits(l).to_f32().mul_add(v, *d);
            }
        }
    }
    d
}

/// [`panel_dots`] with AVX2 + FMA + F16C, for the panel width `w` (1 to [`PANEL`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
fn panel_dots_avx2(isa: Avx2FmaF16c, vals: &[u16], w: usize, y: &[f32]) -> [f32; PANEL] {
    match w {
        8 => panel_dots_w::<8>(isa, vals, y),
        7 => panel_dots_w::<7>(isa, vals, y),
        6 => panel_dots_w::<6>(isa, vals, y),
        5 => panel_dots_w::<5>(isa, vals, y),
        4 => panel_dots_w::<4>(isa, vals, y),
        3 => panel_dots_w::<3>(isa, vals, y),
        2 => panel_dots_w::<2>(isa, vals, y),
        _ => panel_dots_w::<1>(isa, vals, y),
    }
}

/// [`panel_dots_avx2`] for `W` columns: one accumulator per column, two per column for
/// `W <= 4` (alternate blocks), so that the fused multiply-add's latency does not bound it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
fn panel_dots_w<const W: usize>(_: Avx2FmaF16c, vals: &[u16], y: &[f32]) -> [f32; PANEL] {
    use std::arch::x86_64::*;
    let blocks = y.len() / HALF_PAD;
    assert!(W <= PANEL && y.len() == blocks * HALF_PAD && vals.len() == blocks * W * HALF_PAD);
    let mut acc = [_mm256_setzero_ps(); W];
    let mut acc2 = [_mm256_setzero_ps(); W];
    let mut b = 0;
    // SAFETY: block `b < blocks` of `vals` holds `W * 8` entries and of `y` eight. (A macro,
    // not a closure: closures do not inherit `target_feature`.)
    unsafe {
        macro_rules! term {
            ($b:expr, $t:expr) => {
                (
                    _mm256_cvtph_ps(_mm_loadu_si128(
                        vals.as_ptr().add(($b * W + $t) * HALF_PAD).cast(),
                    )),
                    _mm256_loadu_ps(y.as_ptr().add($b * HALF_PAD)),
                )
            };
        }
        if W <= 4 {
            while b + 2 <= blocks {
                for (t, (a, a2)) in acc.iter_mut().zip(&mut acc2).enumerate() {
                    let (c, v) = term!(b, t);
                    *a = _mm256_fmadd_ps(c, v, *a);
                    let (c, v) = term!(b + 1, t);
                    *a2 = _mm256_fmadd_ps(c, v, *a2);
                }
                b += 2;
            }
        }
        while b < blocks {
            for (t, a) in acc.iter_mut().enumerate() {
                let (c, v) = term!(b, t);
                *a = _mm256_fmadd_ps(c, v, *a);
            }
            b += 1;
        }
    }
    let mut d = [0.0f32; PANEL];
    for ((d, a), a2) in d.iter_mut().zip(&acc).zip(&acc2) {
        let v = _mm256_add_ps(*a, *a2);
        let q = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
        let q = _mm_add_ps(q, _mm_movehl_ps(q, q));
        let q = _mm_add_ss(q, _mm_movehdup_ps(q));
        *d = _mm_cvtss_f32(q);
    }
    d
}
