//! Lane arithmetic for the vectorised force kernels of [`crate::fem`]: one trait, [`Lane`],
//! implemented by a single `f64` and by eight `f64` side by side ([`Lanes8`]: [`Plain8`] in
//! plain code, on x86-64 [`Ymm2`] in two AVX2 registers and [`Zmm`] in one AVX-512 register),
//! so that the stress formulas and the force kernels are written once and compiled for each.

use std::ops::{Add, Mul, Sub};

/// A value the stress formulas compute with: one `f64`, or several side by side.
pub(crate) trait Lane:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self>
{
    /// Every lane set to `v`.
    fn splat(v: f64) -> Self;
    /// `a * b + c`; one rounding when `FMA` (a vector type always fuses).
    fn madd<const FMA: bool>(a: Self, b: Self, c: Self) -> Self;
    /// `a * b - c`; one rounding when `FMA` (a vector type always fuses).
    fn msub<const FMA: bool>(a: Self, b: Self, c: Self) -> Self;
}

impl Lane for f64 {
    #[inline(always)]
    fn splat(v: f64) -> Self {
        v
    }

    /// Fused only when `FMA`: the scalar kernels are instantiated with `FMA = true` only
    /// inside functions compiled with the `fma` target feature. Rust never contracts
    /// `a * b + c` by itself, and elsewhere `f64::mul_add` would be a library call.
    #[inline(always)]
    fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
        if FMA { a.mul_add(b, c) } else { a * b + c }
    }

    #[inline(always)]
    fn msub<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
        if FMA { a.mul_add(b, -c) } else { a * b - c }
    }
}

/// Eight `f64` lanes with loads, stores and gathers: the batch type of the force kernels (one
/// lane per element of a batch).
pub(crate) trait Lanes8: Lane {
    /// The eight lanes of `a`.
    fn load(a: &[f64; 8]) -> Self;
    /// Writes the eight lanes to `a`.
    fn store(self, a: &mut [f64; 8]);
    /// Lane l = `*base.offset(offsets[l])`.
    ///
    /// # Safety
    /// Every `base.offset(offsets[l])` must be a readable `f64`.
    unsafe fn gather(base: *const f64, offsets: &[i32; 8]) -> Self;
}

/// Eight `f64` lanes in plain code (the fallback without AVX2).
#[derive(Clone, Copy)]
pub(crate) struct Plain8([f64; 8]);

impl Add for Plain8 {
    type Output = Plain8;
    #[inline(always)]
    fn add(self, o: Plain8) -> Plain8 {
        Plain8(std::array::from_fn(|l| self.0[l] + o.0[l]))
    }
}

impl Sub for Plain8 {
    type Output = Plain8;
    #[inline(always)]
    fn sub(self, o: Plain8) -> Plain8 {
        Plain8(std::array::from_fn(|l| self.0[l] - o.0[l]))
    }
}

impl Mul for Plain8 {
    type Output = Plain8;
    #[inline(always)]
    fn mul(self, o: Plain8) -> Plain8 {
        Plain8(std::array::from_fn(|l| self.0[l] * o.0[l]))
    }
}

impl Lane for Plain8 {
    #[inline(always)]
    fn splat(v: f64) -> Plain8 {
        Plain8([v; 8])
    }

    #[inline(always)]
    fn madd<const FMA: bool>(a: Plain8, b: Plain8, c: Plain8) -> Plain8 {
        Plain8(std::array::from_fn(|l| {
            f64::madd::<FMA>(a.0[l], b.0[l], c.0[l])
        }))
    }

    #[inline(always)]
    fn msub<const FMA: bool>(a: Plain8, b: Plain8, c: Plain8) -> Plain8 {
        Plain8(std::array::from_fn(|l| {
            f64::msub::<FMA>(a.0[l], b.0[l], c.0[l])
        }))
    }
}

impl Lanes8 for Plain8 {
    #[inline(always)]
    fn load(a: &[f64; 8]) -> Plain8 {
        Plain8(*a)
    }

    #[inline(always)]
    fn store(self, a: &mut [f64; 8]) {
        *a = self.0;
    }

    #[inline(always)]
    unsafe fn gather(base: *const f64, offsets: &[i32; 8]) -> Plain8 {
        // SAFETY: every base.offset(offsets[l]) is readable (caller's contract).
        Plain8(std::array::from_fn(|l| unsafe {
            *base.offset(offsets[l] as isize)
        }))
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use x86::{Ymm2, Zmm};

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Lane, Lanes8};
    use std::arch::x86_64::{
        __m128i, __m256d, __m256i, __m512d, _mm_loadu_si128, _mm256_add_pd, _mm256_fmadd_pd,
        _mm256_fmsub_pd, _mm256_i32gather_pd, _mm256_loadu_pd, _mm256_loadu_si256, _mm256_mul_pd,
        _mm256_set1_pd, _mm256_storeu_pd, _mm256_sub_pd, _mm512_add_pd, _mm512_fmadd_pd,
        _mm512_fmsub_pd, _mm512_i32gather_pd, _mm512_loadu_pd, _mm512_mul_pd, _mm512_set1_pd,
        _mm512_storeu_pd, _mm512_sub_pd,
    };
    use std::ops::{Add, Mul, Sub};

    /// Eight `f64` lanes in one AVX-512 register.
    ///
    /// Every operation is an AVX-512F instruction: create and use values only inside
    /// functions compiled with `#[target_feature(enable = "avx512f")]` and reached after
    /// checking the CPU (`fem::has_avx512`). The methods are `#[inline(always)]`, so that
    /// they compile into those callers' bodies.
    #[derive(Clone, Copy)]
    pub(crate) struct Zmm(__m512d);

    impl Lanes8 for Zmm {
        #[inline(always)]
        fn load(a: &[f64; 8]) -> Zmm {
            // SAFETY: `a` is eight readable f64; AVX-512F per the type contract.
            Zmm(unsafe { _mm512_loadu_pd(a.as_ptr()) })
        }

        #[inline(always)]
        fn store(self, a: &mut [f64; 8]) {
            // SAFETY: `a` is eight writable f64; AVX-512F per the type contract.
            unsafe { _mm512_storeu_pd(a.as_mut_ptr(), self.0) }
        }

        #[inline(always)]
        unsafe fn gather(base: *const f64, offsets: &[i32; 8]) -> Zmm {
            // SAFETY: offsets is eight i32; the addressed f64 are readable (caller's
            // contract); AVX-512F per the type contract.
            unsafe {
                let idx = _mm256_loadu_si256(offsets.as_ptr().cast::<__m256i>());
                Zmm(_mm512_i32gather_pd::<8>(idx, base))
            }
        }
    }

    impl Add for Zmm {
        type Output = Zmm;
        #[inline(always)]
        fn add(self, o: Zmm) -> Zmm {
            // SAFETY: Zmm values exist only on CPUs with AVX-512F (type contract).
            Zmm(unsafe { _mm512_add_pd(self.0, o.0) })
        }
    }

    impl Sub for Zmm {
        type Output = Zmm;
        #[inline(always)]
        fn sub(self, o: Zmm) -> Zmm {
            // SAFETY: as in `add`.
            Zmm(unsafe { _mm512_sub_pd(self.0, o.0) })
        }
    }

    impl Mul for Zmm {
        type Output = Zmm;
        #[inline(always)]
        fn mul(self, o: Zmm) -> Zmm {
            // SAFETY: as in `add`.
            Zmm(unsafe { _mm512_mul_pd(self.0, o.0) })
        }
    }

    impl Lane for Zmm {
        #[inline(always)]
        fn splat(v: f64) -> Zmm {
            // SAFETY: only called inside AVX-512 kernels (type contract).
            Zmm(unsafe { _mm512_set1_pd(v) })
        }

        #[inline(always)]
        fn madd<const FMA: bool>(a: Zmm, b: Zmm, c: Zmm) -> Zmm {
            // SAFETY: as in `splat`; AVX-512F includes the fused multiply-adds.
            Zmm(unsafe { _mm512_fmadd_pd(a.0, b.0, c.0) })
        }

        #[inline(always)]
        fn msub<const FMA: bool>(a: Zmm, b: Zmm, c: Zmm) -> Zmm {
            // SAFETY: as in `madd`.
            Zmm(unsafe { _mm512_fmsub_pd(a.0, b.0, c.0) })
        }
    }

    /// Eight `f64` lanes in two AVX2 registers (lanes 0-3, 4-7).
    ///
    /// Every operation is an AVX2 or FMA instruction: create and use values only inside
    /// functions compiled with `#[target_feature(enable = "avx2,fma")]` and reached after
    /// checking the CPU (`fem::has_avx2_fma`), as for [`Zmm`].
    #[derive(Clone, Copy)]
    pub(crate) struct Ymm2(__m256d, __m256d);

    impl Add for Ymm2 {
        type Output = Ymm2;
        #[inline(always)]
        fn add(self, o: Ymm2) -> Ymm2 {
            // SAFETY: Ymm2 values exist only on CPUs with AVX2 and FMA (type contract).
            unsafe { Ymm2(_mm256_add_pd(self.0, o.0), _mm256_add_pd(self.1, o.1)) }
        }
    }

    impl Sub for Ymm2 {
        type Output = Ymm2;
        #[inline(always)]
        fn sub(self, o: Ymm2) -> Ymm2 {
            // SAFETY: as in `add`.
            unsafe { Ymm2(_mm256_sub_pd(self.0, o.0), _mm256_sub_pd(self.1, o.1)) }
        }
    }

    impl Mul for Ymm2 {
        type Output = Ymm2;
        #[inline(always)]
        fn mul(self, o: Ymm2) -> Ymm2 {
            // SAFETY: as in `add`.
            unsafe { Ymm2(_mm256_mul_pd(self.0, o.0), _mm256_mul_pd(self.1, o.1)) }
        }
    }

    impl Lane for Ymm2 {
        #[inline(always)]
        fn splat(v: f64) -> Ymm2 {
            // SAFETY: only called inside AVX2 kernels (type contract).
            unsafe { Ymm2(_mm256_set1_pd(v), _mm256_set1_pd(v)) }
        }

        #[inline(always)]
        fn madd<const FMA: bool>(a: Ymm2, b: Ymm2, c: Ymm2) -> Ymm2 {
            // SAFETY: as in `splat`; FMA per the type contract.
            unsafe {
                Ymm2(
                    _mm256_fmadd_pd(a.0, b.0, c.0),
                    _mm256_fmadd_pd(a.1, b.1, c.1),
                )
            }
        }

        #[inline(always)]
        fn msub<const FMA: bool>(a: Ymm2, b: Ymm2, c: Ymm2) -> Ymm2 {
            // SAFETY: as in `madd`.
            unsafe {
                Ymm2(
                    _mm256_fmsub_pd(a.0, b.0, c.0),
                    _mm256_fmsub_pd(a.1, b.1, c.1),
                )
            }
        }
    }

    impl Lanes8 for Ymm2 {
        #[inline(always)]
        fn load(a: &[f64; 8]) -> Ymm2 {
            // SAFETY: `a` is eight readable f64; AVX per the type contract.
            unsafe {
                Ymm2(
                    _mm256_loadu_pd(a.as_ptr()),
                    _mm256_loadu_pd(a[4..].as_ptr()),
                )
            }
        }

        #[inline(always)]
        fn store(self, a: &mut [f64; 8]) {
            // SAFETY: `a` is eight writable f64; AVX per the type contract.
            unsafe {
                _mm256_storeu_pd(a.as_mut_ptr(), self.0);
                _mm256_storeu_pd(a[4..].as_mut_ptr(), self.1);
            }
        }

        #[inline(always)]
        unsafe fn gather(base: *const f64, offsets: &[i32; 8]) -> Ymm2 {
            // SAFETY: offsets is eight i32; the addressed f64 are readable (caller's
            // contract); AVX2 per the type contract.
            unsafe {
                let lo = _mm_loadu_si128(offsets.as_ptr().cast::<__m128i>());
                let hi = _mm_loadu_si128(offsets[4..].as_ptr().cast::<__m128i>());
                Ymm2(
                    _mm256_i32gather_pd::<8>(base, lo),
                    _mm256_i32gather_pd::<8>(base, hi),
                )
            }
        }
    }
}
