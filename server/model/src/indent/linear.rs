//! The linear systems of the indentation's Newton iterations ([`super::newton`]).
//!
//! The tangent is assembled in 3x3 blocks per pair of nodes that share a cell (a block
//! pattern built once, with the block index of every cell entry precomputed, so an assembly is
//! a scatter without sorting), projected onto the contact constraints of the active nodes
//! ([`System::project`]), and copied into a compressed-column matrix over the free degrees of
//! freedom in the order the block pattern gives (both triangles, symmetric).
//!
//! Solves: preconditioned conjugate gradients ([`System::solve`]) whose preconditioner is a
//! single-precision sparse Cholesky factor of an earlier projected tangent (the ordering and
//! symbolic analysis are made once per pattern: METIS nested dissection,
//! [`crate::linalg::ordering`]). A factor is kept while it makes the iteration converge in fewer
//! steps than the cost of a new one, so most Newton iterations cost back-substitutions
//! (modified Newton's factor with Newton's exact tangent: inexact Newton, Dembo, Eisenstat &
//! Steihaug 1982). Single precision halves the factor's time and memory (measured on a
//! 97 000-equation quadratic block: 6.6 s against 13.0 s); the iteration restores double
//! precision. A tangent that is not positive definite (St. Venant-Kirchhoff under strong
//! compression) is solved directly in double precision: unpivoted `L D L^T` on the same
//! analysis, checked by its residual, else sparse LU.
//!
//! Owns: assembly into the block pattern and the linear solves. Uses: [`crate::linalg::ordering`],
//! [`crate::element`] (cell tangents).

use std::sync::Arc;
use std::time::Instant;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky};
use faer::sparse::linalg::solvers::{Lu, SymbolicLu};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, Mat, Par, Side};
use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::element::FemModel;
use crate::element::tangent::cell_tangent_blocks;
use crate::linalg::ordering::{SparseCholesky, parallelism, symbolic_cholesky};

/// Largest relative residual `|A x - b| / |b|` of a direct `L D L^T` solve that is accepted
/// (else sparse LU solves it).
const LDLT_RESIDUAL: f64 = 1e-8;

/// A constraint of an active contact node on the linear system: the node moves along the unit
/// vector `m` (in its free components) only by a prescribed amount, so its equation along
/// `m` is replaced by `diag * (m . dx) = rhs` ([`System::project`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct NodeConstraint {
    /// The node.
    pub node: u32,
    /// Unit constrained direction (zero in the node's constrained components).
    pub m: DVec3,
    /// Diagonal scale of the replaced equation, N/m.
    pub diag: f64,
}

/// The assembled, projected tangent of one Newton iteration and the solver state kept across
/// iterations (the analysis, the preconditioner's factor, statistics).
pub(super) struct System {
    /// Block row pointers (per node) into `cols` and `blocks`.
    row_ptr: Vec<usize>,
    /// Column node of each block, sorted within a row.
    cols: Vec<u32>,
    /// 3x3 blocks `K_ij` (N/m).
    pub blocks: Vec<DMat3>,
    /// Offsets of each cell's entries in `cell_map`.
    cell_start: Vec<usize>,
    /// Block index of each (cell, a, b) entry, `a * npe + b`.
    cell_map: Vec<u32>,
    /// Equation number of node component `3 i + c`, or `usize::MAX` when constrained.
    pub dof: Vec<usize>,
    /// Number of free equations.
    pub nfree: usize,
    /// Node of each free equation (the ordering's supervariables).
    group: Vec<usize>,
    /// Compressed-column pattern of the free equations (both triangles).
    symbolic: SymbolicSparseColMat<usize>,
    /// Values in `symbolic`'s order.
    pub vals: Vec<f64>,
    /// Cholesky analysis, made at the first factorisation.
    cholesky: Option<Arc<SymbolicCholesky<usize>>>,
    /// The preconditioner's single-precision factor.
    factor: Option<Factor32>,
    /// A direct double-precision solver, made when the tangent is not positive definite.
    direct: Option<SparseCholesky>,
    /// Threads of the factorisations ([`System::set_threads`]).
    threads: usize,
    /// Statistics and the cost model of the refactoring policy.
    pub stats: LinearStats,
}

/// Counters of the linear solves.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LinearStats {
    /// Single-precision factorisations made.
    pub factorizations: usize,
    /// Conjugate-gradient iterations.
    pub iterations: usize,
    /// Direct double-precision solves (indefinite tangents).
    pub direct_solves: usize,
    /// Wall time of the last factorisation, s.
    pub factor_s: f64,
    /// Mean wall time of one conjugate-gradient iteration, s.
    pub iteration_s: f64,
}

/// A single-precision Cholesky factor and its workspace.
struct Factor32 {
    values: Vec<f32>,
    mem: MemBuffer,
    rhs: Mat<f32>,
}

impl System {
    /// The block pattern of `fem`'s cells, the free-equation numbering of its constraints and
    /// the compressed-column pattern.
    pub fn new(fem: &FemModel) -> Result<Self, ModelError> {
        let n = fem.node_count();
        let mut adj: Vec<Vec<u32>> = vec![Vec::new(); n];
        for c in 0..fem.cell_count() {
            let nodes = fem.cell_nodes(c);
            for &a in nodes {
                adj[a as usize].extend_from_slice(nodes);
            }
        }
        let mut row_ptr = Vec::with_capacity(n + 1);
        row_ptr.push(0);
        let mut cols = Vec::new();
        for list in &mut adj {
            list.sort_unstable();
            list.dedup();
            cols.extend_from_slice(list);
            row_ptr.push(cols.len());
            *list = Vec::new();
        }
        let find = |i: u32, j: u32| -> u32 {
            let row = &cols[row_ptr[i as usize]..row_ptr[i as usize + 1]];
            (row_ptr[i as usize]
                + row
                    .binary_search(&j)
                    .expect("a cell pair is in the pattern")) as u32
        };
        let mut cell_start = Vec::with_capacity(fem.cell_count() + 1);
        let mut cell_map = Vec::new();
        for c in 0..fem.cell_count() {
            cell_start.push(cell_map.len());
            let nodes = fem.cell_nodes(c);
            for &a in nodes {
                for &b in nodes {
                    cell_map.push(find(a, b));
                }
            }
        }
        cell_start.push(cell_map.len());
        let (dof, nfree) = crate::statics::free_dofs(fem);
        let mut group = vec![0; nfree];
        for (k, &d) in dof.iter().enumerate() {
            if d != usize::MAX {
                group[d] = k / 3;
            }
        }
        // Column (j, cb) holds rows (i, ca) for the blocks of row j: sorted, since the
        // equations are numbered node by node.
        let mut col_ptr = Vec::with_capacity(nfree + 1);
        col_ptr.push(0);
        let mut row_idx = Vec::new();
        for j in 0..n {
            for cb in 0..3 {
                if dof[3 * j + cb] == usize::MAX {
                    continue;
                }
                for &i in &cols[row_ptr[j]..row_ptr[j + 1]] {
                    for ca in 0..3 {
                        let r = dof[3 * i as usize + ca];
                        if r != usize::MAX {
                            row_idx.push(r);
                        }
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        let nnz = row_idx.len();
        let symbolic = SymbolicSparseColMat::new_checked(nfree, nfree, col_ptr, None, row_idx);
        Ok(Self {
            blocks: vec![DMat3::ZERO; cols.len()],
            row_ptr,
            cols,
            cell_start,
            cell_map,
            dof,
            nfree,
            group,
            symbolic,
            vals: vec![0.0; nnz],
            cholesky: None,
            factor: None,
            direct: None,
            threads: 1,
            stats: LinearStats::default(),
        })
    }

    /// The factorisations (the single-precision preconditioner's and the direct `L D L^T`) on
    /// up to `threads` threads: faer's parallel dense kernels inside the large supernodes
    /// ([`SparseCholesky::with_threads`]). Default 1.
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
        self.factor = None;
    }

    /// Sets every block to the cells' tangent at `x` (N/m).
    pub fn assemble_cells(&mut self, fem: &FemModel, x: &[DVec3]) {
        self.blocks.iter_mut().for_each(|b| *b = DMat3::ZERO);
        let mut tmp = Vec::new();
        for c in 0..fem.cell_count() {
            cell_tangent_blocks(fem, c, x, &mut tmp);
            let map = &self.cell_map[self.cell_start[c]..self.cell_start[c + 1]];
            for (k, &b) in tmp.iter().zip(map) {
                self.blocks[b as usize] += *k;
            }
        }
    }

    /// The nodes sharing a cell with node `i` (itself included), ascending.
    pub fn neighbours(&self, i: u32) -> impl Iterator<Item = u32> + '_ {
        self.cols[self.row_ptr[i as usize]..self.row_ptr[i as usize + 1]]
            .iter()
            .copied()
    }

    /// Index of block `(i, j)`, if the nodes share a cell.
    pub fn block_index(&self, i: u32, j: u32) -> Option<usize> {
        let (s, e) = (self.row_ptr[i as usize], self.row_ptr[i as usize + 1]);
        self.cols[s..e].binary_search(&j).ok().map(|p| s + p)
    }

    /// Adds `k` to block `(i, j)`.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when the nodes share no cell (a term coupling them is
    /// outside the pattern).
    pub fn add_block(&mut self, i: u32, j: u32, k: DMat3) -> Result<(), ModelError> {
        let b = self.block_index(i, j).ok_or_else(|| {
            ModelError::InvalidInput(format!(
                "a contact term couples nodes {i} and {j}, which share no cell"
            ))
        })?;
        self.blocks[b] += k;
        Ok(())
    }

    /// Projects the blocks onto the constraints: `K <- P K P + sum diag m m^T` with `P = I -
    /// m m^T` at each constrained node (identity elsewhere). The result is symmetric positive
    /// definite when `K` is on the constraints' null space, and its solution has `m . dx = 0`
    /// at the constrained nodes for a right-hand side in the range of `P`.
    pub fn project(&mut self, constraints: &[NodeConstraint]) {
        for c in constraints {
            let i = c.node;
            let p = DMat3::IDENTITY - outer(c.m, c.m);
            let (s, e) = (self.row_ptr[i as usize], self.row_ptr[i as usize + 1]);
            for b in s..e {
                let j = self.cols[b];
                self.blocks[b] = p * self.blocks[b];
                if j != i {
                    let t = self.block_index(j, i).expect("the pattern is symmetric");
                    self.blocks[t] *= p;
                } else {
                    self.blocks[b] *= p;
                }
            }
        }
        for c in constraints {
            let d = self.block_index(c.node, c.node).expect("a diagonal block");
            self.blocks[d] += outer(c.m, c.m) * c.diag;
        }
    }

    /// Copies the blocks into the compressed-column values (free components).
    pub fn fill_values(&mut self) {
        let mut k = 0;
        let n = self.row_ptr.len() - 1;
        for j in 0..n {
            for cb in 0..3 {
                if self.dof[3 * j + cb] == usize::MAX {
                    continue;
                }
                for b in self.row_ptr[j]..self.row_ptr[j + 1] {
                    let i = self.cols[b] as usize;
                    // Entry (i ca, j cb) = K_ij[ca][cb] = K_ji[cb][ca] (symmetric tangent).
                    let block = &self.blocks[b];
                    for ca in 0..3 {
                        if self.dof[3 * i + ca] != usize::MAX {
                            self.vals[k] = block.col(ca)[cb];
                            k += 1;
                        }
                    }
                }
            }
        }
        debug_assert_eq!(k, self.vals.len());
    }

    /// `out = A v` with the compressed-column values (free equations).
    pub fn matvec(&self, v: &[f64], out: &mut [f64]) {
        out.iter_mut().for_each(|o| *o = 0.0);
        let (cp, ri) = (self.symbolic.col_ptr(), self.symbolic.row_idx());
        for j in 0..self.nfree {
            let vj = v[j];
            if vj == 0.0 {
                continue;
            }
            for k in cp[j]..cp[j + 1] {
                out[ri[k]] += self.vals[k] * vj;
            }
        }
    }

    /// `|| |A| |v| ||_2` (entrywise absolute values): the size of the terms whose sum is
    /// `A v`, so that `eps` times it bounds the round-off of forces assembled like `A v`.
    pub fn abs_product_norm(&self, v: &[f64]) -> f64 {
        let mut out = vec![0.0; self.nfree];
        let (cp, ri) = (self.symbolic.col_ptr(), self.symbolic.row_idx());
        for j in 0..self.nfree {
            let vj = v[j].abs();
            for k in cp[j]..cp[j + 1] {
                out[ri[k]] += self.vals[k].abs() * vj;
            }
        }
        out.iter().map(|o| o * o).sum::<f64>().sqrt()
    }

    fn analysis(&mut self) -> Result<Arc<SymbolicCholesky<usize>>, ModelError> {
        if self.cholesky.is_none() {
            let s = symbolic_cholesky(self.symbolic.as_ref(), Side::Lower, &self.group)?;
            self.cholesky = Some(Arc::new(s));
        }
        Ok(self.cholesky.clone().expect("made above"))
    }

    /// Factors the current values in single precision as the preconditioner; `false` when
    /// they are not positive definite.
    fn refactor(&mut self) -> Result<bool, ModelError> {
        let symbolic = self.analysis()?;
        let t = Instant::now();
        let par = parallelism(self.threads);
        let (mut values, mut mem, rhs) = match self.factor.take() {
            Some(f) => (f.values, f.mem, f.rhs),
            None => (
                vec![0.0f32; symbolic.len_val()],
                MemBuffer::new(
                    symbolic
                        .factorize_numeric_llt_scratch::<f32>(par, Default::default())
                        .or(symbolic.solve_in_place_scratch::<f32>(1, Par::Seq)),
                ),
                Mat::<f32>::zeros(self.nfree, 1),
            ),
        };
        let v32: Vec<f32> = self.vals.iter().map(|&v| v as f32).collect();
        let a32 = SparseColMatRef::new(self.symbolic.as_ref(), &v32);
        let ok = symbolic
            .factorize_numeric_llt::<f32>(
                &mut values,
                a32,
                Side::Lower,
                Default::default(),
                par,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .is_ok();
        self.stats.factor_s = t.elapsed().as_secs_f64();
        self.stats.factorizations += 1;
        if ok {
            self.factor = Some(Factor32 { values, mem, rhs });
        }
        Ok(ok)
    }

    /// Applies the preconditioner: `z = M^-1 r`.
    fn precondition(&mut self, r: &[f64], z: &mut [f64]) {
        let symbolic = self.cholesky.clone().expect("a factor implies an analysis");
        let f = self.factor.as_mut().expect("a factor");
        for (k, &v) in r.iter().enumerate() {
            f.rhs[(k, 0)] = v as f32;
        }
        LltRef::<usize, f32>::new(&symbolic, &f.values).solve_in_place_with_conj(
            Conj::No,
            f.rhs.as_mut(),
            Par::Seq,
            MemStack::new(&mut f.mem),
        );
        for (k, zk) in z.iter_mut().enumerate() {
            *zk = f64::from(f.rhs[(k, 0)]);
        }
    }

    /// Drops the preconditioner (the next solve factors the current tangent).
    pub fn forget_factor(&mut self) {
        self.factor = None;
    }

    /// Solves `A x = b` (free equations, the current values) to the relative residual
    /// `rel_tol`: conjugate gradients preconditioned by the kept factor, refactored when the
    /// iteration would cost more than a factorisation or when there is none; a tangent that
    /// is not positive definite directly in double precision.
    ///
    /// # Errors
    /// [`ModelError::NoConvergence`] when every factorisation fails.
    pub fn solve(&mut self, b: &[f64], x: &mut [f64], rel_tol: f64) -> Result<(), ModelError> {
        x.iter_mut().for_each(|v| *v = 0.0);
        let bnorm = norm(b);
        if bnorm == 0.0 {
            return Ok(());
        }
        let mut fresh = false;
        if self.factor.is_none() {
            if !self.refactor()? {
                return self.solve_direct(b, x);
            }
            fresh = true;
        }
        loop {
            // A kept factor is worth keeping while its iterations cost less than a new one
            // (at least 10 iterations; a fresh factor gets as many as it needs).
            let ratio = self.stats.factor_s / self.stats.iteration_s.max(1e-6);
            let budget = if fresh {
                2000
            } else {
                (ratio as usize).clamp(10, 400)
            };
            let before = self.stats.iterations;
            match self.pcg(b, x, bnorm * rel_tol, budget) {
                Pcg::Converged => {
                    // A factor that needed more than half a factorisation's worth of
                    // iterations is replaced before the next solve.
                    if !fresh && (self.stats.iterations - before) as f64 > 0.5 * ratio {
                        self.factor = None;
                    }
                    return Ok(());
                }
                Pcg::Indefinite => return self.solve_direct(b, x),
                Pcg::Budget if !fresh => {
                    if !self.refactor()? {
                        return self.solve_direct(b, x);
                    }
                    fresh = true;
                }
                Pcg::Budget => {
                    return Err(ModelError::NoConvergence(format!(
                        "conjugate gradients preconditioned by the current tangent's factor did \
                         not reach {rel_tol:.1e} in {budget} iterations"
                    )));
                }
            }
        }
    }

    /// Preconditioned conjugate gradients from `x` (kept on return) to `|b - A x| <= tol`.
    fn pcg(&mut self, b: &[f64], x: &mut [f64], tol: f64, budget: usize) -> Pcg {
        let n = self.nfree;
        let t = Instant::now();
        let mut r = vec![0.0; n];
        self.matvec(x, &mut r);
        for (ri, bi) in r.iter_mut().zip(b) {
            *ri = bi - *ri;
        }
        let (mut z, mut ap) = (vec![0.0; n], vec![0.0; n]);
        self.precondition(&r, &mut z);
        let mut p = z.clone();
        let mut rz = dot(&r, &z);
        let mut outcome = Pcg::Budget;
        let mut its = 0;
        while its < budget {
            if norm(&r) <= tol {
                outcome = Pcg::Converged;
                break;
            }
            its += 1;
            self.matvec(&p, &mut ap);
            let pap = dot(&p, &ap);
            if !(pap > 0.0) {
                outcome = Pcg::Indefinite;
                break;
            }
            let alpha = rz / pap;
            for k in 0..n {
                x[k] += alpha * p[k];
                r[k] -= alpha * ap[k];
            }
            self.precondition(&r, &mut z);
            let rz_new = dot(&r, &z);
            let beta = rz_new / rz;
            rz = rz_new;
            for k in 0..n {
                p[k] = z[k] + beta * p[k];
            }
        }
        if outcome == Pcg::Budget && norm(&r) <= tol {
            outcome = Pcg::Converged;
        }
        if its > 0 {
            let per = t.elapsed().as_secs_f64() / its as f64;
            let s = &mut self.stats;
            s.iteration_s = if s.iterations == 0 {
                per
            } else {
                0.8 * s.iteration_s + 0.2 * per
            };
            s.iterations += its;
        }
        outcome
    }

    /// Direct double-precision solve of an indefinite tangent: `L D L^T` without pivoting on
    /// the Cholesky analysis, kept when its residual is below [`LDLT_RESIDUAL`], else LU.
    fn solve_direct(&mut self, b: &[f64], x: &mut [f64]) -> Result<(), ModelError> {
        self.stats.direct_solves += 1;
        self.factor = None;
        let n = self.nfree;
        let rhs = Mat::<f64>::from_fn(n, 1, |i, _| b[i]);
        if self.direct.is_none() {
            self.direct = Some(
                SparseCholesky::analyse(self.symbolic.as_ref(), Side::Lower, &self.group)?
                    .with_threads(self.threads),
            );
        }
        let direct = self.direct.as_mut().expect("made above");
        let a = SparseColMatRef::new(self.symbolic.as_ref(), &self.vals);
        if direct.factor_ldlt(a, Side::Lower).is_ok() {
            let mut sol = rhs.clone();
            direct.solve_in_place(sol.as_mut());
            let res = (a * sol.as_ref() - rhs.as_ref()).norm_l2();
            if res <= LDLT_RESIDUAL * rhs.norm_l2() {
                for (k, xk) in x.iter_mut().enumerate() {
                    *xk = sol[(k, 0)];
                }
                return Ok(());
            }
        }
        let factorising = |e: &dyn std::fmt::Debug| {
            ModelError::NoConvergence(format!("factorising the tangent: {e:?}"))
        };
        let lu = SymbolicLu::try_new(self.symbolic.as_ref()).map_err(|e| factorising(&e))?;
        let mut sol = rhs;
        Lu::try_new_with_symbolic(lu, a)
            .map_err(|e| factorising(&e))?
            .solve_in_place(sol.as_mut());
        for (k, xk) in x.iter_mut().enumerate() {
            *xk = sol[(k, 0)];
        }
        Ok(())
    }
}

/// How a conjugate-gradient run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pcg {
    Converged,
    /// The iteration budget ran out.
    Budget,
    /// A direction of non-positive curvature: the matrix is not positive definite.
    Indefinite,
}

/// `a b^T`.
pub(super) fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::MaterialParams;

    /// A small quadratic block, its base clamped and one face on rollers, deformed.
    fn fixture() -> (FemModel, Vec<DVec3>) {
        let mesh = crate::mesh::generate::box_mesh(DVec3::splat(1e-2), [3, 3, 3]).to_quadratic();
        let mut fem = FemModel::new(&mesh, MaterialParams::from_youngs(1e4, 0.3, 1000.0)).unwrap();
        for (i, p) in mesh.nodes.iter().enumerate() {
            if p.z == 0.0 {
                fem.set_constraint(i, crate::element::CLAMPED);
            } else if p.y == 0.0 {
                fem.set_constraint(i, 0b010);
            }
        }
        let x = mesh
            .nodes
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let k = i as f64;
                *p + DVec3::new((k * 0.7).sin(), (k * 1.3).cos(), (k * 0.4).sin()) * 2e-4 * p.z
                    / 1e-2
            })
            .collect();
        (fem, x)
    }

    /// The dense matrix of the compressed-column values.
    fn dense(sys: &System) -> Mat<f64> {
        let n = sys.nfree;
        let mut a = Mat::<f64>::zeros(n, n);
        let (cp, ri) = (sys.symbolic.col_ptr(), sys.symbolic.row_idx());
        for j in 0..n {
            for k in cp[j]..cp[j + 1] {
                a[(ri[k], j)] += sys.vals[k];
            }
        }
        a
    }

    /// The projected system is symmetric, its solution moves the constrained nodes only
    /// tangentially and satisfies `P K z = b`; conjugate gradients with the single-precision
    /// factor of an older matrix reach the requested residual.
    #[test]
    fn projected_solves_respect_the_constraints() {
        let (fem, x) = fixture();
        let mut sys = System::new(&fem).unwrap();
        sys.assemble_cells(&fem, &x);
        sys.fill_values();
        let k = dense(&sys);
        // Top nodes constrained along tilted directions (in their free components).
        let mut constraints = Vec::new();
        for (i, p) in fem.rest().iter().enumerate() {
            if p.z == 1e-2 && fem.constraints()[i] == 0 && constraints.len() < 6 {
                let m = DVec3::new(0.3, -0.2, 1.0).normalize();
                constraints.push(NodeConstraint {
                    node: i as u32,
                    m,
                    diag: 50.0,
                });
            }
        }
        let roller = fem
            .rest()
            .iter()
            .enumerate()
            .position(|(i, p)| p.z == 1e-2 && fem.constraints()[i] == 0b010)
            .unwrap();
        constraints.push(NodeConstraint {
            node: roller as u32,
            m: DVec3::new(0.6, 0.0, 0.8),
            diag: 50.0,
        });
        // Factor the unprojected matrix first: the projected solve then runs on an older
        // factor.
        let n = sys.nfree;
        let b0: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
        let mut z = vec![0.0; n];
        sys.solve(&b0, &mut z, 1e-10).unwrap();
        assert_eq!(sys.stats.factorizations, 1);
        sys.project(&constraints);
        sys.fill_values();
        let a = dense(&sys);
        let asym = (&a - a.transpose()).norm_max();
        assert!(asym < 1e-12 * a.norm_max(), "asymmetry {asym:e}");
        // b in the range of P.
        let mut b = b0.clone();
        for c in &constraints {
            let i = c.node as usize;
            let d: Vec<usize> = (0..3).map(|cc| sys.dof[3 * i + cc]).collect();
            let mut v = DVec3::ZERO;
            for cc in 0..3 {
                if d[cc] != usize::MAX {
                    v[cc] = b[d[cc]];
                }
            }
            v -= c.m * c.m.dot(v);
            for cc in 0..3 {
                if d[cc] != usize::MAX {
                    b[d[cc]] = v[cc];
                }
            }
        }
        sys.solve(&b, &mut z, 1e-10).unwrap();
        let res =
            &a * Mat::<f64>::from_fn(n, 1, |i, _| z[i]) - Mat::<f64>::from_fn(n, 1, |i, _| b[i]);
        assert!(
            res.norm_l2() <= 1e-10 * norm(&b) * 1.0001,
            "{:e}",
            res.norm_l2()
        );
        // m . z = 0 at the constrained nodes, and P K z = b.
        let kz = &k * Mat::<f64>::from_fn(n, 1, |i, _| z[i]);
        let node_vec = |v: &dyn Fn(usize) -> f64, i: usize| {
            let mut out = DVec3::ZERO;
            for cc in 0..3 {
                let d = sys.dof[3 * i + cc];
                if d != usize::MAX {
                    out[cc] = v(d);
                }
            }
            out
        };
        for c in &constraints {
            let i = c.node as usize;
            let zi = node_vec(&|d| z[d], i);
            assert!(c.m.dot(zi).abs() < 1e-9 * norm(&z), "m . z at node {i}");
            let kzi = node_vec(&|d| kz[(d, 0)], i);
            let bi = node_vec(&|d| b[d], i);
            let p = kzi - c.m * c.m.dot(kzi);
            assert!((p - bi).length() < 1e-8 * norm(&b), "P K z at node {i}");
        }
        assert!(sys.stats.iterations > 1, "the old factor needs iterations");
    }
}
