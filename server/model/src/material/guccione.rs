//! Guccione's transversely isotropic law of passive myocardium (J. M. Guccione, A. D. McCulloch,
//! L. K. Waldman, "Passive material properties of intact ventricular myocardium determined from
//! a cylindrical model", J. Biomech. Eng. 113 (1991) 42-55) in the form of the cardiac mechanics
//! benchmark (S. Land et al. 2015, Proc. R. Soc. A 471:20150641, eq. 2.2), with a volumetric
//! penalty for near incompressibility:
//!
//! `Psi = C/2 (e^Q - 1) + kappa/2 (J - 1)^2`,
//! `Q = b_f E_ff^2 + b_t (E_ss^2 + E_nn^2 + E_sn^2 + E_ns^2) + b_fs (E_fs^2 + E_sf^2 + E_fn^2 + E_nf^2)`,
//!
//! with `E` the Green strain written in the local frame `R = [f s n]` (fibre, sheet,
//! sheet-normal, columns of an orthonormal matrix in the rest configuration): `E_loc = R^T E R`.
//! So `Q = sum_ij B_ij (E_loc)_ij^2` with `B = [[b_f, b_fs, b_fs], [b_fs, b_t, b_t], [b_fs, b_t,
//! b_t]]`, and the second Piola-Kirchhoff stress is `S = R S_loc R^T`,
//! `S_loc = C e^Q (B o E_loc)` (`o` the entrywise product). With `b_f = b_t = b_fs = b` the law
//! is isotropic, `Q = b E:E`, and the frame does not matter (its *isotropic limit*; Land's
//! problem 2). At rest it linearises to `S = C B o E` plus `kappa tr(E) I`: for the isotropic
//! limit, linear elasticity with `mu = C b / 2` and `lambda = kappa`.
//!
//! The volumetric term is the coupled form: `J` is the full determinant, `kappa` the penalty
//! (bulk-like) modulus. As `kappa / C` grows the solution tends to the incompressible one
//! (`J = 1`, where the coupled and the isochoric forms of the law coincide). Its element
//! treatment (per integration point, or the element-mean dilatation that keeps quadratic
//! tetrahedra from locking) is chosen in [`crate::element`].
//!
//! Like St. Venant-Kirchhoff, the Green-strain law softens under strong *compressible*
//! compression (the nominal stress of a stretch `l` carries the factor `l (l^2 - 1)`); the
//! volumetric penalty is what keeps a nearly incompressible body out of that regime.
//!
//! Neighbours: dispatched from [`super`] ([`super::first_piola_oriented`] and friends);
//! [`crate::element`] supplies the frame per integration point (the rule-based fibre field).

use glam::{DMat3, DVec3};

/// Parameters of the Guccione law (Land et al. 2015, eq. 2.2) and its volumetric penalty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuccioneParams {
    /// Stiffness scale C, Pa.
    pub c_pa: f64,
    /// Fibre exponent coefficient b_f (dimensionless).
    pub b_f: f64,
    /// Transverse (cross-fibre) coefficient b_t.
    pub b_t: f64,
    /// Fibre-transverse shear coefficient b_fs.
    pub b_fs: f64,
    /// Volumetric penalty kappa of `kappa/2 (J - 1)^2`, Pa.
    pub bulk_modulus_pa: f64,
    /// Whether the volumetric term is evaluated with the element-mean dilatation
    /// `J_e = (deformed volume) / (rest volume)` of each element (the mean-dilatation or
    /// `P2/P0` treatment: quadratic tetrahedra do not lock as `kappa / C` grows) instead of at
    /// every integration point.
    pub mean_dilatation: bool,
}

impl GuccioneParams {
    /// The isotropic limit with `b_f = b_t = b_fs = b`.
    pub fn isotropic(c_pa: f64, b: f64, bulk_modulus_pa: f64) -> Self {
        Self {
            c_pa,
            b_f: b,
            b_t: b,
            b_fs: b,
            bulk_modulus_pa,
            mean_dilatation: false,
        }
    }

    /// Whether the law is isotropic (`b_f = b_t = b_fs`): the frame is then irrelevant.
    pub fn is_isotropic(&self) -> bool {
        self.b_f == self.b_t && self.b_t == self.b_fs
    }

    /// The coefficient matrix `B` of `Q = sum_ij B_ij (E_loc)_ij^2` (symmetric).
    #[inline]
    pub fn coefficients(&self) -> DMat3 {
        let (f, t, fs) = (self.b_f, self.b_t, self.b_fs);
        DMat3::from_cols(
            DVec3::new(f, fs, fs),
            DVec3::new(fs, t, t),
            DVec3::new(fs, t, t),
        )
    }

    /// Largest small-strain shear modulus of the law, `C max(b) / 2`, Pa: an upper bound for
    /// time-step estimates and isotropic preconditioners.
    pub fn max_shear_modulus_pa(&self) -> f64 {
        0.5 * self.c_pa * self.b_f.max(self.b_t).max(self.b_fs)
    }
}

/// Entrywise product `A o B`.
#[inline]
fn hadamard(a: &DMat3, b: &DMat3) -> DMat3 {
    DMat3::from_cols(
        a.x_axis * b.x_axis,
        a.y_axis * b.y_axis,
        a.z_axis * b.z_axis,
    )
}

/// `sum_ij B_ij A_ij^2`.
#[inline]
fn weighted_square(b: &DMat3, a: &DMat3) -> f64 {
    (b.x_axis * a.x_axis * a.x_axis
        + b.y_axis * a.y_axis * a.y_axis
        + b.z_axis * a.z_axis * a.z_axis)
        .element_sum()
}

/// `(E_loc, Q, C e^Q)` at `f` in the frame `r`.
#[inline]
fn strain_state(p: &GuccioneParams, f: &DMat3, r: &DMat3) -> (DMat3, f64, f64) {
    let e = (f.transpose() * *f - DMat3::IDENTITY) * 0.5;
    let el = r.transpose() * e * *r;
    let q = weighted_square(&p.coefficients(), &el);
    (el, q, p.c_pa * q.exp())
}

/// The fibre part of the second Piola-Kirchhoff stress, `S = R (C e^Q B o E_loc) R^T`, Pa, at
/// deformation gradient `f` with frame `r` (no volumetric term).
#[inline]
pub fn guccione_stress(p: &GuccioneParams, f: &DMat3, r: &DMat3) -> DMat3 {
    let (el, _, ceq) = strain_state(p, f, r);
    *r * (hadamard(&p.coefficients(), &el) * ceq) * r.transpose()
}

/// `P = F S` of the fibre part (no volumetric term), Pa.
#[inline]
pub fn first_piola_deviatoric(p: &GuccioneParams, f: &DMat3, r: &DMat3) -> DMat3 {
    *f * guccione_stress(p, f, r)
}

/// Directional derivative of [`first_piola_deviatoric`] along `df`:
/// `dP = dF S + F R dS_loc R^T`, `dS_loc = C e^Q (dQ B o E_loc + B o dE_loc)`,
/// `dQ = 2 sum_ij B_ij (E_loc)_ij (dE_loc)_ij`, `dE_loc = R^T sym(F^T dF) R`, Pa.
#[inline]
pub fn first_piola_deviatoric_differential(
    p: &GuccioneParams,
    f: &DMat3,
    r: &DMat3,
    df: &DMat3,
) -> DMat3 {
    let b = p.coefficients();
    let (el, _, ceq) = strain_state(p, f, r);
    let be = hadamard(&b, &el);
    let ft_df = f.transpose() * *df;
    let del = r.transpose() * ((ft_df + ft_df.transpose()) * 0.5) * *r;
    let dq = 2.0 * super::ddot(&be, &del);
    let s = *r * (be * ceq) * r.transpose();
    let ds = *r * ((be * dq + hadamard(&b, &del)) * ceq) * r.transpose();
    *df * s + *f * ds
}

/// Energy density of the fibre part, `C/2 (e^Q - 1)`, J/m^3.
#[inline]
pub fn energy_density_deviatoric(p: &GuccioneParams, f: &DMat3, r: &DMat3) -> f64 {
    let (_, q, _) = strain_state(p, f, r);
    0.5 * p.c_pa * q.exp_m1()
}

/// The volumetric penalty `U(J) = kappa/2 (J - 1)^2`, its derivative `U'` (Pa) and second
/// derivative `U''` (Pa).
#[inline]
pub fn volumetric(p: &GuccioneParams, j: f64) -> (f64, f64, f64) {
    let k = p.bulk_modulus_pa;
    (0.5 * k * (j - 1.0) * (j - 1.0), k * (j - 1.0), k)
}

/// Complete first Piola-Kirchhoff stress with the volumetric term at the point,
/// `P = F S + kappa (J - 1) cof F`, Pa.
#[inline]
pub(super) fn first_piola(p: &GuccioneParams, f: &DMat3, r: &DMat3) -> DMat3 {
    let (_, du, _) = volumetric(p, f.determinant());
    first_piola_deviatoric(p, f, r) + super::cofactor(f) * du
}

/// Directional derivative of [`first_piola`]:
/// `dP_dev + kappa (cof F : dF) cof F + kappa (J - 1) d cof F`, Pa.
#[inline]
pub(super) fn first_piola_differential(
    p: &GuccioneParams,
    f: &DMat3,
    r: &DMat3,
    df: &DMat3,
) -> DMat3 {
    let cof = super::cofactor(f);
    let (_, du, ddu) = volumetric(p, f.determinant());
    first_piola_deviatoric_differential(p, f, r, df)
        + cof * (ddu * super::ddot(&cof, df))
        + super::neo_hookean::cofactor_differential(f, df) * du
}

/// Energy density with the volumetric term at the point, J/m^3.
#[inline]
pub(super) fn energy_density(p: &GuccioneParams, f: &DMat3, r: &DMat3) -> f64 {
    energy_density_deviatoric(p, f, r) + volumetric(p, f.determinant()).0
}
