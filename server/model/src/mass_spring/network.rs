//! The spring network of eq. 2 (Zhang, Payandeh & Dill): per node a home spring `K_h` to its
//! rest (initial) position, per mesh edge a linear spring `K_m` with its rest length, and
//! velocity damping `K_d`:
//!
//! `f_i = -K_d v_i + K_h l_i + sum_j K_m (l_ij / |l_ij|) (|l_ij| - r_ij) + f_i^e`,
//!
//! `l_i` the vector from the node to its rest position, `l_ij` from node i to neighbour j,
//! `r_ij` the rest length. This module holds the elastic part (forces, energy, the tangent for
//! static solves, the Gershgorin bound on the stiffness-to-mass ratio that fixes the stable
//! time step) and the static equilibrium of a network pressed at a contact ([`press`], the
//! experiment of section 3.2.2 behind eq. 4 and the calibration).
//!
//! Neighbours: used by [`super::calibration`] (static solves), the body (forces, energy,
//! stability) and the tests.

use glam::{DMat3, DVec3};

use crate::ModelError;

/// A linear mesh spring between nodes `i` and `j`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spring {
    /// First node.
    pub i: u32,
    /// Second node.
    pub j: u32,
    /// Rest length `r_ij`, m.
    pub rest_length_m: f64,
    /// Spring constant `K_m` (or `K'_m`), N/m.
    pub stiffness_n_per_m: f64,
}

/// A spring network for static problems: rest positions, fixed nodes, home springs, mesh
/// springs. All slices have one entry per node.
#[derive(Debug, Clone, Default)]
pub struct Network {
    /// Rest positions, m.
    pub rest: Vec<DVec3>,
    /// Nodes held at rest (clamped, outside a local patch, or unused slots).
    pub fixed: Vec<bool>,
    /// Home spring constant per node, N/m.
    pub home_n_per_m: Vec<f64>,
    /// Mesh springs.
    pub springs: Vec<Spring>,
}

/// Force of spring `s` on node `s.i` at positions `x` (N): `K (|l| - r) l / |l|`, `l = x_j -
/// x_i` (eq. 2). Zero for a spring of zero length (its direction is undefined).
#[inline]
pub fn spring_force(s: &Spring, x: &[DVec3]) -> DVec3 {
    let d = x[s.j as usize] - x[s.i as usize];
    let len = d.length();
    if len > 0.0 {
        d * (s.stiffness_n_per_m * (len - s.rest_length_m) / len)
    } else {
        DVec3::ZERO
    }
}

/// Elastic energy of spring `s`, J: `K (|l| - r)^2 / 2`.
#[inline]
pub fn spring_energy(s: &Spring, x: &[DVec3]) -> f64 {
    let stretch = (x[s.j as usize] - x[s.i as usize]).length() - s.rest_length_m;
    0.5 * s.stiffness_n_per_m * stretch * stretch
}

impl Network {
    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.rest.len()
    }

    /// Elastic forces of eq. 2 (home and mesh springs; no damping, no external force) at
    /// positions `x` (m), N, into `f` (overwritten). Fixed nodes get zero.
    ///
    /// # Panics
    /// If `x` or `f` are shorter than the node count.
    pub fn elastic_forces(&self, x: &[DVec3], f: &mut [DVec3]) {
        for (i, fi) in f.iter_mut().enumerate().take(self.rest.len()) {
            *fi = (self.rest[i] - x[i]) * self.home_n_per_m[i];
        }
        for s in &self.springs {
            let fs = spring_force(s, x);
            f[s.i as usize] += fs;
            f[s.j as usize] -= fs;
        }
        for (fi, &fixed) in f.iter_mut().zip(&self.fixed) {
            if fixed {
                *fi = DVec3::ZERO;
            }
        }
    }

    /// Elastic energy at positions `x`, J: `sum K_h |l_i|^2 / 2 + sum K_m (|l_ij| - r_ij)^2 / 2`.
    pub fn elastic_energy(&self, x: &[DVec3]) -> f64 {
        let home: f64 = self
            .rest
            .iter()
            .zip(x)
            .zip(&self.home_n_per_m)
            .map(|((r, x), k)| 0.5 * k * (*x - *r).length_squared())
            .sum();
        home + self
            .springs
            .iter()
            .map(|s| spring_energy(s, x))
            .sum::<f64>()
    }
}

/// The upper bound on the largest eigenvalue of `M^-1 K` (1/s^2) by Gershgorin's theorem on
/// the symmetric scaling `M^-1/2 K M^-1/2` with 3x3 blocks (every block of a spring's tangent
/// at rest has norm `K`; a stretched spring's tangent too): for node i,
/// `(K_h,i + sum_j K_ij) / m_i + sum_j K_ij / sqrt(m_i m_j)`, maximised over the free nodes.
/// `home`, `mass` per node; `springs` as `(i, j, K)`; fixed nodes are skipped. A spring
/// compressed below half its rest length has a larger transverse tangent than `K` and is not
/// covered.
pub fn gershgorin_bound_per_s2(
    home_n_per_m: &[f64],
    mass_kg: &[f64],
    fixed: &[bool],
    springs: impl Iterator<Item = (u32, u32, f64)>,
    scratch_diag: &mut [f64],
    scratch_off: &mut [f64],
) -> f64 {
    let n = home_n_per_m.len();
    scratch_diag[..n].copy_from_slice(home_n_per_m);
    scratch_off[..n].iter_mut().for_each(|v| *v = 0.0);
    for (i, j, k) in springs {
        let (i, j) = (i as usize, j as usize);
        scratch_diag[i] += k;
        scratch_diag[j] += k;
        let c = k / (mass_kg[i] * mass_kg[j]).sqrt();
        scratch_off[i] += c;
        scratch_off[j] += c;
    }
    (0..n)
        .filter(|&i| !fixed[i] && mass_kg[i] > 0.0)
        .map(|i| scratch_diag[i] / mass_kg[i] + scratch_off[i])
        .fold(0.0, f64::max)
}

/// The critical time step of symplectic Euler for a largest eigenvalue `lambda` (1/s^2) of
/// `M^-1 K`: `2 / sqrt(lambda)` (s; infinite for `lambda = 0`). Velocity damping treated
/// implicitly does not lower it.
pub fn critical_time_step_s(lambda_per_s2: f64) -> f64 {
    if lambda_per_s2 > 0.0 {
        2.0 / lambda_per_s2.sqrt()
    } else {
        f64::INFINITY
    }
}

/// A contact load for [`press`]: the force `-F w_i n` on each listed node (`w` sum 1, `n` the
/// outward normal), with the indentation measured as `sum w_i (rest_i - x_i) . n`. One node
/// with weight 1 is the paper's contact node C; the probe's kernel weights spread it like the
/// haptic probe does. With a compliance `c` (m/N) the contact pushes through a spring (the
/// virtual coupling, `c = 1 / k`): the prescribed depth is then `indentation + c F`.
#[derive(Debug, Clone)]
pub struct ContactLoad {
    /// `(node, weight)`, weights summing to 1.
    pub nodes: Vec<(u32, f64)>,
    /// Outward unit normal along which the contact pushes (inward).
    pub normal: DVec3,
    /// Compliance of the contact in series with the surface, m/N (0: rigid).
    pub compliance_m_per_n: f64,
}

/// Result of [`press`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PressResult {
    /// Contact force F (N) that holds the indentation.
    pub force_n: f64,
    /// Newton iterations.
    pub iterations: u32,
}

/// Static equilibrium of `net` with the contact `load` pressed to `depth_m` (m: the weighted
/// normal displacement of the load's nodes plus the compliance times the force): finds
/// positions `x` (m, updated in place from the value given, e.g. the solution at a smaller
/// depth) and the contact force F with `elastic_forces(x) - F w n = 0` at the free nodes. Newton's method on the bordered
/// system (the contact force as the extra unknown), the spring tangent's negative
/// (compression) part dropped so that every linear system is symmetric positive definite
/// (solved by block-Jacobi conjugate gradients), with step halving on the residual.
///
/// # Errors
/// [`ModelError::NoConvergence`] when Newton does not converge in 100 iterations;
/// [`ModelError::InvalidInput`] when no load node is free.
pub fn press(
    net: &Network,
    load: &ContactLoad,
    depth_m: f64,
    x: &mut [DVec3],
    force_guess_n: f64,
) -> Result<PressResult, ModelError> {
    let n = net.node_count();
    let normal = load.normal;
    let mut b = vec![DVec3::ZERO; n];
    for &(i, w) in &load.nodes {
        if !net.fixed[i as usize] {
            b[i as usize] += normal * w;
        }
    }
    if b.iter().all(|v| *v == DVec3::ZERO) {
        return Err(ModelError::InvalidInput(
            "the contact load has no free node".into(),
        ));
    }
    let k_scale = net
        .springs
        .iter()
        .map(|s| s.stiffness_n_per_m)
        .chain(net.home_n_per_m.iter().copied())
        .fold(0.0, f64::max)
        .max(1e-12);
    let indentation = |x: &[DVec3]| -> f64 {
        load.nodes
            .iter()
            .map(|&(i, w)| w * (net.rest[i as usize] - x[i as usize]).dot(normal))
            .sum()
    };
    let mut phi = force_guess_n;
    let mut f = vec![DVec3::ZERO; n];
    let mut r = vec![DVec3::ZERO; n];
    let residual = |x: &[DVec3], phi: f64, f: &mut [DVec3], r: &mut [DVec3]| -> (f64, f64) {
        net.elastic_forces(x, f);
        let mut norm2 = 0.0;
        for i in 0..n {
            r[i] = if net.fixed[i] {
                DVec3::ZERO
            } else {
                f[i] - b[i] * phi
            };
            norm2 += r[i].length_squared();
        }
        let g = indentation(x) + load.compliance_m_per_n * phi - depth_m;
        (norm2, g)
    };
    let (mut norm2, mut g) = residual(x, phi, &mut f, &mut r);
    let mut cg = Cg::new(n);
    let mut x_trial = x.to_vec();
    for it in 0..100u32 {
        let force_tol = 1e-10 * (phi.abs() + k_scale * depth_m.abs()).max(1e-9);
        if norm2.sqrt() <= force_tol && g.abs() <= 1e-10 * depth_m.abs().max(1e-9) {
            return Ok(PressResult {
                force_n: phi,
                iterations: it,
            });
        }
        cg.assemble(net, x);
        let a = cg.solve(net, &r)?.to_vec();
        let c = cg.solve(net, &b)?.to_vec();
        let bta: f64 = b.iter().zip(&a).map(|(p, q)| p.dot(*q)).sum();
        let btc: f64 = b.iter().zip(&c).map(|(p, q)| p.dot(*q)).sum();
        let dphi = (bta - g) / (btc + load.compliance_m_per_n);
        let merit = |n2: f64, g: f64| n2 + (k_scale * g).powi(2);
        let m0 = merit(norm2, g);
        let mut step = 1.0;
        loop {
            for i in 0..n {
                x_trial[i] = x[i] + (a[i] - c[i] * dphi) * step;
            }
            let phi_t = phi + dphi * step;
            let (n2, gt) = residual(&x_trial, phi_t, &mut f, &mut r);
            if merit(n2, gt) < m0 || step < 1e-3 {
                x.copy_from_slice(&x_trial);
                phi = phi_t;
                norm2 = n2;
                g = gt;
                break;
            }
            step *= 0.5;
        }
    }
    Err(ModelError::NoConvergence(format!(
        "static press to {depth_m:.3e} m: residual {:.3e} N after 100 Newton iterations",
        norm2.sqrt()
    )))
}

/// Conjugate gradients on the network's modified tangent (module documentation).
struct Cg {
    /// Per spring: the tangent block `K [n n^T + max(0, 1 - r/l) (I - n n^T)]`.
    blocks: Vec<DMat3>,
    /// Inverse diagonal blocks (block-Jacobi preconditioner).
    diag_inv: Vec<DMat3>,
    x: Vec<DVec3>,
    r: Vec<DVec3>,
    z: Vec<DVec3>,
    p: Vec<DVec3>,
    q: Vec<DVec3>,
}

impl Cg {
    fn new(n: usize) -> Self {
        Self {
            blocks: Vec::new(),
            diag_inv: vec![DMat3::IDENTITY; n],
            x: vec![DVec3::ZERO; n],
            r: vec![DVec3::ZERO; n],
            z: vec![DVec3::ZERO; n],
            p: vec![DVec3::ZERO; n],
            q: vec![DVec3::ZERO; n],
        }
    }

    fn assemble(&mut self, net: &Network, x: &[DVec3]) {
        self.blocks.clear();
        let mut diag: Vec<DMat3> = net
            .home_n_per_m
            .iter()
            .map(|&k| DMat3::from_diagonal(DVec3::splat(k)))
            .collect();
        for s in &net.springs {
            let d = x[s.j as usize] - x[s.i as usize];
            let len = d.length();
            let block = if len > 0.0 {
                let u = d / len;
                let nn = DMat3::from_cols(u * u.x, u * u.y, u * u.z);
                let t = (1.0 - s.rest_length_m / len).max(0.0);
                (nn + (DMat3::IDENTITY - nn) * t) * s.stiffness_n_per_m
            } else {
                DMat3::IDENTITY * s.stiffness_n_per_m
            };
            diag[s.i as usize] += block;
            diag[s.j as usize] += block;
            self.blocks.push(block);
        }
        for (inv, d) in self.diag_inv.iter_mut().zip(&diag) {
            *inv = if d.determinant().abs() > 0.0 {
                d.inverse()
            } else {
                DMat3::ZERO
            };
        }
    }

    fn apply(&self, net: &Network, p: &[DVec3], out: &mut [DVec3]) {
        for (i, o) in out.iter_mut().enumerate() {
            *o = p[i] * net.home_n_per_m[i];
        }
        for (s, block) in net.springs.iter().zip(&self.blocks) {
            let d = *block * (p[s.i as usize] - p[s.j as usize]);
            out[s.i as usize] += d;
            out[s.j as usize] -= d;
        }
        for (o, &fixed) in out.iter_mut().zip(&net.fixed) {
            if fixed {
                *o = DVec3::ZERO;
            }
        }
    }

    /// Solves `K y = rhs` (fixed components zero) to a relative residual of 1e-12.
    fn solve(&mut self, net: &Network, rhs: &[DVec3]) -> Result<&[DVec3], ModelError> {
        let n = rhs.len();
        let dot = |a: &[DVec3], b: &[DVec3]| a.iter().zip(b).map(|(p, q)| p.dot(*q)).sum::<f64>();
        self.x.iter_mut().for_each(|v| *v = DVec3::ZERO);
        for (i, r) in self.r.iter_mut().enumerate().take(n) {
            *r = if net.fixed[i] { DVec3::ZERO } else { rhs[i] };
        }
        let r0 = dot(&self.r, &self.r).sqrt();
        if r0 == 0.0 {
            return Ok(&self.x);
        }
        for i in 0..n {
            self.z[i] = self.diag_inv[i] * self.r[i];
        }
        self.p.copy_from_slice(&self.z);
        let mut rz = dot(&self.r, &self.z);
        for _ in 0..(20 * n).max(100) {
            let mut q = std::mem::take(&mut self.q);
            self.apply(net, &self.p, &mut q);
            self.q = q;
            let alpha = rz / dot(&self.p, &self.q);
            for i in 0..n {
                self.x[i] += self.p[i] * alpha;
                self.r[i] -= self.q[i] * alpha;
            }
            if dot(&self.r, &self.r).sqrt() <= 1e-12 * r0 {
                return Ok(&self.x);
            }
            for i in 0..n {
                self.z[i] = self.diag_inv[i] * self.r[i];
            }
            let rz_new = dot(&self.r, &self.z);
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..n {
                self.p[i] = self.z[i] + self.p[i] * beta;
            }
        }
        Err(ModelError::NoConvergence(
            "conjugate gradients on the spring network's tangent".into(),
        ))
    }
}
