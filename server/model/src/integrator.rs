//! Time integrators: the seed's semi-implicit scheme (seed 000 eq. 34) and symplectic Euler,
//! the critical (Courant) time step, and sub-stepping of a servo tick.
//!
//! Neighbours: [`crate::fem`] provides forces, masses and the rest Jacobian blocks;
//! [`crate::sim`] calls [`integrate_nodes`] once per sub-step.

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::fem::{CLAMPED, FemModel, apply_constraint};
use crate::material::MaterialParams;

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
    /// Fraction of the critical time step used when sub-steps are automatic (0, 1]. The
    /// critical step is computed at rest, but St. Venant-Kirchhoff stiffens under stretch (the
    /// tangent grows by about `(3 lambda^2 - 1) / 2` at stretch `lambda`), so a probe pressing a
    /// few millimetres into soft tissue needs margin: 0.5 kept every LV mesh (1k to 18k tets)
    /// stable under a 3.7 mm indentation with both integrators; 0.6 did not for the
    /// semi-implicit scheme on 18k tets.
    pub safety_factor: f64,
}

impl Default for IntegratorParams {
    fn default() -> Self {
        Self {
            kind: IntegratorKind::SemiImplicit,
            tick_s: 1e-3,
            substeps: None,
            max_substeps: 64,
            safety_factor: 0.5,
        }
    }
}

/// How a servo tick is divided: `substeps` model steps of `sub_dt_s` each.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepPlan {
    /// Model steps per servo tick.
    pub substeps: u32,
    /// Model step, s (`tick_s / substeps`).
    pub sub_dt_s: f64,
    /// Stability limit of the integrator on this mesh and material, s (`f64::INFINITY` when the
    /// analysis finds none).
    pub critical_dt_s: f64,
}

/// Stiffness-proportional damping factor `beta` (s) bounding the viscous stress of eq. 11 at
/// rest: the viscous damping matrix is the stiffness matrix with `(lambda, mu)` replaced by
/// `(2 phi, 2 psi)`, so `D <= beta K` with `beta = max(2 phi / lambda, 2 psi / mu)`.
pub fn viscous_beta_s(m: &MaterialParams) -> f64 {
    let a = if m.lambda_pa > 0.0 {
        2.0 * m.phi_pa_s / m.lambda_pa
    } else {
        0.0
    };
    a.max(2.0 * m.psi_pa_s / m.mu_pa)
}

/// Critical (Courant) time step of `kind` on `fem`, s.
///
/// - Symplectic Euler: `dt_crit = (2 / omega_max) (sqrt(1 + xi^2) - xi)` with
///   `omega_max^2 = lambda_max(M^-1 K)` from power iteration on the assembled-free stiffness
///   action and `xi = beta omega_max / 2` for the viscous stress ([`viscous_beta_s`]).
/// - Semi-implicit (seed 000 eq. 34): a modal analysis of the scheme,
///   `M (v' - v) = -dt K x - dt^2 K_D v'`, is stable when `dt^2 (omega^2 - 2 d) <= 4` where
///   `d` is the Rayleigh quotient of the block diagonal `K_D`; so
///   `dt_crit = 2 / sqrt(lambda_max(M^-1 (K - 2 K_D)))`, infinite when that is not positive.
///   This is exact for commuting `K`, `K_D` and a good estimate otherwise (hence the safety factor).
pub fn critical_time_step(fem: &FemModel, kind: IntegratorKind) -> f64 {
    let beta = viscous_beta_s(&fem.material);
    let damped = |w2: f64| {
        if w2 <= 0.0 {
            return f64::INFINITY;
        }
        let w = w2.sqrt();
        let xi = beta * w / 2.0;
        2.0 / w * ((1.0 + xi * xi).sqrt() - xi)
    };
    match kind {
        IntegratorKind::SymplecticEuler => damped(fem.max_eigenvalue(0.0, 300)),
        IntegratorKind::SemiImplicit => damped(fem.max_eigenvalue(2.0, 300)),
    }
}

/// Chooses the sub-steps of a servo tick.
///
/// # Errors
/// [`ModelError::Unstable`] when fixed `substeps` give a step above `critical_dt_s`, or when
/// automatic sub-stepping would need more than `max_substeps`.
pub fn plan_steps(p: &IntegratorParams, critical_dt_s: f64) -> Result<StepPlan, ModelError> {
    let unstable = |n: u32| ModelError::Unstable {
        integrator: p.kind.name(),
        critical_dt_s,
        tick_s: p.tick_s,
        max_substeps: p.max_substeps,
        sub_dt_s: p.tick_s / n as f64,
    };
    let substeps = match p.substeps {
        Some(n) => {
            let n = n.max(1);
            if p.tick_s / n as f64 > critical_dt_s {
                return Err(unstable(n));
            }
            n
        }
        None => {
            let need = (p.tick_s / (p.safety_factor * critical_dt_s))
                .ceil()
                .max(1.0);
            if need > p.max_substeps as f64 {
                return Err(unstable(p.max_substeps));
            }
            need as u32
        }
    };
    Ok(StepPlan {
        substeps,
        sub_dt_s: p.tick_s / substeps as f64,
        critical_dt_s,
    })
}

/// Per-node inverse of the seed's eq. 34 matrix, extended with the implicit mass damping:
/// `A_i = (1 + alpha dt) I - dt^2 / m_i J_i` with `J_i = -K_ii` at rest, so
/// `A_i = (1 + alpha dt) I + dt^2 / m_i K_ii`. Returns `A_i^-1` per node.
pub fn semi_implicit_inverses(fem: &FemModel, dt_s: f64) -> Vec<DMat3> {
    let alpha = fem.material.mass_damping_per_s;
    fem.rest_diagonal_blocks()
        .iter()
        .zip(&fem.lumped_mass_kg)
        .map(|(k, m)| {
            (DMat3::from_diagonal(DVec3::splat(1.0 + alpha * dt_s)) + *k * (dt_s * dt_s / m))
                .inverse()
        })
        .collect()
}

/// Advances velocities and positions of every free node by one step `dt_s` from the total nodal
/// forces `f` (N). Constrained components keep zero velocity. Returns the largest squared nodal
/// speed after the step (m^2/s^2; NaN if any value became NaN), for divergence checks.
///
/// - [`IntegratorKind::SymplecticEuler`]: `v = (v + dt f / m) / (1 + alpha dt)`, `x += dt v`.
/// - [`IntegratorKind::SemiImplicit`]: `v~ = v + dt f / m`, `v = A_i^-1 v~`, `x += dt v`
///   (seed 000 eq. 34; `a_inv` from [`semi_implicit_inverses`]).
///
/// Allocation-free.
pub fn integrate_nodes(
    kind: IntegratorKind,
    fem: &FemModel,
    a_inv: &[DMat3],
    dt_s: f64,
    f: &[DVec3],
    x: &mut [DVec3],
    v: &mut [DVec3],
) -> f64 {
    let damp = 1.0 / (1.0 + fem.material.mass_damping_per_s * dt_s);
    let mut max_v2: f64 = 0.0;
    let mut non_finite = false;
    for i in 0..x.len() {
        let mask = fem.constraint[i];
        if mask == CLAMPED {
            continue;
        }
        let predicted = v[i] + f[i] * (dt_s / fem.lumped_mass_kg[i]);
        let mut vi = match kind {
            IntegratorKind::SymplecticEuler => predicted * damp,
            IntegratorKind::SemiImplicit => a_inv[i] * predicted,
        };
        apply_constraint(mask, &mut vi);
        v[i] = vi;
        x[i] += vi * dt_s;
        let s = vi.length_squared();
        non_finite |= !s.is_finite();
        max_v2 = max_v2.max(s);
    }
    // `f64::max` drops NaN, so a non-finite speed is reported separately.
    if non_finite { f64::NAN } else { max_v2 }
}

/// `B_i^-1 w` for node `i`: the integrator's per-node update matrix divided into `w` and by the
/// lumped mass, with constrained components zeroed. For symplectic Euler `B_i = m_i (1 + alpha
/// dt) I`; for the semi-implicit scheme `B_i = m_i A_i` (see [`semi_implicit_inverses`]).
/// Used to solve the implicit probe coupling ([`crate::contact::Probe::finish_implicit`]).
#[inline]
pub fn apply_inverse(
    kind: IntegratorKind,
    fem: &FemModel,
    a_inv: &[DMat3],
    dt_s: f64,
    i: usize,
    w: DVec3,
) -> DVec3 {
    let mask = fem.constraint[i];
    if mask == CLAMPED {
        return DVec3::ZERO;
    }
    let m = fem.lumped_mass_kg[i];
    let mut r = match kind {
        IntegratorKind::SymplecticEuler => w / (m * (1.0 + fem.material.mass_damping_per_s * dt_s)),
        IntegratorKind::SemiImplicit => a_inv[i] * w / m,
    };
    apply_constraint(mask, &mut r);
    r
}
