//! `f32` lanes for the single-precision force kernel (`element::kernels::single`): the [`F32Lanes`] trait, [`Y8`] (eight lanes in an AVX2 register) and
//! [`Z16`] (sixteen in an AVX-512 register), with the kernel's packed-row loads and force-row
//! stores. Every method is an `unsafe fn` (the trait's contract: call them only inlined into a
//! function compiled for the type's instruction set).

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::{
    __m128, __m256, __m512, _mm_add_ps, _mm_load_ps, _mm_store_ps, _mm256_add_ps,
    _mm256_castps128_ps256, _mm256_castps256_ps128, _mm256_extractf128_ps, _mm256_fmadd_ps,
    _mm256_insertf128_ps, _mm256_load_ps, _mm256_loadu_ps, _mm256_mul_ps, _mm256_set1_ps,
    _mm256_setzero_ps, _mm256_shuffle_ps, _mm256_sub_ps, _mm256_unpackhi_ps, _mm256_unpacklo_ps,
    _mm512_add_ps, _mm512_castps128_ps512, _mm512_castps512_ps128, _mm512_extractf32x4_ps,
    _mm512_fmadd_ps, _mm512_insertf32x4, _mm512_load_ps, _mm512_loadu_ps, _mm512_mul_ps,
    _mm512_set1_ps, _mm512_setzero_ps, _mm512_shuffle_ps, _mm512_sub_ps, _mm512_unpackhi_ps,
    _mm512_unpacklo_ps,
};

/// [`F32Lanes::WIDTH`] `f32` lanes in one register: the arithmetic of the kernel, written
/// once for both instruction sets.
///
/// # Safety
/// Every method executes instructions of the type's instruction set (`Y8`: AVX2 and FMA;
/// `Z16`: AVX-512F): call them only where it is available, inlined into a function compiled
/// with it (the methods are `#[inline(always)]`; the kernels' entry points carry the
/// `#[target_feature]`).
#[cfg(target_arch = "x86_64")]
pub(crate) trait F32Lanes: Copy {
    /// The number of lanes (divides the single-precision kernel's batch of sixteen).
    const WIDTH: usize;
    unsafe fn zero() -> Self;
    unsafe fn splat(v: f32) -> Self;
    /// The lanes at `p`, aligned to the register's size.
    unsafe fn load(p: *const f32) -> Self;
    /// The lanes at `p`, unaligned.
    unsafe fn loadu(p: *const f32) -> Self;
    /// As [`F32Lanes::load`], volatile: the compiler neither keeps the value in a register
    /// across uses nor spills it (for the batch's `Dm^-1`, in L1 already).
    unsafe fn load_volatile(p: *const f32) -> Self;
    unsafe fn add(self, o: Self) -> Self;
    unsafe fn sub(self, o: Self) -> Self;
    unsafe fn mul(self, o: Self) -> Self;
    /// `a * b + c` in one rounding.
    unsafe fn fma(a: Self, b: Self, c: Self) -> Self;
    /// Rows `[x, y, z]` of the lanes' packed node rows, from entry `at` (0: displacement, 4:
    /// velocity) of row `nodes[l] / 4` for lane l (`base` the first `f32` of the packed array;
    /// rows are 32-byte aligned).
    unsafe fn load_rows(base: *const f32, nodes: &[u32], at: usize) -> [Self; 3];
    /// `force[nodes[l] / 4] += (h[0][l], h[1][l], h[2][l])` lane after lane (`base` the first
    /// `f32` of the force array; rows are 16-byte aligned).
    unsafe fn add_rows(base: *mut f32, nodes: &[u32], h: [Self; 3]);
}

/// `force row += r`, `node4` four times the node.
///
/// # Safety
/// The row inside the force array whose first `f32` is `base`; SSE.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn add_row(base: *mut f32, node4: u32, r: __m128) {
    // SAFETY: the caller's contract; rows are 16-byte aligned.
    unsafe {
        let p = base.add(node4 as usize);
        _mm_store_ps(p, _mm_add_ps(_mm_load_ps(p), r));
    }
}

/// The first three entries from `at` of the packed row of node `node4 / 4`.
///
/// # Safety
/// The row inside the packed array whose first `f32` is `base`; SSE.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn packed_row(base: *const f32, node4: u32, at: usize) -> __m128 {
    // SAFETY: the caller's contract; rows are 32-byte aligned, halves 16-byte aligned.
    unsafe { _mm_load_ps(base.add(2 * node4 as usize + at)) }
}

/// The element-wise methods of [`F32Lanes`] for a lane type wrapping one register, from
/// the intrinsics of its width (zero, splat, aligned and unaligned load, the register type
/// for the volatile load, add, sub, mul, fused multiply-add).
#[cfg(target_arch = "x86_64")]
macro_rules! lane_ops {
    ($zero:ident, $splat:ident, $load:ident, $loadu:ident, $reg:ty, $add:ident, $sub:ident,
     $mul:ident, $fma:ident) => {
        #[inline(always)]
        unsafe fn zero() -> Self {
            // SAFETY (every method): the trait's contract.
            Self(unsafe { $zero() })
        }

        #[inline(always)]
        unsafe fn splat(v: f32) -> Self {
            Self(unsafe { $splat(v) })
        }

        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            Self(unsafe { $load(p) })
        }

        #[inline(always)]
        unsafe fn loadu(p: *const f32) -> Self {
            Self(unsafe { $loadu(p) })
        }

        #[inline(always)]
        unsafe fn load_volatile(p: *const f32) -> Self {
            Self(unsafe { std::ptr::read_volatile(p.cast::<$reg>()) })
        }

        #[inline(always)]
        unsafe fn add(self, o: Self) -> Self {
            Self(unsafe { $add(self.0, o.0) })
        }

        #[inline(always)]
        unsafe fn sub(self, o: Self) -> Self {
            Self(unsafe { $sub(self.0, o.0) })
        }

        #[inline(always)]
        unsafe fn mul(self, o: Self) -> Self {
            Self(unsafe { $mul(self.0, o.0) })
        }

        #[inline(always)]
        unsafe fn fma(a: Self, b: Self, c: Self) -> Self {
            Self(unsafe { $fma(a.0, b.0, c.0) })
        }
    };
}

/// Eight lanes in an AVX2 register.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub(crate) struct Y8(__m256);

#[cfg(target_arch = "x86_64")]
impl F32Lanes for Y8 {
    const WIDTH: usize = 8;

    lane_ops!(
        _mm256_setzero_ps,
        _mm256_set1_ps,
        _mm256_load_ps,
        _mm256_loadu_ps,
        __m256,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_fmadd_ps
    );

    /// Lanes l and l + 4 share a register (low and high halves); four registers are
    /// transposed with seven shuffles.
    #[inline(always)]
    unsafe fn load_rows(base: *const f32, nodes: &[u32], at: usize) -> [Self; 3] {
        let nodes = &nodes[..8];
        unsafe {
            let mut r = [_mm256_setzero_ps(); 4];
            for (l, rl) in r.iter_mut().enumerate() {
                *rl = _mm256_insertf128_ps::<1>(
                    _mm256_castps128_ps256(packed_row(base, nodes[l], at)),
                    packed_row(base, nodes[l + 4], at),
                );
            }
            let t0 = _mm256_unpacklo_ps(r[0], r[1]); // x0 x1 y0 y1 | x4 x5 y4 y5
            let t1 = _mm256_unpackhi_ps(r[0], r[1]); // z0 z1 0 0 | z4 z5 0 0
            let t2 = _mm256_unpacklo_ps(r[2], r[3]); // x2 x3 y2 y3 | ..
            let t3 = _mm256_unpackhi_ps(r[2], r[3]); // z2 z3 0 0 | ..
            [
                Self(_mm256_shuffle_ps::<0x44>(t0, t2)),
                Self(_mm256_shuffle_ps::<0xEE>(t0, t2)),
                Self(_mm256_shuffle_ps::<0x44>(t1, t3)),
            ]
        }
    }

    #[inline(always)]
    unsafe fn add_rows(base: *mut f32, nodes: &[u32], h: [Self; 3]) {
        let nodes = &nodes[..8];
        unsafe {
            let zero = _mm256_setzero_ps();
            let t0 = _mm256_unpacklo_ps(h[0].0, h[1].0); // x0 y0 x1 y1 | x4 y4 x5 y5
            let t1 = _mm256_unpackhi_ps(h[0].0, h[1].0); // x2 y2 x3 y3 | ..
            let t2 = _mm256_unpacklo_ps(h[2].0, zero); // z0 0 z1 0 | ..
            let t3 = _mm256_unpackhi_ps(h[2].0, zero); // z2 0 z3 0 | ..
            let lanes = [
                _mm256_shuffle_ps::<0x44>(t0, t2), // lanes 0 | 4
                _mm256_shuffle_ps::<0xEE>(t0, t2), // lanes 1 | 5
                _mm256_shuffle_ps::<0x44>(t1, t3), // lanes 2 | 6
                _mm256_shuffle_ps::<0xEE>(t1, t3), // lanes 3 | 7
            ];
            for (l, r) in lanes.into_iter().enumerate() {
                add_row(base, nodes[l], _mm256_castps256_ps128(r));
                add_row(base, nodes[l + 4], _mm256_extractf128_ps::<1>(r));
            }
        }
    }
}

/// Sixteen lanes in an AVX-512 register.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub(crate) struct Z16(__m512);

#[cfg(target_arch = "x86_64")]
impl F32Lanes for Z16 {
    const WIDTH: usize = 16;

    lane_ops!(
        _mm512_setzero_ps,
        _mm512_set1_ps,
        _mm512_load_ps,
        _mm512_loadu_ps,
        __m512,
        _mm512_add_ps,
        _mm512_sub_ps,
        _mm512_mul_ps,
        _mm512_fmadd_ps
    );

    /// Lanes l, l + 4, l + 8 and l + 12 share a register (one per 128-bit block); the
    /// in-block unpacks and shuffles of [`Y8::load_rows`] then transpose all four blocks.
    #[inline(always)]
    unsafe fn load_rows(base: *const f32, nodes: &[u32], at: usize) -> [Self; 3] {
        let nodes = &nodes[..16];
        unsafe {
            let mut r = [_mm512_setzero_ps(); 4];
            for (l, rl) in r.iter_mut().enumerate() {
                let q = _mm512_castps128_ps512(packed_row(base, nodes[l], at));
                let q = _mm512_insertf32x4::<1>(q, packed_row(base, nodes[l + 4], at));
                let q = _mm512_insertf32x4::<2>(q, packed_row(base, nodes[l + 8], at));
                *rl = _mm512_insertf32x4::<3>(q, packed_row(base, nodes[l + 12], at));
            }
            let t0 = _mm512_unpacklo_ps(r[0], r[1]);
            let t1 = _mm512_unpackhi_ps(r[0], r[1]);
            let t2 = _mm512_unpacklo_ps(r[2], r[3]);
            let t3 = _mm512_unpackhi_ps(r[2], r[3]);
            [
                Self(_mm512_shuffle_ps::<0x44>(t0, t2)),
                Self(_mm512_shuffle_ps::<0xEE>(t0, t2)),
                Self(_mm512_shuffle_ps::<0x44>(t1, t3)),
            ]
        }
    }

    #[inline(always)]
    unsafe fn add_rows(base: *mut f32, nodes: &[u32], h: [Self; 3]) {
        let nodes = &nodes[..16];
        unsafe {
            let zero = _mm512_setzero_ps();
            let t0 = _mm512_unpacklo_ps(h[0].0, h[1].0);
            let t1 = _mm512_unpackhi_ps(h[0].0, h[1].0);
            let t2 = _mm512_unpacklo_ps(h[2].0, zero);
            let t3 = _mm512_unpackhi_ps(h[2].0, zero);
            // Block j of lanes[l] is the row of lane l + 4 j.
            let lanes = [
                _mm512_shuffle_ps::<0x44>(t0, t2),
                _mm512_shuffle_ps::<0xEE>(t0, t2),
                _mm512_shuffle_ps::<0x44>(t1, t3),
                _mm512_shuffle_ps::<0xEE>(t1, t3),
            ];
            for (l, r) in lanes.into_iter().enumerate() {
                add_row(base, nodes[l], _mm512_castps512_ps128(r));
                add_row(base, nodes[l + 4], _mm512_extractf32x4_ps::<1>(r));
                add_row(base, nodes[l + 8], _mm512_extractf32x4_ps::<2>(r));
                add_row(base, nodes[l + 12], _mm512_extractf32x4_ps::<3>(r));
            }
        }
    }
}
