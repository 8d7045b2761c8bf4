//! The vectorised force kernels: internal forces of linear, quadratic and edge-smoothed
//! elements in batches of [`LANES`] elements side by side, and the backward Euler operator
//! action of quadratic StVK elements, each compiled for AVX-512, AVX2 + FMA and plain code and
//! chosen at run time.
//!
//! Owns: the batch layouts ([`linear`], [`quadratic`], [`domains`]), the per-lane
//! stress formulas ([`stress`]; the lane types are [`crate::simd`]'s) and every `unsafe` block of
//! the element code. May use:
//! [`crate::material`] (parameters; the stress formulas are repeated per lane in [`stress`] and
//! checked against [`crate::material::first_piola`] by the tests below) and the integration
//! points of [`super::quadrature`].
//!
//! **Soundness.** The kernels gather node coordinates through raw pointers. [`Kernels`] is the
//! only way to run them: it checks at construction that every node index of its batches is below
//! its `node_count`, keeps its batches private, and checks before each call that the slices hold
//! at least `node_count` nodes; the CPU features come from tokens made only by run-time
//! detection ([`crate::simd::lanes`]).

use glam::{DMat3, DVec3};

mod domains;

mod linear;
mod parts;
mod quadratic;
mod single;
mod stress;

#[cfg(target_arch = "x86_64")]
use crate::simd::{Avx2Fma, Avx512, Ymm, Zmm};
use crate::simd::{LaneVec, Plain8};
use domains::{DomainBatches, forces_domains};
use linear::{ElementBatch, forces_linear};
use parts::{Cut, OwnedForces};
use quadratic::{QuadraticBatch, forces_quadratic, stvk_operator_quadratic};
pub use single::SingleIsa;
pub use single::{ForcePart, ForceScratch, MAX_FORCE_PARTS};
pub(crate) use single::{RunParts, SingleElastic, SingleLinear};
use std::ops::Range;
use stress::{LANE_COROTATIONAL, LANE_STABLE_NEO_HOOKEAN, LANE_STVK, lane_model};

use super::quadrature::IntegrationPoints;
use crate::material::MaterialParams;

/// Elements per batch of the force kernel: 8 f64 lanes fill an AVX-512 register (an AVX2
/// register holds four: the AVX2 kernels run a batch in two parts).
const LANES: usize = 8;

// The gathers read component c of node n at `(x.as_ptr() as *const f64).add(3 n + c)`: a
// `DVec3` must be three packed f64 in x, y, z order.
const _: () = {
    assert!(std::mem::size_of::<DVec3>() == 24);
    assert!(std::mem::align_of::<DVec3>() == 8);
    assert!(std::mem::offset_of!(DVec3, x) == 0);
    assert!(std::mem::offset_of!(DVec3, y) == 8);
    assert!(std::mem::offset_of!(DVec3, z) == 16);
};

/// The batches of one element layout.
#[derive(Debug, Clone)]
enum Layout {
    /// Linear tetrahedra, one integration point each.
    Linear(Vec<ElementBatch>),
    /// 10-node tetrahedra; lane `l` of batch `b` is element `order[b * LANES + l]`.
    Quadratic {
        batches: Vec<QuadraticBatch>,
        order: Vec<u32>,
    },
    /// Single-point cells with variable node counts (smoothing domains).
    Domains(DomainBatches),
}

/// The vectorised kernels of one model, with the invariant their gathers rely on (module
/// documentation): every node index of the batches is below `node_count`.
#[derive(Debug, Clone)]
pub(crate) struct Kernels {
    node_count: usize,
    layout: Layout,
    /// The evaluation in two parts ([`Kernels::add_forces_parts`]); `None` for quadratic
    /// elements.
    two: Option<TwoParts>,
}

/// The double-precision evaluation in two parts (issue 48 s3, [`parts`]): the elements or
/// smoothing domains cut into the two halves of the Morton curve of their centroids, each half
/// batched apart as the one-part layout is (so each part runs the widest registers and touches
/// a compact half of the body).
/// Invariant (construction): the cut's nodes and the batches' node indices are below the
/// kernels' `node_count`.
#[derive(Debug, Clone)]
struct TwoParts {
    cut: Cut,
    /// The two halves' batches: part p runs `cut.parts[p].batches` of them.
    batches: Batches,
}

/// The batches of [`TwoParts`].
#[derive(Debug, Clone)]
enum Batches {
    Tets(Vec<ElementBatch>),
    Domains(DomainBatches),
}

impl Kernels {
    /// Linear tetrahedra `tets` (with their `Dm^-1` and volumes) over `nodes` rest positions
    /// (m), batched in a cache-friendly order.
    ///
    /// # Panics
    /// If a node index is out of range (the caller validated the mesh).
    pub(crate) fn linear(
        nodes: &[DVec3],
        tets: &[[u32; 4]],
        dm_inv: &[DMat3],
        volume_m3: &[f64],
    ) -> Self {
        let order = locality_order(nodes, tets, LANES);
        let batches = ElementBatch::build(&order, tets, dm_inv, volume_m3);
        // Two parts: the halves of the Morton curve, each batched as `locality_order` does.
        let centroids: Vec<DVec3> = tets.iter().map(|t| tet_centroid(nodes, t)).collect();
        let curve = morton_order(&centroids);
        let (first, second) = curve.split_at(curve.len() / 2);
        let mut halves = ElementBatch::build(&interleave(first, LANES), tets, dm_inv, volume_m3);
        let at = halves.len();
        halves.extend(ElementBatch::build(
            &interleave(second, LANES),
            tets,
            dm_inv,
            volume_m3,
        ));
        let ranges = vec![(0..at, 0..LANES), (at..halves.len(), 0..LANES)];
        let cut = parts::cut(nodes.len(), ranges, &|b, lanes| halves[b].lane_nodes(lanes));
        let two = TwoParts {
            cut,
            batches: Batches::Tets(halves),
        };
        let mut k = Self::checked(nodes.len(), tets.iter().flatten(), Layout::Linear(batches));
        k.two = Some(two);
        k
    }

    /// Quadratic tetrahedra (corners `tets`, integration points `points`) over `nodes`.
    ///
    /// # Panics
    /// As [`Kernels::linear`].
    pub(crate) fn quadratic(
        nodes: &[DVec3],
        tets: &[[u32; 4]],
        points: &IntegrationPoints,
    ) -> Self {
        let order = locality_order(nodes, tets, LANES);
        let batches = QuadraticBatch::build(&order, points);
        Self::checked(
            nodes.len(),
            points.nodes.iter(),
            Layout::Quadratic { batches, order },
        )
    }

    /// Single-point cells of `points` (smoothing domains) over the rest positions `nodes` (m).
    ///
    /// # Panics
    /// As [`Kernels::linear`].
    pub(crate) fn domains(nodes: &[DVec3], points: &IntegrationPoints) -> Self {
        let mut k = Self::checked(
            nodes.len(),
            points.nodes.iter(),
            Layout::Domains(DomainBatches::build(points)),
        );
        k.two = Some(domain_halves(nodes, points));
        k
    }

    /// The invariant of the gathers: every node index (padding lanes repeat real nodes) is
    /// below `node_count`.
    fn checked<'a>(
        node_count: usize,
        mut indices: impl Iterator<Item = &'a u32>,
        layout: Layout,
    ) -> Self {
        assert!(
            indices.all(|&i| (i as usize) < node_count),
            "element node index out of range"
        );
        Self {
            node_count,
            layout,
            two: None,
        }
    }

    /// Adds the internal forces of material `mat` (elastic, plus viscous when `v` is given) to
    /// `f` (N), for positions `x` (m) and velocities `v` (m/s); see
    /// [`super::FemModel::add_internal_forces`]. Returns `false` (and does nothing) when the
    /// material has no lane kernel (corotational).
    ///
    /// # Panics
    /// If `x`, `v` or `f` holds fewer than `node_count` nodes.
    pub(crate) fn add_forces(
        &self,
        mat: &MaterialParams,
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
    ) -> bool {
        let n = self.node_count;
        assert!(x.len() >= n && f.len() >= n && v.is_none_or(|v| v.len() >= n));
        match lane_model(mat.model) {
            Some(LANE_STVK) => self.dispatch_forces::<LANE_STVK>(mat, x, v, f),
            Some(LANE_STABLE_NEO_HOOKEAN) => {
                self.dispatch_forces::<LANE_STABLE_NEO_HOOKEAN>(mat, x, v, f);
            }
            Some(LANE_COROTATIONAL) => self.dispatch_forces::<LANE_COROTATIONAL>(mat, x, v, f),
            _ => return false,
        }
        true
    }

    /// [`Kernels::add_forces`] with the best instruction set of this CPU.
    fn dispatch_forces<const MODEL: u8>(
        &self,
        mat: &MaterialParams,
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
    ) {
        // SAFETY (all three): node indices are below node_count (checked at construction) and
        // the slices hold node_count nodes (asserted by the caller); each token proves its
        // instruction set on this CPU.
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = Avx512::detect() {
            unsafe { forces_avx512::<MODEL>(isa, self, mat, x, v, f) };
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = Avx2Fma::detect() {
            unsafe { forces_avx2::<MODEL>(isa, self, mat, x, v, f) };
            return;
        }
        unsafe { forces_plain::<MODEL>(self, mat, x, v, f) };
    }

    /// [`Kernels::add_forces`] in two parts that `run` runs (issue 48 s3, [`parts`]): the
    /// tetrahedra or smoothing domains of each half of the Morton curve ([`TwoParts`]) in the
    /// widest registers of this CPU (AVX-512, else AVX2); each part sums into its own array
    /// (`ForcePart::sum`) and adds the nodes only it touches to `f`, the nodes both touch are
    /// added afterwards on the caller, part 0 first. So the arithmetic does not depend on
    /// which thread ran which part. Returns `false` (and does nothing) when
    /// `min(parts, scratch.parts())` is below 2, `scratch` serves fewer nodes, the layout has
    /// no cut (quadratic), the material no lane kernel, or the CPU lacks AVX2 and FMA.
    /// Allocation-free.
    ///
    /// # Panics
    /// As [`Kernels::add_forces`].
    pub(crate) fn add_forces_parts(
        &self,
        mat: &MaterialParams,
        (x, v): (&[DVec3], Option<&[DVec3]>),
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
        (parts, run): (usize, RunParts<'_>),
    ) -> bool {
        let n = self.node_count;
        assert!(x.len() >= n && f.len() >= n && v.is_none_or(|v| v.len() >= n));
        let Some(two) = &self.two else { return false };
        #[cfg(target_arch = "x86_64")]
        let Some(avx2) = Avx2Fma::detect() else {
            return false;
        };
        #[cfg(not(target_arch = "x86_64"))]
        return false;
        if parts.min(scratch.parts()) < 2 || scratch.node_count() < n {
            return false;
        }
        let model = match lane_model(mat.model) {
            Some(m) => m,
            None => return false,
        };
        let out = OwnedForces {
            ptr: f.as_mut_ptr(),
            len: n,
        };
        // By reference: the closure must capture the Sync wrapper, not its raw pointer field.
        let out = &out;
        let items = &mut scratch.parts[..2];
        #[cfg(target_arch = "x86_64")]
        run(&mut *items, &|p, part| {
            let sum = &mut part.sum[..n];
            // SAFETY: node indices below n (construction), x, v and sum hold n nodes (asserted
            // above); the token proves AVX2 and FMA; `out` comes from `f` (n nodes), unused
            // until `run` returns, and the two parts own disjoint nodes.
            unsafe {
                match model {
                    LANE_STVK => Self::part::<LANE_STVK>(avx2, two, p, mat, (x, v), sum),
                    LANE_STABLE_NEO_HOOKEAN => {
                        Self::part::<LANE_STABLE_NEO_HOOKEAN>(avx2, two, p, mat, (x, v), sum);
                    }
                    _ => Self::part::<LANE_COROTATIONAL>(avx2, two, p, mat, (x, v), sum),
                }
                for r in two.cut.parts[p].own.iter().cloned() {
                    debug_assert!(r.end <= out.len);
                    let fo = std::slice::from_raw_parts_mut(out.ptr.add(r.start), r.len());
                    for (o, s) in fo.iter_mut().zip(&mut sum[r]) {
                        *o += std::mem::take(s);
                    }
                }
            }
        });
        for &i in &two.cut.shared {
            let i = i as usize;
            for part in items.iter_mut() {
                f[i] += std::mem::take(&mut part.sum[i]);
            }
        }
        true
    }

    /// Part `p` of [`Kernels::add_forces_parts`]: its batches summed into `sum`.
    ///
    /// # Safety
    /// `x`, `v` and `sum` hold at least `node_count` nodes; `two` is this model's.
    #[cfg(target_arch = "x86_64")]
    unsafe fn part<const MODEL: u8>(
        avx2: Avx2Fma,
        two: &TwoParts,
        p: usize,
        mat: &MaterialParams,
        (x, v): (&[DVec3], Option<&[DVec3]>),
        sum: &mut [DVec3],
    ) {
        let plan = &two.cut.parts[p];
        let job = match &two.batches {
            Batches::Tets(b) => PartJob::Tets(&b[plan.batches.clone()]),
            Batches::Domains(d) => PartJob::Domains(d, plan.batches.clone()),
        };
        // SAFETY (both): the caller's contract; the tokens prove their instruction sets.
        unsafe {
            match Avx512::detect() {
                Some(isa) => part_avx512::<MODEL>(isa, job, mat, x, v, sum),
                None => part_avx2::<MODEL>(avx2, job, mat, x, v, sum),
            }
        }
    }

    /// For `parts` of 1 or 2: the nodes the kernels touch and, of them, those both parts of
    /// [`Kernels::add_forces_parts`] touch (0 for one part); `None` otherwise.
    pub(crate) fn cut_nodes(&self, parts: usize) -> Option<(usize, usize)> {
        let cut = &self.two.as_ref()?.cut;
        let owned: usize = cut.parts.iter().flat_map(|p| &p.own).map(|r| r.len()).sum();
        let touched = owned + cut.shared.len();
        match parts {
            1 => Some((touched, 0)),
            2 => Some((touched, cut.shared.len())),
            _ => None,
        }
    }

    /// The single-precision kernel of the smoothing domains of this layout over the rest
    /// positions `rest` (m), or `None` for another layout.
    pub(crate) fn single_domains(&self, rest: &[DVec3]) -> Option<SingleLinear> {
        match &self.layout {
            Layout::Domains(d) => Some(SingleLinear::domains(d.batches(), rest)),
            _ => None,
        }
    }

    /// For quadratic elements: adds the element part of the backward Euler operator of StVK
    /// applied to `p` to `out` (see [`super::FemModel::quadratic_stvk_operator_action`]).
    /// Returns `false` (and does nothing) for other layouts.
    ///
    /// # Panics
    /// If `p` or `out` holds fewer than `node_count` nodes, or `ip_f`, `ip_s` fewer entries
    /// than the elements' integration points.
    pub(crate) fn quadratic_stvk_operator_action(
        &self,
        ip_f: &[DMat3],
        ip_s: &[DMat3],
        c: (f64, f64, f64),
        p: &[DVec3],
        out: &mut [DVec3],
    ) -> bool {
        let Layout::Quadratic { batches, order } = &self.layout else {
            return false;
        };
        let (n, nq) = (self.node_count, 4 * order.len());
        assert!(p.len() >= n && out.len() >= n && ip_f.len() >= nq && ip_s.len() >= nq);
        // SAFETY (all three): as in `dispatch_forces`.
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = Avx512::detect() {
            unsafe { stvk_operator_quadratic_avx512(isa, batches, order, ip_f, ip_s, c, p, out) };
            return true;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = Avx2Fma::detect() {
            unsafe { stvk_operator_quadratic_avx2(isa, batches, order, ip_f, ip_s, c, p, out) };
            return true;
        }
        unsafe {
            stvk_operator_quadratic::<false, Plain8>((), batches, order, ip_f, ip_s, c, p, out)
        };
        true
    }
}

/// Element order for a force kernel of batches of `lanes` elements: by the Morton (Z-order)
/// code of the centroid, so that consecutive batches touch nearby, mostly cache-resident
/// nodes, with `lanes` runs of the curve interleaved (lane l of a batch from run l). Ties keep
/// the mesh order.
pub(crate) fn locality_order(nodes: &[DVec3], tets: &[[u32; 4]], lanes: usize) -> Vec<u32> {
    let centroids: Vec<DVec3> = tets.iter().map(|t| tet_centroid(nodes, t)).collect();
    interleave(&morton_order(&centroids), lanes)
}

/// The centroid of tetrahedron `t` over `nodes` (m).
fn tet_centroid(nodes: &[DVec3], t: &[u32; 4]) -> DVec3 {
    t.iter().map(|&i| nodes[i as usize]).sum::<DVec3>() * 0.25
}

/// `keyed` (elements along the Morton curve) with `lanes` runs of it interleaved, so that the
/// lanes of a batch lie far apart and rarely share a node (a shared node serialises the
/// scatter of the forces).
fn interleave(keyed: &[u32], lanes: usize) -> Vec<u32> {
    let n = keyed.len();
    let run = n.div_ceil(lanes);
    (0..run)
        .flat_map(|k| (0..lanes).map(move |l| l * run + k))
        .filter(|&i| i < n)
        .map(|i| keyed[i])
        .collect()
}

/// The indices of `points` (m) sorted by the Morton (Z-order) code of their position on a
/// 1024-cell grid over their bounding box; ties keep the index order.
fn morton_order(points: &[DVec3]) -> Vec<u32> {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for c in points {
        lo = lo.min(*c);
        hi = hi.max(*c);
    }
    let scale = (hi - lo).max_element();
    let scale = if scale > 0.0 { 1023.0 / scale } else { 0.0 };
    // Spreads the 10 low bits of `v` to every third bit.
    let spread = |v: u64| {
        let mut x = v & 0x3ff;
        x = (x | (x << 16)) & 0x0300_00ff;
        x = (x | (x << 8)) & 0x0300_f00f;
        x = (x | (x << 4)) & 0x030c_30c3;
        (x | (x << 2)) & 0x0924_9249
    };
    let mut keyed: Vec<(u64, u32)> = points
        .iter()
        .enumerate()
        .map(|(e, c)| {
            let q = ((*c - lo) * scale).round();
            let code = spread(q.x as u64) | (spread(q.y as u64) << 1) | (spread(q.z as u64) << 2);
            (code, e as u32)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, e)| e).collect()
}

/// The two parts of smoothing domains `points` over the rest positions `nodes` (m): the cells
/// in Morton order of their nodes' centroid, cut where the first half of the node slots ends,
/// each half batched by node count apart ([`DomainBatches::build_groups`]), so that the halves
/// are compact and share only the nodes along the cut.
fn domain_halves(nodes: &[DVec3], points: &IntegrationPoints) -> TwoParts {
    let cells = points.node_start.len() - 1;
    let cell = |c: usize| &points.nodes[points.node_start[c]..points.node_start[c + 1]];
    let centroids: Vec<DVec3> = (0..cells)
        .map(|c| {
            let ns = cell(c);
            ns.iter().map(|&i| nodes[i as usize]).sum::<DVec3>() / ns.len().max(1) as f64
        })
        .collect();
    let order: Vec<usize> = morton_order(&centroids)
        .into_iter()
        .map(|c| c as usize)
        .collect();
    let total = points.nodes.len();
    let mut slots = 0;
    let at = order
        .iter()
        .position(|&c| {
            slots += cell(c).len();
            2 * slots >= total
        })
        .map_or(cells, |i| i + 1);
    let groups = [order[..at].to_vec(), order[at..].to_vec()];
    let (d, ends) = DomainBatches::build_groups(points, &groups);
    let halves = vec![(0..ends[0], 0..LANES), (ends[0]..ends[1], 0..LANES)];
    let cut = parts::cut(nodes.len(), halves, &|b, _| d.batch_nodes(b));
    TwoParts {
        cut,
        batches: Batches::Domains(d),
    }
}

/// The force kernel of `k`'s layout with lane type `V`.
///
/// # Safety
/// Node indices below the lengths of `x`, `v` (see [`Kernels`]).
#[inline(always)]
unsafe fn forces_with<const FMA: bool, const MODEL: u8, V: LaneVec>(
    isa: V::Isa,
    k: &Kernels,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe {
        match &k.layout {
            Layout::Quadratic { batches, .. } => {
                forces_quadratic::<FMA, MODEL, V>(isa, batches, mat, x, v, f);
            }
            Layout::Domains(d) => {
                forces_domains::<FMA, MODEL, V>(isa, (d, 0..d.len()), mat, x, v, f);
            }
            Layout::Linear(batches) => {
                forces_linear::<FMA, MODEL, V>(isa, batches, mat, x, v, f);
            }
        }
    }
}

/// [`forces_with`] in AVX-512 registers ([`Zmm`]).
///
/// # Safety
/// Node indices as [`forces_with`] (the token proves the instruction set).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn forces_avx512<const MODEL: u8>(
    isa: Avx512,
    k: &Kernels,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe { forces_with::<true, MODEL, Zmm>(isa, k, mat, x, v, f) }
}

/// [`forces_with`] in AVX2 registers ([`Ymm`], a batch in two parts of four lanes).
///
/// # Safety
/// Node indices as [`forces_with`] (the token proves the instruction set).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forces_avx2<const MODEL: u8>(
    isa: Avx2Fma,
    k: &Kernels,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe { forces_with::<true, MODEL, Ymm>(isa, k, mat, x, v, f) }
}

/// [`forces_with`] in plain code ([`Plain8`], unfused multiply-adds).
///
/// # Safety
/// Node indices as [`forces_with`].
unsafe fn forces_plain<const MODEL: u8>(
    k: &Kernels,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract; Plain8 needs no CPU feature.
    unsafe { forces_with::<false, MODEL, Plain8>((), k, mat, x, v, f) }
}

/// What one part of [`Kernels::add_forces_parts`] runs.
enum PartJob<'a> {
    /// These batches of tetrahedra.
    Tets(&'a [ElementBatch]),
    /// These batches of smoothing domains.
    Domains(&'a DomainBatches, Range<usize>),
}

/// One part's forces with lane type `V`, added to `f`.
///
/// # Safety
/// Node indices below the lengths of `x`, `v` (see [`Kernels`]).
#[inline(always)]
unsafe fn part_with<const MODEL: u8, V: LaneVec>(
    isa: V::Isa,
    job: PartJob<'_>,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe {
        match job {
            PartJob::Tets(b) => forces_linear::<true, MODEL, V>(isa, b, mat, x, v, f),
            PartJob::Domains(d, r) => forces_domains::<true, MODEL, V>(isa, (d, r), mat, x, v, f),
        }
    }
}

/// [`part_with`] in AVX-512 registers.
///
/// # Safety
/// As [`part_with`] (the token proves the instruction set).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn part_avx512<const MODEL: u8>(
    isa: Avx512,
    job: PartJob<'_>,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe { part_with::<MODEL, Zmm>(isa, job, mat, x, v, f) }
}

/// [`part_with`] in AVX2 registers (four lanes).
///
/// # Safety
/// As [`part_with`] (the token proves the instruction set).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn part_avx2<const MODEL: u8>(
    isa: Avx2Fma,
    job: PartJob<'_>,
    mat: &MaterialParams,
    x: &[DVec3],
    v: Option<&[DVec3]>,
    f: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe { part_with::<MODEL, Ymm>(isa, job, mat, x, v, f) }
}

/// [`stvk_operator_quadratic`] in AVX-512 registers.
///
/// # Safety
/// Node indices below `p.len()` (the token proves the instruction set).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
#[allow(
    clippy::too_many_arguments,
    reason = "the token, the batches and the cached F, S"
)]
unsafe fn stvk_operator_quadratic_avx512(
    isa: Avx512,
    batches: &[QuadraticBatch],
    order: &[u32],
    ip_f: &[DMat3],
    ip_s: &[DMat3],
    c: (f64, f64, f64),
    p: &[DVec3],
    out: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe { stvk_operator_quadratic::<true, Zmm>(isa, batches, order, ip_f, ip_s, c, p, out) }
}

/// [`stvk_operator_quadratic`] in AVX2 registers (two parts of four lanes per batch).
///
/// # Safety
/// Node indices below `p.len()` (the token proves the instruction set).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(
    clippy::too_many_arguments,
    reason = "the token, the batches and the cached F, S"
)]
unsafe fn stvk_operator_quadratic_avx2(
    isa: Avx2Fma,
    batches: &[QuadraticBatch],
    order: &[u32],
    ip_f: &[DMat3],
    ip_s: &[DMat3],
    c: (f64, f64, f64),
    p: &[DVec3],
    out: &mut [DVec3],
) {
    // SAFETY: the caller's contract.
    unsafe { stvk_operator_quadratic::<true, Ymm>(isa, batches, order, ip_f, ip_s, c, p, out) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::element::{FemModel, StrainSmoothing};
    use crate::material::{self, MaterialModel};
    use crate::mesh::generate::box_mesh;

    /// A large non-affine deformation of the rest shape and pseudo-random velocities.
    fn deformed_state(fem: &FemModel) -> (Vec<DVec3>, Vec<DVec3>) {
        let mut seed = 7_u64;
        let mut next = move || {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (seed >> 11) as f64 / (1_u64 << 53) as f64 - 0.5
        };
        let x = fem
            .rest
            .iter()
            .map(|p| {
                DVec3::new(
                    p.x + 0.2 * p.y + 30.0 * p.z * p.z + 3e-4 * next(),
                    0.9 * p.y - 0.1 * p.x + 3e-4 * next(),
                    1.1 * p.z + 20.0 * p.x * p.y + 3e-4 * next(),
                )
            })
            .collect();
        let v = (0..fem.node_count())
            .map(|_| DVec3::new(next(), next(), next()) * 0.2)
            .collect();
        (x, v)
    }

    /// `x` with every third node mirrored through z = 0: the half-inverted states an inverted
    /// start passes through.
    fn half_inverted(x: &[DVec3]) -> Vec<DVec3> {
        x.iter()
            .enumerate()
            .map(|(i, p)| {
                if i % 3 == 0 {
                    DVec3::new(p.x, p.y, -p.z)
                } else {
                    *p
                }
            })
            .collect()
    }

    /// Every instruction-set variant of the batch kernels that this CPU can run (AVX-512
    /// registers, AVX2 + FMA, plain code) against the scalar element loop `generic_forces`
    /// (`material::first_piola` per element or integration point), for StVK and stable
    /// Neo-Hookean, linear, quadratic and edge-smoothed linear elements, with and without
    /// viscosity. The public
    /// `add_internal_forces` runs only the best variant, so the others are checked here.
    #[test]
    fn every_kernel_variant_matches_the_scalar_element_loop() {
        type Kernel = fn(&FemModel, &[DVec3], Option<&[DVec3]>, &mut [DVec3]);
        // The inputs are the test's own (node indices checked by `FemModel::new`, x and v
        // n long); each instruction set is asserted before its kernel runs.
        fn plain<const MODEL: u8>(m: &FemModel, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
            // SAFETY: see above.
            unsafe { forces_plain::<MODEL>(&m.kernels, &m.material, x, v, f) }
        }
        #[cfg(target_arch = "x86_64")]
        fn avx2<const MODEL: u8>(m: &FemModel, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
            let isa = Avx2Fma::detect().expect("AVX2 and FMA");
            // SAFETY: see above.
            unsafe { forces_avx2::<MODEL>(isa, &m.kernels, &m.material, x, v, f) }
        }
        #[cfg(target_arch = "x86_64")]
        fn zmm<const MODEL: u8>(m: &FemModel, x: &[DVec3], v: Option<&[DVec3]>, f: &mut [DVec3]) {
            let isa = Avx512::detect().expect("AVX-512");
            // SAFETY: see above.
            unsafe { forces_avx512::<MODEL>(isa, &m.kernels, &m.material, x, v, f) }
        }
        let mut checked = 0;
        for (model, kernels) in [
            (MaterialModel::StVenantKirchhoff, {
                let mut k: Vec<(&str, Kernel)> = vec![("plain", plain::<LANE_STVK>)];
                #[cfg(target_arch = "x86_64")]
                {
                    if Avx2Fma::detect().is_some() {
                        k.push(("avx2", avx2::<LANE_STVK>));
                    }
                    if Avx512::detect().is_some() {
                        k.push(("avx512", zmm::<LANE_STVK>));
                    }
                }
                k
            }),
            (MaterialModel::Corotational, {
                let mut k: Vec<(&str, Kernel)> = vec![("plain", plain::<LANE_COROTATIONAL>)];
                #[cfg(target_arch = "x86_64")]
                {
                    if Avx2Fma::detect().is_some() {
                        k.push(("avx2", avx2::<LANE_COROTATIONAL>));
                    }
                    if Avx512::detect().is_some() {
                        k.push(("avx512", zmm::<LANE_COROTATIONAL>));
                    }
                }
                k
            }),
            (MaterialModel::StableNeoHookean, {
                let mut k: Vec<(&str, Kernel)> = vec![("plain", plain::<LANE_STABLE_NEO_HOOKEAN>)];
                #[cfg(target_arch = "x86_64")]
                {
                    if Avx2Fma::detect().is_some() {
                        k.push(("avx2", avx2::<LANE_STABLE_NEO_HOOKEAN>));
                    }
                    if Avx512::detect().is_some() {
                        k.push(("avx512", zmm::<LANE_STABLE_NEO_HOOKEAN>));
                    }
                }
                k
            }),
        ] {
            for (quadratic, smoothing) in [
                (false, StrainSmoothing::None),
                (true, StrainSmoothing::None),
                (false, StrainSmoothing::Edge),
            ] {
                // 3 x 2 x 3 cells: 90 tets (and 169 edge domains), so the last batch has
                // padding lanes.
                let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]);
                let mesh = if quadratic { mesh.to_quadratic() } else { mesh };
                let mut mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
                mat.model = model;
                mat.phi_pa_s = 0.3;
                mat.psi_pa_s = 0.2;
                let fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
                assert_ne!(fem.element_count() % LANES, 0, "want padding lanes");
                assert_ne!(fem.cell_count() % LANES, 0, "want padding lanes");
                if smoothing == StrainSmoothing::Edge {
                    // Domains of several node counts: batches with padding slots.
                    let counts: std::collections::BTreeSet<usize> = (0..fem.cell_count())
                        .map(|c| fem.cell_nodes(c).len())
                        .collect();
                    assert!(counts.len() >= 3, "{counts:?}");
                }
                let (x, v) = deformed_state(&fem);
                let x_inv = half_inverted(&x);
                for (x, velocities) in [
                    (&x, None),
                    (&x, Some(v.as_slice())),
                    (&x_inv, None),
                    (&x_inv, Some(v.as_slice())),
                ] {
                    let mut expected = vec![DVec3::ZERO; fem.node_count()];
                    fem.generic_forces(x, velocities, &mut expected);
                    let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
                    assert!(scale > 0.0);
                    for (name, kernel) in &kernels {
                        let mut f = vec![DVec3::ZERO; fem.node_count()];
                        kernel(&fem, x, velocities, &mut f);
                        let err = f
                            .iter()
                            .zip(&expected)
                            .map(|(a, b)| (*a - *b).length())
                            .fold(0.0, f64::max);
                        assert!(
                            err < 1e-12 * scale,
                            "{name} {model:?} quadratic={quadratic} {smoothing:?} viscous={}: {err:e} of {scale:e}",
                            velocities.is_some()
                        );
                        checked += 1;
                    }
                }
            }
        }
        // At least the plain variant of each of the 12 combinations.
        assert!(checked >= 12);
    }

    /// The double-precision kernel in two parts ([`Kernels::add_forces_parts`]) against the
    /// scalar element loop, as the one-part kernels above: within 1e-12 of the largest nodal
    /// force, linear tetrahedra and smoothing domains (padding lanes and slots), the three lane
    /// materials, with and without the viscous stress, half-inverted or not, adding to
    /// nonzero forces; the part arrays are clean afterwards (a second call adds the same). It
    /// declines for quadratic elements, one part, or a scratch too small.
    #[test]
    fn the_double_precision_kernel_in_two_parts_matches_the_scalar_loop() {
        let serial: RunParts<'_> = &|parts, g| {
            for (p, part) in parts.iter_mut().enumerate() {
                g(p, part);
            }
        };
        let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]);
        let mut checked = 0;
        for model in [
            MaterialModel::StVenantKirchhoff,
            MaterialModel::StableNeoHookean,
            MaterialModel::Corotational,
        ] {
            let mut mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
            mat.model = model;
            mat.phi_pa_s = 0.3;
            mat.psi_pa_s = 0.2;
            for smoothing in [StrainSmoothing::None, StrainSmoothing::Edge] {
                let fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
                let n = fem.node_count();
                let mut scratch = ForceScratch::with_parts(n, 2);
                let (x, v) = deformed_state(&fem);
                let x_inv = half_inverted(&x);
                for (x, vel) in [(&x, None), (&x, Some(v.as_slice())), (&x_inv, Some(&v[..]))] {
                    let mut expected = vec![DVec3::ZERO; n];
                    fem.generic_forces(x, vel, &mut expected);
                    let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
                    let offset: Vec<DVec3> = (0..n).map(|i| DVec3::splat(i as f64)).collect();
                    let mut f = offset.clone();
                    let ran = fem.kernels.add_forces_parts(
                        &mat,
                        (x, vel),
                        &mut f,
                        &mut scratch,
                        (2, serial),
                    );
                    assert_eq!(ran, Avx2Fma::detect().is_some(), "{model:?} {smoothing:?}");
                    if !ran {
                        continue;
                    }
                    let err = f
                        .iter()
                        .zip(&expected)
                        .zip(&offset)
                        .map(|((a, b), o)| (*a - *o - *b).length())
                        .fold(0.0, f64::max);
                    assert!(
                        err < 1e-12 * scale,
                        "{model:?} {smoothing:?} viscous={}: {err:e} of {scale:e}",
                        vel.is_some()
                    );
                    let again = f.clone();
                    let mut f = offset.clone();
                    fem.kernels
                        .add_forces_parts(&mat, (x, vel), &mut f, &mut scratch, (2, serial));
                    assert_eq!(f, again, "{model:?} {smoothing:?}");
                    checked += 1;
                }
                let mut f = vec![DVec3::ZERO; n];
                for (parts, scratch) in [
                    (1, &mut ForceScratch::with_parts(n, 2)),
                    (2, &mut ForceScratch::new(n)),
                    (2, &mut ForceScratch::with_parts(n - 1, 2)),
                ] {
                    let args = (&x[..], None);
                    assert!(!fem.kernels.add_forces_parts(
                        &mat,
                        args,
                        &mut f,
                        scratch,
                        (parts, serial)
                    ));
                }
                assert!(f.iter().all(|a| *a == DVec3::ZERO));
            }
        }
        let quadratic = FemModel::new(
            &mesh.to_quadratic(),
            MaterialParams::from_youngs(1e4, 0.45, 1000.0),
        )
        .unwrap();
        let n = quadratic.node_count();
        let mut f = vec![DVec3::ZERO; n];
        let args = (quadratic.rest(), None);
        let mat = *quadratic.material();
        let mut scratch = ForceScratch::with_parts(n, 2);
        assert!(
            !quadratic
                .kernels
                .add_forces_parts(&mat, args, &mut f, &mut scratch, (2, serial))
        );
        assert!(checked == 0 || checked == 18, "{checked}");
    }

    /// The single-precision kernel of linear StVK and stable Neo-Hookean tetrahedra, standard
    /// and edge-smoothed,
    /// against the double-precision scalar element loop: within 2e-6 of the largest nodal
    /// force for a large non-affine deformation (stretches from about 0.5 to 2), half-inverted
    /// or not, with and without the viscous stress; exactly zero at rest; the same with a force
    /// array that starts nonzero (the kernel adds). 90 tetrahedra and 169 domains of several
    /// node counts: the last batches have padding lanes and slots. Each instruction set this
    /// CPU runs (AVX2 + FMA, AVX-512) and the public path. Without AVX2 + FMA the kernel
    /// declines and the forces are double precision's, bit for bit.
    #[test]
    fn the_single_precision_kernel_matches_the_double_precision_loop() {
        for model in [
            MaterialModel::StVenantKirchhoff,
            MaterialModel::StableNeoHookean,
        ] {
            for smoothing in [StrainSmoothing::None, StrainSmoothing::Edge] {
                if Avx2Fma::detect().is_some() {
                    single_precision_case(model, smoothing);
                } else {
                    single_precision_fallback_case(model, smoothing);
                }
            }
        }
    }

    fn single_precision_fallback_case(model: MaterialModel, smoothing: StrainSmoothing) {
        let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]);
        let mut mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
        mat.model = model;
        mat.phi_pa_s = 0.3;
        let mut fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
        fem.set_single_precision(true).unwrap();
        let n = fem.node_count();
        let mut scratch = ForceScratch::new(n);
        let (x, v) = deformed_state(&fem);
        let single = fem.single.as_ref().expect("single-precision data");
        let mut untouched = vec![DVec3::ONE; n];
        let lame = SingleElastic::of(&mat).expect("a single-precision material");
        let viscosity = (mat.phi_pa_s, mat.psi_pa_s);
        assert!(!single.add_forces(lame, viscosity, &x, Some(&v), &mut untouched, &mut scratch));
        assert!(untouched.iter().all(|a| *a == DVec3::ONE));
        let mut expected = vec![DVec3::ZERO; n];
        fem.add_internal_forces(&x, Some(&v), &mut expected);
        let mut f = vec![DVec3::ZERO; n];
        fem.add_internal_forces_with(&x, Some(&v), &mut f, &mut scratch);
        assert_eq!(f, expected, "{smoothing:?}");
    }

    fn single_precision_case(model: MaterialModel, smoothing: StrainSmoothing) {
        let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]);
        let mut mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
        mat.model = model;
        mat.phi_pa_s = 0.3;
        mat.psi_pa_s = 0.2;
        let mut fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
        fem.set_single_precision(true).unwrap();
        // Padding lanes in both builds' batches (16 lanes, run as two halves of 8 by AVX2).
        assert!(
            !matches!(fem.cell_count() % 16, 0 | 8),
            "want padding lanes"
        );
        let n = fem.node_count();
        let mut scratch = ForceScratch::new(n + 5);
        let (x, v) = deformed_state(&fem);
        let x_inv = half_inverted(&x);
        let single = fem.single.as_ref().expect("single-precision data");
        let lame = SingleElastic::of(&mat).expect("a single-precision material");
        let viscosity = (mat.phi_pa_s, mat.psi_pa_s);
        // Each instruction set this CPU runs, then the public path (the widest of them).
        let isas = single::SingleIsa::available();
        assert!(!isas.is_empty());
        let runs = isas.iter().copied().map(Some).chain([None]);
        for isa in runs {
            for x in [&x, &x_inv] {
                for velocities in [None, Some(v.as_slice())] {
                    let mut expected = vec![DVec3::ZERO; n];
                    fem.generic_forces(x, velocities, &mut expected);
                    let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
                    let offset: Vec<DVec3> = (0..n).map(|i| DVec3::splat(i as f64)).collect();
                    let mut f = offset.clone();
                    match isa {
                        Some(isa) => single.add_forces_on(
                            single::SingleToken::of(isa).expect("listed as available"),
                            lame,
                            viscosity,
                            x,
                            velocities,
                            &mut f,
                            &mut scratch,
                        ),
                        None => fem.add_internal_forces_with(x, velocities, &mut f, &mut scratch),
                    }
                    let err = f
                        .iter()
                        .zip(&expected)
                        .zip(&offset)
                        .map(|((a, b), o)| (*a - *o - *b).length())
                        .fold(0.0, f64::max);
                    assert!(
                        err < 2e-6 * scale && err > 1e-9 * scale, // rounded: the kernel ran
                        "{isa:?} {model:?} {smoothing:?} viscous={}: {err:e} of {scale:e}",
                        velocities.is_some()
                    );
                }
            }
        }
        let mut f = vec![DVec3::ZERO; n];
        let v0 = vec![DVec3::ZERO; n];
        fem.add_internal_forces_with(fem.rest(), Some(&v0), &mut f, &mut scratch);
        assert!(f.iter().all(|a| *a == DVec3::ZERO));
        // A pinned instruction set is the one the public path runs, bit for bit.
        for isa in isas {
            let mut pinned = fem.clone();
            pinned.pin_single_precision_isa(isa).unwrap();
            let single = pinned.single.as_ref().expect("single-precision data");
            let (mut direct, mut public) = (vec![DVec3::ZERO; n], vec![DVec3::ZERO; n]);
            single.add_forces_on(
                single::SingleToken::of(isa).expect("listed as available"),
                lame,
                viscosity,
                &x,
                Some(&v),
                &mut direct,
                &mut scratch,
            );
            pinned.add_internal_forces_with(&x, Some(&v), &mut public, &mut scratch);
            assert_eq!(direct, public, "{isa:?}");
        }
    }

    /// Single precision is refused, with the scene field named, where the kernel does not
    /// apply (quadratic elements, another material), and a scratch too small for the model
    /// falls back to double precision.
    #[test]
    fn single_precision_is_refused_outside_linear_stvk_and_neo_hookean() {
        let mesh = box_mesh(DVec3::splat(0.01), [2, 2, 2]);
        let mat = MaterialParams::from_youngs(1e4, 0.3, 1000.0);
        let mut corotational = mat;
        corotational.model = MaterialModel::Corotational;
        for fem in [
            FemModel::new(&mesh.to_quadratic(), mat).unwrap(),
            FemModel::new(&mesh, corotational).unwrap(),
        ] {
            let mut fem = fem;
            let err = fem.set_single_precision(true).unwrap_err().to_string();
            assert!(err.contains("integrator.force_precision"), "{err}");
            assert!(!fem.single_precision());
            let err = fem
                .pin_single_precision_isa(SingleIsa::Avx2)
                .unwrap_err()
                .to_string();
            assert!(err.contains("single precision is off"), "{err}");
        }
        let mut fem = FemModel::new(&mesh, mat).unwrap();
        fem.set_single_precision(true).unwrap();
        let (x, _) = deformed_state(&fem);
        let mut expected = vec![DVec3::ZERO; fem.node_count()];
        fem.add_internal_forces(&x, None, &mut expected);
        let mut f = vec![DVec3::ZERO; fem.node_count()];
        fem.add_internal_forces_with(&x, None, &mut f, &mut ForceScratch::new(3));
        assert_eq!(f, expected);
    }

    /// Every instruction-set variant of the quadratic backward Euler operator kernel against
    /// the plain one (the integration test `vectorised_operator_matches_the_integration_point_formula`
    /// checks the variant this CPU runs against the formula).
    #[test]
    fn every_operator_variant_matches_the_plain_one() {
        let mesh = box_mesh(DVec3::splat(0.01), [3, 2, 3]).to_quadratic();
        let fem = FemModel::new(&mesh, MaterialParams::from_youngs(1e4, 0.45, 1000.0)).unwrap();
        let (x, p) = deformed_state(&fem);
        let nq = fem.integration_point_count();
        let ip_f: Vec<_> = (0..nq).map(|q| fem.ip_field_gradient(q, &x)).collect();
        let ip_s: Vec<_> = ip_f
            .iter()
            .map(|f| material::stvk_stress(&material::green_strain(f), 4e3, 1e3))
            .collect();
        let c = (1e-6, 3.0e3, 2.0e3);
        let Layout::Quadratic {
            batches: b,
            order: o,
        } = &fem.kernels.layout
        else {
            panic!("quadratic layout");
        };
        let mut expected = vec![DVec3::ZERO; fem.node_count()];
        // SAFETY: node indices checked by `FemModel::new`; p is n long.
        unsafe {
            stvk_operator_quadratic::<false, Plain8>((), b, o, &ip_f, &ip_s, c, &p, &mut expected)
        };
        let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
        assert!(scale > 0.0);
        let check = |name: &str, got: &[DVec3]| {
            let err = got
                .iter()
                .zip(&expected)
                .map(|(a, b)| (*a - *b).length())
                .fold(0.0, f64::max);
            assert!(err < 1e-12 * scale, "{name}: {err:e} of {scale:e}");
        };
        #[cfg(target_arch = "x86_64")]
        {
            if Avx2Fma::detect().is_some() {
                let mut out = vec![DVec3::ZERO; fem.node_count()];
                let isa = Avx2Fma::detect().expect("AVX2 and FMA");
                // SAFETY: indices as above; the token proves the instruction set.
                unsafe { stvk_operator_quadratic_avx2(isa, b, o, &ip_f, &ip_s, c, &p, &mut out) };
                check("avx2", &out);
            }
            if Avx512::detect().is_some() {
                let mut out = vec![DVec3::ZERO; fem.node_count()];
                let isa = Avx512::detect().expect("AVX-512");
                // SAFETY: indices as above; the token proves the instruction set.
                unsafe { stvk_operator_quadratic_avx512(isa, b, o, &ip_f, &ip_s, c, &p, &mut out) };
                check("avx512", &out);
            }
        }
        let mut out = vec![DVec3::ZERO; fem.node_count()];
        assert!(fem.quadratic_stvk_operator_action(&ip_f, &ip_s, c, &p, &mut out));
        check("public", &out);
    }
}
