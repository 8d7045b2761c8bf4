//! [`ParticleProxy`]: the hybrid body's probe, a god-object (proxy) sphere pressed on the
//! active particles and joined to the device point by the virtual coupling (DESIGN.md section
//! 5: "the probe is a rigid sphere touching the surface through a proxy (god object) and a
//! virtual coupling"; the FEM family's is [`crate::contact::Probe`], whose contact geometry is
//! the body's surface triangles, where the hybrid's is its particles).
//!
//! **The proxy.** With the device at `x_d`, the sphere of radius `r` centred at `c` presses
//! every active particle closer than its reach `R_p = r + t_p` with the penalty `k g_p n_p`,
//! `g_p = R_p - |x_p - c|`, `n_p = (x_p - c) / |x_p - c|` (`k` =
//! `hybrid.contact_stiffness_n_per_m`). `t_p` is the particle's *skin*, the material it stands
//! for outside its centre: for a surface particle (less than a lattice spacing `s` below the
//! body's outer surface at rest) its rest depth below that surface, so that the sphere touches
//! it where it touches the body's surface, whatever the lattice's alignment with the surface;
//! for the others half a spacing (a particle stands for a cell of size `s`).
//! [`ParticleProxy::uniform`]: every skin `s / 2` (before 2026-11-26 the only choice: the
//! particles' contact surface then stood up to `s / 2` off the body's, 0.035 mm inside it
//! to 0.023 mm outside it at the lv-probe point for spacings of 0.3 to 0.2 mm, which moved
//! the 0.5 mm press by several per cent from one spacing to the next, `docs/accuracy.md`).
//! The proxy is massless: its centre minimises
//!
//! `E(c) = k_c / 2 |c - x_d|^2 + sum_p k / 2 g_p(c)_+^2`,
//!
//! the coupling's energy (`k_c` = `probe.coupling_stiffness_n_per_m`) plus the penalty's, so
//! the coupling force `k_c (c - x_d)` on the device equals the particles' reaction, and the
//! body's collective motion under the probe sees the coupling in series with the penalty
//! springs (at most `k_c`) instead of the sum of hundreds of them, which an explicit step of
//! the particles and the core's explicit coupling forces cannot carry (`lv-hybrid` pressed
//! 3 mm chattered between 0 and 107 mN from one tick to the next without it). The minimum is
//! found by Gauss-Newton steps (`H = k_c I + sum_p k n_p n_p^T`) with a backtracking line
//! search on `E`, from the last proxy while in contact (a god-object does not pass through
//! the surface) or from the device point out of contact.
//!
//! Neighbours: driven by [`super::body::HybridBody`] every sub-step with the particles'
//! positions; [`crate::contact::ProbeParams`] for the sphere and the coupling.

use glam::{DMat3, DVec3};

use crate::contact::ProbeParams;

/// Most Gauss-Newton iterations of one proxy solve (it converges in 2-6 from the last
/// proxy; an unconverged solve keeps its best iterate and is counted).
const MAX_ITERATIONS: usize = 40;

/// The proxy solve stops when a step is below this share of the lattice spacing.
const STEP_TOLERANCE: f64 = 1e-9;

/// The proxy solve converges when the force balance on the proxy is off by less than this,
/// N (or a millionth of the coupling force).
const FORCE_TOLERANCE_N: f64 = 1e-7;

/// The hybrid body's probe (module documentation): parameters, the proxy and scratch.
#[derive(Debug, Clone)]
pub struct ParticleProxy {
    radius_m: f64,
    /// Each particle's reach `r + t_p`, m.
    reach_m: Vec<f64>,
    /// The largest reach, m.
    max_reach_m: f64,
    spacing_m: f64,
    k_particle_n_per_m: f64,
    k_coupling_n_per_m: f64,
    proxy_m: DVec3,
    in_contact: bool,
    /// Particles near the sphere this update (scratch, capacity of the active set).
    near: Vec<u32>,
    /// Proxy solves that reached [`MAX_ITERATIONS`].
    unconverged: u64,
}

/// Result of one [`ParticleProxy::update`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProxyContact {
    /// Force on the device, N: the coupling's `k_c (c - x_d)`.
    pub force_on_device_n: DVec3,
    /// The stiffness felt at the device, `-d F_device / d x_device`, 3x3 row-major, N/m
    /// (positive definite, as [`crate::contact::Probe`]'s `k_c n n^T`): the coupling in series
    /// with the penalty springs, `k_c I - k_c^2 (k_c I + sum k n n^T)^-1`.
    pub stiffness_n_per_m: [f64; 9],
    /// The proxy's centre, m (the device point out of contact).
    pub proxy_m: DVec3,
    /// Whether a particle touches the proxy sphere.
    pub in_contact: bool,
}

impl ParticleProxy {
    /// A proxy for a probe of `probe.radius_m` with the coupling `probe.
    /// coupling_stiffness_n_per_m`, pressing particles of lattice spacing `spacing_m` (m) with
    /// `k_particle_n_per_m` each; `skin_m`: each particle's skin `t_p` (m, module
    /// documentation; indexed like the positions given to [`Self::update`]); `capacity`: most
    /// active particles.
    pub fn new(
        probe: &ProbeParams,
        spacing_m: f64,
        k_particle_n_per_m: f64,
        skin_m: &[f64],
        capacity: usize,
    ) -> Self {
        let reach_m: Vec<f64> = skin_m.iter().map(|t| probe.radius_m + t).collect();
        let max_reach_m = reach_m
            .iter()
            .copied()
            .fold(probe.radius_m + 0.5 * spacing_m, f64::max);
        Self {
            radius_m: probe.radius_m,
            reach_m,
            max_reach_m,
            spacing_m,
            k_particle_n_per_m,
            k_coupling_n_per_m: probe.coupling_stiffness_n_per_m,
            proxy_m: DVec3::ZERO,
            in_contact: false,
            near: Vec::with_capacity(capacity),
            unconverged: 0,
        }
    }

    /// A proxy whose `particles` particles all have the skin `s / 2` (module documentation).
    pub fn uniform(
        probe: &ProbeParams,
        spacing_m: f64,
        k_particle_n_per_m: f64,
        particles: usize,
        capacity: usize,
    ) -> Self {
        let skin = vec![0.5 * spacing_m; particles];
        Self::new(probe, spacing_m, k_particle_n_per_m, &skin, capacity)
    }

    /// The distance from the sphere's centre within which particle `p` is pressed, m.
    pub fn reach_m(&self, p: usize) -> f64 {
        self.reach_m[p]
    }

    /// The probe sphere's radius, m.
    pub fn radius_m(&self) -> f64 {
        self.radius_m
    }

    /// The last proxy and whether it was in contact.
    pub fn state(&self) -> (DVec3, bool) {
        (self.proxy_m, self.in_contact)
    }

    /// Proxy solves that stopped at the iteration cap since the body was built.
    pub fn unconverged_solves(&self) -> u64 {
        self.unconverged
    }

    /// Forgets the contact (the next update starts from the device point).
    pub fn reset(&mut self) {
        self.in_contact = false;
    }

    /// `E(c)` over the near particles, its gradient (N) and Hessian (N/m): the Newton matrix
    /// `k_c I + sum k (n n^T - g / |x_p - c| (I - n n^T))`, or its Gauss-Newton part
    /// `k_c I + sum k n n^T` when `gauss_newton` (always positive definite).
    fn energy(
        &self,
        c: DVec3,
        device_m: DVec3,
        x: &[DVec3],
        gauss_newton: bool,
    ) -> (f64, DVec3, DMat3) {
        let (k, kc) = (self.k_particle_n_per_m, self.k_coupling_n_per_m);
        let d = c - device_m;
        let mut e = 0.5 * kc * d.length_squared();
        let mut grad = d * kc;
        let mut nn = DMat3::ZERO;
        let mut tangential = 0.0;
        for &p in &self.near {
            let r = x[p as usize] - c;
            let dist = r.length();
            let reach = self.reach_m[p as usize];
            if dist < reach && dist > 0.0 {
                let g = reach - dist;
                let n = r / dist;
                e += 0.5 * k * g * g;
                grad += n * (k * g);
                let w = if gauss_newton { 0.0 } else { g / dist };
                nn += DMat3::from_cols(n * n.x, n * n.y, n * n.z) * (k * (1.0 + w));
                tangential += k * w;
            }
        }
        let h = nn + DMat3::from_diagonal(DVec3::splat(kc - tangential));
        (e, grad, h)
    }

    /// Solves the proxy for the device at `device_m` against the particles `active` at `x`
    /// (m) and adds the penalty forces to `f` when given (N, indexed like `x`).
    /// Allocation-free.
    pub fn update(
        &mut self,
        device_m: DVec3,
        x: &[DVec3],
        active: &[u32],
        f: Option<&mut [DVec3]>,
    ) -> ProxyContact {
        let start = if self.in_contact {
            self.proxy_m
        } else {
            device_m
        };
        self.gather_near(start, device_m, x, active);
        let c = self.minimise(start, device_m, x);
        self.contact_at(c, device_m, x, f)
    }

    /// The particles of `active` (positions `x`, m) the iterates from `start` can reach, into
    /// `near`.
    fn gather_near(&mut self, start: DVec3, device_m: DVec3, x: &[DVec3], active: &[u32]) {
        // Every particle the iterates can reach: they stay between the start and the device,
        // within the largest penetration the coupling allows.
        let span = (start - device_m).length();
        let gather = self.max_reach_m + span + self.spacing_m;
        let (mid, g2) = (0.5 * (start + device_m), (gather + 0.5 * span).powi(2));
        self.near.clear();
        for &p in active {
            if (x[p as usize] - mid).length_squared() < g2 {
                self.near.push(p);
            }
        }
    }

    /// The proxy position minimising `E` from `start` over the `near` particles (Newton with
    /// backtracking, Gauss-Newton where the Newton matrix is not positive definite); counts
    /// an unconverged solve.
    fn minimise(&mut self, start: DVec3, device_m: DVec3, x: &[DVec3]) -> DVec3 {
        let mut c = start;
        let (mut e, mut grad, _) = self.energy(c, device_m, x, false);
        let mut converged = false;
        for _ in 0..MAX_ITERATIONS {
            // Converged when the force balance is off by less than a micronewton-scale share
            // of the coupling force (far below the 7 % force JND).
            let tolerance =
                FORCE_TOLERANCE_N.max(1e-6 * self.k_coupling_n_per_m * (c - device_m).length());
            if grad.length() <= tolerance {
                converged = true;
                break;
            }
            // Newton where its matrix is positive definite, Gauss-Newton otherwise.
            let (_, _, h) = self.energy(c, device_m, x, false);
            let newton = h.determinant() > 0.0
                && h.col(0).x > 0.0
                && h.col(0).x * h.col(1).y - h.col(0).y * h.col(1).x > 0.0;
            let h = if newton {
                h
            } else {
                self.energy(c, device_m, x, true).2
            };
            let step = -(h.inverse() * grad);
            if !step.is_finite() || step.length() < STEP_TOLERANCE * self.spacing_m {
                converged = step.is_finite();
                break;
            }
            // Backtracking on E.
            let mut t = 1.0;
            let mut accepted = false;
            for _ in 0..30 {
                let trial = c + step * t;
                let (e1, g1, _) = self.energy(trial, device_m, x, false);
                if e1 <= e {
                    (c, e, grad) = (trial, e1, g1);
                    accepted = true;
                    break;
                }
                t *= 0.5;
            }
            if !accepted {
                // No decrease along a descent direction: E is at its minimum to round-off.
                converged = true;
                break;
            }
        }
        if !converged {
            self.unconverged += 1;
        }
        c
    }

    /// The contact at proxy position `c`: the penalty forces added to `f` when given (N,
    /// indexed like `x`), the new proxy state, and the device force and stiffness.
    fn contact_at(
        &mut self,
        c: DVec3,
        device_m: DVec3,
        x: &[DVec3],
        mut f: Option<&mut [DVec3]>,
    ) -> ProxyContact {
        // Forces at the final proxy.
        let k = self.k_particle_n_per_m;
        let mut touching = false;
        let mut ks = DMat3::ZERO;
        for &p in &self.near {
            let r = x[p as usize] - c;
            let dist = r.length();
            let reach = self.reach_m[p as usize];
            if dist < reach && dist > 0.0 {
                let n = r / dist;
                if let Some(f) = f.as_deref_mut() {
                    f[p as usize] += n * (k * (reach - dist));
                }
                ks += DMat3::from_cols(n * n.x, n * n.y, n * n.z) * k;
                touching = true;
            }
        }
        self.in_contact = touching;
        self.proxy_m = if touching { c } else { device_m };
        let kc = self.k_coupling_n_per_m;
        let mut stiffness = [0.0; 9];
        let force = if touching {
            let series = DMat3::from_diagonal(DVec3::splat(kc))
                - (ks + DMat3::from_diagonal(DVec3::splat(kc))).inverse() * (kc * kc);
            for r in 0..3 {
                for s in 0..3 {
                    stiffness[3 * r + s] = series.col(s)[r];
                }
            }
            (c - device_m) * kc
        } else {
            DVec3::ZERO
        };
        ProxyContact {
            force_on_device_n: force,
            stiffness_n_per_m: stiffness,
            proxy_m: self.proxy_m,
            in_contact: touching,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat square of particles pressed by the device below it: the proxy rests where the
    /// coupling's force equals the particles' reaction, and the device force is that reaction.
    #[test]
    fn the_proxy_balances_the_coupling_against_the_particles() {
        let s = 2.5e-4;
        let mut x = Vec::new();
        for i in -20..=20 {
            for j in -20..=20 {
                x.push(DVec3::new(i as f64 * s, j as f64 * s, 0.0));
            }
        }
        let active: Vec<u32> = (0..x.len() as u32).collect();
        let probe = ProbeParams::default();
        let mut proxy = ParticleProxy::uniform(&probe, s, 16.0, x.len(), x.len());
        let r = probe.radius_m;
        // The device 0.1 mm into the plane of particle centres (less their half spacing).
        let device = DVec3::new(1e-5, -2e-5, r + 0.5 * s - 1e-4);
        let mut f = vec![DVec3::ZERO; x.len()];
        let out = proxy.update(device, &x, &active, Some(&mut f));
        assert!(out.in_contact);
        // Balanced to the solve's tolerance (its force balance, 1e-7 N here against 8.3 mN).
        let reaction: DVec3 = -f.iter().sum::<DVec3>();
        assert!(
            (reaction - out.force_on_device_n).length() <= FORCE_TOLERANCE_N,
            "{reaction} against {}",
            out.force_on_device_n
        );
        // The proxy sits between the device and the plane, pushed back along +z.
        assert!(out.proxy_m.z > device.z && out.proxy_m.z < r + 0.5 * s);
        assert!(out.force_on_device_n.z > 0.0);
        // The stiffness is minus the derivative of the device force: central differences.
        let h = 1e-7;
        for axis in 0..3 {
            let mut e = DVec3::ZERO;
            e[axis] = h;
            let mut plus = proxy.clone();
            let mut minus = proxy.clone();
            let fp = plus.update(device + e, &x, &active, None).force_on_device_n;
            let fm = minus
                .update(device - e, &x, &active, None)
                .force_on_device_n;
            let fd = (fp - fm) / (2.0 * h);
            for row in 0..3 {
                let k = out.stiffness_n_per_m[3 * row + axis];
                assert!(
                    (-fd[row] - k).abs() < 0.05 * probe.coupling_stiffness_n_per_m,
                    "-d F_{row} / d x_{axis}: {} against {k}",
                    -fd[row]
                );
            }
        }
    }
}
