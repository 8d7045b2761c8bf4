//! Linear tetrahedra in batches of [`LANES`]: gathers of the edge vectors, `F = Ds Dm^-1`
//! (seed 000 eq. 21), the stress and `H = -V P Dm^-T` (eq. 22) in registers, then the nodal
//! forces added lane after lane.

use std::ops::Range;

use glam::{DMat3, DVec3};

use super::LANES;
use super::stress::{dot3, first_piola_lane, gather_differences};
use crate::material::MaterialParams;
use crate::simd::LaneVec;

/// [`LANES`] elements, structure-of-arrays: `dm_inv[3 r + c][lane]` is entry (r, c) of
/// `Dm^-1`. Padding lanes (at the end of the mesh) repeat node 0 with zero `Dm^-1` and volume,
/// so they add exactly zero force.
#[derive(Debug, Clone)]
pub(super) struct ElementBatch {
    nodes: [[u32; 4]; LANES],
    /// `3 * nodes[l][k]` at `node3[k][l]`: f64 offsets of the node coordinates, for gathers.
    node3: [[i32; LANES]; 4],
    dm_inv: [[f64; LANES]; 9],
    volume_m3: [f64; LANES],
}

impl ElementBatch {
    /// Batches of the elements in the given `order` (a permutation of the element indices).
    pub(super) fn build(
        order: &[u32],
        tets: &[[u32; 4]],
        dm_inv: &[DMat3],
        volume_m3: &[f64],
    ) -> Vec<Self> {
        order
            .chunks(LANES)
            .map(|chunk| {
                let mut b = Self {
                    nodes: [[0; 4]; LANES],
                    node3: [[0; LANES]; 4],
                    dm_inv: [[0.0; LANES]; 9],
                    volume_m3: [0.0; LANES],
                };
                for (l, &e) in chunk.iter().enumerate() {
                    let e = e as usize;
                    b.nodes[l] = tets[e];
                    for (row, &node) in b.node3.iter_mut().zip(&tets[e]) {
                        row[l] = 3 * node as i32;
                    }
                    let m = dm_inv[e];
                    for r in 0..3 {
                        for c in 0..3 {
                            b.dm_inv[3 * r + c][l] = m.col(c)[r];
                        }
                    }
                    b.volume_m3[l] = volume_m3[e];
                }
                b
            })
            .collect()
    }
}

/// StVK or stable Neo-Hookean (+ viscous) nodal forces of every batch of linear elements,
/// added to `f` (see [`crate::element::FemModel::add_internal_forces`]), with every batch
/// quantity held in
/// lane type `V` (one lane per element): gathers of the edge vectors, `F = Ds Dm^-1` (seed 000
/// eq. 21), the stress by [`first_piola_lane`] and `H = -V P Dm^-T` (eq. 22) without leaving
/// registers, then [`LaneVec::scatter_add3`] (lane after lane, since lanes may share nodes).
///
/// # Safety
/// Every node index of `batches` must be below `x.len()`, `v.len()` and `f.len()` (see
/// [`super::Kernels`]).
#[inline(always)]
pub(super) unsafe fn forces_linear<const FMA: bool, const MODEL: u8, V: LaneVec>(
    isa: V::Isa,
    batches: &[ElementBatch],
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
            let mut bm = [zero; 9];
            for (b, row) in bm.iter_mut().zip(&batch.dm_inv) {
                *b = V::load(isa, &row[off..]);
            }
            // SAFETY: node indices are below x.len() (caller's contract).
            let fm = edge_gradient::<FMA, V>(
                isa,
                &unsafe { gather_differences::<V, 9>(isa, &batch.node3, off, x) },
                &bm,
            );
            // No closure (`v.map`): closures are not inlined into `target_feature` functions.
            #[allow(clippy::manual_map)]
            let fd = match v {
                // SAFETY: node indices are below v.len() (caller's contract).
                Some(v) => Some(edge_gradient::<FMA, V>(
                    isa,
                    &unsafe { gather_differences::<V, 9>(isa, &batch.node3, off, v) },
                    &bm,
                )),
                None => None,
            };
            let p = first_piola_lane::<FMA, MODEL, V>(isa, &fm, fd.as_ref(), mat);
            let w = zero - V::load(isa, &batch.volume_m3[off..]);
            // Node k + 1 gets column k of H = -V P Dm^-T, node 0 minus their sum.
            let mut h0 = [zero; 3];
            for k in 0..3 {
                // No closure (`from_fn`): closures are not inlined into `target_feature`
                // functions.
                let mut hk = [zero; 3];
                for (i, h) in hk.iter_mut().enumerate() {
                    *h = w * dot3::<FMA, V>(
                        [p[3 * i], p[3 * i + 1], p[3 * i + 2]],
                        [bm[3 * k], bm[3 * k + 1], bm[3 * k + 2]],
                    );
                }
                for (a, b) in h0.iter_mut().zip(hk) {
                    *a = *a - b;
                }
                // SAFETY: node indices are below f.len() (caller's contract), and `f` is
                // borrowed mutably here alone.
                unsafe { V::scatter_add3(hk, fbase, &batch.node3[k + 1][off..]) };
            }
            // SAFETY: as above.
            unsafe { V::scatter_add3(h0, fbase, &batch.node3[0][off..]) };
        }
    }
}

impl ElementBatch {
    /// The nodes of lanes `lanes` (padding included).
    pub(super) fn lane_nodes(&self, lanes: Range<usize>) -> impl Iterator<Item = usize> + '_ {
        self.nodes[lanes].iter().flatten().map(|&i| i as usize)
    }
}

/// `F = Ds Dm^-1`: `d` from [`gather_differences`], `bm[3 r + c]` entry (r, c) of `Dm^-1`;
/// `F_ij = sum_k d[3 k + i] bm[3 k + j]`, row-major (seed 000 eq. 21).
#[inline(always)]
fn edge_gradient<const FMA: bool, V: LaneVec>(isa: V::Isa, d: &[V; 9], bm: &[V; 9]) -> [V; 9] {
    let mut out = [V::splat(isa, 0.0); 9];
    for i in 0..3 {
        for j in 0..3 {
            out[3 * i + j] =
                dot3::<FMA, V>([d[i], d[3 + i], d[6 + i]], [bm[j], bm[3 + j], bm[6 + j]]);
        }
    }
    out
}
