//! A rule-based myocardial fibre field: the local material frame (fibre, sheet, sheet-normal)
//! of every integration point, for [`crate::material::MaterialModel::Guccione`].
//!
//! The rule is the usual Laplace-Dirichlet one (in the spirit of J. D. Bayer, R. C. Blake,
//! G. Plank, N. A. Trayanova, "A novel rule-based algorithm for assigning myocardial fiber
//! orientation to computational heart models", Ann. Biomed. Eng. 40 (2012) 2243, reduced to a
//! single ventricle): a transmural coordinate `t` solves Laplace's equation on the mesh with
//! `t = 0` on the endocardium and `t = 1` on the epicardium; at each point
//!
//! - the transmural direction is `e_t = grad t / |grad t|`,
//! - the circumferential direction `e_c = (e_t x a) / |e_t x a|` for the long axis `a` (base
//!   direction; `+z` for the LV meshes, whose apex is on `-z`),
//! - the longitudinal direction `e_l = e_c x e_t` (towards the base),
//! - the fibre `f = cos(alpha) e_c + sin(alpha) e_l` with the helix angle varying linearly
//!   through the wall, `alpha(t) = alpha_endo + (alpha_epi - alpha_endo) t`,
//! - sheet-normal `n = e_t` and sheet `s = n x f`.
//!
//! With `a = +z` this is the convention of the Land et al. 2015 benchmark (their `f = sin(alpha)
//! dx/du + cos(alpha) dx/dv` on the prolate coordinates of the idealised LV: `alpha = 0` is
//! circumferential, `+90` degrees longitudinal towards the base). Default: `+60` degrees at the
//! endocardium to `-60` at the epicardium.
//!
//! Neighbours: [`super::FemModel::set_fibres`] builds the frames; the Guccione stress of
//! [`crate::material::guccione`] reads them.

use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use glam::{DMat3, DVec3};

use super::FemModel;
use crate::ModelError;

/// The parameters of the rule (module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FibreRule {
    /// Helix angle at the endocardium (`t = 0`), degrees.
    pub helix_endo_deg: f64,
    /// Helix angle at the epicardium (`t = 1`), degrees.
    pub helix_epi_deg: f64,
    /// Long axis, pointing from the apex to the base (normalised when used).
    pub long_axis: DVec3,
}

impl Default for FibreRule {
    /// `+60` degrees at the endocardium, `-60` at the epicardium, long axis `+z`.
    fn default() -> Self {
        Self {
            helix_endo_deg: 60.0,
            helix_epi_deg: -60.0,
            long_axis: DVec3::Z,
        }
    }
}

/// A fibre field: the rule and the transmural coordinate of every node (0 on the endocardium,
/// 1 on the epicardium).
#[derive(Debug, Clone, PartialEq)]
pub struct FibreField {
    /// The rule.
    pub rule: FibreRule,
    /// Transmural coordinate per node, in `[0, 1]`.
    pub transmural: Vec<f64>,
}

impl FibreField {
    /// Solves Laplace's equation for the transmural coordinate on the cells of `fem` (the
    /// scalar stiffness `sum_q w_q grad N_a . grad N_b` of its integration points) with `t = 0`
    /// at `endo_nodes` and `t = 1` at `epi_nodes`, by sparse Cholesky.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`material.fibres`) when either node set is empty or they
    /// overlap, [`ModelError::InvalidMesh`] when the system cannot be factorised (a part of
    /// the mesh touches neither surface).
    pub fn laplace(
        fem: &FemModel,
        endo_nodes: &[u32],
        epi_nodes: &[u32],
        rule: FibreRule,
    ) -> Result<Self, ModelError> {
        let n = fem.node_count();
        let mut value = vec![f64::NAN; n];
        for &i in endo_nodes {
            value[i as usize] = 0.0;
        }
        for &i in epi_nodes {
            if value[i as usize] == 0.0 {
                return Err(ModelError::field(
                    "material.fibres",
                    format!("node {i} is on both the endocardial and the epicardial surface"),
                ));
            }
            value[i as usize] = 1.0;
        }
        if endo_nodes.is_empty() || epi_nodes.is_empty() {
            return Err(ModelError::field(
                "material.fibres",
                "needs nodes on both the endocardial and the epicardial surface",
            ));
        }
        let mut eq = vec![usize::MAX; n];
        let mut free = 0;
        for i in 0..n {
            if value[i].is_nan() {
                eq[i] = free;
                free += 1;
            }
        }
        let mut triplets = Vec::new();
        let mut rhs = Mat::<f64>::zeros(free.max(1), 1);
        for q in 0..fem.integration_point_count() {
            let w = fem.ip_weight_m3(q);
            let nodes = fem.ip_nodes(q);
            let grads = fem.ip_gradients(q);
            for (&na, ga) in nodes.iter().zip(grads) {
                let ra = eq[na as usize];
                if ra == usize::MAX {
                    continue;
                }
                for (&nb, gb) in nodes.iter().zip(grads) {
                    let k = w * ga.dot(*gb);
                    match eq[nb as usize] {
                        usize::MAX => rhs[(ra, 0)] -= k * value[nb as usize],
                        rb if rb <= ra => triplets.push(Triplet::new(ra, rb, k)),
                        _ => {}
                    }
                }
            }
        }
        if free > 0 {
            let k = SparseColMat::<usize, f64>::try_new_from_triplets(free, free, &triplets)
                .map_err(|e| ModelError::InvalidMesh(format!("fibre Laplace assembly: {e:?}")))?;
            let llt = k.sp_cholesky(Side::Lower).map_err(|e| {
                ModelError::InvalidMesh(format!(
                    "the fibre Laplace problem cannot be solved (a part of the mesh touches \
                     neither surface?): {e:?}"
                ))
            })?;
            llt.solve_in_place(rhs.as_mut());
            for i in 0..n {
                if eq[i] != usize::MAX {
                    value[i] = rhs[(eq[i], 0)].clamp(0.0, 1.0);
                }
            }
        }
        Ok(Self {
            rule,
            transmural: value,
        })
    }

    /// The frame `[f s n]` (columns) at a point with transmural coordinate `t` and its
    /// gradient `grad_t` (module documentation). Falls back to any frame with `n` along the
    /// gradient where the gradient is parallel to the axis (the apex).
    pub fn frame(&self, t: f64, grad_t: DVec3) -> DMat3 {
        let e_t = grad_t.normalize_or_zero();
        let e_t = if e_t == DVec3::ZERO { DVec3::X } else { e_t };
        let axis = self.rule.long_axis.normalize_or_zero();
        let mut e_c = e_t.cross(axis);
        if e_c.length_squared() < 1e-12 {
            e_c = e_t.any_orthonormal_vector();
        }
        let e_c = e_c.normalize();
        let e_l = e_c.cross(e_t);
        let alpha = (self.rule.helix_endo_deg
            + (self.rule.helix_epi_deg - self.rule.helix_endo_deg) * t.clamp(0.0, 1.0))
        .to_radians();
        let f = e_c * alpha.cos() + e_l * alpha.sin();
        let n = e_t;
        let s = n.cross(f);
        DMat3::from_cols(f, s, n)
    }
}

/// Values of the shape functions of point `k` of a cell with `nodes` nodes and `points`
/// integration points at the point (quadratic elements: the degree-2 Gauss rule; one-point
/// cells: the mean), written into `out` (length `nodes`).
pub(super) fn point_shape_values(nodes: usize, points: usize, k: usize, out: &mut Vec<f64>) {
    out.clear();
    if nodes == 10 && points == 4 {
        let mut l = [super::quadrature::GAUSS4_B; 4];
        l[k] = super::quadrature::GAUSS4_A;
        for li in l {
            out.push(li * (2.0 * li - 1.0));
        }
        for [i, j] in crate::mesh::TET_EDGES {
            out.push(4.0 * l[i] * l[j]);
        }
    } else {
        out.resize(nodes, 1.0 / nodes as f64);
    }
}
