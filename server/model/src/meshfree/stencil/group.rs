//! The group loop of [`super::StencilGrid`] (module documentation of [`super`] for the formulas):
//! every group of eight cells along x through pass 1 (positions to `F`, hourglass sums), the
//! stress and pass 2 (forces onto the grid), with its lane helpers, written once over
//! [`Lanes8`] (single precision) and compiled plain and for AVX2 + FMA.

use std::ops::Range;

use glam::{DMat3, DVec3};

use super::layout::{GroupRest, StencilLayout};
use super::offsets::Stencil;
use super::{CUBE, CUBE_CLASS, LANES, MAX_PAIRS};
use crate::material::stvk::{green_strain, stvk_stress};
use crate::material::{MaterialModel, MaterialParams, first_piola};
use crate::meshfree::cloud::{MAX_STENCIL, outer};
use crate::simd::Lanes8;
#[cfg(target_arch = "x86_64")]
use crate::simd::{Avx2Fma, Ymm8};
/// Nine lane vectors of a column-major 3x3 matrix per lane.
#[inline(always)]
fn lane_mat<V: Lanes8>(isa: V::Isa, a: &[[f32; LANES]; 9]) -> [V; 9] {
    // A loop, not `array::from_fn`: closures do not inherit the caller's target features.
    let mut m = [V::zero(isa); 9];
    for (m, a) in m.iter_mut().zip(a) {
        *m = V::from_array(isa, *a);
    }
    m
}

/// `N - beta_c (F - I)` for each class `c` of stencil length from `f` = `F - I` (at most
/// three; `N` when `seed`): with `c_k X_k = beta_c w_k`, the part `N w_k - F c_k X_k + c_k X_k`
/// of `grad_ik` (module documentation) is `(N - beta_c (F - I)) w_k`.
#[inline(always)]
fn class_matrices<V: Lanes8>(
    n: &[V; 9],
    f: &[V; 9],
    classes: &[(f64, f64, std::ops::Range<usize>)],
    seed: bool,
    isa: V::Isa,
) -> [[V; 9]; 3] {
    let mut out = [*n; 3];
    if !seed {
        for (o, cl) in out.iter_mut().zip(classes) {
            let beta = V::splat(isa, cl.0);
            for e in 0..9 {
                o[e] = V::nmadd(f[e], beta, n[e]);
            }
        }
    }
    out
}

/// `a b` lane-wise (column-major).
#[inline(always)]
fn mat_mul<V: Lanes8>(a: &[V; 9], b: &[V; 9]) -> [V; 9] {
    let mut out = *a;
    for c in 0..3 {
        for r in 0..3 {
            let mut acc = a[r].mul(b[3 * c]);
            acc = V::madd(a[3 + r], b[3 * c + 1], acc);
            acc = V::madd(a[6 + r], b[3 * c + 2], acc);
            out[3 * c + r] = acc;
        }
    }
    out
}

/// `a v` lane-wise (column-major `a`).
#[inline(always)]
fn mat_vec<V: Lanes8>(a: &[V; 9], v: &[V; 3]) -> [V; 3] {
    let mut out = *v;
    for (r, o) in out.iter_mut().enumerate() {
        let mut acc = a[r].mul(v[0]);
        acc = V::madd(a[3 + r], v[1], acc);
        acc = V::madd(a[6 + r], v[2], acc);
        *o = acc;
    }
    out
}

/// The column-major 3x3 matrix of each lane of nine lane vectors.
#[inline(always)]
fn lane_matrices<V: Lanes8>(a: &[V; 9]) -> [[f64; 9]; LANES] {
    let c: [[f32; LANES]; 9] = [
        a[0].to_array(),
        a[1].to_array(),
        a[2].to_array(),
        a[3].to_array(),
        a[4].to_array(),
        a[5].to_array(),
        a[6].to_array(),
        a[7].to_array(),
        a[8].to_array(),
    ];
    let mut out = [[0.0; 9]; LANES];
    for (l, m) in out.iter_mut().enumerate() {
        for (e, v) in m.iter_mut().enumerate() {
            *v = c[e][l].into();
        }
    }
    out
}

/// [`group_loop`] on AVX2 + FMA lanes, compiled for them (the token proves the CPU has them).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) fn group_loop_avx2(
    isa: Avx2Fma,
    st: &Stencil,
    lay: &StencilLayout,
    part: GroupPart<'_>,
    mat: &MaterialParams,
) {
    group_loop::<Ymm8>(isa, st, lay, part, mat);
}

/// One part of a group loop: the grid positions (x, y, z displacement per cell, shared by
/// every part), the part's own force buffers (`GridBuffers`' layout) and its groups.
pub(super) struct GroupPart<'a> {
    pub(super) pos: [&'a [f32]; 3],
    pub(super) fc: &'a mut [Vec<f32>; 3],
    pub(super) groups: Range<usize>,
}

/// Pass 1's sums of a group: `G` (`ga`), (corrected) `Gb` (`gb`) and `sum_k c_k u_(i+k)`
/// (`cu`), lane-wise ([`pass_one`]).
type PassOne<V> = ([V; 9], [V; 9], [V; 3]);

/// What the stress gives pass 2 for a group: `N`, `F - I` (corrected; zero for the seed
/// variant) and the owner's force, lane-wise.
type StressOut<V> = ([V; 9], [V; 9], [V; 3]);

/// Every group's forces from the grid positions into the grid forces (module documentation
/// of [`super`] for the formulas): pass 1, the stress (St. Venant-Kirchhoff lane-wise, other
/// laws per lane), pass 2.
#[inline(always)]
pub(super) fn group_loop<V: Lanes8>(
    isa: V::Isa,
    st: &Stencil,
    lay: &StencilLayout,
    part: GroupPart<'_>,
    mat: &MaterialParams,
) {
    let GroupPart { pos, fc, groups } = part;
    let stvk = mat.model == MaterialModel::StVenantKirchhoff;
    let neo_hookean = mat.model == MaterialModel::StableNeoHookean && !st.seed;
    let nk = lay.off.len();
    assert!(nk <= MAX_STENCIL && st.w.len() == nk && st.c.len() == nk && st.u.len() == nk);
    let zero = V::zero(isa);
    // Pass 2's `(N - beta F) w_k` of each pair, written before it is read.
    assert!(lay.pairs.len() <= MAX_PAIRS);
    let mut ah = [[zero; 3]; MAX_PAIRS];
    for (g, &base) in lay
        .groups
        .iter()
        .enumerate()
        .take(groups.end)
        .skip(groups.start)
    {
        let b = base as usize;
        let gq = &lay.group_rest[g];
        let own = V::from_array(isa, gq.own);
        let ui = [
            V::load(isa, pos[0], b),
            V::load(isa, pos[1], b),
            V::load(isa, pos[2], b),
        ];
        let sums = pass_one(isa, st, lay, pos, b);
        let out = if st.seed || stvk {
            stress_stvk(isa, st, gq, &sums, ui, own, mat)
        } else if neo_hookean {
            stress_neo_hookean(isa, st, gq, &sums, ui, mat)
        } else {
            stress_per_lane(isa, st, gq, &sums, ui, mat)
        };
        pass_two_group(isa, st, lay, (pos, &mut *fc), b, own, ui, &out, &mut ah);
    }
}

/// Pass 1 of the group at cell `b`, over pairs `(k, -k)` (`w_-k = -w_k`):
/// `G = sum_k u_(i+k) (x) w_k`, and (corrected) `Gb = sum_k beta_k u_(i+k) (x) w_k =
/// sum_k u_(i+k) (x) c_k X_k` and `sum_k c_k u_(i+k)`, class by class (`beta` and `c` depend
/// on `|k|` only).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // one index into several 3x3 lane matrices
fn pass_one<V: Lanes8>(
    isa: V::Isa,
    st: &Stencil,
    lay: &StencilLayout,
    pos: [&[f32]; 3],
    b: usize,
) -> PassOne<V> {
    let (seed, zero) = (st.seed, V::zero(isa));
    let [px, py, pz] = pos;
    let mut ga = [zero; 9];
    let mut gb = [zero; 9];
    let mut cu = [zero; 3];
    if st.cube {
        // The same sums with w_k = scale_c e_k: per class the signed sums of the
        // u_(i+k) - u_(i-k) by grid axis (columns perm[a]), scaled once.
        let perm = lay.grid.perm;
        let (gl, sl) = pass_one_cube::<V>(isa, b, &lay.cube_off, px, py, pz, seed);
        for (c, &(beta, ck, _)) in st.classes.iter().enumerate() {
            let scale = V::splat(isa, st.cube_scale[c]);
            for a in 0..3 {
                for r in 0..3 {
                    let e = 3 * perm[a] + r;
                    if seed {
                        ga[e] = V::madd(gl[c][3 * a + r], scale, ga[e]);
                    } else {
                        let gc = gl[c][3 * a + r].mul(scale);
                        ga[e] = ga[e].add(gc);
                        gb[e] = V::madd(gc, V::splat(isa, beta), gb[e]);
                    }
                }
            }
            if !seed {
                let cv = V::splat(isa, ck);
                for r in 0..3 {
                    cu[r] = V::madd(sl[c][r], cv, cu[r]);
                }
            }
        }
        return (ga, gb, cu);
    }
    for &(beta, ck, ref range) in &st.classes {
        let mut gc = [zero; 9];
        let mut sc = [zero; 3];
        for &(k, o) in &lay.pairs[range.clone()] {
            let (hi, lo) = ((b as isize + o) as usize, (b as isize - o) as usize);
            let a = [
                V::load(isa, px, hi),
                V::load(isa, py, hi),
                V::load(isa, pz, hi),
            ];
            let m = [
                V::load(isa, px, lo),
                V::load(isa, py, lo),
                V::load(isa, pz, lo),
            ];
            let w = st.w[k];
            for r in 0..3 {
                let d = a[r].sub(m[r]);
                for c in 0..3 {
                    gc[3 * c + r] = V::madd(d, V::splat(isa, w[c]), gc[3 * c + r]);
                }
                if !seed {
                    sc[r] = sc[r].add(a[r].add(m[r]));
                }
            }
        }
        if seed {
            for e in 0..9 {
                ga[e] = ga[e].add(gc[e]);
            }
        } else {
            let (bv, cv) = (V::splat(isa, beta), V::splat(isa, ck));
            for e in 0..9 {
                ga[e] = ga[e].add(gc[e]);
                gb[e] = V::madd(gc[e], bv, gb[e]);
            }
            for r in 0..3 {
                cu[r] = V::madd(sc[r], cv, cu[r]);
            }
        }
    }
    (ga, gb, cu)
}

/// The St. Venant-Kirchhoff stress of a group lane-wise (the seed variant's law always), from
/// pass 1's sums and the group's rest data `gq`; `ui`: the owners' displacements, `own`: 1 on
/// owner lanes.
///
/// Seed: `F = F~ = A + G - u_i (x) S`, `E = (F^T F - I) / 2 - E0`, `N = V F S(E)`.
/// Corrected: `F - I = (F~ - A) A^-1 = (G - u_i (x) S) A^-1` (`A A^-1 = I`; zero on padding
/// lanes, whose `A^-1` is stored as zero), `E = ((F - I) + (F - I)^T + (F - I)^T (F - I)) / 2`,
/// `M = V F S(E) + (F - I) Q - Gb + u_i (x) U`, `N = M A^-T` (zero on padding lanes).
#[inline(always)]
fn stress_stvk<V: Lanes8>(
    isa: V::Isa,
    st: &Stencil,
    gq: &GroupRest,
    sums: &PassOne<V>,
    ui: [V; 3],
    own: V,
    mat: &MaterialParams,
) -> StressOut<V> {
    let seed = st.seed;
    let (ga, gb, cu) = sums;
    let (f, fmi) = lane_deformation(isa, seed, gq, ga, ui);
    let e = lane_strain(isa, seed, gq, &f, &fmi);
    let sv = lane_stvk(isa, mat, st.volume_m3, &e);
    let mut m = mat_mul(&f, &sv);
    let ld = |a: &[f32; LANES]| V::from_array(isa, *a);
    let s3 = [ld(&gq.s[0]), ld(&gq.s[1]), ld(&gq.s[2])];
    if seed {
        for x in &mut m {
            *x = x.mul(own);
        }
        let ov = mat_vec(&m, &s3);
        return (m, [V::zero(isa); 9], ov);
    }
    corrected_forces(isa, gq, m, &f, fmi, gb, cu, ui, own, s3)
}

/// `F` and (corrected) `F - I` of a group lane-wise ([`stress_stvk`]); seed: `F` twice.
#[inline(always)]
fn lane_deformation<V: Lanes8>(
    isa: V::Isa,
    seed: bool,
    gq: &GroupRest,
    ga: &[V; 9],
    ui: [V; 3],
) -> ([V; 9], [V; 9]) {
    let ld = |a: &[f32; LANES]| V::from_array(isa, *a);
    let mut ft = [V::zero(isa); 9];
    for c in 0..3 {
        let sc = ld(&gq.s[c]);
        for r in 0..3 {
            let base = if seed {
                ld(&gq.a[3 * c + r]).add(ga[3 * c + r])
            } else {
                ga[3 * c + r]
            };
            ft[3 * c + r] = V::nmadd(ui[r], sc, base);
        }
    }
    // Seed: `fmi` unused.
    let fmi = if seed {
        ft
    } else {
        mat_mul(&ft, &lane_mat(isa, &gq.a))
    };
    let f = if seed {
        ft
    } else {
        let mut f = fmi;
        for i in [0, 4, 8] {
            f[i] = f[i].add(V::splat(isa, 1.0));
        }
        f
    };
    (f, fmi)
}

/// The Green strain lane-wise (column-major, symmetric): seed `(F^T F - I) / 2 - E0` (`E0`
/// in `gq.q`), corrected `((F - I) + (F - I)^T + (F - I)^T (F - I)) / 2` from `fmi`.
#[inline(always)]
fn lane_strain<V: Lanes8>(
    isa: V::Isa,
    seed: bool,
    gq: &GroupRest,
    f: &[V; 9],
    fmi: &[V; 9],
) -> [V; 9] {
    let ld = |a: &[f32; LANES]| V::from_array(isa, *a);
    let half = V::splat(isa, 0.5);
    let mut e = [V::zero(isa); 9];
    for c in 0..3 {
        for d in c..3 {
            let ecd = if seed {
                let mut ctd = f[3 * c].mul(f[3 * d]);
                ctd = V::madd(f[3 * c + 1], f[3 * d + 1], ctd);
                ctd = V::madd(f[3 * c + 2], f[3 * d + 2], ctd);
                let id = if c == d { 1.0 } else { 0.0 };
                ctd.sub(V::splat(isa, id))
                    .mul(half)
                    .sub(ld(&gq.q[3 * d + c]))
            } else {
                let mut ctd = fmi[3 * d + c].add(fmi[3 * c + d]);
                ctd = V::madd(fmi[3 * c], fmi[3 * d], ctd);
                ctd = V::madd(fmi[3 * c + 1], fmi[3 * d + 1], ctd);
                ctd = V::madd(fmi[3 * c + 2], fmi[3 * d + 2], ctd);
                ctd.mul(half)
            };
            e[3 * d + c] = ecd;
            e[3 * c + d] = ecd;
        }
    }
    e
}

/// `V S(E) = V (lambda tr(E) I + 2 mu E)` lane-wise (`v`: the particle volume, m^3).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // one index into two 3x3 lane matrices
fn lane_stvk<V: Lanes8>(isa: V::Isa, mat: &MaterialParams, v: f64, e: &[V; 9]) -> [V; 9] {
    let lv = V::splat(isa, mat.lambda_pa * v);
    let mv = V::splat(isa, 2.0 * mat.mu_pa * v);
    let tr = lv.mul(e[0].add(e[4]).add(e[8]));
    let mut sv = [V::zero(isa); 9];
    for i in 0..9 {
        sv[i] = mv.mul(e[i]);
    }
    for i in [0, 4, 8] {
        sv[i] = sv[i].add(tr);
    }
    sv
}

/// The corrected variant's `N = M A^-T` (`M = V F S(E) + (F - I) Q - Gb + u_i (x) U`, `m`
/// holding `V F S(E)`) and the owner's force `N S - F U + sum_k c_k u_(i+k) - C u_i + U`
/// (`U = 0` on padding lanes), lane-wise; `s3`: `S`.
#[inline(always)]
#[allow(clippy::too_many_arguments)] // the stress's state, split out of one function
#[allow(clippy::needless_range_loop)] // one index into several 3x3 lane matrices
fn corrected_forces<V: Lanes8>(
    isa: V::Isa,
    gq: &GroupRest,
    mut m: [V; 9],
    f: &[V; 9],
    fmi: [V; 9],
    gb: &[V; 9],
    cu: &[V; 3],
    ui: [V; 3],
    own: V,
    s3: [V; 3],
) -> StressOut<V> {
    let zero = V::zero(isa);
    let ld = |a: &[f32; LANES]| V::from_array(isa, *a);
    let h = mat_mul(&fmi, &lane_mat(isa, &gq.q));
    let u3 = [ld(&gq.u[0]), ld(&gq.u[1]), ld(&gq.u[2])];
    for c in 0..3 {
        for r in 0..3 {
            let i = 3 * c + r;
            m[i] = V::madd(ui[r], u3[c], m[i].add(h[i]).sub(gb[i]));
        }
    }
    let a_inv = lane_mat(isa, &gq.a);
    let mut n = [zero; 9];
    // N = M A^-T: N[r][c] = sum_d M[r][d] A^-1[c][d].
    for c in 0..3 {
        for r in 0..3 {
            let mut acc = m[r].mul(a_inv[c]);
            acc = V::madd(m[3 + r], a_inv[3 + c], acc);
            acc = V::madd(m[6 + r], a_inv[6 + c], acc);
            n[3 * c + r] = acc;
        }
    }
    let ns = mat_vec(&n, &s3);
    let fu = mat_vec(f, &u3);
    let cv = ld(&gq.c);
    let mut ov = [zero; 3];
    for r in 0..3 {
        let sdl = V::nmadd(cv, ui[r], cu[r]).add(u3[r]).mul(own);
        ov[r] = ns[r].sub(fu[r]).add(sdl);
    }
    (n, fmi, ov)
}

/// Lanes `l` with `own[l] == 0` set to zero (padding lanes, as [`stress_per_lane`] leaves them).
#[inline(always)]
fn zero_padding<V: Lanes8>(isa: V::Isa, own: &[f32; LANES], v: &mut [V]) {
    for x in v {
        let mut a = x.to_array();
        for (a, &o) in a.iter_mut().zip(own) {
            if o == 0.0 {
                *a = 0.0;
            }
        }
        *x = V::from_array(isa, a);
    }
}

/// The stable Neo-Hookean stress of a group lane-wise (corrected variant): the operations of
/// [`stress_per_lane`] with `first_piola` (`P = mu F + lambda_s (J - alpha) cof F`) in single
/// precision with fused multiply-adds (issue 48: the per-lane loop was about a third of the
/// group loop).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // one index into several 3x3 lane matrices
fn stress_neo_hookean<V: Lanes8>(
    isa: V::Isa,
    st: &Stencil,
    gq: &GroupRest,
    sums: &PassOne<V>,
    ui: [V; 3],
    mat: &MaterialParams,
) -> StressOut<V> {
    let (ga, gb, cu) = sums;
    let ld = |a: &[f32; LANES]| V::from_array(isa, *a);
    let (s3, u3) = (
        [ld(&gq.s[0]), ld(&gq.s[1]), ld(&gq.s[2])],
        [ld(&gq.u[0]), ld(&gq.u[1]), ld(&gq.u[2])],
    );
    let a_inv = lane_mat::<V>(isa, &gq.a);
    let (mut gus, mut a_t) = (*ga, a_inv);
    for c in 0..3 {
        for r in 0..3 {
            // G - u_i (x) S; A^-T.
            gus[3 * c + r] = ga[3 * c + r].sub(ui[r].mul(s3[c]));
            a_t[3 * c + r] = a_inv[3 * r + c];
        }
    }
    let fmi = mat_mul(&gus, &a_inv);
    let mut f = fmi;
    for (i, f) in f.iter_mut().enumerate() {
        *f = f.add(V::splat(isa, if i % 4 == 0 { 1.0 } else { 0.0 }));
    }
    let fq = mat_mul(&fmi, &lane_mat(isa, &gq.q));
    // cof F: columns y x z, z x x, x x y; J = x . (y x z).
    let mut cof = f;
    for (j, [a, b]) in [[1, 2], [2, 0], [0, 1]].into_iter().enumerate() {
        for (r, [p, q]) in [[1, 2], [2, 0], [0, 1]].into_iter().enumerate() {
            let (ap, bq, bp, aq) = (f[3 * a + p], f[3 * b + q], f[3 * b + p], f[3 * a + q]);
            cof[3 * j + r] = V::msub(ap, bq, bp.mul(aq));
        }
    }
    let det = V::madd(f[2], cof[2], V::madd(f[1], cof[1], f[0].mul(cof[0])));
    let ls = mat.lambda_pa + mat.mu_pa;
    let alpha = 1.0 + mat.mu_pa / ls;
    let sj = V::splat(isa, ls).mul(det.sub(V::splat(isa, alpha)));
    let (mu, v) = (V::splat(isa, mat.mu_pa), V::splat(isa, st.volume_m3));
    let mut m = f;
    for c in 0..3 {
        for r in 0..3 {
            let i = 3 * c + r;
            let p = V::madd(cof[i], sj, f[i].mul(mu));
            let h = V::madd(ui[r], u3[c], fq[i].sub(gb[i]));
            m[i] = V::madd(p, v, h);
        }
    }
    let mut n = mat_mul(&m, &a_t);
    let (ns, fu) = (mat_vec(&n, &s3), mat_vec(&f, &u3));
    let cv = ld(&gq.c);
    let mut ov = ns;
    for r in 0..3 {
        let sdl = V::nmadd(ui[r], cv, cu[r]).add(u3[r]);
        ov[r] = ns[r].sub(fu[r]).add(sdl);
    }
    let mut fmi = fmi;
    if gq.own != [1.0; LANES] {
        zero_padding(isa, &gq.own, &mut n);
        zero_padding(isa, &gq.own, &mut fmi);
        zero_padding(isa, &gq.own, &mut ov);
    }
    (n, fmi, ov)
}

/// The stress of a group per lane (laws other than St. Venant-Kirchhoff, corrected variant;
/// the seed branch serves the tests of every law): `F~ = A + G - u_i (x) S`; stress, `N`,
/// `F` (corrected: `F - I`) and the owner's force of each owner lane, zero on padding lanes.
#[inline(always)]
fn stress_per_lane<V: Lanes8>(
    isa: V::Isa,
    st: &Stencil,
    gq: &GroupRest,
    sums: &PassOne<V>,
    ui: [V; 3],
    mat: &MaterialParams,
) -> StressOut<V> {
    let (seed, v) = (st.seed, st.volume_m3);
    let (ga, gb, cu) = sums;
    let gas = lane_matrices(ga);
    let gbs = if seed {
        [[0.0; 9]; LANES]
    } else {
        lane_matrices(gb)
    };
    let uis = [ui[0].to_array(), ui[1].to_array(), ui[2].to_array()];
    let cus = [cu[0].to_array(), cu[1].to_array(), cu[2].to_array()];
    let mut nl = [[0.0f32; LANES]; 9];
    let mut fl = [[0.0f32; LANES]; 9];
    let mut ol = [[0.0f32; LANES]; 3];
    for l in 0..LANES {
        if gq.own[l] == 0.0 {
            continue;
        }
        let lr = gq.lane(l);
        let u_i = DVec3::new(uis[0][l].into(), uis[1][l].into(), uis[2][l].into());
        let g_us = DMat3::from_cols_array(&gas[l]) - outer(u_i, lr.s);
        let (n, f, owner) = if seed {
            let ft = lr.a + g_us;
            let e = green_strain(&ft) - lr.q;
            let n = (ft * stvk_stress(&e, mat.lambda_pa, mat.mu_pa)) * v;
            (n, DMat3::ZERO, n * lr.s)
        } else {
            // F - I = (F~ - A) A^-1.
            let fmi = g_us * lr.a;
            let f = fmi + DMat3::IDENTITY;
            // D = sum_k c_k d_ik (x) X_k = Gb - u_i (x) U + Q; H = F Q - D.
            let h = fmi * lr.q - DMat3::from_cols_array(&gbs[l]) + outer(u_i, lr.u);
            let m = first_piola(mat, &f) * v + h;
            let n = m * lr.a.transpose();
            // sum_k c_k d_ik = sum_k c_k u_(i+k) - C u_i + U.
            let sdl = DVec3::new(cus[0][l].into(), cus[1][l].into(), cus[2][l].into()) - u_i * lr.c
                + lr.u;
            (n, fmi, n * lr.s - f * lr.u + sdl)
        };
        let (na, fa_) = (n.to_cols_array(), f.to_cols_array());
        for e in 0..9 {
            nl[e][l] = na[e] as f32;
            fl[e][l] = fa_[e] as f32;
        }
        for r in 0..3 {
            ol[r][l] = owner[r] as f32;
        }
    }
    let nm = lane_mat::<V>(isa, &nl);
    let fm = lane_mat::<V>(isa, &fl);
    let ov = [
        V::from_array(isa, ol[0]),
        V::from_array(isa, ol[1]),
        V::from_array(isa, ol[2]),
    ];
    (nm, fm, ov)
}

/// Pass 2 of the group at cell `b` from its stress `out` ([`StressOut`]): the cube's written-out
/// loop ([`pass_two_cube`]) or the pair loops ([`pair_grads`], [`pass_two`]; `ah` their
/// scratch).
#[inline(always)]
#[allow(clippy::too_many_arguments)] // the loop's state, split out of one function
fn pass_two_group<V: Lanes8>(
    isa: V::Isa,
    st: &Stencil,
    lay: &StencilLayout,
    (pos, fc): ([&[f32]; 3], &mut [Vec<f32>; 3]),
    b: usize,
    own: V,
    ui: [V; 3],
    out: &StressOut<V>,
    ah: &mut [[V; 3]; MAX_PAIRS],
) {
    let seed = st.seed;
    let [px, py, pz] = pos;
    let (nm, fm, ov) = out;
    let ncl = class_matrices(nm, fm, &st.classes, seed, isa);
    if st.cube {
        let m = cube_columns(isa, &ncl, &st.cube_scale, lay.grid.perm);
        let cko = cube_hourglass(isa, &st.classes, own);
        // c_k u_i per class and component (corrected).
        let mut cui = [[V::zero(isa); 3]; 3];
        if !seed {
            for (cu, ck) in cui.iter_mut().zip(&cko) {
                for r in 0..3 {
                    cu[r] = ck.mul(ui[r]);
                }
            }
        }
        pass_two_cube::<V>(
            isa,
            b,
            &lay.cube_rows,
            &m,
            &cui,
            &cko,
            [px, py, pz],
            fc.each_mut().map(|a| &mut a[..]),
            seed,
            *ov,
        );
    } else {
        pair_grads(isa, &ncl, &st.w, &st.class_of, &lay.pairs, ah);
        pass_two::<V>(
            isa,
            b,
            &lay.rows,
            &st.c,
            &lay.off,
            px,
            py,
            pz,
            fc.each_mut().map(|a| &mut a[..]),
            seed,
            own,
            ui,
            &st.half_of,
            ah,
            *ov,
        );
    }
}

/// `N w_k - F c_k X_k + c_k X_k = (N - beta_k (F - I)) w_k` of each pair `(k, -k)` (one
/// matrix `ncl` per class of length, [`class_matrices`]; odd in `k`: `w_-k = -w_k`, same
/// class) into `ah`, in `pairs` order.
#[inline(always)]
fn pair_grads<V: Lanes8>(
    isa: V::Isa,
    ncl: &[[V; 9]; 3],
    ws: &[[f64; 3]],
    class_of: &[usize],
    pairs: &[(usize, isize)],
    ah: &mut [[V; 3]; MAX_PAIRS],
) {
    for (a, &(k, _)) in ah.iter_mut().zip(pairs) {
        let w = ws[k];
        let (w0, w1, w2) = (
            V::splat(isa, w[0]),
            V::splat(isa, w[1]),
            V::splat(isa, w[2]),
        );
        let nc = &ncl[class_of[k]];
        for r in 0..3 {
            a[r] = V::madd(nc[r], w0, V::madd(nc[3 + r], w1, nc[6 + r].mul(w2)));
        }
    }
}

/// The columns of `scale_c (N - beta_c F)` by grid axis: `m[c][3 a + r]` is row `r` of
/// column `perm[a]` (26-cell cube: `w_k = scale_c e_k` with `e_k` in grid axes, so
/// `(N - beta_c F) w_k` is a signed sum of these columns).
#[inline(always)]
fn cube_columns<V: Lanes8>(
    isa: V::Isa,
    ncl: &[[V; 9]; 3],
    scale: &[f64; 3],
    perm: [usize; 3],
) -> [[V; 9]; 3] {
    let mut m = [[V::zero(isa); 9]; 3];
    for c in 0..3 {
        let sv = V::splat(isa, scale[c]);
        for a in 0..3 {
            for r in 0..3 {
                m[c][3 * a + r] = ncl[c][3 * perm[a] + r].mul(sv);
            }
        }
    }
    m
}

/// `c_k` of each class (faces, edges, corners) on the owner lanes, zero on padding lanes.
#[inline(always)]
fn cube_hourglass<V: Lanes8>(
    isa: V::Isa,
    classes: &[(f64, f64, std::ops::Range<usize>)],
    own: V,
) -> [V; 3] {
    // A loop, not `array::from_fn`: closures do not inherit the caller's target features.
    let mut cko = [V::zero(isa); 3];
    for (c, cl) in cko.iter_mut().zip(classes) {
        *c = V::splat(isa, cl.1).mul(own);
    }
    cko
}

/// The pair of [`CUBE`] holding grid-axis offset `e`, and whether `e` is its negative.
///
/// # Panics
/// If `e` is not an offset of the cube (at compile time where it is used).
const fn cube_pair_of(e: [i32; 3]) -> (usize, bool) {
    let mut j = 0;
    while j < MAX_PAIRS {
        let c = CUBE[j];
        if c[0] == e[0] && c[1] == e[1] && c[2] == e[2] {
            return (j, false);
        }
        if c[0] == -e[0] && c[1] == -e[1] && c[2] == -e[2] {
            return (j, true);
        }
        j += 1;
    }
    panic!("not an offset of the 26-cell cube");
}

/// Row `r` of `sum_a e[a] m[:, a]` for a constant `e` of entries -1, 0, 1 whose first
/// nonzero is 1 (the additions only, once inlined).
#[inline(always)]
fn cube_column_sum<V: Lanes8>(m: &[V; 9], e: [i32; 3], r: usize) -> V {
    let mut acc: Option<V> = None;
    for (a, &ea) in e.iter().enumerate() {
        let col = m[3 * a + r];
        acc = match (ea, acc) {
            (0, acc) => acc,
            (1, None) => Some(col),
            (1, Some(x)) => Some(x.add(col)),
            (_, Some(x)) => Some(x.sub(col)),
            (_, None) => Some(col.neg()),
        };
    }
    acc.expect("a nonzero offset")
}

/// [`pass_two`] for the 26-cell cube: the rows `(a, b)` and `(-a, -b)` together, so that each
/// pair's `(N - beta (F - I)) w_k` is summed once from the class columns `m`
/// ([`cube_columns`]) and serves both its entries (`w_-k = -w_k`); every offset, sign and
/// zero of the stencil is known at compile time. `cko`: `c_k` per class on owner lanes
/// ([`cube_hourglass`]); `cui`: `c_k u_i` per class and component (corrected). Each entry
/// of offset `dx` along the vector axis is subtracted at its row's chunk of eight cells in the
/// forces of that offset (interleaved in `f`, [`super::GridBuffers`]' `fc`): aligned whole-chunk
/// read-modify-writes, no shift across lanes.
#[inline(always)]
#[allow(clippy::too_many_arguments)] // the loop's state, split out of one function
fn pass_two_cube<V: Lanes8>(
    isa: V::Isa,
    b: usize,
    rows: &[isize; 9],
    m: &[[V; 9]; 3],
    cui: &[[V; 3]; 3],
    cko: &[V; 3],
    p: [&[f32]; 3],
    f: [&mut [f32]; 3],
    seed: bool,
    ol: [V; 3],
) {
    // The group's window, checked once for the 80 or so loads and stores below: every row
    // `o = b + rows[_]` has its cells `o - 1 .. o + 1 + LANES` in the positions and its
    // chunk's forces `3 o .. 3 o + 3 LANES` in `f`.
    let (mut rmin, mut rmax) = (0, 0);
    for &ro in rows {
        (rmin, rmax) = (rmin.min(ro), rmax.max(ro));
    }
    let (lo, hi) = (b as isize + rmin, b as isize + rmax);
    let cells = p[0].len().min(p[1].len()).min(p[2].len()) as isize;
    let forces = f[0].len().min(f[1].len()).min(f[2].len()) as isize;
    let w = LANES as isize;
    assert!(
        lo >= 1 && hi + 1 + w <= cells && 3 * hi + 3 * w <= forces,
        "a stencil group's rows outside the grid"
    );
    // `grad` subtracted (`neg`: added) at chunk `o` of the forces of offset `dx`, component
    // `r` (interleaved: at `3 o + LANES (dx + 1)`; a macro, not a closure: closures do not
    // inherit the caller's target features).
    macro_rules! put {
        ($dx:expr, $o:expr, $r:expr, $grad:expr, $neg:expr) => {{
            let (a, i) = (&mut *f[$r], 3 * $o + LANES * ($dx + 1) as usize);
            // SAFETY: `o` is a row of the window checked above, so `i + LANES <= 3 o + 3 LANES`.
            let old = unsafe { V::load_unchecked(isa, a, i) };
            let new = if $neg { old.add($grad) } else { old.sub($grad) };
            // SAFETY: as the load.
            unsafe { new.store_unchecked(a, i) };
        }};
    }
    // The entry `(dx, a, b)` of row one and its negative in row two (owners' chunks `o1` and
    // `o2`, neighbours at `o1 + dx` and `o2 - dx`), component `r`: pair `j`, sign, the
    // hourglass part `c_k (u_(i+k) - u_i)` (corrected; its `c_k X_k` is in `m`).
    macro_rules! entry {
        ($dx:expr, $a:expr, $b:expr, $r:ident, $o1:ident, $o2:ident) => {{
            const JN: (usize, bool) = cube_pair_of([$dx, $a, $b]);
            let (j, neg) = JN;
            let g = cube_column_sum(&m[CUBE_CLASS[j]], CUBE[j], $r);
            if seed {
                put!($dx, $o1, $r, g, neg);
                put!(-$dx, $o2, $r, g, !neg);
            } else {
                // grad_k = (N - beta (F - I)) w_k + c_k u_(i+k) - c_k u_i: the entry `g` or
                // `-g`, its negative the other.
                let (ck, cu) = (cko[CUBE_CLASS[j]], cui[CUBE_CLASS[j]][$r]);
                let (gm, gp) = (g.sub(cu), g.add(cu));
                // SAFETY: `o1`, `o2` are rows of the window checked above and `|dx| <= 1`.
                let (u1, u2) = unsafe {
                    (
                        V::load_unchecked(isa, p[$r], ($o1 as isize + $dx) as usize),
                        V::load_unchecked(isa, p[$r], ($o2 as isize - $dx) as usize),
                    )
                };
                let (d1, d2) = if neg {
                    (V::msub(u1, ck, gp), V::madd(u2, ck, gm))
                } else {
                    (V::madd(u1, ck, gm), V::msub(u2, ck, gp))
                };
                put!($dx, $o1, $r, d1, false);
                put!(-$dx, $o2, $r, d2, false);
            }
        }};
    }
    macro_rules! row_pair {
        ($a:expr, $b:expr) => {{
            let o1 = (b as isize + rows[(($a + 1) + 3 * ($b + 1)) as usize]) as usize;
            let o2 = (b as isize + rows[((1 - $a) + 3 * (1 - $b)) as usize]) as usize;
            for r in 0..3 {
                entry!(-1, $a, $b, r, o1, o2);
                entry!(0, $a, $b, r, o1, o2);
                entry!(1, $a, $b, r, o1, o2);
            }
        }};
    }
    // The centre row: the owner's force and the pair (1, 0, 0) at both ends (its row two is
    // itself).
    for r in 0..3 {
        let o = b;
        put!(0, o, r, ol[r], true);
        entry!(1, 0, 0, r, o, o);
    }
    row_pair!(-1, -1);
    row_pair!(0, -1);
    row_pair!(1, -1);
    row_pair!(-1, 0);
}

/// The force on cell `i` from the cube loop's interleaved forces `fc` (one component):
/// `f0[i] + fm[i + 1] + fp[i - 1]` (summed in double precision), the chunk from cell `c`
/// holding `fm`, `f0`, `fp` at `3 c`, `3 c + LANES`, `3 c + 2 LANES`.
#[inline]
pub(super) fn cube_force_at(fc: &[f32], i: usize) -> f64 {
    let at =
        |j: usize, d: usize| f64::from(fc[3 * (j & !(LANES - 1)) + LANES * d + (j & (LANES - 1))]);
    at(i, 1) + at(i + 1, 0) + at(i - 1, 2)
}

/// Pass 1 for the 26-cell cube: per class (faces, edges, corners) the grid-axis columns
/// `sum_k e_k[a] (u_(i+k) - u_(i-k))` (at `3 a + r`) and (corrected, `!seed`) the sums
/// `sum_k (u_(i+k) + u_(i-k))`, over [`CUBE`]'s pairs at grid offsets `off`.
#[inline(always)]
#[allow(clippy::type_complexity)] // two small per-class arrays
fn pass_one_cube<V: Lanes8>(
    isa: V::Isa,
    b: usize,
    off: &[isize; MAX_PAIRS],
    px: &[f32],
    py: &[f32],
    pz: &[f32],
    seed: bool,
) -> ([[V; 9]; 3], [[V; 3]; 3]) {
    let zero = V::zero(isa);
    let mut g = [[zero; 9]; 3];
    let mut s = [[zero; 3]; 3];
    // The group's window, checked once for the 78 loads below: every pair's cells lie within
    // `reach` of `b`.
    let mut reach = 0;
    for &o in off {
        reach = reach.max(o.unsigned_abs());
    }
    let cells = px.len().min(py.len()).min(pz.len());
    assert!(
        b >= reach && b + reach + LANES <= cells,
        "a stencil group's pairs outside the grid"
    );
    // A macro, not a closure: closures do not inherit the caller's target features.
    macro_rules! ld {
        // SAFETY: `b - reach <= i <= b + reach`, so `i + LANES <= cells` (checked above).
        ($a:expr, $i:expr) => {
            unsafe { V::load_unchecked(isa, $a, $i) }
        };
    }
    macro_rules! pair {
        ($($j:literal),*) => {$(
            let (c, e, o) = (CUBE_CLASS[$j], CUBE[$j], off[$j]);
            let (hi, lo) = ((b as isize + o) as usize, (b as isize - o) as usize);
            let a = [ld!(px, hi), ld!(py, hi), ld!(pz, hi)];
            let m = [ld!(px, lo), ld!(py, lo), ld!(pz, lo)];
            for r in 0..3 {
                let d = a[r].sub(m[r]);
                for (ax, &ea) in e.iter().enumerate() {
                    let x = &mut g[c][3 * ax + r];
                    match ea {
                        0 => {}
                        1 => *x = x.add(d),
                        _ => *x = x.sub(d),
                    }
                }
                if !seed {
                    s[c][r] = s[c][r].add(a[r].add(m[r]));
                }
            }
        )*};
    }
    pair!(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12);
    (g, s)
}

/// Pass 2 of a group (module documentation): `grad_k = N w_k (- F u_k + c_k d_k)`, from
/// `ah` ([`pair_grads`], which holds `c_k X_k`) plus `c_k (u_(i+k) - u_i)` (corrected),
/// subtracted at the neighbour, the owner's force `ol` added at the owner; the three offsets
/// of a row along the vector axis are combined into whole aligned chunks of eight cells first
/// (a store that a later load overlaps only partly stalls the core), written into the forces
/// of offset 0 in `f` (interleaved, [`super::GridBuffers`]' `fc`).
#[inline(always)]
#[allow(clippy::too_many_arguments)] // the loop's state, split out of one function
fn pass_two<V: Lanes8>(
    isa: V::Isa,
    b: usize,
    rows: &[(isize, [usize; 3])],
    cs: &[f64],
    off: &[isize],
    px: &[f32],
    py: &[f32],
    pz: &[f32],
    mut f: [&mut [f32]; 3],
    seed: bool,
    own: V,
    ui: [V; 3],
    half_of: &[(usize, bool)],
    ah: &[[V; 3]; MAX_PAIRS],
    ol: [V; 3],
) {
    let zero = V::zero(isa);
    for &(ro, entries) in rows.iter() {
        let o = (b as isize + ro) as usize;
        let mut centre = if ro == 0 { ol } else { [zero; 3] };
        let mut before = [zero; 3];
        let mut after = [zero; 3];
        for (dx, &k) in entries.iter().enumerate() {
            if k == usize::MAX {
                continue;
            }
            let (j, negative) = half_of[k];
            let mut gr = ah[j];
            if negative {
                gr = [gr[0].neg(), gr[1].neg(), gr[2].neg()];
            }
            if !seed {
                // c_k (u_(i+k) - u_i) for an owner lane (padding lanes: zero); an empty
                // neighbour cell receives a value nobody reads.
                let ck = V::splat(isa, cs[k]).mul(own);
                let o = (b as isize + off[k]) as usize;
                let uj = [
                    V::load(isa, px, o),
                    V::load(isa, py, o),
                    V::load(isa, pz, o),
                ];
                for r in 0..3 {
                    let d = uj[r].sub(ui[r]);
                    gr[r] = V::madd(d, ck, gr[r]);
                }
            }
            for r in 0..3 {
                match dx {
                    0 => {
                        let (c, lo) = gr[r].shift_down();
                        centre[r] = centre[r].sub(c);
                        before[r] = before[r].sub(lo);
                    }
                    1 => centre[r] = centre[r].sub(gr[r]),
                    _ => {
                        let (c, hi) = gr[r].shift_up();
                        centre[r] = centre[r].sub(c);
                        after[r] = after[r].sub(hi);
                    }
                }
            }
        }
        // The chunk from cell `q` (a multiple of LANES) of the forces of offset 0 is at
        // `3 q + LANES` in `f`.
        for (a, (c, (lo, hi))) in f
            .iter_mut()
            .map(|a| &mut **a)
            .zip(centre.iter().zip(before.iter().zip(&after)))
        {
            let (i, chunk) = (3 * o + LANES, 3 * LANES);
            if entries[0] != usize::MAX {
                V::load(isa, a, i - chunk).add(*lo).store(a, i - chunk);
            }
            V::load(isa, a, i).add(*c).store(a, i);
            if entries[2] != usize::MAX {
                V::load(isa, a, i + chunk).add(*hi).store(a, i + chunk);
            }
        }
    }
}
