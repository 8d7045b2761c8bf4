//! What the CPU can run: one *instruction-set token* per instruction set the hot loops are
//! compiled a second time for (`#[target_feature(enable = "avx2,fma")]`, AVX-512, F16C).
//!
//! A token is a zero-sized proof: its only maker is `detect`, which returns `Some` only on a
//! CPU that has every feature the token names, so a function that takes a token by value may
//! call the matching `#[target_feature]` code without another check. On other architectures
//! the same names exist and `detect` returns `None`, so fields of type `Option<Token>` need no
//! `cfg`. No `bool` stands for a CPU feature anywhere: callers hold `Option<Token>`.
//!
//! Neighbours: none (the bottom layer); the lane types of [`crate::simd::lanes`] are made from
//! these tokens.

/// Proof that this CPU runs AVX2 and FMA (x86-64-v3's floating-point part).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Avx2Fma(());

/// Proof that this CPU runs AVX2, FMA and F16C (half-precision conversions).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Avx2FmaF16c(());

/// Proof that this CPU runs AVX-512F, AVX-512VL, AVX2 and FMA.
///
/// VL is required besides F so that one token serves every AVX-512 kernel (the 256-bit forms
/// of AVX-512 instructions need it); every AVX-512 CPU since Skylake-SP has both, and the
/// only ones with F but not VL (Xeon Phi) run the AVX2 builds instead.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Avx512(());

impl Avx2Fma {
    /// The token, when the CPU has AVX2 and FMA (std caches the detection); never off x86-64.
    #[inline]
    pub(crate) fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            (std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"))
                .then_some(Self(()))
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            None
        }
    }
}

impl Avx2FmaF16c {
    /// The token, when the CPU has AVX2, FMA and F16C; never off x86-64.
    #[inline]
    pub(crate) fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            Avx2Fma::detect()
                .filter(|_| std::is_x86_feature_detected!("f16c"))
                .map(|_| Self(()))
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            None
        }
    }
}

impl Avx512 {
    /// The token, when the CPU has AVX-512F, AVX-512VL, AVX2 and FMA; never off x86-64.
    #[inline]
    pub(crate) fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            Avx2Fma::detect()
                .filter(|_| {
                    std::is_x86_feature_detected!("avx512f")
                        && std::is_x86_feature_detected!("avx512vl")
                })
                .map(|_| Self(()))
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            None
        }
    }

    /// The AVX2 and FMA part of the proof.
    #[inline]
    pub(crate) fn avx2_fma(self) -> Avx2Fma {
        Avx2Fma(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The tokens nest as their features do: a richer token implies the poorer ones.
    #[test]
    fn tokens_nest_as_their_features() {
        if Avx512::detect().is_some() || Avx2FmaF16c::detect().is_some() {
            assert!(Avx2Fma::detect().is_some());
        }
        #[cfg(target_arch = "x86_64")]
        assert_eq!(
            Avx2Fma::detect().is_some(),
            std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
        );
    }
}
