//! Single-point cells with a variable node count (the ES-FEM smoothing domains of
//! [`crate::element::smoothing`]) in batches of [`LANES`].

use std::ops::Range;

use glam::DVec3;

use super::LANES;
use super::stress::first_piola_lane;
use crate::element::quadrature::IntegrationPoints;
use crate::material::MaterialParams;
use crate::simd::LaneVec;

/// Single-point cells with a variable number of nodes (the smoothing domains of
/// [`StrainSmoothing::Edge`]) in batches of [`LANES`], for the vectorised force kernel. Batch
/// `b` has node slots `start[b]..start[b + 1]`; slot `s` holds, per lane, the node
/// (`nodes[s]`, and `3 *` it in `node3[s]`) and its smoothed gradient (`grad[s][c]`,
/// component c). Cells are sorted by node count so a batch pads few slots; a padding slot
/// repeats the lane's first node with a zero gradient, a padding lane has weight zero.
#[derive(Debug, Clone, Default)]
pub(super) struct DomainBatches {
    start: Vec<usize>,
    nodes: Vec<[u32; LANES]>,
    node3: Vec<[i32; LANES]>,
    grad: Vec<[[f64; LANES]; 3]>,
    weight_m3: Vec<[f64; LANES]>,
}

/// One batch of [`DomainBatches`]: the slots' nodes and gradients (1/m, component c at
/// `[c]`) and the lanes' volumes (m^3).
pub(super) type DomainBatch<'a> = (
    &'a [[u32; LANES]],
    &'a [[[f64; LANES]; 3]],
    &'a [f64; LANES],
);

impl DomainBatches {
    /// Bytes of the arrays.
    pub(super) fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        b(&self.start) + b(&self.nodes) + b(&self.node3) + b(&self.grad) + b(&self.weight_m3)
    }

    /// The batches, in order.
    pub(super) fn batches(&self) -> impl Iterator<Item = DomainBatch<'_>> {
        self.weight_m3.iter().enumerate().map(|(b, w)| {
            let slots = self.start[b]..self.start[b + 1];
            (&self.nodes[slots.clone()], &self.grad[slots], w)
        })
    }

    /// The cells of `points` sorted by node count (ties in cell order), in batches.
    pub(super) fn build(points: &IntegrationPoints) -> Self {
        let cells = points.node_start.len() - 1;
        Self::build_groups(points, &[(0..cells).collect()]).0
    }

    /// The cells of each group of `groups` in turn, each group sorted by node count (ties in
    /// the group's order) and batched apart (no batch mixes groups), and the end batch of each
    /// group.
    pub(super) fn build_groups(
        points: &IntegrationPoints,
        groups: &[Vec<usize>],
    ) -> (Self, Vec<usize>) {
        debug_assert_eq!(
            points.weight_m3.len(),
            points.node_start.len() - 1,
            "one point per cell"
        );
        let count = |c: usize| points.node_start[c + 1] - points.node_start[c];
        let mut out = Self {
            start: vec![0],
            ..Self::default()
        };
        let mut ends = Vec::with_capacity(groups.len());
        for group in groups {
            let mut order = group.clone();
            order.sort_by_key(|&c| count(c));
            for chunk in order.chunks(LANES) {
                out.push_batch(points, chunk);
            }
            ends.push(out.weight_m3.len());
        }
        (out, ends)
    }

    /// Appends the cells `chunk` (at most [`LANES`]) as one batch.
    fn push_batch(&mut self, points: &IntegrationPoints, chunk: &[usize]) {
        let count = |c: usize| points.node_start[c + 1] - points.node_start[c];
        let slots = chunk.iter().map(|&c| count(c)).max().unwrap_or(0);
        let first = self.nodes.len();
        self.nodes.resize(first + slots, [0; LANES]);
        self.node3.resize(first + slots, [0; LANES]);
        self.grad.resize(first + slots, [[0.0; LANES]; 3]);
        let mut w = [0.0; LANES];
        for (l, &c) in chunk.iter().enumerate() {
            let nodes = &points.nodes[points.node_start[c]..points.node_start[c + 1]];
            let grads = &points.grad[points.grad_start[c]..points.grad_start[c + 1]];
            w[l] = points.weight_m3[c];
            // Padding slots: the lane's first node with a zero gradient.
            let padded = nodes
                .iter()
                .copied()
                .zip(grads.iter().copied())
                .chain(std::iter::repeat((nodes[0], DVec3::ZERO)));
            for (s, (node, g)) in padded.take(slots).enumerate() {
                self.nodes[first + s][l] = node;
                self.node3[first + s][l] = 3 * node as i32;
                for c in 0..3 {
                    self.grad[first + s][c][l] = g[c];
                }
            }
        }
        self.weight_m3.push(w);
        self.start.push(self.nodes.len());
    }

    /// The number of batches.
    pub(super) fn len(&self) -> usize {
        self.weight_m3.len()
    }

    /// The nodes of batch `b` (every lane and slot, padding included).
    pub(super) fn batch_nodes(&self, b: usize) -> impl Iterator<Item = usize> + '_ {
        self.nodes[self.start[b]..self.start[b + 1]]
            .iter()
            .flatten()
            .map(|&i| i as usize)
    }
}

/// Internal forces of the batches `range` of single-point cells with variable node counts
/// ([`DomainBatches`]):
/// `F = sum_s (y_s - y_0) G_s^T` (positions, and velocities for the viscous stress) streamed
/// slot by slot, the stress of material `MODEL`, then `f_s -= w P G_s` added lane after lane ([`LaneVec::scatter_add3`]).
///
/// # Safety
/// Node indices below `x.len()`, `v.len()` and `f.len()` (see [`super::Kernels`]).
#[inline(always)]
pub(super) unsafe fn forces_domains<const FMA: bool, const MODEL: u8, V: LaneVec>(
    isa: V::Isa,
    (d, range): (&DomainBatches, Range<usize>),
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    let zero = V::splat(isa, 0.0);
    let fbase = f.as_mut_ptr().cast::<f64>();
    for (b, w) in d
        .weight_m3
        .iter()
        .enumerate()
        .take(range.end)
        .skip(range.start)
    {
        let (node3, grad) = (
            &d.node3[d.start[b]..d.start[b + 1]],
            &d.grad[d.start[b]..d.start[b + 1]],
        );
        // The batch in parts of V::WIDTH lanes (one part for eight-lane vectors).
        for off in (0..LANES).step_by(V::WIDTH) {
            // SAFETY (both): node indices are below x.len() and v.len() (caller's contract).
            let fm = unsafe { domain_gradient::<FMA, V>(isa, node3, grad, off, x) };
            #[allow(clippy::manual_map)]
            let fd = match v {
                Some(v) => Some(unsafe { domain_gradient::<FMA, V>(isa, node3, grad, off, v) }),
                None => None,
            };
            let p = first_piola_lane::<FMA, MODEL, V>(isa, &fm, fd.as_ref(), mat);
            let wn = zero - V::load(isa, &w[off..]);
            let mut m = [zero; 9];
            for (mk, pk) in m.iter_mut().zip(p) {
                *mk = wn * pk;
            }
            for (n3, g) in node3.iter().zip(grad) {
                let g = [
                    V::load(isa, &g[0][off..]),
                    V::load(isa, &g[1][off..]),
                    V::load(isa, &g[2][off..]),
                ];
                // No closure (`from_fn`): closures are not inlined into `target_feature`
                // functions.
                let mut h = [zero; 3];
                for (i, hi) in h.iter_mut().enumerate() {
                    let acc = V::madd::<FMA>(m[3 * i + 1], g[1], m[3 * i] * g[0]);
                    *hi = V::madd::<FMA>(m[3 * i + 2], g[2], acc);
                }
                // SAFETY: node indices are below f.len() (caller's contract), and `f` is
                // borrowed mutably here alone.
                unsafe { V::scatter_add3(h, fbase, &n3[off..]) };
            }
        }
    }
}

/// `sum_s (y_s - y_0) G_s^T` (row-major) of one batch of [`DomainBatches`], lanes
/// `off..off + V::WIDTH`.
///
/// # Safety
/// Node indices below `y.len()` (see [`super::Kernels`]).
#[inline(always)]
unsafe fn domain_gradient<const FMA: bool, V: LaneVec>(
    isa: V::Isa,
    node3: &[[i32; LANES]],
    grad: &[[[f64; LANES]; 3]],
    off: usize,
    y: &[DVec3],
) -> [V; 9] {
    let base = y.as_ptr().cast::<f64>();
    let mut out = [V::splat(isa, 0.0); 9];
    // SAFETY: as in `gather_differences`.
    let y0 = unsafe { V::gather3(isa, base, &node3[0][off..]) };
    for (n3, g) in node3.iter().zip(grad).skip(1) {
        let g = [
            V::load(isa, &g[0][off..]),
            V::load(isa, &g[1][off..]),
            V::load(isa, &g[2][off..]),
        ];
        // SAFETY: as above.
        let ys = unsafe { V::gather3(isa, base, &n3[off..]) };
        for i in 0..3 {
            let di = ys[i] - y0[i];
            for j in 0..3 {
                out[3 * i + j] = V::madd::<FMA>(di, g[j], out[3 * i + j]);
            }
        }
    }
    out
}
