//! Stable Neo-Hookean (Smith, de Goes & Kim 2018, "Stable Neo-Hookean Flesh Simulation", ACM
//! TOG 37(2):12, eq. 14 without the `log(I_C + 1)` term): `Psi = mu/2 (I_C - 3) +
//! lambda_s/2 (J - alpha)^2 - mu^2/(2 lambda_s)`, defined and smooth for inverted elements. See
//! [`super::MaterialModel::StableNeoHookean`] for the reparametrisation.
//!
//! Neighbours: dispatched from [`super`]; the vectorised kernels of [`crate::element`] use
//! [`neo_hookean_params`].

use glam::DMat3;

use super::ddot;

/// Cofactor matrix `cof(F) = dJ/dF = J F^-T` (defined for singular F too): column j is the
/// cross product of the other two columns of F, in cyclic order.
#[inline]
pub fn cofactor(f: &DMat3) -> DMat3 {
    DMat3::from_cols(
        f.y_axis.cross(f.z_axis),
        f.z_axis.cross(f.x_axis),
        f.x_axis.cross(f.y_axis),
    )
}

/// Directional derivative of [`cofactor`] at `f` along `df` (the derivative of `cof F = J F^-T`).
#[inline]
pub fn cofactor_differential(f: &DMat3, df: &DMat3) -> DMat3 {
    DMat3::from_cols(
        df.y_axis.cross(f.z_axis) + f.y_axis.cross(df.z_axis),
        df.z_axis.cross(f.x_axis) + f.z_axis.cross(df.x_axis),
        df.x_axis.cross(f.y_axis) + f.x_axis.cross(df.y_axis),
    )
}

/// `(lambda_s, alpha)` of the stable Neo-Hookean material, see
/// [`super::MaterialModel::StableNeoHookean`].
#[inline]
pub fn neo_hookean_params(lambda: f64, mu: f64) -> (f64, f64) {
    let ls = lambda + mu;
    (ls, 1.0 + mu / ls)
}

/// `P = mu F + lambda_s (J - alpha) cof(F)`, Pa.
#[inline]
pub(super) fn first_piola(f: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    let (ls, alpha) = neo_hookean_params(lambda_pa, mu_pa);
    *f * mu_pa + cofactor(f) * (ls * (f.determinant() - alpha))
}

/// `dP = mu dF + lambda_s ((cof F : dF) cof F + (J - alpha) d cof F)`, Pa.
#[inline]
pub(super) fn first_piola_differential(f: &DMat3, df: &DMat3, lambda_pa: f64, mu_pa: f64) -> DMat3 {
    let (ls, alpha) = neo_hookean_params(lambda_pa, mu_pa);
    let cof = cofactor(f);
    *df * mu_pa
        + (cof * ddot(&cof, df) + cofactor_differential(f, df) * (f.determinant() - alpha)) * ls
}

/// `Psi(F)`, J/m^3 (zero at `F = I`).
#[inline]
pub(super) fn energy_density(f: &DMat3, lambda_pa: f64, mu_pa: f64) -> f64 {
    let (ls, alpha) = neo_hookean_params(lambda_pa, mu_pa);
    let j = f.determinant() - alpha;
    0.5 * mu_pa * (ddot(f, f) - 3.0) + 0.5 * ls * j * j - 0.5 * mu_pa * mu_pa / ls
}
