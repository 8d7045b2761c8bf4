//! The SIMD layer: what the CPU can run (the instruction-set tokens of [`isa`]), the lane
//! types the element kernels are written over ([`lanes`]) and the eight-lane `f32` type of
//! the meshfree stencil ([`lanes8`]) and the `f32` lanes of the single-precision kernel
//! ([`lanes_f32`], x86-64).
//!
//! **The rule** for every vectorised path of the crate: a vector value or a token exists only
//! after run-time detection (`detect`, the tokens' only maker; vector values are made from a
//! token); every `#[target_feature]` function takes the token of its features as an argument;
//! intrinsics appear only in this module or inside such a function; the call of a
//! `#[target_feature]` entry is the one `unsafe` block of its caller, commented "SAFETY: the
//! token". Operations that are unsafe for memory reasons (gathers and packings through raw
//! offsets) stay `unsafe fn` with their own `# Safety` contract.

pub(crate) mod isa;
pub(crate) mod lanes;
pub(crate) mod lanes8;
#[cfg(target_arch = "x86_64")]
pub(crate) mod lanes_f32;

pub(crate) use isa::{Avx2Fma, Avx2FmaF16c, Avx512};
pub(crate) use lanes::{Lane, LaneVec, Plain8, Ymm, Zmm};
#[cfg(target_arch = "x86_64")]
pub(crate) use lanes_f32::{F32Lanes, Y8, Z16};
#[cfg(target_arch = "x86_64")]
pub(crate) use lanes8::Ymm8;
pub(crate) use lanes8::{Lanes8, Plain8f, WIDTH as LANES8};
