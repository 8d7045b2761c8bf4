//! St. Venant-Kirchhoff (seed 000 section 2): Green strain `E = (F^T F - I) / 2` (eq. 3-4),
//! second Piola-Kirchhoff stress `S = lambda tr(E) I + 2 mu E` (eq. 9), energy density
//! `Psi = lambda/2 tr(E)^2 + mu E:E`. Exact for large rotations; softens, and may invert, under
//! strong compression (the energy of a tetrahedron crushed to a plane is finite).
//!
//! Neighbours: dispatched from [`super::first_piola`]; [`crate::element`] and
//! [`crate::integrate`] call [`stvk_stress`] directly in their StVK-specific paths.

use glam::{DMat3, DVec3};

/// Green strain `E = (F^T F - I) / 2` (seed 000 eq. 3-4). `f`: deformation gradient F.
#[inline]
pub fn green_strain(f: &DMat3) -> DMat3 {
    (f.transpose() * *f - DMat3::IDENTITY) * 0.5
}

/// St. Venant-Kirchhoff second Piola-Kirchhoff stress `S = lambda tr(E) I + 2 mu E`, Pa
/// (seed 000 eq. 9).
#[inline]
pub fn stvk_stress(e: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    let tr = e.x_axis.x + e.y_axis.y + e.z_axis.z;
    *e * (2.0 * mu_pa) + DMat3::from_diagonal(DVec3::splat(lambda_pa * tr))
}

/// St. Venant-Kirchhoff strain energy density `W = lambda/2 tr(E)^2 + mu E:E`, J/m^3.
#[inline]
pub fn stvk_energy_density(e: &DMat3, lambda_pa: f64, mu_pa: f64) -> f64 {
    let tr = e.x_axis.x + e.y_axis.y + e.z_axis.z;
    let ee = e.x_axis.length_squared() + e.y_axis.length_squared() + e.z_axis.length_squared();
    0.5 * lambda_pa * tr * tr + mu_pa * ee
}

/// `P = F S(E(F))`, Pa.
#[inline]
pub(super) fn first_piola(f: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    *f * stvk_stress(&green_strain(f), lambda_pa, mu_pa)
}

/// `dP = dF S + F dS(sym(F^T dF))`, Pa.
#[inline]
pub(super) fn first_piola_differential(f: &DMat3, df: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    let s = stvk_stress(&green_strain(f), lambda_pa, mu_pa);
    let ft_df = f.transpose() * *df;
    let de = (ft_df + ft_df.transpose()) * 0.5;
    *df * s + *f * stvk_stress(&de, lambda_pa, mu_pa)
}
