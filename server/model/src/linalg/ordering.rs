//! Fill-reducing orderings for the sparse Cholesky factorisations of the static solver and of
//! contact-local condensation: nested dissection by METIS (`METIS_NodeND`, Karypis & Kumar
//! 1998, vendored C library through `metis-sys`) on the mesh's node graph.
//!
//! faer's default ordering is approximate minimum degree (AMD). On 3-D meshes nested
//! dissection leaves far less fill: on a quadratic LV mesh refined under the probe (33 000
//! equations, 2.5 million entries) the numeric Cholesky took 2.0 s with AMD
//! (docs/decisions.md, "Nested dissection for the sparse Cholesky"). The ordering works on
//! supervariables (the free components of one node form one vertex weighted by their count),
//! so METIS sees a graph nine times smaller than the matrix.
//!
//! Owns: the ordering. May use: nothing of the crate but its error type.

use std::sync::{Arc, Mutex};

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    CholeskySymbolicParams, LdltRef, LltRef, SymbolicCholesky, SymmetricOrdering,
    factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side};

use crate::ModelError;

/// Serialises the calls into METIS. METIS draws its random numbers from the C library's
/// `rand` after seeding it with `srand` at each call (GKlib `random.c`, libmetis `InitRandom`):
/// one stream for the whole process, so two orderings made at once on two threads interleave
/// it and each gets another ordering than it would alone (another factor, forces that differ
/// in the last digits). Held only for `METIS_NodeND` (set-up and region preparation, never the
/// servo tick); `tests/ordering_threads.rs`.
static METIS_LOCK: Mutex<()> = Mutex::new(());

/// Graphs with fewer vertices than this are ordered by AMD (METIS gains nothing there).
pub const MIN_VERTICES: usize = 64;

/// A fill-reducing permutation of `n` equations: `forward[k]` is the original index of the
/// equation placed `k`-th (METIS's `perm`, faer's forward permutation), `inverse` its inverse.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ordering {
    /// New position to original index.
    pub forward: Vec<usize>,
    /// Original index to new position.
    pub inverse: Vec<usize>,
}

/// Nested-dissection ordering of the symmetric sparsity pattern of an `n x n` matrix given in
/// compressed columns (`col_ptr`, length `n + 1`; `row_idx`, both triangles or either one),
/// with the equations grouped into supervariables: `group[k]` (length `n`) names the node of
/// equation `k`, and the equations of one group are ordered together, in their original order.
/// Groups need not be consecutive or dense; they are renumbered.
///
/// Returns `Ok(None)` for a graph of fewer than [`MIN_VERTICES`] groups (use AMD).
///
/// # Errors
/// [`ModelError::InvalidInput`] when the pattern is malformed (a row index or group out of
/// range, `col_ptr` not increasing) or larger than METIS's 32-bit indices, or when METIS
/// reports an error.
pub fn nested_dissection(
    n: usize,
    col_ptr: &[usize],
    row_idx: &[usize],
    group: &[usize],
) -> Result<Option<Ordering>, ModelError> {
    if col_ptr.len() != n + 1 || group.len() != n {
        return Err(bad(format!(
            "{} column pointers and {} groups for {n} equations",
            col_ptr.len(),
            group.len()
        )));
    }
    if col_ptr.windows(2).any(|w| w[0] > w[1]) || col_ptr[n] > row_idx.len() {
        return Err(bad("column pointers are not increasing".into()));
    }
    let (dense, ng) = dense_groups(group);
    if ng < MIN_VERTICES {
        return Ok(None);
    }
    let members = Members::of(group, &dense, ng);
    let (transpose_ptr, transpose) = transpose_pattern(n, col_ptr, row_idx)?;
    let pattern = Pattern {
        col_ptr,
        row_idx,
        transpose_ptr: &transpose_ptr,
        transpose: &transpose,
    };
    let graph = group_graph(&pattern, group, &dense, &members)?;
    let perm = metis_node_nd(graph, &members, n)?;
    let mut forward = Vec::with_capacity(n);
    for &d in &perm {
        let d = usize::try_from(d)
            .ok()
            .filter(|&d| d < ng)
            .ok_or_else(|| bad(format!("METIS returned vertex {d} of {ng}")))?;
        forward.extend_from_slice(members.of_group(d));
    }
    let mut inverse = vec![usize::MAX; n];
    for (k, &o) in forward.iter().enumerate() {
        inverse[o] = k;
    }
    if forward.len() != n || inverse.contains(&usize::MAX) {
        return Err(bad("METIS's permutation is not one".into()));
    }
    Ok(Some(Ordering { forward, inverse }))
}

/// [`nested_dissection`]'s error for `what`.
fn bad(what: String) -> ModelError {
    ModelError::InvalidInput(format!("nested dissection: {what}"))
}

/// [`nested_dissection`]'s error for `n` equations beyond METIS's indices.
fn too_large(n: usize) -> ModelError {
    bad(format!("{n} equations exceed METIS's 32-bit indices"))
}

/// Dense group numbers in the order of first appearance: per group name its number (or
/// `usize::MAX` for a name no equation has), and the number of groups.
fn dense_groups(group: &[usize]) -> (Vec<usize>, usize) {
    let group_range = group.iter().max().map_or(0, |&g| g + 1);
    let mut dense = vec![usize::MAX; group_range];
    let mut ng = 0;
    for &g in group {
        if dense[g] == usize::MAX {
            dense[g] = ng;
            ng += 1;
        }
    }
    (dense, ng)
}

/// The equations of each dense group, in original order (compressed rows).
struct Members {
    /// Start of each group in `list` (length groups + 1).
    ptr: Vec<usize>,
    list: Vec<usize>,
}

impl Members {
    /// The members of the `ng` dense groups `dense[group[k]]` of the equations `k`.
    fn of(group: &[usize], dense: &[usize], ng: usize) -> Self {
        let mut ptr = vec![0usize; ng + 1];
        for &g in group {
            ptr[dense[g] + 1] += 1;
        }
        for k in 0..ng {
            ptr[k + 1] += ptr[k];
        }
        let mut list = vec![0usize; group.len()];
        let mut fill = ptr.clone();
        for (k, &g) in group.iter().enumerate() {
            let d = dense[g];
            list[fill[d]] = k;
            fill[d] += 1;
        }
        Self { ptr, list }
    }

    /// The equations of dense group `d`.
    fn of_group(&self, d: usize) -> &[usize] {
        &self.list[self.ptr[d]..self.ptr[d + 1]]
    }

    /// Number of groups.
    fn groups(&self) -> usize {
        self.ptr.len() - 1
    }
}

/// The transpose of the pattern's first `col_ptr[n]` entries (compressed columns: pointers,
/// row indices), so that a pattern given by one triangle is seen whole.
///
/// # Errors
/// [`ModelError::InvalidInput`] for a row index out of range.
fn transpose_pattern(
    n: usize,
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Result<(Vec<usize>, Vec<usize>), ModelError> {
    let mut transpose_ptr = vec![0usize; n + 1];
    for &r in &row_idx[..col_ptr[n]] {
        if r >= n {
            return Err(bad(format!("row index {r} out of range for {n} equations")));
        }
        transpose_ptr[r + 1] += 1;
    }
    for k in 0..n {
        transpose_ptr[k + 1] += transpose_ptr[k];
    }
    let mut transpose = vec![0usize; col_ptr[n]];
    let mut cursor = transpose_ptr.clone();
    for c in 0..n {
        for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
            transpose[cursor[r]] = c;
            cursor[r] += 1;
        }
    }
    Ok((transpose_ptr, transpose))
}

/// A sparsity pattern in compressed columns with its transpose.
struct Pattern<'a> {
    col_ptr: &'a [usize],
    row_idx: &'a [usize],
    transpose_ptr: &'a [usize],
    transpose: &'a [usize],
}

/// A graph as METIS reads it: adjacency in compressed rows, 32-bit.
struct Graph {
    xadj: Vec<i32>,
    adjncy: Vec<i32>,
}

/// The group adjacency (symmetric, no self loops): the union over each group's columns of
/// `pattern` and its transpose.
///
/// # Errors
/// [`ModelError::InvalidInput`] beyond METIS's 32-bit indices.
fn group_graph(
    pattern: &Pattern<'_>,
    group: &[usize],
    dense: &[usize],
    members: &Members,
) -> Result<Graph, ModelError> {
    let (n, ng) = (group.len(), members.groups());
    let mut xadj: Vec<i32> = Vec::with_capacity(ng + 1);
    let mut adjncy: Vec<i32> = Vec::new();
    let mut seen = vec![usize::MAX; ng];
    xadj.push(0);
    for d in 0..ng {
        seen[d] = d;
        for &k in members.of_group(d) {
            let neighbours = pattern.row_idx[pattern.col_ptr[k]..pattern.col_ptr[k + 1]]
                .iter()
                .chain(&pattern.transpose[pattern.transpose_ptr[k]..pattern.transpose_ptr[k + 1]]);
            for &r in neighbours {
                let e = dense[group[r]];
                if seen[e] != d {
                    seen[e] = d;
                    adjncy.push(i32::try_from(e).map_err(|_| too_large(n))?);
                }
            }
        }
        xadj.push(i32::try_from(adjncy.len()).map_err(|_| too_large(n))?);
    }
    Ok(Graph { xadj, adjncy })
}

/// `METIS_NodeND` on `graph`, each vertex weighted by its group's size: the permutation of
/// the groups (METIS's `perm`; `n` equations, for the error message).
///
/// # Errors
/// [`ModelError::InvalidInput`] beyond METIS's 32-bit indices or when METIS reports an error.
fn metis_node_nd(mut graph: Graph, members: &Members, n: usize) -> Result<Vec<i32>, ModelError> {
    let ng = members.groups();
    let mut vwgt: Vec<i32> = (0..ng).map(|d| members.of_group(d).len() as i32).collect();
    let mut nvtxs = i32::try_from(ng).map_err(|_| too_large(n))?;
    let mut perm = vec![0i32; ng];
    let mut iperm = vec![0i32; ng];
    let mut options = [-1i32; metis_sys::METIS_NOPTIONS as usize];
    let _one_at_a_time = METIS_LOCK
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    // SAFETY: every array has the length METIS_NodeND reads or writes: `xadj` nvtxs + 1,
    // `adjncy` xadj[nvtxs] (a symmetric graph without self loops, built by `group_graph`),
    // `vwgt`, `perm` and `iperm` nvtxs, `options` METIS_NOPTIONS (set to defaults by -1,
    // which METIS_SetDefaultOptions also writes). The pointers are live and unaliased for
    // the call.
    let status = unsafe {
        metis_sys::METIS_NodeND(
            &mut nvtxs,
            graph.xadj.as_mut_ptr(),
            graph.adjncy.as_mut_ptr(),
            vwgt.as_mut_ptr(),
            options.as_mut_ptr(),
            perm.as_mut_ptr(),
            iperm.as_mut_ptr(),
        )
    };
    if status != metis_sys::rstatus_et_METIS_OK {
        return Err(bad(format!("METIS_NodeND returned status {status}")));
    }
    Ok(perm)
}

/// Bytes of `symbolic`'s arrays, about (faer keeps them private): the permutation, and per
/// supernode its bounds and row pattern (with faer's row-major copy of the pattern), or the
/// simplicial pattern.
pub fn symbolic_heap_bytes(symbolic: &SymbolicCholesky<usize>) -> usize {
    use faer::sparse::linalg::cholesky::SymbolicCholeskyRaw;
    let words = match symbolic.raw() {
        SymbolicCholeskyRaw::Supernodal(s) => 4 * (s.n_supernodes() + 1) + 2 * s.row_idx().len(),
        SymbolicCholeskyRaw::Simplicial(s) => s.col_ptr().len() + s.row_idx().len(),
    };
    let perm = symbolic.perm().map_or(0, |p| 2 * p.len());
    std::mem::size_of::<usize>() * (words + perm + symbolic.nrows())
}

/// The symbolic Cholesky factorisation of a symmetric pattern (`side` the triangle given, or
/// both) under the [`nested_dissection`] ordering of its supervariables `group` (length
/// `pattern.nrows()`), or AMD for a graph too small for it.
///
/// # Errors
/// As [`nested_dissection`]; [`ModelError::InvalidInput`] when faer's analysis fails.
pub fn symbolic_cholesky(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    side: Side,
    group: &[usize],
) -> Result<SymbolicCholesky<usize>, ModelError> {
    let n = pattern.nrows();
    let ordering = nested_dissection(n, pattern.col_ptr(), pattern.row_idx(), group)?;
    match &ordering {
        Some(o) => analyse(
            pattern,
            side,
            SymmetricOrdering::Custom(PermRef::new_checked(&o.forward, &o.inverse, n)),
        ),
        None => analyse(pattern, side, SymmetricOrdering::Amd),
    }
}

/// faer's symbolic analysis of `pattern` under `ordering`.
fn analyse(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    side: Side,
    ordering: SymmetricOrdering<'_, usize>,
) -> Result<SymbolicCholesky<usize>, ModelError> {
    factorize_symbolic_cholesky(pattern, side, ordering, CholeskySymbolicParams::default())
        .map_err(|e| ModelError::InvalidInput(format!("symbolic Cholesky factorisation: {e:?}")))
}

/// The symbolic Cholesky factorisation of a symmetric pattern (`side` the triangle given, or
/// both) under the fill-reducing permutation `forward` (`forward[k]` the original index of
/// the equation placed `k`-th), without ordering it again: the analysis
/// [`symbolic_cholesky`] made when `forward` is its permutation (read back from a region
/// image, where METIS would take a quarter of the read).
///
/// # Errors
/// [`ModelError::InvalidInput`] when `forward` is not a permutation of the pattern's
/// `nrows()` equations, or when faer's analysis fails.
pub fn symbolic_cholesky_in_order(
    pattern: SymbolicSparseColMatRef<'_, usize>,
    side: Side,
    forward: &[usize],
) -> Result<SymbolicCholesky<usize>, ModelError> {
    let n = pattern.nrows();
    let no_ordering = || {
        bad(format!(
            "{} entries are no ordering of {n} equations",
            forward.len()
        ))
    };
    if forward.len() != n {
        return Err(no_ordering());
    }
    let mut inverse = vec![usize::MAX; n];
    for (k, &o) in forward.iter().enumerate() {
        match inverse.get_mut(o) {
            Some(slot) if *slot == usize::MAX => *slot = k,
            _ => return Err(no_ordering()),
        }
    }
    let ordering = SymmetricOrdering::Custom(PermRef::new_checked(forward, &inverse, n));
    analyse(pattern, side, ordering)
}

/// faer's parallelism for a factorisation on `threads` threads: sequential for one, else its
/// rayon mode (dense kernels of the large supernodes on rayon's global pool).
pub(crate) fn parallelism(threads: usize) -> Par {
    if threads > 1 {
        Par::rayon(threads)
    } else {
        Par::Seq
    }
}

/// A sparse symmetric factorisation under the [`symbolic_cholesky`] ordering (double
/// precision): the analysis is made once for a pattern, then refactored for any values on it,
/// as `L L^T` ([`SparseCholesky::factor_llt`], positive definite) or as the unpivoted
/// `L D L^T` ([`SparseCholesky::factor_ldlt`], some indefinite matrices), and solved with the
/// last factorisation.
#[derive(Debug, Clone)]
pub struct SparseCholesky {
    symbolic: Arc<SymbolicCholesky<usize>>,
    values: Vec<f64>,
    /// Which factorisation `values` holds: `None` before the first, `Some(true)` for `L D L^T`.
    ldlt: Option<bool>,
    /// Threads of the allocating factorisations ([`SparseCholesky::with_threads`]).
    threads: usize,
}

impl SparseCholesky {
    /// The analysis of a symmetric pattern (`side` the triangle given, or both) with equation
    /// groups `group` (see [`nested_dissection`]); no values yet.
    ///
    /// # Errors
    /// As [`symbolic_cholesky`].
    pub fn analyse(
        pattern: SymbolicSparseColMatRef<'_, usize>,
        side: Side,
        group: &[usize],
    ) -> Result<Self, ModelError> {
        let symbolic = symbolic_cholesky(pattern, side, group)?;
        Ok(Self {
            values: vec![0.0; symbolic.len_val()],
            symbolic: Arc::new(symbolic),
            ldlt: None,
            threads: 1,
        })
    }

    /// The allocating factorisations ([`SparseCholesky::factor_llt`],
    /// [`SparseCholesky::factor_ldlt`]; set-up and region preparation, never the tick) on up
    /// to `threads` threads: faer's parallel dense kernels inside the large supernodes, on
    /// rayon's global pool (normal priority, started at the first such call). `L L^T` gives the
    /// same factor bit for bit whatever the count (each entry's sum keeps its order; test
    /// `parallel_factorisations_match_the_sequential_one`); `L D L^T` agrees to round-off.
    /// [`SparseCholesky::factor_llt_in`], the allocation-free one, stays on the caller.
    #[must_use]
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.threads = threads.max(1);
        self
    }

    /// Analyses and factors `a` as `L L^T` in one call, on up to `threads` threads
    /// ([`SparseCholesky::with_threads`]).
    ///
    /// # Errors
    /// As [`SparseCholesky::analyse`] and [`SparseCholesky::factor_llt`].
    pub fn factor(
        a: SparseColMatRef<'_, usize, f64>,
        side: Side,
        group: &[usize],
        threads: usize,
    ) -> Result<Self, ModelError> {
        let mut c = Self::analyse(a.symbolic(), side, group)?.with_threads(threads);
        c.factor_llt(a, side)?;
        Ok(c)
    }

    /// Factors `a` (the analysed pattern; the `side` triangle is read) as `L L^T`, on the
    /// threads of [`SparseCholesky::with_threads`].
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] naming faer's error when `a` is not positive definite
    /// (the previous factorisation is then lost).
    pub fn factor_llt(
        &mut self,
        a: SparseColMatRef<'_, usize, f64>,
        side: Side,
    ) -> Result<(), ModelError> {
        let par = parallelism(self.threads);
        let mut mem = MemBuffer::new(
            self.symbolic
                .factorize_numeric_llt_scratch::<f64>(par, Default::default()),
        );
        self.factor_llt_with(a, side, &mut mem, par)
    }

    /// Workspace for [`SparseCholesky::factor_llt_in`].
    pub fn factor_workspace(&self) -> MemBuffer {
        MemBuffer::new(
            self.symbolic
                .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default()),
        )
    }

    /// [`SparseCholesky::factor_llt`] in the workspace `mem` (from
    /// [`SparseCholesky::factor_workspace`]): allocates nothing, for refactoring in the tick.
    ///
    /// # Errors
    /// As [`SparseCholesky::factor_llt`].
    pub fn factor_llt_in(
        &mut self,
        a: SparseColMatRef<'_, usize, f64>,
        side: Side,
        mem: &mut MemBuffer,
    ) -> Result<(), ModelError> {
        self.factor_llt_with(a, side, mem, Par::Seq)
    }

    /// [`SparseCholesky::factor_llt_in`] with faer's parallelism `par` (`mem` sized for it).
    fn factor_llt_with(
        &mut self,
        a: SparseColMatRef<'_, usize, f64>,
        side: Side,
        mem: &mut MemBuffer,
        par: Par,
    ) -> Result<(), ModelError> {
        self.ldlt = None;
        self.symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.values,
                a,
                side,
                Default::default(),
                par,
                MemStack::new(mem),
                Default::default(),
            )
            .map_err(|e| {
                ModelError::InvalidInput(format!("the matrix is not positive definite: {e:?}"))
            })?;
        self.ldlt = Some(false);
        Ok(())
    }

    /// Factors `a` as `L D L^T` without pivoting (symmetric indefinite matrices whose
    /// leading minors do not vanish in this ordering), on the threads of
    /// [`SparseCholesky::with_threads`]. Check the solution's residual: without pivoting a
    /// small pivot may make it inaccurate.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] naming faer's error on a zero pivot.
    pub fn factor_ldlt(
        &mut self,
        a: SparseColMatRef<'_, usize, f64>,
        side: Side,
    ) -> Result<(), ModelError> {
        let par = parallelism(self.threads);
        let mut mem = MemBuffer::new(
            self.symbolic
                .factorize_numeric_ldlt_scratch::<f64>(par, Default::default()),
        );
        self.ldlt = None;
        self.symbolic
            .factorize_numeric_ldlt::<f64>(
                &mut self.values,
                a,
                side,
                Default::default(),
                par,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .map_err(|e| ModelError::InvalidInput(format!("L D L^T factorisation: {e:?}")))?;
        self.ldlt = Some(true);
        Ok(())
    }

    /// Solves `A X = B` in place of `rhs` (`n x k`) with the last factorisation (allocates
    /// the solve's workspace).
    ///
    /// # Panics
    /// Before a successful factorisation.
    pub fn solve_in_place(&self, rhs: MatMut<'_, f64>) {
        let mut mem = self.solve_workspace(rhs.ncols());
        self.solve_in_place_with(rhs, &mut mem);
    }

    /// Workspace for [`SparseCholesky::solve_in_place_with`] with `columns` right-hand sides.
    pub fn solve_workspace(&self, columns: usize) -> MemBuffer {
        MemBuffer::new(
            self.symbolic
                .solve_in_place_scratch::<f64>(columns, Par::Seq),
        )
    }

    /// [`SparseCholesky::solve_in_place`] in the workspace `mem` (from
    /// [`SparseCholesky::solve_workspace`] with at least `rhs.ncols()` columns): allocates
    /// nothing, for the servo tick.
    ///
    /// # Panics
    /// Before a successful factorisation.
    pub fn solve_in_place_with(&self, rhs: MatMut<'_, f64>, mem: &mut MemBuffer) {
        let stack = MemStack::new(mem);
        match self.ldlt {
            Some(false) => LltRef::<usize, f64>::new(&self.symbolic, &self.values)
                .solve_in_place_with_conj(Conj::No, rhs, Par::Seq, stack),
            Some(true) => LdltRef::<usize, f64>::new(&self.symbolic, &self.values)
                .solve_in_place_with_conj(Conj::No, rhs, Par::Seq, stack),
            None => panic!("SparseCholesky::solve_in_place before a successful factorisation"),
        }
    }

    /// Entries of `L`.
    pub fn factor_entries(&self) -> usize {
        self.values.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 5-point Laplacian pattern of an `m x m` grid with `c` equations per node (both
    /// triangles, diagonal included).
    fn grid(m: usize, c: usize) -> (usize, Vec<usize>, Vec<usize>, Vec<usize>) {
        let n = m * m * c;
        let mut col_ptr = vec![0];
        let mut row_idx = Vec::new();
        for node in 0..m * m {
            let (i, j) = (node / m, node % m);
            let mut nb = vec![node];
            if i > 0 {
                nb.push(node - m);
            }
            if i + 1 < m {
                nb.push(node + m);
            }
            if j > 0 {
                nb.push(node - 1);
            }
            if j + 1 < m {
                nb.push(node + 1);
            }
            nb.sort_unstable();
            for _ in 0..c {
                for &b in &nb {
                    row_idx.extend((0..c).map(|k| b * c + k));
                }
                col_ptr.push(row_idx.len());
            }
        }
        let group = (0..n).map(|k| k / c).collect();
        (n, col_ptr, row_idx, group)
    }

    /// Nonzeros of the Cholesky factor of a pattern permuted by `forward`, by the elimination
    /// game (dense boolean, small sizes only).
    fn fill(n: usize, col_ptr: &[usize], row_idx: &[usize], forward: &[usize]) -> usize {
        let inverse: Vec<usize> = {
            let mut v = vec![0; n];
            for (k, &o) in forward.iter().enumerate() {
                v[o] = k;
            }
            v
        };
        let mut a = vec![vec![false; n]; n];
        for c in 0..n {
            for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
                a[inverse[r]][inverse[c]] = true;
                a[inverse[c]][inverse[r]] = true;
            }
        }
        let mut count = 0;
        for k in 0..n {
            let below: Vec<usize> = (k + 1..n).filter(|&i| a[i][k]).collect();
            count += below.len() + 1;
            for &i in &below {
                for &j in &below {
                    a[i][j] = true;
                }
            }
        }
        count
    }

    #[test]
    fn keeps_groups_together_and_is_a_permutation() {
        let (n, col_ptr, row_idx, group) = grid(12, 3);
        let o = nested_dissection(n, &col_ptr, &row_idx, &group)
            .expect("ordering")
            .expect("144 vertices are ordered");
        let mut sorted = o.forward.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..n).collect::<Vec<_>>());
        for (k, &orig) in o.forward.iter().enumerate() {
            assert_eq!(o.inverse[orig], k);
        }
        // The three components of each node stay consecutive, in order.
        for chunk in o.forward.chunks(3) {
            assert_eq!(chunk[0] % 3, 0);
            assert_eq!(chunk[1], chunk[0] + 1);
            assert_eq!(chunk[2], chunk[0] + 2);
        }
    }

    #[test]
    fn leaves_less_fill_than_the_natural_order_on_a_grid() {
        // On an m x m grid the natural (banded) order fills O(m^3), nested dissection
        // O(m^2 log m).
        let (n, col_ptr, row_idx, group) = grid(24, 1);
        let o = nested_dissection(n, &col_ptr, &row_idx, &group)
            .expect("ordering")
            .expect("576 vertices are ordered");
        let natural: Vec<usize> = (0..n).collect();
        let nd = fill(n, &col_ptr, &row_idx, &o.forward);
        let banded = fill(n, &col_ptr, &row_idx, &natural);
        assert!(
            (nd as f64) < 0.75 * banded as f64,
            "nested dissection fill {nd} against natural {banded}"
        );
    }

    /// `L L^T` on two and three threads gives the same factor bit for bit as on one, and its
    /// solve solves the system; `L D L^T` on two threads agrees with one to round-off. The grid
    /// is large enough for faer's parallel dense kernels to run in its top supernodes (its
    /// root separator is 1 728 equations; the factor's 18 million entries took about 0.6 s on
    /// one thread and 0.4 s on two on an idle machine when this test was written).
    #[test]
    fn parallel_factorisations_match_the_sequential_one() {
        let a = crate::linalg::grid_matrix(24);
        let n = a.nrows();
        let group: Vec<usize> = (0..n).map(|q| q / 3).collect();
        let b: Vec<f64> = (0..n)
            .map(|i| ((i * 7919) % 1000) as f64 / 500.0 - 1.0)
            .collect();
        let solve = |threads: usize, ldlt: bool| {
            let mut c = SparseCholesky::analyse(a.symbolic(), Side::Lower, &group)
                .expect("analysis")
                .with_threads(threads);
            if ldlt {
                c.factor_ldlt(a.as_ref(), Side::Lower).expect("L D L^T");
            } else {
                c.factor_llt(a.as_ref(), Side::Lower).expect("L L^T");
            }
            let mut x = b.clone();
            c.solve_in_place(MatMut::from_column_major_slice_mut(&mut x, n, 1));
            (c.values.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), x)
        };
        let (l1, x1) = solve(1, false);
        // A x from the lower triangle.
        let mut ax = vec![0.0; n];
        for j in 0..n {
            for (i, v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                ax[i] += v * x1[j];
                if i != j {
                    ax[j] += v * x1[i];
                }
            }
        }
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let r: Vec<f64> = ax.iter().zip(&b).map(|(p, q)| p - q).collect();
        assert!(norm(&r) < 1e-12 * norm(&b), "residual {}", norm(&r));
        for threads in [2, 3] {
            let (lt, xt) = solve(threads, false);
            assert!(
                lt == l1,
                "the factor on {threads} threads differs from one thread's"
            );
            assert!(xt == x1, "the solution on {threads} threads differs");
        }
        let (_, y1) = solve(1, true);
        let (_, y2) = solve(2, true);
        let d: Vec<f64> = y1.iter().zip(&y2).map(|(p, q)| p - q).collect();
        assert!(
            norm(&d) <= 1e-12 * norm(&y1),
            "L D L^T differs by {}",
            norm(&d)
        );
        let e: Vec<f64> = y1.iter().zip(&x1).map(|(p, q)| p - q).collect();
        assert!(
            norm(&e) <= 1e-10 * norm(&x1),
            "L D L^T against L L^T: {}",
            norm(&e)
        );
    }

    #[test]
    fn small_graphs_and_bad_patterns() {
        let (n, col_ptr, row_idx, group) = grid(4, 3);
        assert_eq!(
            nested_dissection(n, &col_ptr, &row_idx, &group).expect("valid"),
            None
        );
        let (n, col_ptr, mut row_idx, group) = grid(10, 1);
        row_idx[3] = n + 5;
        let err = nested_dissection(n, &col_ptr, &row_idx, &group).unwrap_err();
        assert!(err.to_string().contains("out of range"), "{err}");
        let err = nested_dissection(n, &col_ptr[..n], &row_idx, &group).unwrap_err();
        assert!(err.to_string().contains("column pointers"), "{err}");
    }
}
