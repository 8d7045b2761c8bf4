//! Four `f64` lanes for the meshfree stencil ([`crate::meshfree`]'s group loop): the trait
//! [`Lanes4`] (arithmetic, fused multiply-adds, the one-cell shifts along x) and its plain
//! build [`Plain4`]; the AVX2 + FMA build is [`crate::simd::Ymm`] (`simd/lanes.rs`), whose
//! values exist only after [`crate::simd::Avx2Fma::detect`] returned a token.

/// Four f64 lanes: the plain build ([`Plain4`]) and the AVX2 + FMA one (`Ymm`, made only
/// with an [`crate::simd::Avx2Fma`] token), behind one trait so that the meshfree stencil's
/// group loop is written once.
pub(crate) trait Lanes4: Copy {
    /// The proof that the CPU runs this lane type (a token for `Ymm`).
    type Isa: Copy;
    fn zero(isa: Self::Isa) -> Self;
    fn splat(isa: Self::Isa, v: f64) -> Self;
    /// Lanes `a[i..i + 4]`.
    ///
    /// # Panics
    /// If `a` is shorter than `i + 4`.
    fn load(isa: Self::Isa, a: &[f64], i: usize) -> Self;
    fn from_array(isa: Self::Isa, v: [f64; 4]) -> Self;
    /// Into `a[i..i + 4]`.
    ///
    /// # Panics
    /// If `a` is shorter than `i + 4`.
    fn store(self, a: &mut [f64], i: usize);
    /// [`Lanes4::load`] without the bounds check (the meshfree group loop checks a group's
    /// whole window once instead of each of its 240 or so loads and stores).
    ///
    /// # Safety
    /// `i + 4 <= a.len()`.
    unsafe fn load_unchecked(isa: Self::Isa, a: &[f64], i: usize) -> Self;
    /// [`Lanes4::store`] without the bounds check.
    ///
    /// # Safety
    /// `i + 4 <= a.len()`.
    unsafe fn store_unchecked(self, a: &mut [f64], i: usize);
    fn to_array(self) -> [f64; 4];
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
    /// Moved one cell down (the forces of offset -1 along x): `([v1, v2, v3, 0], [0, 0, 0, v0])`,
    /// the parts in the same chunk of four cells and in the chunk before.
    fn shift_down(self) -> (Self, Self);
    /// Moved one cell up (offset +1 along x): `([0, v0, v1, v2], [v3, 0, 0, 0])`, the parts in
    /// the same chunk and in the chunk after.
    fn shift_up(self) -> (Self, Self);
}

/// Four plain f64 lanes.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Plain4([f64; 4]);

impl Lanes4 for Plain4 {
    type Isa = ();

    #[inline(always)]
    fn zero(_: ()) -> Plain4 {
        Plain4([0.0; 4])
    }

    #[inline(always)]
    fn splat(_: (), v: f64) -> Plain4 {
        Plain4([v; 4])
    }

    #[inline(always)]
    fn load(_: (), a: &[f64], i: usize) -> Plain4 {
        let s = &a[i..i + 4];
        Plain4([s[0], s[1], s[2], s[3]])
    }

    #[inline(always)]
    fn from_array(_: (), v: [f64; 4]) -> Plain4 {
        Plain4(v)
    }

    #[inline(always)]
    fn store(self, a: &mut [f64], i: usize) {
        a[i..i + 4].copy_from_slice(&self.0);
    }

    #[inline(always)]
    unsafe fn load_unchecked(_: (), a: &[f64], i: usize) -> Plain4 {
        debug_assert!(i + 4 <= a.len());
        // SAFETY: `i + 4 <= a.len()` (the caller's contract).
        unsafe {
            Plain4([
                *a.get_unchecked(i),
                *a.get_unchecked(i + 1),
                *a.get_unchecked(i + 2),
                *a.get_unchecked(i + 3),
            ])
        }
    }

    #[inline(always)]
    unsafe fn store_unchecked(self, a: &mut [f64], i: usize) {
        debug_assert!(i + 4 <= a.len());
        // SAFETY: `i + 4 <= a.len()` (the caller's contract).
        unsafe { a.get_unchecked_mut(i..i + 4) }.copy_from_slice(&self.0);
    }

    #[inline(always)]
    fn to_array(self) -> [f64; 4] {
        self.0
    }

    #[inline(always)]
    fn add(self, o: Plain4) -> Plain4 {
        let (a, b) = (self.0, o.0);
        Plain4([a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]])
    }

    #[inline(always)]
    fn sub(self, o: Plain4) -> Plain4 {
        let (a, b) = (self.0, o.0);
        Plain4([a[0] - b[0], a[1] - b[1], a[2] - b[2], a[3] - b[3]])
    }

    #[inline(always)]
    fn mul(self, o: Plain4) -> Plain4 {
        let (a, b) = (self.0, o.0);
        Plain4([a[0] * b[0], a[1] * b[1], a[2] * b[2], a[3] * b[3]])
    }

    #[inline(always)]
    fn madd(a: Plain4, b: Plain4, c: Plain4) -> Plain4 {
        a.mul(b).add(c)
    }

    #[inline(always)]
    fn nmadd(a: Plain4, b: Plain4, c: Plain4) -> Plain4 {
        c.sub(a.mul(b))
    }

    #[inline(always)]
    fn msub(a: Plain4, b: Plain4, c: Plain4) -> Plain4 {
        a.mul(b).sub(c)
    }

    #[inline(always)]
    fn neg(self) -> Plain4 {
        let a = self.0;
        Plain4([-a[0], -a[1], -a[2], -a[3]])
    }

    #[inline(always)]
    fn shift_down(self) -> (Plain4, Plain4) {
        let v = self.0;
        (
            Plain4([v[1], v[2], v[3], 0.0]),
            Plain4([0.0, 0.0, 0.0, v[0]]),
        )
    }

    #[inline(always)]
    fn shift_up(self) -> (Plain4, Plain4) {
        let v = self.0;
        (
            Plain4([0.0, v[0], v[1], v[2]]),
            Plain4([v[3], 0.0, 0.0, 0.0]),
        )
    }
}
