//! Stiffness of a [`FemModel`]: the action of the tangent `K(x) = -d f / d x` on a vector,
//! the tangent blocks of one element or cell (for assembly), the rest diagonal blocks (the
//! seed's per-node Jacobian of eq. 34 and the integrators' preconditioners), and the largest
//! eigenvalue of `M^-1 K` for critical time steps.
//!
//! Neighbours: [`crate::statics`] and [`crate::integrate`] assemble and apply these.

use glam::{DMat3, DVec3};

use super::{FemModel, MAX_CELL_POINTS, apply_constraint};
use crate::material::{self, MaterialParams};

/// Element tangent stiffness blocks `K_ab = -d f_a / d x_b` (3x3, N/m) of linear element `e` at
/// positions `x`, from the directional derivative of `f_a = -V P(F) grad N_a`
/// ([`material::first_piola_differential_oriented`] of the material model in the element's
/// frame).
pub fn element_tangent(fem: &FemModel, e: usize, x: &[DVec3]) -> [[DMat3; 4]; 4] {
    let mat = fem.material();
    let g = fem.shape_gradients(e);
    let fm = fem.deformation_gradient(e, x);
    let vol = fem.volume_m3()[e];
    let mut k = [[DMat3::ZERO; 4]; 4];
    for b in 0..4 {
        let mut cols = [DVec3::ZERO; 4 * 3];
        for j in 0..3 {
            // dF = e_j (grad N_b)^T
            let mut dfm = DMat3::ZERO;
            for (c, &gc) in g[b].to_array().iter().enumerate() {
                let mut col = DVec3::ZERO;
                col[j] = gc;
                *dfm.col_mut(c) = col;
            }
            let dp = material::first_piola_differential_oriented(mat, &fm, &fem.ip_frame(e), &dfm);
            for a in 0..4 {
                cols[a * 3 + j] = dp * g[a] * vol;
            }
        }
        for a in 0..4 {
            k[a][b] = DMat3::from_cols(cols[a * 3], cols[a * 3 + 1], cols[a * 3 + 2]);
        }
    }
    k
}

/// Tangent stiffness blocks of cell `c` (an element of any order, or a smoothing domain) at
/// positions `x`, N/m: `out` is filled with `npe x npe` blocks, block `(a, b)` at
/// `out[a * npe + b]` being `K_ab = -d f_a / d x_b` for the cell nodes `a, b` of
/// [`FemModel::cell_nodes`] (`npe` = 4 or 10 for elements, 4 to 11 for edge domains), summed
/// over the cell's integration points.
pub fn cell_tangent_blocks(fem: &FemModel, c: usize, x: &[DVec3], out: &mut Vec<DMat3>) {
    cell_tangent_blocks_of(fem, fem.material(), c, x, out);
}

/// [`cell_tangent_blocks`] of the material `mat` instead of the model's (for an operator with
/// other coefficients on the same cells, such as a time integrator's matrix).
pub fn cell_tangent_blocks_of(
    fem: &FemModel,
    mat: &MaterialParams,
    c: usize,
    x: &[DVec3],
    out: &mut Vec<DMat3>,
) {
    let npe = fem.cell_nodes(c).len();
    out.clear();
    out.resize(npe * npe, DMat3::ZERO);
    // Mean dilatation: the points see the cell's pressure p_c = U'(J_c); the cell adds the
    // rank-one term U''(J_c) / V_c a a^T with a_a = sum_q w_q cof(F_q) grad N_a.
    let mean = mat.mean_dilatation();
    let mut pc = 0.0;
    let mut ddu_over_v = 0.0;
    let mut avec = [DVec3::ZERO; 16];
    if mean {
        assert!(npe <= avec.len() && fem.cell_points(c).len() <= MAX_CELL_POINTS);
        let (mut vol, mut def) = (0.0, 0.0);
        for q in fem.cell_points(c) {
            let fm = fem.ip_field_gradient(q, x);
            let w = fem.ip_weight_m3(q);
            let cof = material::cofactor(&fm);
            vol += w;
            def += w * fm.determinant();
            for (a, g) in fem.ip_gradients(q).iter().enumerate() {
                avec[a] += cof * *g * w;
            }
        }
        let (_, du, ddu) = material::guccione::volumetric(&mat.guccione, def / vol);
        pc = du + fem.cell_pressure(c);
        ddu_over_v = ddu / vol;
    }
    for q in fem.cell_points(c) {
        let g = fem.ip_gradients(q);
        let w = fem.ip_weight_m3(q);
        let fm = fem.ip_field_gradient(q, x);
        let frame = fem.ip_frame(q);
        for b in 0..npe {
            for j in 0..3 {
                // dF = e_j (grad N_b)^T
                let mut dfm = DMat3::ZERO;
                for (c, gc) in g[b].to_array().into_iter().enumerate() {
                    dfm.col_mut(c)[j] = gc;
                }
                let dp = if mean {
                    material::guccione::first_piola_deviatoric_differential(
                        &mat.guccione,
                        &fm,
                        &frame,
                        &dfm,
                    ) + material::cofactor_differential(&fm, &dfm) * pc
                } else {
                    material::first_piola_differential_oriented(mat, &fm, &frame, &dfm)
                };
                for a in 0..npe {
                    *out[a * npe + b].col_mut(j) += dp * g[a] * w;
                }
            }
        }
    }
    if mean {
        for a in 0..npe {
            for b in 0..npe {
                let (va, vb) = (avec[a], avec[b]);
                out[a * npe + b] += DMat3::from_cols(va * vb.x, va * vb.y, va * vb.z) * ddu_over_v;
            }
        }
    }
}

impl FemModel {
    /// Adds the action of the elastic tangent stiffness `K(x) = -d f_elastic / d x` on the
    /// displacement increment `dx` to `out` (N/m times m = N; all length N):
    /// `dF = dDs Dm^-1`, `dP` from [`material::first_piola_differential`] (for StVK
    /// `dE = sym(F^T dF)`, `dS = lambda tr(dE) I + 2 mu dE`, `dP = dF S + F dS`),
    /// `out_a += V dP grad N_a`. At rest this is the linear-elastic stiffness for every material.
    pub fn stiffness_action(&self, x: &[DVec3], dx: &[DVec3], out: &mut [DVec3]) {
        let mat = &self.material;
        if mat.mean_dilatation() {
            // Per cell: dP_q = dP_dev + p_c d cof F_q + dp_c cof F_q, with p_c = U'(J_c) and
            // dp_c = U''(J_c) sum_q w_q cof F_q : dF_q / V_c.
            let g = &mat.guccione;
            for c in 0..self.cell_count() {
                let (mut vol, mut def, mut dj) = (0.0, 0.0, 0.0);
                for q in self.cell_points(c) {
                    let fm = self.ip_field_gradient(q, x);
                    let w = self.ip_weight_m3(q);
                    vol += w;
                    def += w * fm.determinant();
                    dj += w * material::ddot(
                        &material::cofactor(&fm),
                        &self.ip_field_gradient(q, dx),
                    );
                }
                let (_, du, ddu) = material::guccione::volumetric(g, def / vol);
                let du = du + self.cell_pressure(c);
                let dp_c = ddu * dj / vol;
                for q in self.cell_points(c) {
                    let fm = self.ip_field_gradient(q, x);
                    let dfm = self.ip_field_gradient(q, dx);
                    let dp = material::guccione::first_piola_deviatoric_differential(
                        g,
                        &fm,
                        &self.ip_frame(q),
                        &dfm,
                    ) + material::cofactor_differential(&fm, &dfm) * du
                        + material::cofactor(&fm) * dp_c;
                    self.ip_scatter(q, &(dp * self.ip_weight_m3(q)), out);
                }
            }
            return;
        }
        if !self.is_plain_linear() {
            for q in 0..self.integration_point_count() {
                let fm = self.ip_field_gradient(q, x);
                let dfm = self.ip_field_gradient(q, dx);
                let dp =
                    material::first_piola_differential_oriented(mat, &fm, &self.ip_frame(q), &dfm);
                self.ip_scatter(q, &(dp * self.points.weight_m3[q]), out);
            }
            return;
        }
        for (e, t) in self.tets.iter().enumerate() {
            let [a, b, c, d] = t.map(|i| i as usize);
            let dm_inv = self.dm_inv[e];
            let x0 = x[a];
            let fm = DMat3::from_cols(x[b] - x0, x[c] - x0, x[d] - x0) * dm_inv;
            let d0 = dx[a];
            let dfm = DMat3::from_cols(dx[b] - d0, dx[c] - d0, dx[d] - d0) * dm_inv;
            let dp = material::first_piola_differential_oriented(mat, &fm, &self.ip_frame(e), &dfm);
            let h = dp * dm_inv.transpose() * self.volume_m3[e];
            out[b] += h.x_axis;
            out[c] += h.y_axis;
            out[d] += h.z_axis;
            out[a] -= h.x_axis + h.y_axis + h.z_axis;
        }
    }

    /// The 3x3 diagonal blocks `K_ii` of the linear-elastic stiffness at rest, N/m (one per
    /// node): `K_ii = sum_e V_e ((lambda + mu) g g^T + mu |g|^2 I)` with `g = grad N_i` in `e`.
    /// The same for every [`material::MaterialModel`]: all linearise at rest to this.
    /// The seed's per-node Jacobian of eq. 34 is `J_i = -K_ii` ("precomputed at rest assuming
    /// that its neighbours are fixed").
    pub fn rest_diagonal_blocks(&self) -> Vec<DMat3> {
        let mat = &self.material;
        self.isotropic_diagonal_blocks(mat.lambda_pa, mat.mu_pa)
    }

    /// The 3x3 diagonal blocks of the isotropic operator with Lamé-like coefficients
    /// `(lambda, mu)` at rest: `sum_q w_q ((lambda + mu) g g^T + mu |g|^2 I)`, `g = grad N_i` at
    /// integration point `q` (units of `lambda` times m). [`Self::rest_diagonal_blocks`] is
    /// this with the material's Lamé parameters; with `(2 phi, 2 psi)` it is the viscous one.
    pub fn isotropic_diagonal_blocks(&self, lambda: f64, mu: f64) -> Vec<DMat3> {
        let mut k = vec![DMat3::ZERO; self.node_count()];
        for q in 0..self.integration_point_count() {
            let w = self.points.weight_m3[q];
            for (&i, &ga) in self.ip_nodes(q).iter().zip(self.ip_gradients(q)) {
                let outer = DMat3::from_cols(ga * ga.x, ga * ga.y, ga * ga.z);
                k[i as usize] += (outer * (lambda + mu)
                    + DMat3::from_diagonal(DVec3::splat(mu * ga.length_squared())))
                    * w;
            }
        }
        k
    }

    /// Largest eigenvalue of the symmetric operator `M^-1/2 (K - c K_D) M^-1/2` on the free
    /// degrees of freedom at rest, by shifted power iteration with a Rayleigh-quotient estimate,
    /// 1/s^2. `K` is the linear-elastic stiffness, `K_D` its block diagonal, `c >= 0`.
    /// With `c = 0` this is `omega_max^2`, the square of the highest natural frequency.
    ///
    /// The estimate approaches the true value from below; `iterations` of 300 give about 0.1 %
    /// on the meshes we use.
    pub fn max_eigenvalue(&self, diag_weight: f64, iterations: usize) -> f64 {
        let n = self.node_count();
        let kd = self.rest_diagonal_blocks();
        let inv_sqrt_m: Vec<f64> = self.lumped_mass_kg.iter().map(|m| 1.0 / m.sqrt()).collect();
        // Shift so the operator is positive semi-definite: -c K_D >= -c max_i lambda_max(K_ii)/m_i.
        let shift = if diag_weight > 0.0 {
            diag_weight
                * kd.iter()
                    .zip(&self.lumped_mass_kg)
                    .map(|(k, m)| gershgorin_bound(k) / m)
                    .fold(0.0, f64::max)
        } else {
            0.0
        };
        let mut z: Vec<DVec3> = (0..n)
            .map(|i| {
                // Deterministic pseudo-random start vector.
                let h = |s: u64| {
                    ((i as u64).wrapping_mul(6364136223846793005).wrapping_add(s) >> 33) as f64
                };
                DVec3::new(h(1), h(2), h(3)) / (u32::MAX as f64) - 0.25
            })
            .collect();
        for (i, zi) in z.iter_mut().enumerate() {
            apply_constraint(self.constraint[i], zi);
        }
        let norm = |v: &[DVec3]| v.iter().map(|a| a.length_squared()).sum::<f64>().sqrt();
        let mut tmp = vec![DVec3::ZERO; n];
        let mut out = vec![DVec3::ZERO; n];
        let mut estimate = 0.0;
        for _ in 0..iterations {
            let nz = norm(&z);
            if nz == 0.0 {
                return 0.0;
            }
            for (i, zi) in z.iter_mut().enumerate() {
                *zi /= nz;
                tmp[i] = *zi * inv_sqrt_m[i];
            }
            out.iter_mut().for_each(|o| *o = DVec3::ZERO);
            self.stiffness_action(&self.rest, &tmp, &mut out);
            for i in 0..n {
                let mut y =
                    (out[i] - (kd[i] * tmp[i]) * diag_weight) * inv_sqrt_m[i] + z[i] * shift;
                apply_constraint(self.constraint[i], &mut y);
                out[i] = y;
            }
            estimate = z.iter().zip(&out).map(|(a, b)| a.dot(*b)).sum::<f64>();
            std::mem::swap(&mut z, &mut out);
        }
        estimate - shift
    }
}

/// Gershgorin bound on the largest eigenvalue of a 3x3 matrix.
fn gershgorin_bound(m: &DMat3) -> f64 {
    (0..3)
        .map(|r| m.row(r).abs().element_sum())
        .fold(0.0, f64::max)
}
