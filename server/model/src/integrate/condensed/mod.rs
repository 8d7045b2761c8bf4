//! Backward Euler on a contact-local *active region* with the rest of the body condensed
//! statically (Guyan reduction): the haptic loop computes only what the contact needs.
//!
//! A probe pressing an organ deforms it strongly near the contact and barely elsewhere. The
//! body is split by an [`ActiveRegion`] (a ball around the expected contact):
//!
//! - **active elements**: every tetrahedron with a (corner) node inside the ball. They keep the full
//!   nonlinear material, the viscous stress, the lumped masses and the dynamics;
//! - **far elements**: all others, linearised at rest and massless (quasi-static). Their
//!   stiffness is condensed onto the *interface* nodes `G` (active nodes that also belong to a
//!   far element): with `F` the far-only free components,
//!   `S = K_GG - K_GF K_FF^-1 K_FG` (Guyan, AIAA J. 3 (1965) 380),
//!   so the far part acts on the active region exactly as the linear elastic body it is, at
//!   the cost of a dense `3|G| x 3|G|` matrix-vector product per tick.
//!
//! This is the hybrid of Cotin, Delingette & Ayache (The Visual Computer 16 (2000) 437): a
//! nonlinear model where the tool acts, a precomputed linear one elsewhere; in the spirit of
//! seed 001's two-layer model (a detailed model only where the tool acts) and seed 003's haptic
//! subdivision (level of detail at the contact), the work follows the contact. Each servo tick
//! takes one backward Euler step (see [`crate::integrate`] for the linearisation) with the
//! matrix frozen at rest and factorised once, solved for the new velocity `v'` directly:
//!
//! `(A + gamma U U^T) v' = M v + h (f_el(x) + f_ext - S u_G - U phi0)`,
//! `A = M (1 + alpha h) + h D_0 + h^2 (c K_0 + S)`, `x' = x + h v'`,
//!
//! `K_0`, `D_0` the rest stiffness and viscous matrices of the active elements (for the
//! viscous stress of seed 000 eq. 10-11, the stiffness with `(lambda, mu) -> (2 phi, 2 psi)`),
//! `c` the [`ActiveRegion::stiffness_margin`], `f_el` the active elements' exact nonlinear
//! elastic forces. At rest (`v = v' = 0`) the equation is `f = 0` whatever the matrix, so
//! equilibria are exact for the split model and the frozen matrix only changes the path to
//! them (a modified Newton step per tick). Because `v'` is solved for directly (not `dv` from
//! `b - A v`), an inexact solve cannot shift an equilibrium either, which is why the factor is
//! computed in single precision and the tick sweeps it in half precision
//! ([`crate::linalg::supernodal`]: a quarter of the memory a double-precision factor would stream per
//! tick; the rounding moves the default `lv`'s step by about 1e-3, checked at construction
//! against `HALF_MAX_DEVIATION`). The probe's term
//! `h^2 A^T C A` ([`ContactCoupling`]: the patch's coupling, or the implicit sphere's faces) is
//! added exactly by Woodbury, with `A^-1 A^T` from columns precomputed for the active touchable
//! nodes ([`CondensedSolver::prepare_contact`]); a one-row coupling over many nodes (the
//! patch on a fine mesh) instead sweeps the half-precision factor forward once for both
//! right-hand sides and backward once ([`PAIRED_SWEEP_MIN_RATIO`]). The factor is faer's sparse
//! Cholesky
//! (supernodal, nested-dissection ordering), solved by [`crate::linalg::supernodal`]'s sweep (faer's
//! solve for a simplicial factor) with its workspace allocated at construction, so
//! [`CondensedSolver::step`] allocates nothing.
//!
//! **Relaxation.** The frozen matrix is a modified Newton step: where the tangent under the
//! probe outgrows `2 c K_0` (St. Venant-Kirchhoff pressed 5 mm or more into the LV's 3 mm wall,
//! whose tangent there even turns indefinite) the step overshoots and the tick settles into a
//! two-tick oscillation (nodes flipping by 0.3 mm, the force between 48 and 65 mN at 5 mm on
//! the default mesh). A velocity field that reverses from one tick to the next (cosine with the
//! previous one below [`REVERSAL_COSINE`], some component faster than
//! [`REVERSAL_MIN_SPEED_M_PER_S`]) is that overshoot, not motion (the body's own modes take
//! many ticks per period), so the solved velocity is scaled by a factor that halves on each
//! such tick (down to [`MIN_RELAXATION`]) and grows back by [`RELAXATION_RECOVERY`] per tick
//! otherwise: an under-relaxed Newton iteration. It only removes velocity, and `v' = 0` still
//! needs `f = 0`, so equilibria are unchanged; a shallow press triggers it once at most, where
//! the device stops (docs/decisions.md, "The whole-body rest factor"). The other overshoot is
//! one-sided: St. Venant-Kirchhoff elements inverted under a deep dent (a 50 mN point load
//! on a probe-sized patch dents the default `lv`'s wall 6 mm) stay inverted after the load
//! ends, then snap back, and the frozen matrix turns the snap into a runaway (nodal speeds
//! from 0.4 to 2.4 m/s in one tick, then to 100 m/s); so a tick whose fastest velocity
//! component exceeds [`SNAP_MIN_SPEED_M_PER_S`] and [`SNAP_GROWTH`] times the previous tick's
//! is relaxed the same way (docs/decisions.md, "Relaxing the snap of inverted elements").
//!
//! Limits: the ball is fixed when the model is built (a contact outside it is not seen: the
//! caller restricts the touchable surface, [`CondensedSolver::is_active_triangle`]), unless it
//! follows the probe ([`ActiveRegion::follow`], [`crate::integrate::follow`]: successive
//! solvers, the state handed over by [`CondensedSolver::hand_over`]); far
//! elements are linear (small rotations), so the ball must contain every element that strains
//! or rotates appreciably; external loads act on active nodes only. The far part's boundary
//! nodes (what viewers draw) are refreshed from the interface a slice per tick
//! ([`SURFACE_REFRESH_TICKS`]) through the far map `-(K_FF^-1 K_FG)`, stored in half
//! precision (each far node placed to about `3e-4` of the interface displacement); all far
//! positions are recovered on request ([`CondensedSolver::recover_far_field`], one sparse
//! solve, or the map of a following region).
//! With strain smoothing, each part builds its smoothing domains from its own elements, so an
//! edge on the interface has one domain per side.

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::sparse::SparseColMat;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky};
use faer::{Conj, Mat, Par, Side};
use glam::DVec3;

use crate::linalg::ordering::{SparseCholesky, symbolic_cholesky};
use crate::linalg::supernodal::{HalfFactor, SupernodalSolve};

use crate::ModelError;
use crate::contact::ContactCoupling;
use crate::contact::coupling::{MAX_COUPLING_ROWS, cholesky_in_place, cholesky_solve};
use crate::element::FemModel;
use crate::element::tangent::cell_tangent_blocks_of;
use crate::material::{MaterialModel, MaterialParams};
use crate::mesh::TetMesh;

/// Largest memory of the contact columns [`CondensedSolver::prepare_contact`] precomputes:
/// 512 MiB (`lv_h1.msh` whole-body: 268 MB; a 50 000-element scene's touchable surface would
/// take several GB and minutes of solves). Beyond it a tick in contact solves twice.
pub const PREPARED_CONTACT_MAX_BYTES: usize = 512 << 20;

/// The contact-local region of a condensed model: every tetrahedron with a corner node within
/// `radius_m` of `centre_m` (rest positions) is active.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActiveRegion {
    /// Centre, m (rest configuration).
    pub centre_m: DVec3,
    /// Radius, m (> 0).
    pub radius_m: f64,
    /// Factor `c >= 1` on the active elements' rest stiffness in the frozen tick matrix
    /// (`h^2 c K_0`; default [`DEFAULT_STIFFNESS_MARGIN`]). The matrix is frozen at rest while
    /// the tangent of a strained body grows (St. Venant-Kirchhoff: by `(3 lambda^2 - 1) / 2` at
    /// stretch `lambda`); a step with a matrix softer than half the tangent overshoots into an
    /// oscillation. A margin only slows the approach to equilibrium in the soft directions; the
    /// equilibrium itself does not depend on it. Near incompressibility needs more (the
    /// measured choices: `docs/decisions.md`, "Contact-local condensation").
    pub stiffness_margin: f64,
    /// Whether the region follows the probe ([`crate::integrate::follow`]): regions are then
    /// re-centred on the touchable surface near the device, prepared off the servo thread
    /// and swapped in at tick boundaries, and each keeps the far-field rows its successors
    /// need ([`CondensedSolver::hand_over`]).
    pub follow: bool,
}

impl ActiveRegion {
    /// A fixed region holding every node of `rest` (m), hence every element: a condensed
    /// solver built on it condenses nothing and is backward Euler with the rest matrix
    /// factorised once ([`crate::integrate::LinearSolver::RestCholesky`]).
    pub fn whole_body(rest: &[DVec3], stiffness_margin: f64) -> Self {
        let (lo, hi) = rest.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let centre_m = if rest.is_empty() {
            DVec3::ZERO
        } else {
            (lo + hi) / 2.0
        };
        let radius_m = rest
            .iter()
            .map(|p| p.distance(centre_m))
            .fold(0.0, f64::max);
        Self {
            centre_m,
            // Every node strictly inside, whatever the rounding.
            radius_m: radius_m * (1.0 + 1e-9) + 1e-12,
            stiffness_margin,
            follow: false,
        }
    }
}

/// A following region is swapped in when the device is within this many radii of its centre
/// (or nearer to it than to the current one; [`crate::integrate::follow`]).
pub const FOLLOW_NEAR_RADII: f64 = 0.5;

/// A following region's next centre leads the device by its velocity times the preparation
/// time, at most this many radii ([`crate::integrate::follow`]).
pub const FOLLOW_LEAD_RADII: f64 = 1.0;

/// The condensed boundary nodes (what viewers see of the far part) are refreshed from the
/// interface over this many ticks, a slice per tick ([`CondensedSolver::step`]): 32 ms, about
/// one frame of a 30 Hz viewer. (On 100 000 tetrahedra the far surface has about 18 000
/// components; refreshing them over 16 ticks cost more per tick than the Schur product.)
pub const SURFACE_REFRESH_TICKS: usize = 32;

/// Most multiply-adds one tick spends on the far-surface refresh (rows times interface
/// components): beyond it the refresh takes more than [`SURFACE_REFRESH_TICKS`] ticks
/// ([`CondensedSolver::surface_refresh_ticks`]). Its rows are streamed from main memory (the
/// map of a following region is tens of megabytes): `lv_100k_condensed` (18 936 surface rows
/// of 792) refreshes in 60 ticks instead of 32, 0.5 MB per tick.
pub const SURFACE_REFRESH_MAX_MACS: usize = 1 << 18;

/// Default [`ActiveRegion::stiffness_margin`].
pub const DEFAULT_STIFFNESS_MARGIN: f64 = 2.0;

/// The solved velocity field counts as reversed when its cosine with the previous tick's is
/// below this (module documentation, "Relaxation").
pub const REVERSAL_COSINE: f64 = -0.5;

/// ... and its fastest component exceeds this, m/s (0.1 mm/s: below it a reversal is
/// round-off at rest).
pub const REVERSAL_MIN_SPEED_M_PER_S: f64 = 1e-4;

/// A solved velocity component faster than [`SNAP_MIN_SPEED_M_PER_S`] and more than this many
/// times the fastest component of the velocity the body has (the previous tick's, as relaxed)
/// also counts as overshoot (module documentation, "Relaxation"). So while the factor is
/// small and the solve still asks for more than 0.2 m/s, the factor stays small: the body
/// approaches the equilibrium more slowly after a snap (after the demo's press with an 80 mN
/// dent, the force is back within 1e-6 of the press alone's 1.03 s after the load ends).
pub const SNAP_GROWTH: f64 = 3.0;

/// ... m/s: 0.2 mm per 1 ms tick, far above the speed at which a hand moves tissue (the
/// default `lv`'s shear wave speed `sqrt(mu / rho)` is 2.2 m/s).
pub const SNAP_MIN_SPEED_M_PER_S: f64 = 0.2;

/// Smallest factor on the solved velocity.
pub const MIN_RELAXATION: f64 = 1.0 / 16.0;

/// Growth of the factor per tick without reversal, back to 1.
pub const RELAXATION_RECOVERY: f64 = 1.1;

/// Sizes of a condensed model, for reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CondensedSizes {
    /// Active tetrahedra.
    pub active_tets: usize,
    /// Nodes of active tetrahedra.
    pub active_nodes: usize,
    /// Interface nodes (active nodes shared with far elements).
    pub interface_nodes: usize,
    /// Free components solved per tick.
    pub equations: usize,
    /// Stored entries of the Cholesky factor.
    pub factor_entries: usize,
}

/// Solve workspace, allocated once (a clone allocates its own).
struct Workspace {
    buffer: MemBuffer,
    req: StackReq,
}

impl Workspace {
    fn new(req: StackReq) -> Self {
        Self {
            buffer: MemBuffer::new(req),
            req,
        }
    }
}

impl Clone for Workspace {
    fn clone(&self) -> Self {
        Self::new(self.req)
    }
}

impl std::fmt::Debug for Workspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Workspace({:?})", self.req)
    }
}

/// Far field: the factor of `K_FF` and the coupling `K_FG`, to recover far displacements.
#[derive(Debug, Clone)]
struct FarField {
    /// Global component index `3 i + c` of each far equation.
    dofs: Vec<usize>,
    llt: Option<crate::linalg::ordering::SparseCholesky>,
    /// `K_FG` as (far equation, interface component, value).
    kfg: Vec<(usize, usize, f64)>,
}

/// Backward Euler on an active region with the far body condensed (module documentation).
/// Built once per scene; [`CondensedSolver::step`] is allocation-free.
#[derive(Debug, Clone)]
pub struct CondensedSolver {
    h: f64,
    region: ActiveRegion,
    /// The active elements (all nodes of the body, numbered as in the body; far nodes have no
    /// element here). Its forces are the active region's.
    active: FemModel,
    /// Per global component `3 i + c`: the equation number, or `usize::MAX` (far or clamped).
    eq: Vec<usize>,
    /// Global component of each equation.
    eq_dof: Vec<usize>,
    /// Lumped mass per equation, kg.
    mass: Vec<f64>,
    /// Global component of each interface component (free ones only).
    gamma_dof: Vec<usize>,
    /// `S`, N/m: its upper triangle, row `a` holding columns `a..g` from
    /// [`packed_row_start`], single precision (its product is a force; 1e-7 relative is far
    /// below the discretisation error). Each entry is read once per tick for both halves:
    /// the tick streams a quarter of the double-precision matrix.
    schur: Vec<f32>,
    /// Scratch: `S u_G`.
    su: Vec<f64>,
    /// Scratch: a one-row coupling's row `a` over the equations.
    a_row: Vec<f32>,
    /// Whether the CPU has AVX2 and FMA (the tick's vector loops use them then).
    avx2: bool,
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// Cholesky factor of `A`, single precision.
    factor: Vec<f32>,
    /// Factor on the solved velocity (module documentation, "Relaxation"), in
    /// `[MIN_RELAXATION, 1]`.
    relaxation: f64,
    /// Ticks whose velocity reversed (each halved `relaxation`).
    relaxed_ticks: u64,
    /// The tick's one-column solve ([`SupernodalSolve`]; `None` for a simplicial factor,
    /// solved by faer through `factor`).
    sweep: Option<SupernodalSolve>,
    /// `factor` in half precision for `sweep` (`factor` then holds its rounded values; `None`
    /// when the rounding would move the step too far, [`half_of`], and faer solves through
    /// `factor`).
    half: Option<HalfFactor>,
    stack: Workspace,
    /// Right-hand sides: the step's and the coupling's `U`.
    rhs: Mat<f32>,
    /// The step's right-hand side in double precision (with interface components only: a
    /// whole-body solver writes it straight into `rhs`).
    b: Vec<f64>,
    /// Per body node: its column block in `contact_z`, or `u32::MAX`
    /// ([`CondensedSolver::prepare_contact`]).
    contact_col: Vec<u32>,
    /// `A^-1 e` for the three components of every contact node: per node its three columns of
    /// `m` values one after the other (x, y, z).
    contact_z: Vec<f32>,
    /// Scratch: the probe's correction `A^-1 A^T s`, then the solved velocity `v'` before
    /// relaxation.
    z1: Vec<f64>,
    /// Woodbury capacitance of the probe's term (`F x F`, [`MAX_COUPLING_ROWS`] squared).
    capacitance: Vec<f64>,
    /// Global component of each row of `map`: the far boundary's free components, or every
    /// far free component for a following region.
    map_dofs: Vec<usize>,
    /// Their displacement per interface displacement, `-(K_FF^-1 K_FG)` rows, row-major
    /// `|map_dofs| x g`, IEEE half precision (bits): it only places far nodes (viewers, the
    /// probe beyond the region, nodes a successor takes over), each to about `3e-4` of the
    /// interface displacement, and it is most of a following region's memory.
    map: Vec<u16>,
    /// Rows of `map` on the far boundary (what viewers see), refreshed a slice per tick.
    surface_rows: Vec<u32>,
    /// Following regions: per global component its row of `map` or `u32::MAX`
    /// ([`Self::hand_over`]); empty otherwise.
    map_row: Vec<u32>,
    /// Next entry of `surface_rows` to refresh.
    surface_cursor: usize,
    u_gamma: Vec<f64>,
    /// `u_gamma` in single precision, for the map's rows.
    u_gamma32: Vec<f32>,
    /// Whether the AVX2 + FMA + F16C build of the map's rows runs on this CPU.
    f16c: bool,
    far: FarField,
    sizes: CondensedSizes,
    node_active: Vec<bool>,
    /// The tick matrix with the rest stiffness unscaled (margin 1), used instead of `factor`
    /// on ticks where a node enters the probe's rows ([`Self::add_entry_factor`]).
    entry: Option<EntryFactor>,
    /// The nodes of the last tick's probe rows (capacity [`ENTRY_TRACKED_NODES`]).
    last_contact: Vec<u32>,
}

/// A one-row probe coupling over `N` nodes is solved by the paired sweep
/// ([`SupernodalSolve::forward_pair`]) instead of the prepared columns when the columns'
/// `3 N m` multiply-adds (read from memory) reach this share of the factor's entries (the
/// paired sweep's extra arithmetic, on entries it reads anyway). Measured in one process on
/// this 2-core AVX2 machine, the two alternated: at 0.20 (built-in `lv`, 12 patch nodes) the
/// columns were 17 % faster per tick, at 0.32 (`lv_h1_condensed`, 55) the same, at 0.40
/// (`lv_100k_condensed`, 100) the paired sweep 16-22 % faster.
pub const PAIRED_SWEEP_MIN_RATIO: f64 = 0.3;

/// Probe-row nodes remembered between ticks to tell a node entering the contact.
const ENTRY_TRACKED_NODES: usize = 3 * MAX_COUPLING_ROWS;

/// A second numeric factor on the solver's analysis and its prepared contact columns
/// ([`CondensedSolver::add_entry_factor`]).
#[derive(Debug, Clone)]
struct EntryFactor {
    factor: Vec<f32>,
    half: Option<HalfFactor>,
    contact_z: Vec<f32>,
}

/// Largest estimated contraction `||I - A_h^-1 A||` (`A_h` the half-precision factor's
/// matrix) for which the tick uses the half-precision factor: beyond it the rounding would
/// move the step's matrix by more than a few percent of the stiffness margin it is built
/// with, and the single-precision factor is kept.
const HALF_MAX_DEVIATION: f64 = 0.05;

/// Power iterations of [`half_of`]'s estimate.
const HALF_CHECK_ITERATIONS: usize = 12;

/// The half-precision form of `factor` (the factor of `a_lower`, the lower triangle of `A`)
/// for `sweep`, with `factor` rounded to the values it holds, when the rounding moves the
/// solve by at most [`HALF_MAX_DEVIATION`]: estimated by power iteration on `I - A_h^-1 A`
/// from a fixed pseudo-random start. `None` (and `factor` untouched) otherwise, without a
/// sweep, or when the half-precision factor would exceed 32-bit offsets.
fn half_of(
    sweep: Option<&mut SupernodalSolve>,
    factor: &mut [f32],
    a_lower: &SparseColMat<usize, f32>,
) -> Option<HalfFactor> {
    let sweep = sweep?;
    let mut rounded = factor.to_vec();
    let half = sweep.half_factor(&mut rounded)?;
    let m = a_lower.nrows();
    let mut x: Vec<f64> = (0..m as u64)
        .map(|i| ((i.wrapping_mul(2_654_435_761) % 1_000) as f64) / 500.0 - 1.0)
        .collect();
    let mut y = vec![0.0f32; m];
    let mut deviation = 0.0f64;
    for _ in 0..HALF_CHECK_ITERATIONS {
        let norm = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        if !(norm > 0.0) {
            break;
        }
        x.iter_mut().for_each(|v| *v /= norm);
        // y = A x (lower triangle stored: both halves).
        let mut ax = vec![0.0f64; m];
        for j in 0..m {
            for (i, &a) in a_lower.row_idx_of_col(j).zip(a_lower.val_of_col(j)) {
                let a = f64::from(a);
                ax[i] += a * x[j];
                if i != j {
                    ax[j] += a * x[i];
                }
            }
        }
        for (yi, a) in y.iter_mut().zip(&ax) {
            *yi = *a as f32;
        }
        sweep.solve_in_place(&half, &mut y);
        // x <- x - A_h^-1 A x; its norm is the contraction along x.
        for (xi, &yi) in x.iter_mut().zip(&y) {
            *xi -= f64::from(yi);
        }
        deviation = x.iter().map(|v| v * v).sum::<f64>().sqrt();
    }
    if !(deviation <= HALF_MAX_DEVIATION) {
        return None;
    }
    factor.copy_from_slice(&rounded);
    Some(half)
}

/// `a . b` for a row `a` of the far map (half-precision bits) and `b` in single precision,
/// summed in single precision with eight independent partial sums (portable).
fn dot_half_plain(a: &[u16], b: &[f32]) -> f64 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += half::f16::from_bits(x[k]).to_f32() * y[k];
        }
    }
    let tail: f32 = ra
        .iter()
        .zip(rb)
        .map(|(x, y)| half::f16::from_bits(*x).to_f32() * y)
        .sum();
    f64::from(acc.iter().sum::<f32>() + tail)
}

/// [`dot_half_plain`] with AVX2 + FMA + F16C: four accumulators of eight lanes.
///
/// # Safety
/// The CPU must support AVX2, FMA and F16C.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn dot_half_avx2(a: &[u16], b: &[f32]) -> f64 {
    use std::arch::x86_64::*;
    assert_eq!(a.len(), b.len());
    let n = a.len();
    let mut acc = [_mm256_setzero_ps(); 4];
    let mut k = 0;
    // SAFETY: every access reads eight entries below `n` of slices of length `n`.
    unsafe {
        while k + 32 <= n {
            for (j, acc) in acc.iter_mut().enumerate() {
                let c = _mm256_cvtph_ps(_mm_loadu_si128(a.as_ptr().add(k + 8 * j).cast()));
                *acc = _mm256_fmadd_ps(c, _mm256_loadu_ps(b.as_ptr().add(k + 8 * j)), *acc);
            }
            k += 32;
        }
        while k + 8 <= n {
            let c = _mm256_cvtph_ps(_mm_loadu_si128(a.as_ptr().add(k).cast()));
            acc[0] = _mm256_fmadd_ps(c, _mm256_loadu_ps(b.as_ptr().add(k)), acc[0]);
            k += 8;
        }
    }
    let v = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
    let mut lanes = [0.0f32; 8];
    // SAFETY: `lanes` holds eight `f32`.
    unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), v) };
    let tail: f32 = a[k..]
        .iter()
        .zip(&b[k..])
        .map(|(x, y)| half::f16::from_bits(*x).to_f32() * y)
        .sum();
    f64::from(lanes.iter().sum::<f32>() + tail)
}

/// A row of the far map times the interface displacement, with the CPU's build.
fn dot_half(f16c: bool, a: &[u16], b: &[f32]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if f16c {
        // SAFETY: `f16c` comes from `crate::simd::has_avx2_fma_f16c` on this CPU.
        return unsafe { dot_half_avx2(a, b) };
    }
    let _ = f16c;
    dot_half_plain(a, b)
}

/// `out += scale a_f` over the equations (`eq`: equation of each global component, or
/// `usize::MAX`), `a_f` row `f` of the probe's coupling.
fn add_row(eq: &[usize], c: ContactCoupling<'_>, f: usize, scale: f64, out: &mut [f32]) {
    for (i, u) in c.row(f) {
        for k in 0..3 {
            let e = eq[3 * i as usize + k];
            if e != usize::MAX {
                out[e] += (u[k] * scale) as f32;
            }
        }
    }
}

/// Start of row `a` in the packed upper triangle of a symmetric `g x g` matrix (row `a`
/// holds columns `a..g`, `g - a` entries).
fn packed_row_start(a: usize, g: usize) -> usize {
    a * g - a * a.saturating_sub(1) / 2
}

/// One row of a symmetric product from its upper triangle: `y += s u_a` and returns `s . u`
/// (`s` the row's entries right of the diagonal, single precision; `u`, `y` the matching
/// entries), eight independent partial sums so that it vectorises.
#[inline(always)]
fn sym_row_plain(s: &[f32], u: &[f64], y: &mut [f64], ua: f64) -> f64 {
    let mut acc = [0.0; 8];
    let (cs, cu, cy) = (s.chunks_exact(8), u.chunks_exact(8), y.chunks_exact_mut(8));
    let (rs, ru) = (cs.remainder(), cu.remainder());
    for ((x, w), z) in cs.zip(cu).zip(cy) {
        for k in 0..8 {
            let v = f64::from(x[k]);
            acc[k] += v * w[k];
            z[k] += v * ua;
        }
    }
    let n = s.len() - rs.len();
    let mut tail = 0.0;
    for ((x, w), z) in rs.iter().zip(ru).zip(&mut y[n..]) {
        let v = f64::from(*x);
        tail += v * w;
        *z += v * ua;
    }
    acc.iter().sum::<f64>() + tail
}

/// [`sym_row_plain`] compiled for AVX2 + FMA.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn sym_row_avx2(s: &[f32], u: &[f64], y: &mut [f64], ua: f64) -> f64 {
    sym_row_plain(s, u, y, ua)
}

fn sym_row(avx2: bool, s: &[f32], u: &[f64], y: &mut [f64], ua: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: `avx2` comes from `crate::simd::has_avx2_fma` on this CPU.
        return unsafe { sym_row_avx2(s, u, y, ua) };
    }
    let _ = avx2;
    sym_row_plain(s, u, y, ua)
}

/// `z += a[0] y_0 + a[1] y_1 + a[2] y_2`, `y` the three single-precision columns `y_k` of
/// `z`'s length one after the other.
#[inline(always)]
fn axpy3_plain(z: &mut [f64], a: [f64; 3], y: &[f32]) {
    let m = z.len();
    let (y0, y1, y2) = (&y[..m], &y[m..2 * m], &y[2 * m..3 * m]);
    for (((zr, &u0), &u1), &u2) in z.iter_mut().zip(y0).zip(y1).zip(y2) {
        *zr += a[0] * f64::from(u0) + a[1] * f64::from(u1) + a[2] * f64::from(u2);
    }
}

/// [`axpy3_plain`] compiled for AVX2 + FMA.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn axpy3_avx2(z: &mut [f64], a: [f64; 3], y: &[f32]) {
    axpy3_plain(z, a, y);
}

fn axpy3(avx2: bool, z: &mut [f64], a: [f64; 3], y: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: `avx2` comes from `crate::simd::has_avx2_fma` on this CPU.
        return unsafe { axpy3_avx2(z, a, y) };
    }
    let _ = avx2;
    axpy3_plain(z, a, y);
}

/// One assembly entry: row, column (32-bit: the triplets of an edge-smoothed far part run to
/// tens of millions, and a third less memory matters there) and value.
#[derive(Clone, Copy)]
struct Entry<T> {
    row: u32,
    col: u32,
    val: T,
}

impl<T> Entry<T> {
    fn new(row: usize, col: usize, val: T) -> Self {
        // Indices are equation numbers, below 3 n (checked in `CondensedSolver::new`).
        Self {
            row: row as u32,
            col: col as u32,
            val,
        }
    }
}

/// Square `n x n` sparse matrix from triplets, duplicates summed. A counting sort by column
/// and a dense row marker per column: linear in the triplets, where a general sort of the
/// millions of triplets of an edge-smoothed far part took a fifth of a region's preparation.
///
/// # Errors
/// [`ModelError::InvalidMesh`] for an index out of range.
fn sparse<T: Copy + Default + std::ops::AddAssign + faer::traits::ComplexField>(
    n: usize,
    t: &[Entry<T>],
) -> Result<SparseColMat<usize, T>, ModelError> {
    if t.iter().any(|e| e.row as usize >= n || e.col as usize >= n) {
        return Err(ModelError::InvalidMesh(
            "sparse assembly: an index is out of range".into(),
        ));
    }
    // Bucket the triplets by column.
    let mut start = vec![0usize; n + 1];
    for e in t {
        start[e.col as usize + 1] += 1;
    }
    for j in 0..n {
        start[j + 1] += start[j];
    }
    let mut fill = start.clone();
    let mut order = vec![0u32; t.len()];
    for (k, e) in t.iter().enumerate() {
        order[fill[e.col as usize]] = k as u32;
        fill[e.col as usize] += 1;
    }
    // Per column: merge duplicate rows through a marker, then sort the distinct rows.
    let mut slot = vec![usize::MAX; n];
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut rows: Vec<usize> = Vec::new();
    let mut vals: Vec<T> = Vec::new();
    let mut column: Vec<(usize, T)> = Vec::new();
    col_ptr.push(0);
    for j in 0..n {
        column.clear();
        for &k in &order[start[j]..start[j + 1]] {
            let e = &t[k as usize];
            match slot[e.row as usize] {
                usize::MAX => {
                    slot[e.row as usize] = column.len();
                    column.push((e.row as usize, e.val));
                }
                s => column[s].1 += e.val,
            }
        }
        for &(r, _) in &column {
            slot[r] = usize::MAX;
        }
        column.sort_unstable_by_key(|&(r, _)| r);
        rows.extend(column.iter().map(|&(r, _)| r));
        vals.extend(column.iter().map(|&(_, v)| v));
        col_ptr.push(rows.len());
    }
    let symbolic = faer::sparse::SymbolicSparseColMat::new_checked(n, n, col_ptr, None, rows);
    Ok(SparseColMat::new(symbolic, vals))
}

/// The model of the tetrahedra `keep` of `body` (mesh `mesh`): every node kept, so numbering
/// is shared; the body's material, strain smoothing and constraints.
fn part_model(body: &FemModel, mesh: &TetMesh, keep: &[bool]) -> Result<FemModel, ModelError> {
    let mut m = FemModel::with_smoothing(
        &sub_mesh(mesh, keep),
        *body.material(),
        body.strain_smoothing(),
    )?;
    m.copy_constraints_from(body);
    m.copy_fibres_from(body);
    m.set_single_precision(body.single_precision())?;
    Ok(m)
}

/// The sub-mesh with the tetrahedra `keep` (every node kept, so numbering is shared).
fn sub_mesh(mesh: &TetMesh, keep: &[bool]) -> TetMesh {
    fn kept<T: Copy>(rows: &[T], keep: &[bool]) -> Vec<T> {
        rows.iter()
            .zip(keep)
            .filter(|(_, k)| **k)
            .map(|(r, _)| *r)
            .collect()
    }
    TetMesh {
        nodes: mesh.nodes.clone(),
        tets: kept(&mesh.tets, keep),
        tet_edge_nodes: kept(&mesh.tet_edge_nodes, keep),
        surfaces: Vec::new(),
        node_groups: Vec::new(),
    }
}

/// Calls `push(row, col, value)` for every entry of the rest tangent stiffness of material
/// `mat` on every cell of `fem` (N/m), rows and columns as global components `3 i + c`,
/// constrained components skipped (duplicates are summed by the caller's assembly).
/// What the tick matrix `A = M (1 + alpha h) + h D0 + h^2 (c K0 + S)` is made of, for any
/// stiffness margin `c` (the lumped masses are the whole body's: an interface node keeps the
/// share of its far elements).
struct TickMatrixParts<'a> {
    active: &'a FemModel,
    material: MaterialParams,
    eq: &'a [usize],
    gamma_dof: &'a [usize],
    /// `S`, row-major `g x g`.
    schur: &'a [f64],
    /// Lumped mass per equation, kg.
    mass: &'a [f64],
    h: f64,
}

impl TickMatrixParts<'_> {
    /// The lower triangle of `A` with margin `c`, in single precision: the solve only sets
    /// the step, while the residual (forces) stays in double precision, so equilibria are
    /// unaffected (module documentation); it halves the memory the solve streams.
    fn lower(&self, c: f64) -> Result<SparseColMat<usize, f32>, ModelError> {
        let (h, mat, eq) = (self.h, self.material, self.eq);
        let combined = MaterialParams {
            model: MaterialModel::StVenantKirchhoff,
            lambda_pa: c * h * h * mat.lambda_pa + 2.0 * h * mat.phi_pa_s,
            mu_pa: c * h * h * mat.mu_pa + 2.0 * h * mat.psi_pa_s,
            ..mat
        };
        let mut lower = Vec::new();
        let mut push = |r: usize, c: usize, v: f64| {
            if c <= r {
                lower.push(Entry::new(r, c, v as f32));
            }
        };
        rest_tangent(self.active, &combined, |r, c, v| push(eq[r], eq[c], v));
        let g = self.gamma_dof.len();
        for a in 0..g {
            for b in 0..g {
                let v = h * h * self.schur[a * g + b];
                if v != 0.0 {
                    push(eq[self.gamma_dof[a]], eq[self.gamma_dof[b]], v);
                }
            }
        }
        for (k, m) in self.mass.iter().enumerate() {
            push(k, k, m * (1.0 + mat.mass_damping_per_s * h));
        }
        sparse(self.mass.len(), &lower)
    }
}

/// The single-precision Cholesky factor of `a_lower` on its analysis `symbolic`.
///
/// # Errors
/// [`ModelError::InvalidMesh`] when the matrix is not positive definite.
fn factorize(
    symbolic: &SymbolicCholesky<usize>,
    a_lower: &SparseColMat<usize, f32>,
) -> Result<Vec<f32>, ModelError> {
    let mut factor = vec![0.0f32; symbolic.len_val()];
    let mut mem =
        MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f32>(Par::Seq, Default::default()));
    symbolic
        .factorize_numeric_llt::<f32>(
            &mut factor,
            a_lower.as_ref(),
            Side::Lower,
            Default::default(),
            Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        )
        .map_err(|e| {
            ModelError::InvalidMesh(format!("the tick matrix is not positive definite: {e:?}"))
        })?;
    Ok(factor)
}

fn rest_tangent(fem: &FemModel, mat: &MaterialParams, mut push: impl FnMut(usize, usize, f64)) {
    let mut blocks = Vec::new();
    let constraint = fem.constraints();
    for c in 0..fem.cell_count() {
        cell_tangent_blocks_of(fem, mat, c, fem.rest(), &mut blocks);
        let t = fem.cell_nodes(c);
        for (a, &na) in t.iter().enumerate() {
            for (b, &nb) in t.iter().enumerate() {
                let k = blocks[a * t.len() + b];
                for ca in 0..3 {
                    if constraint[na as usize] & (1 << ca) != 0 {
                        continue;
                    }
                    for cb in 0..3 {
                        if constraint[nb as usize] & (1 << cb) != 0 {
                            continue;
                        }
                        push(3 * na as usize + ca, 3 * nb as usize + cb, k.col(cb)[ca]);
                    }
                }
            }
        }
    }
}

fn rest_tangent_opt(fem: Option<&FemModel>, push: impl FnMut(usize, usize, f64)) {
    if let Some(f) = fem {
        rest_tangent(f, f.material(), push);
    }
}

impl CondensedSolver {
    /// Splits `body` (the whole body's model, with its constraints; `mesh` its mesh) by
    /// `region`, condenses the far part and factorises the tick matrix for the step `dt_s` (s).
    /// Costs one sparse factorisation of the far stiffness and `3|G|` solves with it. A region holding every element condenses nothing: then this is
    /// backward Euler with a prefactored rest matrix on the whole body.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`active_region`) for a non-positive radius, a stiffness
    /// margin outside `[1, 100]`, or a region with no element;
    /// [`ModelError::InvalidMesh`] when a factorisation fails (a far part that is not held by
    /// clamps, or an indefinite matrix).
    pub fn new(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        dt_s: f64,
    ) -> Result<Self, ModelError> {
        Self::new_with_progress(body, mesh, region, dt_s, &mut |_, _| {})
    }

    /// [`CondensedSolver::new`] reporting its stages: `progress(stage, fraction)` with the
    /// fraction of the work done in `[0, 1]` (the far factorisation, the column solves in
    /// blocks of 64, the tick factorisation); for set-up output on large meshes.
    ///
    /// # Errors
    /// As [`CondensedSolver::new`].
    pub fn new_with_progress(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        dt_s: f64,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        let field = |m: &str| ModelError::field("active_region", m);
        if !(region.radius_m > 0.0) || !region.radius_m.is_finite() || !region.centre_m.is_finite()
        {
            return Err(field("needs a finite centre and a positive radius"));
        }
        if !(region.stiffness_margin >= 1.0) || region.stiffness_margin > 100.0 {
            return Err(field("stiffness_margin must be in [1, 100]"));
        }
        let n = body.node_count();
        if 3 * n > u32::MAX as usize {
            return Err(field(
                "the mesh has more nodes than 32-bit equation numbers allow",
            ));
        }
        let r2 = region.radius_m * region.radius_m;
        let inside: Vec<bool> = body
            .rest()
            .iter()
            .map(|p| p.distance_squared(region.centre_m) <= r2)
            .collect();
        let keep: Vec<bool> = mesh
            .tets
            .iter()
            .map(|t| t.iter().any(|&i| inside[i as usize]))
            .collect();
        let active_tets = keep.iter().filter(|k| **k).count();
        if active_tets == 0 {
            return Err(field("contains no element"));
        }
        let active = part_model(body, mesh, &keep)?;
        let far_keep: Vec<bool> = keep.iter().map(|k| !k).collect();
        // None when the region holds every element: then this is backward Euler with a
        // prefactored rest matrix on the whole body.
        let far_model = if far_keep.contains(&true) {
            Some(part_model(body, mesh, &far_keep)?)
        } else {
            None
        };
        let mut node_active = vec![false; n];
        let mut node_far = vec![false; n];
        for (e, (t, k)) in mesh.tets.iter().zip(&keep).enumerate() {
            let mid = mesh.tet_edge_nodes.get(e).map_or(&[][..], |m| &m[..]);
            for &i in t.iter().chain(mid) {
                if *k {
                    node_active[i as usize] = true;
                } else {
                    node_far[i as usize] = true;
                }
            }
        }
        let free = |i: usize, c: usize| body.constraints()[i] & (1 << c) == 0;
        // Equations: free components of active nodes.
        let mut eq = vec![usize::MAX; 3 * n];
        let mut eq_dof = Vec::new();
        for i in (0..n).filter(|&i| node_active[i]) {
            for c in (0..3).filter(|&c| free(i, c)) {
                eq[3 * i + c] = eq_dof.len();
                eq_dof.push(3 * i + c);
            }
        }
        let m_eq = eq_dof.len();
        // Interface components and far-only components.
        let mut gamma_index = vec![usize::MAX; 3 * n];
        let mut gamma_dof = Vec::new();
        let mut far_index = vec![usize::MAX; 3 * n];
        let mut far_dofs = Vec::new();
        let mut interface_nodes = 0;
        for i in 0..n {
            if node_active[i] && node_far[i] {
                interface_nodes += 1;
            }
            for c in (0..3).filter(|&c| free(i, c)) {
                if node_active[i] && node_far[i] {
                    gamma_index[3 * i + c] = gamma_dof.len();
                    gamma_dof.push(3 * i + c);
                } else if node_far[i] && !node_active[i] {
                    far_index[3 * i + c] = far_dofs.len();
                    far_dofs.push(3 * i + c);
                }
            }
        }
        let g = gamma_dof.len();
        let f = far_dofs.len();
        progress("condensation: far stiffness", 0.0);
        // Far stiffness blocks.
        let mut kgg = vec![0.0; g * g];
        let mut kff = Vec::new();
        let mut kfg = Vec::new();
        rest_tangent_opt(far_model.as_ref(), |r, c, v| {
            match (gamma_index[r], gamma_index[c], far_index[r], far_index[c]) {
                (gr, gc, _, _) if gr != usize::MAX && gc != usize::MAX => kgg[gr * g + gc] += v,
                (_, gc, fr, _) if fr != usize::MAX && gc != usize::MAX => kfg.push((fr, gc, v)),
                (_, _, fr, fc) if fr != usize::MAX && fc != usize::MAX && fc <= fr => {
                    kff.push(Entry::new(fr, fc, v));
                }
                _ => {}
            }
        });
        let mut schur = kgg;
        // Rows of `-X` kept: the far boundary components (the surface viewers see, refreshed a
        // slice per tick), or for a following region every far component (a successor may
        // activate any far node: `hand_over`).
        let mut on_boundary = vec![false; n];
        for t in mesh.boundary_triangles() {
            for i in t {
                on_boundary[i as usize] = true;
            }
        }
        let map_far: Vec<usize> = (0..f)
            .filter(|&k| region.follow || on_boundary[far_dofs[k] / 3])
            .collect();
        let surface_rows: Vec<u32> = (0..map_far.len())
            .filter(|&r| on_boundary[far_dofs[map_far[r]] / 3])
            .map(|r| r as u32)
            .collect();
        let mut map = vec![0u16; map_far.len() * g];
        let mut map_row = vec![u32::MAX; if region.follow { 3 * n } else { 0 }];
        if region.follow {
            for (r, &k) in map_far.iter().enumerate() {
                map_row[far_dofs[k]] = r as u32;
            }
        }
        let llt = if f > 0 {
            progress("condensation: far factorisation", 0.15);
            let far_nodes: Vec<usize> = far_dofs.iter().map(|&d| d / 3).collect();
            // The triplets go before the factorisation (on a 100 000-tet mesh they are about
            // 0.4 GB, as much as the factor).
            let kff_csc = sparse(f, &std::mem::take(&mut kff))?;
            let llt =
                SparseCholesky::factor(kff_csc.as_ref(), Side::Lower, &far_nodes).map_err(|e| {
                    ModelError::InvalidMesh(format!(
                        "the far part is not held (add clamps or enlarge the active region): {e}"
                    ))
                })?;
            drop(kff_csc);
            // X = K_FF^-1 K_FG, in blocks of columns; S -= K_GF X.
            let mut by_col: Vec<Vec<(usize, f64)>> = vec![Vec::new(); g];
            for &(fr, gc, v) in &kfg {
                by_col[gc].push((fr, v));
            }
            const BLOCK: usize = 64;
            for j0 in (0..g).step_by(BLOCK) {
                progress(
                    "condensation: interface column solves",
                    0.25 + 0.6 * j0 as f64 / g as f64,
                );
                let w = BLOCK.min(g - j0);
                let mut x = Mat::<f64>::zeros(f, w);
                for j in 0..w {
                    for &(fr, v) in &by_col[j0 + j] {
                        x[(fr, j)] += v;
                    }
                }
                llt.solve_in_place(x.as_mut());
                for (r, &k) in map_far.iter().enumerate() {
                    for j in 0..w {
                        let q = half::f16::from_f64(-x[(k, j)]);
                        // Entries are displacements per interface displacement, of order
                        // one; beyond half precision's range the far part is barely held.
                        if !q.is_finite() {
                            return Err(ModelError::InvalidMesh(format!(
                                "the far part is barely held: a far displacement is {:.3e} times \
                                 an interface displacement (add clamps or enlarge the active \
                                 region)",
                                x[(k, j)].abs()
                            )));
                        }
                        map[r * g + j0 + j] = q.to_bits();
                    }
                }
                // S[gi, j0 + j] -= sum_fr K_FG[fr, gi] X[fr, j]
                for &(fr, gi, v) in &kfg {
                    let row = &mut schur[gi * g + j0..gi * g + j0 + w];
                    for (j, s) in row.iter_mut().enumerate() {
                        *s -= v * x[(fr, j)];
                    }
                }
            }
            // A following region recovers its far field from its maps only (the factor is
            // most of its memory: 42 of 80 MB on `lv_h1` at r = 7 mm).
            (!region.follow).then_some(llt)
        } else {
            None
        };
        // Symmetrise (round-off).
        for a in 0..g {
            for b in 0..a {
                let s = 0.5 * (schur[a * g + b] + schur[b * g + a]);
                schur[a * g + b] = s;
                schur[b * g + a] = s;
            }
        }
        progress("condensation: tick matrix factorisation", 0.85);
        let h = dt_s;
        let mass: Vec<f64> = eq_dof
            .iter()
            .map(|d| body.lumped_mass_kg()[d / 3])
            .collect();
        let parts = TickMatrixParts {
            active: &active,
            material: *body.material(),
            eq: &eq,
            gamma_dof: &gamma_dof,
            schur: &schur,
            mass: &mass,
            h,
        };
        let a_lower = parts.lower(region.stiffness_margin)?;
        let eq_nodes: Vec<usize> = eq_dof.iter().map(|&d| d / 3).collect();
        let symbolic = symbolic_cholesky(a_lower.symbolic(), Side::Lower, &eq_nodes)?;
        let mut factor = factorize(&symbolic, &a_lower)?;
        let mut sweep = SupernodalSolve::new(&symbolic);
        let half = half_of(sweep.as_mut(), &mut factor, &a_lower);
        let schur: Vec<f32> = (0..g)
            .flat_map(|a| schur[a * g + a..(a + 1) * g].iter().map(|&v| v as f32))
            .collect();
        let stack = Workspace::new(symbolic.solve_in_place_scratch::<f32>(2, Par::Seq));
        progress("condensation: done", 1.0);
        let sizes = CondensedSizes {
            active_tets,
            active_nodes: node_active.iter().filter(|a| **a).count(),
            interface_nodes,
            equations: m_eq,
            factor_entries: factor.len(),
        };
        Ok(Self {
            h,
            region,
            active,
            eq,
            eq_dof,
            mass,
            gamma_dof,
            schur,
            su: vec![0.0; g],
            a_row: vec![0.0; m_eq],
            avx2: crate::simd::has_avx2_fma(),
            sweep,
            half,
            relaxation: 1.0,
            relaxed_ticks: 0,
            symbolic: Arc::new(symbolic),
            factor,
            stack,
            rhs: Mat::zeros(m_eq, 2),
            b: vec![0.0; m_eq],
            contact_col: vec![u32::MAX; n],
            contact_z: Vec::new(),
            z1: vec![0.0; m_eq],
            capacitance: vec![0.0; MAX_COUPLING_ROWS * MAX_COUPLING_ROWS],
            u_gamma: vec![0.0; g],
            u_gamma32: vec![0.0; g],
            f16c: crate::simd::has_avx2_fma_f16c(),
            map_dofs: map_far.iter().map(|&k| far_dofs[k]).collect(),
            map,
            surface_rows,
            map_row,
            surface_cursor: 0,
            far: FarField {
                dofs: far_dofs,
                llt,
                kfg,
            },
            sizes,
            node_active,
            entry: None,
            last_contact: Vec::with_capacity(ENTRY_TRACKED_NODES),
        })
    }

    /// Adds the entry factor: the same region's tick matrix with the rest stiffness unscaled
    /// (`c = 1`), stepped instead on ticks where a node enters the probe's rows. With the
    /// implicit sphere a face entering the contact while sliding otherwise takes its load
    /// against a body `c` times too stiff in its first tick, and the force turns at once (a
    /// 20 mm/s stroke on the default LV: 9.0 % between ticks with `c = 2`, 6.1 % with the
    /// entry factor; docs/decisions.md, "The whole-body rest factor"). Only those ticks use
    /// it, so `c` still guards every other tick against the stiffening tangent. Costs a second
    /// numeric factorisation on the same analysis, its memory and that of a second set of
    /// prepared contact columns (both sets share [`PREPARED_CONTACT_MAX_BYTES`]); a margin of
    /// 1 needs none. Meant for whole-body solvers (a following region's successors are
    /// prepared without it).
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] when the matrix is not positive definite.
    pub fn add_entry_factor(&mut self) -> Result<(), ModelError> {
        if self.region.stiffness_margin <= 1.0 {
            return Ok(());
        }
        let g = self.gamma_dof.len();
        let mut schur = vec![0.0f64; g * g];
        for a in 0..g {
            let start = packed_row_start(a, g);
            for (b, &v) in (a..g).zip(&self.schur[start..start + g - a]) {
                schur[a * g + b] = f64::from(v);
                schur[b * g + a] = f64::from(v);
            }
        }
        let parts = TickMatrixParts {
            active: &self.active,
            material: *self.active.material(),
            eq: &self.eq,
            gamma_dof: &self.gamma_dof,
            schur: &schur,
            mass: &self.mass,
            h: self.h,
        };
        let a_lower = parts.lower(1.0)?;
        let mut factor = factorize(&self.symbolic, &a_lower)?;
        let half = half_of(self.sweep.as_mut(), &mut factor, &a_lower);
        // Columns already prepared: the same nodes through the new factor.
        let mut list: Vec<(u32, u32)> = self
            .contact_col
            .iter()
            .enumerate()
            .filter(|(_, c)| **c != u32::MAX)
            .map(|(i, &c)| (c, i as u32))
            .collect();
        list.sort_unstable();
        let nodes: Vec<u32> = list.iter().map(|&(_, i)| i).collect();
        let contact_z = if nodes.is_empty() {
            Vec::new()
        } else {
            self.contact_columns(&factor, &nodes)
        };
        self.entry = Some(EntryFactor {
            factor,
            half,
            contact_z,
        });
        Ok(())
    }

    /// Precomputes `A^-1 e` for the three components of each of `nodes` (the nodes a probe
    /// patch can hold: the active touchable surface), so that a tick in contact needs one
    /// right-hand side instead of two. Nodes outside the region are skipped; a patch with a
    /// node not prepared falls back to the second right-hand side. Costs `3 |nodes|` solves
    /// and `12 m |nodes|` bytes (`m` equations), at most [`PREPARED_CONTACT_MAX_BYTES`]:
    /// beyond it nothing is prepared (a client's large whole-body scene must not take
    /// gigabytes and minutes of solves) and the result is `false`.
    pub fn prepare_contact(&mut self, nodes: &[u32]) -> bool {
        self.prepare_contact_within(nodes, PREPARED_CONTACT_MAX_BYTES)
    }

    /// [`Self::prepare_contact`] with the memory limit `max_bytes`; `false` (nothing
    /// prepared, the columns of an earlier call dropped) when the columns would exceed it.
    pub fn prepare_contact_within(&mut self, nodes: &[u32], max_bytes: usize) -> bool {
        let m = self.eq_dof.len();
        let mut list: Vec<u32> = nodes
            .iter()
            .copied()
            .filter(|&i| self.node_active.get(i as usize).copied().unwrap_or(false))
            .collect();
        list.sort_unstable();
        list.dedup();
        self.contact_col.iter_mut().for_each(|c| *c = u32::MAX);
        let factors = if self.entry.is_some() { 2 } else { 1 };
        if 12usize
            .saturating_mul(m)
            .saturating_mul(list.len())
            .saturating_mul(factors)
            > max_bytes
        {
            self.contact_z = Vec::new();
            if let Some(e) = self.entry.as_mut() {
                e.contact_z = Vec::new();
            }
            return false;
        }
        for (c, &i) in list.iter().enumerate() {
            self.contact_col[i as usize] = c as u32;
        }
        self.contact_z = self.contact_columns(&self.factor, &list);
        if let Some(e) = &self.entry {
            let z = self.contact_columns(&e.factor, &list);
            if let Some(e) = self.entry.as_mut() {
                e.contact_z = z;
            }
        }
        true
    }

    /// `A^-1 e` through `factor` (of this solver's analysis) for the three components of each
    /// node of `list`: per node its three columns of `m` values one after the other.
    fn contact_columns(&self, factor: &[f32], list: &[u32]) -> Vec<f32> {
        let m = self.eq_dof.len();
        let mut z = vec![0.0; 3 * m * list.len()];
        const BLOCK: usize = 16;
        let mut mem = MemBuffer::new(
            self.symbolic
                .solve_in_place_scratch::<f32>(3 * BLOCK, Par::Seq),
        );
        for (b, chunk) in list.chunks(BLOCK).enumerate() {
            let mut e = Mat::<f32>::zeros(m, 3 * chunk.len());
            for (j, &i) in chunk.iter().enumerate() {
                for k in 0..3 {
                    let q = self.eq[3 * i as usize + k];
                    if q != usize::MAX {
                        e[(q, 3 * j + k)] = 1.0;
                    }
                }
            }
            LltRef::<usize, f32>::new(&self.symbolic, factor).solve_in_place_with_conj(
                Conj::No,
                e.as_mut(),
                Par::Seq,
                MemStack::new(&mut mem),
            );
            for j in 0..chunk.len() {
                let c = b * BLOCK + j;
                // A constrained component has a zero column (its e was zero).
                for (k, dst) in z[3 * c * m..3 * (c + 1) * m]
                    .chunks_exact_mut(m)
                    .enumerate()
                {
                    dst.copy_from_slice(e.col_as_slice(3 * j + k));
                }
            }
        }
        z
    }

    /// Far-surface rows refreshed per tick: [`SURFACE_REFRESH_TICKS`] ticks for all, or
    /// fewer rows when that exceeds [`SURFACE_REFRESH_MAX_MACS`].
    fn surface_rows_per_tick(&self) -> usize {
        let g = self.gamma_dof.len().max(1);
        self.surface_rows
            .len()
            .div_ceil(SURFACE_REFRESH_TICKS)
            .min((SURFACE_REFRESH_MAX_MACS / g).max(1))
    }

    /// Ticks a full refresh of the far surface takes (at most the viewers' lag behind the
    /// interface): [`SURFACE_REFRESH_TICKS`], more on large far surfaces
    /// ([`SURFACE_REFRESH_MAX_MACS`]); 0 without far surface.
    pub fn surface_refresh_ticks(&self) -> usize {
        let rows = self.surface_rows.len();
        if rows == 0 {
            0
        } else {
            rows.div_ceil(self.surface_rows_per_tick())
        }
    }

    /// The active elements as a model over the whole body's nodes: its
    /// [`FemModel::add_internal_forces`] gives the active region's forces.
    pub fn active_model(&self) -> &FemModel {
        &self.active
    }

    /// The region this solver simulates.
    pub fn region(&self) -> ActiveRegion {
        self.region
    }

    /// Whether the region holds every element (nothing condensed: backward Euler with the rest
    /// factor on the whole body, [`crate::integrate::LinearSolver::RestCholesky`]).
    pub fn is_whole_body(&self) -> bool {
        self.gamma_dof.is_empty() && self.far.dofs.is_empty()
    }

    /// Sizes of the split, for reports.
    pub fn sizes(&self) -> CondensedSizes {
        self.sizes
    }

    /// Ticks so far whose solved velocity field reversed and was relaxed, and the factor on
    /// the velocity now (module documentation, "Relaxation").
    pub fn relaxation(&self) -> (u64, f64) {
        (self.relaxed_ticks, self.relaxation)
    }

    /// Step the matrix was factorised for, s.
    pub fn dt_s(&self) -> f64 {
        self.h
    }

    /// Whether node `i` belongs to an active element.
    pub fn is_active_node(&self, i: u32) -> bool {
        self.node_active[i as usize]
    }

    /// Whether every corner of triangle `t` is an active node (contact and loads must stay
    /// on such triangles).
    pub fn is_active_triangle(&self, t: &[u32; 3]) -> bool {
        t.iter().all(|&i| self.is_active_node(i))
    }

    /// One backward Euler step (module documentation). `f` (N, one per body node) holds the
    /// active elements' elastic force at `x` (from [`Self::active_model`]), external loads on
    /// active nodes and the coupling's explicit part; the far field's `-S u_G` is added here.
    /// Updates `x`, `v` of the active nodes and the positions of a slice of the far boundary
    /// nodes (all of them every [`Self::surface_refresh_ticks`] ticks); other far nodes keep
    /// their values (see [`Self::recover_far_field`]). Returns the largest squared nodal speed
    /// (m^2/s^2; NaN if any value is not finite). Allocation-free.
    ///
    /// # Panics
    /// If the slices are shorter than the body's node count.
    pub fn step(
        &mut self,
        f: &[DVec3],
        coupling: Option<ContactCoupling<'_>>,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        // Without an entry factor there is nothing to tell apart.
        if self.entry.is_none() {
            return self.step_solved(f, coupling, x, v);
        }
        // A node entering the probe's rows: the step with the unscaled rest stiffness.
        let entering = coupling.is_some_and(|c| {
            c.nodes.len() > ENTRY_TRACKED_NODES
                || c.nodes.iter().any(|i| !self.last_contact.contains(i))
        });
        self.last_contact.clear();
        if let Some(c) = coupling {
            let k = c.nodes.len().min(ENTRY_TRACKED_NODES);
            self.last_contact.extend_from_slice(&c.nodes[..k]);
        }
        let entry = if entering { self.entry.take() } else { None };
        let Some(mut entry) = entry else {
            return self.step_solved(f, coupling, x, v);
        };
        // The entry factor and its columns stand in for this tick (swapped, not copied).
        std::mem::swap(&mut self.factor, &mut entry.factor);
        std::mem::swap(&mut self.half, &mut entry.half);
        std::mem::swap(&mut self.contact_z, &mut entry.contact_z);
        let r = self.step_solved(f, coupling, x, v);
        std::mem::swap(&mut self.factor, &mut entry.factor);
        std::mem::swap(&mut self.half, &mut entry.half);
        std::mem::swap(&mut self.contact_z, &mut entry.contact_z);
        self.entry = Some(entry);
        r
    }

    /// [`Self::step`] with the factor in `factor` (and its columns in `contact_z`).
    fn step_solved(
        &mut self,
        f: &[DVec3],
        coupling: Option<ContactCoupling<'_>>,
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) -> f64 {
        let h = self.h;
        // Component `d` of a node array is entry `d` of its flat view.
        let x: &mut [f64] = bytemuck::cast_slice_mut(x);
        let v: &mut [f64] = bytemuck::cast_slice_mut(v);
        let f: &[f64] = bytemuck::cast_slice(f);
        let rest: &[f64] = bytemuck::cast_slice(self.active.rest());
        let g = self.gamma_dof.len();
        for ((u, u32), &d) in self
            .u_gamma
            .iter_mut()
            .zip(&mut self.u_gamma32)
            .zip(&self.gamma_dof)
        {
            *u = x[d] - rest[d];
            *u32 = *u as f32;
        }
        // Far boundary nodes: a slice of rows per tick, so the surface is at most
        // `surface_refresh_ticks` ticks behind the interface.
        let rows = self.surface_rows.len();
        if rows > 0 {
            let per_tick = self.surface_rows_per_tick();
            let end = (self.surface_cursor + per_tick).min(rows);
            for &r in &self.surface_rows[self.surface_cursor..end] {
                let r = r as usize;
                let d = self.map_dofs[r];
                let u = dot_half(self.f16c, &self.map[r * g..(r + 1) * g], &self.u_gamma32);
                x[d] = rest[d] + u;
            }
            self.surface_cursor = if end == rows { 0 } else { end };
        }
        // b = M v + h (f - S u_G), into the first right-hand-side column (the second is
        // filled where it is used).
        let rhs0 = self.rhs.col_as_slice_mut(0);
        if g == 0 {
            for ((r, &d), &m) in rhs0.iter_mut().zip(&self.eq_dof).zip(&self.mass) {
                *r = (m * v[d] + h * f[d]) as f32;
            }
        } else {
            for ((b, &d), &m) in self.b.iter_mut().zip(&self.eq_dof).zip(&self.mass) {
                *b = m * v[d] + h * f[d];
            }
            // S u_G from the packed upper triangle: row `a` adds its dot product to entry
            // `a` and its entries times `u_a` to the entries after it.
            self.su.iter_mut().for_each(|s| *s = 0.0);
            for a in 0..g {
                let start = packed_row_start(a, g);
                let row = &self.schur[start..start + g - a];
                let ua = self.u_gamma[a];
                let (head, tail) = self.su.split_at_mut(a + 1);
                let s = sym_row(self.avx2, &row[1..], &self.u_gamma[a + 1..], tail, ua);
                head[a] += f64::from(row[0]) * ua + s;
            }
            for (&da, &su) in self.gamma_dof.iter().zip(&self.su) {
                self.b[self.eq[da]] -= h * su;
            }
            for (r, b) in rhs0.iter_mut().zip(&self.b) {
                *r = *b as f32;
            }
        }
        // The probe's term `h^2 A^T C A` by Woodbury on the factor:
        // `v' = z0 - A^-1 A^T W^-1 A z0`, `z0 = A^-1 b`, `W = C^-1 / h^2 + A A^-1 A^T`, with the
        // columns `A^-1 e` prepared for the contact nodes ([`Self::prepare_contact`]); a row
        // with a node not prepared falls back to one more solve per row.
        let m = self.eq_dof.len();
        self.z1.iter_mut().for_each(|z| *z = 0.0);
        // One row `a` (the kernel patch) over many nodes through the half-precision sweep:
        // both forward sweeps in one pass over the factor, `W = C^-1 / h^2 + a A^-1 a`,
        // `s = a z0 / W`, then one backward sweep of `b - s a`: `v' = A^-1 (b - s a)`, without
        // the prepared columns ([`PAIRED_SWEEP_MIN_RATIO`]).
        let factor_len = self
            .sweep
            .as_ref()
            .map_or(usize::MAX, SupernodalSolve::factor_len);
        let one_row = coupling.filter(|c| {
            c.rows() == 1
                && (3 * c.nodes.len() * m) as f64 >= PAIRED_SWEEP_MIN_RATIO * factor_len as f64
        });
        let paired =
            if let (Some(c), Some(sweep), Some(half)) = (one_row, &mut self.sweep, &self.half) {
                self.a_row.iter_mut().for_each(|a| *a = 0.0);
                add_row(&self.eq, c, 0, 1.0, &mut self.a_row);
                let (aa, ab) = sweep.forward_pair(half, self.rhs.col_as_slice(0), &self.a_row);
                let w = c.compliance[0] / (h * h) + aa;
                // A capacitance that is not positive: no correction, as for several rows.
                let s = if w > 0.0 { ab / w } else { 0.0 };
                sweep.backward_combined(half, s as f32, self.rhs.col_as_slice_mut(0));
                true
            } else {
                self.solve_column(0);
                false
            };
        if let Some(c) = coupling.filter(|_| !paired) {
            let nf = c.rows();
            let prepared = c
                .nodes
                .iter()
                .all(|&i| self.contact_col[i as usize] != u32::MAX);
            // t = A z0.
            let mut t = [0.0; MAX_COUPLING_ROWS];
            for (f, tf) in t.iter_mut().enumerate().take(nf) {
                for (i, u) in c.row(f) {
                    for k in 0..3 {
                        let e = self.eq[3 * i as usize + k];
                        if e != usize::MAX {
                            *tf += u[k] * f64::from(self.rhs[(e, 0)]);
                        }
                    }
                }
            }
            let w = &mut self.capacitance[..nf * nf];
            for f in 0..nf {
                for g in 0..nf {
                    w[f * nf + g] = c.compliance[f * nf + g] / (h * h);
                }
            }
            // One row (the kernel patch: every patch node in it): `z1 = A^-1 a^T` from the
            // prepared columns first, then `W += a z1`. The pair loop below reads `3 N^2`
            // scattered entries of the columns for a row of `N` nodes, about a fifth of the
            // tick on a 0.5 mm mesh.
            let single_row = prepared && nf == 1;
            if single_row {
                for (l, u) in c.row(0) {
                    let base = self.contact_col[l as usize] as usize * 3 * m;
                    axpy3(
                        self.avx2,
                        &mut self.z1,
                        u.to_array(),
                        &self.contact_z[base..base + 3 * m],
                    );
                }
                let mut s = 0.0;
                for (j, u) in c.row(0) {
                    for a in 0..3 {
                        let e = self.eq[3 * j as usize + a];
                        if e != usize::MAX {
                            s += u[a] * self.z1[e];
                        }
                    }
                }
                w[0] += s;
            } else if prepared {
                for f in 0..nf {
                    for g in 0..=f {
                        let mut s = 0.0;
                        for (j, u) in c.row(f) {
                            for (l, wv) in c.row(g) {
                                let base = self.contact_col[l as usize] as usize * 3 * m;
                                for a in 0..3 {
                                    let e = self.eq[3 * j as usize + a];
                                    if e == usize::MAX {
                                        continue;
                                    }
                                    let z = &self.contact_z[base + e..];
                                    s += u[a]
                                        * (wv.x * f64::from(z[0])
                                            + wv.y * f64::from(z[m])
                                            + wv.z * f64::from(z[2 * m]));
                                }
                            }
                        }
                        w[f * nf + g] += s;
                        if g != f {
                            w[g * nf + f] += s;
                        }
                    }
                }
            } else {
                for g in 0..nf {
                    self.solve_row(c, g);
                    for f in 0..nf {
                        let mut s = 0.0;
                        for (i, u) in c.row(f) {
                            for k in 0..3 {
                                let e = self.eq[3 * i as usize + k];
                                if e != usize::MAX {
                                    s += u[k] * f64::from(self.rhs[(e, 1)]);
                                }
                            }
                        }
                        self.capacitance[f * nf + g] += s;
                    }
                }
            }
            let w = &mut self.capacitance[..nf * nf];
            if cholesky_in_place(w, nf) {
                cholesky_solve(w, nf, &mut t[..nf]);
                // z1 = A^-1 A^T s.
                if single_row {
                    let s = t[0];
                    self.z1.iter_mut().for_each(|z| *z *= s);
                } else if prepared {
                    for (f, &tf) in t.iter().enumerate().take(nf) {
                        for (l, u) in c.row(f) {
                            let base = self.contact_col[l as usize] as usize * 3 * m;
                            axpy3(
                                self.avx2,
                                &mut self.z1,
                                (u * tf).to_array(),
                                &self.contact_z[base..base + 3 * m],
                            );
                        }
                    }
                } else {
                    self.rhs.col_mut(1).fill(0.0);
                    for (f, &tf) in t.iter().enumerate().take(nf) {
                        add_row(&self.eq, c, f, tf, self.rhs.col_as_slice_mut(1));
                    }
                    self.solve_column(1);
                    for (k, z) in self.z1.iter_mut().enumerate() {
                        *z = f64::from(self.rhs[(k, 1)]);
                    }
                }
            } else if single_row {
                // No correction, as for several rows.
                self.z1.iter_mut().for_each(|z| *z = 0.0);
            }
        }
        // Under-relaxation of the modified Newton step (module documentation, "Relaxation"):
        // a velocity field that reverses from one tick to the next is the frozen matrix's
        // overshoot, never the body's motion.
        // `z1` becomes the solved (unrelaxed) velocity.
        // A velocity component that grows SNAP_GROWTH-fold in one tick past SNAP_MIN_SPEED is
        // the same overshoot in one direction (an inverted element snapping back).
        let (mut dot_old_new, mut old2, mut new2) = (0.0, 0.0, 0.0);
        let (mut new_max2, mut old_max2) = (0.0f64, 0.0f64);
        let z0 = self.rhs.col_as_slice(0);
        for ((z, &d), &z0) in self.z1.iter_mut().zip(&self.eq_dof).zip(z0) {
            let vn = f64::from(z0) - *z;
            *z = vn;
            let vo = v[d];
            dot_old_new += vo * vn;
            old2 += vo * vo;
            new2 += vn * vn;
            new_max2 = new_max2.max(vn * vn);
            old_max2 = old_max2.max(vo * vo);
        }
        let reversed = dot_old_new < REVERSAL_COSINE * (old2 * new2).sqrt()
            && new_max2 > REVERSAL_MIN_SPEED_M_PER_S * REVERSAL_MIN_SPEED_M_PER_S;
        let snapped = new_max2 > SNAP_GROWTH * SNAP_GROWTH * old_max2
            && new_max2 > SNAP_MIN_SPEED_M_PER_S * SNAP_MIN_SPEED_M_PER_S;
        self.relaxation = if reversed || snapped {
            self.relaxed_ticks += 1;
            (self.relaxation * 0.5).max(MIN_RELAXATION)
        } else {
            (self.relaxation * RELAXATION_RECOVERY).min(1.0)
        };
        let alpha = self.relaxation;
        for (&d, &vn) in self.eq_dof.iter().zip(&self.z1) {
            let vi = alpha * vn;
            v[d] = vi;
            x[d] += vi * h;
        }
        let mut max_v2: f64 = 0.0;
        let mut non_finite = false;
        let mut last = usize::MAX;
        for &d in &self.eq_dof {
            let i = d / 3;
            if i != last {
                last = i;
                let s =
                    v[3 * i] * v[3 * i] + v[3 * i + 1] * v[3 * i + 1] + v[3 * i + 2] * v[3 * i + 2];
                non_finite |= !s.is_finite();
                max_v2 = max_v2.max(s);
            }
        }
        if non_finite { f64::NAN } else { max_v2 }
    }

    /// `A^-1 a_g` for row `g` of the probe's term into the second right-hand-side column (the
    /// fallback for nodes without prepared columns).
    fn solve_row(&mut self, c: ContactCoupling<'_>, g: usize) {
        self.rhs.col_mut(1).fill(0.0);
        add_row(&self.eq, c, g, 1.0, self.rhs.col_as_slice_mut(1));
        self.solve_column(1);
    }

    /// `A^-1` applied in place to column `col` of `rhs` (allocation-free).
    fn solve_column(&mut self, col: usize) {
        if let (Some(sweep), Some(half)) = (&mut self.sweep, &self.half) {
            sweep.solve_in_place(half, self.rhs.col_as_slice_mut(col));
            return;
        }
        LltRef::<usize, f32>::new(&self.symbolic, &self.factor).solve_in_place_with_conj(
            Conj::No,
            self.rhs.as_mut().subcols_mut(col, 1),
            Par::Seq,
            MemStack::new(&mut self.stack.buffer),
        );
    }

    /// Hands the state over from `self` (the region in use) to `next` at a tick boundary:
    /// every node `next` simulates that `self` condenses gets the displacement the far field
    /// of `self` gives it for the current interface displacement (`u = -K_FF^-1 K_FG u_G`,
    /// from the map of every far component kept when `self` was built with
    /// [`ActiveRegion::follow`]) and zero
    /// velocity (the far field is quasi-static); nodes both simulate keep their state, and
    /// nodes only `self` simulates keep their positions (`next` refreshes its far surface
    /// from its own map) with zero velocity.
    /// Returns `false`, touching nothing, when `self` has no such map (not built to follow).
    /// Costs `3 g` multiply-adds per such node (`g` interface
    /// components of `self`); allocation-free.
    ///
    /// # Panics
    /// If `x`, `v` are shorter than the body's node count or `next` is of another body.
    pub fn hand_over(&mut self, next: &CondensedSolver, x: &mut [DVec3], v: &mut [DVec3]) -> bool {
        let node_active = &self.node_active;
        let taken = |d: usize| !node_active[d / 3];
        let missing = next
            .eq_dof
            .iter()
            .any(|&d| taken(d) && self.map_row.get(d).is_none_or(|&r| r == u32::MAX));
        if missing {
            return false;
        }
        let rest = self.active.rest();
        for ((u, u32), &d) in self
            .u_gamma
            .iter_mut()
            .zip(&mut self.u_gamma32)
            .zip(&self.gamma_dof)
        {
            *u = x[d / 3][d % 3] - rest[d / 3][d % 3];
            *u32 = *u as f32;
        }
        let g = self.gamma_dof.len();
        for &d in &next.eq_dof {
            if taken(d) {
                let r = self.map_row[d] as usize;
                let u = dot_half(self.f16c, &self.map[r * g..(r + 1) * g], &self.u_gamma32);
                x[d / 3][d % 3] = rest[d / 3][d % 3] + u;
                v[d / 3][d % 3] = 0.0;
            }
        }
        // Nodes `next` condenses become quasi-static: their kinetic energy is dropped (never
        // injected), and the probe's coupling sees them at rest.
        for &d in &self.eq_dof {
            if !next.node_active[d / 3] {
                v[d / 3][d % 3] = 0.0;
            }
        }
        true
    }

    /// Bytes held by the region's numeric arrays (tick factor, maps, coupling columns, far
    /// factor), for reports; index arrays and the active elements' model are not counted.
    pub fn memory_bytes(&self) -> usize {
        let far = self.far.llt.as_ref().map_or(0, |l| 8 * l.factor_entries());
        let half = |h: &Option<HalfFactor>| h.as_ref().map_or(0, HalfFactor::memory_bytes);
        let entry = self.entry.as_ref().map_or(0, |e| {
            4 * (e.factor.len() + e.contact_z.len()) + half(&e.half)
        });
        entry
            + half(&self.half)
            + 4 * (self.factor.len() + self.schur.len() + self.contact_z.len())
            + 2 * self.map.len()
            + 24 * self.far.kfg.len()
            + far
    }

    /// Elastic energy of the condensed far part for the interface displacement in `x`,
    /// `u_G^T S u_G / 2`, J (exact for its linear elements).
    pub fn far_energy_j(&self, x: &[DVec3]) -> f64 {
        let g = self.gamma_dof.len();
        let u = |a: usize| {
            let d = self.gamma_dof[a];
            x[d / 3][d % 3] - self.active.rest()[d / 3][d % 3]
        };
        // Packed upper triangle: the off-diagonal entries count twice.
        (0..g)
            .map(|a| {
                let start = packed_row_start(a, g);
                let row = &self.schur[start..start + g - a];
                let off: f64 = (a + 1..g).map(|b| f64::from(row[b - a]) * u(b)).sum();
                u(a) * (0.5 * f64::from(row[0]) * u(a) + off)
            })
            .sum::<f64>()
    }

    /// Sets the far-only nodes of `x` to the static linear response of the far body to the
    /// interface displacement, `u_F = -K_FF^-1 K_FG u_G` (one sparse solve; allocates). Far
    /// velocities are left as they are (zero for a quasi-static far field).
    /// A following region ([`ActiveRegion::follow`]) keeps no far factor: it sets the far
    /// nodes from its map of every far component instead.
    pub fn recover_far_field(&self, x: &mut [DVec3]) {
        let Some(llt) = &self.far.llt else {
            let g = self.gamma_dof.len();
            let rest = self.active.rest();
            let u_gamma: Vec<f32> = self
                .gamma_dof
                .iter()
                .map(|&d| (x[d / 3][d % 3] - rest[d / 3][d % 3]) as f32)
                .collect();
            for (r, &d) in self.map_dofs.iter().enumerate() {
                x[d / 3][d % 3] = rest[d / 3][d % 3]
                    + dot_half(self.f16c, &self.map[r * g..(r + 1) * g], &u_gamma);
            }
            return;
        };
        let mut b = Mat::<f64>::zeros(self.far.dofs.len(), 1);
        for &(fr, gc, v) in &self.far.kfg {
            let d = self.gamma_dof[gc];
            b[(fr, 0)] -= v * (x[d / 3][d % 3] - self.active.rest()[d / 3][d % 3]);
        }
        llt.solve_in_place(b.as_mut());
        for (k, &d) in self.far.dofs.iter().enumerate() {
            x[d / 3][d % 3] = self.active.rest()[d / 3][d % 3] + b[(k, 0)];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{dot_half, packed_row_start, sym_row};

    /// The packed upper triangle's product (plain lanes, and AVX2 where the CPU has it) is the
    /// dense symmetric product, for sizes with and without a tail of eight.
    #[test]
    fn the_packed_symmetric_product_is_the_dense_one() {
        for g in [1usize, 7, 8, 13, 24, 31] {
            // A symmetric matrix with entries exact in single precision.
            let entry = |a: usize, b: usize| {
                let (i, j) = (a.min(b), a.max(b));
                ((i * 37 + j * 11) % 17) as f64 / 8.0 - 1.0
            };
            let u: Vec<f64> = (0..g).map(|a| (a as f64 * 0.7).sin()).collect();
            let packed: Vec<f32> = (0..g)
                .flat_map(|a| (a..g).map(move |b| entry(a, b) as f32))
                .collect();
            assert_eq!(packed.len(), g * (g + 1) / 2);
            assert_eq!(packed_row_start(g - 1, g), packed.len() - 1);
            let dense: Vec<f64> = (0..g)
                .map(|a| (0..g).map(|b| entry(a, b) * u[b]).sum())
                .collect();
            for avx2 in [false, crate::simd::has_avx2_fma()] {
                let mut y = vec![0.0; g];
                for a in 0..g {
                    let start = packed_row_start(a, g);
                    let row = &packed[start..start + g - a];
                    let (head, tail) = y.split_at_mut(a + 1);
                    let s = sym_row(avx2, &row[1..], &u[a + 1..], tail, u[a]);
                    head[a] += f64::from(row[0]) * u[a] + s;
                }
                for (a, (p, d)) in y.iter().zip(&dense).enumerate() {
                    assert!((p - d).abs() <= 1e-12, "g {g}, row {a}: {p} against {d}");
                }
            }
        }
    }

    /// A row of the half-precision far map times the interface displacement (plain lanes, and
    /// AVX2 + F16C where the CPU has it) is the double-precision sum of the rounded entries to
    /// single-precision round-off, for lengths with and without a tail of eight or 32; and the
    /// rounding places the row's sum within `2^-11` of each entry's magnitude.
    #[test]
    fn a_half_precision_map_row_is_its_rounded_dot_product() {
        for g in [1usize, 7, 8, 13, 32, 45, 792] {
            let exact: Vec<f64> = (0..g)
                .map(|j| ((j * 31 % 23) as f64 - 11.0) / 37.0)
                .collect();
            let u: Vec<f64> = (0..g).map(|j| 1e-3 * (j as f64 * 0.37).cos()).collect();
            let row: Vec<u16> = exact
                .iter()
                .map(|&v| half::f16::from_f64(v).to_bits())
                .collect();
            let u32: Vec<f32> = u.iter().map(|&v| v as f32).collect();
            let rounded: f64 = row
                .iter()
                .zip(&u32)
                .map(|(&h, &b)| f64::from(half::f16::from_bits(h).to_f32()) * f64::from(b))
                .sum();
            let magnitude: f64 = exact.iter().zip(&u).map(|(a, b)| (a * b).abs()).sum();
            let true_value: f64 = exact.iter().zip(&u).map(|(a, b)| a * b).sum();
            assert!((rounded - true_value).abs() <= magnitude * (1.0 / 2048.0) + 1e-12 * g as f64);
            for f16c in [false, crate::simd::has_avx2_fma_f16c()] {
                let d = dot_half(f16c, &row, &u32);
                assert!(
                    (d - rounded).abs() <= 1e-6 * magnitude,
                    "g {g}, f16c {f16c}: {d} against {rounded}"
                );
            }
        }
    }
}
