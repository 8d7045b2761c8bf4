//! [`ParticleCloud`]: every particle of a meshfree body at rest (lattice cell, rest position,
//! volume, mass) with the neighbour grid, and the rest data of each particle's energy term
//! ([`ParticleCloud::term_rest`]): the kernel-gradient weights `g_ij` of the deformation
//! gradient `F_i = sum_j (x_j - x_i) (x) g_ij`, the hourglass stiffnesses and the rest strain.
//!
//! **Deformation gradient (seed 000 eq. 25, differentiated).** With `X_ij = X_j - X_i`,
//! `r = |X_ij|` and the kernel slope `W'(r) < 0`, the kernel-sum gradient is
//! `F_i = sum_j (x_j - x_i) (x) w_ij`, `w_ij = V_j (-W'(r) / r) X_ij` (eq. 25 with `x = sum x_j
//! W V_j` and its gradient taken in the difference form, which is exact for constants). Its
//! value for the rest positions is the moment matrix `A_i = sum_j X_ij (x) w_ij`.
//!
//! - `seed`: `g_ij = w_ij / alpha`, where `alpha` makes `A = I` for a particle with the full
//!   stencil (the lattice sum of a normalised kernel is `alpha I`, not `I`, for the few
//!   neighbours of a real stencil; without it every particle would be prestrained at rest).
//!   Near boundaries `A_i != I`; the Green strain is measured from the rest value,
//!   `E_i = (F_i^T F_i - A_i^T A_i) / 2` (else the body would be stressed at rest), so rigid
//!   motions are free of stress but an affine field is not reproduced there.
//! - `corrected`: `g_ij = L_i^T w_ij` with the Bonet-Lok correction `L_i = A_i^-1` (Bonet &
//!   Lok 1999, CMAME 180:97), so `F_i` is exact for every affine field (first-order
//!   consistency, the patch test).
//!
//! **Hourglass control (corrected, after Ganzenmueller 2015, CMAME 286:87).** The corrected
//! gradient does not see fields that are affine over each stencil but not globally (on a
//! lattice, the checkerboard `u_j = (-1)^(i+j+k) u` has `F = I` everywhere): zero-energy modes.
//! Ganzenmueller penalises the pair error `e_ij = F_i X_ij - x_ij` against the particle's own
//! affine prediction with a stiffness `alpha E V_i V_j W_ij / r^2`; we use the same error and
//! stiffness in energy form, `E_hg = sum_i sum_j c_ij |e_ij|^2 / 2`, `c_ij = kappa E V_i V_j
//! W(r) / r^2` (N/m), so the force is its exact gradient (conservative, momentum-conserving),
//! and it vanishes for every affine field, rigid motions included.
//!
//! Neighbours: [`super::lattice`] finds the neighbours; [`super::block`] runs the terms.

use glam::{DMat3, DVec3};

use super::kernel::Kernel;
use super::lattice::Lattice;
use super::{MeshfreeParams, MeshfreeVariant};
use crate::ModelError;
use crate::material::MaterialParams;

/// Largest number of neighbours of a particle (stencil size) the run-time arrays support.
pub const MAX_STENCIL: usize = 64;

/// Condition number of the moment matrix above which a particle's neighbourhood is too
/// degenerate for the corrected gradient (a particle on a sharp edge with its neighbours
/// nearly in a plane).
pub const MAX_MOMENT_CONDITION: f64 = 1e3;

/// The rest data of one particle's energy term (module documentation). Arrays hold
/// `count` entries in the order of the neighbours given to [`ParticleCloud::term_rest`].
#[derive(Debug, Clone)]
pub struct TermRest {
    /// Number of neighbours.
    pub count: usize,
    /// `g_ij`, 1/m.
    pub g: [DVec3; MAX_STENCIL],
    /// Hourglass stiffness `c_ij`, N/m (zero in the seed variant).
    pub hourglass_n_per_m: [f64; MAX_STENCIL],
    /// Rest offsets `X_ij = X_j - X_i`, m.
    pub offset_m: [DVec3; MAX_STENCIL],
    /// `sum_j g_ij`, 1/m.
    pub g_sum: DVec3,
    /// Rest Green strain of the kernel estimate, `(A^T A - I) / 2` (seed; zero when corrected).
    pub rest_strain: DMat3,
}

impl Default for TermRest {
    fn default() -> Self {
        Self {
            count: 0,
            g: [DVec3::ZERO; MAX_STENCIL],
            hourglass_n_per_m: [0.0; MAX_STENCIL],
            offset_m: [DVec3::ZERO; MAX_STENCIL],
            g_sum: DVec3::ZERO,
            rest_strain: DMat3::ZERO,
        }
    }
}

/// Every particle of a meshfree body at rest with its neighbour grid (module documentation).
#[derive(Debug, Clone)]
pub struct ParticleCloud {
    lattice: Lattice,
    /// Lattice cell (linear index) of each particle.
    cell: Vec<u32>,
    rest_m: Vec<DVec3>,
    volume_m3: f64,
    mass_kg: f64,
    kernel: Kernel,
    params: MeshfreeParams,
    material: MaterialParams,
    /// Seed variant: `1 / alpha` (module documentation); 1 when corrected.
    normalisation: f64,
}

impl ParticleCloud {
    /// A cloud with one particle at each of the lattice cells `cells` (linear indices, each at
    /// most once) of `lattice`, each of volume `s^3` and mass `rho s^3` (the seed's uniform
    /// grid), with the kernel and variant of `params` and the material `material`. The lattice
    /// must have been made with the support radius of `params` ([`MeshfreeParams::support_m`]).
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `particles.smoothing_ratio` when the stencil holds
    /// fewer than 6 or more than [`MAX_STENCIL`] offsets.
    pub fn new(
        mut lattice: Lattice,
        cells: Vec<u32>,
        params: MeshfreeParams,
        material: MaterialParams,
    ) -> Result<Self, ModelError> {
        let n = lattice.stencil().len();
        if !(6..=MAX_STENCIL).contains(&n) {
            return Err(ModelError::field(
                "particles.smoothing_ratio",
                format!(
                    "gives {n} neighbours per particle; the meshfree terms need 6 to {MAX_STENCIL}"
                ),
            ));
        }
        let s = lattice.spacing_m();
        let rest_m = cells
            .iter()
            .map(|&c| lattice.position(lattice.cell(c as usize)))
            .collect();
        for (p, &c) in cells.iter().enumerate() {
            let ijk = lattice.cell(c as usize);
            lattice.set(ijk, p as u32);
        }
        let kernel = params.kernel();
        let volume = s * s * s;
        let mut cloud = Self {
            lattice,
            cell: cells,
            rest_m,
            volume_m3: volume,
            mass_kg: material.density_kg_per_m3 * volume,
            kernel,
            params,
            material,
            normalisation: 1.0,
        };
        if params.variant == MeshfreeVariant::Seed {
            // The moment matrix of a full stencil is alpha I by the cubic symmetry.
            let a = cloud.moment_of_offsets(
                cloud
                    .lattice
                    .stencil()
                    .iter()
                    .map(|d| DVec3::new(d[0] as f64, d[1] as f64, d[2] as f64) * s),
            );
            cloud.normalisation = 3.0 / (a.x_axis.x + a.y_axis.y + a.z_axis.z);
        }
        Ok(cloud)
    }

    /// Number of particles.
    #[inline]
    pub fn len(&self) -> usize {
        self.rest_m.len()
    }

    /// Whether the cloud has no particle.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.rest_m.is_empty()
    }

    /// Rest positions, m.
    #[inline]
    pub fn rest_m(&self) -> &[DVec3] {
        &self.rest_m
    }

    /// Volume of every particle, `s^3`, m^3.
    #[inline]
    pub fn volume_m3(&self) -> f64 {
        self.volume_m3
    }

    /// Mass of every particle, `rho s^3`, kg.
    #[inline]
    pub fn mass_kg(&self) -> f64 {
        self.mass_kg
    }

    /// The kernel.
    #[inline]
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// The meshfree parameters.
    #[inline]
    pub fn params(&self) -> &MeshfreeParams {
        &self.params
    }

    /// The material.
    #[inline]
    pub fn material(&self) -> &MaterialParams {
        &self.material
    }

    /// The neighbour grid.
    #[inline]
    pub fn lattice(&self) -> &Lattice {
        &self.lattice
    }

    /// Largest neighbour count (the stencil size).
    #[inline]
    pub fn stencil_len(&self) -> usize {
        self.lattice.stencil().len()
    }

    /// Lattice cell of particle `p`.
    #[inline]
    pub fn cell_of(&self, p: u32) -> [usize; 3] {
        self.lattice.cell(self.cell[p as usize] as usize)
    }

    /// Writes the neighbours of particle `p` (the occupied stencil cells, in stencil order)
    /// into `out` and returns their number. Allocation-free.
    ///
    /// # Panics
    /// If `out` is shorter than the stencil.
    pub fn neighbours(&self, p: u32, out: &mut [u32]) -> usize {
        let ijk = self.cell_of(p);
        let mut n = 0;
        for d in self.lattice.stencil() {
            if let Some(q) = self.lattice.get_offset(ijk, *d) {
                out[n] = q;
                n += 1;
            }
        }
        n
    }

    /// The particle at lattice cell `ijk`, if any.
    pub fn particle_at(&self, ijk: [usize; 3]) -> Option<u32> {
        self.lattice.get_offset(ijk, [0, 0, 0])
    }

    /// `sum_j X_j (x) V (-W'(r)/r) X_j` over the given rest offsets (the uncorrected, not yet
    /// normalised moment matrix).
    fn moment_of_offsets(&self, offsets: impl Iterator<Item = DVec3>) -> DMat3 {
        let mut a = DMat3::ZERO;
        for d in offsets {
            let r = d.length();
            let w = d * (self.volume_m3 * -self.kernel.slope(r) / r);
            a += outer(d, w);
        }
        a
    }

    /// The moment matrix `A_p` of particle `p` over its neighbours `nbr` (seed-normalised) and
    /// its condition number (infinite when singular).
    pub fn moment(&self, p: u32, nbr: &[u32]) -> (DMat3, f64) {
        let xp = self.rest_m[p as usize];
        let a = self.moment_of_offsets(nbr.iter().map(|&q| self.rest_m[q as usize] - xp))
            * self.normalisation;
        (a, condition(&a))
    }

    /// Fills `out` with the rest data of the energy term of particle `p` whose neighbours are
    /// `nbr` (module documentation). Allocation-free.
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] when the corrected variant's moment matrix is singular or its
    /// condition number exceeds [`MAX_MOMENT_CONDITION`] (the preprocessing removes such
    /// particles first).
    ///
    /// # Panics
    /// If `nbr` is longer than [`MAX_STENCIL`].
    pub fn term_rest(&self, p: u32, nbr: &[u32], out: &mut TermRest) -> Result<(), ModelError> {
        let xp = self.rest_m[p as usize];
        let (a, cond) = self.moment(p, nbr);
        out.count = nbr.len();
        let corrected = self.params.variant == MeshfreeVariant::Corrected;
        let l_t = if corrected {
            if !(cond <= MAX_MOMENT_CONDITION) {
                return Err(ModelError::InvalidMesh(format!(
                    "particle {p} at {xp} has a degenerate neighbourhood (moment matrix condition {cond:.3e})"
                )));
            }
            a.inverse().transpose()
        } else {
            DMat3::IDENTITY
        };
        let e_young = self.material.youngs_modulus_pa();
        let kappa = if corrected {
            self.params.hourglass_coefficient
        } else {
            0.0
        };
        let mut g_sum = DVec3::ZERO;
        for (k, &q) in nbr.iter().enumerate() {
            let d = self.rest_m[q as usize] - xp;
            let g = l_t * self.pair_weight(d);
            out.g[k] = g;
            out.offset_m[k] = d;
            let r = d.length();
            out.hourglass_n_per_m[k] =
                kappa * e_young * self.volume_m3 * self.volume_m3 * self.kernel.value(r) / (r * r);
            g_sum += g;
        }
        out.g_sum = g_sum;
        out.rest_strain = if corrected {
            DMat3::ZERO
        } else {
            (a.transpose() * a - DMat3::IDENTITY) * 0.5
        };
        Ok(())
    }

    /// The uncorrected (seed-normalised) kernel-gradient weight `w_ij = V (-W'(r) / r) X_ij`
    /// of a pair at rest offset `offset_m = X_ij` (m), 1/m (module documentation). On the
    /// lattice it depends on the stencil offset only, which the stencil loop
    /// (`super::stencil`) uses.
    #[inline]
    pub fn pair_weight(&self, offset_m: DVec3) -> DVec3 {
        let r = offset_m.length();
        offset_m * (self.volume_m3 * -self.kernel.slope(r) / r * self.normalisation)
    }

    /// The hourglass stiffness `c_ij` of a pair at rest offset `offset_m` (m), N/m (zero in
    /// the seed variant).
    #[inline]
    pub fn hourglass_stiffness(&self, offset_m: DVec3) -> f64 {
        if self.params.variant == MeshfreeVariant::Corrected {
            let r = offset_m.length();
            self.params.hourglass_coefficient
                * self.material.youngs_modulus_pa()
                * self.volume_m3
                * self.volume_m3
                * self.kernel.value(r)
                / (r * r)
        } else {
            0.0
        }
    }

    /// Heap memory, bytes.
    pub fn memory_bytes(&self) -> usize {
        self.lattice.memory_bytes() + self.cell.capacity() * 4 + self.rest_m.capacity() * 24
    }
}

/// `a b^T` (the column of index k is `a b_k`).
#[inline]
pub fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// Condition number of a symmetric positive semi-definite 3x3 matrix in the Frobenius norm,
/// `|A| |A^-1|` (infinite when singular).
pub fn condition(a: &DMat3) -> f64 {
    let det = a.determinant();
    if !(det.abs() > 0.0) {
        return f64::INFINITY;
    }
    let fro = |m: &DMat3| {
        (m.x_axis.length_squared() + m.y_axis.length_squared() + m.z_axis.length_squared()).sqrt()
    };
    fro(a) * fro(&a.inverse())
}

impl MeshfreeParams {
    /// The kernel, with smoothing length `smoothing_ratio * spacing_m`.
    pub fn kernel(&self) -> Kernel {
        Kernel {
            kind: self.kernel,
            smoothing_length_m: self.smoothing_ratio * self.spacing_m,
        }
    }

    /// Support radius `2 h`, m.
    pub fn support_m(&self) -> f64 {
        2.0 * self.smoothing_ratio * self.spacing_m
    }
}
