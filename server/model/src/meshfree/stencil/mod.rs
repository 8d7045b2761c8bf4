//! [`StencilGrid`]: the stencil layout of a [`super::TermBlock`]'s force loop. The particles a
//! block touches are copied onto a dense local grid (the bounding box of their lattice cells,
//! structure of arrays), so that neighbour `k` of the particle in grid cell `i` is the cell
//! `i + off_k` for a constant `off_k`, and [`LANES`] owners adjacent along x are one vector:
//! their neighbours `k` are consecutive cells, loaded and stored without any index.
//!
//! **Single precision.** The grid holds displacements from rest and forces in `f32`, eight
//! lanes to a vector ([`crate::simd::Lanes8`]); the rest data are rounded to `f32` once per
//! layout. The forces agree with the double-precision general loop to a few parts in a
//! million of the largest (unit test in `block.rs`): a displacement of a few millimetres keeps
//! about 1e-10 m, far below the neighbour differences the terms are made of.
//!
//! **Why it is exact.** On the lattice every per-pair rest quantity depends on the stencil
//! offset only: the uncorrected weight `w_k` ([`ParticleCloud::pair_weight`]), the rest
//! offset `X_k` and the hourglass stiffness `c_k`. The corrected gradient is
//! `g_ik = A_i^-T w_k` (Bonet-Lok, [`super::cloud`]), so with `F~_i = sum_k d_ik (x) w_k`
//! (`d_ik = x_j - x_i`, over present neighbours):
//! - `F_i = F~_i A_i^-1` (seed: `F_i = F~_i`, `A_i^-1 = I`);
//! - the hourglass matrix `H_i = sum_k c_k e_ik (x) X_k`, `e_ik = F_i X_k - d_ik`, is
//!   `F_i Q_i - D_i` with the rest constant `Q_i = sum_k c_k X_k X_k^T` and
//!   `D_i = sum_k d_ik (x) c_k X_k`, summed in the same pass as `F~_i`;
//! - the force on neighbour `k` is minus `grad_ik = N_i w_k - F_i u_k + c_k d_ik`, with
//!   `N_i = (V P_i + H_i) A_i^-T` and `u_k = c_k X_k`, and the owner's is
//!   `sum_k grad_ik = N_i S_i - F_i U_i + sum_k c_k d_ik` with the rest sums `S_i = sum_k w_k`,
//!   `U_i = sum_k u_k` over present neighbours.
//!
//! These are the formulas of [`super::block`] regrouped, so the forces agree with the general
//! loop to single-precision round-off (unit test in `block.rs`). Per term only a few 3x3
//! matrices are stored (no per-pair data at all); a missing neighbour is a zero in the
//! occupancy array, which masks `d_ik` in the first pass; in the second pass its `grad_ik` is
//! written into the empty cell, whose force nobody reads. Lanes of a group that own no term (tied particles, empty cells)
//! have `N = F = 0` and masked `d`, so they add nothing.
//!
//! **The 26-cell cube.** Both passes run over pairs `(k, -k)` (`w_-k = -w_k`, same class),
//! so pass 2 forms each pair's `(N - beta F) w_k` once for both entries. When the stencil is
//! the whole cube (the usual `h = spacing`), `w_k` is a class constant times the lattice
//! offset, so the loops are written out for its 13 pairs with every zero and sign known at
//! compile time: sums and differences of positions and of matrix columns, one product per
//! class, instead of a product per weight component. The general stencil keeps the pair
//! loops; a unit test in `block.rs` checks both, along every vector axis.
//!
//! **When it is used.** When the bounding box of the touched particles fits the grid's
//! capacity (sized at construction: no allocation at run time); otherwise (active regions far
//! apart) the block falls back to its general loop.
//!
//! Neighbours: built and driven by [`super::block::TermBlock`]; rest data from
//! [`super::cloud::ParticleCloud`].

use std::ops::Range;

use glam::{DMat3, DVec3};

use super::cloud::ParticleCloud;
use crate::material::MaterialParams;
use crate::pool::{TickPool, cut_at_middle};
use crate::simd::{Avx2Fma, Plain8f};

mod group;
mod layout;
mod offsets;
use group::{GroupPart, cube_force_at, group_loop};
use layout::StencilLayout;
use offsets::Stencil;

/// Lanes of a group: owners adjacent along the vector axis in one [`crate::simd::Lanes8`]
/// vector.
pub(super) const LANES: usize = crate::simd::LANES8;

/// Most pairs `(k, -k)` of a stencil of reach one (the 26-cell cube).
const MAX_PAIRS: usize = 13;

/// The 26-cell cube's pairs `(k, -k)` by the `k` whose first nonzero offset is positive, in
/// grid axes (the vector axis first), by class: faces, edges, corners.
const CUBE: [[i32; 3]; MAX_PAIRS] = [
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 1, 0],
    [1, -1, 0],
    [1, 0, 1],
    [1, 0, -1],
    [0, 1, 1],
    [0, 1, -1],
    [1, 1, 1],
    [1, 1, -1],
    [1, -1, 1],
    [1, -1, -1],
];

/// Class (0 faces, 1 edges, 2 corners) of each of [`CUBE`]'s pairs.
const CUBE_CLASS: [usize; MAX_PAIRS] = [0, 0, 0, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2];

/// The scratch of one evaluation, per grid cell (sized once, to the grid's capacity).
#[derive(Debug, Clone)]
struct GridBuffers {
    /// Displacements from rest (single precision) and occupancy (1 where a touched particle
    /// sits) per grid cell.
    px: Vec<f32>,
    py: Vec<f32>,
    pz: Vec<f32>,
    occ: Vec<f32>,
    /// Forces (x, y, z components) by offset `dx` along the vector axis, stored at their
    /// owner's cell (the cube loop: no shift across lanes; the pair loops write offset 0
    /// only, shifted) and interleaved by chunk of [`LANES`] cells: the chunk from cell `c`
    /// holds `fm`, `f0`, `fp` of its cells at `3 c + LANES (dx + 1)`; the force on cell `i` is
    /// `f0[i] + fm[i + 1] + fp[i - 1]` ([`cube_force_at`]). One set per part of the
    /// evaluation (issue 48: the groups cut into the tick pool's parts, each adding into its
    /// own set; the force on a cell is the sum over the sets); one set: the one-core loop.
    fc: Vec<[Vec<f32>; 3]>,
    /// The force on each touched particle (by entry of the layout's `by_particle`), summed
    /// over the parts before it is written to the caller's array.
    red: Vec<DVec3>,
}

impl GridBuffers {
    /// Zeroed buffers of `capacity_cells` cells.
    fn new(capacity_cells: usize, touched: usize) -> Self {
        Self {
            px: vec![0.0; capacity_cells],
            py: vec![0.0; capacity_cells],
            pz: vec![0.0; capacity_cells],
            occ: vec![0.0; capacity_cells],
            fc: vec![Self::force_set(capacity_cells)],
            red: vec![DVec3::ZERO; touched],
        }
    }

    /// One zeroed set of force buffers for `capacity_cells` cells.
    fn force_set(capacity_cells: usize) -> [Vec<f32>; 3] {
        [
            vec![0.0; 3 * capacity_cells],
            vec![0.0; 3 * capacity_cells],
            vec![0.0; 3 * capacity_cells],
        ]
    }
}

/// The stencil layout of a term block (module documentation), sized once: the cloud's
/// [`Stencil`], the block's [`StencilLayout`] and the [`GridBuffers`] of an evaluation.
#[derive(Debug, Clone)]
pub(crate) struct StencilGrid {
    /// The AVX2 + FMA token where the CPU has them.
    #[cfg(target_arch = "x86_64")]
    isa: Option<Avx2Fma>,
    stencil: Stencil,
    layout: StencilLayout,
    buffers: GridBuffers,
}

impl StencilGrid {
    /// A grid for blocks of up to `terms` terms touching up to `touched` particles of `cloud`,
    /// holding at most `capacity_cells` grid cells.
    pub(crate) fn new(
        cloud: &ParticleCloud,
        terms: usize,
        touched: usize,
        capacity_cells: usize,
    ) -> Self {
        let stencil = Stencil::new(cloud);
        let layout = StencilLayout::new(&stencil, terms, touched, capacity_cells);
        Self {
            #[cfg(target_arch = "x86_64")]
            isa: Avx2Fma::detect(),
            stencil,
            layout,
            buffers: GridBuffers::new(capacity_cells, touched),
        }
    }

    /// Runs the plain lanes from now on even where the CPU has AVX2 (tests of both builds).
    #[cfg(test)]
    pub(crate) fn plain_lanes_only(&mut self) {
        #[cfg(target_arch = "x86_64")]
        {
            self.isa = None;
        }
    }

    /// Runs the general stencil's pair loops from now on even for the 26-cell cube (tests of
    /// both).
    #[cfg(test)]
    pub(crate) fn pair_loops_only(&mut self) {
        self.stencil.cube = false;
    }

    /// Vectorises along lattice axis `axis`, with the groups shifted by `shift` cells
    /// (less than [`LANES`]) along it, from the next layout on (tests of every axis
    /// permutation and of several shifts).
    #[cfg(test)]
    pub(crate) fn force_vector_axis(&mut self, axis: usize, shift: usize) {
        self.layout.fast_axis = Some((axis, shift));
    }

    /// Cuts every later evaluation's groups into `parts` parts (at least 1), each with its own
    /// force buffers, for a tick pool of `parts` threads ([`Self::forces_in`]). Set-up, not a
    /// tick: allocates the buffers of the new parts.
    pub(crate) fn set_parts(&mut self, parts: usize) {
        let capacity = self.buffers.px.len();
        self.buffers
            .fc
            .resize_with(parts.max(1), || GridBuffers::force_set(capacity));
    }

    /// Grid cells in use and groups of [`LANES`] lanes (for studies of the lane occupancy).
    pub(crate) fn size(&self) -> (usize, usize) {
        (self.layout.cells, self.layout.groups.len())
    }

    /// Lays out the block: `particles` (global index of each local particle), the local index
    /// of each term's owner and each term's rest strain (seed). Allocation-free. Returns false
    /// (grid not usable) when the bounding box exceeds the capacity.
    pub(crate) fn build(
        &mut self,
        cloud: &ParticleCloud,
        particles: &[u32],
        owner_local: &[u32],
        rest_strain: &[DMat3],
    ) -> bool {
        self.layout.build(
            &self.stencil,
            &mut self.buffers,
            cloud,
            particles,
            owner_local,
            rest_strain,
        )
    }

    /// The terms' forces (N) at positions `x` (m, by global particle) written (`add`: added)
    /// into `f` (by global particle) for every touched particle, in the AVX2 + FMA build
    /// where the CPU has it, the groups cut into the parts of [`Self::set_parts`] and run on
    /// `pool` (serially without one). The grid holds displacements from the rest positions of
    /// the cloud the grid was built with (zero in empty cells). One part is the one-core loop
    /// bit for bit; more parts sum each cell's force over the parts (round-off apart).
    /// Allocation-free.
    pub(crate) fn forces_in(
        &mut self,
        pool: Option<&TickPool>,
        mat: &MaterialParams,
        x: &[DVec3],
        f: &mut [DVec3],
        add: bool,
    ) {
        let Self {
            stencil,
            layout,
            buffers: buf,
            ..
        } = self;
        let by = &layout.by_particle;
        let halves = pool
            .filter(|p| p.threads() > 1)
            .and_then(|pool| Some((pool, cut_at_middle(by.len(), |j| by[j].1)?)));
        gather_positions(halves, layout, x, [&mut buf.px, &mut buf.py, &mut buf.pz]);
        let pos = [&buf.px[..], &buf.py[..], &buf.pz[..]];
        let (parts, groups) = (buf.fc.len(), layout.groups.len());
        #[cfg(target_arch = "x86_64")]
        let isa = self.isa;
        let (st, lay) = (&*stencil, &*layout);
        let part = |k: usize, fc: &mut [Vec<f32>; 3]| {
            for &c in &lay.write_chunks {
                let c = 3 * c as usize;
                for a in fc.iter_mut() {
                    a[c..c + 3 * LANES].fill(0.0);
                }
            }
            let part = GroupPart {
                pos,
                fc,
                groups: groups * k / parts..groups * (k + 1) / parts,
            };
            #[cfg(target_arch = "x86_64")]
            if let Some(isa) = isa {
                // SAFETY: the token.
                unsafe { group::group_loop_avx2(isa, st, lay, part, mat) };
            } else {
                group_loop::<Plain8f>((), st, lay, part, mat);
            }
            #[cfg(not(target_arch = "x86_64"))]
            group_loop::<Plain8f>((), st, lay, part, mat);
        };
        match pool {
            Some(pool) if parts > 1 => pool.for_each_mut(&mut buf.fc, &part),
            _ => buf
                .fc
                .iter_mut()
                .enumerate()
                .for_each(|(k, fc)| part(k, fc)),
        }
        let n = layout.by_particle.len();
        let red = &mut buf.red[..n];
        let (sets, entries) = (&buf.fc[..], &layout.by_particle[..]);
        match halves {
            Some((pool, (h, _))) => {
                let (lo, hi) = red.split_at_mut(h);
                let mut parts = [(lo, 0), (hi, h)];
                pool.for_each_mut(&mut parts, &|_, (out, start)| {
                    sum_parts(sets, &entries[*start..*start + out.len()], out);
                });
            }
            None => sum_parts(sets, entries, red),
        }
        for (&(p, _), &fi) in entries.iter().zip(&*red) {
            if add {
                f[p as usize] += fi;
            } else {
                f[p as usize] = fi;
            }
        }
    }
}

/// The grid positions: the displacement from rest of every touched particle at its cell (in
/// single precision), in two halves on `halves`' pool (each writing its side of the cell
/// arrays: [`cut_at_middle`] by cell), else serially; the same values either way.
/// Allocation-free.
fn gather_positions(
    halves: Option<(&TickPool, (usize, usize))>,
    layout: &StencilLayout,
    x: &[DVec3],
    [px, py, pz]: [&mut Vec<f32>; 3],
) {
    let run = |entries: Range<usize>, [px, py, pz]: [&mut [f32]; 3], offset: usize| {
        let (by, rest) = (
            &layout.by_particle[entries.clone()],
            &layout.rest_of[entries],
        );
        for (&(p, i), r) in by.iter().zip(rest) {
            let (i, xp) = (i as usize - offset, x[p as usize] - *r);
            px[i] = xp.x as f32;
            py[i] = xp.y as f32;
            pz[i] = xp.z as f32;
        }
    };
    let n = layout.by_particle.len();
    match halves {
        Some((pool, (h, cell))) => {
            let ((px0, px1), (py0, py1), (pz0, pz1)) = (
                px.split_at_mut(cell),
                py.split_at_mut(cell),
                pz.split_at_mut(cell),
            );
            let mut parts = [([px0, py0, pz0], 0..h, 0), ([px1, py1, pz1], h..n, cell)];
            pool.for_each_mut(&mut parts, &|_, (cells, entries, offset)| {
                let [a, b, c] = cells;
                run(entries.clone(), [&mut **a, &mut **b, &mut **c], *offset);
            });
        }
        None => run(0..n, [&mut px[..], &mut py[..], &mut pz[..]], 0),
    }
}

/// `out[j]`: the force on the cell of `entries[j]` summed over the parts' force sets (the
/// first set's value, then each later one added, as one part would read it).
fn sum_parts(sets: &[[Vec<f32>; 3]], entries: &[(u32, u32)], out: &mut [DVec3]) {
    for (&(_, i), o) in entries.iter().zip(out) {
        let i = i as usize;
        let mut fi = DVec3::ZERO;
        for (k, fc) in sets.iter().enumerate() {
            let fk = DVec3::new(
                cube_force_at(&fc[0], i),
                cube_force_at(&fc[1], i),
                cube_force_at(&fc[2], i),
            );
            fi = if k == 0 { fk } else { fi + fk };
        }
        *o = fi;
    }
}
