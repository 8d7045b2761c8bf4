//! Time integrators: the seed's semi-implicit scheme and symplectic Euler.
//!
//! Placeholder; filled in by the FEM core change.

/// Which time integrator advances the FEM nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntegratorKind {
    /// Seed 000 eq. 34: explicit velocity predictor, then `v = (I - dt^2/m J_ii)^-1 v~` with the
    /// per-node 3x3 Jacobian `J_ii = dF_i/dx_i` precomputed at rest, then `x += dt v`.
    SemiImplicit,
    /// Symplectic (semi-implicit) Euler: `v += dt F/m`, `x += dt v`. The explicit reference.
    SymplecticEuler,
}

impl IntegratorKind {
    /// The name used in scene files (`semi-implicit`, `symplectic-euler`).
    pub fn name(self) -> &'static str {
        match self {
            Self::SemiImplicit => "semi-implicit",
            Self::SymplecticEuler => "symplectic-euler",
        }
    }
}

/// Integrator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntegratorParams {
    /// Which scheme.
    pub kind: IntegratorKind,
    /// Servo tick (one call of `Simulation::tick`), s. Default 1 ms.
    pub tick_s: f64,
    /// Fixed sub-steps per tick; `None` chooses the fewest that keep the sub-step below
    /// `safety_factor` times the critical time step.
    pub substeps: Option<u32>,
    /// Largest sub-step count allowed; a configuration needing more is rejected as unstable.
    pub max_substeps: u32,
    /// Fraction of the critical time step used when sub-steps are automatic (0, 1].
    pub safety_factor: f64,
}

impl Default for IntegratorParams {
    fn default() -> Self {
        Self {
            kind: IntegratorKind::SemiImplicit,
            tick_s: 1e-3,
            substeps: None,
            max_substeps: 64,
            safety_factor: 0.8,
        }
    }
}
