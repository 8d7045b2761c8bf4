//! Static equilibrium `f_int(x) + f_ext = 0` for reference solutions (Lamé sphere, patch tests,
//! converged probe references): Newton's method on the tangent stiffness of the material model with a
//! backtracking line search that accepts a step when it lowers the total potential energy
//! `W(x) - f_ext . x` or the residual norm (the energy criterion matters for slender bodies:
//! the linearised step of a bending beam leaves a large axial residual from the quadratic
//! Green strain even though it is an excellent step, and a residual-norm search alone
//! stalled); each linear system is solved by faer's sparse Cholesky (sparse LU
//! when the tangent is not positive definite, e.g. StVK under strong compression).
//!
//! Constrained components (see [`crate::element::ConstraintMask`]) keep the values they have in the
//! initial positions, so prescribed displacements are imposed by setting them before the solve.
//!
//! Besides dead loads, a solve may carry one extra potential term ([`StaticTerm`]: its energy,
//! forces and stiffness), which is how the sphere indentation of [`crate::indent`] adds its
//! augmented-Lagrangian contact energy without the solver knowing about contact.
//!
//! Owns: the Newton solver and nothing else (loads come from [`crate::loads`], tangents from
//! [`crate::element::tangent`]). Not used by the real-time path.

use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::element::tangent::cell_tangent_blocks;
use crate::element::{ConstraintMask, FemModel};

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

/// Numbering of the free (unconstrained) degrees of freedom: `dof[3 i + c]` is the equation
/// number of component `c` of node `i`, or `usize::MAX` when it is constrained; and the count.
pub fn free_dofs(fem: &FemModel) -> (Vec<usize>, usize) {
    let mut dof = vec![usize::MAX; 3 * fem.node_count()];
    let mut free = 0;
    for (i, &mask) in fem.constraints().iter().enumerate() {
        for c in 0..3 {
            if mask & (1 << c) == 0 {
                dof[3 * i + c] = free;
                free += 1;
            }
        }
    }
    (dof, free)
}

/// Norm of the free components of the residual `f_int(x) + f_ext` (N): what
/// [`solve_static`] drives to zero. Allocates one force vector.
///
/// # Panics
/// If `f_ext` or `x` is shorter than the node count.
pub fn free_residual_norm(fem: &FemModel, f_ext: &[DVec3], x: &[DVec3]) -> f64 {
    let mut r = f_ext[..fem.node_count()].to_vec();
    fem.add_internal_forces(x, None, &mut r);
    free_norm(fem.constraints(), &r)
}

/// Appends the free entries of the 3x3 block `k` coupling nodes `i` (rows) and `j` (columns)
/// to `triplets`, in the equation numbering `dof` of [`free_dofs`].
fn push_block(
    triplets: &mut Vec<Triplet<usize, usize, f64>>,
    dof: &[usize],
    i: u32,
    j: u32,
    k: &DMat3,
) {
    for ca in 0..3 {
        let ra = dof[3 * i as usize + ca];
        if ra == usize::MAX {
            continue;
        }
        for cb in 0..3 {
            let rb = dof[3 * j as usize + cb];
            if rb != usize::MAX {
                // column cb, row ca of the block
                triplets.push(Triplet::new(ra, rb, k.col(cb)[ca]));
            }
        }
    }
}

/// Norm of the unconstrained components of `r`.
fn free_norm(constraint: &[ConstraintMask], r: &[DVec3]) -> f64 {
    let mut s = 0.0;
    for (ri, &mask) in r.iter().zip(constraint) {
        for c in 0..3 {
            if mask & (1 << c) == 0 {
                s += ri[c] * ri[c];
            }
        }
    }
    s.sqrt()
}

/// An extra potential energy `E(x)` a static solve minimises together with the elastic energy
/// (a contact term, a spring to a target). Its forces are `-dE/dx`, its stiffness
/// `d^2E/dx^2`; both must be consistent with `energy` (the line search uses it).
pub trait StaticTerm {
    /// `E(x)`, J.
    fn energy(&self, x: &[DVec3]) -> f64;
    /// Adds `-dE/dx` (N, one vector per node) to `f`.
    fn add_forces(&self, x: &[DVec3], f: &mut [DVec3]);
    /// Calls `add(i, j, K_ij)` for every nonzero 3x3 block `d^2E / dx_i dx_j` (N/m) of the
    /// stiffness at `x` (blocks may repeat; they are summed).
    fn for_each_stiffness_block(&self, x: &[DVec3], add: &mut dyn FnMut(u32, u32, DMat3));
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
    solve_static_with(fem, f_ext, None, x, params)
}

/// [`solve_static`] with an extra potential term: solves `f_int(x) + f_ext + f_term(x) = 0`.
/// The tolerance is `params.rel_tol` times `|f_ext| + |f_term(x)|` (the term's forces count as
/// load: a displacement-driven contact has no external load at all). An empty `f_ext` means
/// no external load.
///
/// # Errors
/// As [`solve_static`].
pub fn solve_static_with(
    fem: &FemModel,
    f_ext: &[DVec3],
    term: Option<&dyn StaticTerm>,
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
    let no_load;
    let f_ext = if f_ext.is_empty() {
        no_load = vec![DVec3::ZERO; n];
        &no_load[..]
    } else {
        f_ext
    };
    let load_norm = f_ext.iter().map(|v| v.length_squared()).sum::<f64>().sqrt();
    let mut term_f = vec![DVec3::ZERO; if term.is_some() { n } else { 0 }];
    // The extra term's share of the load scale: the largest norm of its forces seen so far, so
    // an iterate where the term lets go (a contact released) does not shrink the tolerance to
    // `abs_tol_n`.
    let mut term_scale = 0.0f64;
    // Residual r = f_ext + f_int + f_term at x, its free norm and the tolerance there.
    let mut residual = |x: &[DVec3], r: &mut Vec<DVec3>| -> (f64, f64) {
        r.clear();
        r.extend_from_slice(f_ext);
        fem.add_internal_forces(x, None, r);
        let mut scale = load_norm;
        if let Some(term) = term {
            term_f.iter_mut().for_each(|v| *v = DVec3::ZERO);
            term.add_forces(x, &mut term_f);
            let mut s2 = 0.0;
            for (ri, fi) in r.iter_mut().zip(&term_f) {
                *ri += *fi;
                s2 += fi.length_squared();
            }
            term_scale = term_scale.max(s2.sqrt());
            scale += term_scale;
        }
        (
            free_norm(fem.constraints(), r),
            (params.rel_tol * scale).max(params.abs_tol_n),
        )
    };
    let mut r = Vec::with_capacity(n);
    let (mut rnorm, mut tol) = residual(x, &mut r);
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
                    push_block(&mut triplets, &dof, t[a], t[b], &blocks[a * npe + b]);
                }
            }
        }
        if let Some(term) = term {
            term.for_each_stiffness_block(x, &mut |i, j, k| {
                push_block(&mut triplets, &dof, i, j, &k);
            });
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
                + term.map_or(0.0, |t| t.energy(y))
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
            let (tn, ttol) = residual(&trial, &mut r);
            if tn < rnorm || (tn.is_finite() && potential(&trial) < pi0) || step < 1e-3 {
                x.copy_from_slice(&trial);
                (rnorm, tol) = (tn, ttol);
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
