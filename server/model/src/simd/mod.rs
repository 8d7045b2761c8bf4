//! The SIMD layer: what the CPU can run ([`isa`]) and the lane types the element kernels are
//! written over ([`lanes`]).

pub(crate) mod isa;
pub(crate) mod lanes;

pub(crate) use isa::{has_avx2_fma, has_avx2_fma_f16c, has_avx512f};
pub(crate) use lanes::{Avx2Fma, Avx512, Lane, LaneVec, Plain8, Ymm, Zmm};
