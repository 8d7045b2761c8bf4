//! The viscous stress of seed 000 (eq. 10-11), added to the elastic stress of every material as
//! `P_v = F S_v`.
//!
//! Neighbours: [`crate::element`] adds it in the force kernels; [`crate::integrate`] treats it
//! implicitly in backward Euler (it is linear in the velocity).

use glam::{DMat3, DVec3};

/// Viscous stress of seed 000 eq. 10-11: with the strain rate `nu = F^T Fdot + Fdot^T F`
/// (eq. 10, which is twice dE/dt), `S_v = 2 psi nu + phi tr(nu) I`, Pa.
#[inline]
pub fn viscous_stress(f: &DMat3, f_dot: &DMat3, phi_pa_s: f64, psi_pa_s: f64) -> DMat3 {
    let a = f.transpose() * *f_dot;
    let nu = a + a.transpose();
    let tr = nu.x_axis.x + nu.y_axis.y + nu.z_axis.z;
    nu * (2.0 * psi_pa_s) + DMat3::from_diagonal(DVec3::splat(phi_pa_s * tr))
}
