//! Smoothing kernels `W(r, h)` with compact support `2 h` (seed 000 eq. 23-25), normalised so
//! that `integral W dV = 1`.
//!
//! - [`KernelKind::SeedLinear`]: the seed's "linear approximation of the Lennard-Jones
//!   potential which fulfils kernel requirements" (section 3.2, after eq. 24): a cone,
//!   `W = 3 / (pi R^3) (1 - r / R)` for `r < R = 2 h`, positive, decreasing, compactly
//!   supported.
//! - [`KernelKind::WendlandC2`]: Wendland's C2 kernel, `W = 21 / (16 pi h^3) (1 - q/2)^4
//!   (2 q + 1)`, `q = r / h`, smooth at the origin and at the rim (the corrected variant's).
//!
//! Neighbours: used by [`super::cloud`] to precompute kernel gradients of each particle pair.

use std::f64::consts::PI;

/// Which kernel function.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KernelKind {
    /// The seed's linear (cone) kernel.
    SeedLinear,
    /// Wendland C2.
    WendlandC2,
}

impl KernelKind {
    /// The scene-file name: `"seed-linear"` or `"wendland-c2"`.
    pub fn name(self) -> &'static str {
        match self {
            Self::SeedLinear => "seed-linear",
            Self::WendlandC2 => "wendland-c2",
        }
    }

    /// Parses a scene-file name; `None` if unknown.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::SeedLinear, Self::WendlandC2]
            .into_iter()
            .find(|k| k.name() == name)
    }

    /// The variant's default kernel: the seed's cone for `seed`, Wendland C2 for `corrected`.
    pub fn default_for(variant: super::MeshfreeVariant) -> Self {
        match variant {
            super::MeshfreeVariant::Seed => Self::SeedLinear,
            super::MeshfreeVariant::Corrected => Self::WendlandC2,
        }
    }
}

/// A kernel of one kind and smoothing length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kernel {
    /// Kernel function.
    pub kind: KernelKind,
    /// Smoothing length `h`, m; the support radius is `2 h`.
    pub smoothing_length_m: f64,
}

impl Kernel {
    /// Support radius `2 h`, m.
    #[inline]
    pub fn support_m(&self) -> f64 {
        2.0 * self.smoothing_length_m
    }

    /// `W(r)`, 1/m^3 (zero for `r >= 2 h`).
    #[inline]
    pub fn value(&self, r: f64) -> f64 {
        let h = self.smoothing_length_m;
        match self.kind {
            KernelKind::SeedLinear => {
                let big_r = 2.0 * h;
                if r >= big_r {
                    0.0
                } else {
                    3.0 / (PI * big_r * big_r * big_r) * (1.0 - r / big_r)
                }
            }
            KernelKind::WendlandC2 => {
                let q = r / h;
                if q >= 2.0 {
                    0.0
                } else {
                    let a = 1.0 - 0.5 * q;
                    21.0 / (16.0 * PI * h * h * h) * a * a * a * a * (2.0 * q + 1.0)
                }
            }
        }
    }

    /// `dW/dr`, 1/m^4 (zero for `r >= 2 h`; the cone's slope at `r = 0` is its one-sided value).
    #[inline]
    pub fn slope(&self, r: f64) -> f64 {
        let h = self.smoothing_length_m;
        match self.kind {
            KernelKind::SeedLinear => {
                let big_r = 2.0 * h;
                if r >= big_r {
                    0.0
                } else {
                    -3.0 / (PI * big_r * big_r * big_r * big_r)
                }
            }
            KernelKind::WendlandC2 => {
                let q = r / h;
                if q >= 2.0 {
                    0.0
                } else {
                    // d/dq [(1 - q/2)^4 (2q + 1)] = -5 q (1 - q/2)^3
                    let a = 1.0 - 0.5 * q;
                    -21.0 / (16.0 * PI * h * h * h * h) * 5.0 * q * a * a * a
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both kernels integrate to one over their support and their slope is the derivative of
    /// their value.
    #[test]
    fn kernels_are_normalised_and_consistent() {
        for kind in [KernelKind::SeedLinear, KernelKind::WendlandC2] {
            let k = Kernel {
                kind,
                smoothing_length_m: 0.7e-3,
            };
            let n = 200_000;
            let dr = k.support_m() / n as f64;
            let integral: f64 = (0..n)
                .map(|i| {
                    let r = (i as f64 + 0.5) * dr;
                    4.0 * PI * r * r * k.value(r) * dr
                })
                .sum();
            assert!((integral - 1.0).abs() < 1e-8, "{kind:?}: {integral}");
            for r in [0.1e-3, 0.5e-3, 1.1e-3] {
                let e = 1e-9;
                let fd = (k.value(r + e) - k.value(r - e)) / (2.0 * e);
                assert!(
                    (fd - k.slope(r)).abs() <= 1e-6 * k.slope(r).abs(),
                    "{kind:?} at {r}"
                );
            }
        }
    }
}
