//! The single-precision force kernel of linear St Venant-Kirchhoff and stable Neo-Hookean
//! tetrahedra, standard or edge-smoothed: sixteen cells per AVX-512 register, or eight per
//! AVX2 + FMA register (a batch of sixteen in two halves); no gather instruction and no scalar
//! scatter.
//!
//! The double-precision kernel ([`super::linear`]) spends most of its time moving data, not on
//! the stress: per element it gathers twelve coordinates (masked loads and transposes) and
//! scatters twelve force components one scalar read-modify-write at a time
//! (`docs/benchmarks.md`, "Where the `lv_h1` force evaluation's time goes"). This kernel
//!
//! 1. packs the nodal displacements `u = x - X` (and velocities) once per call into a
//!    single-precision node array, one aligned 32-byte row per node (`u`, 0, `v`, 0), in double
//!    precision before rounding, so the rounding error is relative to the displacement, not to
//!    the position;
//! 2. loads each corner's rows with one 16-byte load per lane and transposes four lanes per
//!    128-bit block with unpacks and shuffles;
//! 3. computes, with `G = Du Dm^-1` the displacement gradient (`F = I + G`, seed 000 eq. 21),
//!    `2E = G + G^T + G^T G` (Green strain without the cancellation of `F^T F - I`), the
//!    second Piola-Kirchhoff stress `S = lambda tr(E) I + 2 mu E` plus the viscous stress of
//!    [`crate::material::viscous_stress`] (eq. 11, `A = F^T F'`), scaled by `-V`,
//!    then `P = F S` and `H = P Dm^-T` (eq. 22), all in registers; for stable Neo-Hookean
//!    (Smith, de Goes, Kim 2018; [`crate::material::MaterialModel::StableNeoHookean`]) the
//!    elastic `P = mu F + lambda_s (J - alpha) cof F` is written in `G` so that every term
//!    vanishes at rest exactly ([`neo_hookean_piola`]) and only the viscous `S` goes through
//!    `F S`;
//! 4. transposes the four corner forces back to one 16-byte row per lane and adds it to a
//!    single-precision nodal force array (four read-modify-writes per element instead of
//!    twelve), which is finally added to the double-precision forces and cleared.
//!
//! The smoothing domains of edge-based strain smoothing ([`super::domains`], 4 to 11 nodes)
//! take the same steps, with `G = sum_s (u_s - u_0) g_s^T` over their node slots and the force
//! `-V P g_s` added to each slot's node.
//!
//! The arithmetic is written once over a lane type ([`F32Lanes`]: `Y8`, eight lanes of AVX2,
//! and `Z16`, sixteen of AVX-512F) and compiled for each inside a `#[target_feature]` entry
//! point; the best the CPU runs is chosen per call ([`SingleIsa::detect`]). Both give the same
//! forces up to the order of the sums over a node's elements.
//!
//! The stress arithmetic is single precision; sums over the elements of a node are single
//! precision too. The rest state gives exactly zero force (`G = 0`); the error against the
//! double-precision kernel is measured by the tests (`docs/accuracy.md`).

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::{_mm_load_ps, _mm_store_ps, _mm256_setzero_ps};

use std::ops::Range;

use glam::{DMat3, DVec3};

use super::domains::DomainBatch;
use crate::simd::{Avx2Fma, Avx512};
#[cfg(target_arch = "x86_64")]
use crate::simd::{F32Lanes, Y8, Z16};

#[cfg(target_arch = "x86_64")]
mod stress;
pub use super::parts::MAX_FORCE_PARTS;
use super::parts::{self, Cut, OwnedForces, PartPlan, Split};
#[cfg(target_arch = "x86_64")]
use stress::{LaneCoefficients, scaled_piola};

/// Lanes of a batch of the single-precision kernel: sixteen `f32` fill an AVX-512 register;
/// the AVX2 build runs a batch as two halves of eight.
const SINGLE_LANES: usize = 16;

// A batch of smoothing domains joins two of the double-precision kernel's batches.
const _: () = assert!(SINGLE_LANES == 2 * super::LANES);

/// Sixteen elements side by side; padding lanes repeat node 0 with zero `Dm^-1` and volume,
/// so they add exactly zero force.
#[derive(Debug, Clone)]
#[repr(C, align(64))]
struct SingleBatch {
    /// `nodes[k][l]`: four times corner k of lane l (the `f32` offset of its force row, and
    /// half that of its packed row: both are then one addressing mode, no shift).
    nodes: [[u32; SINGLE_LANES]; 4],
    /// `dm_inv[3 r + c][l]`: entry (r, c) of `Dm^-1` (1/m).
    dm_inv: [[f32; SINGLE_LANES]; 9],
    /// Rest volume (m^3).
    volume_m3: [f32; SINGLE_LANES],
}

/// One node of the packed input: displacement (m) and velocity (m/s), each padded to four.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(32))]
pub(crate) struct PackedNode([f32; 8]);

/// One node of the single-precision force sums (N), padded to four.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(16))]
pub(crate) struct NodeForce([f32; 4]);

/// The work arrays of the single-precision force kernel, per part of an evaluation
/// ([`ForcePart`]), reused across calls so that a call allocates nothing. Arrays for `n` nodes
/// serve every model of at most `n` nodes (a condensed region's model and its whole body).
#[derive(Debug, Clone, Default)]
pub struct ForceScratch {
    pub(super) parts: Vec<ForcePart>,
}

/// The work arrays of one part of a force evaluation, one row per node (72 bytes a node): the
/// packed displacements and velocities of the nodes the part touches and its single-precision
/// force sums, and the double-precision kernel's force sums (all zero between calls). The
/// items a tick pool's job runs over ([`crate::element::PartRunner`]).
#[derive(Debug, Clone, Default)]
pub struct ForcePart {
    packed: Vec<PackedNode>,
    force: Vec<NodeForce>,
    /// The double-precision kernel's sums (N), `super::Kernels::add_forces_parts`.
    pub(super) sum: Vec<DVec3>,
}

impl ForceScratch {
    /// Work arrays for models of at most `node_count` nodes, one part (the one-core path).
    pub fn new(node_count: usize) -> Self {
        Self::with_parts(node_count, 1)
    }

    /// Work arrays for models of at most `node_count` nodes and evaluations cut into at most
    /// `parts` parts (at least one; more than [`MAX_FORCE_PARTS`] are never used).
    pub fn with_parts(node_count: usize, parts: usize) -> Self {
        let mut s = Self::default();
        s.ensure(node_count, parts);
        s
    }

    /// Grows the arrays to serve `node_count` nodes and `parts` parts (set-up: allocates when
    /// they grow; at most [`MAX_FORCE_PARTS`] parts are kept).
    pub fn ensure(&mut self, node_count: usize, parts: usize) {
        let parts = parts.clamp(1, MAX_FORCE_PARTS);
        let node_count = node_count.max(self.node_count());
        if self.parts.len() < parts {
            self.parts.resize_with(parts, ForcePart::default);
        }
        for p in &mut self.parts {
            p.packed.resize(node_count, PackedNode::default());
            p.force.resize(node_count, NodeForce::default());
            p.sum.resize(node_count, DVec3::ZERO);
        }
    }

    /// The largest node count the arrays serve.
    pub fn node_count(&self) -> usize {
        self.parts.first().map_or(0, |p| p.packed.len())
    }

    /// The most parts the arrays serve (0 for the empty scratch).
    pub fn parts(&self) -> usize {
        self.parts.len()
    }
}

/// Runs the parts of one force evaluation: calls `f(p, &mut parts[p])` once for every `p`
/// (each on one thread, in any order) and returns when all are done. Allocation-free in the
/// tick ([`crate::pool::TickPool::for_each_mut`]).
pub(crate) type RunParts<'a> =
    &'a dyn Fn(&mut [ForcePart], &(dyn Fn(usize, &mut ForcePart) + Sync));

/// One node slot of a batch of sixteen smoothing domains: per lane, four times the node and
/// its smoothed gradient (1/m, component c at `grad[c]`). Padding slots repeat the lane's
/// first node with a zero gradient.
#[derive(Debug, Clone)]
#[repr(C, align(64))]
struct DomainSlot {
    nodes: [u32; SINGLE_LANES],
    grad: [[f32; SINGLE_LANES]; 3],
}

/// The cells of one layout in batches of sixteen.
#[derive(Debug, Clone)]
enum SingleLayout {
    /// Linear tetrahedra.
    Tets(Vec<SingleBatch>),
    /// Single-point smoothing domains (edge-based strain smoothing): batch `b` has slots
    /// `start[b]..start[b + 1]` and rest volumes `volume_m3[b]` (zero on padding lanes).
    Domains {
        start: Vec<usize>,
        slots: Vec<DomainSlot>,
        volume_m3: Vec<[f32; SINGLE_LANES]>,
    },
}

/// The instruction sets the single-precision force kernel is built for
/// ([`crate::element::FemModel::pin_single_precision_isa`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SingleIsa {
    /// Eight lanes per AVX2 register (AVX2 and FMA).
    Avx2,
    /// Sixteen lanes per AVX-512 register (AVX-512F, AVX-512VL, AVX2 and FMA: the
    /// `crate::simd` AVX-512 token).
    Avx512,
}

impl SingleIsa {
    /// The widest instruction set of this CPU that the kernel is built for, or `None`
    /// (without AVX2 and FMA).
    pub fn detect() -> Option<Self> {
        SingleToken::detect().map(SingleToken::isa)
    }

    /// Whether this CPU runs this instruction set (a query; the kernel's proof is the
    /// token, `SingleToken`). Allocation-free (the tick asks).
    pub fn is_available(self) -> bool {
        SingleToken::of(self).is_some()
    }

    /// Every instruction set of this CPU that the kernel is built for (for tests and
    /// benchmarks that compare them).
    pub fn available() -> Vec<Self> {
        [Self::Avx2, Self::Avx512]
            .into_iter()
            .filter(|isa| isa.is_available())
            .collect()
    }
}

/// The proof that this CPU runs the kernel's build for one [`SingleIsa`]: the instruction-set
/// token of [`crate::simd`] that build needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SingleToken {
    /// The AVX2 build (eight lanes).
    Avx2(Avx2Fma),
    /// The AVX-512 build (sixteen lanes).
    Avx512(Avx512),
}

impl SingleToken {
    /// The token of the widest build this CPU runs, or `None` (without AVX2 and FMA).
    pub(crate) fn detect() -> Option<Self> {
        Self::of(SingleIsa::Avx512).or_else(|| Self::of(SingleIsa::Avx2))
    }

    /// The token of the build `isa`, when this CPU runs it.
    pub(crate) fn of(isa: SingleIsa) -> Option<Self> {
        match isa {
            SingleIsa::Avx2 => Avx2Fma::detect().map(Self::Avx2),
            SingleIsa::Avx512 => Avx512::detect().map(Self::Avx512),
        }
    }

    /// The instruction set this token proves.
    pub(crate) fn isa(self) -> SingleIsa {
        match self {
            Self::Avx2(_) => SingleIsa::Avx2,
            Self::Avx512(_) => SingleIsa::Avx512,
        }
    }

    /// The AVX2 and FMA part of the proof (the packing and unpacking run on it).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    fn avx2_fma(self) -> Avx2Fma {
        match self {
            Self::Avx2(t) => t,
            Self::Avx512(t) => t.avx2_fma(),
        }
    }
}

/// The batches of the single-precision kernel of one model of linear tetrahedra (standard
/// or edge-smoothed), with the rest positions the displacements are taken from. Invariant
/// (checked at construction): every node index is below `rest.len()`.
#[derive(Debug, Clone)]
pub(crate) struct SingleLinear {
    layout: SingleLayout,
    rest: Vec<DVec3>,
    /// `cuts[k - 1]`: the evaluation in `k` parts (invariant: their batch ranges cover the
    /// batches, their nodes are below `rest.len()`).
    cuts: Vec<Cut>,
    /// The instruction set of [`Self::add_forces`] (its token): the widest of this CPU unless
    /// pinned.
    isa: Option<SingleToken>,
}

impl SingleLinear {
    /// Bytes of the batches, the rest positions and the cuts.
    pub(crate) fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        let layout = match &self.layout {
            SingleLayout::Tets(batches) => b(batches),
            SingleLayout::Domains {
                start,
                slots,
                volume_m3,
            } => b(start) + b(slots) + b(volume_m3),
        };
        layout
            + b(&self.rest)
            + b(&self.cuts)
            + self.cuts.iter().map(Cut::heap_bytes).sum::<usize>()
    }

    /// The elements of a batch: [`Self::build`]'s order should interleave this many runs
    /// ([`super::locality_order`]).
    pub(crate) const LANES: usize = SINGLE_LANES;

    /// Batches of the elements `tets` (with `Dm^-1`, 1/m, and rest volumes, m^3) in the order
    /// `order` (a permutation of the element indices), over the rest positions `rest` (m).
    ///
    /// # Panics
    /// If a node index is out of range (the caller validated the mesh).
    pub(crate) fn build(
        order: &[u32],
        rest: &[DVec3],
        tets: &[[u32; 4]],
        dm_inv: &[DMat3],
        volume_m3: &[f64],
    ) -> Self {
        assert!(
            tets.iter().flatten().all(|&i| (i as usize) < rest.len()),
            "element node index out of range"
        );
        let batches = order
            .chunks(SINGLE_LANES)
            .map(|chunk| {
                let mut b = SingleBatch {
                    nodes: [[0; SINGLE_LANES]; 4],
                    dm_inv: [[0.0; SINGLE_LANES]; 9],
                    volume_m3: [0.0; SINGLE_LANES],
                };
                for (l, &e) in chunk.iter().enumerate() {
                    let e = e as usize;
                    for (k, &node) in tets[e].iter().enumerate() {
                        // Below 2^30: FemModel::new refuses more than i32::MAX / 3 nodes.
                        b.nodes[k][l] = 4 * node;
                    }
                    for r in 0..3 {
                        for c in 0..3 {
                            b.dm_inv[3 * r + c][l] = dm_inv[e].col(c)[r] as f32;
                        }
                    }
                    b.volume_m3[l] = volume_m3[e] as f32;
                }
                // Padding lanes repeat the first lane's node 0.
                for l in chunk.len()..SINGLE_LANES {
                    for k in 0..4 {
                        b.nodes[k][l] = b.nodes[0][0];
                    }
                }
                b
            })
            .collect::<Vec<SingleBatch>>();
        let work = vec![1; batches.len()];
        let split = (&work[..], SINGLE_LANES, Split::Lanes);
        let cuts = parts::cuts(rest.len(), split, |b, lanes| {
            let nodes = batches[b].nodes;
            lanes.flat_map(move |l| nodes.map(|corner| (corner[l] / 4) as usize))
        });
        Self {
            layout: SingleLayout::Tets(batches),
            rest: rest.to_vec(),
            cuts,
            isa: SingleToken::detect(),
        }
    }

    /// Batches of smoothing domains: `batches` yields, per batch of eight, the slots' nodes
    /// and gradients (1/m) and the lanes' volumes (m^3), as the double-precision kernel
    /// batches them (`super::domains::DomainBatches`, sorted by slot count); two of them make
    /// one batch of sixteen, the shorter padded with its lanes' first nodes and zero
    /// gradients. Over the rest positions `rest` (m).
    ///
    /// # Panics
    /// If a node index is out of range (the caller validated the mesh).
    pub(crate) fn domains<'a>(
        batches: impl Iterator<Item = DomainBatch<'a>>,
        rest: &[DVec3],
    ) -> Self {
        const HALF: usize = super::LANES;
        let batches: Vec<DomainBatch<'a>> = batches.collect();
        let (mut start, mut slots, mut volume) = (vec![0], Vec::new(), Vec::new());
        for pair in batches.chunks(2) {
            let count = pair.iter().map(|b| b.0.len()).max().unwrap_or(0);
            // Lanes of a missing second half repeat the first lane's first node.
            let filler = pair[0].0.first().map_or(0, |n| n[0]);
            for s in 0..count {
                let mut slot = DomainSlot {
                    nodes: [4 * filler; SINGLE_LANES],
                    grad: [[0.0; SINGLE_LANES]; 3],
                };
                for (h, (nodes, grads, _)) in pair.iter().enumerate() {
                    for l in 0..HALF {
                        let (node, g) = match (nodes.get(s), grads.get(s)) {
                            (Some(n), Some(g)) => (n[l], g.map(|c| c[l] as f32)),
                            _ => (nodes[0][l], [0.0; 3]),
                        };
                        assert!(
                            (node as usize) < rest.len(),
                            "domain node index out of range"
                        );
                        // Below 2^30: FemModel::new refuses more than i32::MAX / 3 nodes.
                        slot.nodes[HALF * h + l] = 4 * node;
                        for (c, gc) in g.into_iter().enumerate() {
                            slot.grad[c][HALF * h + l] = gc;
                        }
                    }
                }
                slots.push(slot);
            }
            start.push(slots.len());
            let mut w = [0.0; SINGLE_LANES];
            for (h, (_, _, wh)) in pair.iter().enumerate() {
                for l in 0..HALF {
                    w[HALF * h + l] = wh[l] as f32;
                }
            }
            volume.push(w);
        }
        let work: Vec<usize> = start.windows(2).map(|w| w[1] - w[0]).collect();
        let split = (&work[..], SINGLE_LANES, Split::Batches);
        let cuts = parts::cuts(rest.len(), split, |b, lanes| {
            slots[start[b]..start[b + 1]]
                .iter()
                .flat_map(move |s| s.nodes[lanes.clone()].iter().map(|&i| (i / 4) as usize))
        });
        Self {
            cuts,
            layout: SingleLayout::Domains {
                start,
                slots,
                volume_m3: volume,
            },
            rest: rest.to_vec(),
            isa: SingleToken::detect(),
        }
    }

    /// The nodes the batches touch and, of them, those several of `parts` parts touch (the
    /// cut), for `parts` in `1..=MAX_FORCE_PARTS`.
    pub(crate) fn cut_nodes(&self, parts: usize) -> Option<(usize, usize)> {
        let cut = self.cuts.get(parts.checked_sub(1)?)?;
        let owned: usize = cut.parts.iter().flat_map(|p| &p.own).map(|r| r.len()).sum();
        Some((owned + cut.shared.len(), cut.shared.len()))
    }

    /// Pins the instruction set of [`Self::add_forces`] to `isa`, which this CPU must run.
    ///
    /// # Errors
    /// A message naming the instruction set when this CPU does not run it.
    pub(crate) fn pin_isa(&mut self, isa: SingleIsa) -> Result<(), String> {
        let token = SingleToken::of(isa)
            .ok_or_else(|| format!("this CPU does not run the {isa:?} build"))?;
        self.isa = Some(token);
        Ok(())
    }

    /// Adds the internal forces (N) of the elastic law `elastic`, plus the viscous ones
    /// (`phi_pa_s`, `psi_pa_s`) when `v` (m/s) is given, for positions `x` (m), to `f`, in
    /// single precision, with the widest instruction set of this CPU ([`SingleIsa::detect`])
    /// or the pinned one ([`Self::pin_isa`]). Returns `false` (and does nothing) without AVX2
    /// and FMA.
    ///
    /// # Panics
    /// If `x`, `v`, `f` or `scratch` holds fewer nodes than the model.
    pub(crate) fn add_forces(
        &self,
        elastic: SingleElastic,
        viscosity: (f64, f64),
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) -> bool {
        self.add_forces_parts(elastic, viscosity, (x, v), f, scratch, (1, &serial_parts))
    }

    /// [`Self::add_forces`] cut into `parts` parts (at most `scratch.parts()` and
    /// [`MAX_FORCE_PARTS`]; the arithmetic depends only on that number) that `run` runs:
    /// contiguous batch ranges, each part packing the nodes it touches into its own arrays and
    /// adding the sums of the nodes only it touches to `f`; the nodes several parts touch are
    /// summed afterwards on the calling thread, in part order. One part is the one-core path.
    ///
    /// # Panics
    /// As [`Self::add_forces`].
    pub(crate) fn add_forces_parts(
        &self,
        elastic: SingleElastic,
        viscosity: (f64, f64),
        xv: (&[DVec3], Option<&[DVec3]>),
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
        parts: (usize, RunParts<'_>),
    ) -> bool {
        match self.isa {
            Some(token) => {
                self.add_forces_in(token, (elastic, viscosity), xv, f, scratch, parts);
                true
            }
            None => false,
        }
    }

    /// [`Self::add_forces`] with the build that `token` proves (the tests compare the builds).
    ///
    /// # Panics
    /// As [`Self::add_forces`].
    #[cfg(test)]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn add_forces_on(
        &self,
        token: SingleToken,
        elastic: SingleElastic,
        viscosity: (f64, f64),
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) {
        let law = (elastic, viscosity);
        self.add_forces_in(token, law, (x, v), f, scratch, (1, &serial_parts));
    }

    /// [`Self::add_forces_parts`] with the build that `token` proves.
    ///
    /// # Panics
    /// As [`Self::add_forces`].
    pub(crate) fn add_forces_in(
        &self,
        token: SingleToken,
        (elastic, viscosity): (SingleElastic, (f64, f64)),
        (x, v): (&[DVec3], Option<&[DVec3]>),
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
        (parts, run): (usize, RunParts<'_>),
    ) {
        let n = self.rest.len();
        assert!(x.len() >= n && f.len() >= n && v.is_none_or(|v| v.len() >= n));
        assert!(scratch.node_count() >= n, "force scratch too small");
        let k = parts.clamp(1, scratch.parts().min(MAX_FORCE_PARTS));
        let (cut, items) = (&self.cuts[k - 1], &mut scratch.parts[..k]);
        #[cfg(target_arch = "x86_64")]
        {
            let coef = Coefficients::of(elastic, viscosity);
            let out = OwnedForces {
                ptr: f.as_mut_ptr(),
                len: n,
            };
            run(&mut *items, &|p, part| {
                // SAFETY: the token; `cut` is one of this model's cuts, `x`, `v` and `part`
                // hold n nodes (asserted above); `out` comes from `f` (n nodes), unused
                // until `run` returns, and the parts of a cut own disjoint nodes.
                unsafe { self.part_forces(token, coef, &cut.parts[p], (x, v), part, &out) }
            });
            for &i in &cut.shared {
                let i = i as usize;
                for part in items.iter_mut() {
                    let s = std::mem::take(&mut part.force[i]).0;
                    f[i] += DVec3::new(s[0] as f64, s[1] as f64, s[2] as f64);
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (token, elastic, viscosity, cut, items, run);
    }

    /// One part of [`Self::add_forces_in`]: packs the nodes `plan` touches into `part`, runs
    /// its batches into `part`'s sums, and adds the sums of the nodes it owns to `out` (and
    /// clears them).
    ///
    /// # Safety
    /// The CPU runs `token`'s build; `plan` is a part of one of `self.cuts`; `x`, `v` and
    /// `part`'s arrays hold at least `self.rest.len()` nodes; `out` points to at least that
    /// many nodes that nothing else reads or writes at `plan.own` during the call.
    #[cfg(target_arch = "x86_64")]
    unsafe fn part_forces(
        &self,
        token: SingleToken,
        coef: Coefficients,
        plan: &PartPlan,
        (x, v): (&[DVec3], Option<&[DVec3]>),
        part: &mut ForcePart,
        out: &OwnedForces,
    ) {
        let n = self.rest.len();
        let (packed, force) = (&mut part.packed[..n], &mut part.force[..n]);
        let avx2 = token.avx2_fma();
        let (layout, batches) = (&self.layout, (plan.batches.clone(), plan.lanes.clone()));
        // Half the lanes of a batch run in the eight-lane build (AVX2), whatever the CPU.
        let token = if plan.lanes.len() < SINGLE_LANES {
            SingleToken::Avx2(avx2)
        } else {
            token
        };
        // SAFETY: the caller's contract; the runs and the batches' node indices are below n
        // (construction), so every slice below has one length and every index is in range.
        unsafe {
            for r in plan.touched.iter().cloned() {
                let (rest, p) = (&self.rest[r.clone()], &mut packed[r.clone()]);
                pack_avx2(avx2, &x[r.clone()], Some(rest), p, 0);
                if let Some(v) = v {
                    pack_avx2(avx2, &v[r.clone()], None, &mut packed[r], 4);
                }
            }
            match (token, v.is_some()) {
                (SingleToken::Avx512(t), true) => {
                    forces_avx512::<true>(t, layout, batches, coef, packed, force)
                }
                (SingleToken::Avx512(t), false) => {
                    forces_avx512::<false>(t, layout, batches, coef, packed, force)
                }
                (SingleToken::Avx2(t), true) => {
                    forces_avx2::<true>(t, layout, batches, coef, packed, force)
                }
                (SingleToken::Avx2(t), false) => {
                    forces_avx2::<false>(t, layout, batches, coef, packed, force)
                }
            }
            for r in plan.own.iter().cloned() {
                debug_assert!(r.end <= out.len);
                let f = std::slice::from_raw_parts_mut(out.ptr.add(r.start), r.len());
                unpack_avx2(avx2, &mut force[r], f);
            }
        }
    }
}

/// The one-thread [`RunParts`]: every part on the caller, in order.
fn serial_parts(parts: &mut [ForcePart], f: &(dyn Fn(usize, &mut ForcePart) + Sync)) {
    for (p, part) in parts.iter_mut().enumerate() {
        f(p, part);
    }
}

/// `packed[i][at..at + 4] = a[i] - rest[i]` (or `a[i]`) rounded to single precision, in the
/// first three of the four entries (the fourth is never read).
///
/// # Safety
/// `a`, `rest` and `packed` of one length (the token proves AVX2).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn pack_avx2(
    _isa: Avx2Fma,
    a: &[DVec3],
    rest: Option<&[DVec3]>,
    packed: &mut [PackedNode],
    at: usize,
) {
    use std::arch::x86_64::{
        _mm_alignr_epi8, _mm_castps_si128, _mm_castsi128_ps, _mm_setzero_ps, _mm256_cvtpd_ps,
        _mm256_loadu_pd, _mm256_sub_pd,
    };
    let n = packed.len();
    let chunks = n / 4;
    // SAFETY: the caller's contract: 12 f64 from 12 c are inside `a` and `rest` for c below
    // n / 4 (a DVec3 is three packed f64, asserted in the parent module), and the rows of
    // `packed` are 16-byte aligned at entries 0 and 4.
    unsafe {
        let ap = a.as_ptr().cast::<f64>();
        let rp = rest.map(|r| r.as_ptr().cast::<f64>());
        let out = packed.as_mut_ptr().cast::<f32>();
        for c in 0..chunks {
            // f0 = x0 y0 z0 x1, f1 = y1 z1 x2 y2, f2 = z2 x3 y3 z3 (no closure: it would not
            // inherit the target feature).
            let mut f = [_mm_castps_si128(_mm_setzero_ps()); 3];
            for (k, fk) in f.iter_mut().enumerate() {
                let mut d = _mm256_loadu_pd(ap.add(12 * c + 4 * k));
                if let Some(rp) = rp {
                    d = _mm256_sub_pd(d, _mm256_loadu_pd(rp.add(12 * c + 4 * k)));
                }
                *fk = _mm_castps_si128(_mm256_cvtpd_ps(d));
            }
            let [f0, f1, f2] = f;
            let rows = [
                f0,
                _mm_alignr_epi8::<12>(f1, f0),
                _mm_alignr_epi8::<8>(f2, f1),
                _mm_alignr_epi8::<4>(f2, f2),
            ];
            for (k, r) in rows.into_iter().enumerate() {
                _mm_store_ps(out.add(8 * (4 * c + k) + at), _mm_castsi128_ps(r));
            }
        }
    }
    for i in 4 * chunks..n {
        let u = rest.map_or(a[i], |r| a[i] - r[i]);
        packed[i].0[at..at + 3].copy_from_slice(&[u.x as f32, u.y as f32, u.z as f32]);
    }
}

/// `f[i] += force[i]` (in double precision) and `force[i] = 0`.
///
/// # Safety
/// `force` and `f` of one length (the token proves AVX2).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn unpack_avx2(_isa: Avx2Fma, force: &mut [NodeForce], f: &mut [DVec3]) {
    use std::arch::x86_64::{
        _mm_blend_ps, _mm_shuffle_ps, _mm256_add_pd, _mm256_cvtps_pd, _mm256_loadu_pd,
        _mm256_storeu_pd, _mm256_storeu_ps,
    };
    let n = force.len();
    let chunks = n / 4;
    // SAFETY: the caller's contract: four 16-byte aligned rows from 4 c, and 12 f64 from
    // 12 c inside `f`, for c below n / 4.
    unsafe {
        let src = force.as_mut_ptr().cast::<f32>();
        let dst = f.as_mut_ptr().cast::<f64>();
        for c in 0..chunks {
            let r = [
                _mm_load_ps(src.add(16 * c)),
                _mm_load_ps(src.add(16 * c + 4)),
                _mm_load_ps(src.add(16 * c + 8)),
                _mm_load_ps(src.add(16 * c + 12)),
            ];
            // x0 y0 z0 x1, y1 z1 x2 y2, z2 x3 y3 z3.
            let t = _mm_shuffle_ps::<0b10_10_00_00>(r[3], r[2]); // x3 x3 z2 z2
            let a = [
                _mm_blend_ps::<0b1000>(r[0], _mm_shuffle_ps::<0>(r[1], r[1])),
                _mm_shuffle_ps::<0b01_00_10_01>(r[1], r[2]),
                _mm_shuffle_ps::<0b10_01_00_10>(t, r[3]),
            ];
            for (k, a) in a.into_iter().enumerate() {
                let p = dst.add(12 * c + 4 * k);
                _mm256_storeu_pd(p, _mm256_add_pd(_mm256_loadu_pd(p), _mm256_cvtps_pd(a)));
            }
            _mm256_storeu_ps(src.add(16 * c), _mm256_setzero_ps());
            _mm256_storeu_ps(src.add(16 * c + 8), _mm256_setzero_ps());
        }
    }
    for i in 4 * chunks..n {
        let s = force[i].0;
        f[i] += DVec3::new(s[0] as f64, s[1] as f64, s[2] as f64);
        force[i] = NodeForce::default();
    }
}

/// The elastic law of the single-precision kernel and its Lamé constants (Pa).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum SingleElastic {
    /// St Venant-Kirchhoff, `S = lambda tr(E) I + 2 mu E` (seed 000 eq. 9).
    StVenantKirchhoff {
        /// Lamé lambda, Pa.
        lambda_pa: f64,
        /// Shear modulus mu, Pa.
        mu_pa: f64,
    },
    /// Stable Neo-Hookean, `P = mu F + lambda_s (J - alpha) cof F`
    /// ([`crate::material::MaterialModel::StableNeoHookean`]).
    StableNeoHookean {
        /// Lamé lambda, Pa.
        lambda_pa: f64,
        /// Shear modulus mu, Pa.
        mu_pa: f64,
    },
}

impl SingleElastic {
    /// The law of `mat`, or `None` for a material the kernel does not cover (corotational,
    /// Guccione, a mean-dilatation volumetric term).
    pub(crate) fn of(mat: &crate::material::MaterialParams) -> Option<Self> {
        use crate::material::MaterialModel;
        let (lambda_pa, mu_pa) = (mat.lambda_pa, mat.mu_pa);
        match mat.model {
            _ if mat.mean_dilatation() => None,
            MaterialModel::StVenantKirchhoff => Some(Self::StVenantKirchhoff { lambda_pa, mu_pa }),
            MaterialModel::StableNeoHookean => Some(Self::StableNeoHookean { lambda_pa, mu_pa }),
            _ => None,
        }
    }
}

/// The material constants of the kernel, single precision.
#[derive(Clone, Copy)]
struct Coefficients {
    /// Stable Neo-Hookean (`lambda_s`, `mu` used) instead of StVK (`half_lambda`, `mu`).
    neo_hookean: bool,
    half_lambda: f32,
    /// `lambda_s = lambda + mu` of stable Neo-Hookean.
    lambda_s: f32,
    mu: f32,
    /// Multiplies `tr(A + A^T)` ([`crate::material::viscous_stress`]).
    phi: f32,
    /// Multiplies `A + A^T`.
    two_psi: f32,
}

impl Coefficients {
    /// The constants of `elastic` and the viscosities `(phi, psi)` (Pa s).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    fn of(elastic: SingleElastic, viscosity: (f64, f64)) -> Self {
        let (neo_hookean, lambda_pa, mu_pa) = match elastic {
            SingleElastic::StVenantKirchhoff { lambda_pa, mu_pa } => (false, lambda_pa, mu_pa),
            SingleElastic::StableNeoHookean { lambda_pa, mu_pa } => (true, lambda_pa, mu_pa),
        };
        Self {
            neo_hookean,
            half_lambda: (0.5 * lambda_pa) as f32,
            lambda_s: crate::material::neo_hookean_params(lambda_pa, mu_pa).0 as f32,
            mu: mu_pa as f32,
            phi: viscosity.0 as f32,
            two_psi: (2.0 * viscosity.1) as f32,
        }
    }
}

/// `a0 b0 + a1 b1 + a2 b2`.
///
/// # Safety
/// [`F32Lanes`]' contract.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn dot3<V: F32Lanes>(a: [V; 3], b: [V; 3]) -> V {
    // SAFETY: the caller's contract.
    unsafe { V::fma(a[2], b[2], V::fma(a[1], b[1], a[0].mul(b[0]))) }
}

/// Corner rows of `V::WIDTH` lanes: `[ux, uy, uz]` (and `[vx, vy, vz]` when `VISCOUS`);
/// `nodes[l]` is four times the node of lane l.
///
/// # Safety
/// [`F32Lanes`]' contract; every node below `packed.len()`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn load_corner<V: F32Lanes, const VISCOUS: bool>(
    packed: &[PackedNode],
    nodes: &[u32],
) -> ([V; 3], [V; 3]) {
    // SAFETY: the caller's contract.
    unsafe {
        let base = packed.as_ptr().cast::<f32>();
        let u = V::load_rows(base, nodes, 0);
        let v = if VISCOUS {
            V::load_rows(base, nodes, 4)
        } else {
            [V::zero(); 3]
        };
        (u, v)
    }
}

/// `m[3 i + j] = sum_k d[3 k + i] Bm_kj`: the gradient of the edge differences `d`
/// (component i of edge k at `d[3 k + i]`) through `Dm^-1` of batch `b`, lanes from `half`,
/// eq. 21.
///
/// # Safety
/// [`F32Lanes`]' contract; `half + V::WIDTH <= SINGLE_LANES`, `half` a multiple of `V::WIDTH`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn edge_gradient<V: F32Lanes>(d: &[V; 9], b: &SingleBatch, half: usize) -> [V; 9] {
    // SAFETY: the caller's contract.
    unsafe {
        let mut m = [V::zero(); 9];
        for j in 0..3 {
            let col = [bm(b, j, half), bm(b, 3 + j, half), bm(b, 6 + j, half)];
            for i in 0..3 {
                m[3 * i + j] = dot3([d[i], d[3 + i], d[6 + i]], col);
            }
        }
        m
    }
}

/// Entry `r = 3 row + column` of `Dm^-1` for the lanes of batch `b` from `half`, read from
/// memory at each use (volatile, so that the compiler neither keeps nine of them in registers
/// nor spills them to the stack: they are in L1 already).
///
/// # Safety
/// [`F32Lanes`]' contract; `half + V::WIDTH <= SINGLE_LANES`, `half` a multiple of `V::WIDTH`
/// (then the lanes are aligned: the batch is 64-byte aligned, its rows 64 bytes long).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn bm<V: F32Lanes>(b: &SingleBatch, r: usize, half: usize) -> V {
    let lanes = &b.dm_inv[r][half..half + V::WIDTH];
    // SAFETY: the caller's contract; `lanes` is V::WIDTH aligned f32.
    unsafe { V::load_volatile(lanes.as_ptr()) }
}

/// The kernel over every batch of tetrahedra (module documentation), `V::WIDTH` lanes at a
/// time.
///
/// # Safety
/// [`F32Lanes`]' contract; `lanes` within `0..SINGLE_LANES`, its ends multiples of `V::WIDTH`;
/// every node index of `batches` below `packed.len()` and
/// `force.len()`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn tet_forces<V: F32Lanes, const VISCOUS: bool>(
    (batches, lanes): (&[SingleBatch], Range<usize>),
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    // SAFETY: the caller's contract (batch rows are aligned: the struct is 64-byte aligned).
    unsafe {
        let k = LaneCoefficients::<V>::new(c);
        let zero = V::zero();
        let fbase = force.as_mut_ptr().cast::<f32>();
        for b in batches {
            for half in lanes.clone().step_by(V::WIDTH) {
                let nodes = |k: usize| &b.nodes[k][half..half + V::WIDTH];
                let (u0, v0) = load_corner::<V, VISCOUS>(packed, nodes(0));
                // Edge differences: component i of edge k (corner k+1 minus corner 0) at 3 k + i.
                let mut du = [zero; 9];
                let mut dv = [zero; 9];
                for k in 0..3 {
                    let (uk, vk) = load_corner::<V, VISCOUS>(packed, nodes(k + 1));
                    for i in 0..3 {
                        du[3 * k + i] = uk[i].sub(u0[i]);
                        if VISCOUS {
                            dv[3 * k + i] = vk[i].sub(v0[i]);
                        }
                    }
                }
                let g = edge_gradient(&du, b, half);
                let gd = if VISCOUS {
                    edge_gradient(&dv, b, half)
                } else {
                    [zero; 9]
                };
                let volume = V::load(b.volume_m3[half..half + V::WIDTH].as_ptr());
                let p = scaled_piola::<V, VISCOUS>(&g, &gd, volume, &k);
                // H_k (force on corner k+1), component i = sum_j P_ij Bm_kj; corner 0 gets
                // minus their sum.
                let mut h0 = [zero; 3];
                for k in 0..3 {
                    let row = [
                        bm(b, 3 * k, half),
                        bm(b, 3 * k + 1, half),
                        bm(b, 3 * k + 2, half),
                    ];
                    let mut hk = [zero; 3];
                    for i in 0..3 {
                        hk[i] = dot3([p[3 * i], p[3 * i + 1], p[3 * i + 2]], row);
                        h0[i] = h0[i].sub(hk[i]);
                    }
                    V::add_rows(fbase, nodes(k + 1), hk);
                }
                V::add_rows(fbase, nodes(0), h0);
            }
        }
    }
}

/// The kernel over batches of smoothing domains (`start`, `slots`, `volume_m3` of
/// [`SingleLayout::Domains`]), `V::WIDTH` lanes at a time: `G = sum_s (u_s - u_0) g_s^T` over
/// the slots (velocities too when `VISCOUS`), [`scaled_piola`], then `-V P g_s` added to each
/// slot's node.
///
/// # Safety
/// [`F32Lanes`]' contract; `lanes` as in [`tet_forces`]; every node of the slots below
/// `packed.len()` and `force.len()`;
/// `start` has one more entry than `volume_m3`, ascending within `slots.len()`, at least one
/// slot a batch.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn domain_forces<V: F32Lanes, const VISCOUS: bool>(
    (start, slots, volume_m3): (&[usize], &[DomainSlot], &[[f32; SINGLE_LANES]]),
    lanes: Range<usize>,
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    // SAFETY: the caller's contract (slots are 64-byte aligned, their rows 64 bytes long).
    unsafe {
        let k = LaneCoefficients::<V>::new(c);
        let zero = V::zero();
        let fbase = force.as_mut_ptr().cast::<f32>();
        for (b, volume) in volume_m3.iter().enumerate() {
            let batch = &slots[start[b]..start[b + 1]];
            for half in lanes.clone().step_by(V::WIDTH) {
                let lanes = half..half + V::WIDTH;
                let grad = |slot: &DomainSlot| {
                    [
                        V::load(slot.grad[0][lanes.clone()].as_ptr()),
                        V::load(slot.grad[1][lanes.clone()].as_ptr()),
                        V::load(slot.grad[2][lanes.clone()].as_ptr()),
                    ]
                };
                let (u0, v0) = load_corner::<V, VISCOUS>(packed, &batch[0].nodes[lanes.clone()]);
                let mut g = [zero; 9];
                let mut gd = [zero; 9];
                for slot in &batch[1..] {
                    let (us, vs) = load_corner::<V, VISCOUS>(packed, &slot.nodes[lanes.clone()]);
                    let gr = grad(slot);
                    for i in 0..3 {
                        let du = us[i].sub(u0[i]);
                        let dv = vs[i].sub(v0[i]);
                        for j in 0..3 {
                            g[3 * i + j] = V::fma(du, gr[j], g[3 * i + j]);
                            if VISCOUS {
                                gd[3 * i + j] = V::fma(dv, gr[j], gd[3 * i + j]);
                            }
                        }
                    }
                }
                let volume = V::loadu(volume[lanes.clone()].as_ptr());
                let p = scaled_piola::<V, VISCOUS>(&g, &gd, volume, &k);
                for slot in batch {
                    let gr = grad(slot);
                    let mut h = [zero; 3];
                    for (i, hi) in h.iter_mut().enumerate() {
                        *hi = dot3([p[3 * i], p[3 * i + 1], p[3 * i + 2]], gr);
                    }
                    V::add_rows(fbase, &slot.nodes[lanes.clone()], h);
                }
            }
        }
    }
}

/// The kernel of the batches `batches` of `layout` with lane type `V`.
///
/// # Safety
/// As [`tet_forces`] and [`domain_forces`]; `batches` within the layout's batches; `lanes`
/// within `0..SINGLE_LANES`, its ends multiples of `V::WIDTH`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn layout_forces<V: F32Lanes, const VISCOUS: bool>(
    layout: &SingleLayout,
    (batches, lanes): (Range<usize>, Range<usize>),
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    // SAFETY: the caller's contract.
    unsafe {
        match layout {
            SingleLayout::Tets(b) => {
                tet_forces::<V, VISCOUS>((&b[batches], lanes), c, packed, force)
            }
            SingleLayout::Domains {
                start,
                slots,
                volume_m3,
            } => {
                let start = &start[batches.start..=batches.end];
                let volume_m3 = &volume_m3[batches];
                let batches = (start, &slots[..], volume_m3);
                domain_forces::<V, VISCOUS>(batches, lanes, c, packed, force)
            }
        }
    }
}

/// [`layout_forces`] in AVX2 registers, eight lanes.
///
/// # Safety
/// `batches` (batch range, lanes) as [`layout_forces`]; every node index of the layout below `packed.len()`
/// and `force.len()` (the token proves AVX2 and FMA).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forces_avx2<const VISCOUS: bool>(
    _isa: Avx2Fma,
    layout: &SingleLayout,
    batches: (Range<usize>, Range<usize>),
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    // SAFETY: the caller's contract; this function is compiled with AVX2 and FMA.
    unsafe { layout_forces::<Y8, VISCOUS>(layout, batches, c, packed, force) }
}

/// [`layout_forces`] in AVX-512 registers, sixteen lanes.
///
/// # Safety
/// `batches` (batch range, lanes) as [`layout_forces`]; every node index of the layout below `packed.len()`
/// and `force.len()` (the token proves AVX-512F, AVX-512VL, AVX2 and FMA; the build enables
/// only the F part it uses, as before).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn forces_avx512<const VISCOUS: bool>(
    _isa: Avx512,
    layout: &SingleLayout,
    batches: (Range<usize>, Range<usize>),
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    // SAFETY: the caller's contract; this function is compiled with AVX-512F.
    unsafe { layout_forces::<Z16, VISCOUS>(layout, batches, c, packed, force) }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vectorised packing and unpacking (four nodes at a time) and their scalar tails,
    /// for every remainder: `packed` holds `a - rest` rounded, `f` gains the sums and the sums
    /// are cleared.
    #[test]
    fn packing_and_unpacking_cover_every_tail() {
        let Some(isa) = Avx2Fma::detect() else {
            eprintln!("no AVX2: nothing to test");
            return;
        };
        for n in 0..11 {
            let a: Vec<DVec3> = (0..n)
                .map(|i| DVec3::new(0.1 + i as f64, -0.2 * i as f64, 1e-3 * (i * i) as f64))
                .collect();
            let rest: Vec<DVec3> = (0..n).map(|i| DVec3::splat(0.01 * i as f64)).collect();
            let mut packed = vec![PackedNode::default(); n];
            // SAFETY: the token; slices of one length.
            unsafe {
                pack_avx2(isa, &a, Some(&rest), &mut packed, 0);
                pack_avx2(isa, &a, None, &mut packed, 4);
            }
            for i in 0..n {
                let u = a[i] - rest[i];
                assert_eq!(
                    packed[i].0[..3],
                    [u.x as f32, u.y as f32, u.z as f32],
                    "{n} {i}"
                );
                let w = a[i];
                assert_eq!(
                    packed[i].0[4..7],
                    [w.x as f32, w.y as f32, w.z as f32],
                    "{n} {i}"
                );
            }
            let mut force: Vec<NodeForce> = (0..n)
                .map(|i| NodeForce([i as f32, 2.0 * i as f32, -(i as f32), 0.0]))
                .collect();
            let mut f = a.clone();
            // SAFETY: as above.
            unsafe { unpack_avx2(isa, &mut force, &mut f) };
            for i in 0..n {
                let k = i as f64;
                assert_eq!(f[i], a[i] + DVec3::new(k, 2.0 * k, -k), "{n} {i}");
                assert_eq!(force[i].0, [0.0; 4]);
            }
        }
    }
}
