//! The particle neighbour grid: particles sampled on a regular lattice of spacing `s` (the
//! seed's "uniform initial grid", section 3.2) are found through a dense cell array over the
//! lattice's bounding box (cell -> particle index), and a particle's neighbours are the
//! lattice offsets within the kernel support, the *stencil*. In the total-Lagrangian form
//! neighbours are fixed in the rest configuration, so the grid is built once and never
//! searched again at run time.
//!
//! Memory: 4 bytes per lattice cell of the bounding box (for a shell-shaped particle layer about
//! five cells per particle).
//!
//! Neighbours: [`super::cloud::ParticleCloud`] owns one; the hybrid body's preprocessing fills
//! it.

use glam::DVec3;

/// "No particle in this cell."
pub const EMPTY: u32 = u32::MAX;

/// A regular lattice with a dense cell -> particle map (module documentation).
#[derive(Debug, Clone)]
pub struct Lattice {
    /// Position of cell (0, 0, 0), m.
    origin_m: DVec3,
    /// Lattice spacing, m.
    spacing_m: f64,
    /// Cells along x, y, z.
    dims: [usize; 3],
    /// Particle index per cell (x fastest), [`EMPTY`] where there is none.
    cells: Vec<u32>,
    /// Integer offsets of the neighbours within the support radius (the origin excluded),
    /// sorted by length then lexicographically.
    stencil: Vec<[i32; 3]>,
}

impl Lattice {
    /// An empty lattice of `dims` cells at `origin_m` with spacing `spacing_m`, whose stencil
    /// holds the offsets `d != 0` with `|d| s < support_m` (strictly inside the support, where
    /// the kernels are non-zero).
    ///
    /// # Panics
    /// If the spacing is not positive or the cell count overflows `u32`.
    pub fn new(origin_m: DVec3, spacing_m: f64, dims: [usize; 3], support_m: f64) -> Self {
        assert!(spacing_m > 0.0, "lattice spacing must be positive");
        let count = dims[0]
            .checked_mul(dims[1])
            .and_then(|c| c.checked_mul(dims[2]))
            .filter(|&c| c < EMPTY as usize)
            .expect("lattice cell count");
        let reach = (support_m / spacing_m).ceil() as i32;
        let mut stencil = Vec::new();
        for k in -reach..=reach {
            for j in -reach..=reach {
                for i in -reach..=reach {
                    let d2 = (i * i + j * j + k * k) as f64;
                    if d2 > 0.0 && d2.sqrt() * spacing_m < support_m * (1.0 - 1e-12) {
                        stencil.push([i, j, k]);
                    }
                }
            }
        }
        stencil.sort_by_key(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2], *d));
        Self {
            origin_m,
            spacing_m,
            dims,
            cells: vec![EMPTY; count],
            stencil,
        }
    }

    /// Lattice spacing, m.
    #[inline]
    pub fn spacing_m(&self) -> f64 {
        self.spacing_m
    }

    /// Cells along x, y, z.
    #[inline]
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// The stencil offsets (module documentation).
    #[inline]
    pub fn stencil(&self) -> &[[i32; 3]] {
        &self.stencil
    }

    /// Position of cell `ijk`, m.
    #[inline]
    pub fn position(&self, ijk: [usize; 3]) -> DVec3 {
        self.origin_m + DVec3::new(ijk[0] as f64, ijk[1] as f64, ijk[2] as f64) * self.spacing_m
    }

    /// Linear index of cell `ijk` (x fastest).
    #[inline]
    pub fn index(&self, ijk: [usize; 3]) -> usize {
        ijk[0] + self.dims[0] * (ijk[1] + self.dims[1] * ijk[2])
    }

    /// The cell of linear index `c`.
    #[inline]
    pub fn cell(&self, c: usize) -> [usize; 3] {
        let i = c % self.dims[0];
        let r = c / self.dims[0];
        [i, r % self.dims[1], r / self.dims[1]]
    }

    /// The cell nearest to `p` (m), clamped into the lattice.
    pub fn nearest_cell(&self, p: DVec3) -> [usize; 3] {
        let q = (p - self.origin_m) / self.spacing_m;
        let c = |v: f64, n: usize| (v.round().max(0.0) as usize).min(n - 1);
        [
            c(q.x, self.dims[0]),
            c(q.y, self.dims[1]),
            c(q.z, self.dims[2]),
        ]
    }

    /// Records particle `p` in cell `ijk`.
    ///
    /// # Panics
    /// If `ijk` is outside the lattice.
    pub fn set(&mut self, ijk: [usize; 3], p: u32) {
        let c = self.index(ijk);
        self.cells[c] = p;
    }

    /// The particle in cell `ijk` + `d`, or `None` outside the lattice or in an empty cell.
    #[inline]
    pub fn get_offset(&self, ijk: [usize; 3], d: [i32; 3]) -> Option<u32> {
        let mut c = [0usize; 3];
        for a in 0..3 {
            let v = ijk[a] as i64 + d[a] as i64;
            if v < 0 || v >= self.dims[a] as i64 {
                return None;
            }
            c[a] = v as usize;
        }
        let p = self.cells[self.index(c)];
        (p != EMPTY).then_some(p)
    }

    /// Renumbers the particles of every cell through `new_index` (old particle index -> new
    /// one, [`EMPTY`] to clear the cell).
    ///
    /// # Panics
    /// If a cell holds an index outside `new_index`.
    pub fn renumber(&mut self, new_index: &[u32]) {
        for c in &mut self.cells {
            if *c != EMPTY {
                *c = new_index[*c as usize];
            }
        }
    }

    /// Heap memory of the grid, bytes.
    pub fn memory_bytes(&self) -> usize {
        self.cells.capacity() * 4 + self.stencil.capacity() * 12
    }
}
