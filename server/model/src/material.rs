//! Material parameters and constitutive laws (seed 000 section 2).
//!
//! - Green strain `E = (F^T F - I) / 2` (eq. 3-4),
//! - St. Venant-Kirchhoff second Piola-Kirchhoff stress `S = lambda tr(E) I + 2 mu E` (eq. 9),
//! - viscous stress from the strain rate `nu = F^T Fdot + Fdot^T F` (eq. 10),
//!   `S_v = 2 psi nu + phi tr(nu) I` (eq. 11), added to the elastic stress (as `P_v = F S_v`
//!   for every material),
//! - beside StVK (issue 3 section 1), behind the same interface ([`MaterialModel`],
//!   [`first_piola`], [`first_piola_differential`], [`energy_density`]): corotational linear
//!   elasticity (rotation from the polar decomposition of F, [`polar_decomposition`]) and the
//!   stable Neo-Hookean material of Smith, de Goes and Kim 2018 ("Stable Neo-Hookean Flesh
//!   Simulation", ACM TOG 37(2):12). All three linearise at rest to the same linear elasticity
//!   with the given Lamé parameters.
//!
//! Neighbours: [`crate::fem`] evaluates these per element; [`crate::scene`] fills
//! [`MaterialParams`] from a scene file.

use glam::{DMat3, DVec3};

use crate::ModelError;

/// Constitutive model of the elastic stress. Scene name in parentheses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MaterialModel {
    /// St. Venant-Kirchhoff (`"stvk"`, the seed's, eq. 9): `Psi = lambda/2 tr(E)^2 + mu E:E`.
    /// Exact for large rotations, but it softens and may invert under strong compression.
    #[default]
    StVenantKirchhoff,
    /// Corotational linear elasticity (`"corotational"`):
    /// `Psi = mu |F - R|^2 + lambda/2 tr(R^T F - I)^2` with R the rotation of the polar
    /// decomposition `F = R S` (for inverted elements the proper-rotation variant of Irving et
    /// al. 2004, see [`polar_decomposition`]).
    Corotational,
    /// Stable Neo-Hookean (`"stable-neo-hookean"`, Smith, de Goes, Kim 2018, eq. 14 without the
    /// `log(I_C + 1)` term): `Psi = mu/2 (I_C - 3) + lambda_s/2 (J - alpha)^2 - mu^2/(2 lambda_s)`
    /// with `lambda_s = lambda + mu`, `alpha = 1 + mu / lambda_s` (the constant makes
    /// `Psi(I) = 0`). Defined and smooth for inverted elements.
    ///
    /// Reparametrisation: at `F = I`, `P = mu I + lambda_s (1 - alpha) I = 0`, and the second
    /// variation is `mu (dF:dF + dF:dF^T) + (lambda_s - mu) tr(dF)^2` (from
    /// `d^2 J = tr(dF)^2 - tr(dF^2)` and `J - alpha = -mu/lambda_s`), which is linear
    /// elasticity exactly when `lambda_s = lambda + mu`.
    StableNeoHookean,
}

impl MaterialModel {
    /// The scene-file name: `"stvk"`, `"corotational"` or `"stable-neo-hookean"`.
    pub fn scene_name(self) -> &'static str {
        match self {
            Self::StVenantKirchhoff => "stvk",
            Self::Corotational => "corotational",
            Self::StableNeoHookean => "stable-neo-hookean",
        }
    }

    /// Parses a scene-file name (see [`MaterialModel::scene_name`]); `None` if unknown.
    pub fn from_scene_name(name: &str) -> Option<Self> {
        [
            Self::StVenantKirchhoff,
            Self::Corotational,
            Self::StableNeoHookean,
        ]
        .into_iter()
        .find(|m| m.scene_name() == name)
    }
}

/// Material parameters of a homogeneous body, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaterialParams {
    /// Constitutive model of the elastic stress (default St. Venant-Kirchhoff).
    pub model: MaterialModel,
    /// First Lamé parameter lambda, Pa.
    pub lambda_pa: f64,
    /// Second Lamé parameter (shear modulus) mu, Pa.
    pub mu_pa: f64,
    /// Viscous parameter phi of eq. 11 (volumetric strain-rate term), Pa s.
    pub phi_pa_s: f64,
    /// Viscous parameter psi of eq. 11 (deviatoric strain-rate term), Pa s.
    pub psi_pa_s: f64,
    /// Mass density rho, kg/m^3.
    pub density_kg_per_m3: f64,
    /// Mass-proportional (Rayleigh alpha) damping, 1/s. Not in the seed; 0 disables it. Applied
    /// implicitly, so it never limits the stable time step.
    pub mass_damping_per_s: f64,
}

impl Default for MaterialParams {
    /// Soft tissue: E = 14.5 kPa, nu = 0.45 (see [`MaterialParams::from_youngs`]), rho = 1060 kg/m^3.
    fn default() -> Self {
        let mut m = Self::from_youngs(14.5e3, 0.45, 1060.0);
        m.phi_pa_s = 0.05;
        m.psi_pa_s = 0.05;
        m.mass_damping_per_s = 5.0;
        m
    }
}

impl MaterialParams {
    /// Lamé parameters from Young's modulus `e_pa` (Pa) and Poisson ratio `nu`:
    /// `lambda = E nu / ((1 + nu)(1 - 2 nu))`, `mu = E / (2 (1 + nu))`. No viscosity or damping.
    pub fn from_youngs(e_pa: f64, nu: f64, density_kg_per_m3: f64) -> Self {
        Self {
            model: MaterialModel::StVenantKirchhoff,
            lambda_pa: e_pa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
            mu_pa: e_pa / (2.0 * (1.0 + nu)),
            phi_pa_s: 0.0,
            psi_pa_s: 0.0,
            density_kg_per_m3,
            mass_damping_per_s: 0.0,
        }
    }

    /// Young's modulus `E = mu (3 lambda + 2 mu) / (lambda + mu)`, Pa.
    pub fn youngs_modulus_pa(&self) -> f64 {
        self.mu_pa * (3.0 * self.lambda_pa + 2.0 * self.mu_pa) / (self.lambda_pa + self.mu_pa)
    }

    /// Poisson ratio `nu = lambda / (2 (lambda + mu))`.
    pub fn poisson_ratio(&self) -> f64 {
        self.lambda_pa / (2.0 * (self.lambda_pa + self.mu_pa))
    }

    /// P-wave (dilatational) speed `sqrt((lambda + 2 mu) / rho)`, m/s.
    pub fn dilatational_wave_speed_m_per_s(&self) -> f64 {
        ((self.lambda_pa + 2.0 * self.mu_pa) / self.density_kg_per_m3).sqrt()
    }

    /// Checks that every parameter is finite and physically admissible.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming the `material.*` field that is wrong.
    pub fn validate(&self) -> Result<(), ModelError> {
        let checks: [(&str, f64, bool); 6] = [
            ("material.lambda_pa", self.lambda_pa, self.lambda_pa >= 0.0),
            ("material.mu_pa", self.mu_pa, self.mu_pa > 0.0),
            ("material.phi_pa_s", self.phi_pa_s, self.phi_pa_s >= 0.0),
            ("material.psi_pa_s", self.psi_pa_s, self.psi_pa_s >= 0.0),
            (
                "material.density_kg_per_m3",
                self.density_kg_per_m3,
                self.density_kg_per_m3 > 0.0,
            ),
            (
                "material.mass_damping_per_s",
                self.mass_damping_per_s,
                self.mass_damping_per_s >= 0.0,
            ),
        ];
        for (field, v, ok) in checks {
            if !v.is_finite() || !ok {
                return Err(ModelError::field(field, format!("{v} is not admissible")));
            }
        }
        Ok(())
    }
}

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
    *e * (2.0 * mu_pa) + DMat3::from_diagonal(glam::DVec3::splat(lambda_pa * tr))
}

/// St. Venant-Kirchhoff strain energy density `W = lambda/2 tr(E)^2 + mu E:E`, J/m^3.
#[inline]
pub fn stvk_energy_density(e: &DMat3, lambda_pa: f64, mu_pa: f64) -> f64 {
    let tr = e.x_axis.x + e.y_axis.y + e.z_axis.z;
    let ee = e.x_axis.length_squared() + e.y_axis.length_squared() + e.z_axis.length_squared();
    0.5 * lambda_pa * tr * tr + mu_pa * ee
}

/// Viscous stress of seed 000 eq. 10-11: with the strain rate `nu = F^T Fdot + Fdot^T F`
/// (eq. 10, which is twice dE/dt), `S_v = 2 psi nu + phi tr(nu) I`, Pa.
#[inline]
pub fn viscous_stress(f: &DMat3, f_dot: &DMat3, phi_pa_s: f64, psi_pa_s: f64) -> DMat3 {
    let a = f.transpose() * *f_dot;
    let nu = a + a.transpose();
    let tr = nu.x_axis.x + nu.y_axis.y + nu.z_axis.z;
    nu * (2.0 * psi_pa_s) + DMat3::from_diagonal(glam::DVec3::splat(phi_pa_s * tr))
}

/// `tr(A)`.
#[inline]
fn trace(a: &DMat3) -> f64 {
    a.x_axis.x + a.y_axis.y + a.z_axis.z
}

/// Frobenius product `A : B = sum_ij A_ij B_ij`.
#[inline]
fn ddot(a: &DMat3, b: &DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

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

/// Directional derivative of [`cofactor`] at `f` along `df`.
#[inline]
fn cofactor_differential(f: &DMat3, df: &DMat3) -> DMat3 {
    DMat3::from_cols(
        df.y_axis.cross(f.z_axis) + f.y_axis.cross(df.z_axis),
        df.z_axis.cross(f.x_axis) + f.z_axis.cross(df.x_axis),
        df.x_axis.cross(f.y_axis) + f.x_axis.cross(df.y_axis),
    )
}

/// Symmetric eigen-decomposition by cyclic Jacobi rotations: returns `(V, d)` with
/// `A = V diag(d) V^T`, V orthonormal, `d` sorted in decreasing order. `a` must be symmetric.
#[allow(
    clippy::needless_range_loop,
    reason = "Jacobi rotations index rows and columns p, q together"
)]
pub fn symmetric_eigen(a: &DMat3) -> (DMat3, DVec3) {
    let mut m = a.to_cols_array_2d(); // m[col][row], symmetric so also m[row][col]
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]; // v[col][row]
    let scale = m.iter().flatten().fold(0.0_f64, |s, x| s.max(x.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return (DMat3::IDENTITY, DVec3::new(m[0][0], m[1][1], m[2][2]));
    }
    for _sweep in 0..32 {
        let off = m[0][1] * m[0][1] + m[0][2] * m[0][2] + m[1][2] * m[1][2];
        if off <= (1e-18 * scale) * (1e-18 * scale) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            let apq = m[p][q];
            if apq == 0.0 {
                continue;
            }
            // Rotation annihilating (p, q) (Golub & Van Loan, Algorithm 8.4.2).
            let tau = (m[q][q] - m[p][p]) / (2.0 * apq);
            let t = tau.signum() / (tau.abs() + (1.0 + tau * tau).sqrt());
            let t = if tau == 0.0 { 1.0 } else { t };
            let c = 1.0 / (1.0 + t * t).sqrt();
            let s = t * c;
            // m <- J^T m J with J = rotation in the (p, q) plane.
            for k in 0..3 {
                let (mkp, mkq) = (m[k][p], m[k][q]);
                m[k][p] = c * mkp - s * mkq;
                m[k][q] = s * mkp + c * mkq;
            }
            for k in 0..3 {
                let (mpk, mqk) = (m[p][k], m[q][k]);
                m[p][k] = c * mpk - s * mqk;
                m[q][k] = s * mpk + c * mqk;
            }
            for row in 0..3 {
                let (vp, vq) = (v[p][row], v[q][row]);
                v[p][row] = c * vp - s * vq;
                v[q][row] = s * vp + c * vq;
            }
        }
    }
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| m[j][j].total_cmp(&m[i][i]));
    let cols = order.map(|i| DVec3::from_array(v[i]));
    (
        DMat3::from_cols(cols[0], cols[1], cols[2]),
        DVec3::new(
            m[order[0]][order[0]],
            m[order[1]][order[1]],
            m[order[2]][order[2]],
        ),
    )
}

/// A unit vector orthogonal to the unit vector `u`.
fn any_orthogonal(u: DVec3) -> DVec3 {
    let a = if u.x.abs() < 0.6 { DVec3::X } else { DVec3::Y };
    (a - u * u.dot(a)).normalize()
}

/// Rotation-variant singular value decomposition `F = U diag(sigma) V^T` with U and V proper
/// rotations (det = +1), `sigma_1 >= sigma_2 >= |sigma_3|`, and `sigma_3 < 0` exactly when
/// `det F < 0` (Irving, Teran, Fedkiw 2004, "Invertible finite elements for robust simulation of
/// large deformation", section 5: the reflection is moved onto the smallest singular value).
///
/// V from a Jacobi eigen-decomposition of `F^T F`, then U from a Gram-Schmidt QR of `F V`
/// with `u_3 = u_1 x u_2` (as in McAdams et al. 2011), which stays defined for rank-deficient F.
pub fn rotation_variant_svd(f: &DMat3) -> (DMat3, DVec3, DMat3) {
    let (mut v, _) = symmetric_eigen(&(f.transpose() * *f));
    if v.determinant() < 0.0 {
        v.z_axis = -v.z_axis;
    }
    let b = *f * v;
    let s1 = b.x_axis.length();
    let u1 = if s1 > 0.0 {
        b.x_axis / s1
    } else {
        // F = 0: any rotation.
        v.x_axis
    };
    let b2 = b.y_axis - u1 * u1.dot(b.y_axis);
    let n2 = b2.length();
    let u2 = if n2 > 1e-300 && n2 > 1e-15 * s1 {
        b2 / n2
    } else {
        any_orthogonal(u1)
    };
    let u3 = u1.cross(u2);
    let sigma = DVec3::new(s1, u2.dot(b.y_axis), u3.dot(b.z_axis));
    (DMat3::from_cols(u1, u2, u3), sigma, v)
}

/// Polar decomposition `F = R S` with R a proper rotation and S symmetric, returned as
/// `(R, S)`. For `det F < 0` (an inverted element) S is indefinite: R is the rotation of
/// [`rotation_variant_svd`] (`R = U V^T`, `S = V diag(sigma) V^T` with `sigma_3 < 0`), not the
/// reflection of the classical polar decomposition, so the corotational force pushes the element
/// back through the inversion (Irving et al. 2004).
pub fn polar_decomposition(f: &DMat3) -> (DMat3, DMat3) {
    let (u, sigma, v) = rotation_variant_svd(f);
    let r = u * v.transpose();
    let s = v * DMat3::from_diagonal(sigma) * v.transpose();
    (r, (s + s.transpose()) * 0.5)
}

/// Differential of the rotation of [`polar_decomposition`]: with `F = R S`, `R^T dR = [w]x`
/// and `((tr S) I - S) w = axial(R^T dF - dF^T R)` (from the skew part of
/// `R^T dF = [w]x S + dS`, using `[w]x S + S [w]x = [((tr S) I - S) w]x`). Solved in the
/// eigenbasis V of S, where the matrix is `diag(sigma_2 + sigma_3, sigma_1 + sigma_3,
/// sigma_1 + sigma_2)`; a pair sum below `1e-12 * sigma_1` in magnitude (an element crushed to
/// a line, or half way through an inversion) is clamped there, which bounds dR.
fn rotation_differential(u: &DMat3, sigma: DVec3, v: &DMat3, df: &DMat3) -> DMat3 {
    let r = *u * v.transpose();
    let m = r.transpose() * *df;
    let k = m - m.transpose();
    let a = DVec3::new(k.y_axis.z, k.z_axis.x, k.x_axis.y);
    let floor = 1e-12 * sigma.x.abs().max(1e-300);
    let clamp = |d: f64| {
        if d.abs() >= floor {
            d
        } else if d >= 0.0 {
            floor
        } else {
            -floor
        }
    };
    let den = DVec3::new(
        clamp(sigma.y + sigma.z),
        clamp(sigma.x + sigma.z),
        clamp(sigma.x + sigma.y),
    );
    let w = *v * ((v.transpose() * a) / den);
    r * skew(w)
}

/// `[w]x`, the cross-product matrix: `[w]x y = w x y`.
#[inline]
fn skew(w: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, w.z, -w.y),
        DVec3::new(-w.z, 0.0, w.x),
        DVec3::new(w.y, -w.x, 0.0),
    )
}

/// Elastic first Piola-Kirchhoff stress `P(F) = dPsi/dF` of `mat.model`, Pa.
/// StVK: `P = F S(E)`; corotational: `P = 2 mu (F - R) + lambda tr(R^T F - I) R`; stable
/// Neo-Hookean: `P = mu F + lambda_s (J - alpha) cof(F)`.
#[inline]
pub fn first_piola(mat: &MaterialParams, f: &DMat3) -> DMat3 {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    match mat.model {
        MaterialModel::StVenantKirchhoff => *f * stvk_stress(&green_strain(f), lambda, mu),
        MaterialModel::Corotational => {
            let (r, s) = polar_decomposition(f);
            (*f - r) * (2.0 * mu) + r * (lambda * (trace(&s) - 3.0))
        }
        MaterialModel::StableNeoHookean => {
            let (ls, alpha) = neo_hookean_params(lambda, mu);
            *f * mu + cofactor(f) * (ls * (f.determinant() - alpha))
        }
    }
}

/// `(lambda_s, alpha)` of the stable Neo-Hookean material, see [`MaterialModel::StableNeoHookean`].
#[inline]
pub(crate) fn neo_hookean_params(lambda: f64, mu: f64) -> (f64, f64) {
    let ls = lambda + mu;
    (ls, 1.0 + mu / ls)
}

/// Exact directional derivative `dP = (dP/dF) : dF` of [`first_piola`] at `f` along `df`, Pa.
/// StVK: `dF S + F dS(sym(F^T dF))`; corotational:
/// `2 mu (dF - dR) + lambda ((R : dF) R + tr(S - I) dR)` with dR from
/// the polar-decomposition differential (`d tr(S) = R : dF`); stable Neo-Hookean:
/// `mu dF + lambda_s ((cof F : dF) cof F + (J - alpha) d cof F)`.
#[inline]
pub fn first_piola_differential(mat: &MaterialParams, f: &DMat3, df: &DMat3) -> DMat3 {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    match mat.model {
        MaterialModel::StVenantKirchhoff => {
            let s = stvk_stress(&green_strain(f), lambda, mu);
            let ft_df = f.transpose() * *df;
            let de = (ft_df + ft_df.transpose()) * 0.5;
            *df * s + *f * stvk_stress(&de, lambda, mu)
        }
        MaterialModel::Corotational => {
            let (u, sigma, v) = rotation_variant_svd(f);
            let r = u * v.transpose();
            let dr = rotation_differential(&u, sigma, &v, df);
            let tr_s = sigma.x + sigma.y + sigma.z;
            (*df - dr) * (2.0 * mu) + (r * ddot(&r, df) + dr * (tr_s - 3.0)) * lambda
        }
        MaterialModel::StableNeoHookean => {
            let (ls, alpha) = neo_hookean_params(lambda, mu);
            let cof = cofactor(f);
            *df * mu
                + (cof * ddot(&cof, df) + cofactor_differential(f, df) * (f.determinant() - alpha))
                    * ls
        }
    }
}

/// Elastic strain energy density `Psi(F)` of `mat.model`, J/m^3 (zero at `F = I`).
#[inline]
pub fn energy_density(mat: &MaterialParams, f: &DMat3) -> f64 {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    match mat.model {
        MaterialModel::StVenantKirchhoff => stvk_energy_density(&green_strain(f), lambda, mu),
        MaterialModel::Corotational => {
            let (r, s) = polar_decomposition(f);
            let d = *f - r;
            let t = trace(&s) - 3.0;
            mu * ddot(&d, &d) + 0.5 * lambda * t * t
        }
        MaterialModel::StableNeoHookean => {
            let (ls, alpha) = neo_hookean_params(lambda, mu);
            let j = f.determinant() - alpha;
            0.5 * mu * (ddot(f, f) - 3.0) + 0.5 * ls * j * j - 0.5 * mu * mu / ls
        }
    }
}
