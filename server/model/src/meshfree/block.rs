//! [`TermBlock`]: the run-time energy terms of a set of particles (the active ones and the
//! inactive neighbours whose terms reach them), with their rest data filled once when the set
//! changes, and [`critical_time_step`], the explicit stability limit of a cloud.
//!
//! **Energy and force (seed 000 eq. 26-29, total-Lagrangian).** Term `i` (owner particle `i`,
//! neighbours `j`, rest data from [`ParticleCloud::term_rest`]) has
//! `F_i = sum_j (x_j - x_i) (x) g_ij` and the energy `V_i Psi(F_i)`; its gradient is
//! `d/dx_j = V_i P_i g_ij`, `d/dx_i = -V_i P_i sum_j g_ij` with `P = dPsi/dF` (eq. 29's
//! `sum_j V_i V_j sigma grad W_ij` in first Piola-Kirchhoff form). The corrected variant adds
//! the hourglass energy `sum_j c_ij |e_ij|^2 / 2`, `e_ij = F_i X_ij - x_ij`, whose gradient is
//! `d/dx_j = H_i g_ij - c_ij e_ij` with `H_i = sum_j c_ij e_ij (x) X_ij` (and minus the sum for
//! the owner). Forces are minus these gradients, so they sum to zero in every term (linear
//! momentum) and vanish for rigid motions.
//!
//! The seed variant uses St. Venant-Kirchhoff (seed eq. 9) with the strain measured from the
//! kernel estimate at rest, `E_i = (F_i^T F_i - A_i^T A_i) / 2` ([`super::cloud`]).
//!
//! Neighbours: rest data from [`super::cloud`]; used by the hybrid body.

use glam::{DMat3, DVec3};

use super::MeshfreeVariant;
use super::cloud::{MAX_STENCIL, ParticleCloud, TermRest, outer};
use crate::ModelError;
use crate::material::stvk::{green_strain, stvk_energy_density, stvk_stress};
use crate::material::{energy_density, first_piola};

/// The energy terms of a set of particles (module documentation), sized once.
#[derive(Debug, Clone)]
pub struct TermBlock {
    stride: usize,
    capacity: usize,
    len: usize,
    seed: bool,
    owner: Vec<u32>,
    count: Vec<u32>,
    nbr: Vec<u32>,
    g: Vec<DVec3>,
    offset: Vec<DVec3>,
    hourglass: Vec<f64>,
    g_sum: Vec<DVec3>,
    rest_strain: Vec<DMat3>,
    scratch: Box<TermRest>,
    nbr_scratch: [u32; MAX_STENCIL],
}

impl TermBlock {
    /// An empty block for up to `capacity` terms of particles of `cloud`.
    pub fn new(cloud: &ParticleCloud, capacity: usize) -> Self {
        let stride = cloud.stencil_len();
        Self {
            stride,
            capacity,
            len: 0,
            seed: cloud.params().variant == MeshfreeVariant::Seed,
            owner: vec![0; capacity],
            count: vec![0; capacity],
            nbr: vec![0; capacity * stride],
            g: vec![DVec3::ZERO; capacity * stride],
            offset: vec![DVec3::ZERO; capacity * stride],
            hourglass: vec![0.0; capacity * stride],
            g_sum: vec![DVec3::ZERO; capacity],
            rest_strain: vec![DMat3::ZERO; capacity],
            scratch: Box::default(),
            nbr_scratch: [0; MAX_STENCIL],
        }
    }

    /// Number of terms.
    #[inline]
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the block has no term.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Largest number of terms.
    #[inline]
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Owner particle of each term.
    #[inline]
    pub fn owners(&self) -> &[u32] {
        &self.owner[..self.len]
    }

    /// Neighbours of term `t`.
    #[inline]
    pub fn neighbours(&self, t: usize) -> &[u32] {
        let base = t * self.stride;
        &self.nbr[base..base + self.count[t] as usize]
    }

    /// Removes every term (allocation-free).
    pub fn clear(&mut self) {
        self.len = 0;
    }

    /// Adds the term of particle `p` (its rest data, [`ParticleCloud::term_rest`]).
    /// Allocation-free. Returns `Ok(false)` (nothing added) when the block is full.
    ///
    /// # Errors
    /// As [`ParticleCloud::term_rest`] (a degenerate neighbourhood in the corrected variant).
    pub fn push(&mut self, cloud: &ParticleCloud, p: u32) -> Result<bool, ModelError> {
        if self.len == self.capacity {
            return Ok(false);
        }
        let n = cloud.neighbours(p, &mut self.nbr_scratch);
        cloud.term_rest(p, &self.nbr_scratch[..n], &mut self.scratch)?;
        let t = self.len;
        let base = t * self.stride;
        self.owner[t] = p;
        self.count[t] = n as u32;
        self.nbr[base..base + n].copy_from_slice(&self.nbr_scratch[..n]);
        self.g[base..base + n].copy_from_slice(&self.scratch.g[..n]);
        self.offset[base..base + n].copy_from_slice(&self.scratch.offset_m[..n]);
        self.hourglass[base..base + n].copy_from_slice(&self.scratch.hourglass_n_per_m[..n]);
        self.g_sum[t] = self.scratch.g_sum;
        self.rest_strain[t] = self.scratch.rest_strain;
        self.len += 1;
        Ok(true)
    }

    /// Deformation gradient `F_t` of term `t` at positions `x` (m, indexed by particle).
    #[inline]
    pub fn deformation_gradient(&self, t: usize, x: &[DVec3]) -> DMat3 {
        let base = t * self.stride;
        let xi = x[self.owner[t] as usize];
        let mut f = DMat3::ZERO;
        for k in 0..self.count[t] as usize {
            f += outer(x[self.nbr[base + k] as usize] - xi, self.g[base + k]);
        }
        f
    }

    /// Sets `f[p] = 0` for every particle `p` a term touches (owners and neighbours).
    pub fn zero_forces(&self, f: &mut [DVec3]) {
        for t in 0..self.len {
            f[self.owner[t] as usize] = DVec3::ZERO;
            for &q in self.neighbours(t) {
                f[q as usize] = DVec3::ZERO;
            }
        }
    }

    /// Adds the elastic (and hourglass) forces of every term (N) at positions `x` (m) into
    /// `f`, both indexed by particle (length at least the cloud's particle count).
    /// Allocation-free.
    pub fn add_forces(&self, cloud: &ParticleCloud, x: &[DVec3], f: &mut [DVec3]) {
        let v = cloud.volume_m3();
        let mat = cloud.material();
        for t in 0..self.len {
            let base = t * self.stride;
            let n = self.count[t] as usize;
            let i = self.owner[t] as usize;
            let xi = x[i];
            let mut fg = DMat3::ZERO;
            for k in 0..n {
                fg += outer(x[self.nbr[base + k] as usize] - xi, self.g[base + k]);
            }
            let p = if self.seed {
                let e = green_strain(&fg) - self.rest_strain[t];
                fg * stvk_stress(&e, mat.lambda_pa, mat.mu_pa)
            } else {
                first_piola(mat, &fg)
            };
            // m = V P + H (the matrix applied to g_ij), minus c e for the hourglass part.
            let mut m = p * v;
            if !self.seed {
                // Pair errors e_ij once, then H and the gradients.
                let mut e = [DVec3::ZERO; MAX_STENCIL];
                let mut h = DMat3::ZERO;
                for (k, ek) in e[..n].iter_mut().enumerate() {
                    let xk = self.offset[base + k];
                    *ek = fg * xk - (x[self.nbr[base + k] as usize] - xi);
                    h += outer(*ek * self.hourglass[base + k], xk);
                }
                m += h;
                let mut owner = DVec3::ZERO;
                for (k, ek) in e[..n].iter().enumerate() {
                    let j = self.nbr[base + k] as usize;
                    let grad = m * self.g[base + k] - *ek * self.hourglass[base + k];
                    f[j] -= grad;
                    owner += grad;
                }
                f[i] += owner;
            } else {
                for k in 0..n {
                    f[self.nbr[base + k] as usize] -= m * self.g[base + k];
                }
                f[i] += m * self.g_sum[t];
            }
        }
    }

    /// Total energy of the terms (elastic plus hourglass), J, at positions `x` (m).
    pub fn energy(&self, cloud: &ParticleCloud, x: &[DVec3]) -> f64 {
        let v = cloud.volume_m3();
        let mat = cloud.material();
        let mut total = 0.0;
        for t in 0..self.len {
            let base = t * self.stride;
            let fg = self.deformation_gradient(t, x);
            total += v * if self.seed {
                let e = green_strain(&fg) - self.rest_strain[t];
                stvk_energy_density(&e, mat.lambda_pa, mat.mu_pa)
            } else {
                energy_density(mat, &fg)
            };
            if !self.seed {
                let xi = x[self.owner[t] as usize];
                for k in 0..self.count[t] as usize {
                    let j = self.nbr[base + k] as usize;
                    let e = fg * self.offset[base + k] - (x[j] - xi);
                    total += 0.5 * self.hourglass[base + k] * e.length_squared();
                }
            }
        }
        total
    }
}

/// Explicit stability limit of the whole cloud, s: `2 / sqrt(lambda_max)` of `M^-1 K` at rest,
/// with `lambda_max` bounded above by Gershgorin's theorem on the linearised stiffness of every
/// term (elastic block norms `V_i c |g_ij| |g_ik|` plus the hourglass blocks). At rest every law
/// linearises to isotropic elasticity, whose block `K_jk u = V (lambda g_j (g_k . u) + mu (u
/// (g_k . g_j) + g_k (u . g_j)))` has norm at most `V (lambda + 2 mu) |g_j| |g_k|`, so
/// `c = lambda + 2 mu`. Conservative: the true limit is larger (tests/meshfree.rs: stable at
/// 0.9 times the bound, divergent at 3 times). Used for the Verlet step of seed eq. 33 and its velocity form.
///
/// Cost: one pass over every particle's neighbourhood (no storage beyond one `f64` per
/// particle).
///
/// # Errors
/// As [`ParticleCloud::term_rest`].
pub fn critical_time_step(cloud: &ParticleCloud) -> Result<f64, ModelError> {
    let n = cloud.len();
    let mat = cloud.material();
    let c = mat.lambda_pa.max(0.0) + 2.0 * mat.mu_pa;
    let v = cloud.volume_m3();
    let mut row = vec![0.0f64; n];
    let mut nbr = [0u32; MAX_STENCIL];
    let mut rest = Box::<TermRest>::default();
    let mut coef = [0.0f64; MAX_STENCIL + 1];
    for p in 0..n as u32 {
        let k = cloud.neighbours(p, &mut nbr);
        cloud.term_rest(p, &nbr[..k], &mut rest)?;
        // Elastic: row sums of |K_ab| <= V c |g_a| (sum_b |g_b|), the owner's g being -g_sum.
        let total: f64 = rest.g[..k].iter().map(|g| g.length()).sum::<f64>() + rest.g_sum.length();
        for m in 0..k {
            row[nbr[m] as usize] += v * c * rest.g[m].length() * total;
        }
        row[p as usize] += v * c * rest.g_sum.length() * total;
        // Hourglass: e_q = sum_m B_qm x'_m, B_qm = g_m . X_q - delta_qm, owner -sum_m B_qm.
        for q in 0..k {
            let cq = rest.hourglass_n_per_m[q];
            if cq == 0.0 {
                continue;
            }
            let mut owner = 0.0;
            let mut abs_sum = 0.0;
            for (m, (g, out)) in rest.g[..k].iter().zip(&mut coef[..k]).enumerate() {
                let b = g.dot(rest.offset_m[q]) - if m == q { 1.0 } else { 0.0 };
                *out = b;
                owner -= b;
                abs_sum += b.abs();
            }
            abs_sum += owner.abs();
            for (q, c) in nbr[..k].iter().zip(&coef[..k]) {
                row[*q as usize] += cq * c.abs() * abs_sum;
            }
            row[p as usize] += cq * owner.abs() * abs_sum;
        }
    }
    let lambda_max = row.iter().fold(0.0f64, |a, &r| a.max(r)) / cloud.mass_kg();
    Ok(if lambda_max > 0.0 {
        2.0 / lambda_max.sqrt()
    } else {
        f64::INFINITY
    })
}
