//! Lane arithmetic for the vectorised force kernels of [`crate::fem`]: one trait, [`Lane`],
//! implemented by a single `f64` and (on x86-64) by eight `f64` in one AVX-512 register
//! ([`Zmm`]), so that the stress formulas are written once and compiled for both.

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

#[cfg(target_arch = "x86_64")]
pub(crate) use zmm::Zmm;

#[cfg(target_arch = "x86_64")]
mod zmm {
    use super::Lane;
    use std::arch::x86_64::{
        __m512d, _mm512_add_pd, _mm512_fmadd_pd, _mm512_fmsub_pd, _mm512_loadu_pd, _mm512_mul_pd,
        _mm512_set1_pd, _mm512_storeu_pd, _mm512_sub_pd,
    };
    use std::ops::{Add, Mul, Sub};

    /// Eight `f64` lanes in one AVX-512 register.
    ///
    /// Every operation is an AVX-512F instruction: create and use values only inside
    /// functions compiled with `#[target_feature(enable = "avx512f")]` and reached after
    /// checking the CPU (`fem::has_avx512`). The methods are `#[inline(always)]`, so that
    /// they compile into those callers' bodies.
    #[derive(Clone, Copy)]
    pub(crate) struct Zmm(pub(crate) __m512d);

    impl Zmm {
        /// The eight lanes of `a`.
        #[inline(always)]
        pub(crate) fn load(a: &[f64; 8]) -> Zmm {
            // SAFETY: `a` is eight readable f64; AVX-512F per the type contract.
            Zmm(unsafe { _mm512_loadu_pd(a.as_ptr()) })
        }

        /// Writes the eight lanes to `a`.
        #[inline(always)]
        pub(crate) fn store(self, a: &mut [f64; 8]) {
            // SAFETY: `a` is eight writable f64; AVX-512F per the type contract.
            unsafe { _mm512_storeu_pd(a.as_mut_ptr(), self.0) }
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
}
