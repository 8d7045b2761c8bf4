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
use crate::contact::coupling::{MAX_MERGED_ROWS, cholesky_in_place, cholesky_solve};
use crate::element::FemModel;
use crate::element::tangent::cell_tangent_blocks_of;
use crate::material::{MaterialModel, MaterialParams};
use crate::mesh::TetMesh;
use crate::pool::TickPool;
use crate::simd::{Avx2Fma, Avx2FmaF16c};

mod build;
mod contact;
mod far;
mod half;
mod image;
mod step;

pub use build::TILE_RING_SLACK_M;
use build::{TickMatrixParts, ball_of, factorize};
use half::{add_row, axpy3, dot_half, half_of, packed_row_start, sym_row};
use image::unpack_symmetric;
pub use image::{TILE_IMAGE_FORMAT, TILE_IMAGE_HEADER_BYTES};

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
    /// Whether a following region keeps a cache of regions prepared ahead
    /// ([`TileMode::Background`], [`crate::integrate::follow`]; issue 48 s2).
    pub tiles: TileMode,
}

/// The region cache of a following region ([`ActiveRegion::tiles`]; scene key
/// `active_region.tiles`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum TileMode {
    /// Every region is prepared on demand (the default).
    #[default]
    Off,
    /// Regions ("tiles") are prepared ahead, while the worker is idle, at centres covering the
    /// touchable surface: every touchable node lies within `cover_m` (m, > 0) of a centre
    /// ([`crate::integrate::follow::tile_centres`]); a request takes the nearest built tile.
    Background {
        /// Covering radius of the tile centres, m.
        cover_m: f64,
    },
}

/// Threads of a set-up's column solves ([`CondensedSolver::new_in_threads`]): the machine's
/// ([`std::thread::available_parallelism`]; 1 when unknown), at most
/// [`MAX_PREPARATION_THREADS`]. A set-up runs before its session ticks; a following region's
/// later preparations use the session's tick threads instead
/// ([`crate::integrate::follow`]).
pub fn setup_threads() -> usize {
    std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .clamp(1, MAX_PREPARATION_THREADS)
}

/// Most threads a region's preparation uses.
pub const MAX_PREPARATION_THREADS: usize = 8;

/// Smallest [`TileMode::Background`] covering radius a scene may set, m (0.5 mm: below it the
/// tiles of a touchable surface number in the thousands).
pub const MIN_TILE_COVER_M: f64 = 5e-4;

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
            tiles: TileMode::Off,
        }
    }
}

/// Most balls of a union region ([`RegionBalls`]): one per tool slot
/// ([`crate::body::MAX_TOOLS`]).
pub const MAX_REGION_BALLS: usize = 4;

/// The centres (m, rest configuration) of a region that is the union of balls of one radius
/// ([`CondensedSolver::new_union`]; issue 50: a following region around several tools), in a
/// fixed capacity of [`MAX_REGION_BALLS`] (no allocation: the servo's requests carry it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegionBalls {
    centres: [DVec3; MAX_REGION_BALLS],
    len: usize,
}

impl RegionBalls {
    /// No ball.
    pub const EMPTY: Self = Self {
        centres: [DVec3::ZERO; MAX_REGION_BALLS],
        len: 0,
    };

    /// One ball at `centre_m`.
    pub fn one(centre_m: DVec3) -> Self {
        let mut b = Self::EMPTY;
        b.push(centre_m);
        b
    }

    /// Adds a ball at `centre_m`; `false` (nothing added) when full.
    pub fn push(&mut self, centre_m: DVec3) -> bool {
        if self.len == MAX_REGION_BALLS {
            return false;
        }
        self.centres[self.len] = centre_m;
        self.len += 1;
        true
    }

    /// The centres, m.
    pub fn centres(&self) -> &[DVec3] {
        &self.centres[..self.len]
    }

    /// The distance from `p` (m) to the nearest centre, m (infinite without ball).
    pub fn distance(&self, p: DVec3) -> f64 {
        self.centres()
            .iter()
            .map(|c| c.distance(p))
            .fold(f64::INFINITY, f64::min)
    }
}

/// Balls of a union region whose centres are at least this many radii apart keep the far
/// field's coupling between their interfaces out of the tick matrix (it acts through the
/// residual; `build::TickMatrixParts::lower`): their gap is then at least 0.5 radius. Measured
/// steady and accurate at 2.77 radii (`lv_h1_condensed`, tools on opposite sides) and at
/// 2.57 radii (`tests/tools.rs`: forces within 0.6 % of the whole body's).
pub const SEPARATE_BALLS_RADII: f64 = 2.5;

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
/// Built once per scene; [`CondensedSolver::step`] is allocation-free. Its parts: what the
/// scene set (`CondensedParams`), what construction built (`CondensedSystem`), the contact
/// columns prepared for the touchable nodes (`ContactColumns`), what a tick hands to the
/// next (`CondensedState`), what a tick overwrites (`CondensedScratch`) and the counters
/// (`CondensedStats`).
#[derive(Debug, Clone)]
pub struct CondensedSolver {
    params: CondensedParams,
    system: CondensedSystem,
    contact: ContactColumns,
    state: CondensedState,
    scratch: CondensedScratch,
    stats: CondensedStats,
}

/// What a condensed solver was built for (read only).
#[derive(Debug, Clone, Copy)]
struct CondensedParams {
    /// The step the tick matrix was factorised for, s.
    h: f64,
    region: ActiveRegion,
    /// The balls whose union is the region (the first at `region.centre_m`).
    balls: RegionBalls,
}

/// What construction builds once and the tick reads: the split, its numbering, the condensed
/// far part and the tick matrix's factor ([`CondensedSolver::new`]). The supernodal sweep is
/// the one member a tick writes (its own work vectors); the entry factor, when added, is
/// swapped with `factor` / `half` for the ticks that use it ([`CondensedSolver::step`]).
#[derive(Debug, Clone)]
struct CondensedSystem {
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
    schur: Arc<[f32]>,
    /// The AVX2 + FMA token when the CPU has them (the tick's vector loops use them then).
    avx2: Option<Avx2Fma>,
    /// The AVX2 + FMA + F16C token when the CPU has them (the map's rows use that build).
    f16c: Option<Avx2FmaF16c>,
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// Cholesky factor of `A`, single precision.
    factor: Vec<f32>,
    /// The tick's one-column solve ([`SupernodalSolve`], keeping its own work vectors; `None`
    /// for a simplicial factor, solved by faer through `factor`).
    sweep: Option<SupernodalSolve>,
    /// `factor` in half precision for `sweep` (`factor` then holds its rounded values; `None`
    /// when the rounding would move the step too far, [`half_of`], and faer solves through
    /// `factor`).
    half: Option<Arc<HalfFactor>>,
    /// Global component of each row of `map`: the far boundary's free components, or every
    /// far free component for a following region (those of its ring for a tile,
    /// `build::tile_ring`).
    map_dofs: Vec<usize>,
    /// Their displacement per interface displacement, `-(K_FF^-1 K_FG)` rows, row-major
    /// `|map_dofs| x g`, IEEE half precision (bits): it only places far nodes (viewers, the
    /// probe beyond the region, nodes a successor takes over), each to about `3e-4` of the
    /// interface displacement, and it is most of a following region's memory.
    map: Arc<[u16]>,
    /// Rows of `map` on the far boundary (what viewers see), refreshed a slice per tick.
    surface_rows: Vec<u32>,
    /// Following regions: per global component its row of `map` or `u32::MAX`
    /// ([`CondensedSolver::hand_over`]); empty otherwise.
    map_row: Vec<u32>,
    far: FarField,
    sizes: CondensedSizes,
    node_active: Vec<bool>,
    /// The tick matrix with the rest stiffness unscaled (margin 1), used instead of `factor`
    /// on ticks where a node enters the probe's rows ([`CondensedSolver::add_entry_factor`]).
    entry: Option<EntryFactor>,
}

/// The contact columns `A^-1 e` prepared for the touchable nodes
/// ([`CondensedSolver::prepare_contact`]; not per tick).
#[derive(Debug, Clone)]
struct ContactColumns {
    /// Per body node: its column block in `z`, or `u32::MAX`.
    col: Vec<u32>,
    /// `A^-1 e` for the three components of every contact node: per node its three columns of
    /// `m` values one after the other (x, y, z).
    z: Arc<[f32]>,
}

/// What one tick hands to the next.
#[derive(Debug, Clone)]
struct CondensedState {
    /// Factor on the solved velocity (module documentation, "Relaxation"), in
    /// `[MIN_RELAXATION, 1]`.
    relaxation: f64,
    /// The nodes of the last tick's probe rows (capacity [`ENTRY_TRACKED_NODES`]).
    last_contact: Vec<u32>,
    /// Next entry of `surface_rows` to refresh.
    surface_cursor: usize,
}

/// Work arrays every tick overwrites, allocated at construction (`m` equations, `g` interface
/// components).
#[derive(Debug, Clone)]
struct CondensedScratch {
    /// `S u_G` (`g`).
    su: Vec<f64>,
    /// A one-row coupling's row `a` over the equations (`m`).
    a_row: Vec<f32>,
    /// faer's solve workspace.
    stack: Workspace,
    /// Right-hand sides: the step's and the coupling's `U` (`m x 2`).
    rhs: Mat<f32>,
    /// The step's right-hand side in double precision (with interface components only: a
    /// whole-body solver writes it straight into `rhs`).
    b: Vec<f64>,
    /// The probe's correction `A^-1 A^T s`, then the solved velocity `v'` before relaxation.
    z1: Vec<f64>,
    /// Woodbury capacitance of the probe's term (`F x F`, [`MAX_MERGED_ROWS`] squared).
    capacitance: Vec<f64>,
    /// The interface displacement `u_G` (`g`).
    u_gamma: Vec<f64>,
    /// `u_gamma` in single precision, for the map's rows.
    u_gamma32: Vec<f32>,
    /// The far products cut in two for a tick pool ([`CondensedSolver::set_parts`]).
    far_cut: Option<FarCut>,
}

/// The tick's far products (`S u_G` and the far surface rows) cut into two parts of a tick
/// pool's parts job ([`CondensedSolver::set_parts`]).
#[derive(Debug, Clone)]
struct FarCut {
    /// First packed row of `S` of the second part (the rows before it hold about half of
    /// the entries).
    row: usize,
    /// The second part's sums of `S u_G` (`g`; it writes entries `row..` only).
    su: Vec<f64>,
    /// One tick's far surface rows' displacements ([`CondensedSolver::surface_rows_per_tick`]).
    surface_u: Vec<f64>,
}

impl CondensedScratch {
    /// Zeroed work arrays for `m` equations and `g` interface components; `stack` the solve
    /// workspace.
    fn new(m: usize, g: usize, stack: Workspace) -> Self {
        Self {
            su: vec![0.0; g],
            a_row: vec![0.0; m],
            stack,
            rhs: Mat::zeros(m, 2),
            b: vec![0.0; m],
            z1: vec![0.0; m],
            capacitance: vec![0.0; MAX_MERGED_ROWS * MAX_MERGED_ROWS],
            u_gamma: vec![0.0; g],
            u_gamma32: vec![0.0; g],
            far_cut: None,
        }
    }
}

/// Counters for reports.
#[derive(Debug, Clone, Copy, Default)]
struct CondensedStats {
    /// Ticks whose velocity reversed (each halved the relaxation).
    relaxed_ticks: u64,
    /// Components the last hand-over from this region started at rest for lack of a row
    /// ([`CondensedSolver::unmapped_hand_over`]).
    unmapped_hand_over: usize,
}

/// A one-row probe coupling over `N` nodes is solved by the paired sweep
/// ([`SupernodalSolve::forward_pair`]) instead of the prepared columns when the columns'
/// `3 N m` multiply-adds (read from memory) reach this share of the factor's entries (the
/// paired sweep's extra arithmetic, on entries it reads anyway). Measured in one process on
/// this 2-core AVX2 machine, the two alternated: at 0.20 (built-in `lv`, 12 patch nodes) the
/// columns were 17 % faster per tick, at 0.32 (`lv_h1_condensed`, 55) the same, at 0.40
/// (`lv_100k_condensed`, 100) the paired sweep 16-22 % faster.
pub const PAIRED_SWEEP_MIN_RATIO: f64 = 0.3;

/// A far part whose `S` (packed upper triangle) holds fewer entries than this keeps its far
/// products whole whatever the thread count ([`CondensedSolver::set_parts`]): a part's
/// products are then too short for the hand-over between the threads to pay.
pub const CUT_FAR_MIN_ENTRIES: usize = 100_000;

/// Probe-row nodes remembered between ticks to tell a node entering the contact.
const ENTRY_TRACKED_NODES: usize = 3 * MAX_MERGED_ROWS;

/// A second numeric factor on the solver's analysis and its prepared contact columns
/// ([`CondensedSolver::add_entry_factor`]).
#[derive(Debug, Clone)]
struct EntryFactor {
    factor: Vec<f32>,
    half: Option<Arc<HalfFactor>>,
    contact_z: Arc<[f32]>,
}

impl CondensedSolver {
    /// Far-surface rows refreshed per tick: [`SURFACE_REFRESH_TICKS`] ticks for all, or
    /// fewer rows when that exceeds [`SURFACE_REFRESH_MAX_MACS`].
    fn surface_rows_per_tick(&self) -> usize {
        let g = self.system.gamma_dof.len().max(1);
        self.system
            .surface_rows
            .len()
            .div_ceil(SURFACE_REFRESH_TICKS)
            .min((SURFACE_REFRESH_MAX_MACS / g).max(1))
    }

    /// Cuts the tick's far products (`S u_G` by packed rows, the far surface rows of the
    /// tick by halves) into two parts for a tick pool of `parts` threads (issue 48 s1), when
    /// `parts >= 2` and `S` holds at least [`CUT_FAR_MIN_ENTRIES`] entries; with `parts` 1
    /// the cut is removed. [`Self::step_in`] then runs them as a parts job of its pool (a
    /// following region's coarse companion ticks later, beside the solve). `S u_G` then sums the two parts' rows separately (double-precision round-off),
    /// whoever runs them. The sweeps stay whole: the interface's dense `S` makes the tick
    /// factor top-heavy (docs/decisions.md, "The condensed tick on two threads"). Returns
    /// whether it cut. Set-up, not a tick: allocates (call it on a prepared region before
    /// it is swapped in).
    pub fn set_parts(&mut self, parts: usize) -> bool {
        let g = self.system.gamma_dof.len();
        self.scratch.far_cut = (parts >= 2 && g * (g + 1) / 2 >= CUT_FAR_MIN_ENTRIES).then(|| {
            // Row `a` of the packed triangle holds `g - a` entries: the first `row` rows hold
            // half of them when `(g - row)^2 = g^2 / 2`.
            let row = ((g as f64) * (1.0 - std::f64::consts::FRAC_1_SQRT_2)).round() as usize;
            FarCut {
                row: row.min(g),
                su: vec![0.0; g],
                surface_u: vec![0.0; self.surface_rows_per_tick()],
            }
        });
        self.scratch.far_cut.is_some()
    }

    /// Ticks a full refresh of the far surface takes (at most the viewers' lag behind the
    /// interface): [`SURFACE_REFRESH_TICKS`], more on large far surfaces
    /// ([`SURFACE_REFRESH_MAX_MACS`]); 0 without far surface.
    pub fn surface_refresh_ticks(&self) -> usize {
        let rows = self.system.surface_rows.len();
        if rows == 0 {
            0
        } else {
            rows.div_ceil(self.surface_rows_per_tick())
        }
    }

    /// The active elements as a model over the whole body's nodes: its
    /// [`FemModel::add_internal_forces`] gives the active region's forces.
    pub fn active_model(&self) -> &FemModel {
        &self.system.active
    }

    /// The region this solver simulates (of a union, the first ball's centre).
    pub fn region(&self) -> ActiveRegion {
        self.params.region
    }

    /// The balls whose union is the region ([`CondensedSolver::new_union`]; one otherwise).
    pub fn balls(&self) -> RegionBalls {
        self.params.balls
    }

    /// Whether the region holds every element (nothing condensed: backward Euler with the rest
    /// factor on the whole body, [`crate::integrate::LinearSolver::RestCholesky`]).
    pub fn is_whole_body(&self) -> bool {
        self.system.gamma_dof.is_empty() && self.system.far.dofs.is_empty()
    }

    /// Sizes of the split, for reports.
    pub fn sizes(&self) -> CondensedSizes {
        self.system.sizes
    }

    /// Ticks so far whose solved velocity field reversed and was relaxed, and the factor on
    /// the velocity now (module documentation, "Relaxation").
    pub fn relaxation(&self) -> (u64, f64) {
        (self.stats.relaxed_ticks, self.state.relaxation)
    }

    /// Step the matrix was factorised for, s.
    pub fn dt_s(&self) -> f64 {
        self.params.h
    }

    /// Whether node `i` belongs to an active element.
    pub fn is_active_node(&self, i: u32) -> bool {
        self.system.node_active[i as usize]
    }

    /// Whether every corner of triangle `t` is an active node (contact and loads must stay
    /// on such triangles).
    pub fn is_active_triangle(&self, t: &[u32; 3]) -> bool {
        t.iter().all(|&i| self.is_active_node(i))
    }

    /// Drops what a stepped copy of a prepared following region never reads (a cached tile,
    /// [`TileMode::Background`]; issue 48 s2): the far coupling `K_FG` triplets when there is
    /// no far factor (only [`Self::recover_far_field`] reads them, with that factor; a
    /// following region keeps none), and the single-precision tick factor when the tick
    /// sweeps its half-precision copy and there is no entry factor (then only
    /// [`Self::prepare_contact`] reads it: call that first; afterwards it prepares nothing).
    /// Steps are unchanged bit for bit. Returns the bytes freed ([`Self::memory_bytes`]).
    pub fn trim_for_tiles(&mut self) -> usize {
        let before = self.memory_bytes();
        let sys = &mut self.system;
        if sys.far.llt.is_none() {
            sys.far.kfg = Vec::new();
        }
        if sys.sweep.is_some() && sys.half.is_some() && sys.entry.is_none() {
            sys.factor = Vec::new();
        }
        before - self.memory_bytes()
    }

    /// Reads every numeric array the tick reads once (one byte per cache line) and returns a
    /// sum to keep the reads: a region whose arrays are shared with a tile that has not been
    /// read for a while ([`Self::trim_for_tiles`], [`crate::integrate::follow`]) gets them
    /// back into the caches and its pages into memory on the preparing thread, not on the
    /// servo's first tick with it. About a millisecond for a 20 MB region.
    pub fn touch(&self) -> u64 {
        use crate::linalg::supernodal::touch_words;
        let sys = &self.system;
        touch_words(&sys.map)
            .wrapping_add(touch_words(&sys.schur))
            .wrapping_add(touch_words(&sys.factor))
            .wrapping_add(touch_words(&self.contact.z))
            .wrapping_add(sys.half.as_ref().map_or(0, |h| h.touch()))
    }

    /// Bytes of everything the region holds on the heap, about: [`Self::memory_bytes`] plus
    /// the active elements' model ([`FemModel::heap_bytes`]), the tick factor's symbolic
    /// analysis and sweep, the index arrays and the tick's work arrays. What a region cache
    /// counts against its memory limit ([`crate::integrate::follow::RegionCacheDir`]).
    pub fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        let sys = &self.system;
        let sc = &self.scratch;
        let indices = b(&sys.eq)
            + b(&sys.eq_dof)
            + b(&sys.mass)
            + b(&sys.gamma_dof)
            + b(&sys.map_dofs)
            + b(&sys.surface_rows)
            + b(&sys.map_row)
            + b(&sys.node_active)
            + b(&sys.far.dofs)
            + b(&self.contact.col)
            + b(&self.state.last_contact);
        let work = b(&sc.su)
            + b(&sc.a_row)
            + sc.stack.req.size_bytes()
            + 4 * sc.rhs.nrows() * sc.rhs.ncols()
            + b(&sc.b)
            + b(&sc.z1)
            + b(&sc.capacitance)
            + b(&sc.u_gamma)
            + b(&sc.u_gamma32)
            + sc.far_cut
                .as_ref()
                .map_or(0, |c| b(&c.su) + b(&c.surface_u));
        self.memory_bytes()
            + sys.active.heap_bytes()
            + crate::linalg::ordering::symbolic_heap_bytes(&sys.symbolic)
            + sys.sweep.as_ref().map_or(0, SupernodalSolve::heap_bytes)
            + indices
            + work
    }

    /// Bytes held by the region's numeric arrays (tick factor, maps, coupling columns, far
    /// factor), for reports; index arrays and the active elements' model are not counted.
    pub fn memory_bytes(&self) -> usize {
        let far = self
            .system
            .far
            .llt
            .as_ref()
            .map_or(0, |l| 8 * l.factor_entries());
        let half = |h: &Option<Arc<HalfFactor>>| h.as_ref().map_or(0, |h| h.memory_bytes());
        let entry = self.system.entry.as_ref().map_or(0, |e| {
            4 * (e.factor.len() + e.contact_z.len()) + half(&e.half)
        });
        entry
            + half(&self.system.half)
            + 4 * (self.system.factor.len() + self.system.schur.len() + self.contact.z.len())
            + 2 * self.system.map.len()
            + 24 * self.system.far.kfg.len()
            + far
    }
}
