//! Diagnostics for tests and the set-up check: momentum, energy and the power-iteration
//! estimate of the coupled system's largest eigenvalue.

use super::EigenEstimate;
use super::HybridBody;
use crate::ModelError;
use crate::hybrid::CoreStep;
use glam::DVec3;

impl HybridBody {
    /// Total linear momentum of the simulated degrees of freedom (core nodes and active
    /// particles; with `scaled_motion = "deviation"` the core nodes' alone, the momentum
    /// conjugate to a translation), kg m/s.
    pub fn linear_momentum(&self) -> DVec3 {
        let mut p = DVec3::ZERO;
        for (v, m) in self.state.vc.iter().zip(self.fem.lumped_mass_kg()) {
            p += *v * *m;
        }
        if !self.setup.deviation {
            for &q in &self.regions.active_list {
                p += self.state.vp[q as usize] * self.setup.particle_mass_kg;
            }
        }
        p
    }

    /// Kinetic and elastic energy (J) of the simulated degrees of freedom (the terms of the
    /// active set at the current tied positions; with `scaled_motion = "deviation"` the
    /// particles' kinetic part is their deviations').
    pub fn energy(&self) -> (f64, f64) {
        let mut kin = 0.0;
        for (v, m) in self.state.vc.iter().zip(self.fem.lumped_mass_kg()) {
            kin += 0.5 * m * v.length_squared();
        }
        for &q in &self.regions.active_list {
            kin += 0.5 * self.setup.particle_mass_kg * self.state.vp[q as usize].length_squared();
        }
        let replaced = self
            .pipeline
            .layer
            .as_ref()
            .map_or(0.0, |l| l.replaced_energy(&self.fem, &self.state.xc));
        let elastic = self.fem.elastic_energy(&self.state.xc) - replaced
            + self
                .pipeline
                .block
                .energy(&self.model.cloud, &self.state.xp);
        (kin, elastic)
    }

    /// Estimates the largest eigenvalue of `M^-1 K` of the current simulated system (free core
    /// nodes and active particles, tied particles following the core; `K` linearised at the
    /// current positions by forward differences of the forces, velocities held at zero, no
    /// probe) by power iteration on `M^-1/2 K M^-1/2`, stopping when the Rayleigh quotient
    /// changes by less than `tolerance` (relative) over ten iterations or after
    /// `max_iterations`. A diagnostic for studies of the explicit step (the body's own
    /// sub-steps use the Gershgorin bound of [`crate::meshfree::critical_time_step`]); the
    /// state is restored afterwards. Allocates.
    ///
    /// # Errors
    /// [`ModelError::NoConvergence`] when the quotient has not settled to `tolerance` after
    /// `max_iterations` (the message gives the last change).
    pub fn max_eigenvalue_estimate(
        &mut self,
        max_iterations: usize,
        tolerance: f64,
    ) -> Result<EigenEstimate, ModelError> {
        let x0c = self.state.xc.clone();
        let x0p = self.state.xp.clone();
        // Deviation mode: the active particles' coordinates are their deviations.
        let x0d = self.state.xd.clone();
        let v0c = std::mem::replace(&mut self.state.vc, vec![DVec3::ZERO; x0c.len()]);
        // The implicit core is not part of the explicit system: held.
        let free: Vec<bool> = self
            .fem
            .constraints()
            .iter()
            .map(|c| *c == 0 && self.model.params.core_step == CoreStep::Explicit)
            .collect();
        let inv_sqrt_mc: Vec<f64> = self
            .fem
            .lumped_mass_kg()
            .iter()
            .map(|m| 1.0 / m.sqrt())
            .collect();
        let inv_sqrt_mp = 1.0 / self.setup.particle_mass_kg.sqrt();
        let active = self.regions.active_list.clone();
        self.particle_forces(None);
        self.core_forces();
        let (f0c, f0p) = (self.scratch.fc.clone(), self.scratch.fp.clone());
        // Step length: 1e-7 of the particle spacing for a unit mass-weighted vector.
        let eps = 1e-7 * self.model.params.meshfree.spacing_m / inv_sqrt_mp;
        let (mut uc, mut up) = power_start(&free, x0p.len(), &active);
        let mut history = Vec::with_capacity(max_iterations);
        let mut result = None;
        for it in 0..max_iterations {
            let norm = (uc.iter().map(|u| u.length_squared()).sum::<f64>()
                + active
                    .iter()
                    .map(|&p| up[p as usize].length_squared())
                    .sum::<f64>())
            .sqrt();
            for (i, u) in uc.iter_mut().enumerate() {
                *u /= norm;
                self.state.xc[i] = x0c[i] + *u * (eps * inv_sqrt_mc[i]);
            }
            for &p in &active {
                let p = p as usize;
                up[p] /= norm;
                if self.setup.deviation {
                    self.state.xd[p] = x0d[p] + up[p] * (eps * inv_sqrt_mp);
                } else {
                    self.state.xp[p] = x0p[p] + up[p] * (eps * inv_sqrt_mp);
                }
            }
            self.state.xp_fresh = false;
            self.particle_forces(None);
            self.core_forces();
            // w = M^-1/2 K M^-1/2 u, with K u ~ -(f(x0 + eps M^-1/2 u) - f(x0)) / eps.
            let mut rayleigh = 0.0;
            for (i, u) in uc.iter_mut().enumerate() {
                let w = if free[i] {
                    -(self.scratch.fc[i] - f0c[i]) * (inv_sqrt_mc[i] / eps)
                } else {
                    DVec3::ZERO
                };
                rayleigh += w.dot(*u);
                *u = w;
            }
            for &p in &active {
                let p = p as usize;
                let w = -(self.scratch.fp[p] - f0p[p]) * (inv_sqrt_mp / eps);
                rayleigh += w.dot(up[p]);
                up[p] = w;
            }
            history.push(rayleigh);
            if it >= 10 {
                let change = (rayleigh - history[it - 10]).abs() / rayleigh.abs();
                if change < tolerance {
                    result = Some(EigenEstimate {
                        lambda_per_s2: rayleigh,
                        relative_change: change,
                        iterations: it + 1,
                        critical_step_s: 2.0 / rayleigh.sqrt(),
                    });
                    break;
                }
            }
        }
        self.state.xc.copy_from_slice(&x0c);
        self.state.xp.copy_from_slice(&x0p);
        self.state.xd.copy_from_slice(&x0d);
        self.state.xp_fresh = false;
        self.state.vc = v0c;
        self.particle_forces(None);
        result.ok_or_else(|| unsettled(&history, tolerance))
    }
}

/// The power iteration's deterministic start, every component present: core nodes where
/// `free`, then the `active` particles (of `np`), from a multiplicative hash of the index.
fn power_start(free: &[bool], np: usize, active: &[u32]) -> (Vec<DVec3>, Vec<DVec3>) {
    let start = |i: usize| {
        let h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        DVec3::new(
            (h >> 40) as f64 / (1u64 << 24) as f64 - 0.5,
            ((h >> 20) & 0xF_FFFF) as f64 / (1u64 << 20) as f64 - 0.5,
            (h & 0xF_FFFF) as f64 / (1u64 << 20) as f64 - 0.5,
        )
    };
    let nc = free.len();
    let uc = (0..nc)
        .map(|i| if free[i] { start(i) } else { DVec3::ZERO })
        .collect();
    let mut up = vec![DVec3::ZERO; np];
    for &p in active {
        up[p as usize] = start(nc + p as usize);
    }
    (uc, up)
}

/// The error of a power iteration whose Rayleigh quotients `history` did not settle to
/// `tolerance` over ten iterations.
fn unsettled(history: &[f64], tolerance: f64) -> ModelError {
    let n = history.len();
    let change = if n > 10 {
        (history[n - 1] - history[n - 11]).abs() / history[n - 1].abs()
    } else {
        f64::NAN
    };
    ModelError::NoConvergence(format!(
        "power iteration for lambda_max: relative change {change:.2e} after {n} iterations (tolerance {tolerance:.1e})"
    ))
}
