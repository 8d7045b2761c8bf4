//! Time integrators: the seed's semi-implicit scheme (seed 000 eq. 34), symplectic Euler and
//! implicit backward Euler, the critical (Courant) time step, sub-stepping of a servo tick, and
//! [`Stepper`], the one type the FEM body steps with ([`explicit`], [`implicit`], [`condensed`]).
//!
//! Backward Euler ([`implicit::ImplicitSolver`]) takes one Newton step of the implicit equations per
//! sub-step (Baraff & Witkin 1998, "Large steps in cloth simulation", eq. 15-18): with
//! `v' = v + dv`, `x' = x + h v'`, the linearisation `f(x', v') ~ f_el(x) - K(x) h v' - D(x) v'`
//! (the viscous force of eq. 10-11 is linear in the velocity, `f_visc(x, v) = -D(x) v`) and the
//! mass damping `-alpha M v'` treated implicitly gives
//!
//! `A dv = h (f_el(x) + f_visc(x, v) + f_ext - U phi0 - alpha M v) - h^2 K v - gamma U U^T v`,
//! with `A = M (1 + alpha h) + h D(x) + h^2 K(x) + gamma U U^T`,
//!
//! which, because `f_visc = -D v`, is `A dv = M v + h (f_el + f_ext - U phi0) - A v`: the
//! viscous force is never evaluated separately. `gamma U U^T` is the probe's virtual coupling
//! (rank one over the contact patch, `gamma = h (k h + b)`, see
//! [`crate::contact::Probe::coupling_gamma`]), so the coupling is exactly implicit inside the
//! same solve; in general the probe's term is `h^2 A^T C A` ([`crate::contact::ContactCoupling`]:
//! one row for the patch, one per face in contact for the implicit sphere). `A` is applied matrix-free in one element loop on deformation gradients cached at
//! the start of the step (the material's tangent, see `Operator::apply`, plus the viscous
//! action) and the system is solved by preconditioned conjugate gradients, warm-started with
//! the previous step's `dv`, capped at `cg_max_iterations` or a relative residual of
//! `cg_tolerance`. The preconditioner is block-Jacobi on the 3x3 blocks of `A` at rest
//! (constant per sub-step size) plus the probe's low-rank term, inverted exactly by
//! Woodbury (Sherman-Morrison for the patch's single row). Follower pressure is explicit (its load stiffness is not symmetric).
//! Constrained components are projected out of the system.
//!
//! Owns: the step of the dynamic state and the completion of the probe's virtual coupling in
//! each scheme. May use: [`crate::element`] (forces, masses, tangent action, rest blocks),
//! [`crate::contact`] (the probe and its low-rank coupling term), [`crate::material`],
//! [`crate::mesh`]. Used by the FEM body ([`crate::fem`]), which calls [`Stepper::step`] once
//! per sub-step.

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::contact::{ContactCoupling, ContactModel, CouplingMerge, Probe};
use crate::element::{FemModel, ForceScratch, PartRunner};
use crate::material::MaterialParams;
use crate::mesh::TetMesh;

pub mod condensed;
pub mod explicit;
pub mod follow;
pub mod implicit;
pub(crate) mod region_section;

use crate::pool::TickPool;
use condensed::{ActiveRegion, CondensedSolver};
use implicit::{CgStats, ImplicitSolver};

/// Which time integrator advances the FEM nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntegratorKind {
    /// Seed 000 eq. 34: explicit velocity predictor, then `v = (I - dt^2/m J_ii)^-1 v~` with the
    /// per-node 3x3 Jacobian `J_ii = dF_i/dx_i` precomputed at rest, then `x += dt v`.
    SemiImplicit,
    /// Symplectic (semi-implicit) Euler: `v += dt F/m`, `x += dt v`. The explicit reference.
    SymplecticEuler,
    /// Implicit backward Euler, one Newton step per sub-step solved by preconditioned CG
    /// ([`ImplicitSolver`]). Unconditionally stable for the linearised system, so one sub-step
    /// per tick by default.
    BackwardEuler,
}

/// The contact model an FEM body uses for the scene's `requested` one:
/// [`ContactModel::Auto`] becomes the kernel patch with the sphere's local indentation in series
/// ([`ContactModel::PatchLocal`]: the material's own law of a sphere on a half-space, the patch
/// raised by its rest sag, a fixed footprint) under every integrator. On the real-time LV meshes
/// it is the most accurate model against the rigid-sphere reference (`docs/accuracy.md`,
/// "The sphere's local law in the patch"): the exact sphere reaches its mesh's own equilibrium,
/// but the default mesh's facets, 2-4 mm, are coarser than the contact, and it reads 60-90 %
/// high there; the plain patch spreads the load over 4 mm and reads 75-90 % high; the patch with
/// Hertz's linear law (the default until 2026-11-26) read 17-23 % low at 0.5 mm and 10 % high at
/// 4 mm. The sphere runs under every integrator: explicit in the step
/// under the explicit ones, implicit (the faces in contact as penalty springs in series with
/// the coupling, solved inside the step; [`crate::contact::Probe::use_implicit_sphere`]) under
/// backward Euler and the condensed model (frictionless or with the friction cone of the
/// other models), so the integrator does not enter the choice.
pub fn resolve_contact_model(requested: ContactModel) -> ContactModel {
    match requested {
        ContactModel::Auto => ContactModel::PatchLocal,
        other => other,
    }
}

impl IntegratorKind {
    /// Every integrator, in the order of the scene-file documentation (for parsing and
    /// listings; the README test checks each is documented).
    pub const ALL: [IntegratorKind; 3] = [
        Self::SemiImplicit,
        Self::SymplecticEuler,
        Self::BackwardEuler,
    ];

    /// The name used in scene files (`semi-implicit`, `symplectic-euler`, `backward-euler`).
    pub fn name(self) -> &'static str {
        match self {
            Self::SemiImplicit => "semi-implicit",
            Self::SymplecticEuler => "symplectic-euler",
            Self::BackwardEuler => "backward-euler",
        }
    }

    /// Parses a scene-file name (see [`IntegratorKind::name`]); `None` if unknown.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

/// How backward Euler solves its linear system.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LinearSolver {
    /// Matrix-free preconditioned CG on the tangent at the current state, capped at
    /// `cg_max_iterations` ([`ImplicitSolver`]).
    #[default]
    Cg,
    /// The tick matrix frozen at rest (stiffness times `stiffness_margin`), Cholesky-factorised
    /// once at set-up and solved directly every tick: a modified Newton step per tick whose
    /// equilibria are exact ([`CondensedSolver`] with a region holding every element). Costs one
    /// force evaluation and two triangular sweeps per tick, memory for the factor and for the
    /// prepared contact columns (`12 m` bytes per touchable node, `m` equations).
    RestCholesky,
}

impl LinearSolver {
    /// Every linear solver, in the order of the docs.
    pub const ALL: [LinearSolver; 2] = [Self::Cg, Self::RestCholesky];

    /// The name used in scene files (`cg`, `rest-cholesky`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Cg => "cg",
            Self::RestCholesky => "rest-cholesky",
        }
    }

    /// Parses a scene-file name (see [`LinearSolver::name`]); `None` if unknown.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

/// Integrator settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntegratorParams {
    /// Which scheme.
    pub kind: IntegratorKind,
    /// Servo tick (one call of `FemBody::tick`), s. Default 1 ms.
    pub tick_s: f64,
    /// Fixed sub-steps per tick; `None` chooses the fewest that keep the sub-step below
    /// `safety_factor` times the critical time step.
    pub substeps: Option<u32>,
    /// Largest sub-step count allowed; a configuration needing more is rejected as unstable.
    pub max_substeps: u32,
    /// Fraction of the critical time step used when sub-steps are automatic (0, 1]. The
    /// critical step is computed at rest, but St. Venant-Kirchhoff stiffens under stretch (the
    /// tangent grows by about `(3 lambda^2 - 1) / 2` at stretch `lambda`), so a probe pressing a
    /// few millimetres into soft tissue needs margin (default 0.5; why: `docs/decisions.md`,
    /// "Safety factor 0.5, not 0.8").
    pub safety_factor: f64,
    /// Backward Euler: largest number of conjugate-gradient iterations per Newton step.
    /// Default 20.
    pub cg_max_iterations: u32,
    /// Backward Euler: relative residual `|r| / |rhs|` at which CG stops. Default 1e-3.
    pub cg_tolerance: f64,
    /// Backward Euler: how the step's linear system is solved (default [`LinearSolver::Cg`]).
    /// A scene with an active region always uses the rest factor (of its region).
    pub linear_solver: LinearSolver,
    /// Backward Euler with [`LinearSolver::RestCholesky`]: factor `c` in `[1, 100]` on the rest
    /// stiffness of the frozen matrix ([`ActiveRegion::stiffness_margin`]; default
    /// [`condensed::DEFAULT_STIFFNESS_MARGIN`]).
    pub stiffness_margin: f64,
    /// Whether [`plan_steps`] refuses a step above the critical one (default true). Off only in
    /// stress tests and benchmarks that must run a known-unstable configuration to show that the
    /// divergence monitor reports it ([`ModelError::Diverged`]) instead of producing NaN.
    pub check_critical_step: bool,
    /// Whether the servo's internal forces run through the single-precision kernel
    /// ([`FemModel::set_single_precision`]; scene key `force_precision = "single"`). Default
    /// false (double precision).
    pub single_precision_forces: bool,
}

impl Default for IntegratorParams {
    fn default() -> Self {
        Self {
            kind: IntegratorKind::SemiImplicit,
            tick_s: 1e-3,
            substeps: None,
            max_substeps: 64,
            safety_factor: 0.5,
            cg_max_iterations: 20,
            cg_tolerance: 1e-3,
            linear_solver: LinearSolver::Cg,
            stiffness_margin: condensed::DEFAULT_STIFFNESS_MARGIN,
            check_critical_step: true,
            single_precision_forces: false,
        }
    }
}

/// How a servo tick is divided: `substeps` model steps of `sub_dt_s` each.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepPlan {
    /// Model steps per servo tick.
    pub substeps: u32,
    /// Model step, s (`tick_s / substeps`).
    pub sub_dt_s: f64,
    /// Stability limit of the integrator on this mesh and material, s (`f64::INFINITY` when the
    /// analysis finds none).
    pub critical_dt_s: f64,
}

/// Stiffness-proportional damping factor `beta` (s) bounding the viscous stress of eq. 11 at
/// rest: the viscous damping matrix is the stiffness matrix with `(lambda, mu)` replaced by
/// `(2 phi, 2 psi)`, so `D <= beta K` with `beta = max(2 phi / lambda, 2 psi / mu)`.
pub fn viscous_beta_s(m: &MaterialParams) -> f64 {
    let a = if m.lambda_pa > 0.0 {
        2.0 * m.phi_pa_s / m.lambda_pa
    } else {
        0.0
    };
    a.max(2.0 * m.psi_pa_s / m.mu_pa)
}

/// The symplectic Euler step limit (s) of a mode `omega2_per_s2 = omega^2` (1/s^2) damped by
/// the stiffness-proportional factor `beta_s` ([`viscous_beta_s`]): `(2 / omega) (sqrt(1 +
/// xi^2) - xi)` with `xi = beta omega / 2`; infinite when `omega2_per_s2 <= 0`.
pub fn damped_critical_step_s(omega2_per_s2: f64, beta_s: f64) -> f64 {
    if omega2_per_s2 <= 0.0 {
        return f64::INFINITY;
    }
    let w = omega2_per_s2.sqrt();
    let xi = beta_s * w / 2.0;
    2.0 / w * ((1.0 + xi * xi).sqrt() - xi)
}

/// The inverse of [`damped_critical_step_s`]: the largest `omega^2` (1/s^2) whose step limit
/// is at least `dt_s` (s). With `a = 2 / dt`: `omega^2 = a^2 / (1 + a beta)` (squaring
/// `omega sqrt(1 + xi^2) = a - beta omega^2 / 2`).
pub fn damped_max_omega2_per_s2(dt_s: f64, beta_s: f64) -> f64 {
    let a = 2.0 / dt_s;
    a * a / (1.0 + a * beta_s)
}

/// Critical (Courant) time step of `kind` on `fem`, s.
///
/// - Symplectic Euler: `dt_crit = (2 / omega_max) (sqrt(1 + xi^2) - xi)` with
///   `omega_max^2 = lambda_max(M^-1 K)` from power iteration on the assembled-free stiffness
///   action and `xi = beta omega_max / 2` for the viscous stress ([`viscous_beta_s`]).
/// - Semi-implicit (seed 000 eq. 34): a modal analysis of the scheme,
///   `M (v' - v) = -dt K x - dt^2 K_D v'`, is stable when `dt^2 (omega^2 - 2 d) <= 4` where
///   `d` is the Rayleigh quotient of the block diagonal `K_D`; so
///   `dt_crit = 2 / sqrt(lambda_max(M^-1 (K - 2 K_D)))`, infinite when that is not positive.
///   This is exact for commuting `K`, `K_D` and a good estimate otherwise (hence the safety factor).
/// - Backward Euler: `f64::INFINITY` (unconditionally stable for the linearised system).
pub fn critical_time_step(fem: &FemModel, kind: IntegratorKind) -> f64 {
    let beta = viscous_beta_s(fem.material());
    let damped = |w2: f64| damped_critical_step_s(w2, beta);
    match kind {
        IntegratorKind::SymplecticEuler => damped(fem.max_eigenvalue(0.0, 300)),
        IntegratorKind::SemiImplicit => damped(fem.max_eigenvalue(2.0, 300)),
        IntegratorKind::BackwardEuler => f64::INFINITY,
    }
}

/// Chooses the sub-steps of a servo tick.
///
/// # Errors
/// [`ModelError::Unstable`] when fixed `substeps` give a step above `critical_dt_s`, or when
/// automatic sub-stepping would need more than `max_substeps` (neither when
/// `check_critical_step` is off: automatic sub-stepping then uses at most `max_substeps`).
pub fn plan_steps(p: &IntegratorParams, critical_dt_s: f64) -> Result<StepPlan, ModelError> {
    let unstable = |n: u32, max_substeps: u32| ModelError::Unstable {
        integrator: p.kind.name(),
        critical_dt_s,
        tick_s: p.tick_s,
        max_substeps,
        sub_dt_s: p.tick_s / n as f64,
    };
    let substeps = match p.substeps {
        Some(n) => {
            let n = n.max(1);
            if p.check_critical_step && p.tick_s / n as f64 > critical_dt_s {
                return Err(unstable(n, n));
            }
            n
        }
        None => {
            let need = (p.tick_s / (p.safety_factor * critical_dt_s))
                .ceil()
                .max(1.0);
            if need > p.max_substeps as f64 {
                if p.check_critical_step {
                    return Err(unstable(p.max_substeps, p.max_substeps));
                }
                p.max_substeps
            } else {
                need as u32
            }
        }
    };
    Ok(StepPlan {
        substeps,
        sub_dt_s: p.tick_s / substeps as f64,
        critical_dt_s,
    })
}

/// Dynamic state of a body: what a [`Stepper`] advances.
#[derive(Debug, Clone)]
pub struct FemState {
    /// Node positions, m.
    pub x: Vec<DVec3>,
    /// Node velocities, m/s.
    pub v: Vec<DVec3>,
    /// Simulated time, s.
    pub time_s: f64,
}

/// What one step reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// Largest squared nodal speed after the step among the nodes the step moved, m^2/s^2;
    /// NaN when any of them became non-finite (divergence checks).
    pub max_speed2_m2_per_s2: f64,
}

/// The time stepper of a FEM body: one type per scheme, each completing the probe's virtual
/// coupling its own way (module documentation).
#[derive(Debug, Clone)]
pub enum Stepper {
    /// Seed eq. 34 ([`IntegratorKind::SemiImplicit`]) or symplectic Euler, node by node; the
    /// coupling is solved over the contact patch by Sherman-Morrison
    /// ([`Probe::finish_implicit`]).
    Explicit {
        /// [`IntegratorKind::SemiImplicit`] or [`IntegratorKind::SymplecticEuler`].
        kind: IntegratorKind,
        /// Seed eq. 34 per-node matrices `A_i^-1` (semi-implicit only; empty otherwise).
        a_inv: Vec<DMat3>,
        /// Sub-step, s.
        dt_s: f64,
    },
    /// Backward Euler on the whole body, the coupling inside its CG solve.
    Implicit(Box<ImplicitSolver>),
    /// Backward Euler on a contact-local active region with the rest condensed, the coupling
    /// added by Woodbury to its prefactored solve.
    Condensed(Box<CondensedSolver>),
}

impl Stepper {
    /// The stepper of `params.kind` for `fem` (mesh `mesh`) with sub-step `plan.sub_dt_s`; with
    /// an active region, the condensed one.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] for an active region with another integrator than backward
    /// Euler; the errors of [`CondensedSolver::new`].
    pub fn new(
        fem: &FemModel,
        mesh: &TetMesh,
        params: &IntegratorParams,
        plan: &StepPlan,
        region: Option<ActiveRegion>,
    ) -> Result<Self, ModelError> {
        Self::new_with_progress(fem, mesh, params, plan, region, &mut |_, _| {})
    }

    /// [`Stepper::new`] reporting the condensation's stages
    /// ([`CondensedSolver::new_with_progress`]); the other steppers report nothing.
    ///
    /// # Errors
    /// As [`Stepper::new`].
    pub fn new_with_progress(
        fem: &FemModel,
        mesh: &TetMesh,
        params: &IntegratorParams,
        plan: &StepPlan,
        region: Option<ActiveRegion>,
        progress: &mut dyn FnMut(&str, f64),
    ) -> Result<Self, ModelError> {
        let h = plan.sub_dt_s;
        Ok(match (params.kind, region) {
            (IntegratorKind::BackwardEuler, Some(r)) => {
                Self::Condensed(Box::new(CondensedSolver::new_in_threads(
                    fem,
                    mesh,
                    r,
                    condensed::RegionBalls::one(r.centre_m),
                    h,
                    condensed::setup_threads(),
                    progress,
                )?))
            }
            (_, Some(_)) => {
                return Err(ModelError::field(
                    "active_region",
                    "needs integrator.kind = \"backward-euler\"",
                ));
            }
            (IntegratorKind::BackwardEuler, None) => {
                Self::Implicit(Box::new(ImplicitSolver::new(fem, h, params)))
            }
            (kind, None) => Self::Explicit {
                kind,
                a_inv: if kind == IntegratorKind::SemiImplicit {
                    explicit::semi_implicit_inverses(fem, h)
                } else {
                    Vec::new()
                },
                dt_s: h,
            },
        })
    }

    /// The scheme.
    pub fn kind(&self) -> IntegratorKind {
        match self {
            Self::Explicit { kind, .. } => *kind,
            Self::Implicit(_) | Self::Condensed(_) => IntegratorKind::BackwardEuler,
        }
    }

    /// The elements whose internal forces drive a step: `body`, or the active region of a
    /// condensed model.
    pub fn force_model<'a>(&'a self, body: &'a FemModel) -> &'a FemModel {
        match self {
            Self::Condensed(c) => c.active_model(),
            _ => body,
        }
    }

    /// Adds the internal forces a step needs (N) to `f`, for the state `x`, `v`: elastic and
    /// viscous for the explicit schemes, elastic only for backward Euler (which treats the
    /// viscous force implicitly inside its solve). Allocation-free.
    /// With `scratch` for the model's node count, a model with single precision enabled uses
    /// it ([`FemModel::add_internal_forces_with`]).
    pub fn add_internal_forces(
        &self,
        body: &FemModel,
        x: &[DVec3],
        v: &[DVec3],
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) {
        self.force_model(body)
            .add_internal_forces_with(x, self.viscous_velocities(v), f, scratch);
    }

    /// The velocities the viscous stress takes: the explicit schemes' `v`; none for the
    /// implicit ones, whose solve treats the viscous force implicitly.
    fn viscous_velocities<'v>(&self, v: &'v [DVec3]) -> Option<&'v [DVec3]> {
        match self {
            Self::Explicit { .. } => Some(v),
            Self::Implicit(_) | Self::Condensed(_) => None,
        }
    }

    /// [`Self::add_internal_forces`] cut into parts that `pool` runs
    /// ([`FemModel::add_internal_forces_in`]: the arithmetic depends only on the number of parts,
    /// `min(pool.threads(), scratch.parts())`; one part is [`Self::add_internal_forces`] bit for
    /// bit). Allocation-free.
    pub fn add_internal_forces_in<R: PartRunner + ?Sized>(
        &self,
        pool: &R,
        body: &FemModel,
        (x, v): (&[DVec3], &[DVec3]),
        f: &mut [DVec3],
        scratch: &mut ForceScratch,
    ) {
        self.force_model(body).add_internal_forces_in(
            pool,
            x,
            self.viscous_velocities(v),
            f,
            scratch,
        );
    }

    /// Advances `state` (positions, velocities; not the time) by one sub-step from the nodal
    /// forces `f` (N: internal forces from [`Stepper::add_internal_forces`], external loads and
    /// the coupling's explicit reaction, [`Probe::add_reaction`]) and completes the probe's
    /// coupling: afterwards `probe.state` holds the device force of the step. Allocation-free.
    ///
    /// # Panics
    /// If the slices are shorter than the body's node count.
    pub fn step(
        &mut self,
        body: &FemModel,
        f: &[DVec3],
        probe: &mut Probe,
        state: &mut FemState,
    ) -> StepReport {
        // One probe never joins terms: an empty merge allocates nothing.
        let mut merge = CouplingMerge::default();
        self.step_tools(
            None,
            None,
            body,
            f,
            std::slice::from_mut(probe),
            &mut merge,
            state,
        )
    }

    /// [`Self::step`] with several probes (tools, issue 50) acting on the body in the same
    /// step: `f` holds every probe's explicit reaction. Backward Euler solves all the probes'
    /// terms at once: with two or more in contact, their rows joined in `merge` (sized for
    /// `probes`, [`CouplingMerge::with_capacity`]) with the block-diagonal compliance, exact
    /// in the same Woodbury solve; with at most one, that probe's term as [`Self::step`]
    /// (bit for bit). The explicit schemes complete the probes' couplings one after another
    /// (Sherman-Morrison each, on the velocities the previous one left). A condensed region
    /// runs the pieces [`CondensedSolver::set_parts`] cut on `pool` and `beside` (other work
    /// of the tick) on a worker beside its solve ([`CondensedSolver::step_in`]); the other
    /// steppers run `beside` first. Allocation-free (`beside` aside).
    ///
    /// # Panics
    /// As [`Self::step`]; when `merge` is too small for the probes in contact.
    #[allow(clippy::too_many_arguments)]
    pub fn step_tools(
        &mut self,
        pool: Option<&TickPool>,
        beside: Option<&mut (dyn FnMut() + Send)>,
        body: &FemModel,
        f: &[DVec3],
        probes: &mut [Probe],
        merge: &mut CouplingMerge,
        state: &mut FemState,
    ) -> StepReport {
        let (x, v) = (&mut state.x, &mut state.v);
        let beside = match (self.condensed(), beside) {
            (None, Some(b)) => {
                b();
                None
            }
            (_, b) => b,
        };
        let max_v2 = match self {
            Self::Condensed(solver) => {
                let h = solver.dt_s();
                let coupling = joined_coupling(probes, merge, h);
                let max_v2 = solver.step_in(pool, beside, f, coupling, x, v);
                probes.iter_mut().for_each(|p| p.finish_solved(h, v));
                max_v2
            }
            Self::Implicit(solver) => {
                let h = solver.dt_s();
                let max_v2 = solver.step(body, f, joined_coupling(probes, merge, h), x, v);
                probes.iter_mut().for_each(|p| p.finish_solved(h, v));
                max_v2
            }
            Self::Explicit { kind, a_inv, dt_s } => {
                let (kind, h) = (*kind, *dt_s);
                let mut max_v2 = explicit::integrate_nodes(kind, body, a_inv, h, f, x, v);
                for probe in probes.iter_mut().filter(|p| p.state.in_contact) {
                    probe.finish_implicit(h, x, v, |i, w| {
                        explicit::apply_inverse(kind, body, a_inv, h, i, w)
                    });
                    // The completion moved the patch nodes again.
                    for &i in probe.patch().0 {
                        let s = v[i as usize].length_squared();
                        if !s.is_finite() || s > max_v2 {
                            max_v2 = if s.is_finite() { s } else { f64::NAN };
                        }
                    }
                }
                max_v2
            }
        };
        StepReport {
            max_speed2_m2_per_s2: max_v2,
        }
    }

    /// Conjugate-gradient statistics of the last whole-body backward Euler step (default for
    /// the other schemes).
    pub fn cg_stats(&self) -> CgStats {
        match self {
            Self::Implicit(s) => s.stats(),
            _ => CgStats::default(),
        }
    }

    /// Forgets what a step carries over to the next (the backward Euler warm start), after the
    /// state was replaced from outside.
    pub fn reset(&mut self) {
        if let Self::Implicit(s) = self {
            s.reset_warm_start();
        }
    }

    /// The condensed solver, when the body has an active region.
    pub fn condensed(&self) -> Option<&CondensedSolver> {
        match self {
            Self::Condensed(c) => Some(c),
            _ => None,
        }
    }

    /// The condensed solver, mutably (set-up: [`CondensedSolver::set_parts`]).
    pub fn condensed_mut(&mut self) -> Option<&mut CondensedSolver> {
        match self {
            Self::Condensed(c) => Some(c),
            _ => None,
        }
    }
}

/// The implicit term of `probes` for sub-step `h`: none out of contact, the one probe's in
/// contact, or the terms of those in contact joined in `merge` (block-diagonal compliance).
fn joined_coupling<'a>(
    probes: &'a mut [Probe],
    merge: &'a mut CouplingMerge,
    h: f64,
) -> Option<ContactCoupling<'a>> {
    let touching = probes.iter().filter(|p| p.state.in_contact).count();
    if touching <= 1 {
        return probes
            .iter_mut()
            .find(|p| p.state.in_contact)
            .and_then(|p| p.coupling(h));
    }
    merge.clear();
    for p in probes.iter_mut() {
        if let Some(c) = p.coupling(h) {
            merge.push(c);
        }
    }
    merge.view()
}

#[cfg(test)]
mod tests {
    use super::{damped_critical_step_s, damped_max_omega2_per_s2};

    /// Largest amplitude over 4 000 symplectic Euler steps of `x'' = -w^2 x - beta w^2 x'`
    /// (the stiffness-proportional damping explicit, as in the step), from `x = 1`.
    fn growth(omega2: f64, beta: f64, dt: f64) -> f64 {
        let (mut x, mut v, mut largest) = (1.0f64, 0.0f64, 0.0f64);
        for _ in 0..4000 {
            v += dt * (-omega2 * x - beta * omega2 * v);
            x += dt * v;
            largest = largest.max(x.abs());
        }
        largest
    }

    #[test]
    fn the_damped_step_limit_is_where_a_damped_mode_turns_unstable() {
        for (omega2, beta) in [(1e6, 0.0), (1e6, 1e-4), (4e8, 5e-5), (1e4, 0.05)] {
            let dt = damped_critical_step_s(omega2, beta);
            assert!(growth(omega2, beta, 0.99 * dt) < 10.0, "{omega2} {beta}");
            assert!(growth(omega2, beta, 1.01 * dt) > 1e3, "{omega2} {beta}");
            // The inverse: the largest omega^2 whose limit is that step.
            let back = damped_max_omega2_per_s2(dt, beta);
            assert!(
                (back / omega2 - 1.0).abs() < 1e-12,
                "{back} against {omega2}"
            );
        }
        assert_eq!(damped_critical_step_s(0.0, 1e-3), f64::INFINITY);
    }
}
