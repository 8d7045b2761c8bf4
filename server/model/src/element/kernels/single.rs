//! The single-precision force kernel of linear St Venant-Kirchhoff tetrahedra, standard or
//! edge-smoothed (AVX2 + FMA): eight cells per register, no gather instruction and no scalar
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
//! 2. loads each corner's rows with one 16-byte load per lane and transposes eight lanes with
//!    seven shuffles;
//! 3. computes, with `G = Du Dm^-1` the displacement gradient (`F = I + G`, seed 000 eq. 21),
//!    `2E = G + G^T + G^T G` (Green strain without the cancellation of `F^T F - I`), the
//!    second Piola-Kirchhoff stress `S = lambda tr(E) I + 2 mu E` plus the viscous stress of
//!    [`crate::material::viscous_stress`] (eq. 11, `A = F^T F'`), scaled by `-V`,
//!    then `P = F S` and `H = P Dm^-T` (eq. 22), all in registers;
//! 4. transposes the four corner forces back to one 16-byte row per lane and adds it to a
//!    single-precision nodal force array (four read-modify-writes per element instead of
//!    twelve), which is finally added to the double-precision forces and cleared.
//!
//! The smoothing domains of edge-based strain smoothing ([`super::domains`], 4 to 11 nodes)
//! take the same steps, with `G = sum_s (u_s - u_0) g_s^T` over their node slots and the force
//! `-V P g_s` added to each slot's node.
//!
//! The stress arithmetic is single precision; sums over the elements of a node are single
//! precision too. The rest state gives exactly zero force (`G = 0`); the error against the
//! double-precision kernel is measured by the tests (`docs/accuracy.md`).

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::{
    __m128, __m256, _mm_add_ps, _mm_load_ps, _mm_store_ps, _mm256_add_ps, _mm256_castps128_ps256,
    _mm256_castps256_ps128, _mm256_extractf128_ps, _mm256_fmadd_ps, _mm256_insertf128_ps,
    _mm256_load_ps, _mm256_mul_ps, _mm256_set1_ps, _mm256_setzero_ps, _mm256_shuffle_ps,
    _mm256_sub_ps, _mm256_unpackhi_ps, _mm256_unpacklo_ps,
};

use glam::{DMat3, DVec3};

use super::domains::DomainBatch;

/// Lanes of the single-precision kernel: eight `f32` fill an AVX2 register.
const SINGLE_LANES: usize = 8;

/// Eight elements side by side; padding lanes repeat node 0 with zero `Dm^-1` and volume, so
/// they add exactly zero force.
#[derive(Debug, Clone)]
#[repr(C, align(32))]
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

/// The work arrays of the single-precision force kernel, one row per node (48 bytes a node),
/// reused across calls so that a call allocates nothing. Arrays for `n` nodes serve every model
/// of at most `n` nodes (a condensed region's model and its whole body).
#[derive(Debug, Clone, Default)]
pub struct ForceScratch {
    packed: Vec<PackedNode>,
    force: Vec<NodeForce>,
}

impl ForceScratch {
    /// Work arrays for models of at most `node_count` nodes.
    pub fn new(node_count: usize) -> Self {
        Self {
            packed: vec![PackedNode::default(); node_count],
            force: vec![NodeForce::default(); node_count],
        }
    }

    /// The largest node count the arrays serve.
    pub fn node_count(&self) -> usize {
        self.packed.len()
    }
}

/// One node slot of a batch of eight smoothing domains: per lane, four times the node and
/// its smoothed gradient (1/m, component c at `grad[c]`). Padding slots repeat the lane's
/// first node with a zero gradient.
#[derive(Debug, Clone)]
#[repr(C, align(32))]
struct DomainSlot {
    nodes: [u32; SINGLE_LANES],
    grad: [[f32; SINGLE_LANES]; 3],
}

/// The cells of one layout in batches of eight.
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

/// The batches of the single-precision kernel of one model of linear tetrahedra (standard
/// or edge-smoothed), with the rest positions the displacements are taken from. Invariant
/// (checked at construction): every node index is below `rest.len()`.
#[derive(Debug, Clone)]
pub(crate) struct SingleLinear {
    layout: SingleLayout,
    rest: Vec<DVec3>,
}

impl SingleLinear {
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
            .collect();
        Self {
            layout: SingleLayout::Tets(batches),
            rest: rest.to_vec(),
        }
    }

    /// Batches of smoothing domains: `batches` yields, per batch of eight, the slots' nodes
    /// and gradients (1/m) and the lanes' volumes (m^3), as the double-precision kernel
    /// batches them (`super::domains::DomainBatches`); over the rest positions `rest` (m).
    ///
    /// # Panics
    /// If a node index is out of range (the caller validated the mesh).
    pub(crate) fn domains<'a>(
        batches: impl Iterator<Item = DomainBatch<'a>>,
        rest: &[DVec3],
    ) -> Self {
        let (mut start, mut slots, mut volume) = (vec![0], Vec::new(), Vec::new());
        for (nodes, grads, w) in batches {
            for (n, g) in nodes.iter().zip(grads) {
                assert!(
                    n.iter().all(|&i| (i as usize) < rest.len()),
                    "domain node index out of range"
                );
                slots.push(DomainSlot {
                    // Below 2^30: FemModel::new refuses more than i32::MAX / 3 nodes.
                    nodes: n.map(|i| 4 * i),
                    grad: g.map(|c| c.map(|x| x as f32)),
                });
            }
            start.push(slots.len());
            volume.push(w.map(|x| x as f32));
        }
        Self {
            layout: SingleLayout::Domains {
                start,
                slots,
                volume_m3: volume,
            },
            rest: rest.to_vec(),
        }
    }

    /// Adds the StVK internal forces (N) of Lamé `lambda_pa`, `mu_pa`, plus the viscous ones
    /// (`phi_pa_s`, `psi_pa_s`) when `v` (m/s) is given, for positions `x` (m), to `f`, in
    /// single precision. Returns `false` (and does nothing) without AVX2 and FMA.
    ///
    /// # Panics
    /// If `x`, `v`, `f` or `scratch` holds fewer nodes than the model.
    pub(crate) fn add_forces(
        &self,
        lame: (f64, f64),
        viscosity: (f64, f64),
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) -> bool {
        let n = self.rest.len();
        assert!(x.len() >= n && f.len() >= n && v.is_none_or(|v| v.len() >= n));
        assert!(scratch.node_count() >= n, "force scratch too small");
        let (packed, force) = (&mut scratch.packed[..n], &mut scratch.force[..n]);
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::has_avx2_fma() {
            // SAFETY: AVX2 was detected; the slices hold n nodes each.
            unsafe {
                pack_avx2(&x[..n], Some(&self.rest), packed, 0);
                if let Some(v) = v {
                    pack_avx2(&v[..n], None, packed, 4);
                }
            }
            let coef = Coefficients {
                half_lambda: (0.5 * lame.0) as f32,
                mu: lame.1 as f32,
                phi: viscosity.0 as f32,
                two_psi: (2.0 * viscosity.1) as f32,
            };
            // SAFETY: AVX2 and FMA were detected; every node index of the batches is below
            // n = packed.len() = force.len() (checked at construction).
            unsafe {
                match (&self.layout, v.is_some()) {
                    (SingleLayout::Tets(b), true) => forces_avx2::<true>(b, coef, packed, force),
                    (SingleLayout::Tets(b), false) => forces_avx2::<false>(b, coef, packed, force),
                    (
                        SingleLayout::Domains {
                            start,
                            slots,
                            volume_m3,
                        },
                        viscous,
                    ) => {
                        let d = (start.as_slice(), slots.as_slice(), volume_m3.as_slice());
                        if viscous {
                            domain_forces_avx2::<true>(d, coef, packed, force);
                        } else {
                            domain_forces_avx2::<false>(d, coef, packed, force);
                        }
                    }
                }
            }
            // SAFETY: AVX2 was detected; the slices hold n nodes each.
            unsafe { unpack_avx2(force, &mut f[..n]) };
            return true;
        }
        let _ = (lame, viscosity, packed, force);
        false
    }
}

/// `packed[i][at..at + 4] = a[i] - rest[i]` (or `a[i]`) rounded to single precision, in the
/// first three of the four entries (the fourth is never read).
///
/// # Safety
/// AVX2; `a`, `rest` and `packed` of one length.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn pack_avx2(a: &[DVec3], rest: Option<&[DVec3]>, packed: &mut [PackedNode], at: usize) {
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
/// AVX2; `force` and `f` of one length.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn unpack_avx2(force: &mut [NodeForce], f: &mut [DVec3]) {
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

/// The material constants of the kernel, single precision.
#[derive(Clone, Copy)]
struct Coefficients {
    half_lambda: f32,
    mu: f32,
    /// Multiplies `tr(A + A^T)` ([`crate::material::viscous_stress`]).
    phi: f32,
    /// Multiplies `A + A^T`.
    two_psi: f32,
}

/// `a * b + c` in one rounding.
///
/// # Safety
/// FMA.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn fma(a: __m256, b: __m256, c: __m256) -> __m256 {
    // SAFETY: the caller's contract.
    unsafe { _mm256_fmadd_ps(a, b, c) }
}

/// `a0 b0 + a1 b1 + a2 b2`.
///
/// # Safety
/// AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn dot3(a: [__m256; 3], b: [__m256; 3]) -> __m256 {
    // SAFETY: the caller's contract.
    unsafe { fma(a[2], b[2], fma(a[1], b[1], _mm256_mul_ps(a[0], b[0]))) }
}

/// The half `half` (0: displacement, 1: velocity) of the rows of lanes `l` and `l + 4` in
/// the low and high halves (`nodes[l]` four times the node of lane l).
///
/// # Safety
/// AVX2; the nodes of lanes `l`, `l + 4` below the packed array's length.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn pair(base: *const f32, nodes: &[u32; SINGLE_LANES], l: usize, half: usize) -> __m256 {
    // SAFETY: the caller's contract; rows are 32-byte aligned, halves 16-byte aligned.
    unsafe {
        let lo = base.add(2 * nodes[l] as usize + 4 * half);
        let hi = base.add(2 * nodes[l + 4] as usize + 4 * half);
        _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(_mm_load_ps(lo)), _mm_load_ps(hi))
    }
}

/// Rows `[x, y, z]` of eight lanes from four pairs of padded rows (lanes l, l + 4 in r_l).
///
/// # Safety
/// AVX2.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn transpose_in(r: [__m256; 4]) -> [__m256; 3] {
    // SAFETY: the caller's contract.
    unsafe {
        let t0 = _mm256_unpacklo_ps(r[0], r[1]); // x0 x1 y0 y1 | x4 x5 y4 y5
        let t1 = _mm256_unpackhi_ps(r[0], r[1]); // z0 z1 0 0 | z4 z5 0 0
        let t2 = _mm256_unpacklo_ps(r[2], r[3]); // x2 x3 y2 y3 | ..
        let t3 = _mm256_unpackhi_ps(r[2], r[3]); // z2 z3 0 0 | ..
        [
            _mm256_shuffle_ps::<0x44>(t0, t2),
            _mm256_shuffle_ps::<0xEE>(t0, t2),
            _mm256_shuffle_ps::<0x44>(t1, t3),
        ]
    }
}

/// Corner `k`'s rows of eight lanes: `[ux, uy, uz]` (and `[vx, vy, vz]` when `VISCOUS`);
/// `nodes[l]` is four times the node of lane l.
///
/// # Safety
/// AVX2; every node below `packed.len()`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn load_corner<const VISCOUS: bool>(
    packed: &[PackedNode],
    nodes: &[u32; SINGLE_LANES],
) -> ([__m256; 3], [__m256; 3]) {
    // SAFETY: the caller's contract.
    unsafe {
        let base = packed.as_ptr().cast::<f32>();
        let u = transpose_in([
            pair(base, nodes, 0, 0),
            pair(base, nodes, 1, 0),
            pair(base, nodes, 2, 0),
            pair(base, nodes, 3, 0),
        ]);
        let v = if VISCOUS {
            transpose_in([
                pair(base, nodes, 0, 1),
                pair(base, nodes, 1, 1),
                pair(base, nodes, 2, 1),
                pair(base, nodes, 3, 1),
            ])
        } else {
            [_mm256_setzero_ps(); 3]
        };
        (u, v)
    }
}

/// `force[node] += r` for one padded row, `node4` four times the node.
///
/// # Safety
/// The node below `force.len()` (`base` its first `f32`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn add_row(base: *mut f32, node4: u32, r: __m128) {
    // SAFETY: the caller's contract; rows are 16-byte aligned.
    unsafe {
        let p = base.add(node4 as usize);
        _mm_store_ps(p, _mm_add_ps(_mm_load_ps(p), r));
    }
}

/// Adds corner forces `h` (`[x, y, z]` rows of eight lanes) to the force rows of the nodes
/// (`nodes[l]` four times the node of lane l).
///
/// # Safety
/// AVX2; every node below `force.len()`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn add_corner(force: &mut [NodeForce], nodes: &[u32; SINGLE_LANES], h: [__m256; 3]) {
    // SAFETY: the caller's contract.
    unsafe {
        let zero = _mm256_setzero_ps();
        let t0 = _mm256_unpacklo_ps(h[0], h[1]); // x0 y0 x1 y1 | x4 y4 x5 y5
        let t1 = _mm256_unpackhi_ps(h[0], h[1]); // x2 y2 x3 y3 | ..
        let t2 = _mm256_unpacklo_ps(h[2], zero); // z0 0 z1 0 | ..
        let t3 = _mm256_unpackhi_ps(h[2], zero); // z2 0 z3 0 | ..
        let lanes = [
            _mm256_shuffle_ps::<0x44>(t0, t2), // lanes 0 | 4
            _mm256_shuffle_ps::<0xEE>(t0, t2), // lanes 1 | 5
            _mm256_shuffle_ps::<0x44>(t1, t3), // lanes 2 | 6
            _mm256_shuffle_ps::<0xEE>(t1, t3), // lanes 3 | 7
        ];
        let base = force.as_mut_ptr().cast::<f32>();
        for l in 0..4 {
            add_row(base, nodes[l], _mm256_castps256_ps128(lanes[l]));
            add_row(base, nodes[l + 4], _mm256_extractf128_ps::<1>(lanes[l]));
        }
    }
}

/// Row `r` of `Dm^-1`'s entries of a batch (`r = 3 row + column`), read from memory at each
/// use: a volatile read, so that the compiler neither keeps nine of them in the sixteen
/// registers nor spills them to the stack (they are in L1 already).
///
/// # Safety
/// AVX2.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn bm(b: &SingleBatch, r: usize) -> __m256 {
    // SAFETY: the row is 32 aligned bytes of the batch (the struct is 32-byte aligned).
    unsafe { std::ptr::read_volatile(b.dm_inv[r].as_ptr().cast::<__m256>()) }
}

/// `m[3 i + j] = sum_k d[3 k + i] Bm_kj`: the gradient of the edge differences `d`
/// (component i of edge k at `d[3 k + i]`) through `Dm^-1` of batch `b`, eq. 21.
///
/// # Safety
/// AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn edge_gradient(d: &[__m256; 9], b: &SingleBatch) -> [__m256; 9] {
    // SAFETY: the caller's contract.
    unsafe {
        let mut m = [_mm256_setzero_ps(); 9];
        for j in 0..3 {
            let col = [bm(b, j), bm(b, 3 + j), bm(b, 6 + j)];
            for i in 0..3 {
                m[3 * i + j] = dot3([d[i], d[3 + i], d[6 + i]], col);
            }
        }
        m
    }
}

/// The symmetric entries 00 11 22 01 02 12 of a 3x3 matrix, in that order.
const SYM: [(usize, usize); 6] = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)];

/// The constants of the stress, splatted once per call.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct LaneCoefficients {
    half_lambda: __m256,
    mu: __m256,
    phi: __m256,
    two_psi: __m256,
}

#[cfg(target_arch = "x86_64")]
impl LaneCoefficients {
    /// # Safety
    /// AVX.
    #[inline(always)]
    unsafe fn new(c: Coefficients) -> Self {
        // SAFETY: the caller's contract.
        unsafe {
            Self {
                half_lambda: _mm256_set1_ps(c.half_lambda),
                mu: _mm256_set1_ps(c.mu),
                phi: _mm256_set1_ps(c.phi),
                two_psi: _mm256_set1_ps(c.two_psi),
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
/// AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn scaled_piola<const VISCOUS: bool>(
    g: &[__m256; 9],
    gd: &[__m256; 9],
    volume: __m256,
    k: &LaneCoefficients,
) -> [__m256; 9] {
    // SAFETY: the caller's contract.
    unsafe {
        let zero = _mm256_setzero_ps();
        let (half_lambda, mu, phi, two_psi) = (k.half_lambda, k.mu, k.phi, k.two_psi);
        // 2E_ij = G_ij + G_ji + sum_r G_ri G_rj.
        let mut e2 = [zero; 6];
        for (s, &(i, j)) in SYM.iter().enumerate() {
            let gtg = dot3([g[i], g[3 + i], g[6 + i]], [g[j], g[3 + j], g[6 + j]]);
            e2[s] = _mm256_add_ps(gtg, _mm256_add_ps(g[3 * i + j], g[3 * j + i]));
        }
        // S / (-V) = lambda/2 tr(2E) I + mu 2E, plus the viscous phi tr(A + A^T) I + 2 psi (A + A^T)
        // of crate::material::viscous_stress (seed eq. 11 with the factor of the module note).
        let mut tr = _mm256_mul_ps(
            half_lambda,
            _mm256_add_ps(e2[0], _mm256_add_ps(e2[1], e2[2])),
        );
        let mut s = [zero; 6];
        for k in 0..6 {
            s[k] = _mm256_mul_ps(mu, e2[k]);
        }
        if VISCOUS {
            // A = F^T F' = F' + G^T F'; 2E' = A + A^T.
            let mut a = [zero; 9];
            for i in 0..3 {
                for j in 0..3 {
                    a[3 * i + j] = fma(
                        g[6 + i],
                        gd[6 + j],
                        fma(g[3 + i], gd[3 + j], fma(g[i], gd[j], gd[3 * i + j])),
                    );
                }
            }
            let mut trd = zero;
            for (k, &(i, j)) in SYM.iter().enumerate() {
                let ed2 = _mm256_add_ps(a[3 * i + j], a[3 * j + i]);
                if k < 3 {
                    trd = _mm256_add_ps(trd, ed2);
                }
                s[k] = fma(two_psi, ed2, s[k]);
            }
            tr = fma(phi, trd, tr);
        }
        let w = _mm256_sub_ps(zero, volume);
        for (k, sk) in s.iter_mut().enumerate() {
            let diagonal = if k < 3 { _mm256_add_ps(*sk, tr) } else { *sk };
            *sk = _mm256_mul_ps(w, diagonal);
        }
        // The full symmetric -V S, row-major.
        let sm = [s[0], s[3], s[4], s[3], s[1], s[5], s[4], s[5], s[2]];
        // P = F S = S + G S.
        let mut p = [zero; 9];
        for i in 0..3 {
            for j in 0..3 {
                p[3 * i + j] = fma(
                    g[3 * i + 2],
                    sm[6 + j],
                    fma(g[3 * i + 1], sm[3 + j], fma(g[3 * i], sm[j], sm[3 * i + j])),
                );
            }
        }
        p
    }
}

/// The kernel over every batch (module documentation).
///
/// # Safety
/// AVX2 and FMA; every node index of `batches` below `packed.len()` and `force.len()`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forces_avx2<const VISCOUS: bool>(
    batches: &[SingleBatch],
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    // SAFETY: the caller's contract (batch rows are 32-byte aligned: the struct is).
    unsafe {
        let k = LaneCoefficients::new(c);
        let zero = _mm256_setzero_ps();
        for b in batches {
            let (u0, v0) = load_corner::<VISCOUS>(packed, &b.nodes[0]);
            // Edge differences: component i of edge k (corner k+1 minus corner 0) at 3 k + i.
            let mut du = [zero; 9];
            let mut dv = [zero; 9];
            for k in 0..3 {
                let (uk, vk) = load_corner::<VISCOUS>(packed, &b.nodes[k + 1]);
                for i in 0..3 {
                    du[3 * k + i] = _mm256_sub_ps(uk[i], u0[i]);
                    if VISCOUS {
                        dv[3 * k + i] = _mm256_sub_ps(vk[i], v0[i]);
                    }
                }
            }
            let g = edge_gradient(&du, b);
            let gd = if VISCOUS {
                edge_gradient(&dv, b)
            } else {
                [zero; 9]
            };
            let p = scaled_piola::<VISCOUS>(&g, &gd, _mm256_load_ps(b.volume_m3.as_ptr()), &k);
            // H_k (force on corner k+1), component i = sum_j P_ij Bm_kj; corner 0 gets minus
            // their sum.
            let mut h0 = [zero; 3];
            for k in 0..3 {
                let row = [bm(b, 3 * k), bm(b, 3 * k + 1), bm(b, 3 * k + 2)];
                let mut hk = [zero; 3];
                for i in 0..3 {
                    hk[i] = dot3([p[3 * i], p[3 * i + 1], p[3 * i + 2]], row);
                    h0[i] = _mm256_sub_ps(h0[i], hk[i]);
                }
                add_corner(force, &b.nodes[k + 1], hk);
            }
            add_corner(force, &b.nodes[0], h0);
        }
    }
}

/// The kernel over batches of smoothing domains (`start`, `slots`, `volume_m3` of
/// [`SingleLayout::Domains`]): `G = sum_s (u_s - u_0) g_s^T` over the slots (velocities too
/// when `VISCOUS`), [`scaled_piola`], then `-V P g_s` added to each slot's node.
///
/// # Safety
/// AVX2 and FMA; every node of the slots below `packed.len()` and `force.len()`; `start` has
/// one more entry than `volume_m3`, ascending within `slots.len()`, at least one slot a batch.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn domain_forces_avx2<const VISCOUS: bool>(
    (start, slots, volume_m3): (&[usize], &[DomainSlot], &[[f32; SINGLE_LANES]]),
    c: Coefficients,
    packed: &[PackedNode],
    force: &mut [NodeForce],
) {
    use std::arch::x86_64::_mm256_loadu_ps;
    // SAFETY: the caller's contract (slots are 32-byte aligned).
    unsafe {
        let k = LaneCoefficients::new(c);
        let zero = _mm256_setzero_ps();
        for (b, volume) in volume_m3.iter().enumerate() {
            let batch = &slots[start[b]..start[b + 1]];
            let (u0, v0) = load_corner::<VISCOUS>(packed, &batch[0].nodes);
            let mut g = [zero; 9];
            let mut gd = [zero; 9];
            for slot in &batch[1..] {
                let (us, vs) = load_corner::<VISCOUS>(packed, &slot.nodes);
                let gr = [
                    _mm256_load_ps(slot.grad[0].as_ptr()),
                    _mm256_load_ps(slot.grad[1].as_ptr()),
                    _mm256_load_ps(slot.grad[2].as_ptr()),
                ];
                for i in 0..3 {
                    let du = _mm256_sub_ps(us[i], u0[i]);
                    let dv = _mm256_sub_ps(vs[i], v0[i]);
                    for j in 0..3 {
                        g[3 * i + j] = fma(du, gr[j], g[3 * i + j]);
                        if VISCOUS {
                            gd[3 * i + j] = fma(dv, gr[j], gd[3 * i + j]);
                        }
                    }
                }
            }
            let p = scaled_piola::<VISCOUS>(&g, &gd, _mm256_loadu_ps(volume.as_ptr()), &k);
            for slot in batch {
                let gr = [
                    _mm256_load_ps(slot.grad[0].as_ptr()),
                    _mm256_load_ps(slot.grad[1].as_ptr()),
                    _mm256_load_ps(slot.grad[2].as_ptr()),
                ];
                let mut h = [zero; 3];
                for (i, hi) in h.iter_mut().enumerate() {
                    *hi = dot3([p[3 * i], p[3 * i + 1], p[3 * i + 2]], gr);
                }
                add_corner(force, &slot.nodes, h);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vectorised packing and unpacking (four nodes at a time) and their scalar tails,
    /// for every remainder: `packed` holds `a - rest` rounded, `f` gains the sums and the sums
    /// are cleared.
    #[test]
    fn packing_and_unpacking_cover_every_tail() {
        if !crate::cpu::has_avx2_fma() {
            eprintln!("no AVX2: nothing to test");
            return;
        }
        for n in 0..11 {
            let a: Vec<DVec3> = (0..n)
                .map(|i| DVec3::new(0.1 + i as f64, -0.2 * i as f64, 1e-3 * (i * i) as f64))
                .collect();
            let rest: Vec<DVec3> = (0..n).map(|i| DVec3::splat(0.01 * i as f64)).collect();
            let mut packed = vec![PackedNode::default(); n];
            // SAFETY: AVX2 checked above; slices of one length.
            unsafe {
                pack_avx2(&a, Some(&rest), &mut packed, 0);
                pack_avx2(&a, None, &mut packed, 4);
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
            unsafe { unpack_avx2(&mut force, &mut f) };
            for i in 0..n {
                let k = i as f64;
                assert_eq!(f[i], a[i] + DVec3::new(k, 2.0 * k, -k), "{n} {i}");
                assert_eq!(force[i].0, [0.0; 4]);
            }
        }
    }
}
