//! Material parameters and constitutive laws (seed 000 section 2).
//!
//! - Green strain `E = (F^T F - I) / 2` (eq. 3-4),
//! - St. Venant-Kirchhoff second Piola-Kirchhoff stress `S = lambda tr(E) I + 2 mu E` (eq. 9),
//! - viscous stress from the strain rate `nu = F^T Fdot + Fdot^T F` (eq. 10),
//!   `S_v = 2 psi nu + phi tr(nu) I` (eq. 11), added to the elastic stress.
//!
//! Neighbours: [`crate::fem`] evaluates these per element; [`crate::scene`] fills
//! [`MaterialParams`] from a scene file.

use glam::DMat3;

use crate::ModelError;

/// Material parameters of a homogeneous body, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MaterialParams {
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
