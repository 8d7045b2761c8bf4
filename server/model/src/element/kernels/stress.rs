//! Lane arithmetic shared by the kernels: 3-vector helpers, the first Piola-Kirchhoff stress of
//! one lane (the formulas of [`crate::material`] written once for every lane type), and the
//! gathers of nodal differences.

use glam::DVec3;

use super::LANES;
use super::lanes::{Lane, Lanes8};
use crate::material::{self, MaterialModel, MaterialParams};

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

/// The `MODEL` of the lane kernels for `model`, or `None` (corotational, Guccione: scalar path).
pub(super) fn lane_model(model: MaterialModel) -> Option<u8> {
    match model {
        MaterialModel::StVenantKirchhoff => Some(LANE_STVK),
        MaterialModel::StableNeoHookean => Some(LANE_STABLE_NEO_HOOKEAN),
        MaterialModel::Corotational | MaterialModel::Guccione => None,
    }
}

/// First Piola-Kirchhoff stress `P = P_elastic + F S_viscous` of one lane, row-major
/// (`fm[3 i + j] = F_ij`, `fd` = `dF/dt` likewise, or `None` without viscosity), Pa. Elastic
/// part by `MODEL`: StVK `F S` with `C = F^T F`, `S = mu (C - I) + lambda/2 (tr C - 3) I`
/// (seed 000 eq. 9); stable Neo-Hookean `mu F + lambda_s (J - alpha) cof F` (see
/// [`MaterialModel::StableNeoHookean`]). Viscous `S_v = 2 psi nu + phi tr(nu) I`,
/// `nu = F^T Fdot + Fdot^T F` (eq. 10-11). The same formulas as [`material::first_piola`] and
/// [`material::viscous_stress`], generic over the lane type `T` (one `f64` or a [`Lanes8`]).
#[inline(always)]
pub(super) fn first_piola_lane<const FMA: bool, const MODEL: u8, T: Lane>(
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
/// `node3` (row a: `3 *` node a of each lane), `y` positions or velocities: `out[3 (a - 1) + c]`
/// holds component c, one lane per element. For a linear batch (N = 9) these are the edge
/// vectors `Ds`; for a quadratic one (N = 27) the differences to the first corner.
///
/// # Safety
/// Node indices below `y.len()` (see [`super::Kernels`]).
#[inline(always)]
pub(super) unsafe fn gather_differences<V: Lanes8, const N: usize>(
    isa: V::Isa,
    node3: &[[i32; LANES]],
    y: &[DVec3],
) -> [V; N] {
    debug_assert_eq!(node3.len(), N / 3 + 1);
    // DVec3 is three packed f64 (checked at compile time in `super`), so component c of node n
    // is at 3 n + c.
    let base = y.as_ptr().cast::<f64>();
    let mut out = [V::splat(isa, 0.0); N];
    for c in 0..3 {
        // SAFETY: node3 holds 3 * (node index), so offset + c addresses a component of a node
        // below y.len() (caller's contract).
        unsafe {
            let p = base.add(c);
            let y0 = V::gather(isa, p, &node3[0]);
            for a in 1..=N / 3 {
                out[3 * (a - 1) + c] = V::gather(isa, p, &node3[a]) - y0;
            }
        }
    }
    out
}
