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
//! - Guccione's transversely isotropic law of passive myocardium with a volumetric penalty
//!   ([`guccione`]; Guccione, McCulloch & Waldman 1991, in the form of Land et al. 2015), whose
//!   stress depends on a local fibre frame: [`first_piola_oriented`] and friends take it (the
//!   other laws ignore it).
//!
//! One file per law: [`stvk`], [`corotational`], [`neo_hookean`], [`guccione`], [`viscous`];
//! this module holds the parameters and the dispatch on [`MaterialModel`].
//!
//! Owns: constitutive laws of one material point (no mesh, no nodes). May use: nothing of the
//! crate but [`crate::ModelError`]. Used by [`crate::element`] (per integration point),
//! [`crate::integrate`] (tangents) and [`crate::scene`] (fills [`MaterialParams`]).

use glam::DMat3;

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
    /// Guccione's transversely isotropic law of passive myocardium with a volumetric penalty
    /// (`"guccione"`, [`guccione`]): `Psi = C/2 (e^Q - 1) + kappa/2 (J - 1)^2`, parameters in
    /// [`MaterialParams::guccione`]. Exponential, fibre-dependent stiffness; nearly
    /// incompressible for a large `kappa / C`.
    Guccione,
}

impl MaterialModel {
    /// Every model, in the order of the scene-file documentation.
    pub const ALL: [MaterialModel; 4] = [
        Self::StVenantKirchhoff,
        Self::Corotational,
        Self::StableNeoHookean,
        Self::Guccione,
    ];

    /// The scene-file name: `"stvk"`, `"corotational"`, `"stable-neo-hookean"` or
    /// `"guccione"`.
    pub fn scene_name(self) -> &'static str {
        match self {
            Self::StVenantKirchhoff => "stvk",
            Self::Corotational => "corotational",
            Self::StableNeoHookean => "stable-neo-hookean",
            Self::Guccione => "guccione",
        }
    }

    /// Parses a scene-file name (see [`MaterialModel::scene_name`]); `None` if unknown.
    pub fn from_scene_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.scene_name() == name)
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
    /// Parameters of [`MaterialModel::Guccione`] (ignored by the other models). With that
    /// model `lambda_pa` is its bulk modulus and `mu_pa` its largest small-strain shear modulus
    /// ([`MaterialParams::with_guccione`]), so that time-step estimates and isotropic
    /// preconditioners see the right scale.
    pub guccione: GuccioneParams,
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
            guccione: GuccioneParams::isotropic(2.0 * e_pa / (2.0 * (1.0 + nu)), 1.0, 0.0),
        }
    }

    /// The Guccione material `g` (model [`MaterialModel::Guccione`]) with density
    /// `density_kg_per_m3`: `lambda_pa = g.bulk_modulus_pa`, `mu_pa = C max(b) / 2` (exact
    /// small-strain values in the isotropic limit). No viscosity or damping.
    pub fn with_guccione(g: GuccioneParams, density_kg_per_m3: f64) -> Self {
        Self {
            model: MaterialModel::Guccione,
            lambda_pa: g.bulk_modulus_pa,
            mu_pa: g.max_shear_modulus_pa(),
            phi_pa_s: 0.0,
            psi_pa_s: 0.0,
            density_kg_per_m3,
            mass_damping_per_s: 0.0,
            guccione: g,
        }
    }

    /// Whether the model's stress depends on a local frame (Guccione with distinct
    /// coefficients).
    pub fn is_anisotropic(&self) -> bool {
        self.model == MaterialModel::Guccione && !self.guccione.is_isotropic()
    }

    /// Whether the volumetric term is evaluated per element with the mean dilatation
    /// ([`GuccioneParams::mean_dilatation`]).
    pub fn mean_dilatation(&self) -> bool {
        self.model == MaterialModel::Guccione && self.guccione.mean_dilatation
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
        if self.model == MaterialModel::Guccione {
            let g = &self.guccione;
            let checks: [(&str, f64, bool); 5] = [
                ("material.guccione_c_pa", g.c_pa, g.c_pa > 0.0),
                ("material.b_f", g.b_f, g.b_f > 0.0),
                ("material.b_t", g.b_t, g.b_t > 0.0),
                ("material.b_fs", g.b_fs, g.b_fs > 0.0),
                (
                    "material.bulk_modulus_pa",
                    g.bulk_modulus_pa,
                    g.bulk_modulus_pa >= 0.0,
                ),
            ];
            for (field, v, ok) in checks {
                if !v.is_finite() || !ok {
                    return Err(ModelError::field(field, format!("{v} is not admissible")));
                }
            }
        }
        Ok(())
    }
}

pub mod corotational;
pub mod guccione;
pub mod neo_hookean;
pub mod stvk;
pub mod viscous;

pub use corotational::{polar_decomposition, rotation_variant_svd, symmetric_eigen};
pub use guccione::GuccioneParams;
pub use neo_hookean::{cofactor, cofactor_differential, neo_hookean_params};
pub use stvk::{green_strain, stvk_energy_density, stvk_stress};
pub use viscous::viscous_stress;

/// `tr(A)`.
#[inline]
pub(crate) fn trace(a: &DMat3) -> f64 {
    a.x_axis.x + a.y_axis.y + a.z_axis.z
}

/// Frobenius product `A : B = sum_ij A_ij B_ij`.
#[inline]
pub(crate) fn ddot(a: &DMat3, b: &DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

/// Elastic first Piola-Kirchhoff stress `P(F) = dPsi/dF` of `mat.model`, Pa, in the identity
/// frame ([`first_piola_oriented`]). StVK: `P = F S(E)`; corotational:
/// `P = 2 mu (F - R) + lambda tr(R^T F - I) R`; stable Neo-Hookean:
/// `P = mu F + lambda_s (J - alpha) cof(F)`; Guccione: `F S + kappa (J - 1) cof F`.
#[inline]
pub fn first_piola(mat: &MaterialParams, f: &DMat3) -> DMat3 {
    first_piola_oriented(mat, f, &DMat3::IDENTITY)
}

/// [`first_piola`] with the local material frame `frame` (orthonormal columns fibre, sheet,
/// sheet-normal in the rest configuration; only [`MaterialModel::Guccione`] uses it), Pa.
#[inline]
pub fn first_piola_oriented(mat: &MaterialParams, f: &DMat3, frame: &DMat3) -> DMat3 {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    match mat.model {
        MaterialModel::StVenantKirchhoff => stvk::first_piola(f, lambda, mu),
        MaterialModel::Corotational => corotational::first_piola(f, lambda, mu),
        MaterialModel::StableNeoHookean => neo_hookean::first_piola(f, lambda, mu),
        MaterialModel::Guccione => guccione::first_piola(&mat.guccione, f, frame),
    }
}

/// Exact directional derivative `dP = (dP/dF) : dF` of [`first_piola`] at `f` along `df`, Pa
/// (each law's module gives its formula), in the identity frame.
#[inline]
pub fn first_piola_differential(mat: &MaterialParams, f: &DMat3, df: &DMat3) -> DMat3 {
    first_piola_differential_oriented(mat, f, &DMat3::IDENTITY, df)
}

/// [`first_piola_differential`] in the local frame `frame` (see [`first_piola_oriented`]), Pa.
#[inline]
pub fn first_piola_differential_oriented(
    mat: &MaterialParams,
    f: &DMat3,
    frame: &DMat3,
    df: &DMat3,
) -> DMat3 {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    match mat.model {
        MaterialModel::StVenantKirchhoff => stvk::first_piola_differential(f, df, lambda, mu),
        MaterialModel::Corotational => corotational::first_piola_differential(f, df, lambda, mu),
        MaterialModel::StableNeoHookean => neo_hookean::first_piola_differential(f, df, lambda, mu),
        MaterialModel::Guccione => guccione::first_piola_differential(&mat.guccione, f, frame, df),
    }
}

/// Elastic strain energy density `Psi(F)` of `mat.model`, J/m^3 (zero at `F = I`), in the
/// identity frame.
#[inline]
pub fn energy_density(mat: &MaterialParams, f: &DMat3) -> f64 {
    energy_density_oriented(mat, f, &DMat3::IDENTITY)
}

/// [`energy_density`] in the local frame `frame` (see [`first_piola_oriented`]), J/m^3.
#[inline]
pub fn energy_density_oriented(mat: &MaterialParams, f: &DMat3, frame: &DMat3) -> f64 {
    let (lambda, mu) = (mat.lambda_pa, mat.mu_pa);
    match mat.model {
        MaterialModel::StVenantKirchhoff => stvk_energy_density(&green_strain(f), lambda, mu),
        MaterialModel::Corotational => corotational::energy_density(f, lambda, mu),
        MaterialModel::StableNeoHookean => neo_hookean::energy_density(f, lambda, mu),
        MaterialModel::Guccione => guccione::energy_density(&mat.guccione, f, frame),
    }
}
