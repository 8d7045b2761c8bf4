//! The edge-smoothed forces through the elements (issue 48 s3): for linear tetrahedra the
//! element gradient `F_e` is constant, so the smoothed gradient of edge `k` is the
//! volume-weighted average `F_k = sum_{e ∋ k} (V_e / 6 V_k) F_e` (the definition of
//! [`crate::element::StrainSmoothing::Edge`]), and its forces fold back to the elements:
//! `f_j = -sum_e (V_e / 6) (sum_{k ⊂ e} P_k) grad N_j^e`. Per evaluation: `F_e` of every
//! tetrahedron (the gathers of the plain kernel), `F_k` by a short weighted sum of rows,
//! `P_k`, `T_e = sum of the six P_k` of a tetrahedron, and the plain kernel's scatter: 4 node
//! gathers and scatters per tetrahedron instead of about 7 per domain.
//!
//! Rows (`F_e`, `P_k`: nine `f64`, row-major) live in [`AverageRows`] (in the caller's
//! `ForceScratch`); batches hold rows in lane order (row `b * LANES + l` is lane l of batch
//! b).

use std::collections::HashMap;

use glam::{DMat3, DVec3};

use super::LANES;
use super::linear::{ElementBatch, edge_gradient, nodal_forces, scatter_linear};
use super::stress::{first_piola_lane, gather_differences};
use crate::material::MaterialParams;
use crate::simd::LaneVec;

/// A 3x3 matrix, row-major.
type Row = [f64; 9];

/// Edges per window of the domain order ([`Averaged::build`]).
const WINDOW: usize = 16 * LANES;

/// The element-average layout of the edge-smoothed forces of linear tetrahedra (module
/// documentation). Invariant (construction): every row index below the row counts
/// ([`Averaged::rows`]).
#[derive(Debug, Clone)]
pub(super) struct Averaged {
    /// The tetrahedra in batches (locality order); tetrahedron row = batch * LANES + lane.
    tets: Vec<ElementBatch>,
    /// Per tetrahedron batch, the domain row of each of its six edges per lane (padding
    /// lanes: row 0; their volume is zero).
    tet_domains: Vec<[[u32; LANES]; 6]>,
    /// Domain batch `d` has ring slots `start[d]..start[d + 1]`.
    start: Vec<usize>,
    /// Per ring slot and lane: the tetrahedron row (padding slots: the lane's first).
    ring: Vec<[u32; LANES]>,
    /// Per ring slot and lane: `V_e / (6 V_k)` (padding: 0).
    share: Vec<[f64; LANES]>,
}

/// The rows of one evaluation of [`Averaged`]: the elements' `F` (and `dF/dt` for the viscous
/// stress) and the domains' `P`. Sized by [`AverageRows::ensure`]; a call with rows too few
/// declines.
#[derive(Debug, Clone, Default)]
pub(crate) struct AverageRows {
    f: Vec<Row>,
    fd: Vec<Row>,
    p: Vec<Row>,
}

impl AverageRows {
    /// Grows the rows to `(tets, domains)` rows (set-up: allocates when they grow).
    pub(super) fn ensure(&mut self, (tets, domains): (usize, usize)) {
        if self.f.len() < tets {
            self.f.resize(tets, [0.0; 9]);
            self.fd.resize(tets, [0.0; 9]);
        }
        if self.p.len() < domains {
            self.p.resize(domains, [0.0; 9]);
        }
    }

    /// Whether the rows serve `(tets, domains)` rows.
    pub(super) fn serves(&self, (tets, domains): (usize, usize)) -> bool {
        self.f.len() >= tets && self.fd.len() >= tets && self.p.len() >= domains
    }
}

impl Averaged {
    /// The layout of the linear tetrahedra `tets` (their `Dm^-1` and volumes) in the element
    /// `order` (a permutation of the tetrahedra).
    pub(super) fn build(
        order: &[u32],
        tets: &[[u32; 4]],
        dm_inv: &[DMat3],
        volume_m3: &[f64],
    ) -> Self {
        let batches = ElementBatch::build(order, tets, dm_inv, volume_m3);
        // Edge ids in order of first appearance along the element order; each edge's ring.
        let mut ids = HashMap::with_capacity(2 * tets.len());
        let mut edge_of = vec![[0usize; 6]; order.len()];
        let mut rings: Vec<Vec<(u32, f64)>> = Vec::new();
        for (row, &e) in order.iter().enumerate() {
            let t = tets[e as usize];
            for (j, [a, b]) in crate::mesh::TET_EDGES.into_iter().enumerate() {
                let key = (t[a].min(t[b]), t[a].max(t[b]));
                let next = ids.len();
                let k = *ids.entry(key).or_insert(next);
                if k == rings.len() {
                    rings.push(Vec::new());
                }
                rings[k].push((row as u32, volume_m3[e as usize] / 6.0));
                edge_of[row][j] = k;
            }
        }
        // Domains in windows of `WINDOW` edges along the element order, each sorted by ring
        // size (ties in edge order), batched: few padding slots, and the rows a batch reads
        // stay near each other (a global sort would scatter them over the mesh).
        let mut sorted: Vec<usize> = (0..rings.len()).collect();
        for w in sorted.chunks_mut(WINDOW) {
            w.sort_by_key(|&k| rings[k].len());
        }
        let mut domain_row = vec![0u32; rings.len()];
        let mut out = Self {
            tets: Vec::new(),
            tet_domains: Vec::new(),
            start: vec![0],
            ring: Vec::new(),
            share: Vec::new(),
        };
        for (q, &k) in sorted.iter().enumerate() {
            domain_row[k] = q as u32;
        }
        for chunk in sorted.chunks(LANES) {
            out.push_domain_batch(chunk.iter().map(|&k| rings[k].as_slice()));
        }
        out.tet_domains = edge_of
            .chunks(LANES)
            .map(|rows| {
                let mut d = [[0u32; LANES]; 6];
                for (l, edges) in rows.iter().enumerate() {
                    for (j, &k) in edges.iter().enumerate() {
                        d[j][l] = domain_row[k];
                    }
                }
                d
            })
            .collect();
        out.tets = batches;
        out
    }

    /// Appends one batch of domains (each a ring of `(tetrahedron row, V_e / 6)`).
    fn push_domain_batch<'a>(&mut self, rings: impl Iterator<Item = &'a [(u32, f64)]> + Clone) {
        let slots = rings.clone().map(|r| r.len()).max().unwrap_or(0);
        let first = self.ring.len();
        self.ring.resize(first + slots, [0; LANES]);
        self.share.resize(first + slots, [0.0; LANES]);
        for (l, r) in rings.enumerate() {
            let vk: f64 = r.iter().map(|(_, w)| w).sum();
            for s in 0..slots {
                let (row, w) = r.get(s).map_or((r[0].0, 0.0), |&(row, w)| (row, w / vk));
                self.ring[first + s][l] = row;
                self.share[first + s][l] = w;
            }
        }
        self.start.push(self.ring.len());
    }

    /// The rows an evaluation needs: `(tetrahedra, domains)`, padding lanes included.
    pub(super) fn rows(&self) -> (usize, usize) {
        (LANES * self.tets.len(), LANES * (self.start.len() - 1))
    }

    /// The node indices of the tetrahedra (padding included).
    pub(super) fn nodes(&self) -> impl Iterator<Item = usize> + '_ {
        self.tets.iter().flat_map(|b| b.lane_nodes(0..LANES))
    }
}

/// Internal forces of the layout `a` (module documentation), added to `f`, with rows `rows`.
///
/// # Safety
/// Node indices below `x.len()` and `v.len()` (see [`super::Kernels`]); `rows` serves
/// [`Averaged::rows`].
#[inline(always)]
pub(super) unsafe fn forces_averaged<const MODEL: u8, V: LaneVec>(
    isa: V::Isa,
    (a, rows): (&Averaged, &mut AverageRows),
    mat: &MaterialParams,
    (x, v): (&[DVec3], Option<&[DVec3]>),
    f: &mut [DVec3],
) {
    debug_assert!(rows.serves(a.rows()));
    for (b, batch) in a.tets.iter().enumerate() {
        for off in (0..LANES).step_by(V::WIDTH) {
            let bm = batch.dm_inv_lanes::<V>(isa, off);
            let at = b * LANES + off;
            // SAFETY (both): node indices below x.len(), v.len() (caller's contract).
            let d = unsafe { gather_differences::<V, 9>(isa, batch.node3(), off, x) };
            put_rows(&edge_gradient::<true, V>(isa, &d, &bm), &mut rows.f[at..]);
            if let Some(v) = v {
                let d = unsafe { gather_differences::<V, 9>(isa, batch.node3(), off, v) };
                put_rows(&edge_gradient::<true, V>(isa, &d, &bm), &mut rows.fd[at..]);
            }
        }
    }
    for d in 0..a.start.len() - 1 {
        let slots = a.start[d]..a.start[d + 1];
        let (ring, share) = (&a.ring[slots.clone()], &a.share[slots]);
        for off in (0..LANES).step_by(V::WIDTH) {
            let fm = average::<V>(isa, (ring, share), off, &rows.f);
            #[allow(clippy::manual_map)]
            let fd = match v {
                Some(_) => Some(average::<V>(isa, (ring, share), off, &rows.fd)),
                None => None,
            };
            let p = first_piola_lane::<true, MODEL, V>(isa, &fm, fd.as_ref(), mat);
            put_rows(&p, &mut rows.p[d * LANES + off..]);
        }
    }
    let sixth = V::splat(isa, -1.0 / 6.0);
    for (batch, domains) in a.tets.iter().zip(&a.tet_domains) {
        let mut h = [[0.0; LANES]; 9];
        for off in (0..LANES).step_by(V::WIDTH) {
            let t = fold::<V>(isa, domains, off, &rows.p);
            let bm = batch.dm_inv_lanes::<V>(isa, off);
            let w = sixth * batch.volume_lanes::<V>(isa, off);
            nodal_forces::<true, V>(&t, &bm, w, off, &mut h);
        }
        scatter_linear(batch, &h, f);
    }
}

/// Lanes `off..off + V::WIDTH` of `m` as rows `out[0..V::WIDTH]`.
#[inline(always)]
fn put_rows<V: LaneVec>(m: &[V; 9], out: &mut [Row]) {
    let mut buf = [[0.0; LANES]; 9];
    for (c, v) in m.iter().enumerate() {
        v.store(&mut buf[c]);
    }
    for (l, row) in out[..V::WIDTH].iter_mut().enumerate() {
        for c in 0..9 {
            row[c] = buf[c][l];
        }
    }
}

/// `sum_s share[s][l] rows[ring[s][l]]` for lanes `off..off + V::WIDTH`, in lanes.
#[inline(always)]
fn average<V: LaneVec>(
    isa: V::Isa,
    (ring, share): (&[[u32; LANES]], &[[f64; LANES]]),
    off: usize,
    rows: &[Row],
) -> [V; 9] {
    let mut buf = [[0.0; LANES]; 9];
    for l in off..off + V::WIDTH {
        let mut acc = [0.0; 9];
        for (r, w) in ring.iter().zip(share) {
            let (row, w) = (&rows[r[l] as usize], w[l]);
            for c in 0..9 {
                acc[c] = w.mul_add(row[c], acc[c]);
            }
        }
        for c in 0..9 {
            buf[c][l] = acc[c];
        }
    }
    load_lanes::<V>(isa, &buf, off)
}

/// `sum_j rows[domains[j][l]]` over the six edges, lanes `off..off + V::WIDTH`, in lanes.
#[inline(always)]
fn fold<V: LaneVec>(isa: V::Isa, domains: &[[u32; LANES]; 6], off: usize, rows: &[Row]) -> [V; 9] {
    let mut buf = [[0.0; LANES]; 9];
    for l in off..off + V::WIDTH {
        let mut acc = [0.0; 9];
        for d in domains {
            let row = &rows[d[l] as usize];
            for c in 0..9 {
                acc[c] += row[c];
            }
        }
        for c in 0..9 {
            buf[c][l] = acc[c];
        }
    }
    load_lanes::<V>(isa, &buf, off)
}

/// Lanes `off..off + V::WIDTH` of the structure-of-arrays `buf` (no closure: closures are not
/// inlined into the `target_feature` kernels).
#[inline(always)]
fn load_lanes<V: LaneVec>(isa: V::Isa, buf: &[[f64; LANES]; 9], off: usize) -> [V; 9] {
    let mut out = [V::splat(isa, 0.0); 9];
    for (o, b) in out.iter_mut().zip(buf) {
        *o = V::load(isa, &b[off..]);
    }
    out
}
