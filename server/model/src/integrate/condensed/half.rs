use super::*;

/// Largest estimated contraction `||I - A_h^-1 A||` (`A_h` the half-precision factor's
/// matrix) for which the tick uses the half-precision factor: beyond it the rounding would
/// move the step's matrix by more than a few percent of the stiffness margin it is built
/// with, and the single-precision factor is kept.
pub(super) const HALF_MAX_DEVIATION: f64 = 0.05;

/// Power iterations of [`half_of`]'s estimate.
const HALF_CHECK_ITERATIONS: usize = 12;

/// The half-precision form of `factor` (the factor of `a_lower`, the lower triangle of `A`)
/// for `sweep`, with `factor` rounded to the values it holds, when the rounding moves the
/// solve by at most [`HALF_MAX_DEVIATION`]: estimated by power iteration on `I - A_h^-1 A`
/// from a fixed pseudo-random start. `None` (and `factor` untouched) otherwise, without a
/// sweep, or when the half-precision factor would exceed 32-bit offsets.
pub(super) fn half_of(
    sweep: Option<&mut SupernodalSolve>,
    factor: &mut [f32],
    a_lower: &SparseColMat<usize, f32>,
) -> Option<HalfFactor> {
    let sweep = sweep?;
    let mut rounded = factor.to_vec();
    let half = sweep.half_factor(&mut rounded)?;
    let m = a_lower.nrows();
    let mut x: Vec<f64> = (0..m as u64)
        .map(|i| ((i.wrapping_mul(2_654_435_761) % 1_000) as f64) / 500.0 - 1.0)
        .collect();
    let mut y = vec![0.0f32; m];
    let mut deviation = 0.0f64;
    for _ in 0..HALF_CHECK_ITERATIONS {
        let norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(norm > 0.0) {
            break;
        }
        x.iter_mut().for_each(|v| *v /= norm);
        // y = A x (lower triangle stored: both halves).
        let mut ax = vec![0.0f64; m];
        for j in 0..m {
            for (i, &a) in a_lower.row_idx_of_col(j).zip(a_lower.val_of_col(j)) {
                let a = f64::from(a);
                ax[i] += a * x[j];
                if i != j {
                    ax[j] += a * x[i];
                }
            }
        }
        for (yi, a) in y.iter_mut().zip(&ax) {
            *yi = *a as f32;
        }
        sweep.solve_in_place(&half, &mut y);
        // x <- x - A_h^-1 A x; its norm is the contraction along x.
        for (xi, &yi) in x.iter_mut().zip(&y) {
            *xi -= f64::from(yi);
        }
        deviation = x.iter().map(|v| v * v).sum::<f64>().sqrt();
    }
    if !(deviation <= HALF_MAX_DEVIATION) {
        return None;
    }
    factor.copy_from_slice(&rounded);
    Some(half)
}

/// `a . b` for a row `a` of the far map (half-precision bits) and `b` in single precision,
/// summed in single precision with eight independent partial sums (portable).
fn dot_half_plain(a: &[u16], b: &[f32]) -> f64 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += ::half::f16::from_bits(x[k]).to_f32() * y[k];
        }
    }
    let tail: f32 = ra
        .iter()
        .zip(rb)
        .map(|(x, y)| ::half::f16::from_bits(*x).to_f32() * y)
        .sum();
    f64::from(acc.iter().sum::<f32>() + tail)
}

/// [`dot_half_plain`] with AVX2 + FMA + F16C (the token): four accumulators of eight lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
fn dot_half_avx2(_: Avx2FmaF16c, a: &[u16], b: &[f32]) -> f64 {
    use std::arch::x86_64::*;
    assert_eq!(a.len(), b.len());
    let n = a.len();
    let mut acc = [_mm256_setzero_ps(); 4];
    let mut k = 0;
    // SAFETY: every access reads eight entries below `n` of slices of length `n`.
    unsafe {
        while k + 32 <= n {
            for (j, acc) in acc.iter_mut().enumerate() {
                let c = _mm256_cvtph_ps(_mm_loadu_si128(a.as_ptr().add(k + 8 * j).cast()));
                *acc = _mm256_fmadd_ps(c, _mm256_loadu_ps(b.as_ptr().add(k + 8 * j)), *acc);
            }
            k += 32;
        }
        while k + 8 <= n {
            let c = _mm256_cvtph_ps(_mm_loadu_si128(a.as_ptr().add(k).cast()));
            acc[0] = _mm256_fmadd_ps(c, _mm256_loadu_ps(b.as_ptr().add(k)), acc[0]);
            k += 8;
        }
    }
    let v = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
    let mut lanes = [0.0f32; 8];
    // SAFETY: `lanes` holds eight `f32`.
    unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), v) };
    let tail: f32 = a[k..]
        .iter()
        .zip(&b[k..])
        .map(|(x, y)| ::half::f16::from_bits(*x).to_f32() * y)
        .sum();
    f64::from(lanes.iter().sum::<f32>() + tail)
}

/// A row of the far map times the interface displacement, with the CPU's build.
pub(super) fn dot_half(isa: Option<Avx2FmaF16c>, a: &[u16], b: &[f32]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if let Some(isa) = isa {
        // SAFETY: the token proves AVX2, FMA and F16C on this CPU.
        return unsafe { dot_half_avx2(isa, a, b) };
    }
    let _ = isa;
    dot_half_plain(a, b)
}

/// `out += scale a_f` over the equations (`eq`: equation of each global component, or
/// `usize::MAX`), `a_f` row `f` of the probe's coupling.
pub(super) fn add_row(eq: &[usize], c: ContactCoupling<'_>, f: usize, scale: f64, out: &mut [f32]) {
    for (i, u) in c.row(f) {
        for k in 0..3 {
            let e = eq[3 * i as usize + k];
            if e != usize::MAX {
                out[e] += (u[k] * scale) as f32;
            }
        }
    }
}

/// Start of row `a` in the packed upper triangle of a symmetric `g x g` matrix (row `a`
/// holds columns `a..g`, `g - a` entries).
pub(super) fn packed_row_start(a: usize, g: usize) -> usize {
    a * g - a * a.saturating_sub(1) / 2
}

/// One row of a symmetric product from its upper triangle: `y += s u_a` and returns `s . u`
/// (`s` the row's entries right of the diagonal, single precision; `u`, `y` the matching
/// entries), eight independent partial sums so that it vectorises.
#[inline(always)]
fn sym_row_plain(s: &[f32], u: &[f64], y: &mut [f64], ua: f64) -> f64 {
    let mut acc = [0.0; 8];
    let (cs, cu, cy) = (s.chunks_exact(8), u.chunks_exact(8), y.chunks_exact_mut(8));
    let (rs, ru) = (cs.remainder(), cu.remainder());
    for ((x, w), z) in cs.zip(cu).zip(cy) {
        for k in 0..8 {
            let v = f64::from(x[k]);
            acc[k] += v * w[k];
            z[k] += v * ua;
        }
    }
    let n = s.len() - rs.len();
    let mut tail = 0.0;
    for ((x, w), z) in rs.iter().zip(ru).zip(&mut y[n..]) {
        let v = f64::from(*x);
        tail += v * w;
        *z += v * ua;
    }
    acc.iter().sum::<f64>() + tail
}

/// [`sym_row_plain`] compiled for AVX2 + FMA (the token).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn sym_row_avx2(_: Avx2Fma, s: &[f32], u: &[f64], y: &mut [f64], ua: f64) -> f64 {
    sym_row_plain(s, u, y, ua)
}

pub(super) fn sym_row(isa: Option<Avx2Fma>, s: &[f32], u: &[f64], y: &mut [f64], ua: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if let Some(isa) = isa {
        // SAFETY: the token proves AVX2 and FMA on this CPU.
        return unsafe { sym_row_avx2(isa, s, u, y, ua) };
    }
    let _ = isa;
    sym_row_plain(s, u, y, ua)
}

/// `z += a[0] y_0 + a[1] y_1 + a[2] y_2`, `y` the three single-precision columns `y_k` of
/// `z`'s length one after the other.
#[inline(always)]
fn axpy3_plain(z: &mut [f64], a: [f64; 3], y: &[f32]) {
    let m = z.len();
    let (y0, y1, y2) = (&y[..m], &y[m..2 * m], &y[2 * m..3 * m]);
    for (((zr, &u0), &u1), &u2) in z.iter_mut().zip(y0).zip(y1).zip(y2) {
        *zr += a[0] * f64::from(u0) + a[1] * f64::from(u1) + a[2] * f64::from(u2);
    }
}

/// [`axpy3_plain`] compiled for AVX2 + FMA (the token).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn axpy3_avx2(_: Avx2Fma, z: &mut [f64], a: [f64; 3], y: &[f32]) {
    axpy3_plain(z, a, y);
}

pub(super) fn axpy3(isa: Option<Avx2Fma>, z: &mut [f64], a: [f64; 3], y: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    if let Some(isa) = isa {
        // SAFETY: the token proves AVX2 and FMA on this CPU.
        return unsafe { axpy3_avx2(isa, z, a, y) };
    }
    let _ = isa;
    axpy3_plain(z, a, y);
}

#[cfg(test)]
mod tests {
    use super::{dot_half, packed_row_start, sym_row};
    use crate::simd::{Avx2Fma, Avx2FmaF16c};

    /// The packed upper triangle's product (plain lanes, and AVX2 where the CPU has it) is the
    /// dense symmetric product, for sizes with and without a tail of eight.
    #[test]
    fn the_packed_symmetric_product_is_the_dense_one() {
        for g in [1usize, 7, 8, 13, 24, 31] {
            // A symmetric matrix with entries exact in single precision.
            let entry = |a: usize, b: usize| {
                let (i, j) = (a.min(b), a.max(b));
                ((i * 37 + j * 11) % 17) as f64 / 8.0 - 1.0
            };
            let u: Vec<f64> = (0..g).map(|a| (a as f64 * 0.7).sin()).collect();
            let packed: Vec<f32> = (0..g)
                .flat_map(|a| (a..g).map(move |b| entry(a, b) as f32))
                .collect();
            assert_eq!(packed.len(), g * (g + 1) / 2);
            assert_eq!(packed_row_start(g - 1, g), packed.len() - 1);
            let dense: Vec<f64> = (0..g)
                .map(|a| (0..g).map(|b| entry(a, b) * u[b]).sum())
                .collect();
            for isa in [None, Avx2Fma::detect()] {
                let mut y = vec![0.0; g];
                for a in 0..g {
                    let start = packed_row_start(a, g);
                    let row = &packed[start..start + g - a];
                    let (head, tail) = y.split_at_mut(a + 1);
                    let s = sym_row(isa, &row[1..], &u[a + 1..], tail, u[a]);
                    head[a] += f64::from(row[0]) * u[a] + s;
                }
                for (a, (p, d)) in y.iter().zip(&dense).enumerate() {
                    assert!((p - d).abs() <= 1e-12, "g {g}, row {a}: {p} against {d}");
                }
            }
        }
    }

    /// A row of the half-precision far map times the interface displacement (plain lanes, and
    /// AVX2 + F16C where the CPU has it) is the double-precision sum of the rounded entries to
    /// single-precision round-off, for lengths with and without a tail of eight or 32; and the
    /// rounding places the row's sum within `2^-11` of each entry's magnitude.
    #[test]
    fn a_half_precision_map_row_is_its_rounded_dot_product() {
        for g in [1usize, 7, 8, 13, 32, 45, 792] {
            let exact: Vec<f64> = (0..g)
                .map(|j| ((j * 31 % 23) as f64 - 11.0) / 37.0)
                .collect();
            let u: Vec<f64> = (0..g).map(|j| 1e-3 * (j as f64 * 0.37).cos()).collect();
            let row: Vec<u16> = exact
                .iter()
                .map(|&v| ::half::f16::from_f64(v).to_bits())
                .collect();
            let u32: Vec<f32> = u.iter().map(|&v| v as f32).collect();
            let rounded: f64 = row
                .iter()
                .zip(&u32)
                .map(|(&h, &b)| f64::from(::half::f16::from_bits(h).to_f32()) * f64::from(b))
                .sum();
            let magnitude: f64 = exact.iter().zip(&u).map(|(a, b)| (a * b).abs()).sum();
            let true_value: f64 = exact.iter().zip(&u).map(|(a, b)| a * b).sum();
            assert!((rounded - true_value).abs() <= magnitude * (1.0 / 2048.0) + 1e-12 * g as f64);
            for isa in [None, Avx2FmaF16c::detect()] {
                let d = dot_half(isa, &row, &u32);
                assert!(
                    (d - rounded).abs() <= 1e-6 * magnitude,
                    "g {g}, {isa:?}: {d} against {rounded}"
                );
            }
        }
    }
}
