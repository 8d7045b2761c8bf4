//! Quadratic (10-node) tetrahedra in batches of [`LANES`]: the force kernel and the backward
//! Euler operator action of StVK, four integration points per element.

use glam::{DMat3, DVec3};

use super::LANES;
use super::stress::{dot3, first_piola_lane, gather_differences};
use crate::element::quadrature::IntegrationPoints;
use crate::material::MaterialParams;
use crate::simd::LaneVec;

/// [`LANES`] quadratic elements, structure-of-arrays, for the vectorised StVK kernel of
/// 10-node tetrahedra: `grad[q][3 (a - 1) + c][l]` is component c of `grad N_a` (a = 1..9;
/// `grad N_0` is minus their sum and is not needed, since forces use differences to node 0)
/// at integration point q of lane l, `weight_m3[q][l]` its weight. Padding lanes repeat node
/// 0 with zero gradients and weights.
#[derive(Debug, Clone)]
pub(super) struct QuadraticBatch {
    nodes: [[u32; 10]; LANES],
    /// `3 * nodes[l][a]` at `node3[a][l]`: f64 offsets of the node coordinates, for gathers.
    node3: [[i32; LANES]; 10],
    grad: [[[f64; LANES]; 27]; 4],
    weight_m3: [[f64; LANES]; 4],
}

impl QuadraticBatch {
    pub(super) fn build(order: &[u32], points: &IntegrationPoints) -> Vec<Self> {
        order
            .chunks(LANES)
            .map(|chunk| {
                let mut b = Self {
                    nodes: [[0; 10]; LANES],
                    node3: [[0; LANES]; 10],
                    grad: [[[0.0; LANES]; 27]; 4],
                    weight_m3: [[0.0; LANES]; 4],
                };
                for (l, &e) in chunk.iter().enumerate() {
                    let e = e as usize;
                    b.nodes[l].copy_from_slice(&points.nodes[10 * e..10 * e + 10]);
                    debug_assert_eq!(points.node_start[e], 10 * e);
                    for (row, &node) in b.node3.iter_mut().zip(&b.nodes[l]) {
                        row[l] = 3 * node as i32;
                    }
                    for q in 0..4 {
                        let ip = 4 * e + q;
                        b.weight_m3[q][l] = points.weight_m3[ip];
                        for a in 1..10 {
                            let g = points.grad[points.grad_start[ip] + a];
                            for c in 0..3 {
                                b.grad[q][3 * (a - 1) + c][l] = g[c];
                            }
                        }
                    }
                }
                b
            })
            .collect()
    }
}

/// StVK or stable Neo-Hookean (+ viscous) nodal forces of quadratic elements, added to `f`
/// (see [`FemModel::add_internal_forces`]), every batch quantity held in lane type `V` (one
/// lane per element): gathers of `x_a - x_0` (a = 1..9), then per integration point
/// `F = sum_a (x_a - x_0) (grad N_a)^T`, the stress by [`first_piola_lane`] and
/// `h_a -= w P grad N_a`, then [`scatter_quadratic`] (`f_0 -= sum_a h_a`).
///
/// # Safety
/// Node indices below `x.len()`, `v.len()` and `f.len()` (see [`super::Kernels`]).
#[inline(always)]
pub(super) unsafe fn forces_quadratic<const FMA: bool, const MODEL: u8, V: LaneVec>(
    isa: V::Isa,
    batches: &[QuadraticBatch],
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    let zero = V::splat(isa, 0.0);
    let fbase = f.as_mut_ptr().cast::<f64>();
    for batch in batches {
        // The batch in parts of V::WIDTH lanes (one part for eight-lane vectors).
        for off in (0..LANES).step_by(V::WIDTH) {
            // SAFETY: node indices are below x.len() and v.len() (caller's contract).
            let d = unsafe { gather_differences::<V, 27>(isa, &batch.node3, off, x) };
            // No closure (`v.map`): closures are not inlined into `target_feature` functions.
            #[allow(clippy::manual_map)]
            let dv = match v {
                // SAFETY: as above.
                Some(v) => Some(unsafe { gather_differences::<V, 27>(isa, &batch.node3, off, v) }),
                None => None,
            };
            let mut h = [zero; 27];
            for q in 0..4 {
                let g = &batch.grad[q];
                let fm = quadratic_gradient::<FMA, V>(isa, &d, g, off);
                #[allow(clippy::manual_map)]
                let fd = match &dv {
                    Some(dv) => Some(quadratic_gradient::<FMA, V>(isa, dv, g, off)),
                    None => None,
                };
                let p = first_piola_lane::<FMA, MODEL, V>(isa, &fm, fd.as_ref(), mat);
                let w = zero - V::load(isa, &batch.weight_m3[q][off..]);
                let mut m = [zero; 9];
                for (mk, pk) in m.iter_mut().zip(p) {
                    *mk = w * pk;
                }
                add_divergence::<FMA, V>(isa, &m, g, off, &mut h);
            }
            // SAFETY: node indices are below f.len() (caller's contract), and `f` is borrowed
            // mutably here alone.
            unsafe { scatter_quadratic::<V>(isa, &h, &batch.node3, off, fbase) };
        }
    }
}

/// `h_a += M grad N_a` (a = 1..9), `M` row-major (already scaled by the integration weight),
/// `g` a batch's gradients at one integration point (lanes from `off`): the scatter-side
/// counterpart of [`quadratic_gradient`].
#[inline(always)]
fn add_divergence<const FMA: bool, V: LaneVec>(
    isa: V::Isa,
    m: &[V; 9],
    g: &[[f64; LANES]; 27],
    off: usize,
    h: &mut [V; 27],
) {
    for a in 0..9 {
        let ga = [
            V::load(isa, &g[3 * a][off..]),
            V::load(isa, &g[3 * a + 1][off..]),
            V::load(isa, &g[3 * a + 2][off..]),
        ];
        for i in 0..3 {
            let acc = V::madd::<FMA>(m[3 * i], ga[0], h[3 * a + i]);
            let acc = V::madd::<FMA>(m[3 * i + 1], ga[1], acc);
            h[3 * a + i] = V::madd::<FMA>(m[3 * i + 2], ga[2], acc);
        }
    }
}

/// Adds the per-node vectors `h` of lanes `off..off + V::WIDTH` of a quadratic batch
/// (`h[3 (a - 1) + c]`: component c) to the nodes at `base + node3[a][l]`: `h_a` to node a for
/// a = 1..9 and `-sum_a h_a` to node 0, lane after lane ([`LaneVec::scatter_add3`]). Padding
/// lanes carry zeros (zero gradients and weights), so adding them changes nothing.
///
/// # Safety
/// `base` is the first `f64` of a `[DVec3]` holding every node of `node3`, borrowed mutably
/// by the caller alone.
#[inline(always)]
unsafe fn scatter_quadratic<V: LaneVec>(
    isa: V::Isa,
    h: &[V; 27],
    node3: &[[i32; LANES]; 10],
    off: usize,
    base: *mut f64,
) {
    let mut h0 = [V::splat(isa, 0.0); 3];
    for a in 0..9 {
        let ha = [h[3 * a], h[3 * a + 1], h[3 * a + 2]];
        for (s, x) in h0.iter_mut().zip(ha) {
            *s = *s - x;
        }
        // SAFETY: the caller's contract.
        unsafe { V::scatter_add3(ha, base, &node3[a + 1][off..]) };
    }
    // SAFETY: as above.
    unsafe { V::scatter_add3(h0, base, &node3[0][off..]) };
}

/// `F = sum_a d_a (grad N_a)^T`, row-major: `d` from [`gather_differences`], `g` a batch's
/// gradients at one integration point (lanes from `off`).
#[inline(always)]
fn quadratic_gradient<const FMA: bool, V: LaneVec>(
    isa: V::Isa,
    d: &[V; 27],
    g: &[[f64; LANES]; 27],
    off: usize,
) -> [V; 9] {
    let mut out = [V::splat(isa, 0.0); 9];
    for a in 0..9 {
        let ga = [
            V::load(isa, &g[3 * a][off..]),
            V::load(isa, &g[3 * a + 1][off..]),
            V::load(isa, &g[3 * a + 2][off..]),
        ];
        for i in 0..3 {
            for j in 0..3 {
                out[3 * i + j] = V::madd::<FMA>(d[3 * a + i], ga[j], out[3 * i + j]);
            }
        }
    }
    out
}

/// Action of the backward Euler operator's element part on `p` for quadratic StVK elements,
/// added to `out` (see [`FemModel::quadratic_stvk_operator_action`]), every batch quantity in
/// lane type `V`: per integration point `dF = sum_a p_a (grad N_a)^T`,
/// `w (h2 dF S + F S_stvk(sym(F^T dF); lam, mu)) grad N_a` with the cached `F` and `S`.
///
/// # Safety
/// Node indices below `p.len()` and `out.len()` (see [`super::Kernels`]).
#[inline(always)]
#[allow(
    clippy::too_many_arguments,
    reason = "the token, the batches and the cached F, S"
)]
pub(super) unsafe fn stvk_operator_quadratic<const FMA: bool, V: LaneVec>(
    isa: V::Isa,
    batches: &[QuadraticBatch],
    order: &[u32],
    ip_f: &[DMat3],
    ip_s: &[DMat3],
    (h2, lam, mu): (f64, f64, f64),
    p: &[DVec3],
    out: &mut [DVec3],
) {
    let zero = V::splat(isa, 0.0);
    let (h2, lam, mu2, half) = (
        V::splat(isa, h2),
        V::splat(isa, lam),
        V::splat(isa, 2.0 * mu),
        V::splat(isa, 0.5),
    );
    let obase = out.as_mut_ptr().cast::<f64>();
    for (b, batch) in batches.iter().enumerate() {
        let elements = &order[b * LANES..((b + 1) * LANES).min(order.len())];
        // The batch in parts of V::WIDTH lanes (one part for eight-lane vectors).
        for off in (0..LANES).step_by(V::WIDTH) {
            // SAFETY: node indices are below p.len() (caller's contract).
            let dp = unsafe { gather_differences::<V, 27>(isa, &batch.node3, off, p) };
            let mut h = [zero; 27];
            for q in 0..4 {
                let g = &batch.grad[q];
                let df = quadratic_gradient::<FMA, V>(isa, &dp, g, off);
                // Cached F and S of each lane's integration point, lane-innermost, row-major.
                let mut fl = [[0.0; LANES]; 9];
                let mut sl = [[0.0; LANES]; 9];
                for (l, &e) in elements.iter().enumerate().skip(off).take(V::WIDTH) {
                    let ip = 4 * e as usize + q;
                    let (f, s) = (ip_f[ip], ip_s[ip]);
                    for i in 0..3 {
                        for j in 0..3 {
                            fl[3 * i + j][l] = f.col(j)[i];
                            sl[3 * i + j][l] = s.col(j)[i];
                        }
                    }
                }
                let (mut f, mut s) = ([zero; 9], [zero; 9]);
                for k in 0..9 {
                    f[k] = V::load(isa, &fl[k][off..]);
                    s[k] = V::load(isa, &sl[k][off..]);
                }
                // dE = sym(F^T dF), dS = 2 mu dE + lam tr(dE) I.
                let mut de = [zero; 9];
                for i in 0..3 {
                    for j in 0..3 {
                        let a = dot3::<FMA, V>(
                            [f[i], f[3 + i], f[6 + i]],
                            [df[j], df[3 + j], df[6 + j]],
                        );
                        let b = dot3::<FMA, V>(
                            [f[j], f[3 + j], f[6 + j]],
                            [df[i], df[3 + i], df[6 + i]],
                        );
                        de[3 * i + j] = half * (a + b);
                    }
                }
                let tr = de[0] + de[4] + de[8];
                let mut ds = [zero; 9];
                for (d, e) in ds.iter_mut().zip(de) {
                    *d = mu2 * e;
                }
                for k in [0, 4, 8] {
                    ds[k] = V::madd::<FMA>(lam, tr, ds[k]);
                }
                let w = V::load(isa, &batch.weight_m3[q][off..]);
                let mut pk = [zero; 9];
                for i in 0..3 {
                    for j in 0..3 {
                        let geo = dot3::<FMA, V>(
                            [df[3 * i], df[3 * i + 1], df[3 * i + 2]],
                            [s[j], s[3 + j], s[6 + j]],
                        );
                        let mat = dot3::<FMA, V>(
                            [f[3 * i], f[3 * i + 1], f[3 * i + 2]],
                            [ds[j], ds[3 + j], ds[6 + j]],
                        );
                        pk[3 * i + j] = w * V::madd::<FMA>(h2, geo, mat);
                    }
                }
                add_divergence::<FMA, V>(isa, &pk, g, off, &mut h);
            }
            // SAFETY: node indices are below out.len() (caller's contract), and `out` is
            // borrowed mutably here alone.
            unsafe { scatter_quadratic::<V>(isa, &h, &batch.node3, off, obase) };
        }
    }
}
