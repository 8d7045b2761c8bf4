//! Explicit-in-force time steps, node by node: the seed's semi-implicit scheme (seed 000
//! eq. 34: explicit velocity predictor, then the per-node rest Jacobian solved implicitly) and
//! symplectic Euler, both with implicit mass damping.
//!
//! Neighbours: [`super::Stepper`] calls [`integrate_nodes`] and completes the probe coupling
//! with [`apply_inverse`].

use glam::{DMat3, DVec3};

use super::IntegratorKind;
use crate::element::{CLAMPED, FemModel, apply_constraint};

/// Per-node inverse of the seed's eq. 34 matrix, extended with the implicit mass damping:
/// `A_i = (1 + alpha dt) I - dt^2 / m_i J_i` with `J_i = -K_ii` at rest, so
/// `A_i = (1 + alpha dt) I + dt^2 / m_i K_ii`. Returns `A_i^-1` per node.
pub fn semi_implicit_inverses(fem: &FemModel, dt_s: f64) -> Vec<DMat3> {
    let alpha = fem.material().mass_damping_per_s;
    fem.rest_diagonal_blocks()
        .iter()
        .zip(fem.lumped_mass_kg())
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
/// - [`IntegratorKind::BackwardEuler`] needs the global solve of
///   [`super::implicit::ImplicitSolver::step`]; here it degrades to its block-diagonal
///   (per-node) approximation, which is the semi-implicit update, so `a_inv` must be given.
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
    let damp = 1.0 / (1.0 + fem.material().mass_damping_per_s * dt_s);
    let mut max_v2: f64 = 0.0;
    let mut non_finite = false;
    for i in 0..x.len() {
        let mask = fem.constraints()[i];
        if mask == CLAMPED {
            continue;
        }
        let predicted = v[i] + f[i] * (dt_s / fem.lumped_mass_kg()[i]);
        let mut vi = match kind {
            IntegratorKind::SymplecticEuler => predicted * damp,
            IntegratorKind::SemiImplicit | IntegratorKind::BackwardEuler => a_inv[i] * predicted,
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
    let mask = fem.constraints()[i];
    if mask == CLAMPED {
        return DVec3::ZERO;
    }
    let m = fem.lumped_mass_kg()[i];
    let mut r = match kind {
        IntegratorKind::SymplecticEuler => {
            w / (m * (1.0 + fem.material().mass_damping_per_s * dt_s))
        }
        IntegratorKind::SemiImplicit | IntegratorKind::BackwardEuler => a_inv[i] * w / m,
    };
    apply_constraint(mask, &mut r);
    r
}
