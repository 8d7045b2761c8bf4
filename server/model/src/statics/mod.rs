//! Static equilibrium `f_int(x) + f_ext = 0` for reference solutions (Lamé sphere, patch tests,
//! converged probe references): Newton's method on the tangent stiffness of the material model with a
//! backtracking line search that accepts a step when it lowers the total potential energy
//! `W(x) - f_ext . x` or the residual norm (the energy criterion matters for slender bodies:
//! the linearised step of a bending beam leaves a large axial residual from the quadratic
//! Green strain even though it is an excellent step, and a residual-norm search alone
//! stalled); each linear system is solved by faer's sparse Cholesky under a nested-dissection
//! ordering ([`crate::linalg::ordering`]; when the tangent is not positive definite, e.g. StVK under
//! strong compression or a sphere contact's curvature term, an unpivoted `L D L^T` on the same
//! analysis checked by its residual, else sparse LU), the pattern's ordering and symbolic
//! factorisation computed once per solve.
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
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::sparse::{Argsort, Pair, SparseColMat, SymbolicSparseColMat, Triplet};
use faer::{Mat, Side};
use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::element::tangent::cell_tangent_blocks;
use crate::element::{ConstraintMask, FemModel};
use crate::linalg::ordering::SparseCholesky;
use crate::loads::{SceneLoads, add_pressure_load, face_points, face_tangents, quadratic_face};
mod load_path;
pub use load_path::{
    LoadPathReport, MAX_VOLUME_PASSES, VOLUME_TOLERANCE, penalty_continuation, solve_scene_loads,
    with_bulk_modulus,
};

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
    /// Threads of each Newton system's factorisation (1: the calling thread;
    /// [`crate::linalg::ordering::SparseCholesky::with_threads`]: more give the same
    /// Cholesky factor and an `L D L^T` equal to round-off).
    pub threads: usize,
}

impl Default for StaticParams {
    fn default() -> Self {
        Self {
            rel_tol: 1e-10,
            abs_tol_n: 1e-14,
            max_iterations: 50,
            threads: 1,
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

/// Largest relative residual `|K dx - r| / |r|` of an unpivoted `L D L^T` solve of an
/// indefinite tangent that Newton takes (else sparse LU solves it): an inexact Newton step
/// this accurate keeps the iteration's quadratic convergence to the solver's tolerances.
const LDLT_RESIDUAL: f64 = 1e-8;

/// The Newton tangent `K` in the free equation numbering, assembled for one
/// [`solve_static_with`] call: the cells' entries, whose pattern is the same at every
/// iteration, and a [`StaticTerm`]'s, whose coupled nodes change with the iterate (a contact's
/// active set). The sparsity pattern and its symbolic Cholesky factorisation (ordering,
/// elimination tree) are built at the first iteration and kept; a term entry outside the
/// pattern is added to it and the analysis redone (on a sphere contact, never: a contact
/// point's nodes share a cell). The sort and the ordering cost more than the numeric
/// factorisation on quadratic meshes, so most iterations skip them.
#[derive(Default)]
struct Tangent {
    /// Row and column of each cell entry, in assembly order (duplicates are summed).
    pairs: Vec<Pair<usize, usize>>,
    /// Value of each entry of `pairs`.
    vals: Vec<f64>,
    /// The term's entries of this iteration.
    term: Vec<Triplet<usize, usize, f64>>,
    /// Term entries outside the cells' pattern met so far: part of the pattern.
    extra: Vec<Pair<usize, usize>>,
    /// The symbolic matrix of `pairs` and `extra`, the order of their values and the symbolic
    /// Cholesky (if the analysis succeeded).
    pattern: Option<Pattern>,
    /// `vals` followed by a zero per `extra` entry.
    padded: Vec<f64>,
    /// The node of each free equation: the supervariables of the ordering.
    group: Vec<usize>,
    /// Threads of the factorisations ([`StaticParams::threads`]).
    threads: usize,
    /// Which factorisation solved the last system.
    last: Factorisation,
}

/// The factorisation that solved a Newton system ([`Tangent::solve`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
enum Factorisation {
    /// Sparse Cholesky (the tangent is positive definite).
    #[default]
    Llt,
    /// Unpivoted `L D L^T` on the Cholesky's analysis (indefinite, accepted by its residual).
    Ldlt,
    /// Sparse LU.
    Lu,
}

/// The kept analysis of a [`Tangent`]'s pattern.
struct Pattern {
    symbolic: SymbolicSparseColMat<usize>,
    /// The order of the values in `symbolic` for the entries as assembled.
    argsort: Argsort<usize>,
    /// The Cholesky (or `L D L^T`) factor under a nested-dissection ordering
    /// ([`crate::linalg::ordering`]), analysed once per pattern.
    llt: SparseCholesky,
    /// The symbolic LU, made the first time Cholesky fails.
    lu: Option<SymbolicLu<usize>>,
}

impl Tangent {
    fn clear(&mut self) {
        self.pairs.clear();
        self.vals.clear();
        self.term.clear();
    }

    /// Clears the tangent and pushes the cells' tangent blocks at `x` and the term's
    /// stiffness blocks (`blocks` a work array).
    fn fill_at(
        &mut self,
        fem: &FemModel,
        term: Option<&dyn StaticTerm>,
        x: &[DVec3],
        dof: &[usize],
        blocks: &mut Vec<DMat3>,
    ) {
        self.clear();
        for c in 0..fem.cell_count() {
            cell_tangent_blocks(fem, c, x, blocks);
            let t = fem.cell_nodes(c);
            let npe = t.len();
            for a in 0..npe {
                for b in 0..npe {
                    self.push_block(dof, t[a], t[b], &blocks[a * npe + b], false);
                }
            }
        }
        if let Some(term) = term {
            term.for_each_stiffness_block(x, &mut |i, j, k| {
                self.push_block(dof, i, j, &k, true);
            });
        }
    }

    /// Appends the free entries of the 3x3 block `k` coupling nodes `i` (rows) and `j`
    /// (columns), in the equation numbering `dof` of [`free_dofs`]: a cell's block, or with
    /// `from_term` a [`StaticTerm`]'s.
    fn push_block(&mut self, dof: &[usize], i: u32, j: u32, k: &DMat3, from_term: bool) {
        for ca in 0..3 {
            let ra = dof[3 * i as usize + ca];
            if ra == usize::MAX {
                continue;
            }
            for cb in 0..3 {
                let rb = dof[3 * j as usize + cb];
                if rb != usize::MAX {
                    // column cb, row ca of the block
                    let v = k.col(cb)[ca];
                    if from_term {
                        self.term.push(Triplet::new(ra, rb, v));
                    } else {
                        self.pairs.push(Pair::new(ra, rb));
                        self.vals.push(v);
                    }
                }
            }
        }
    }

    /// The assembled `K` on the kept pattern (built or extended as needed).
    fn assemble(&mut self, nfree: usize) -> Result<SparseColMat<usize, f64>, ModelError> {
        let assembly = |e: &dyn std::fmt::Debug| {
            ModelError::NoConvergence(format!("assembling the tangent: {e:?}"))
        };
        loop {
            if self.pattern.is_none() {
                let mut all = self.pairs.clone();
                all.extend_from_slice(&self.extra);
                let (symbolic, argsort) =
                    SymbolicSparseColMat::try_new_from_indices(nfree, nfree, &all)
                        .map_err(|e| assembly(&e))?;
                let llt = SparseCholesky::analyse(symbolic.as_ref(), Side::Lower, &self.group)
                    .map_err(|e| assembly(&e))?
                    .with_threads(self.threads);
                self.pattern = Some(Pattern {
                    symbolic,
                    argsort,
                    llt,
                    lu: None,
                });
            }
            let Some(Pattern {
                symbolic, argsort, ..
            }) = &self.pattern
            else {
                unreachable!("the pattern was built above")
            };
            self.padded.clear();
            self.padded.extend_from_slice(&self.vals);
            self.padded.resize(self.vals.len() + self.extra.len(), 0.0);
            let mut kmat = SparseColMat::new_from_argsort(symbolic.clone(), argsort, &self.padded)
                .map_err(|e| assembly(&e))?;
            let (col_ptr, row_idx) = (symbolic.col_ptr(), symbolic.row_idx());
            let mut missing = false;
            let vals = kmat.val_mut();
            for t in &self.term {
                let rows = &row_idx[col_ptr[t.col]..col_ptr[t.col + 1]];
                // Rows are sorted within a column; the linear search is a guard.
                let found = rows
                    .binary_search(&t.row)
                    .ok()
                    .or_else(|| rows.iter().position(|&r| r == t.row));
                match found {
                    Some(p) => vals[col_ptr[t.col] + p] += t.val,
                    None => {
                        self.extra.push(Pair::new(t.row, t.col));
                        missing = true;
                    }
                }
            }
            if !missing {
                return Ok(kmat);
            }
            self.pattern = None;
        }
    }

    /// Solves `K dx = r` in place of `rhs` (`nfree` equations): sparse Cholesky on the kept
    /// symbolic factorisation (nested-dissection ordering, [`crate::linalg::ordering`]); when `K` is not
    /// positive definite (StVK under strong compression, the curvature term of a sphere
    /// contact), `L D L^T` without pivoting on the same analysis, kept when its solution's
    /// residual is below [`LDLT_RESIDUAL`] of `|r|`; sparse LU otherwise. Why not a diagonal
    /// shift: docs/decisions.md ("Newton's linear systems keep their pattern").
    fn solve(&mut self, nfree: usize, mut rhs: faer::MatMut<'_, f64>) -> Result<(), ModelError> {
        let kmat = self.assemble(nfree)?;
        let Some(pattern) = &mut self.pattern else {
            unreachable!("assemble built the pattern")
        };
        let llt = &mut pattern.llt;
        if llt.factor_llt(kmat.as_ref(), Side::Lower).is_ok() {
            llt.solve_in_place(rhs);
            self.last = Factorisation::Llt;
            return Ok(());
        }
        if llt.factor_ldlt(kmat.as_ref(), Side::Lower).is_ok() {
            let mut x = rhs.to_owned();
            llt.solve_in_place(x.as_mut());
            let residual = (kmat.as_ref() * x.as_ref() - rhs.as_ref()).norm_l2();
            if residual <= LDLT_RESIDUAL * rhs.norm_l2() {
                rhs.copy_from(&x);
                self.last = Factorisation::Ldlt;
                return Ok(());
            }
        }
        let factorising = |e: &dyn std::fmt::Debug| {
            ModelError::NoConvergence(format!("factorising the tangent: {e:?}"))
        };
        let lu_symbolic = match &pattern.lu {
            Some(lu) => lu.clone(),
            None => {
                let lu =
                    SymbolicLu::try_new(pattern.symbolic.as_ref()).map_err(|e| factorising(&e))?;
                pattern.lu = Some(lu.clone());
                lu
            }
        };
        Lu::try_new_with_symbolic(lu_symbolic, kmat.as_ref())
            .map_err(|e| factorising(&e))?
            .solve_in_place(rhs);
        self.last = Factorisation::Lu;
        Ok(())
    }
}

/// The node of each free equation of the numbering `dof` of [`free_dofs`] (`nfree` of them).
fn free_dof_nodes(dof: &[usize], nfree: usize) -> Vec<usize> {
    let mut group = vec![0; nfree];
    for (k, &d) in dof.iter().enumerate() {
        if d != usize::MAX {
            group[d] = k / 3;
        }
    }
    group
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

/// Follower pressures as a [`StaticTerm`], so that Newton sees their load stiffness.
///
/// - Flat triangles `(a, b, c)` (outward oriented; linear meshes) of a pressure `p` carry the
///   force `-p/6 (b - a) x (c - a)` on each of their nodes ([`crate::loads::add_pressure_forces`]) and the
///   stiffness blocks `K_ka = p/6 [c - b]x`, `K_kb = p/6 [a - c]x`, `K_kc = p/6 [b - a]x` for
///   `k` in `a, b, c` (`[v]x` the cross-product matrix).
/// - Curved 6-node faces (quadratic meshes, [`crate::loads::PressureLoad::quadratic`]) carry
///   the consistent forces `f_k = -p int N_k (x_xi x x_eta)`
///   ([`crate::loads::add_quadratic_pressure_forces`]) and the stiffness
///   `K_kb = p int N_k (N_b,eta [x_xi]x - N_b,xi [x_eta]x)`, by the same exact rule.
///
/// The dynamic bodies apply the same forces. The energy is `E = p V`, `V` the volume of the
/// cone from the origin over the surface (`sum (1/6) a . (b x c)`, or `(1/3) int x . n dA`),
/// so `-dE/dx` equals the forces at every node whose faces close around it; on an open surface
/// the rim nodes differ, and the assembled stiffness is then symmetric only when the rim is
/// clamped (as the LV's endocardium at the base). On a free rim the Cholesky factorisation
/// reads the lower half of a slightly unsymmetric tangent: Newton converges more slowly there,
/// never to a wrong answer (the residual it checks is exact).
///
/// Source: the load stiffness of a follower pressure (e.g. Bonet & Wood, Nonlinear Continuum
/// Mechanics for Finite Element Analysis, 2nd ed., section 8.5).
pub struct FollowerPressure<'a> {
    /// (triangles, Pa, quadratic faces).
    loads: Vec<(&'a [[u32; 3]], f64, bool)>,
}

impl<'a> FollowerPressure<'a> {
    /// The follower pressures of `loads`, each multiplied by `scale` (a load increment's
    /// fraction). Dead pressures are not included (see [`crate::loads::static_dead_forces`]).
    pub fn new(loads: &'a SceneLoads, scale: f64) -> Self {
        Self {
            loads: loads
                .pressure
                .iter()
                .filter(|p| p.follower)
                .map(|p| (&p.triangles[..], p.pressure_pa * scale, p.quadratic))
                .collect(),
        }
    }

    /// Whether there is no follower pressure.
    pub fn is_empty(&self) -> bool {
        self.loads.is_empty()
    }
}

/// The cross-product matrix `[v]x`: `[v]x u = v x u`.
fn cross_matrix(v: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, v.z, -v.y),
        DVec3::new(-v.z, 0.0, v.x),
        DVec3::new(v.y, -v.x, 0.0),
    )
}

impl StaticTerm for FollowerPressure<'_> {
    fn energy(&self, x: &[DVec3]) -> f64 {
        let points = face_points();
        let mut e = 0.0;
        for &(tris, p, quadratic) in &self.loads {
            let v: f64 = if quadratic {
                tris.chunks(4)
                    .map(|g| {
                        let face = quadratic_face(g).expect("four-way split of a 6-node face");
                        points
                            .iter()
                            .map(|q| {
                                let (t_xi, t_eta) = face_tangents(q, &face, x);
                                let at: DVec3 = face
                                    .iter()
                                    .zip(&q.n)
                                    .map(|(&i, n)| x[i as usize] * *n)
                                    .sum();
                                q.w * at.dot(t_xi.cross(t_eta)) / 3.0
                            })
                            .sum::<f64>()
                    })
                    .sum()
            } else {
                tris.iter()
                    .map(|t| {
                        let [a, b, c] = t.map(|i| x[i as usize]);
                        a.dot(b.cross(c)) / 6.0
                    })
                    .sum()
            };
            e += p * v;
        }
        e
    }

    fn add_forces(&self, x: &[DVec3], f: &mut [DVec3]) {
        for &(tris, p, quadratic) in &self.loads {
            add_pressure_load(tris, quadratic, x, p, f);
        }
    }

    fn for_each_stiffness_block(&self, x: &[DVec3], add: &mut dyn FnMut(u32, u32, DMat3)) {
        let points = face_points();
        for &(tris, p, quadratic) in &self.loads {
            if quadratic {
                for g in tris.chunks(4) {
                    let face = quadratic_face(g).expect("four-way split of a 6-node face");
                    let mut blocks = [DMat3::ZERO; 36];
                    for q in &points {
                        let (t_xi, t_eta) = face_tangents(q, &face, x);
                        let (c_xi, c_eta) = (cross_matrix(t_xi), cross_matrix(t_eta));
                        for b in 0..6 {
                            let d = (c_xi * q.deta[b] - c_eta * q.dxi[b]) * (p * q.w);
                            for k in 0..6 {
                                blocks[6 * k + b] += d * q.n[k];
                            }
                        }
                    }
                    for k in 0..6 {
                        for b in 0..6 {
                            add(face[k], face[b], blocks[6 * k + b]);
                        }
                    }
                }
                continue;
            }
            for t in tris.iter() {
                let [a, b, c] = t.map(|i| x[i as usize]);
                let cols = [
                    cross_matrix(c - b) * (p / 6.0),
                    cross_matrix(a - c) * (p / 6.0),
                    cross_matrix(b - a) * (p / 6.0),
                ];
                for &k in t {
                    for (&j, kj) in t.iter().zip(&cols) {
                        add(k, j, *kj);
                    }
                }
            }
        }
    }
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
    let mut residual = Residual {
        fem,
        f_ext,
        term,
        params,
        load_norm: f_ext.iter().map(|v| v.length_squared()).sum::<f64>().sqrt(),
        term_f: vec![DVec3::ZERO; if term.is_some() { n } else { 0 }],
        term_scale: 0.0,
    };
    let mut r = Vec::with_capacity(n);
    let (mut rnorm, mut tol) = residual.eval(x, &mut r);
    let mut tangent = Tangent {
        group: free_dof_nodes(&dof, nfree),
        threads: params.threads,
        ..Tangent::default()
    };
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
        tangent.fill_at(fem, term, x, &dof, &mut blocks);
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
        tangent.solve(nfree, rhs.as_mut())?;
        let search = LineSearch {
            dof: &dof,
            dx: &rhs,
            rnorm,
        };
        (rnorm, tol) = search.run(&mut residual, x, &mut trial, &mut r);
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

/// The residual of [`solve_static_with`] and its tolerance.
struct Residual<'a> {
    fem: &'a FemModel,
    /// Dead external nodal forces, N (one per node).
    f_ext: &'a [DVec3],
    term: Option<&'a dyn StaticTerm>,
    params: &'a StaticParams,
    /// `|f_ext|`, N.
    load_norm: f64,
    /// The term's forces (one per node with a term, else empty), N.
    term_f: Vec<DVec3>,
    /// The extra term's share of the load scale: the largest norm of its forces seen so far,
    /// so an iterate where the term lets go (a contact released) does not shrink the
    /// tolerance to `abs_tol_n`.
    term_scale: f64,
}

impl Residual<'_> {
    /// Residual `r = f_ext + f_int + f_term` at `x`; returns its free norm and the tolerance
    /// there (N).
    fn eval(&mut self, x: &[DVec3], r: &mut Vec<DVec3>) -> (f64, f64) {
        r.clear();
        r.extend_from_slice(self.f_ext);
        self.fem.add_internal_forces(x, None, r);
        let mut scale = self.load_norm;
        if let Some(term) = self.term {
            self.term_f.iter_mut().for_each(|v| *v = DVec3::ZERO);
            term.add_forces(x, &mut self.term_f);
            let mut s2 = 0.0;
            for (ri, fi) in r.iter_mut().zip(&self.term_f) {
                *ri += *fi;
                s2 += fi.length_squared();
            }
            self.term_scale = self.term_scale.max(s2.sqrt());
            scale += self.term_scale;
        }
        (
            free_norm(self.fem.constraints(), r),
            (self.params.rel_tol * scale).max(self.params.abs_tol_n),
        )
    }

    /// The total potential at `y`, J: elastic energy, minus the dead loads' work, plus the
    /// term's energy.
    fn potential(&self, y: &[DVec3]) -> f64 {
        self.fem.elastic_energy(y)
            - y.iter()
                .zip(self.f_ext)
                .map(|(a, b)| a.dot(*b))
                .sum::<f64>()
            + self.term.map_or(0.0, |t| t.energy(y))
    }
}

/// One backtracking line search of [`solve_static_with`] along the Newton step `dx`.
struct LineSearch<'a> {
    /// Free equation of each global component, or `usize::MAX`.
    dof: &'a [usize],
    /// The Newton step on the free equations (one column), m.
    dx: &'a Mat<f64>,
    /// The residual's free norm at `x`, N.
    rnorm: f64,
}

impl LineSearch<'_> {
    /// Halves the step from 1 until the residual norm or the total potential decreases (or
    /// the step is below 1e-3; module documentation), then moves `x` there (`trial` and `r`
    /// are work arrays; `r` holds the residual there). Returns the residual's free norm and
    /// the tolerance at the new `x`.
    fn run(
        &self,
        residual: &mut Residual<'_>,
        x: &mut [DVec3],
        trial: &mut [DVec3],
        r: &mut Vec<DVec3>,
    ) -> (f64, f64) {
        let pi0 = residual.potential(x);
        let mut step = 1.0;
        loop {
            trial.copy_from_slice(x);
            for (i, t) in trial.iter_mut().enumerate().take(self.dof.len() / 3) {
                for c in 0..3 {
                    let d = self.dof[3 * i + c];
                    if d != usize::MAX {
                        t[c] += step * self.dx[(d, 0)];
                    }
                }
            }
            let (tn, ttol) = residual.eval(trial, r);
            if tn < self.rnorm || (tn.is_finite() && residual.potential(trial) < pi0) || step < 1e-3
            {
                x.copy_from_slice(trial);
                return (tn, ttol);
            }
            step *= 0.5;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::MaterialParams;

    /// Dense `K` of the entries pushed to `t` (cells and term), `n` equations.
    fn dense(t: &Tangent, n: usize) -> Mat<f64> {
        let mut k = Mat::<f64>::zeros(n, n);
        for (p, v) in t.pairs.iter().zip(&t.vals) {
            k[(p.row, p.col)] += v;
        }
        for e in &t.term {
            k[(e.row, e.col)] += e.val;
        }
        k
    }

    /// A chain of `nodes` nodes with 3x3 blocks `a` on the diagonal and `b` between
    /// neighbours; node 0 fully constrained (its equations are dropped).
    fn chain(t: &mut Tangent, dof: &[usize], nodes: u32, a: DMat3, b: DMat3) {
        t.clear();
        for i in 0..nodes {
            t.push_block(dof, i, i, &a, false);
            if i + 1 < nodes {
                t.push_block(dof, i, i + 1, &b, false);
                t.push_block(dof, i + 1, i, &b.transpose(), false);
            }
        }
    }

    #[test]
    fn tangent_solves_match_dense_and_extend_the_pattern() {
        // Enough nodes for the nested-dissection ordering (crate::linalg::ordering::MIN_VERTICES).
        let nodes = 80u32;
        // Node 0 constrained: dof numbering skips it.
        let mut dof = vec![usize::MAX; 3 * nodes as usize];
        for (k, d) in dof.iter_mut().skip(3).enumerate() {
            *d = k;
        }
        let n = 3 * (nodes as usize - 1);
        let a = DMat3::from_cols_array(&[4.0, 0.5, 0.0, 0.5, 5.0, 0.2, 0.0, 0.2, 6.0]);
        let b = DMat3::from_cols_array(&[-1.0, 0.1, 0.0, 0.0, -1.2, 0.1, 0.3, 0.0, -0.9]);
        let mut t = tangent_for(&dof);
        let rhs_of = |n: usize| Mat::<f64>::from_fn(n, 1, |i, _| 1.0 + i as f64 * 0.25);
        for iteration in 0..3 {
            chain(&mut t, &dof, nodes, a * (1.0 + 0.1 * iteration as f64), b);
            // A term coupling nodes 1 and 5, outside the chain's pattern: the pattern grows.
            let c = DMat3::from_diagonal(DVec3::new(0.3, 0.2, 0.1));
            t.push_block(&dof, 1, 5, &c, true);
            t.push_block(&dof, 5, 1, &c, true);
            t.push_block(&dof, 1, 1, &c, true);
            t.push_block(&dof, 5, 5, &c, true);
            let k = dense(&t, n);
            let r = rhs_of(n);
            let mut x = r.clone();
            t.solve(n, x.as_mut()).unwrap();
            let residual = &k * &x - &r;
            assert!(
                residual.norm_l2() < 1e-12 * r.norm_l2(),
                "iteration {iteration}"
            );
            assert_eq!(t.last, Factorisation::Llt);
            assert_eq!(
                t.extra.len(),
                2 * 9,
                "the term's off-pattern blocks were added once"
            );
        }
    }

    /// A tangent whose free equations are numbered as `dof` (three per node).
    fn tangent_for(dof: &[usize]) -> Tangent {
        let nfree = dof.iter().filter(|&&d| d != usize::MAX).count();
        Tangent {
            group: free_dof_nodes(dof, nfree),
            ..Tangent::default()
        }
    }

    #[test]
    fn an_indefinite_tangent_is_solved_exactly() {
        let nodes = 4u32;
        let dof: Vec<usize> = (0..3 * nodes as usize).collect();
        let n = dof.len();
        let r = Mat::<f64>::from_fn(n, 1, |i, _| if i % 3 == 2 { 1.0 } else { 0.3 });
        // Diagonal blocks with one negative eigenvalue each: K is indefinite, Cholesky fails
        // and L D L^T answers. Then blocks with a zero leading entry: the unpivoted L D L^T
        // meets a zero pivot, and LU answers.
        let indefinite = DMat3::from_diagonal(DVec3::new(3.0, 2.0, -0.5));
        let zero_pivot = DMat3::from_cols_array(&[0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        for (a, expected) in [
            (indefinite, Factorisation::Ldlt),
            (zero_pivot, Factorisation::Lu),
        ] {
            let b = DMat3::from_diagonal(DVec3::splat(-0.4));
            let mut t = tangent_for(&dof);
            chain(&mut t, &dof, nodes, a, b);
            let mut x = r.clone();
            t.solve(n, x.as_mut()).unwrap();
            assert_eq!(t.last, expected);
            let k = dense(&t, n);
            assert!(
                k.llt(Side::Lower).is_err(),
                "the test matrix must be indefinite"
            );
            let residual = &k * &x - &r;
            assert!(residual.norm_l2() < 1e-12 * r.norm_l2(), "{expected:?}");
        }
    }

    /// The inner surface of a thick sphere (linear or quadratic), its nodes moved off the
    /// sphere, with a pressure.
    fn pressed_surface(quadratic: bool) -> (SceneLoads, Vec<DVec3>) {
        let mesh = if quadratic {
            crate::mesh::generate::sphere_shell_quadratic(7e-3, 10e-3, 150)
        } else {
            crate::mesh::generate::sphere_shell(7e-3, 10e-3, 400)
        };
        let tris = mesh.surface("INNER").unwrap().triangles.clone();
        assert_eq!(crate::loads::is_quadratic_split(&tris), quadratic);
        let loads = SceneLoads {
            pressure: vec![crate::loads::PressureLoad {
                surfaces: vec!["INNER".into()],
                triangles: tris,
                pressure_pa: 1.0e4,
                follower: true,
                quadratic,
            }],
            ..SceneLoads::default()
        };
        let x = mesh
            .nodes
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let k = i as f64;
                *p + DVec3::new((k * 1.3).sin(), (k * 2.1).cos(), (k * 0.7).sin()) * 4e-4
            })
            .collect();
        (loads, x)
    }

    #[test]
    fn follower_pressure_forces_are_the_energy_gradient_on_a_closed_surface() {
        for quadratic in [false, true] {
            forces_are_the_energy_gradient(quadratic);
        }
    }

    fn forces_are_the_energy_gradient(quadratic: bool) {
        let (loads, x) = pressed_surface(quadratic);
        let term = FollowerPressure::new(&loads, 0.8);
        let mut f = vec![DVec3::ZERO; x.len()];
        term.add_forces(&x, &mut f);
        let on_surface: Vec<usize> = (0..x.len()).filter(|&i| f[i] != DVec3::ZERO).collect();
        assert!(on_surface.len() > 20);
        let h = 1e-7;
        let mut worst = 0.0f64;
        let scale = on_surface
            .iter()
            .map(|&i| f[i].length())
            .fold(0.0, f64::max);
        for &i in on_surface.iter().step_by(7) {
            for c in 0..3 {
                let mut y = x.clone();
                y[i][c] += h;
                let ep = term.energy(&y);
                y[i][c] -= 2.0 * h;
                let em = term.energy(&y);
                let fd = -(ep - em) / (2.0 * h);
                worst = worst.max((fd - f[i][c]).abs() / scale);
            }
        }
        assert!(
            worst < 1e-6,
            "force vs -dE/dx: worst {worst:e} of the largest force"
        );
    }

    #[test]
    fn follower_pressure_stiffness_is_the_derivative_of_its_forces() {
        for quadratic in [false, true] {
            stiffness_is_the_derivative(quadratic);
        }
    }

    fn stiffness_is_the_derivative(quadratic: bool) {
        let (loads, x) = pressed_surface(quadratic);
        let term = FollowerPressure::new(&loads, 1.0);
        let n = x.len();
        let mut k = Mat::<f64>::zeros(3 * n, 3 * n);
        term.for_each_stiffness_block(&x, &mut |i, j, b| {
            for r in 0..3 {
                for c in 0..3 {
                    k[(3 * i as usize + r, 3 * j as usize + c)] += b.col(c)[r];
                }
            }
        });
        let forces = |y: &[DVec3]| {
            let mut f = vec![DVec3::ZERO; n];
            term.add_forces(y, &mut f);
            f
        };
        let h = 1e-7;
        let mut worst = 0.0f64;
        let mut largest = 0.0f64;
        let mut checked = 0;
        for j in (0..n).step_by(5) {
            for c in 0..3 {
                let mut y = x.clone();
                y[j][c] += h;
                let fp = forces(&y);
                y[j][c] -= 2.0 * h;
                let fm = forces(&y);
                for i in 0..n {
                    for r in 0..3 {
                        let fd = -(fp[i][r] - fm[i][r]) / (2.0 * h);
                        let kk = k[(3 * i + r, 3 * j + c)];
                        worst = worst.max((fd - kk).abs());
                        largest = largest.max(kk.abs());
                    }
                }
                checked += 1;
            }
        }
        assert!(checked > 30 && largest > 0.0);
        assert!(
            worst < 1e-6 * largest,
            "K vs -df/dx: worst {worst:e}, largest entry {largest:e}"
        );
        // On a closed surface the assembled stiffness is symmetric (the Hessian of p V).
        let mut asym = 0.0f64;
        for i in 0..3 * n {
            for j in 0..i {
                asym = asym.max((k[(i, j)] - k[(j, i)]).abs());
            }
        }
        assert!(
            asym < 1e-12 * largest,
            "quadratic {quadratic}: asymmetry {asym:e}"
        );
    }

    #[test]
    fn the_penalty_rises_tenfold_from_twenty_shear_moduli() {
        let g = crate::material::GuccioneParams {
            c_pa: 1e4,
            b_f: 1.0,
            b_t: 1.0,
            b_fs: 1.0,
            bulk_modulus_pa: 1e7,
            mean_dilatation: true,
        };
        let m = MaterialParams::with_guccione(g, 1000.0);
        let stages = penalty_continuation(&m);
        assert_eq!(stages.len(), 3, "{stages:?}");
        for (s, e) in stages.iter().zip([1e5, 1e6, 1e7]) {
            assert!((s / e - 1.0).abs() < 1e-12, "{stages:?}");
        }
        let soft = with_bulk_modulus(&m, 5e4);
        assert_eq!(penalty_continuation(&soft), vec![5e4]);
        assert_eq!(soft.guccione.bulk_modulus_pa, 5e4);
        let stvk = MaterialParams::from_youngs(1e4, 0.49, 1000.0);
        assert_eq!(penalty_continuation(&stvk), vec![stvk.lambda_pa]);
    }
}
