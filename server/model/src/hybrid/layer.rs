//! [`LayerElements`]: with `hybrid.inactive_layer = "elements"` ([`super::InactiveLayer`]) the
//! FEM covers the whole wall and shares the wall's energy with the particles' meshfree terms:
//!
//! `E = sum_e (1 - a_e) E_e(x_c) + sum_(i in block) V_i Psi(F_i)`,
//!
//! where the block holds the terms the body evaluates (the active particles' and their
//! inactive neighbours', [`crate::meshfree::TermBlock`]) and `a_e` is the share of element
//! `e`'s volume whose particles' terms are in the block: `a_e = (n_e^block / n_e) c_e` with
//! `n_e` the particles tied to `e` (every particle lies in an element and follows its
//! interpolation) and `c_e = min(1, n_e s^3 / V_e)` the share of the element the particle
//! lattice covers. Where no particle is simulated the elements carry the layer's stiffness;
//! where the particles are simulated their terms take it over, element by element in
//! proportion. `a_e` is capped at [`MAX_REPLACED_SHARE`]: an element whose particles are all
//! simulated keeps a small share of its energy, so that its nodes, which the particles' ties
//! alone would leave free to drift against the particles' deviations (a zero-energy motion),
//! follow the particles.
//!
//! Neighbours: [`super::body::HybridBody`] counts the block's terms per element when it
//! refills them and calls [`LayerElements::subtract_forces`] after the FEM's forces; the
//! element loops use [`crate::element::FemModel`]'s integration points.

use glam::DVec3;

use super::prepare::HybridModel;
use crate::element::FemModel;
use crate::material::{energy_density_oriented, first_piola_oriented, viscous_stress};

/// Largest share of an element's energy the particles' terms replace (module documentation).
/// Measured on `lv-hybrid`: its effect on the press force is below 1 % (`docs/accuracy.md`).
pub const MAX_REPLACED_SHARE: f64 = 0.98;

/// The per-element shares of the wall's energy (module documentation), sized once.
#[derive(Debug, Clone)]
pub struct LayerElements {
    /// Particles tied to each element.
    particles: Vec<u32>,
    /// The share of each element the particle lattice covers, `c_e`.
    coverage: Vec<f64>,
    /// Block terms per element (counted by [`Self::count_term`]).
    terms: Vec<u32>,
    /// Elements with block terms.
    touched: Vec<u32>,
    /// `a_e` of the touched elements, in the order of `touched`.
    share: Vec<f64>,
}

impl LayerElements {
    /// The counts of `model`'s particles per element of `fem` (the model's core mesh).
    pub fn new(model: &HybridModel, fem: &FemModel) -> Self {
        let particles = model.particles_per_element();
        let cell_volume =
            |e: usize| -> f64 { fem.cell_points(e).map(|q| fem.ip_weight_m3(q)).sum() };
        let s3 = model.cloud.volume_m3();
        let coverage = particles
            .iter()
            .enumerate()
            .map(|(e, &n)| (n as f64 * s3 / cell_volume(e)).min(1.0))
            .collect();
        let ne = particles.len();
        Self {
            particles,
            coverage,
            terms: vec![0; ne],
            touched: Vec::with_capacity(ne),
            share: Vec::with_capacity(ne),
        }
    }

    /// Forgets the block's terms (before they are counted again).
    pub fn clear(&mut self) {
        for &e in &self.touched {
            self.terms[e as usize] = 0;
        }
        self.touched.clear();
        self.share.clear();
    }

    /// Counts one block term of a particle tied to element `e`.
    #[inline]
    pub fn count_term(&mut self, e: u32) {
        let t = &mut self.terms[e as usize];
        if *t == 0 {
            self.touched.push(e);
        }
        *t += 1;
    }

    /// Computes `a_e` of the counted elements.
    pub fn finish(&mut self) {
        self.share.clear();
        for &e in &self.touched {
            let e = e as usize;
            let a = self.terms[e] as f64 / self.particles[e].max(1) as f64 * self.coverage[e];
            self.share.push(a.min(MAX_REPLACED_SHARE));
        }
    }

    /// The elements whose energy the block's terms replace in part, with `a_e`.
    pub fn replaced(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        self.touched.iter().copied().zip(self.share.iter().copied())
    }

    /// Takes the replaced shares of the elements' internal forces out of `f` (N) for positions
    /// `x` (m) and, when given, velocities `v` (m/s, the viscous stress): adds
    /// `a_e w_q P(F_q) grad N_a` at each integration point of each replaced element, the
    /// opposite of what [`FemModel::add_internal_forces`] added, times `a_e`.
    pub fn subtract_forces(
        &self,
        fem: &FemModel,
        x: &[DVec3],
        v: Option<&[DVec3]>,
        f: &mut [DVec3],
    ) {
        let mat = fem.material();
        let viscous = v.filter(|_| mat.phi_pa_s > 0.0 || mat.psi_pa_s > 0.0);
        for (e, a) in self.replaced() {
            for q in fem.cell_points(e as usize) {
                let fm = fem.ip_field_gradient(q, x);
                let mut p = first_piola_oriented(mat, &fm, &fem.ip_frame(q));
                if let Some(v) = viscous {
                    let f_dot = fem.ip_field_gradient(q, v);
                    p += fm * viscous_stress(&fm, &f_dot, mat.phi_pa_s, mat.psi_pa_s);
                }
                fem.ip_scatter(q, &(p * (a * fem.ip_weight_m3(q))), f);
            }
        }
    }

    /// The elastic energy the replaced shares take out of the FEM's, J.
    pub fn replaced_energy(&self, fem: &FemModel, x: &[DVec3]) -> f64 {
        let mat = fem.material();
        let mut e_j = 0.0;
        for (e, a) in self.replaced() {
            for q in fem.cell_points(e as usize) {
                let fm = fem.ip_field_gradient(q, x);
                e_j +=
                    a * fem.ip_weight_m3(q) * energy_density_oriented(mat, &fm, &fem.ip_frame(q));
            }
        }
        e_j
    }
}
