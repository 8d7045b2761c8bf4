//! Meshfree (SPH-type) elasticity of the seeds' particle layer (seed 000 section 3.2, eq.
//! 23-29; time stepping eq. 33), in a total-Lagrangian form: neighbours, kernel gradients and
//! volumes are those of the rest configuration, the deformation gradient of particle `i` is a
//! kernel sum over its rest neighbours, and the elastic force is the exact negative gradient of
//! the discrete energy `sum_i V_i Psi(F_i)` (plus the hourglass energy of the corrected
//! variant), so that rigid motions are force-free, linear and angular momentum are conserved
//! and the forces are conservative.
//!
//! Two variants ([`MeshfreeVariant`]):
//! - `seed`: the seed's cone kernel (the "linear approximation of the Lennard-Jones potential",
//!   after eq. 24) and the plain kernel-sum gradient of eq. 25 (the moving-least-squares
//!   derivative of eq. 27-29 without correction), St. Venant-Kirchhoff stress (eq. 9) measured
//!   from the rest estimate of the strain. It fails the patch test near boundaries and has
//!   zero-energy (hourglass) modes.
//! - `corrected`: Wendland C2 kernel, Bonet-Lok gradient correction (first-order consistent: an
//!   affine field is reproduced exactly) and Ganzenmueller's hourglass control, any material law.
//!
//! Submodules: [`kernel`] (W and dW/dr), [`lattice`] (the regular sampling grid and neighbour
//! stencil), [`cloud`] (rest data of all particles and of one particle's term), [`block`] (the
//! run-time terms of a set of particles: forces, energy, critical time step), `stencil` (the
//! block's fast force loop on a dense local grid, four owners per vector).
//!
//! Neighbours: uses [`crate::material`]; used by [`crate::scene`] (parameters) and the hybrid
//! body [`crate::hybrid`].

pub mod block;
pub mod cloud;
pub mod kernel;
pub mod lattice;
mod stencil;

pub use block::{TermBlock, critical_time_step};
pub use cloud::ParticleCloud;
pub use kernel::{Kernel, KernelKind};
pub use lattice::Lattice;

/// Which meshfree formulation (module documentation). Scene names in parentheses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MeshfreeVariant {
    /// As the seed writes it (`"seed"`): cone kernel, uncorrected gradient, StVK.
    Seed,
    /// Bonet-Lok corrected gradient with hourglass control (`"corrected"`, the default).
    #[default]
    Corrected,
}

impl MeshfreeVariant {
    /// The scene-file name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Seed => "seed",
            Self::Corrected => "corrected",
        }
    }

    /// Parses a scene-file name; `None` if unknown.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Seed, Self::Corrected]
            .into_iter()
            .find(|v| v.name() == name)
    }
}

/// Parameters of a meshfree discretisation, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeshfreeParams {
    /// Formulation.
    pub variant: MeshfreeVariant,
    /// Kernel function (the seed's cone for `seed`, Wendland C2 for `corrected` by default).
    pub kernel: KernelKind,
    /// Lattice spacing `s` of the particles, m.
    pub spacing_m: f64,
    /// Smoothing length over spacing, `h / s` (support radius `2 h`); 1.0 gives the 26
    /// neighbours of the 3x3x3 cube.
    pub smoothing_ratio: f64,
    /// Dimensionless hourglass coefficient (Ganzenmueller 2015 uses 10 to 50 for his force
    /// form; ours is the energy form, see [`cloud`]); ignored by the seed variant.
    pub hourglass_coefficient: f64,
}

impl Default for MeshfreeParams {
    fn default() -> Self {
        Self {
            variant: MeshfreeVariant::Corrected,
            kernel: KernelKind::WendlandC2,
            spacing_m: 1e-3,
            smoothing_ratio: 1.0,
            hourglass_coefficient: 0.5,
        }
    }
}
