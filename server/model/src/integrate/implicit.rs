//! Backward Euler, one Newton step per sub-step solved by preconditioned conjugate gradients
//! with the matrix applied matrix-free (see the module documentation of [`super`] for the
//! system).
//!
//! Neighbours: [`crate::element`] (forces, tangent action, rest blocks),
//! [`crate::contact::coupling`] (the probe's low-rank term, solved inside the same system).

use glam::{DMat3, DVec3};

use crate::contact::coupling::{
    MAX_COUPLED_PROBES, MAX_COUPLING_ROWS, MAX_MERGED_ROWS, cholesky_in_place, cholesky_solve,
};
use crate::contact::{ContactCoupling, MAX_PATCH_NODES};
use crate::element::{ConstraintMask, FemModel, apply_constraint};
use crate::material::{self, MaterialModel};

use super::IntegratorParams;

/// Conjugate-gradient statistics of the last backward Euler step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CgStats {
    /// Iterations used (each is one application of the system matrix).
    pub iterations: u32,
    /// Final `|r| / |rhs|` (0 when the right-hand side vanished).
    pub relative_residual: f64,
    /// Whether the tolerance was reached within the iteration cap.
    pub converged: bool,
}

/// Backward Euler solver: the preconditioner and every CG vector, sized at construction so that
/// [`ImplicitSolver::step`] allocates nothing. See the module documentation for the system.
#[derive(Debug, Clone)]
pub struct ImplicitSolver {
    dt_s: f64,
    max_iterations: u32,
    tolerance: f64,
    /// `m_i (1 + alpha h)`, kg.
    mass_factor: Vec<f64>,
    /// Inverses of the rest blocks of `A`, `m_i (1 + alpha h) I + h D_ii + h^2 K_ii`, 1/kg.
    precond_inv: Vec<DMat3>,
    /// `B_i^-1 u_e` per entry `(i, u_e)` of the probe's term (projected): its low-rank term is
    /// inverted exactly in the preconditioner by the Woodbury identity.
    patch_bu: Vec<DVec3>,
    /// Cholesky factor of the Woodbury capacitance `C^-1 / h^2 + A B^-1 A^T` (`F x F`).
    capacitance: Vec<f64>,
    /// Deformation gradient per element at the start of the step.
    elem_f: Vec<DMat3>,
    /// Per element at the start of the step: the StVK second Piola-Kirchhoff stress (StVK) or
    /// the rotation of the polar decomposition (corotational, stable Neo-Hookean).
    elem_s: Vec<DMat3>,
    /// The step's right-hand side and CG vectors.
    cg: CgVectors,
    stats: CgStats,
}

/// The vectors of one CG solve (`n` nodes each), allocated at construction; `dv` is kept
/// from one step to the next as the warm start.
#[derive(Debug, Clone)]
struct CgVectors {
    /// `M v + h f - A v` (projected).
    rhs: Vec<DVec3>,
    /// The solution `dv`, m/s.
    dv: Vec<DVec3>,
    /// Residual `rhs - A dv`.
    r: Vec<DVec3>,
    /// Preconditioned residual `P^-1 r`.
    z: Vec<DVec3>,
    /// Search direction.
    p: Vec<DVec3>,
    /// `A p` (or `A` of whatever was applied last).
    ap: Vec<DVec3>,
}

impl ImplicitSolver {
    /// Prepares the solver for `fem` and sub-step `dt_s` (s) with the CG settings of `params`.
    pub fn new(fem: &FemModel, dt_s: f64, params: &IntegratorParams) -> Self {
        let n = fem.node_count();
        let mat = fem.material();
        let h = dt_s;
        let mass_factor: Vec<f64> = fem
            .lumped_mass_kg()
            .iter()
            .map(|m| m * (1.0 + mat.mass_damping_per_s * h))
            .collect();
        // D_ii at rest: the stiffness blocks with (lambda, mu) -> (2 phi, 2 psi) (eq. 10-11).
        let mut precond: Vec<DMat3> = fem
            .rest_diagonal_blocks()
            .iter()
            .zip(&mass_factor)
            .map(|(k, m)| DMat3::from_diagonal(DVec3::splat(*m)) + *k * (h * h))
            .collect();
        for (p, d) in precond
            .iter_mut()
            .zip(fem.isotropic_diagonal_blocks(2.0 * mat.phi_pa_s, 2.0 * mat.psi_pa_s))
        {
            *p += d * h;
        }
        let precond_inv = precond.iter().map(|b| b.inverse()).collect();
        Self {
            dt_s,
            max_iterations: params.cg_max_iterations,
            tolerance: params.cg_tolerance,
            mass_factor,
            precond_inv,
            patch_bu: Vec::with_capacity(
                MAX_COUPLED_PROBES * MAX_PATCH_NODES.max(3 * MAX_COUPLING_ROWS),
            ),
            capacitance: vec![0.0; MAX_MERGED_ROWS * MAX_MERGED_ROWS],
            elem_f: vec![DMat3::IDENTITY; fem.integration_point_count()],
            elem_s: vec![DMat3::ZERO; fem.integration_point_count()],
            cg: CgVectors {
                rhs: vec![DVec3::ZERO; n],
                dv: vec![DVec3::ZERO; n],
                r: vec![DVec3::ZERO; n],
                z: vec![DVec3::ZERO; n],
                p: vec![DVec3::ZERO; n],
                ap: vec![DVec3::ZERO; n],
            },
            stats: CgStats::default(),
        }
    }

    /// Sub-step the solver was prepared for, s.
    pub fn dt_s(&self) -> f64 {
        self.dt_s
    }

    /// Statistics of the last step.
    pub fn stats(&self) -> CgStats {
        self.stats
    }

    /// One backward Euler step of `dt_s`: solves `A dv = M v + h f - A v` (module documentation)
    /// by preconditioned CG warm-started with the previous step's `dv`, then `v += dv`,
    /// `x += h v`. `f` (N) holds every force except the viscous one and the implicit part of the
    /// coupling: the elastic force at `x`, external loads, and the coupling's explicit part
    /// (`-U phi0`). Returns the largest squared nodal speed after the step (m^2/s^2; NaN if any
    /// value is not finite). Allocation-free.
    ///
    /// # Panics
    /// If the slices are shorter than the node count of the model the solver was built for.
    pub fn step(
        &mut self,
        fem: &FemModel,
        f: &[DVec3],
        coupling: Option<ContactCoupling<'_>>,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        let h = self.dt_s;
        let mat = fem.material();
        let viscous = mat.phi_pa_s > 0.0 || mat.psi_pa_s > 0.0;
        self.cache_deformation(fem, x);
        let op = Operator {
            fem,
            h,
            viscous,
            mass_factor: &self.mass_factor,
            elem_f: &self.elem_f,
            elem_s: &self.elem_s,
            coupling,
        };
        let woodbury = coupling.and_then(|c| {
            woodbury_capacitance(
                WoodburyInputs {
                    fem,
                    h,
                    precond_inv: &self.precond_inv,
                    coupling: c,
                },
                &mut self.patch_bu,
                &mut self.capacitance,
            )
        });
        let pre = Preconditioner {
            precond_inv: &self.precond_inv,
            constraints: fem.constraints(),
            coupling,
            woodbury,
            patch_bu: &self.patch_bu,
            capacitance: &self.capacitance,
        };
        let rhs_norm = self.cg.right_hand_side(&op, f, v);
        self.cg.warm_start(&op);
        let target = self.tolerance * rhs_norm;
        let (iterations, r_norm) = self.cg.solve(&op, &pre, target, self.max_iterations);
        self.stats = CgStats {
            iterations,
            relative_residual: if rhs_norm > 0.0 {
                r_norm / rhs_norm
            } else {
                0.0
            },
            converged: r_norm <= target,
        };
        self.cg.update(fem, h, x, v)
    }

    /// The deformation gradient at each integration point at `x` (m) and what the operator
    /// freezes there: the StVK second Piola-Kirchhoff stress or the polar rotation.
    fn cache_deformation(&mut self, fem: &FemModel, x: &[DVec3]) {
        let mat = fem.material();
        for (q, fe) in self.elem_f.iter_mut().enumerate() {
            *fe = fem.ip_field_gradient(q, x);
        }
        for (se, fe) in self.elem_s.iter_mut().zip(&self.elem_f) {
            *se = match mat.model {
                MaterialModel::StVenantKirchhoff => {
                    material::stvk_stress(&material::green_strain(fe), mat.lambda_pa, mat.mu_pa)
                }
                _ => material::polar_decomposition(fe).0,
            };
        }
    }

    /// Forgets the warm start (after the state was replaced from outside).
    pub fn reset_warm_start(&mut self) {
        self.cg.dv.iter_mut().for_each(|d| *d = DVec3::ZERO);
    }
}

/// What [`woodbury_capacitance`] reads.
struct WoodburyInputs<'a> {
    fem: &'a FemModel,
    h: f64,
    /// Inverses of the rest blocks `B_i`, 1/kg.
    precond_inv: &'a [DMat3],
    coupling: ContactCoupling<'a>,
}

/// The low-rank part of the preconditioner `P = B + h^2 A^T C A` (B the block diagonal at
/// rest), inverted exactly by Woodbury: `P^-1 r = B^-1 r - B^-1 A^T W^-1 A B^-1 r`,
/// `W = C^-1 / h^2 + A B^-1 A^T`. Writes `B_i^-1 u_e` per entry of the probe's term into
/// `patch_bu` and the Cholesky factor of `W` into `capacitance`; returns the number of rows
/// `F`, or `None` when `W` is not positive definite (no low-rank part then). Without the
/// low-rank part CG needed many more iterations (the coupling's weight `h^2 C` is far above
/// the contact nodes' masses on fine meshes) and a capped solve could diverge.
fn woodbury_capacitance(
    inputs: WoodburyInputs<'_>,
    patch_bu: &mut Vec<DVec3>,
    capacitance: &mut [f64],
) -> Option<usize> {
    let WoodburyInputs {
        fem,
        h,
        precond_inv,
        coupling: c,
    } = inputs;
    patch_bu.clear();
    for (&i, &u) in c.nodes.iter().zip(c.vectors) {
        let mut bu = precond_inv[i as usize] * u;
        apply_constraint(fem.constraints()[i as usize], &mut bu);
        patch_bu.push(bu);
    }
    let nf = c.rows();
    let w = &mut capacitance[..nf * nf];
    for f in 0..nf {
        for g in 0..=f {
            let (g0, g1) = (c.row_ptr[g] as usize, c.row_ptr[g + 1] as usize);
            let mut s = c.compliance[f * nf + g] / (h * h);
            for (i, u) in c.row(f) {
                for (&node, bu) in c.nodes[g0..g1].iter().zip(&patch_bu[g0..g1]) {
                    if node == i {
                        s += u.dot(*bu);
                    }
                }
            }
            w[f * nf + g] = s;
            w[g * nf + f] = s;
        }
    }
    cholesky_in_place(w, nf).then_some(nf)
}

/// The preconditioner `P^-1` of the CG solve: the inverse rest blocks and, with a probe,
/// the Woodbury correction of its low-rank term ([`woodbury_capacitance`]).
struct Preconditioner<'a> {
    precond_inv: &'a [DMat3],
    constraints: &'a [ConstraintMask],
    coupling: Option<ContactCoupling<'a>>,
    /// Rows of the low-rank part, when its capacitance was factorised.
    woodbury: Option<usize>,
    patch_bu: &'a [DVec3],
    /// Cholesky factor of the capacitance `W`.
    capacitance: &'a [f64],
}

impl Preconditioner<'_> {
    /// `z = P^-1 r` (constrained components of `z` are zero).
    fn apply(&self, r: &[DVec3], z: &mut [DVec3]) {
        for i in 0..r.len() {
            z[i] = self.precond_inv[i] * r[i];
        }
        for (zi, &m) in z.iter_mut().zip(self.constraints) {
            apply_constraint(m, zi);
        }
        if let (Some(c), Some(nf)) = (self.coupling, self.woodbury) {
            let mut t = [0.0; MAX_MERGED_ROWS];
            c.a_times(z, &mut t);
            cholesky_solve(self.capacitance, nf, &mut t[..nf]);
            for (f, &tf) in t.iter().enumerate().take(nf) {
                for e in c.row_ptr[f] as usize..c.row_ptr[f + 1] as usize {
                    z[c.nodes[e] as usize] -= self.patch_bu[e] * tf;
                }
            }
        }
    }
}

impl CgVectors {
    /// `rhs = M v + h f - A v` (projected); returns its norm.
    fn right_hand_side(&mut self, op: &Operator<'_>, f: &[DVec3], v: &[DVec3]) -> f64 {
        let fem = op.fem;
        op.apply(v, &mut self.ap);
        for i in 0..v.len() {
            let mut b = v[i] * fem.lumped_mass_kg()[i] + f[i] * op.h - self.ap[i];
            apply_constraint(fem.constraints()[i], &mut b);
            self.rhs[i] = b;
        }
        norm(&self.rhs)
    }

    /// Warm start: the previous step's dv (already projected), scaled by the minimiser
    /// `s = rhs.dv / dv.A.dv` (clamped to [0, 1]) of the step's quadratic energy
    /// `dv.A.dv / 2 - rhs.dv` along it, so the start is never worse than zero; `r` its
    /// residual. Reusing dv unscaled made a capped solve (5-10 iterations) diverge on lv_h1
    /// (18k tets): the stiff components that CG leaves unresolved were re-applied every step.
    fn warm_start(&mut self, op: &Operator<'_>) {
        op.apply(&self.dv, &mut self.ap);
        let curvature = dot(&self.dv, &self.ap);
        let scale = if curvature > 0.0 {
            (dot(&self.rhs, &self.dv) / curvature).clamp(0.0, 1.0)
        } else {
            0.0
        };
        for i in 0..self.dv.len() {
            self.dv[i] *= scale;
            self.r[i] = self.rhs[i] - self.ap[i] * scale;
        }
    }

    /// Preconditioned CG from the warm start until `|r| <= target` or `max_iterations`;
    /// returns the iterations and the final `|r|`.
    fn solve(
        &mut self,
        op: &Operator<'_>,
        pre: &Preconditioner<'_>,
        target: f64,
        max_iterations: u32,
    ) -> (u32, f64) {
        let n = self.dv.len();
        pre.apply(&self.r, &mut self.z);
        self.p.copy_from_slice(&self.z);
        let mut rz = dot(&self.r, &self.z);
        let mut iterations = 0;
        let mut r_norm = norm(&self.r);
        while r_norm > target && iterations < max_iterations {
            op.apply(&self.p, &mut self.ap);
            let pap = dot(&self.p, &self.ap);
            // An indefinite tangent (strong compression, inverted elements) or a non-finite
            // state ends CG here. At the first iteration the step falls back to the
            // preconditioned residual `dv0 + P^-1 r0` (a block-Jacobi step on the SPD rest
            // blocks, like the seed's per-node scheme), so the body still moves.
            if !(pap > 0.0) || !(rz > 0.0) {
                if iterations == 0 && rz > 0.0 {
                    for i in 0..n {
                        self.dv[i] += self.z[i];
                    }
                }
                break;
            }
            iterations += 1;
            let alpha = rz / pap;
            for i in 0..n {
                self.dv[i] += self.p[i] * alpha;
                self.r[i] -= self.ap[i] * alpha;
            }
            r_norm = norm(&self.r);
            pre.apply(&self.r, &mut self.z);
            let rz_new = dot(&self.r, &self.z);
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..n {
                self.p[i] = self.z[i] + self.p[i] * beta;
            }
        }
        (iterations, r_norm)
    }

    /// `v += dv` (projected), `x += h v`; returns the largest squared nodal speed (NaN if any
    /// value is not finite, and the warm start is forgotten).
    fn update(&mut self, fem: &FemModel, h: f64, x: &mut [DVec3], v: &mut [DVec3]) -> f64 {
        let mut max_v2: f64 = 0.0;
        let mut non_finite = false;
        for i in 0..v.len() {
            let mut vi = v[i] + self.dv[i];
            apply_constraint(fem.constraints()[i], &mut vi);
            v[i] = vi;
            x[i] += vi * h;
            let s = vi.length_squared();
            non_finite |= !s.is_finite();
            max_v2 = max_v2.max(s);
        }
        if non_finite {
            // Never warm-start from garbage.
            self.dv.iter_mut().for_each(|d| *d = DVec3::ZERO);
            f64::NAN
        } else {
            max_v2
        }
    }
}

/// The backward Euler matrix `A` applied matrix-free (module documentation).
struct Operator<'a> {
    fem: &'a FemModel,
    h: f64,
    viscous: bool,
    mass_factor: &'a [f64],
    elem_f: &'a [DMat3],
    /// StVK stresses per element (empty for the other materials).
    elem_s: &'a [DMat3],
    coupling: Option<ContactCoupling<'a>>,
}

impl Operator<'_> {
    /// `out = A p` on the free components (constrained components of `out` are zero).
    ///
    /// One element loop on the deformation gradients cached at the start of the step:
    /// `h^2 K p + h D p` is `V (h^2 dP + h F S_v(F, dF)) Dm^-T` per element with
    /// `dF = dDs(p) Dm^-1`, `dP` the material's [`material::first_piola_differential`] and
    /// `S_v` the viscous stress of eq. 11, which for `nu = 2 sym(F^T dF)` is the StVK law with
    /// `(2 phi, 2 psi)`. For StVK both share `dE = sym(F^T dF)`:
    /// `h^2 dF S + F S_stvk(dE; h^2 lambda + 2 h phi, h^2 mu + 2 h psi)`.
    ///
    /// Corotational and stable Neo-Hookean use the warped linear-elastic stiffness with the
    /// rotation `R` of the polar decomposition frozen over the step (Müller et al. 2002):
    /// `dP = R (mu (G + G^T) + lambda tr(G) I)`, `G = R^T dF`. It is exact at rest (both
    /// materials linearise there to linear elasticity), annihilates infinitesimal rotations,
    /// and stays positive semi-definite for inverted elements, where the exact tangents are
    /// indefinite and the one-step Newton / CG solve diverged in the stability suite (an
    /// inverted cube). The forces stay exact, so equilibria are unchanged.
    fn apply(&self, p: &[DVec3], out: &mut [DVec3]) {
        let fem = self.fem;
        let h = self.h;
        let h2 = h * h;
        let mat = fem.material();
        let (lam, mu) = (
            h2 * mat.lambda_pa + 2.0 * h * mat.phi_pa_s,
            h2 * mat.mu_pa + 2.0 * h * mat.psi_pa_s,
        );
        let (vphi, vpsi) = (2.0 * h * mat.phi_pa_s, 2.0 * h * mat.psi_pa_s);
        out.iter_mut().for_each(|o| *o = DVec3::ZERO);
        // `h^2 dP + h F S_v` at one element or integration point with cached `F`, `S` (or `R`).
        let dp_of = |fm: DMat3, s: DMat3, df: DMat3| -> DMat3 {
            let ft_df = fm.transpose() * df;
            let de = (ft_df + ft_df.transpose()) * 0.5;
            if mat.model == MaterialModel::StVenantKirchhoff {
                df * (s * h2) + fm * material::stvk_stress(&de, lam, mu)
            } else {
                let g = s.transpose() * df;
                let tr = g.x_axis.x + g.y_axis.y + g.z_axis.z;
                let lin = (g + g.transpose()) * mat.mu_pa
                    + DMat3::from_diagonal(DVec3::splat(mat.lambda_pa * tr));
                let mut dp = s * lin * h2;
                if self.viscous {
                    dp += fm * material::stvk_stress(&de, vphi, vpsi);
                }
                dp
            }
        };
        if fem.is_quadratic() && mat.model == MaterialModel::StVenantKirchhoff {
            fem.quadratic_stvk_operator_action(self.elem_f, self.elem_s, (h2, lam, mu), p, out);
        } else if !fem.is_plain_linear() {
            for q in 0..fem.integration_point_count() {
                let df = fem.ip_field_gradient(q, p);
                let dp = dp_of(self.elem_f[q], self.elem_s[q], df);
                fem.ip_scatter(q, &(dp * fem.ip_weight_m3(q)), out);
            }
        } else {
            for (e, t) in fem.tets().iter().enumerate() {
                let [a, b, c, d] = t.map(|i| i as usize);
                let dm_inv = fem.dm_inv()[e];
                let p0 = p[a];
                let df = DMat3::from_cols(p[b] - p0, p[c] - p0, p[d] - p0) * dm_inv;
                let dp = dp_of(self.elem_f[e], self.elem_s[e], df);
                let hm = dp * dm_inv.transpose() * fem.volume_m3()[e];
                out[b] += hm.x_axis;
                out[c] += hm.y_axis;
                out[d] += hm.z_axis;
                out[a] -= hm.x_axis + hm.y_axis + hm.z_axis;
            }
        }
        for i in 0..p.len() {
            out[i] += p[i] * self.mass_factor[i];
        }
        if let Some(c) = self.coupling {
            let mut y = [0.0; MAX_MERGED_ROWS];
            c.a_times(p, &mut y);
            c.apply_c(&mut y[..c.rows()]);
            c.add_at(&y[..c.rows()], h2, out);
        }
        for (o, &m) in out.iter_mut().zip(fem.constraints()) {
            project(m, o);
        }
    }
}

#[inline]
fn project(mask: ConstraintMask, v: &mut DVec3) {
    apply_constraint(mask, v);
}

fn dot(a: &[DVec3], b: &[DVec3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x.dot(*y)).sum()
}

fn norm(a: &[DVec3]) -> f64 {
    dot(a, a).sqrt()
}
