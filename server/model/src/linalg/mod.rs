//! Sparse linear algebra shared by the solvers: fill-reducing orderings ([`ordering`]) and the
//! supernodal triangular sweeps ([`supernodal`]).

pub mod ordering;
pub mod supernodal;

/// Bytes of `v`'s heap buffer (its capacity), for the memory counts
/// ([`crate::element::FemModel::heap_bytes`],
/// [`crate::integrate::condensed::CondensedSolver::heap_bytes`]).
pub(crate) fn vec_bytes<T>(v: &Vec<T>) -> usize {
    v.capacity() * std::mem::size_of::<T>()
}

/// A 3-D Laplacian-like positive definite matrix on an `n^3` grid with three components per
/// node (each node's components coupled, each component to its six neighbours'): the lower
/// triangle, large enough from `n = 9` for faer to choose a supernodal factor. For tests.
#[cfg(test)]
pub(crate) fn grid_matrix(n: usize) -> faer::sparse::SparseColMat<usize, f64> {
    let id = |i: usize, j: usize, k: usize| (i * n + j) * n + k;
    let mut t = Vec::new();
    for i in 0..n {
        for j in 0..n {
            for k in 0..n {
                let a = id(i, j, k);
                for c in 0..3 {
                    t.push(faer::sparse::Triplet::new(
                        3 * a + c,
                        3 * a + c,
                        7.0 + c as f64,
                    ));
                    if c > 0 {
                        t.push(faer::sparse::Triplet::new(3 * a + c, 3 * a, 0.5));
                    }
                }
                for (di, dj, dk) in [(1, 0, 0), (0, 1, 0), (0, 0, 1)] {
                    let (p, q, r) = (i + di, j + dj, k + dk);
                    if p < n && q < n && r < n {
                        let b = id(p, q, r);
                        for c in 0..3 {
                            t.push(faer::sparse::Triplet::new(3 * b + c, 3 * a + c, -1.0));
                        }
                    }
                }
            }
        }
    }
    let m = 3 * n * n * n;
    faer::sparse::SparseColMat::try_new_from_triplets(m, m, &t).expect("a valid pattern")
}
