//! The stress of the single-precision kernel ([`super`]), in registers: StVK's second
//! Piola-Kirchhoff stress through `F S`, stable Neo-Hookean's first Piola-Kirchhoff stress
//! written in the displacement gradient, the viscous stress; `-V P` per lane.

use super::{Coefficients, F32Lanes, dot3};

/// The symmetric entries 00 11 22 01 02 12 of a 3x3 matrix, in that order.
const SYM: [(usize, usize); 6] = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)];

/// The constants of the stress, splatted once per call.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub(super) struct LaneCoefficients<V> {
    neo_hookean: bool,
    half_lambda: V,
    lambda_s: V,
    mu: V,
    phi: V,
    two_psi: V,
}

#[cfg(target_arch = "x86_64")]
impl<V: F32Lanes> LaneCoefficients<V> {
    /// # Safety
    /// [`F32Lanes`]' contract.
    #[inline(always)]
    pub(super) unsafe fn new(c: Coefficients) -> Self {
        // SAFETY: the caller's contract.
        unsafe {
            Self {
                neo_hookean: c.neo_hookean,
                half_lambda: V::splat(c.half_lambda),
                lambda_s: V::splat(c.lambda_s),
                mu: V::splat(c.mu),
                phi: V::splat(c.phi),
                two_psi: V::splat(c.two_psi),
            }
        }
    }
}

/// `-V P` (row-major) from the displacement gradient `g = F - I` and, when `VISCOUS`, the
/// velocity gradient `gd = F'`, for rest volumes `volume` (m^3): `2E = G + G^T + G^T G`,
/// `S = lambda/2 tr(2E) I + mu 2E` plus the viscous stress of
/// [`crate::material::viscous_stress`] (`A = F^T F' = F' + G^T F'`, seed eq. 11 with the
/// module note's factor), `P = F S = S + G S` (eq. 9, 22).
///
/// # Safety
/// [`F32Lanes`]' contract.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) unsafe fn scaled_piola<V: F32Lanes, const VISCOUS: bool>(
    g: &[V; 9],
    gd: &[V; 9],
    volume: V,
    k: &LaneCoefficients<V>,
) -> [V; 9] {
    // SAFETY: the caller's contract.
    unsafe {
        let zero = V::zero();
        let (half_lambda, mu, phi, two_psi) = (k.half_lambda, k.mu, k.phi, k.two_psi);
        // S / (-V) = lambda/2 tr(2E) I + mu 2E (StVK only: stable Neo-Hookean's elastic P is
        // added below), plus the viscous phi tr(A + A^T) I + 2 psi (A + A^T) of
        // crate::material::viscous_stress (seed eq. 11 with the factor of the module note).
        let mut tr = zero;
        let mut s = [zero; 6];
        if !k.neo_hookean {
            // 2E_ij = G_ij + G_ji + sum_r G_ri G_rj.
            let mut e2 = [zero; 6];
            for (s, &(i, j)) in SYM.iter().enumerate() {
                let gtg = dot3([g[i], g[3 + i], g[6 + i]], [g[j], g[3 + j], g[6 + j]]);
                e2[s] = gtg.add(g[3 * i + j].add(g[3 * j + i]));
            }
            tr = half_lambda.mul(e2[0].add(e2[1].add(e2[2])));
            for k in 0..6 {
                s[k] = mu.mul(e2[k]);
            }
        }
        if VISCOUS {
            // A = F^T F' = F' + G^T F'; 2E' = A + A^T.
            let mut a = [zero; 9];
            for i in 0..3 {
                for j in 0..3 {
                    a[3 * i + j] = V::fma(
                        g[6 + i],
                        gd[6 + j],
                        V::fma(g[3 + i], gd[3 + j], V::fma(g[i], gd[j], gd[3 * i + j])),
                    );
                }
            }
            let mut trd = zero;
            for (k, &(i, j)) in SYM.iter().enumerate() {
                let ed2 = a[3 * i + j].add(a[3 * j + i]);
                if k < 3 {
                    trd = trd.add(ed2);
                }
                s[k] = V::fma(two_psi, ed2, s[k]);
            }
            tr = V::fma(phi, trd, tr);
        }
        let w = zero.sub(volume);
        for (k, sk) in s.iter_mut().enumerate() {
            let diagonal = if k < 3 { sk.add(tr) } else { *sk };
            *sk = w.mul(diagonal);
        }
        // The full symmetric -V S, row-major.
        let sm = [s[0], s[3], s[4], s[3], s[1], s[5], s[4], s[5], s[2]];
        // P = F S = S + G S.
        let mut p = [zero; 9];
        for i in 0..3 {
            for j in 0..3 {
                p[3 * i + j] = V::fma(
                    g[3 * i + 2],
                    sm[6 + j],
                    V::fma(
                        g[3 * i + 1],
                        sm[3 + j],
                        V::fma(g[3 * i], sm[j], sm[3 * i + j]),
                    ),
                );
            }
        }
        if k.neo_hookean {
            let elastic = neo_hookean_piola(g, k);
            for (pk, ek) in p.iter_mut().zip(elastic) {
                *pk = V::fma(w, ek, *pk);
            }
        }
        p
    }
}

/// `a b - c d` as `fma(a, b, -(c d))`.
///
/// # Safety
/// [`F32Lanes`]' contract.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn difference_of_products<V: F32Lanes>(a: V, b: V, c: V, d: V) -> V {
    // SAFETY: the caller's contract.
    unsafe { V::fma(a, b, V::zero().sub(c.mul(d))) }
}

/// Stable Neo-Hookean's elastic `P = mu F + lambda_s (J - alpha) cof F` (row-major, Pa) from
/// the displacement gradient `g = G = F - I`, written so that every term vanishes at `G = 0`
/// exactly: with `alpha = 1 + mu / lambda_s`, `P = mu G - mu D + lambda_s (J - 1) (I + D)`,
/// `D = cof F - I = tr(G) I - G^T + cof G`, `J - 1 = tr G + tr(cof G) + det G`.
///
/// # Safety
/// [`F32Lanes`]' contract.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn neo_hookean_piola<V: F32Lanes>(g: &[V; 9], k: &LaneCoefficients<V>) -> [V; 9] {
    // SAFETY: the caller's contract.
    unsafe {
        // cof(G): column j is the cross product of the other two columns, in cyclic order.
        let cross = difference_of_products::<V>;
        let cof = [
            cross(g[4], g[8], g[7], g[5]),
            cross(g[5], g[6], g[8], g[3]),
            cross(g[3], g[7], g[6], g[4]),
            cross(g[7], g[2], g[1], g[8]),
            cross(g[8], g[0], g[2], g[6]),
            cross(g[6], g[1], g[0], g[7]),
            cross(g[1], g[5], g[4], g[2]),
            cross(g[2], g[3], g[5], g[0]),
            cross(g[0], g[4], g[3], g[1]),
        ];
        let tr_g = g[0].add(g[4]).add(g[8]);
        let det_g = V::fma(g[0], cof[0], V::fma(g[3], cof[3], g[6].mul(cof[6])));
        let j_minus_1 = tr_g.add(cof[0].add(cof[4]).add(cof[8])).add(det_g);
        let (mu, pressure) = (k.mu, k.lambda_s.mul(j_minus_1));
        let mut p = [V::zero(); 9];
        for i in 0..3 {
            for j in 0..3 {
                // D_ij = tr(G) delta_ij - G_ji + cof(G)_ij.
                let mut d = cof[3 * i + j].sub(g[3 * j + i]);
                if i == j {
                    d = d.add(tr_g);
                }
                let cof_f = if i == j { d.add(V::splat(1.0)) } else { d };
                // mu (G - D) + lambda_s (J - 1) cof F.
                p[3 * i + j] = V::fma(pressure, cof_f, mu.mul(g[3 * i + j].sub(d)));
            }
        }
        p
    }
}
