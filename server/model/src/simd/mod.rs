//! The SIMD layer: what the CPU can run (the instruction-set tokens of [`isa`]) and the lane
//! types the element kernels are written over ([`lanes`]).

pub(crate) mod isa;
pub(crate) mod lanes;

#[allow(unused_imports)] // Avx2FmaF16c: first caller in issue 49 step 2d
pub(crate) use isa::{Avx2Fma, Avx2FmaF16c, Avx512, has_avx2_fma, has_avx2_fma_f16c, has_avx512f};
pub(crate) use lanes::{Lane, LaneVec, Plain8, Ymm, Zmm};
