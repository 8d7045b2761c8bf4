//! The probe's implicit term as a low-rank matrix `h^2 A^T C A` of the backward Euler system,
//! shared by the probe (which builds it) and the implicit integrators (which solve with it):
//! the type both sides use, so that neither module imports the other.
//!
//! Two probes build it: the kernel patch's virtual coupling is one row, `A = U^T`,
//! `U = (w_i n)` over the patch, with `C = k + b / h` (the coupling against the surface's motion
//! along `n`); the implicit sphere contact ([`crate::contact::Probe`] under backward Euler) has
//! one row per face in contact, `a_f = (beta_fj nu_f)` over the face's corners (barycentric
//! coordinates of the face's point closest to the proxy, unit direction from the proxy's centre
//! to it), and `C^-1 = I / k_p + N^T Q_c^-1 N`: the faces' penalty springs in series with the
//! coupling through the massless proxy, eliminated exactly (module documentation of
//! [`crate::contact`]).

use glam::DVec3;

/// Largest number of rows of one probe's [`ContactCoupling`] (faces in contact at once).
pub const MAX_COUPLING_ROWS: usize = 48;

/// Most probes whose terms a [`CouplingMerge`] joins (the bodies' tool slots, issue 50; the
/// FEM body checks that `crate::body::MAX_TOOLS` fits).
pub const MAX_COUPLED_PROBES: usize = 4;

/// Largest number of rows of a [`ContactCoupling`] the integrators solve with: the rows of
/// [`MAX_COUPLED_PROBES`] probes.
pub const MAX_MERGED_ROWS: usize = MAX_COUPLED_PROBES * MAX_COUPLING_ROWS;

/// The probe's implicit term `h^2 A^T C A` of the backward Euler matrix (module
/// documentation). `A` has `F = row_ptr.len() - 1` sparse rows over the body's nodes: row `f`
/// holds `(nodes[e], vectors[e])` for `e` in `row_ptr[f]..row_ptr[f + 1]` (a node at most once
/// per row); `C` is `F x F` symmetric positive definite, given as its inverse (the compliance,
/// m/N) and that inverse's lower Cholesky factor, both row-major with stride `F`.
#[derive(Debug, Clone, Copy)]
pub struct ContactCoupling<'a> {
    /// Row offsets into `nodes` / `vectors`, `F + 1` of them.
    pub row_ptr: &'a [u32],
    /// Nodes of the entries.
    pub nodes: &'a [u32],
    /// Entries (dimensionless direction times weight).
    pub vectors: &'a [DVec3],
    /// `C^-1`, `F x F` row-major, m/N.
    pub compliance: &'a [f64],
    /// Lower Cholesky factor `L` of `C^-1 = L L^T`, `F x F` row-major.
    pub compliance_factor: &'a [f64],
}

impl ContactCoupling<'_> {
    /// Number of rows `F` (at most [`MAX_COUPLING_ROWS`]).
    pub fn rows(&self) -> usize {
        self.row_ptr.len() - 1
    }

    /// The entries of row `f`: `(node, vector)`.
    pub fn row(&self, f: usize) -> impl Iterator<Item = (u32, DVec3)> + '_ {
        let (a, b) = (self.row_ptr[f] as usize, self.row_ptr[f + 1] as usize);
        self.nodes[a..b]
            .iter()
            .copied()
            .zip(self.vectors[a..b].iter().copied())
    }

    /// `y = A p` for a nodal field `p` (one vector per body node); `y` has `F` values.
    pub fn a_times(&self, p: &[DVec3], y: &mut [f64]) {
        for (f, y) in y.iter_mut().enumerate().take(self.rows()) {
            *y = self.row(f).map(|(i, u)| u.dot(p[i as usize])).sum();
        }
    }

    /// `y <- C y` (two triangular solves with the compliance factor).
    pub fn apply_c(&self, y: &mut [f64]) {
        cholesky_solve(self.compliance_factor, self.rows(), y);
    }

    /// `out += s A^T y` (nodal field).
    pub fn add_at(&self, y: &[f64], s: f64, out: &mut [DVec3]) {
        for (f, &yf) in y.iter().enumerate().take(self.rows()) {
            for (i, u) in self.row(f) {
                out[i as usize] += u * (yf * s);
            }
        }
    }
}

/// The terms of several probes joined into one [`ContactCoupling`] (several tools on one
/// body, issue 50): their rows one after another, and the block-diagonal compliance and
/// factor of their blocks (each probe's proxy and coupling are its own, so the probes couple
/// only through the body). Solved exactly by the integrators' Woodbury terms like one probe's
/// rows. Buffers sized at construction: joining is allocation-free.
#[derive(Debug, Clone, Default)]
pub struct CouplingMerge {
    row_ptr: Vec<u32>,
    nodes: Vec<u32>,
    vectors: Vec<DVec3>,
    /// The blocks' compliances and factors as given, one after another (row-major each).
    blocks: Vec<f64>,
    /// Rows of each block.
    block_rows: Vec<usize>,
    compliance: Vec<f64>,
    factor: Vec<f64>,
}

impl CouplingMerge {
    /// Buffers for `probes` probes (at most [`MAX_COUPLED_PROBES`]) of at most `entries`
    /// entries each.
    pub fn with_capacity(probes: usize, entries: usize) -> Self {
        let probes = probes.min(MAX_COUPLED_PROBES);
        let rows = probes * MAX_COUPLING_ROWS;
        Self {
            row_ptr: Vec::with_capacity(rows + 1),
            nodes: Vec::with_capacity(probes * entries),
            vectors: Vec::with_capacity(probes * entries),
            blocks: Vec::with_capacity(2 * probes * MAX_COUPLING_ROWS * MAX_COUPLING_ROWS),
            block_rows: Vec::with_capacity(probes),
            compliance: vec![0.0; rows * rows],
            factor: vec![0.0; rows * rows],
        }
    }

    /// Forgets the joined terms.
    pub fn clear(&mut self) {
        self.row_ptr.clear();
        self.nodes.clear();
        self.vectors.clear();
        self.blocks.clear();
        self.block_rows.clear();
    }

    /// Appends one probe's term `c`.
    ///
    /// # Panics
    /// When the buffers of [`Self::with_capacity`] are full (more probes or entries).
    pub fn push(&mut self, c: ContactCoupling<'_>) {
        assert!(
            self.block_rows.len() < self.block_rows.capacity(),
            "CouplingMerge: more probes than its capacity"
        );
        let nf = c.rows();
        if self.row_ptr.is_empty() {
            self.row_ptr.push(0);
        }
        let base = self.nodes.len() as u32;
        for f in 0..nf {
            self.row_ptr.push(base + c.row_ptr[f + 1] - c.row_ptr[0]);
        }
        let (a, b) = (c.row_ptr[0] as usize, c.row_ptr[nf] as usize);
        self.nodes.extend_from_slice(&c.nodes[a..b]);
        self.vectors.extend_from_slice(&c.vectors[a..b]);
        self.blocks.extend_from_slice(&c.compliance[..nf * nf]);
        self.blocks
            .extend_from_slice(&c.compliance_factor[..nf * nf]);
        self.block_rows.push(nf);
    }

    /// The joined term: the rows appended so far with the block-diagonal compliance and
    /// factor (`None` without rows).
    pub fn view(&mut self) -> Option<ContactCoupling<'_>> {
        let total: usize = self.block_rows.iter().sum();
        if total == 0 {
            return None;
        }
        self.compliance[..total * total].fill(0.0);
        self.factor[..total * total].fill(0.0);
        let (mut at, mut offset) = (0, 0);
        for &nf in &self.block_rows {
            let (c, l) = (
                &self.blocks[at..at + nf * nf],
                &self.blocks[at + nf * nf..at + 2 * nf * nf],
            );
            for f in 0..nf {
                let row = (offset + f) * total + offset;
                self.compliance[row..row + nf].copy_from_slice(&c[f * nf..(f + 1) * nf]);
                self.factor[row..row + nf].copy_from_slice(&l[f * nf..(f + 1) * nf]);
            }
            at += 2 * nf * nf;
            offset += nf;
        }
        Some(ContactCoupling {
            row_ptr: &self.row_ptr,
            nodes: &self.nodes,
            vectors: &self.vectors,
            compliance: &self.compliance[..total * total],
            compliance_factor: &self.factor[..total * total],
        })
    }
}

/// In-place Cholesky factorisation `a = L L^T` of the `n x n` row-major symmetric matrix `a`
/// (its lower triangle is read, `L` is written there and the upper triangle zeroed). Returns
/// `false`, with `a` partly overwritten, when `a` is not positive definite (or not finite).
pub fn cholesky_in_place(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if !(d > 0.0) {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
        for k in j + 1..n {
            a[j * n + k] = 0.0;
        }
    }
    true
}

/// Solves `L L^T z = y` in place for the factor `l` of [`cholesky_in_place`] (`n x n`).
pub fn cholesky_solve(l: &[f64], n: usize, y: &mut [f64]) {
    for i in 0..n {
        let mut s = y[i];
        for k in 0..i {
            s -= l[i * n + k] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = y[i];
        for k in i + 1..n {
            s -= l[k * n + i] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The factor solves a random symmetric positive definite system to round-off, and a
    /// matrix with a negative pivot is refused.
    #[test]
    fn cholesky_solves_spd_systems_and_refuses_indefinite_ones() {
        let n = 7;
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let b: Vec<f64> = (0..n * n).map(|_| rnd()).collect();
        // a = b b^T + n I.
        let mut a = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                a[i * n + j] = (0..n).map(|k| b[i * n + k] * b[j * n + k]).sum::<f64>()
                    + if i == j { n as f64 } else { 0.0 };
            }
        }
        let x: Vec<f64> = (0..n).map(|_| rnd()).collect();
        let mut y: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| a[i * n + j] * x[j]).sum())
            .collect();
        let mut l = a.clone();
        assert!(cholesky_in_place(&mut l, n));
        cholesky_solve(&l, n, &mut y);
        for (yi, xi) in y.iter().zip(&x) {
            assert!((yi - xi).abs() < 1e-13, "{yi} {xi}");
        }
        let mut bad = a.clone();
        bad[3 * n + 3] = -1.0;
        assert!(!cholesky_in_place(&mut bad, n));
    }

    /// Two probes' terms join into rows one after another with the block-diagonal compliance
    /// and factor; a cleared merge has no term.
    #[test]
    fn a_merge_joins_rows_with_the_block_diagonal_compliance() {
        let one = ContactCoupling {
            row_ptr: &[0, 2],
            nodes: &[3, 4],
            vectors: &[DVec3::X, DVec3::Y],
            compliance: &[4.0],
            compliance_factor: &[2.0],
        };
        let two = ContactCoupling {
            row_ptr: &[0, 1, 2],
            nodes: &[4, 5],
            vectors: &[DVec3::Z, DVec3::X],
            compliance: &[9.0, 0.0, 0.0, 1.0],
            compliance_factor: &[3.0, 0.0, 0.0, 1.0],
        };
        let mut merge = CouplingMerge::with_capacity(2, 8);
        merge.push(one);
        merge.push(two);
        let c = merge.view().expect("rows");
        assert_eq!(c.rows(), 3);
        assert_eq!(c.row_ptr, &[0, 2, 3, 4]);
        assert_eq!(c.nodes, &[3, 4, 4, 5]);
        assert_eq!(c.compliance, &[4.0, 0.0, 0.0, 0.0, 9.0, 0.0, 0.0, 0.0, 1.0]);
        assert_eq!(
            c.compliance_factor,
            &[2.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 1.0]
        );
        // `C y` with the joined factor is each block's.
        let mut y = [8.0, 18.0, 5.0];
        c.apply_c(&mut y);
        assert_eq!(y, [2.0, 2.0, 5.0]);
        merge.clear();
        assert!(merge.view().is_none());
    }
}
