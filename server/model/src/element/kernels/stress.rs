//! Lane arithmetic shared by the kernels: 3-vector helpers, the first Piola-Kirchhoff stress of
//! one lane (the formulas of [`crate::material`] written once for every lane type), and the
//! gathers of nodal differences.

use glam::DVec3;

use super::LANES;
use crate::material::{self, MaterialModel, MaterialParams};
use crate::simd::{Lane, LaneVec};

/// `a . b` of two 3-vectors with [`Lane::madd`] (fused multiply-adds when `FMA`; Rust never
/// contracts `a * b + c` by itself, and fusing cut the kernels' instruction count by a third).
#[inline(always)]
pub(super) fn dot3<const FMA: bool, T: Lane>(a: [T; 3], b: [T; 3]) -> T {
    T::madd::<FMA>(a[2], b[2], T::madd::<FMA>(a[1], b[1], a[0] * b[0]))
}

/// Column `j` of a row-major 3x3 matrix.
#[inline(always)]
pub(super) fn column<T: Copy>(m: &[T; 9], j: usize) -> [T; 3] {
    [m[j], m[3 + j], m[6 + j]]
}

/// `a x b` with [`Lane::msub`].
#[inline(always)]
pub(super) fn cross3<const FMA: bool, T: Lane>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [
        T::msub::<FMA>(a[1], b[2], a[2] * b[1]),
        T::msub::<FMA>(a[2], b[0], a[0] * b[2]),
        T::msub::<FMA>(a[0], b[1], a[1] * b[0]),
    ]
}

/// Material models with a vectorised lane kernel, the `MODEL` parameter of the batch kernels.
pub(super) const LANE_STVK: u8 = 0;

/// See [`LANE_STVK`].
pub(super) const LANE_STABLE_NEO_HOOKEAN: u8 = 1;

/// See [`LANE_STVK`].
pub(super) const LANE_COROTATIONAL: u8 = 2;

/// The `MODEL` of the lane kernels for `model`, or `None` (Guccione: scalar path, its fibre
/// frame varies per element).
pub(super) fn lane_model(model: MaterialModel) -> Option<u8> {
    match model {
        MaterialModel::StVenantKirchhoff => Some(LANE_STVK),
        MaterialModel::StableNeoHookean => Some(LANE_STABLE_NEO_HOOKEAN),
        MaterialModel::Corotational => Some(LANE_COROTATIONAL),
        MaterialModel::Guccione => None,
    }
}

/// Newton iterations of [`polar_rotation_lane`]: from a singular value in [0.1, 10] the
/// iteration `sigma <- (sigma + 1/sigma) / 2` reaches 1 to round-off in 8 steps.
const POLAR_ITERATIONS: usize = 8;

/// The rotation `R` of the polar decomposition `F = R S` of each lane (row-major), by Newton's
/// iteration `X <- (X + X^-T) / 2` from `X = F` (Higham 1986, "Computing the polar
/// decomposition - with applications", eq. 3.1; `X^-T = cof X / det X`). Where a lane is
/// inverted or flat (`det F <= 0`, where the corotational law wants the rotation of
/// Irving et al. 2004 rather than the reflection Newton converges to) or has not converged
/// (the last step moved X by more than 1e-9 in Frobenius norm: singular values outside about
/// [0.1, 10]), the whole batch takes the scalar
/// [`crate::material::corotational::polar_decomposition`] lane by lane; both give the same R
/// to round-off where both apply.
#[inline(always)]
pub(super) fn polar_rotation_lane<const FMA: bool, T: LaneVec>(isa: T::Isa, fm: &[T; 9]) -> [T; 9] {
    match newton_polar_lane::<FMA, T>(isa, fm) {
        Some(r) => r,
        None => T::map_matrix_lanes(isa, fm, |f| {
            let m = glam::DMat3::from_cols_array(&f).transpose();
            let (r, _) = material::corotational::polar_decomposition(&m);
            r.transpose().to_cols_array()
        }),
    }
}

/// The Newton part of [`polar_rotation_lane`]: `None` when a lane has `det F <= 0` (or NaN)
/// or has not converged.
#[inline(always)]
pub(super) fn newton_polar_lane<const FMA: bool, T: LaneVec>(
    isa: T::Isa,
    fm: &[T; 9],
) -> Option<[T; 9]> {
    let cross = cross3::<FMA, T>;
    let dot = dot3::<FMA, T>;
    let half = T::splat(isa, 0.5);
    let row = |m: &[T; 9], i: usize| [m[3 * i], m[3 * i + 1], m[3 * i + 2]];
    let det_f = dot(row(fm, 0), cross(row(fm, 1), row(fm, 2)));
    // `!(a > b)` so that NaN lanes fail the checks too.
    #[allow(clippy::neg_cmp_op_on_partial_ord, reason = "NaN must fail the check")]
    if !(det_f.min_lane() > 0.0) {
        return None;
    }
    let mut x = *fm;
    let mut moved = T::splat(isa, 0.0);
    for it in 0..POLAR_ITERATIONS {
        let (r0, r1, r2) = (row(&x, 0), row(&x, 1), row(&x, 2));
        // Rows of cof X: r1 x r2, r2 x r0, r0 x r1; det X = r0 . (r1 x r2).
        let c = [cross(r1, r2), cross(r2, r0), cross(r0, r1)];
        let inv_det = T::splat(isa, 1.0) / dot(r0, c[0]);
        let mut next = x;
        for i in 0..3 {
            for j in 0..3 {
                next[3 * i + j] = half * T::madd::<FMA>(c[i][j], inv_det, x[3 * i + j]);
            }
        }
        if it + 1 == POLAR_ITERATIONS {
            let d: [T; 9] = std::array::from_fn(|k| next[k] - x[k]);
            moved = dot([d[0], d[1], d[2]], [d[0], d[1], d[2]])
                + dot([d[3], d[4], d[5]], [d[3], d[4], d[5]])
                + dot([d[6], d[7], d[8]], [d[6], d[7], d[8]]);
        }
        x = next;
    }
    #[allow(clippy::neg_cmp_op_on_partial_ord, reason = "NaN must fail the check")]
    if !(moved.max_lane() < 1e-18) {
        return None;
    }
    Some(x)
}

/// First Piola-Kirchhoff stress `P = P_elastic + F S_viscous` of one lane, row-major
/// (`fm[3 i + j] = F_ij`, `fd` = `dF/dt` likewise, or `None` without viscosity), Pa. Elastic
/// part by `MODEL`: StVK `F S` with `C = F^T F`, `S = mu (C - I) + lambda/2 (tr C - 3) I`
/// (seed 000 eq. 9); stable Neo-Hookean `mu F + lambda_s (J - alpha) cof F` (see
/// [`MaterialModel::StableNeoHookean`]); corotational `2 mu (F - R) + lambda (tr(R^T F) - 3) R`
/// with R from [`polar_rotation_lane`]. Viscous `S_v = 2 psi nu + phi tr(nu) I`,
/// `nu = F^T Fdot + Fdot^T F` (eq. 10-11). The same formulas as [`material::first_piola`] and
/// [`material::viscous_stress`], generic over the lane type `T` (a [`LaneVec`]).
#[inline(always)]
pub(super) fn first_piola_lane<const FMA: bool, const MODEL: u8, T: LaneVec>(
    isa: T::Isa,
    fm: &[T; 9],
    fd: Option<&[T; 9]>,
    mat: &MaterialParams,
) -> [T; 9] {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    let (phi, psi) = (mat.phi_pa_s, mat.psi_pa_s);
    // No closures here: they are not inlined into the `target_feature` kernels.
    let dot = dot3::<FMA, T>;
    let (c0, c1, c2) = (column(fm, 0), column(fm, 1), column(fm, 2));
    let zero = T::splat(isa, 0.0);
    let mu_v = T::splat(isa, mu);
    // s: the symmetric stress multiplied by F from the left (StVK: S_elastic + S_v; stable
    // Neo-Hookean: S_v only).
    let mut s = [zero; 9];
    if MODEL == LANE_STVK {
        // C = F^T F (symmetric), S = mu (C - I) + lambda/2 (tr C - 3) I.
        let (c00, c11, c22) = (dot(c0, c0), dot(c1, c1), dot(c2, c2));
        let (c01, c02, c12) = (dot(c0, c1), dot(c0, c2), dot(c1, c2));
        let diag = T::splat(isa, 0.5 * lambda) * (c00 + c11 + c22 - T::splat(isa, 3.0)) - mu_v;
        s = [
            T::madd::<FMA>(mu_v, c00, diag),
            mu_v * c01,
            mu_v * c02,
            mu_v * c01,
            T::madd::<FMA>(mu_v, c11, diag),
            mu_v * c12,
            mu_v * c02,
            mu_v * c12,
            T::madd::<FMA>(mu_v, c22, diag),
        ];
    }
    if let Some(fd) = fd {
        // A = F^T Fdot, nu = A + A^T, S_v = 2 psi nu + phi tr(nu) I (eq. 10-11).
        let (d0, d1, d2) = (column(fd, 0), column(fd, 1), column(fd, 2));
        let two = T::splat(isa, 2.0);
        let n00 = two * dot(c0, d0);
        let n11 = two * dot(c1, d1);
        let n22 = two * dot(c2, d2);
        let n01 = dot(c0, d1) + dot(c1, d0);
        let n02 = dot(c0, d2) + dot(c2, d0);
        let n12 = dot(c1, d2) + dot(c2, d1);
        let vd = T::splat(isa, phi) * (n00 + n11 + n22);
        let p2 = T::splat(isa, 2.0 * psi);
        s[0] = s[0] + (T::madd::<FMA>(p2, n00, vd));
        s[4] = s[4] + (T::madd::<FMA>(p2, n11, vd));
        s[8] = s[8] + (T::madd::<FMA>(p2, n22, vd));
        s[1] = s[1] + p2 * n01;
        s[3] = s[3] + p2 * n01;
        s[2] = s[2] + p2 * n02;
        s[6] = s[6] + p2 * n02;
        s[5] = s[5] + p2 * n12;
        s[7] = s[7] + p2 * n12;
    }
    let mut p = [zero; 9];
    if MODEL == LANE_STVK || fd.is_some() {
        for i in 0..3 {
            for j in 0..3 {
                p[3 * i + j] = dot(
                    [fm[3 * i], fm[3 * i + 1], fm[3 * i + 2]],
                    [s[j], s[3 + j], s[6 + j]],
                );
            }
        }
    }
    if MODEL == LANE_COROTATIONAL {
        let r = polar_rotation_lane::<FMA, T>(isa, fm);
        // tr(R^T F) = sum R_ij F_ij (= tr S).
        let tr = dot([r[0], r[1], r[2]], [fm[0], fm[1], fm[2]])
            + dot([r[3], r[4], r[5]], [fm[3], fm[4], fm[5]])
            + dot([r[6], r[7], r[8]], [fm[6], fm[7], fm[8]]);
        let k = T::splat(isa, lambda) * (tr - T::splat(isa, 3.0));
        let two_mu = T::splat(isa, 2.0 * mu);
        for i in 0..9 {
            p[i] = p[i] + T::madd::<FMA>(two_mu, fm[i] - r[i], k * r[i]);
        }
    }
    if MODEL == LANE_STABLE_NEO_HOOKEAN {
        // cof F: columns c1 x c2, c2 x c0, c0 x c1 (= J F^-T); J = c0 . (c1 x c2).
        let cross = cross3::<FMA, T>;
        let cof = [cross(c1, c2), cross(c2, c0), cross(c0, c1)];
        let j = dot(c0, cof[0]);
        let (ls, alpha) = material::neo_hookean_params(lambda, mu);
        let k = T::splat(isa, ls) * (j - T::splat(isa, alpha));
        for i in 0..3 {
            for jj in 0..3 {
                p[3 * i + jj] =
                    p[3 * i + jj] + T::madd::<FMA>(mu_v, fm[3 * i + jj], k * cof[jj][i]);
            }
        }
    }
    p
}

/// Differences `y_a - y_0` (a = 1..N/3) of the nodes of a batch whose gather offsets are
/// `node3` (row a: `3 *` node a of each lane), `y` positions or velocities, for the lanes
/// `off..off + V::WIDTH` of the batch: `out[3 (a - 1) + c]` holds component c, one lane per
/// element. For a linear batch (N = 9) these are the edge
/// vectors `Ds`; for a quadratic one (N = 27) the differences to the first corner.
///
/// # Safety
/// Node indices below `y.len()` (see [`super::Kernels`]).
#[inline(always)]
pub(super) unsafe fn gather_differences<V: LaneVec, const N: usize>(
    isa: V::Isa,
    node3: &[[i32; LANES]],
    off: usize,
    y: &[DVec3],
) -> [V; N] {
    debug_assert_eq!(node3.len(), N / 3 + 1);
    // DVec3 is three packed f64 (checked at compile time in `super`), so component c of node n
    // is at 3 n + c.
    let base = y.as_ptr().cast::<f64>();
    let mut out = [V::splat(isa, 0.0); N];
    // SAFETY: node3 holds 3 * (node index), so the three f64 from base + node3[a][l] are the
    // components of a node below y.len() (caller's contract).
    unsafe {
        let y0 = V::gather3(isa, base, &node3[0][off..]);
        for a in 1..=N / 3 {
            let ya = V::gather3(isa, base, &node3[a][off..]);
            for c in 0..3 {
                out[3 * (a - 1) + c] = ya[c] - y0[c];
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::{LaneVec, Plain8};
    use glam::{DMat3, DQuat};

    /// Eight deformation gradients `Q diag(s) P^T` (rotations Q, P) with singular values `s`.
    fn batch(singular: [[f64; 3]; 8]) -> ([Plain8; 9], [DMat3; 8]) {
        let mats: [DMat3; 8] = std::array::from_fn(|l| {
            let q = DQuat::from_axis_angle(
                glam::DVec3::new(1.0, 2.0, 0.5 + l as f64).normalize(),
                0.3 * l as f64 + 0.1,
            );
            let p = DQuat::from_axis_angle(
                glam::DVec3::new(-0.3, 1.0, l as f64).normalize(),
                1.1 - 0.2 * l as f64,
            );
            DMat3::from_quat(q)
                * DMat3::from_diagonal(glam::DVec3::from_array(singular[l]))
                * DMat3::from_quat(p).transpose()
        });
        let rows: [[f64; 9]; 8] = std::array::from_fn(|l| mats[l].transpose().to_cols_array());
        let lanes = std::array::from_fn(|k| {
            Plain8::load((), &std::array::from_fn::<f64, 8, _>(|l| rows[l][k]))
        });
        (lanes, mats)
    }

    fn lane_matrix(m: &[Plain8; 9], l: usize) -> DMat3 {
        let rows: [f64; 9] = std::array::from_fn(|k| {
            let mut a = [0.0; 8];
            m[k].store(&mut a);
            a[l]
        });
        DMat3::from_cols_array(&rows).transpose()
    }

    #[test]
    fn newton_polar_matches_the_svd_rotation_for_stretches_from_a_tenth_to_ten() {
        let s = [
            [1.0, 1.0, 1.0],
            [1.2, 0.9, 0.8],
            [2.0, 0.5, 1.0],
            [0.1, 1.0, 3.0],
            [10.0, 0.2, 0.5],
            [1.0 + 1e-9, 1.0, 1.0 - 1e-9],
            [0.3, 0.3, 0.3],
            [5.0, 5.0, 0.15],
        ];
        let (lanes, mats) = batch(s);
        let r = newton_polar_lane::<false, Plain8>((), &lanes).expect("converges in 8 steps");
        for (l, f) in mats.iter().enumerate() {
            let (expected, _) = material::corotational::polar_decomposition(f);
            let err = (lane_matrix(&r, l) - expected)
                .to_cols_array()
                .iter()
                .map(|e| e.abs())
                .fold(0.0, f64::max);
            assert!(
                err < 1e-13,
                "lane {l} (singular values {:?}): {err:e}",
                s[l]
            );
        }
    }

    #[test]
    fn inverted_and_extreme_lanes_take_the_scalar_rotation() {
        for bad in [[1.0, 1.0, -0.5], [1e3, 1.0, 1e-3], [1.0, 1.0, 0.0]] {
            let mut s = [[1.1, 0.9, 1.0]; 8];
            s[3] = bad;
            let (lanes, mats) = batch(s);
            assert!(
                newton_polar_lane::<false, Plain8>((), &lanes).is_none(),
                "{bad:?}"
            );
            let r = polar_rotation_lane::<false, Plain8>((), &lanes);
            for (l, f) in mats.iter().enumerate() {
                let (expected, _) = material::corotational::polar_decomposition(f);
                let got = lane_matrix(&r, l);
                let err = (got - expected)
                    .to_cols_array()
                    .iter()
                    .map(|e| e.abs())
                    .fold(0.0, f64::max);
                assert!(err < 1e-12, "lane {l} with {bad:?}: {err:e}");
                // A proper rotation even for the inverted lane (Irving et al. 2004).
                assert!((got.determinant() - 1.0).abs() < 1e-12);
            }
        }
    }
}
