//! What the CPU can run: the fast builds of the hot loops that are written as plain Rust and
//! compiled a second time with `#[target_feature(enable = "avx2,fma")]` (or AVX-512) are
//! chosen here.
//!
//! Neighbours: none (the bottom layer); used by [`crate::meshfree::block`],
//! [`crate::integrate::condensed`] and the single-precision force kernel
//! (`element::kernels::single`).

/// Whether this CPU runs AVX2 and FMA (std caches the detection).
#[cfg(target_arch = "x86_64")]
pub(crate) fn has_avx2_fma() -> bool {
    std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
}

/// Whether this CPU runs AVX2 and FMA: never off x86-64.
#[cfg(not(target_arch = "x86_64"))]
pub(crate) fn has_avx2_fma() -> bool {
    false
}

/// Whether this CPU runs AVX-512F, AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
pub(crate) fn has_avx512f() -> bool {
    has_avx2_fma() && std::is_x86_feature_detected!("avx512f")
}

/// Whether this CPU runs AVX-512F, AVX2 and FMA: never off x86-64.
#[cfg(not(target_arch = "x86_64"))]
pub(crate) fn has_avx512f() -> bool {
    false
}

/// Whether this CPU runs AVX2, FMA and F16C (half-precision conversions).
#[cfg(target_arch = "x86_64")]
pub(crate) fn has_avx2_fma_f16c() -> bool {
    has_avx2_fma() && std::is_x86_feature_detected!("f16c")
}

/// Whether this CPU runs AVX2, FMA and F16C: never off x86-64.
#[cfg(not(target_arch = "x86_64"))]
pub(crate) fn has_avx2_fma_f16c() -> bool {
    false
}
