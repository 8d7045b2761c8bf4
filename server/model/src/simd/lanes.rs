//! Lane arithmetic for the vectorised force kernels: one trait, [`Lane`], implemented by a
//! single `f64` and by several `f64` side by side ([`LaneVec`]: [`Plain8`], eight lanes in plain
//! code; on x86-64 [`Ymm`], four lanes in one AVX2 register, and [`Zmm`], eight in one AVX-512
//! register), so that the stress formulas and the force kernels are written once and compiled
//! for each. The batches hold [`crate::element::kernels::LANES`] (eight) elements; a vector of fewer lanes runs a
//! batch in parts ([`LaneVec::WIDTH`] lanes at a time).
//!
//! **Soundness.** Every operation of [`Ymm`] and [`Zmm`] is an AVX2/FMA or AVX-512
//! instruction. A value of these types can only be made from an *instruction-set token*
//! ([`Lane::Isa`]: [`Avx2Fma`], [`Avx512`]) and a token can only be obtained from run-time
//! feature detection ([`Avx2Fma::detect`], [`Avx512::detect`]), so safe code cannot execute an
//! instruction the CPU lacks. Operations on existing values need no token: the value proves
//! that one was obtained.

use std::ops::{Add, Div, Mul, Sub};

/// A value the stress formulas compute with: one `f64`, or several side by side.
pub(crate) trait Lane:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self>
{
    /// The instruction-set token that values of this type need to be made (`()` for plain
    /// code).
    type Isa: Copy;
    /// Every lane set to `v`.
    fn splat(isa: Self::Isa, v: f64) -> Self;
    /// `a * b + c`; one rounding when `FMA` (a vector type always fuses).
    fn madd<const FMA: bool>(a: Self, b: Self, c: Self) -> Self;
    /// `a * b - c`; one rounding when `FMA` (a vector type always fuses).
    fn msub<const FMA: bool>(a: Self, b: Self, c: Self) -> Self;
}

impl Lane for f64 {
    type Isa = ();

    #[inline(always)]
    fn splat(_: (), v: f64) -> Self {
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

/// [`LaneVec::WIDTH`] `f64` lanes with loads, stores and gathers: the vector type of the force
/// kernels (one lane per element of a batch).
pub(crate) trait LaneVec: Lane {
    /// The number of lanes (at most 8, and a divisor of the kernels' batch size).
    const WIDTH: usize;
    /// The lanes from the first [`LaneVec::WIDTH`] entries of `a`.
    ///
    /// # Panics
    /// If `a` is shorter than [`LaneVec::WIDTH`] (the kernels slice fixed-size arrays at
    /// constant offsets, so the check is compiled away).
    fn load(isa: Self::Isa, a: &[f64]) -> Self;
    /// Writes the lanes to the first [`LaneVec::WIDTH`] entries of `a`.
    ///
    /// # Panics
    /// As [`LaneVec::load`].
    fn store(self, a: &mut [f64]);
    /// Lane l = `*base.offset(offsets[l])`.
    ///
    /// # Safety
    /// `offsets` holds at least [`LaneVec::WIDTH`] entries and every
    /// `base.offset(offsets[l])` for l below it is a readable `f64`.
    unsafe fn gather(isa: Self::Isa, base: *const f64, offsets: &[i32]) -> Self;

    /// The three components of a point per lane: `[c][l] = *base.offset(offsets[l] + c)`
    /// (`base` the first `f64` of a `[DVec3]`, `offsets[l]` three times a point index). Three
    /// [`LaneVec::gather`]s unless a lane type has a faster way.
    ///
    /// # Safety
    /// `offsets` holds at least [`LaneVec::WIDTH`] entries and the three `f64` from every
    /// `base.offset(offsets[l])` for l below it are readable.
    #[inline(always)]
    unsafe fn gather3(isa: Self::Isa, base: *const f64, offsets: &[i32]) -> [Self; 3] {
        // SAFETY: the caller's contract.
        unsafe {
            [
                Self::gather(isa, base, offsets),
                Self::gather(isa, base.add(1), offsets),
                Self::gather(isa, base.add(2), offsets),
            ]
        }
    }

    /// Adds lane l's `(v[0], v[1], v[2])` to the three `f64` at `base.offset(offsets[l])`
    /// (`base` the first `f64` of a `[DVec3]`, `offsets[l]` three times a point index), lane
    /// after lane, so lanes may name the same point. Scalar unless a lane type has a faster way.
    ///
    /// # Safety
    /// `offsets` holds at least [`LaneVec::WIDTH`] entries, the three `f64` from every
    /// `base.offset(offsets[l])` for l below it are writable, and nothing else accesses them
    /// meanwhile.
    #[inline(always)]
    unsafe fn scatter_add3(v: [Self; 3], base: *mut f64, offsets: &[i32]) {
        let offsets = &offsets[..Self::WIDTH];
        let mut a = [[0.0; 8]; 3];
        for (c, vc) in v.iter().enumerate() {
            vc.store(&mut a[c]);
        }
        for (l, &o) in offsets.iter().enumerate() {
            for (c, ac) in a.iter().enumerate() {
                // SAFETY: the caller's contract.
                unsafe { *base.offset(o as isize + c as isize) += ac[l] };
            }
        }
    }

    /// The largest lane (a NaN lane makes it NaN; callers compare with `<`, so a NaN never
    /// passes a check).
    #[inline(always)]
    fn max_lane(self) -> f64 {
        let mut a = [0.0; 8];
        self.store(&mut a);
        a[..Self::WIDTH]
            .iter()
            .copied()
            .fold(
                f64::NEG_INFINITY,
                |m, x| if x > m || x.is_nan() { x } else { m },
            )
    }

    /// The smallest lane (as [`LaneVec::max_lane`]).
    #[inline(always)]
    fn min_lane(self) -> f64 {
        let mut a = [0.0; 8];
        self.store(&mut a);
        a[..Self::WIDTH]
            .iter()
            .copied()
            .fold(
                f64::INFINITY,
                |m, x| if x < m || x.is_nan() { x } else { m },
            )
    }

    /// Applies `f` to each lane's row-major 3x3 matrix `m` (the rare scalar fallback of a
    /// vectorised formula), through stores and loads.
    #[inline(always)]
    fn map_matrix_lanes(
        isa: Self::Isa,
        m: &[Self; 9],
        f: impl Fn([f64; 9]) -> [f64; 9],
    ) -> [Self; 9] {
        let mut a = [[0.0; 8]; 9];
        for (k, v) in m.iter().enumerate() {
            v.store(&mut a[k]);
        }
        let mut out = [[0.0; 8]; 9];
        for l in 0..Self::WIDTH {
            let r = f(std::array::from_fn(|k| a[k][l]));
            for k in 0..9 {
                out[k][l] = r[k];
            }
        }
        std::array::from_fn(|k| Self::load(isa, &out[k]))
    }
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

impl Div for Plain8 {
    type Output = Plain8;
    #[inline(always)]
    fn div(self, o: Plain8) -> Plain8 {
        Plain8(std::array::from_fn(|l| self.0[l] / o.0[l]))
    }
}

impl Lane for Plain8 {
    type Isa = ();

    #[inline(always)]
    fn splat(_: (), v: f64) -> Plain8 {
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

impl LaneVec for Plain8 {
    const WIDTH: usize = 8;

    #[inline(always)]
    fn load(_: (), a: &[f64]) -> Plain8 {
        Plain8(a[..8].try_into().expect("eight lanes"))
    }

    #[inline(always)]
    fn store(self, a: &mut [f64]) {
        a[..8].copy_from_slice(&self.0);
    }

    #[inline(always)]
    unsafe fn gather(_: (), base: *const f64, offsets: &[i32]) -> Plain8 {
        let offsets = &offsets[..8];
        // SAFETY: every base.offset(offsets[l]) is readable (caller's contract).
        Plain8(std::array::from_fn(|l| unsafe {
            *base.offset(offsets[l] as isize)
        }))
    }
}

#[cfg(target_arch = "x86_64")]
pub(crate) use x86::{Ymm, Zmm};

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Lane, LaneVec};
    use crate::simd::isa::{Avx2Fma, Avx512};
    use std::arch::x86_64::{
        __m128i, __m256d, __m256i, __m512d, _mm_add_pd, _mm_add_sd, _mm_load_sd, _mm_loadu_pd,
        _mm_loadu_si128, _mm_store_sd, _mm_storeu_pd, _mm256_add_pd, _mm256_castpd256_pd128,
        _mm256_div_pd, _mm256_extractf128_pd, _mm256_fmadd_pd, _mm256_fmsub_pd,
        _mm256_i32gather_pd, _mm256_loadu_pd, _mm256_loadu_si256, _mm256_maskload_pd,
        _mm256_maskz_loadu_pd, _mm256_mul_pd, _mm256_permute2f128_pd, _mm256_set_epi64x,
        _mm256_set1_pd, _mm256_setzero_pd, _mm256_storeu_pd, _mm256_sub_pd, _mm256_unpackhi_pd,
        _mm256_unpacklo_pd, _mm512_add_pd, _mm512_castpd256_pd512, _mm512_castpd512_pd256,
        _mm512_div_pd, _mm512_extractf64x4_pd, _mm512_fmadd_pd, _mm512_fmsub_pd,
        _mm512_i32gather_pd, _mm512_insertf64x4, _mm512_loadu_pd, _mm512_mul_pd, _mm512_set1_pd,
        _mm512_storeu_pd, _mm512_sub_pd,
    };
    use std::ops::{Add, Div, Mul, Sub};

    /// Eight `f64` lanes in one AVX-512 register.
    ///
    /// Every operation is an AVX-512F instruction. Values are made only with an [`Avx512`]
    /// token, so they exist only on CPUs that have the instructions; the methods are
    /// `#[inline(always)]` so that they compile into the `#[target_feature]` kernels that call
    /// them (outside those, an operation is a call to an out-of-line instruction, still valid on
    /// this CPU).
    #[derive(Clone, Copy)]
    pub(crate) struct Zmm(__m512d);

    impl LaneVec for Zmm {
        const WIDTH: usize = 8;

        #[inline(always)]
        fn load(_: Avx512, a: &[f64]) -> Zmm {
            let a = &a[..8];
            // SAFETY: `a` is eight readable f64; AVX-512F per the token.
            Zmm(unsafe { _mm512_loadu_pd(a.as_ptr()) })
        }

        #[inline(always)]
        fn store(self, a: &mut [f64]) {
            let a = &mut a[..8];
            // SAFETY: `a` is eight writable f64; `self` exists, so AVX-512F is available.
            unsafe { _mm512_storeu_pd(a.as_mut_ptr(), self.0) }
        }

        #[inline(always)]
        unsafe fn gather(_: Avx512, base: *const f64, offsets: &[i32]) -> Zmm {
            let offsets = &offsets[..8];
            // SAFETY: offsets is eight i32; the addressed f64 are readable (caller's
            // contract); AVX-512F per the token.
            unsafe {
                let idx = _mm256_loadu_si256(offsets.as_ptr().cast::<__m256i>());
                Zmm(_mm512_i32gather_pd::<8>(idx, base))
            }
        }

        /// Eight masked loads of `x, y, z` (the fourth `f64` masked off: never read) and two
        /// 4x4 transposes joined, as [`Ymm`]'s: three hardware gathers of eight cost more
        /// (docs/benchmarks.md, "Point rows instead of gathers").
        #[inline(always)]
        unsafe fn gather3(_: Avx512, base: *const f64, offsets: &[i32]) -> [Zmm; 3] {
            let offsets = &offsets[..8];
            // SAFETY: AVX-512F and AVX-512VL per the token; each masked load reads the three
            // f64 at base + offsets[l], readable by the caller's contract, and never touches
            // the masked-off fourth (masked-off elements neither read nor fault).
            unsafe {
                let lo = rows4(base, [offsets[0], offsets[1], offsets[2], offsets[3]]);
                let hi = rows4(base, [offsets[4], offsets[5], offsets[6], offsets[7]]);
                // No closure: closures are not inlined into `target_feature` functions.
                [
                    Zmm(_mm512_insertf64x4::<1>(
                        _mm512_castpd256_pd512(lo[0]),
                        hi[0],
                    )),
                    Zmm(_mm512_insertf64x4::<1>(
                        _mm512_castpd256_pd512(lo[1]),
                        hi[1],
                    )),
                    Zmm(_mm512_insertf64x4::<1>(
                        _mm512_castpd256_pd512(lo[2]),
                        hi[2],
                    )),
                ]
            }
        }

        /// Two 4x4 transposes into point rows `x, y, z, 0`, each added to its point by
        /// [`add_row`].
        #[inline(always)]
        unsafe fn scatter_add3(v: [Zmm; 3], base: *mut f64, offsets: &[i32]) {
            let offsets = &offsets[..8];
            // SAFETY: AVX-512F and AVX-512VL exist (the values do); the masked loads and
            // stores touch only the three f64 at base + offsets[l], writable by the caller's
            // contract, one lane after the other.
            unsafe {
                for half in 0..2 {
                    let (x, y, z) = if half == 0 {
                        (
                            _mm512_castpd512_pd256(v[0].0),
                            _mm512_castpd512_pd256(v[1].0),
                            _mm512_castpd512_pd256(v[2].0),
                        )
                    } else {
                        (
                            _mm512_extractf64x4_pd::<1>(v[0].0),
                            _mm512_extractf64x4_pd::<1>(v[1].0),
                            _mm512_extractf64x4_pd::<1>(v[2].0),
                        )
                    };
                    let rows = point_rows4(x, y, z);
                    for (r, &o) in rows.iter().zip(&offsets[4 * half..4 * half + 4]) {
                        add_row(base.offset(o as isize), *r);
                    }
                }
            }
        }
    }

    /// Adds the first three `f64` of `r` to the three at `p`, as a pair `x, y` and a single
    /// `z`: plain loads and stores, which the next read of the same point takes from the store
    /// buffer (a masked store there stalls the read: 5 times slower in the linear kernel).
    ///
    /// # Safety
    /// AVX2; the three `f64` at `p` are writable.
    #[inline(always)]
    unsafe fn add_row(p: *mut f64, r: __m256d) {
        // SAFETY: the caller's contract.
        unsafe {
            let xy = _mm_add_pd(_mm_loadu_pd(p), _mm256_castpd256_pd128(r));
            _mm_storeu_pd(p, xy);
            let z = _mm_add_sd(_mm_load_sd(p.add(2)), _mm256_extractf128_pd::<1>(r));
            _mm_store_sd(p.add(2), z);
        }
    }

    /// Four point rows `[x_l, y_l, z_l, 0]` from the lanes of `x, y, z` (a 4x4 transpose).
    ///
    /// # Safety
    /// AVX2.
    #[inline(always)]
    unsafe fn point_rows4(x: __m256d, y: __m256d, z: __m256d) -> [__m256d; 4] {
        // SAFETY: the caller's contract.
        unsafe {
            let zero = _mm256_setzero_pd();
            let t0 = _mm256_unpacklo_pd(x, y); // x0 y0 x2 y2
            let t1 = _mm256_unpackhi_pd(x, y); // x1 y1 x3 y3
            let t2 = _mm256_unpacklo_pd(z, zero); // z0 0 z2 0
            let t3 = _mm256_unpackhi_pd(z, zero); // z1 0 z3 0
            [
                _mm256_permute2f128_pd::<0x20>(t0, t2),
                _mm256_permute2f128_pd::<0x20>(t1, t3),
                _mm256_permute2f128_pd::<0x31>(t0, t2),
                _mm256_permute2f128_pd::<0x31>(t1, t3),
            ]
        }
    }

    /// The components of four points, one lane each: `[c][l]` is component c of the point at
    /// `base + offsets[l]` (three f64), by four masked row loads and a 4x4 transpose.
    ///
    /// # Safety
    /// AVX-512F and AVX-512VL; the three f64 at every `base + offsets[l]` are readable.
    #[inline(always)]
    unsafe fn rows4(base: *const f64, offsets: [i32; 4]) -> [__m256d; 3] {
        // SAFETY: the caller's contract (masked-off elements neither read nor fault).
        unsafe {
            let r0 = _mm256_maskz_loadu_pd(0b0111, base.offset(offsets[0] as isize));
            let r1 = _mm256_maskz_loadu_pd(0b0111, base.offset(offsets[1] as isize));
            let r2 = _mm256_maskz_loadu_pd(0b0111, base.offset(offsets[2] as isize));
            let r3 = _mm256_maskz_loadu_pd(0b0111, base.offset(offsets[3] as isize));
            lanes_of_rows4([r0, r1, r2, r3])
        }
    }

    /// The 4x4 transpose of four point rows `r_l = [x_l, y_l, z_l, 0]`: `[x, y, z]`, one lane
    /// per point (the inverse of [`point_rows4`]).
    ///
    /// # Safety
    /// AVX2.
    #[inline(always)]
    unsafe fn lanes_of_rows4([r0, r1, r2, r3]: [__m256d; 4]) -> [__m256d; 3] {
        // SAFETY: the caller's contract.
        unsafe {
            let t0 = _mm256_unpacklo_pd(r0, r1); // x0 x1 z0 z1
            let t1 = _mm256_unpackhi_pd(r0, r1); // y0 y1 0 0
            let t2 = _mm256_unpacklo_pd(r2, r3); // x2 x3 z2 z3
            let t3 = _mm256_unpackhi_pd(r2, r3); // y2 y3 0 0
            [
                _mm256_permute2f128_pd::<0x20>(t0, t2),
                _mm256_permute2f128_pd::<0x20>(t1, t3),
                _mm256_permute2f128_pd::<0x31>(t0, t2),
            ]
        }
    }

    impl Add for Zmm {
        type Output = Zmm;
        #[inline(always)]
        fn add(self, o: Zmm) -> Zmm {
            // SAFETY: Zmm values are made only with an Avx512 token, so this CPU has AVX-512F.
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

    impl Div for Zmm {
        type Output = Zmm;
        #[inline(always)]
        fn div(self, o: Zmm) -> Zmm {
            // SAFETY: as in `add`.
            Zmm(unsafe { _mm512_div_pd(self.0, o.0) })
        }
    }

    impl Lane for Zmm {
        type Isa = Avx512;

        #[inline(always)]
        fn splat(_: Avx512, v: f64) -> Zmm {
            // SAFETY: the Avx512 token proves the CPU has AVX-512F.
            Zmm(unsafe { _mm512_set1_pd(v) })
        }

        #[inline(always)]
        fn madd<const FMA: bool>(a: Zmm, b: Zmm, c: Zmm) -> Zmm {
            // SAFETY: as in `add`; AVX-512F includes the fused multiply-adds.
            Zmm(unsafe { _mm512_fmadd_pd(a.0, b.0, c.0) })
        }

        #[inline(always)]
        fn msub<const FMA: bool>(a: Zmm, b: Zmm, c: Zmm) -> Zmm {
            // SAFETY: as in `madd`.
            Zmm(unsafe { _mm512_fmsub_pd(a.0, b.0, c.0) })
        }
    }

    /// Four `f64` lanes in one AVX2 register: a batch of eight elements runs in two parts.
    /// (Eight lanes in a pair of registers, the earlier design, left the kernels' 3x3 matrices
    /// in 18 of the 16 AVX2 registers and spilled: decisions.md, "StVK force kernel".)
    ///
    /// Every operation is an AVX2 or FMA instruction; values are made only with an [`Avx2Fma`]
    /// token, as for [`Zmm`].
    #[derive(Clone, Copy)]
    pub(crate) struct Ymm(__m256d);

    impl Add for Ymm {
        type Output = Ymm;
        #[inline(always)]
        fn add(self, o: Ymm) -> Ymm {
            // SAFETY: Ymm values are made only with an Avx2Fma token, so this CPU has AVX2 and FMA.
            Ymm(unsafe { _mm256_add_pd(self.0, o.0) })
        }
    }

    impl Sub for Ymm {
        type Output = Ymm;
        #[inline(always)]
        fn sub(self, o: Ymm) -> Ymm {
            // SAFETY: as in `add`.
            Ymm(unsafe { _mm256_sub_pd(self.0, o.0) })
        }
    }

    impl Mul for Ymm {
        type Output = Ymm;
        #[inline(always)]
        fn mul(self, o: Ymm) -> Ymm {
            // SAFETY: as in `add`.
            Ymm(unsafe { _mm256_mul_pd(self.0, o.0) })
        }
    }

    impl Div for Ymm {
        type Output = Ymm;
        #[inline(always)]
        fn div(self, o: Ymm) -> Ymm {
            // SAFETY: as in `add`.
            Ymm(unsafe { _mm256_div_pd(self.0, o.0) })
        }
    }

    impl Lane for Ymm {
        type Isa = Avx2Fma;

        #[inline(always)]
        fn splat(_: Avx2Fma, v: f64) -> Ymm {
            // SAFETY: the Avx2Fma token proves the CPU has AVX2.
            Ymm(unsafe { _mm256_set1_pd(v) })
        }

        #[inline(always)]
        fn madd<const FMA: bool>(a: Ymm, b: Ymm, c: Ymm) -> Ymm {
            // SAFETY: as in `add`; the token that made the values proves FMA.
            Ymm(unsafe { _mm256_fmadd_pd(a.0, b.0, c.0) })
        }

        #[inline(always)]
        fn msub<const FMA: bool>(a: Ymm, b: Ymm, c: Ymm) -> Ymm {
            // SAFETY: as in `madd`.
            Ymm(unsafe { _mm256_fmsub_pd(a.0, b.0, c.0) })
        }
    }

    impl LaneVec for Ymm {
        const WIDTH: usize = 4;

        #[inline(always)]
        fn load(_: Avx2Fma, a: &[f64]) -> Ymm {
            let a = &a[..4];
            // SAFETY: `a` is four readable f64; AVX2 per the token.
            Ymm(unsafe { _mm256_loadu_pd(a.as_ptr()) })
        }

        #[inline(always)]
        fn store(self, a: &mut [f64]) {
            let a = &mut a[..4];
            // SAFETY: `a` is four writable f64; `self` exists, so AVX2 is available.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), self.0) }
        }

        #[inline(always)]
        unsafe fn gather(_: Avx2Fma, base: *const f64, offsets: &[i32]) -> Ymm {
            let offsets = &offsets[..4];
            // SAFETY: offsets is four i32; the addressed f64 are readable (caller's
            // contract); AVX2 per the token.
            unsafe {
                let idx = _mm_loadu_si128(offsets.as_ptr().cast::<__m128i>());
                Ymm(_mm256_i32gather_pd::<8>(base, idx))
            }
        }

        /// Four masked loads of `x, y, z` (the fourth `f64` is masked off, so it is never read)
        /// and a 4x4 transpose: on AMD Zen 3 three hardware gathers of four cost about twice
        /// as much (the force kernels wait on them; docs/benchmarks.md).
        #[inline(always)]
        unsafe fn gather3(_: Avx2Fma, base: *const f64, offsets: &[i32]) -> [Ymm; 3] {
            let offsets = &offsets[..4];
            // SAFETY: AVX2 per the token; each masked load reads the three f64 at
            // base + offsets[l], readable by the caller's contract, and never touches the
            // masked-off fourth (masked-off elements of VMASKMOVPD neither read nor fault).
            unsafe {
                let mask = _mm256_set_epi64x(0, -1, -1, -1);
                // No closure: closures are not inlined into `target_feature` functions.
                let r0 = _mm256_maskload_pd(base.offset(offsets[0] as isize), mask);
                let r1 = _mm256_maskload_pd(base.offset(offsets[1] as isize), mask);
                let r2 = _mm256_maskload_pd(base.offset(offsets[2] as isize), mask);
                let r3 = _mm256_maskload_pd(base.offset(offsets[3] as isize), mask);
                let [x, y, z] = lanes_of_rows4([r0, r1, r2, r3]);
                [Ymm(x), Ymm(y), Ymm(z)]
            }
        }

        /// A 4x4 transpose into point rows, each added to its point by [`add_row`].
        #[inline(always)]
        unsafe fn scatter_add3(v: [Ymm; 3], base: *mut f64, offsets: &[i32]) {
            let offsets = &offsets[..4];
            // SAFETY: AVX2 exists (the values do); the loads and stores touch only the three
            // f64 at base + offsets[l], writable by the caller's contract, lane after lane.
            unsafe {
                let rows = point_rows4(v[0].0, v[1].0, v[2].0);
                for (r, &o) in rows.iter().zip(offsets) {
                    add_row(base.offset(o as isize), *r);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `gather3` and `scatter_add3` of a lane type against plain indexing, on points of which
    /// lanes 1, 4 and 6 name the same one (the scatter must add them all) and the last is the
    /// slice's end (the masked loads must not read past it).
    fn check<V: LaneVec>(isa: V::Isa) {
        let points: Vec<[f64; 3]> = (0..9)
            .map(|i| [1.0 + i as f64, -2.5 * i as f64, 0.125 + (i * i) as f64])
            .collect();
        let idx = [8usize, 2, 5, 0, 2, 7, 2, 3];
        let offsets: [i32; 8] = idx.map(|i| 3 * i as i32);
        let flat: Vec<f64> = points.iter().flatten().copied().collect();
        for part in (0..8).step_by(V::WIDTH) {
            // SAFETY: every offset names a whole point of `flat`.
            let g = unsafe { V::gather3(isa, flat.as_ptr(), &offsets[part..]) };
            for (c, gc) in g.iter().enumerate() {
                let mut a = [0.0; 8];
                gc.store(&mut a);
                for l in 0..V::WIDTH {
                    assert_eq!(a[l], points[idx[part + l]][c], "lane {l} component {c}");
                }
            }
            let lanes: [[f64; 8]; 3] =
                std::array::from_fn(|c| std::array::from_fn(|l| (10 * l + c) as f64 + 0.5));
            let v = lanes.map(|a| V::load(isa, &a));
            let mut out = flat.clone();
            // SAFETY: as above; `out` is borrowed here alone.
            unsafe { V::scatter_add3(v, out.as_mut_ptr(), &offsets[part..]) };
            let mut want = flat.clone();
            for l in 0..V::WIDTH {
                for c in 0..3 {
                    want[3 * idx[part + l] + c] += lanes[c][l];
                }
            }
            assert_eq!(out, want);
        }
    }

    #[test]
    fn every_lane_type_gathers_and_adds_points_as_plain_indexing_does() {
        check::<Plain8>(());
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = crate::simd::isa::Avx2Fma::detect() {
            check::<Ymm>(isa);
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = crate::simd::isa::Avx512::detect() {
            check::<Zmm>(isa);
        }
    }
}
