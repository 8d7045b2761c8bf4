//! Eight `f32` lanes for the meshfree stencil ([`crate::meshfree`]'s group loop): the trait
//! [`Lanes8`] (arithmetic, fused multiply-adds, the one-cell shifts along x) and its plain
//! build [`Plain8f`]; the AVX2 + FMA build is [`Ymm8`], whose
//! values exist only after [`crate::simd::Avx2Fma::detect`] returned a token.
//!
//! Single precision: the stencil works on displacements from rest (a few millimetres, so
//! single precision keeps them to about 1e-10 m) and its forces agree with the
//! double-precision general loop to a few parts in a million of the largest (unit test in
//! `meshfree/block.rs`); eight lanes do about twice the work per instruction of the four
//! `f64` lanes it replaced (docs/benchmarks.md, "The stencil loop in eight single-precision
//! lanes").

/// Lanes of a [`Lanes8`] vector (the meshfree stencil's group width follows it).
pub(crate) const WIDTH: usize = 8;

/// Eight f32 lanes: the plain build ([`Plain8f`]) and the AVX2 + FMA one ([`Ymm8`], made only
/// with an [`crate::simd::Avx2Fma`] token), behind one trait so that the meshfree stencil's
/// group loop is written once.
pub(crate) trait Lanes8: Copy {
    /// The proof that the CPU runs this lane type (a token for [`Ymm8`]).
    type Isa: Copy;
    fn zero(isa: Self::Isa) -> Self;
    /// Every lane `v`, rounded to single precision.
    fn splat(isa: Self::Isa, v: f64) -> Self;
    /// Lanes `a[i..i + 8]`.
    ///
    /// # Panics
    /// If `a` is shorter than `i + 8`.
    fn load(isa: Self::Isa, a: &[f32], i: usize) -> Self;
    fn from_array(isa: Self::Isa, v: [f32; WIDTH]) -> Self;
    /// Into `a[i..i + 8]`.
    ///
    /// # Panics
    /// If `a` is shorter than `i + 8`.
    fn store(self, a: &mut [f32], i: usize);
    /// [`Lanes8::load`] without the bounds check (the meshfree group loop checks a group's
    /// whole window once instead of each of its 240 or so loads and stores).
    ///
    /// # Safety
    /// `i + 8 <= a.len()`.
    unsafe fn load_unchecked(isa: Self::Isa, a: &[f32], i: usize) -> Self;
    /// [`Lanes8::store`] without the bounds check.
    ///
    /// # Safety
    /// `i + 8 <= a.len()`.
    unsafe fn store_unchecked(self, a: &mut [f32], i: usize);
    fn to_array(self) -> [f32; WIDTH];
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    /// `a b + c`.
    fn madd(a: Self, b: Self, c: Self) -> Self;
    /// `c - a b`.
    fn nmadd(a: Self, b: Self, c: Self) -> Self;
    /// `a b - c`.
    fn msub(a: Self, b: Self, c: Self) -> Self;
    /// `-self` (exact: the sign bits flipped).
    fn neg(self) -> Self;
    /// Moved one cell down (the forces of offset -1 along x): `([v1, .., v7, 0], [0, .., 0,
    /// v0])`, the parts in the same chunk of eight cells and in the chunk before.
    fn shift_down(self) -> (Self, Self);
    /// Moved one cell up (offset +1 along x): `([0, v0, .., v6], [v7, 0, .., 0])`, the parts
    /// in the same chunk and in the chunk after.
    fn shift_up(self) -> (Self, Self);
}

/// Eight plain f32 lanes.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Plain8f([f32; WIDTH]);

impl Plain8f {
    /// Lane-wise `op`.
    #[inline(always)]
    fn map2(self, o: Plain8f, op: impl Fn(f32, f32) -> f32) -> Plain8f {
        let (a, b) = (self.0, o.0);
        Plain8f([
            op(a[0], b[0]),
            op(a[1], b[1]),
            op(a[2], b[2]),
            op(a[3], b[3]),
            op(a[4], b[4]),
            op(a[5], b[5]),
            op(a[6], b[6]),
            op(a[7], b[7]),
        ])
    }
}

impl Lanes8 for Plain8f {
    type Isa = ();

    #[inline(always)]
    fn zero(_: ()) -> Plain8f {
        Plain8f([0.0; WIDTH])
    }

    #[inline(always)]
    fn splat(_: (), v: f64) -> Plain8f {
        Plain8f([v as f32; WIDTH])
    }

    #[inline(always)]
    fn load(_: (), a: &[f32], i: usize) -> Plain8f {
        Plain8f(a[i..i + 8].try_into().expect("eight lanes"))
    }

    #[inline(always)]
    fn from_array(_: (), v: [f32; WIDTH]) -> Plain8f {
        Plain8f(v)
    }

    #[inline(always)]
    fn store(self, a: &mut [f32], i: usize) {
        a[i..i + 8].copy_from_slice(&self.0);
    }

    #[inline(always)]
    unsafe fn load_unchecked(_: (), a: &[f32], i: usize) -> Plain8f {
        debug_assert!(i + 8 <= a.len());
        // SAFETY: `i + 8 <= a.len()` (the caller's contract).
        Plain8f(unsafe { *a.as_ptr().add(i).cast::<[f32; WIDTH]>() })
    }

    #[inline(always)]
    unsafe fn store_unchecked(self, a: &mut [f32], i: usize) {
        debug_assert!(i + 8 <= a.len());
        // SAFETY: `i + 8 <= a.len()` (the caller's contract).
        unsafe { *a.as_mut_ptr().add(i).cast::<[f32; WIDTH]>() = self.0 };
    }

    #[inline(always)]
    fn to_array(self) -> [f32; WIDTH] {
        self.0
    }

    #[inline(always)]
    fn add(self, o: Plain8f) -> Plain8f {
        self.map2(o, |a, b| a + b)
    }

    #[inline(always)]
    fn sub(self, o: Plain8f) -> Plain8f {
        self.map2(o, |a, b| a - b)
    }

    #[inline(always)]
    fn mul(self, o: Plain8f) -> Plain8f {
        self.map2(o, |a, b| a * b)
    }

    #[inline(always)]
    fn madd(a: Plain8f, b: Plain8f, c: Plain8f) -> Plain8f {
        a.mul(b).add(c)
    }

    #[inline(always)]
    fn nmadd(a: Plain8f, b: Plain8f, c: Plain8f) -> Plain8f {
        c.sub(a.mul(b))
    }

    #[inline(always)]
    fn msub(a: Plain8f, b: Plain8f, c: Plain8f) -> Plain8f {
        a.mul(b).sub(c)
    }

    #[inline(always)]
    fn neg(self) -> Plain8f {
        Plain8f(self.0.map(|a| -a))
    }

    #[inline(always)]
    fn shift_down(self) -> (Plain8f, Plain8f) {
        let (mut c, mut lo) = ([0.0; WIDTH], [0.0; WIDTH]);
        c[..7].copy_from_slice(&self.0[1..]);
        lo[7] = self.0[0];
        (Plain8f(c), Plain8f(lo))
    }

    #[inline(always)]
    fn shift_up(self) -> (Plain8f, Plain8f) {
        let (mut c, mut hi) = ([0.0; WIDTH], [0.0; WIDTH]);
        c[1..].copy_from_slice(&self.0[..7]);
        hi[0] = self.0[7];
        (Plain8f(c), Plain8f(hi))
    }
}

/// Eight f32 lanes in an AVX2 register, for the meshfree stencil.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub(crate) struct Ymm8(std::arch::x86_64::__m256);

/// [`Lanes8`] on [`Ymm8`]: the meshfree stencil's AVX2 + FMA lanes. Every intrinsic call is
/// sound because a `Ymm8` value exists only after [`crate::simd::Avx2Fma::detect`] returned a
/// token (its constructors take it), and loads and stores check their slice bounds first (the
/// unchecked ones leave it to their callers' contract).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{Lanes8, WIDTH, Ymm8 as Y8};
    use crate::simd::isa::Avx2Fma;

    /// `v`'s lanes permuted by `from` (lane `l` takes lane `from[l]`), in two parts: the
    /// lanes of mask `ZERO_A` cleared in the first, those of `ZERO_B` in the second (blends
    /// with zero).
    #[inline(always)]
    fn rotated_parts<const ZERO_A: i32, const ZERO_B: i32>(v: Y8, from: [i32; WIDTH]) -> (Y8, Y8) {
        // SAFETY: `v` exists, so the CPU runs AVX2.
        unsafe {
            let idx = _mm256_loadu_si256(from.as_ptr().cast());
            let r = _mm256_permutevar8x32_ps(v.0, idx);
            let z = _mm256_setzero_ps();
            (
                Y8(_mm256_blend_ps::<ZERO_A>(r, z)),
                Y8(_mm256_blend_ps::<ZERO_B>(r, z)),
            )
        }
    }

    impl Lanes8 for Y8 {
        type Isa = Avx2Fma;

        #[inline(always)]
        fn zero(_: Avx2Fma) -> Y8 {
            // SAFETY (every intrinsic below): the token proves AVX2 and FMA, and a `Ymm8`
            // value exists only with it.
            Y8(unsafe { _mm256_setzero_ps() })
        }

        #[inline(always)]
        fn splat(_: Avx2Fma, v: f64) -> Y8 {
            Y8(unsafe { _mm256_set1_ps(v as f32) })
        }

        #[inline(always)]
        fn load(_: Avx2Fma, a: &[f32], i: usize) -> Y8 {
            let s = &a[i..i + 8];
            Y8(unsafe { _mm256_loadu_ps(s.as_ptr()) })
        }

        #[inline(always)]
        fn from_array(_: Avx2Fma, v: [f32; WIDTH]) -> Y8 {
            Y8(unsafe { _mm256_loadu_ps(v.as_ptr()) })
        }

        #[inline(always)]
        fn store(self, a: &mut [f32], i: usize) {
            let s = &mut a[i..i + 8];
            unsafe { _mm256_storeu_ps(s.as_mut_ptr(), self.0) }
        }

        #[inline(always)]
        unsafe fn load_unchecked(_: Avx2Fma, a: &[f32], i: usize) -> Y8 {
            debug_assert!(i + 8 <= a.len());
            // SAFETY: `a[i..i + 8]` is readable (the caller's contract).
            Y8(unsafe { _mm256_loadu_ps(a.as_ptr().add(i)) })
        }

        #[inline(always)]
        unsafe fn store_unchecked(self, a: &mut [f32], i: usize) {
            debug_assert!(i + 8 <= a.len());
            // SAFETY: `a[i..i + 8]` is writable (the caller's contract).
            unsafe { _mm256_storeu_ps(a.as_mut_ptr().add(i), self.0) }
        }

        #[inline(always)]
        fn to_array(self) -> [f32; WIDTH] {
            let mut v = [0.0; WIDTH];
            unsafe { _mm256_storeu_ps(v.as_mut_ptr(), self.0) };
            v
        }

        #[inline(always)]
        fn add(self, o: Y8) -> Y8 {
            Y8(unsafe { _mm256_add_ps(self.0, o.0) })
        }

        #[inline(always)]
        fn sub(self, o: Y8) -> Y8 {
            Y8(unsafe { _mm256_sub_ps(self.0, o.0) })
        }

        #[inline(always)]
        fn mul(self, o: Y8) -> Y8 {
            Y8(unsafe { _mm256_mul_ps(self.0, o.0) })
        }

        #[inline(always)]
        fn madd(a: Y8, b: Y8, c: Y8) -> Y8 {
            Y8(unsafe { _mm256_fmadd_ps(a.0, b.0, c.0) })
        }

        #[inline(always)]
        fn nmadd(a: Y8, b: Y8, c: Y8) -> Y8 {
            Y8(unsafe { _mm256_fnmadd_ps(a.0, b.0, c.0) })
        }

        #[inline(always)]
        fn msub(a: Y8, b: Y8, c: Y8) -> Y8 {
            Y8(unsafe { _mm256_fmsub_ps(a.0, b.0, c.0) })
        }

        #[inline(always)]
        fn neg(self) -> Y8 {
            Y8(unsafe { _mm256_xor_ps(self.0, _mm256_set1_ps(-0.0)) })
        }

        #[inline(always)]
        fn shift_down(self) -> (Y8, Y8) {
            // Rotated one lane down ([v1, .., v7, v0]): lane 7 is the chunk before's.
            rotated_parts::<0b1000_0000, 0b0111_1111>(self, [1, 2, 3, 4, 5, 6, 7, 0])
        }

        #[inline(always)]
        fn shift_up(self) -> (Y8, Y8) {
            // Rotated one lane up ([v7, v0, .., v6]): lane 0 is the chunk after's.
            rotated_parts::<0b0000_0001, 0b1111_1110>(self, [7, 0, 1, 2, 3, 4, 5, 6])
        }
    }
}
