//! [`TermBlock`]: the run-time energy terms of a set of particles (the active ones and the
//! inactive neighbours whose terms reach them), with their rest data filled once when the set
//! changes, and [`critical_time_step`], the explicit stability limit of a cloud.
//!
//! **Energy and force (seed 000 eq. 26-29, total-Lagrangian).** Term `i` (owner particle `i`,
//! neighbours `j`, rest data from [`ParticleCloud::term_rest`]) has
//! `F_i = sum_j (x_j - x_i) (x) g_ij` and the energy `V_i Psi(F_i)`; its gradient is
//! `d/dx_j = V_i P_i g_ij`, `d/dx_i = -V_i P_i sum_j g_ij` with `P = dPsi/dF` (eq. 29's
//! `sum_j V_i V_j sigma grad W_ij` in first Piola-Kirchhoff form). The corrected variant adds
//! the hourglass energy `sum_j c_ij |e_ij|^2 / 2`, `e_ij = F_i X_ij - x_ij`, whose gradient is
//! `d/dx_j = H_i g_ij - c_ij e_ij` with `H_i = sum_j c_ij e_ij (x) X_ij` (and minus the sum for
//! the owner). Forces are minus these gradients, so they sum to zero in every term (linear
//! momentum) and vanish for rigid motions.
//!
//! The seed variant uses St. Venant-Kirchhoff (seed eq. 9) with the strain measured from the
//! kernel estimate at rest, `E_i = (F_i^T F_i - A_i^T A_i) / 2` ([`super::cloud`]).
//!
//! Neighbours: rest data from [`super::cloud`]; used by the hybrid body.

use glam::{DMat3, DVec3};

use super::MeshfreeVariant;
use super::cloud::{MAX_STENCIL, ParticleCloud, TermRest, outer};
use super::stencil::StencilGrid;
use crate::ModelError;
use crate::material::stvk::{green_strain, stvk_energy_density, stvk_stress};
use crate::material::{energy_density, first_piola};
use crate::pool::TickPool;
use crate::simd::Avx2Fma;

/// The energy terms of a set of particles (module documentation), sized once.
///
/// **Layout.** The particles the terms touch (owners and neighbours) get local indices in the
/// order they are first met; each term stores its neighbours' local indices and its rest data
/// in structure-of-arrays form, padded with zero weights to a stride that is a multiple of
/// four (`g = 0`, `X = 0`, `c = 0` on the owner's own slot), so the loops over a neighbourhood
/// have a fixed length and vectorise. A force evaluation gathers the touched particles'
/// positions into a compact local array, runs the terms there and writes the forces back:
/// the working set stays in the core's cache whatever the size of the whole cloud.
#[derive(Debug, Clone)]
pub struct TermBlock {
    stride: usize,
    capacity: usize,
    len: usize,
    seed: bool,
    /// Global particle of each term (its owner).
    owner: Vec<u32>,
    /// Local index of each term's owner.
    owner_local: Vec<u32>,
    /// Local indices of each term's neighbours, `stride` per term (padding: the owner).
    nbr: Vec<u32>,
    gx: Vec<f64>,
    gy: Vec<f64>,
    gz: Vec<f64>,
    ox: Vec<f64>,
    oy: Vec<f64>,
    oz: Vec<f64>,
    hourglass: Vec<f64>,
    rest_strain: Vec<DMat3>,
    /// Global particle of each local index.
    particles: Vec<u32>,
    /// Local index of each global particle (`u32::MAX`: not in the block).
    local_of: Vec<u32>,
    /// Positions and forces of the touched particles, by local index.
    x_local: Vec<DVec3>,
    f_local: Vec<DVec3>,
    /// The AVX2 + FMA token when the CPU has them (the force loop's fast build).
    isa: Option<Avx2Fma>,
    scratch: Box<TermRest>,
    nbr_scratch: [u32; MAX_STENCIL],
    /// The stencil layout of the force loop ([`super::stencil`]), rebuilt at the first force
    /// evaluation after the terms changed.
    stencil: StencilGrid,
    stencil_state: StencilState,
    /// Whether the stencil loop may be used (the general loop otherwise).
    use_stencil: bool,
}

/// Whether the stencil layout matches the current terms.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StencilState {
    /// The terms changed since the layout was built.
    Stale,
    /// Built and in use.
    Ready,
    /// The bounding box did not fit the grid: the general loop runs.
    TooLarge,
}

/// Grid cells of the stencil layout per term of capacity (the bounding box of a compact active
/// set holds about 3 to 10 cells per term); at least [`MIN_STENCIL_CELLS`].
const STENCIL_CELLS_PER_TERM: usize = 48;

/// Smallest grid of the stencil layout, cells.
const MIN_STENCIL_CELLS: usize = 1 << 15;

/// `sum_k u_k (x) v_k` as a column-major 3x3 (`[3 c + r] = sum_k u_r[k] v_c[k]`) over slices of
/// a length that is a multiple of four, with four partial sums per entry so that it
/// vectorises (a plain sum is a serial chain of adds). No closures: it inlines into the
/// `target_feature` build of the caller.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // one index into six parallel slices
fn outer_sum(u: [&[f64]; 3], v: [&[f64]; 3]) -> [f64; 9] {
    let n = u[0].len();
    let (ux, uy, uz) = (&u[0][..n], &u[1][..n], &u[2][..n]);
    let (vx, vy, vz) = (&v[0][..n], &v[1][..n], &v[2][..n]);
    let mut acc = [[0.0f64; 4]; 9];
    for c in (0..n).step_by(4) {
        for l in 0..4 {
            let k = c + l;
            acc[0][l] += ux[k] * vx[k];
            acc[1][l] += uy[k] * vx[k];
            acc[2][l] += uz[k] * vx[k];
            acc[3][l] += ux[k] * vy[k];
            acc[4][l] += uy[k] * vy[k];
            acc[5][l] += uz[k] * vy[k];
            acc[6][l] += ux[k] * vz[k];
            acc[7][l] += uy[k] * vz[k];
            acc[8][l] += uz[k] * vz[k];
        }
    }
    let mut out = [0.0f64; 9];
    for (o, row) in out.iter_mut().zip(&acc) {
        *o = (row[0] + row[1]) + (row[2] + row[3]);
    }
    out
}

/// `n` rounded up to a multiple of four.
fn padded(n: usize) -> usize {
    n.div_ceil(4) * 4
}

impl TermBlock {
    /// An empty block for up to `capacity` terms of particles of `cloud`.
    pub fn new(cloud: &ParticleCloud, capacity: usize) -> Self {
        let stride = padded(cloud.stencil_len());
        let slots = capacity * stride;
        let touched = cloud.len().min(capacity * (cloud.stencil_len() + 1));
        Self {
            stride,
            capacity,
            len: 0,
            seed: cloud.params().variant == MeshfreeVariant::Seed,
            owner: vec![0; capacity],
            owner_local: vec![0; capacity],
            nbr: vec![0; slots],
            gx: vec![0.0; slots],
            gy: vec![0.0; slots],
            gz: vec![0.0; slots],
            ox: vec![0.0; slots],
            oy: vec![0.0; slots],
            oz: vec![0.0; slots],
            hourglass: vec![0.0; slots],
            rest_strain: vec![DMat3::ZERO; capacity],
            particles: Vec::with_capacity(touched),
            local_of: vec![u32::MAX; cloud.len()],
            x_local: vec![DVec3::ZERO; touched],
            f_local: vec![DVec3::ZERO; touched],
            isa: Avx2Fma::detect(),
            scratch: Box::default(),
            nbr_scratch: [0; MAX_STENCIL],
            stencil: StencilGrid::new(
                cloud,
                capacity,
                touched,
                (capacity * STENCIL_CELLS_PER_TERM).max(MIN_STENCIL_CELLS),
            ),
            stencil_state: StencilState::Stale,
            use_stencil: true,
        }
    }

    /// Chooses the force loop: `true` (the default) runs the stencil loop whenever the touched
    /// particles' bounding box fits its grid, `false` always the general loop (for tests and
    /// benchmarks of the two; their forces agree to single-precision round-off).
    pub fn set_stencil_loop(&mut self, on: bool) {
        self.use_stencil = on;
    }

    /// Cuts the stencil loop of later evaluations into `parts` parts (at least 1), for a tick
    /// pool of that many threads ([`Self::write_forces_in`]). Set-up, not a tick: allocates
    /// the parts' force buffers.
    pub fn set_parts(&mut self, parts: usize) {
        self.stencil.set_parts(parts);
    }

    /// Whether the last force evaluation ran the stencil loop, with its grid cells and groups
    /// of four lanes (`None`: the general loop ran).
    pub fn stencil_layout(&self) -> Option<(usize, usize)> {
        (self.use_stencil && self.stencil_state == StencilState::Ready).then(|| self.stencil.size())
    }

    /// Number of terms.
    #[inline]
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the block has no term.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Largest number of terms.
    #[inline]
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Owner particle of each term.
    #[inline]
    pub fn owners(&self) -> &[u32] {
        &self.owner[..self.len]
    }

    /// Removes every term (allocation-free).
    pub fn clear(&mut self) {
        for &p in &self.particles {
            self.local_of[p as usize] = u32::MAX;
        }
        self.particles.clear();
        self.len = 0;
        self.stencil_state = StencilState::Stale;
    }

    /// The local index of global particle `p`, assigned if new.
    fn local(&mut self, p: u32) -> u32 {
        let l = &mut self.local_of[p as usize];
        if *l == u32::MAX {
            *l = self.particles.len() as u32;
            self.particles.push(p);
        }
        *l
    }

    /// Adds the term of particle `p` (its rest data, [`ParticleCloud::term_rest`]).
    /// Allocation-free. Returns `Ok(false)` (nothing added) when the block is full.
    ///
    /// # Errors
    /// As [`ParticleCloud::term_rest`] (a degenerate neighbourhood in the corrected variant).
    pub fn push(&mut self, cloud: &ParticleCloud, p: u32) -> Result<bool, ModelError> {
        if self.len == self.capacity {
            return Ok(false);
        }
        let n = cloud.neighbours(p, &mut self.nbr_scratch);
        let new = std::iter::once(p)
            .chain(self.nbr_scratch[..n].iter().copied())
            .filter(|&q| self.local_of[q as usize] == u32::MAX)
            .count();
        if self.particles.len() + new > self.x_local.len() {
            return Ok(false);
        }
        cloud.term_rest(p, &self.nbr_scratch[..n], &mut self.scratch)?;
        let t = self.len;
        let base = t * self.stride;
        let own = self.local(p);
        self.owner[t] = p;
        self.owner_local[t] = own;
        for k in 0..self.stride {
            let s = base + k;
            if k < n {
                self.nbr[s] = self.local(self.nbr_scratch[k]);
                let (g, o) = (self.scratch.g[k], self.scratch.offset_m[k]);
                (self.gx[s], self.gy[s], self.gz[s]) = (g.x, g.y, g.z);
                (self.ox[s], self.oy[s], self.oz[s]) = (o.x, o.y, o.z);
                self.hourglass[s] = self.scratch.hourglass_n_per_m[k];
            } else {
                self.nbr[s] = own;
                (self.gx[s], self.gy[s], self.gz[s]) = (0.0, 0.0, 0.0);
                (self.ox[s], self.oy[s], self.oz[s]) = (0.0, 0.0, 0.0);
                self.hourglass[s] = 0.0;
            }
        }
        self.rest_strain[t] = self.scratch.rest_strain;
        self.len += 1;
        self.stencil_state = StencilState::Stale;
        Ok(true)
    }

    /// Deformation gradient `F_t` of term `t` at positions `x` (m, indexed by particle).
    pub fn deformation_gradient(&self, t: usize, x: &[DVec3]) -> DMat3 {
        let base = t * self.stride;
        let xi = x[self.owner[t] as usize];
        let mut f = DMat3::ZERO;
        for s in base..base + self.stride {
            let d = x[self.particles[self.nbr[s] as usize] as usize] - xi;
            f += outer(d, DVec3::new(self.gx[s], self.gy[s], self.gz[s]));
        }
        f
    }

    /// Adds the elastic (and hourglass) forces of every term (N) at positions `x` (m) into
    /// `f`, both indexed by particle (length at least the cloud's particle count).
    /// Allocation-free.
    pub fn add_forces(&mut self, cloud: &ParticleCloud, x: &[DVec3], f: &mut [DVec3]) {
        if self.stencil_forces(None, cloud, x, f, true) {
            return;
        }
        self.local_forces(cloud, x);
        for (&p, fl) in self.particles.iter().zip(&self.f_local) {
            f[p as usize] += *fl;
        }
    }

    /// Writes the elastic (and hourglass) forces of the terms (N) at positions `x` (m) into
    /// `f` for every particle a term touches, overwriting what was there (the other entries
    /// are left alone): zeroing those entries and [`Self::add_forces`] in one pass.
    /// Allocation-free.
    pub fn write_forces(&mut self, cloud: &ParticleCloud, x: &[DVec3], f: &mut [DVec3]) {
        self.write_forces_in(None, cloud, x, f);
    }

    /// [`Self::write_forces`] with the stencil loop's groups cut into the parts of
    /// [`Self::set_parts`] on `pool` (issue 48; the general loop stays serial). One part is
    /// [`Self::write_forces`] bit for bit; more parts sum each particle's force over the parts
    /// (round-off apart). Allocation-free.
    pub fn write_forces_in(
        &mut self,
        pool: Option<&TickPool>,
        cloud: &ParticleCloud,
        x: &[DVec3],
        f: &mut [DVec3],
    ) {
        if self.stencil_forces(pool, cloud, x, f, false) {
            return;
        }
        self.local_forces(cloud, x);
        for (&p, fl) in self.particles.iter().zip(&self.f_local) {
            f[p as usize] = *fl;
        }
    }

    /// The stencil loop's forces written (`add`: added) into `f` when it can run (its layout
    /// rebuilt if the terms changed); false (nothing done) when the general loop must run.
    fn stencil_forces(
        &mut self,
        pool: Option<&TickPool>,
        cloud: &ParticleCloud,
        x: &[DVec3],
        f: &mut [DVec3],
        add: bool,
    ) -> bool {
        if !self.use_stencil {
            return false;
        }
        if self.stencil_state == StencilState::Stale {
            let fits = self.stencil.build(
                cloud,
                &self.particles,
                &self.owner_local[..self.len],
                &self.rest_strain[..self.len],
            );
            self.stencil_state = if fits {
                StencilState::Ready
            } else {
                StencilState::TooLarge
            };
        }
        if self.stencil_state != StencilState::Ready {
            return false;
        }
        self.stencil.forces_in(pool, cloud.material(), x, f, add);
        true
    }

    /// The terms' forces into `f_local` by the general loop (module documentation for the
    /// formulas), with the AVX2 + FMA build of the loop where the CPU has it.
    fn local_forces(&mut self, cloud: &ParticleCloud, x: &[DVec3]) {
        let n_local = self.particles.len();
        for (xl, &p) in self.x_local.iter_mut().zip(&self.particles) {
            *xl = x[p as usize];
        }
        self.f_local[..n_local].fill(DVec3::ZERO);
        #[cfg(target_arch = "x86_64")]
        if let Some(isa) = self.isa {
            // SAFETY: the token.
            unsafe { self.term_loop_avx2(isa, cloud) };
            return;
        }
        self.term_loop(cloud);
    }

    /// [`Self::term_loop`] compiled for AVX2 + FMA (the token proves the CPU has them).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn term_loop_avx2(&mut self, _isa: Avx2Fma, cloud: &ParticleCloud) {
        self.term_loop(cloud);
    }

    /// Every term's forces from `x_local` into `f_local`. Reductions over a neighbourhood
    /// keep four partial sums per entry (the stride is a multiple of four) so that they
    /// vectorise; no closures, so that it inlines into [`Self::term_loop_avx2`].
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // one index into several parallel arrays
    fn term_loop(&mut self, cloud: &ParticleCloud) {
        let v = cloud.volume_m3();
        let mat = cloud.material();
        let s = self.stride;
        assert!(s.is_multiple_of(4) && s <= MAX_STENCIL);
        let mut dx = [0.0f64; MAX_STENCIL];
        let mut dy = [0.0f64; MAX_STENCIL];
        let mut dz = [0.0f64; MAX_STENCIL];
        let mut ex = [0.0f64; MAX_STENCIL];
        let mut ey = [0.0f64; MAX_STENCIL];
        let mut ez = [0.0f64; MAX_STENCIL];
        for t in 0..self.len {
            let base = t * s;
            let nbr = &self.nbr[base..base + s];
            let gx = &self.gx[base..base + s];
            let gy = &self.gy[base..base + s];
            let gz = &self.gz[base..base + s];
            let own = self.owner_local[t] as usize;
            let xi = self.x_local[own];
            for k in 0..s {
                let d = self.x_local[nbr[k] as usize] - xi;
                dx[k] = d.x;
                dy[k] = d.y;
                dz[k] = d.z;
            }
            // F = sum_k d_k (x) g_k.
            let a = outer_sum([&dx[..s], &dy[..s], &dz[..s]], [gx, gy, gz]);
            let fg = DMat3::from_cols_array(&a);
            let p = if self.seed {
                let e = green_strain(&fg) - self.rest_strain[t];
                fg * stvk_stress(&e, mat.lambda_pa, mat.mu_pa)
            } else {
                first_piola(mat, &fg)
            };
            // m = V P + H, the matrix applied to g_k.
            let mut m = (p * v).to_cols_array();
            if !self.seed {
                // Pair errors c_k e_k = c_k (F X_k - d_k), then H = sum c_k e_k (x) X_k.
                let ox = &self.ox[base..base + s];
                let oy = &self.oy[base..base + s];
                let oz = &self.oz[base..base + s];
                let ck = &self.hourglass[base..base + s];
                for k in 0..s {
                    ex[k] = (a[0] * ox[k] + a[3] * oy[k] + a[6] * oz[k] - dx[k]) * ck[k];
                    ey[k] = (a[1] * ox[k] + a[4] * oy[k] + a[7] * oz[k] - dy[k]) * ck[k];
                    ez[k] = (a[2] * ox[k] + a[5] * oy[k] + a[8] * oz[k] - dz[k]) * ck[k];
                }
                let h = outer_sum([&ex[..s], &ey[..s], &ez[..s]], [ox, oy, oz]);
                for (mi, hi) in m.iter_mut().zip(h) {
                    *mi += hi;
                }
            }
            // grad_k = m g_k - c_k e_k (no hourglass part in the seed variant).
            for k in 0..s {
                dx[k] = m[0] * gx[k] + m[3] * gy[k] + m[6] * gz[k];
                dy[k] = m[1] * gx[k] + m[4] * gy[k] + m[7] * gz[k];
                dz[k] = m[2] * gx[k] + m[5] * gy[k] + m[8] * gz[k];
            }
            if !self.seed {
                for k in 0..s {
                    dx[k] -= ex[k];
                    dy[k] -= ey[k];
                    dz[k] -= ez[k];
                }
            }
            let mut owner = DVec3::ZERO;
            for k in 0..s {
                let grad = DVec3::new(dx[k], dy[k], dz[k]);
                self.f_local[nbr[k] as usize] -= grad;
                owner += grad;
            }
            self.f_local[own] += owner;
        }
    }

    /// Total energy of the terms (elastic plus hourglass), J, at positions `x` (m).
    pub fn energy(&self, cloud: &ParticleCloud, x: &[DVec3]) -> f64 {
        let v = cloud.volume_m3();
        let mat = cloud.material();
        let mut total = 0.0;
        for t in 0..self.len {
            let base = t * self.stride;
            let fg = self.deformation_gradient(t, x);
            total += v * if self.seed {
                let e = green_strain(&fg) - self.rest_strain[t];
                stvk_energy_density(&e, mat.lambda_pa, mat.mu_pa)
            } else {
                energy_density(mat, &fg)
            };
            if !self.seed {
                let xi = x[self.owner[t] as usize];
                for s in base..base + self.stride {
                    let xj = x[self.particles[self.nbr[s] as usize] as usize];
                    let o = DVec3::new(self.ox[s], self.oy[s], self.oz[s]);
                    let e = fg * o - (xj - xi);
                    total += 0.5 * self.hourglass[s] * e.length_squared();
                }
            }
        }
        total
    }
}

/// Explicit stability limit of the whole cloud, s: `2 / sqrt(lambda_max)` of `M^-1 K` at rest,
/// with `lambda_max` bounded above by Gershgorin's theorem on the *assembled* linearised
/// stiffness (scalar rows of `K`, every term's blocks summed before the absolute values are
/// taken). At rest every law linearises to isotropic elasticity, whose term block is
/// `K_ab = V (lambda g_a g_b^T + mu (g_a . g_b) I + mu g_b g_a^T)` (owner: `g = -sum_j g_ij`),
/// plus the hourglass blocks `sum_q c_q B_qa B_qb I` of the corrected variant
/// (`e_q = sum_m B_qm u_m`, `B_qm = g_m . X_q - [m = q] + [m = owner]`). Rigorous at rest, and
/// 1.5 (seed) to 1.6 (corrected) times longer than the bound of the summed block norms
/// (`V (lambda + 2 mu) |g_a| |g_b|` per term, which ignores that the terms' blocks cancel in
/// part: on the infinite lattice the true limit is 2.1 to 2.3 times that one, issue 13).
///
/// A row depends only on which lattice cells within two cells of its particle are occupied,
/// so rows are memoised by that pattern (the interior is one pattern). Stencils reaching
/// beyond one cell use the summed-norm bound.
///
/// Used for the Verlet step of seed eq. 33 and its velocity form.
///
/// # Errors
/// As [`ParticleCloud::term_rest`].
pub fn critical_time_step(cloud: &ParticleCloud) -> Result<f64, ModelError> {
    let reach = cloud
        .lattice()
        .stencil()
        .iter()
        .flat_map(|d| d.iter().map(|v| v.unsigned_abs()))
        .max()
        .unwrap_or(0);
    let lambda_max = if reach == 1 {
        assembled_gershgorin(cloud)?
    } else {
        summed_norm_gershgorin(cloud)?
    } / cloud.mass_kg();
    Ok(if lambda_max > 0.0 {
        2.0 / lambda_max.sqrt()
    } else {
        f64::INFINITY
    })
}

/// The largest scalar row sum of `|K|` over the cloud, N/m (stencil reach one cell):
/// [`critical_time_step`].
fn assembled_gershgorin(cloud: &ParticleCloud) -> Result<f64, ModelError> {
    use std::collections::HashMap;
    let lattice = cloud.lattice();
    let mut memo: HashMap<u128, f64> = HashMap::new();
    let mut nbr = [0u32; MAX_STENCIL];
    let mut nbr_i = [0u32; MAX_STENCIL];
    let mut terms: HashMap<u64, Box<TermRest>> = HashMap::new();
    let mut acc = vec![[0.0f64; 9]; 125];
    let mut cells = [[0i32; 3]; MAX_STENCIL + 1];
    let mut best: f64 = 0.0;
    for a in 0..cloud.len() as u32 {
        let ca = cloud.cell_of(a);
        let key = cube_occupancy(cloud, ca);
        if let Some(&row) = memo.get(&key) {
            best = best.max(row);
            continue;
        }
        acc.iter_mut().for_each(|b| *b = [0.0; 9]);
        let ka = cloud.neighbours(a, &mut nbr);
        for &i in std::iter::once(&a).chain(&nbr[..ka]) {
            // Term i's neighbours (stencil order), their cells relative to a, and its
            // occupancy pattern: a term's rest data depend only on that pattern.
            let ci = cloud.cell_of(i);
            let rel = |c: [usize; 3]| {
                [
                    c[0] as i32 - ca[0] as i32,
                    c[1] as i32 - ca[1] as i32,
                    c[2] as i32 - ca[2] as i32,
                ]
            };
            let ri = rel(ci);
            cells[0] = ri;
            let mut ki = 0;
            let mut term_key = 0u64;
            for (bit, d) in lattice.stencil().iter().enumerate() {
                if let Some(q) = lattice.get_offset(ci, *d) {
                    term_key |= 1u64 << bit;
                    nbr_i[ki] = q;
                    cells[ki + 1] = [ri[0] + d[0], ri[1] + d[1], ri[2] + d[2]];
                    ki += 1;
                }
            }
            let rest: &TermRest = match terms.get(&term_key) {
                Some(r) => r,
                None => {
                    let mut r = Box::<TermRest>::default();
                    cloud.term_rest(i, &nbr_i[..ki], &mut r)?;
                    terms.entry(term_key).or_insert(r)
                }
            };
            add_term_blocks(cloud, rest, &nbr_i[..ki], a, &cells[..=ki], &mut acc);
        }
        let mut row: f64 = 0.0;
        for r in 0..3 {
            let sum: f64 = acc
                .iter()
                .map(|b| b[r].abs() + b[3 + r].abs() + b[6 + r].abs())
                .sum();
            row = row.max(sum);
        }
        memo.insert(key, row);
        best = best.max(row);
    }
    Ok(best)
}

/// Bit of cell offset `d` (each component in -2..=2) in the 5 x 5 x 5 cube around a particle
/// ([`assembled_gershgorin`]).
fn cube_bit(d: [i32; 3]) -> usize {
    ((d[0] + 2) + 5 * ((d[1] + 2) + 5 * (d[2] + 2))) as usize
}

/// The occupied cells of the 5 x 5 x 5 cube around lattice cell `ca`, as bits of a u128
/// ([`cube_bit`]): the key of a row of [`assembled_gershgorin`].
fn cube_occupancy(cloud: &ParticleCloud, ca: [usize; 3]) -> u128 {
    let mut key = 0u128;
    for dz in -2..=2 {
        for dy in -2..=2 {
            for dx in -2..=2 {
                if cloud.lattice().get_offset(ca, [dx, dy, dz]).is_some() {
                    key |= 1u128 << cube_bit([dx, dy, dz]);
                }
            }
        }
    }
    key
}

/// Adds term `i`'s 3x3 stiffness blocks `K_ab` (row of particle `a`, every node `b` of the
/// term: its owner then its neighbours `nbr_i`, at cells `cells` relative to `a`) into `acc`
/// (by [`cube_bit`]): elastic `V (lambda g_a (x) g_b + mu g_b (x) g_a + mu (g_a . g_b) I)`
/// plus the hourglass part; `rest`: the term's rest data.
fn add_term_blocks(
    cloud: &ParticleCloud,
    rest: &TermRest,
    nbr_i: &[u32],
    a: u32,
    cells: &[[i32; 3]],
    acc: &mut [[f64; 9]],
) {
    let mat = cloud.material();
    let (lam, mu) = (mat.lambda_pa, mat.mu_pa);
    let v = cloud.volume_m3();
    let ki = nbr_i.len();
    let mut g = [DVec3::ZERO; MAX_STENCIL + 1];
    let mut cb_qa = [0.0f64; MAX_STENCIL];
    // Nodes of term i: the owner (g = -g_sum), then its neighbours.
    g[0] = -rest.g_sum;
    let mut alpha = 0;
    for (m, &q) in nbr_i.iter().enumerate() {
        g[m + 1] = rest.g[m];
        if q == a {
            alpha = m + 1;
        }
    }
    let ga = g[alpha];
    // Hourglass: sum_q c_q B_qa B_qb = g_b . Y - [b = q] c_q B_qa + [b = owner]
    // sum_q c_q B_qa, with Y = sum_q c_q B_qa X_q.
    let hourglass = rest.hourglass_n_per_m[..ki].iter().any(|&c| c != 0.0);
    let mut y = DVec3::ZERO;
    let mut cb_sum = 0.0;
    if hourglass {
        for (q, cb) in cb_qa[..ki].iter_mut().enumerate() {
            let b = ga.dot(rest.offset_m[q])
                + if alpha == q + 1 { -1.0 } else { 0.0 }
                + if alpha == 0 { 1.0 } else { 0.0 };
            *cb = rest.hourglass_n_per_m[q] * b;
            y += rest.offset_m[q] * *cb;
            cb_sum += *cb;
        }
    }
    for beta in 0..=ki {
        let gb = g[beta];
        let mut blk = [0.0f64; 9];
        let dot = ga.dot(gb);
        for c in 0..3 {
            for r in 0..3 {
                blk[3 * c + r] = v * (lam * ga[r] * gb[c] + mu * gb[r] * ga[c])
                    + if r == c { v * mu * dot } else { 0.0 };
            }
        }
        if hourglass {
            let h = gb.dot(y) + if beta == 0 { cb_sum } else { -cb_qa[beta - 1] };
            for d in [0, 4, 8] {
                blk[d] += h;
            }
        }
        let slot = &mut acc[cube_bit(cells[beta])];
        for (s, b) in slot.iter_mut().zip(blk) {
            *s += b;
        }
    }
}

/// The largest row of the summed-norm Gershgorin bound over the cloud, N/m (the bound before
/// issue 13: elastic block norms `V c |g_a| |g_b|`, `c = lambda + 2 mu`, and the hourglass
/// blocks, each term on its own).
fn summed_norm_gershgorin(cloud: &ParticleCloud) -> Result<f64, ModelError> {
    let n = cloud.len();
    let mat = cloud.material();
    let c = mat.lambda_pa.max(0.0) + 2.0 * mat.mu_pa;
    let v = cloud.volume_m3();
    let mut row = vec![0.0f64; n];
    let mut nbr = [0u32; MAX_STENCIL];
    let mut rest = Box::<TermRest>::default();
    let mut coef = [0.0f64; MAX_STENCIL + 1];
    for p in 0..n as u32 {
        let k = cloud.neighbours(p, &mut nbr);
        cloud.term_rest(p, &nbr[..k], &mut rest)?;
        // Elastic: row sums of |K_ab| <= V c |g_a| (sum_b |g_b|), the owner's g being -g_sum.
        let total: f64 = rest.g[..k].iter().map(|g| g.length()).sum::<f64>() + rest.g_sum.length();
        for m in 0..k {
            row[nbr[m] as usize] += v * c * rest.g[m].length() * total;
        }
        row[p as usize] += v * c * rest.g_sum.length() * total;
        // Hourglass: e_q = sum_m B_qm x'_m, B_qm = g_m . X_q - delta_qm, owner -sum_m B_qm.
        for q in 0..k {
            let cq = rest.hourglass_n_per_m[q];
            if cq == 0.0 {
                continue;
            }
            let mut owner = 0.0;
            let mut abs_sum = 0.0;
            for (m, (g, out)) in rest.g[..k].iter().zip(&mut coef[..k]).enumerate() {
                let b = g.dot(rest.offset_m[q]) - if m == q { 1.0 } else { 0.0 };
                *out = b;
                owner -= b;
                abs_sum += b.abs();
            }
            abs_sum += owner.abs();
            for (q, c) in nbr[..k].iter().zip(&coef[..k]) {
                row[*q as usize] += cq * c.abs() * abs_sum;
            }
            row[p as usize] += cq * owner.abs() * abs_sum;
        }
    }
    Ok(row.iter().fold(0.0f64, |a, &r| a.max(r)))
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::TermBlock;
    use crate::material::{MaterialModel, MaterialParams};
    use crate::meshfree::{KernelKind, Lattice, MeshfreeParams, MeshfreeVariant, ParticleCloud};

    /// The stencil loop (AVX2 where the CPU has it, and the plain lanes; the 26-cell cube's
    /// specialised loops and the general stencil's pair loops) gives the general loop's
    /// forces to single-precision round-off (1e-5 of the largest force; 1.8e-6 measured):
    /// both variants, three laws, a ragged particle set (a ball with holes, so owners miss
    /// neighbours and groups have padding lanes), a partial set of terms, a large smooth
    /// deformation (displacements of a few millimetres at a 1 mm spacing) plus noise.
    #[test]
    fn the_stencil_layout_takes_the_axis_and_shift_with_the_fewest_groups() {
        // A cube of 8 cells a side at cells 3..=10 and a small one at 0..=1 that sets the
        // bounding box: along every axis the cube's rows start three cells past the box, so
        // groups of eight cells aligned to the box split every row in two and only a shift of
        // five fits each row in one group.
        let (n, s) = (11, 1e-3);
        let params = MeshfreeParams {
            variant: MeshfreeVariant::Corrected,
            kernel: KernelKind::default_for(MeshfreeVariant::Corrected),
            spacing_m: s,
            smoothing_ratio: 1.0,
            hourglass_coefficient: 0.5,
        };
        let lattice = Lattice::new(DVec3::ZERO, s, [n, n, n], params.support_m());
        let cells: Vec<u32> = (0..(n * n * n) as u32)
            .filter(|&i| {
                let c = [i as usize % n, i as usize / n % n, i as usize / (n * n)];
                c.iter().all(|&v| v >= 3) || c.iter().all(|&v| v <= 1)
            })
            .collect();
        let material = MaterialParams::from_youngs(14.5e3, 0.45, 1060.0);
        let cloud = ParticleCloud::new(lattice, cells, params, material).expect("cloud");
        let groups = |forced: Option<(usize, usize)>| {
            let mut block = TermBlock::new(&cloud, cloud.len());
            for p in (0..cloud.len() as u32).filter(|p| p % 5 != 3) {
                let _ = block.push(&cloud, p);
            }
            block.set_stencil_loop(true);
            if let Some((axis, shift)) = forced {
                block.stencil.force_vector_axis(axis, shift);
            }
            let mut f = vec![DVec3::ZERO; cloud.len()];
            block.add_forces(&cloud, cloud.rest_m(), &mut f);
            block.stencil_layout().expect("a stencil layout").1
        };
        let forced: Vec<usize> = (0..3)
            .flat_map(|axis| (0..crate::simd::LANES8).map(move |shift| (axis, shift)))
            .map(|c| groups(Some(c)))
            .collect();
        let fewest = *forced.iter().min().expect("24 layouts");
        let most = *forced.iter().max().expect("24 layouts");
        assert!(
            fewest < most,
            "every layout has {fewest} groups: the test shows nothing"
        );
        assert_eq!(groups(None), fewest, "groups by (axis, shift): {forced:?}");
    }

    #[test]
    fn stencil_loop_matches_the_general_loop() {
        let n = 11;
        let s = 1e-3;
        for variant in [MeshfreeVariant::Seed, MeshfreeVariant::Corrected] {
            for model in [
                MaterialModel::StVenantKirchhoff,
                MaterialModel::StableNeoHookean,
                MaterialModel::Corotational,
            ] {
                if variant == MeshfreeVariant::Seed && model != MaterialModel::StVenantKirchhoff {
                    continue; // the seed variant is StVK whatever the law
                }
                let params = MeshfreeParams {
                    variant,
                    kernel: KernelKind::default_for(variant),
                    spacing_m: s,
                    smoothing_ratio: 1.0,
                    hourglass_coefficient: 0.5,
                };
                let lattice = Lattice::new(DVec3::ZERO, s, [n, n, n], params.support_m());
                let c = (n as f64 - 1.0) / 2.0;
                let cells: Vec<u32> = (0..(n * n * n) as u32)
                    .filter(|&i| {
                        let (x, y, z) = (i as usize % n, i as usize / n % n, i as usize / (n * n));
                        let r2 = (x as f64 - c).powi(2)
                            + (y as f64 - c).powi(2)
                            + (z as f64 - c).powi(2);
                        r2 <= c * c && (x * 7 + y * 3 + z * 5) % 11 != 0
                    })
                    .collect();
                let mut material = MaterialParams::from_youngs(14.5e3, 0.45, 1060.0);
                material.model = model;
                let cloud = ParticleCloud::new(lattice, cells, params, material).expect("cloud");
                let x: Vec<DVec3> = cloud
                    .rest_m()
                    .iter()
                    .enumerate()
                    .map(|(i, p)| {
                        let h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                        let noise = DVec3::new(
                            (h >> 40) as f64 / (1u64 << 24) as f64 - 0.5,
                            ((h >> 20) & 0xF_FFFF) as f64 / (1u64 << 20) as f64 - 0.5,
                            (h & 0xF_FFFF) as f64 / (1u64 << 20) as f64 - 0.5,
                        );
                        DVec3::new(
                            p.x * (1.0 + 0.2 * (p.y / s * 0.3).sin()),
                            p.y - 0.15 * p.z,
                            0.9 * p.z + 0.1 * p.x,
                        ) + noise * (0.1 * s)
                    })
                    .collect();
                let mut forces = Vec::new();
                // Modes: general loop; stencil AVX2 and plain, cube loops along each axis
                // (groups shifted by 3, 6, 1, 4, 7 and 2 cells along it); stencil AVX2 and
                // plain, pair loops.
                for mode in 0..9 {
                    let mut block = TermBlock::new(&cloud, cloud.len());
                    for p in (0..cloud.len() as u32).filter(|p| p % 5 != 3) {
                        // Degenerate neighbourhoods (corrected) are refused, as in the body.
                        let _ = block.push(&cloud, p);
                    }
                    block.set_stencil_loop(mode != 0);
                    if mode % 2 == 0 && mode != 0 {
                        block.stencil.plain_lanes_only();
                    }
                    if (1..7).contains(&mode) {
                        block
                            .stencil
                            .force_vector_axis((mode - 1) / 2, 3 * mode % 8);
                    } else if mode >= 7 {
                        block.stencil.pair_loops_only();
                    }
                    let mut f = vec![DVec3::splat(7.0); cloud.len()];
                    block.add_forces(&cloud, &x, &mut f);
                    assert_eq!(block.stencil_layout().is_some(), mode != 0);
                    forces.push(f);
                }
                let scale = forces[0]
                    .iter()
                    .fold(0.0f64, |a, f| a.max((*f - DVec3::splat(7.0)).length()));
                assert!(scale > 0.0);
                for (mode, f) in forces.iter().enumerate().skip(1) {
                    let err = f
                        .iter()
                        .zip(&forces[0])
                        .fold(0.0f64, |a, (u, v)| a.max((*u - *v).length()));
                    assert!(
                        err <= 1e-5 * scale,
                        "{variant:?} {model:?} mode {mode}: {err:e} of {scale:e}"
                    );
                }
            }
        }
    }
}
