//! Static equilibrium `f_int(x) + f_ext = 0` for reference solutions (Lamé sphere, patch tests,
//! converged probe references): Newton's method on the tangent stiffness of the material model with a
//! backtracking line search that accepts a step when it lowers the total potential energy
//! `W(x) - f_ext . x` or the residual norm (the energy criterion matters for slender bodies:
//! the linearised step of a bending beam leaves a large axial residual from the quadratic
//! Green strain even though it is an excellent step, and a residual-norm search alone
//! stalled); each linear system is solved by faer's sparse Cholesky (sparse LU
//! when the tangent is not positive definite, e.g. StVK under strong compression).
//!
//! Constrained components (see [`crate::fem::ConstraintMask`]) keep the values they have in the
//! initial positions, so prescribed displacements are imposed by setting them before the solve.
//!
//! Neighbours: [`crate::fem`] (forces, tangent blocks).

use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::fem::FemModel;
use crate::material;

/// Newton solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticParams {
    /// Stop when the free residual norm is below `rel_tol` times the external load norm
    /// (or `abs_tol_n` when the load is zero).
    pub rel_tol: f64,
    /// Absolute residual tolerance, N.
    pub abs_tol_n: f64,
    /// Largest Newton iteration count.
    pub max_iterations: usize,
}

impl Default for StaticParams {
    fn default() -> Self {
        Self {
            rel_tol: 1e-10,
            abs_tol_n: 1e-14,
            max_iterations: 50,
        }
    }
}

/// Outcome of a static solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StaticReport {
    /// Newton iterations used.
    pub iterations: usize,
    /// Final free residual norm, N.
    pub residual_n: f64,
}

/// Element tangent stiffness blocks `K_ab = -d f_a / d x_b` (3x3, N/m) of element `e` at
/// positions `x`, from the directional derivative of `f_a = -V P(F) grad N_a`
/// ([`material::first_piola_differential`] of the material model).
pub fn element_tangent(fem: &FemModel, e: usize, x: &[DVec3]) -> [[DMat3; 4]; 4] {
    let mat = &fem.material;
    let g = fem.shape_gradients(e);
    let fm = fem.deformation_gradient(e, x);
    let vol = fem.volume_m3[e];
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
            let dp = material::first_piola_differential(mat, &fm, &dfm);
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
    let mat = &fem.material;
    let npe = fem.cell_nodes(c).len();
    out.clear();
    out.resize(npe * npe, DMat3::ZERO);
    for q in fem.cell_points(c) {
        let g = fem.ip_gradients(q);
        let w = fem.ip_weight_m3(q);
        let fm = fem.ip_field_gradient(q, x);
        for b in 0..npe {
            for j in 0..3 {
                // dF = e_j (grad N_b)^T
                let mut dfm = DMat3::ZERO;
                for (c, gc) in g[b].to_array().into_iter().enumerate() {
                    dfm.col_mut(c)[j] = gc;
                }
                let dp = material::first_piola_differential(mat, &fm, &dfm);
                for a in 0..npe {
                    *out[a * npe + b].col_mut(j) += dp * g[a] * w;
                }
            }
        }
    }
}

/// Nodal forces (N) of a uniform pressure `pressure_pa` (Pa) on `triangles` at positions `x`:
/// each triangle carries `-p A n` (n its outward unit normal, A its area), one third per vertex.
/// A positive pressure pushes the surface inwards along its outward normal (for the inner
/// surface of a hollow body, whose outward normal faces the cavity, it inflates the body).
/// Evaluated at rest positions this is a dead load; re-evaluated each step, a follower load.
pub fn add_pressure_forces(triangles: &[[u32; 3]], x: &[DVec3], pressure_pa: f64, f: &mut [DVec3]) {
    for t in triangles {
        let [a, b, c] = t.map(|i| x[i as usize]);
        // (b-a) x (c-a) = 2 A n
        let fa = (b - a).cross(c - a) * (-pressure_pa / 6.0);
        for &i in t {
            f[i as usize] += fa;
        }
    }
}

/// Numbering of the free (unconstrained) degrees of freedom: `dof[3 i + c]` is the equation
/// number of component `c` of node `i`, or `usize::MAX` when it is constrained; and the count.
pub fn free_dofs(fem: &FemModel) -> (Vec<usize>, usize) {
    let mut dof = vec![usize::MAX; 3 * fem.node_count()];
    let mut free = 0;
    for (i, &mask) in fem.constraint.iter().enumerate() {
        for c in 0..3 {
            if mask & (1 << c) == 0 {
                dof[3 * i + c] = free;
                free += 1;
            }
        }
    }
    (dof, free)
}

/// Solves `f_int(x) + f_ext = 0` for the free components of `x` (m), starting from `x`, with
/// dead external nodal forces `f_ext` (N). Constrained components keep their values in `x`.
///
/// # Errors
/// [`ModelError::NoConvergence`] when Newton does not reach the tolerance or a factorisation
/// fails.
pub fn solve_static(
    fem: &FemModel,
    f_ext: &[DVec3],
    x: &mut [DVec3],
    params: &StaticParams,
) -> Result<StaticReport, ModelError> {
    let n = fem.node_count();
    let (dof, nfree) = free_dofs(fem);
    if nfree == 0 {
        return Ok(StaticReport {
            iterations: 0,
            residual_n: 0.0,
        });
    }
    let residual = |x: &[DVec3], r: &mut Vec<DVec3>| -> f64 {
        r.clear();
        r.extend_from_slice(f_ext);
        fem.add_internal_forces(x, None, r);
        let mut s = 0.0;
        for i in 0..n {
            for c in 0..3 {
                if dof[3 * i + c] != usize::MAX {
                    s += r[i][c] * r[i][c];
                }
            }
        }
        s.sqrt()
    };
    let load_norm = f_ext.iter().map(|v| v.length_squared()).sum::<f64>().sqrt();
    let tol = (params.rel_tol * load_norm).max(params.abs_tol_n);
    let mut r = Vec::with_capacity(n);
    let mut rnorm = residual(x, &mut r);
    let triplets_needed: usize = (0..fem.cell_count())
        .map(|c| 9 * fem.cell_nodes(c).len().pow(2))
        .sum();
    let mut triplets = Vec::with_capacity(triplets_needed);
    let npe = (0..fem.cell_count())
        .map(|c| fem.cell_nodes(c).len())
        .max()
        .unwrap_or(4);
    let mut blocks = Vec::with_capacity(npe * npe);
    let mut trial = x.to_vec();
    for it in 0..params.max_iterations {
        if rnorm <= tol {
            return Ok(StaticReport {
                iterations: it,
                residual_n: rnorm,
            });
        }
        triplets.clear();
        for c in 0..fem.cell_count() {
            cell_tangent_blocks(fem, c, x, &mut blocks);
            let t = fem.cell_nodes(c);
            let npe = t.len();
            for a in 0..npe {
                for b in 0..npe {
                    let k = &blocks[a * npe + b];
                    for ca in 0..3 {
                        let ra = dof[3 * t[a] as usize + ca];
                        if ra == usize::MAX {
                            continue;
                        }
                        for cb in 0..3 {
                            let rb = dof[3 * t[b] as usize + cb];
                            if rb != usize::MAX {
                                // column cb, row ca of the block
                                triplets.push(Triplet::new(ra, rb, k.col(cb)[ca]));
                            }
                        }
                    }
                }
            }
        }
        let kmat = SparseColMat::<usize, f64>::try_new_from_triplets(nfree, nfree, &triplets)
            .map_err(|e| ModelError::NoConvergence(format!("assembling the tangent: {e:?}")))?;
        let mut rhs = Mat::<f64>::zeros(nfree, 1);
        for i in 0..n {
            for c in 0..3 {
                let d = dof[3 * i + c];
                if d != usize::MAX {
                    rhs[(d, 0)] = r[i][c];
                }
            }
        }
        // K dx = r (r = f_int + f_ext, K = -d f_int/dx).
        match kmat.sp_cholesky(Side::Lower) {
            Ok(llt) => llt.solve_in_place(rhs.as_mut()),
            Err(_) => kmat
                .sp_lu()
                .map_err(|e| ModelError::NoConvergence(format!("factorising the tangent: {e:?}")))?
                .solve_in_place(rhs.as_mut()),
        }
        // Backtracking line search on the total potential or the residual norm (module docs).
        let potential = |y: &[DVec3]| {
            fem.elastic_energy(y) - y.iter().zip(f_ext).map(|(a, b)| a.dot(*b)).sum::<f64>()
        };
        let pi0 = potential(x);
        let mut step = 1.0;
        loop {
            trial.copy_from_slice(x);
            for i in 0..n {
                for c in 0..3 {
                    let d = dof[3 * i + c];
                    if d != usize::MAX {
                        trial[i][c] += step * rhs[(d, 0)];
                    }
                }
            }
            let tn = residual(&trial, &mut r);
            if tn < rnorm || (tn.is_finite() && potential(&trial) < pi0) || step < 1e-3 {
                x.copy_from_slice(&trial);
                rnorm = tn;
                break;
            }
            step *= 0.5;
        }
        if !rnorm.is_finite() {
            return Err(ModelError::NoConvergence(
                "the residual became non-finite".into(),
            ));
        }
    }
    if rnorm <= tol {
        Ok(StaticReport {
            iterations: params.max_iterations,
            residual_n: rnorm,
        })
    } else {
        Err(ModelError::NoConvergence(format!(
            "Newton stopped after {} iterations with residual {rnorm:.3e} N (tolerance {tol:.3e} N)",
            params.max_iterations
        )))
    }
}
