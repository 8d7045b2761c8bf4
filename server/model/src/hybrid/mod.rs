//! The seeds' hybrid model (seed 000 sections 4-6, seed 001): a tetrahedral FEM core `Omega_e`
//! and, between the core's outer boundary and the body's outer surface, a layer `Omega_p` of
//! meshfree particles ([`crate::meshfree`]) sampled on a regular lattice, of which only the
//! regions under the probe are simulated.
//!
//! - [`mod@prepare`]: preprocessing: the core mesh, the outer surface, the particle lattice, the
//!   ties of every particle and outer vertex to the core, the per-vertex particle regions.
//! - [`body`]: [`HybridBody`], the family's [`crate::body::SoftBody`]: activation, coupling,
//!   time stepping; [`proxy`]: the probe (proxy sphere and virtual coupling); [`layer`]: the
//!   elements' and the particles' shares of the wall's energy
//!   (`inactive_layer = "elements"`); [`implicit`]: the core's linearly implicit step.
//!
//! **Geometry.** The built-in hybrid scenes are shells of revolution between two ellipsoids
//! (the seeds' "region between two concentric ellipsoids", section 6), optionally truncated at a
//! base plane (the LV): [`ShellGeometry`]. The core is the inner part of the wall
//! (`core_fraction` of its thickness, meshed with
//! [`crate::mesh::generate::truncated_ellipsoid_shell`]); the particles fill the rest.
//!
//! **Coupling (section 6.1).** Every particle and every outer-surface vertex is tied to one core
//! tetrahedron by its barycentric coordinates at rest, `x_p = sum_k w_pk x_k` (`sum_k w_pk = 1`;
//! coordinates outside `[0, 1]` extrapolate the tetrahedron's affine map to points outside the
//! core). Inactive particles follow this map; the particles inside the core (the *anchors*,
//! a band two kernel supports thick below the core's outer boundary) always do. The forces
//! that active particles' terms put on tied particles go back to the core nodes with the same
//! weights, so the total force, hence linear momentum, is conserved exactly, and an affine
//! motion of the core moves tied particles affinely (the patch test across the interface).
//! This replaces the seed's "gradient vector field" boundary forces and averaged boundary
//! displacements by a kinematic tie that is exact for constant strain.
//!
//! Neighbours: uses [`crate::meshfree`], [`crate::element`], [`crate::integrate`],
//! [`crate::mesh`], [`crate::body`]; used by [`crate::scene`] (parameters) and
//! [`crate::build_body`].

pub mod body;
pub mod implicit;
pub mod layer;
pub mod prepare;
pub mod proxy;
pub(crate) mod section;

use glam::DVec3;

pub use body::{EigenEstimate, HybridBody};
pub use implicit::ImplicitCore;
pub use layer::LayerElements;
pub use prepare::{HybridModel, prepare};
pub use proxy::ParticleProxy;
pub use section::HybridScene;

use crate::ModelError;
use crate::meshfree::MeshfreeParams;

/// A shell of revolution between the ellipsoids `inner` and `outer` (semi-axes, m), kept below
/// `z = z_cut` when given. Layer `t` in `[0, 1]` is the ellipsoid of semi-axes
/// `inner + t (outer - inner)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShellGeometry {
    /// Inner semi-axes, m.
    pub inner_m: DVec3,
    /// Outer semi-axes, m.
    pub outer_m: DVec3,
    /// Base plane, m (`None`: closed shell).
    pub z_cut_m: Option<f64>,
}

impl ShellGeometry {
    /// Semi-axes of layer `t`, m.
    pub fn axes(&self, t: f64) -> DVec3 {
        self.inner_m + (self.outer_m - self.inner_m) * t
    }

    /// `|x / axes(t)|^2 - 1`: negative inside layer `t`'s ellipsoid.
    pub fn level(&self, x: DVec3, t: f64) -> f64 {
        (x / self.axes(t)).length_squared() - 1.0
    }

    /// Whether `x` (m) lies in the wall between layers `t0` and `t1` (and below the base).
    pub fn contains(&self, x: DVec3, t0: f64, t1: f64) -> bool {
        self.z_cut_m.is_none_or(|z| x.z <= z) && self.level(x, t0) >= 0.0 && self.level(x, t1) < 0.0
    }

    /// The depth of `x` (m) below the outer surface (layer 1's ellipsoid, the base plane
    /// ignored), m: positive inside. Newton steps on the level function along its gradient
    /// carry `x` to the surface; the length of that path is the distance along the surface
    /// normal to within `O(d^2 / R)` for a depth `d` small against the surface's radii of
    /// curvature `R` (exact on a sphere).
    pub fn outer_depth_m(&self, x: DVec3) -> f64 {
        let a2 = self.outer_m * self.outer_m;
        let mut q = x;
        for _ in 0..16 {
            let g = (q * q / a2).element_sum() - 1.0;
            let grad = 2.0 * q / a2;
            let step = grad * (g / grad.length_squared());
            q -= step;
            if step.length() <= 1e-12 * self.outer_m.max_element() {
                break;
            }
        }
        let d = (q - x).length();
        if self.level(x, 1.0) < 0.0 { d } else { -d }
    }
}

/// Parameters of the hybrid model (`[hybrid]` in a scene), SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HybridParams {
    /// Meshfree discretisation of the particle layer (variant, spacing, kernel width, hourglass).
    pub meshfree: MeshfreeParams,
    /// Fraction of the wall thickness given to the FEM core, in (0, 1).
    pub core_fraction: f64,
    /// Wanted tetrahedra of the outer-surface shell mesh (sets the outer surface's resolution
    /// and so the size of the per-vertex particle regions).
    pub surface_target_tets: usize,
    /// Outer vertices closer than this to the probe centre get their particle regions
    /// activated, m.
    pub activation_radius_m: f64,
    /// Active regions whose vertex is farther than this from the probe are released once their
    /// particles follow the core again (within `release_tolerance_m`), m.
    pub release_radius_m: f64,
    /// Largest deviation of a region's particles from the core's interpolation (m) at which
    /// the region may be released.
    pub release_tolerance_m: f64,
    /// Most particles simulated at once.
    pub max_active_particles: usize,
    /// Penalty stiffness between the probe sphere and one particle, N/m (used when
    /// `contact_stiffness_pa_per_m` is `None`).
    pub contact_stiffness_n_per_m: f64,
    /// Penalty stiffness per area of the particles' cells, Pa/m (N/m per m^2): one particle's
    /// penalty is this times `spacing_m^2`, so the contact's stiffness per area does not
    /// change when the lattice is refined (issue 46 section 3; docs/decisions.md). `None`:
    /// `contact_stiffness_n_per_m` per particle, whatever the spacing.
    pub contact_stiffness_pa_per_m: Option<f64>,
    /// Multiplier of every mass, core and particles (1: the material's density, the seed's).
    /// Not in the seed: above 1 it slows the whole dynamics down by its square root and raises
    /// the critical steps as much; static forces do not change.
    pub mass_scale: f64,
    /// Multiplier of the core's mass (its own and the particle layer's, which the core
    /// carries through the ties), [`CoreMassScale`]. Not in the seed.
    pub core_mass_scale: CoreMassScale,
    /// Which motion of an active particle `mass_scale` weighs ([`ScaledMotion`]).
    pub scaled_motion: ScaledMotion,
    /// How the core steps ([`CoreStep`]).
    pub core_step: CoreStep,
    /// What carries the stiffness of the particle layer where no particle is simulated
    /// ([`InactiveLayer`]).
    pub inactive_layer: InactiveLayer,
    /// Element order of the FEM (`mesh.order`): 1 (linear tetrahedra) or 2 (curved 10-node
    /// tetrahedra, with `inactive_layer = "elements"` only).
    pub core_order: u8,
    /// Fraction of the critical step used, in (0, 1].
    pub safety_factor: f64,
    /// Most sub-steps per servo tick.
    pub max_substeps: u32,
}

/// The core's mass multiplier (`hybrid.core_mass_scale`: a number, `"auto"` or `"uniform"`).
///
/// The core carries its own mass and the particle layer's (the inactive particles follow it),
/// so this scale sets the body's inertia; the active particles keep `mass_scale`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum CoreMassScale {
    /// `mass_scale`: the whole body slowed down uniformly by its square root, statics
    /// unchanged (the default, and the behaviour before the key existed).
    #[default]
    Uniform,
    /// The smallest value in `[1, mass_scale]` at which the core's critical step (with the
    /// coupling margin) adds no sub-step to the count the particles' step sets: the body keeps
    /// as much of its real inertia as that step allows at no extra cost (about 24 on
    /// `lv-hybrid`; chosen by [`HybridBody::new`], read back with
    /// [`HybridBody::core_mass_scale`]).
    Auto,
    /// This value, in `[1, 1e6]`; 1 is the body's real inertia, the sub-steps then follow the
    /// core's critical step (`docs/accuracy.md`, "The hybrid model's real-inertia core").
    Fixed(f64),
}

/// Which motion of an active particle carries the scaled mass (`hybrid.scaled_motion`). Not in
/// the seed.
///
/// An active particle's position is written `x_p = sum_k w_pk x_k + d_p`: the core's
/// interpolation at its tie plus its deviation `d_p`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ScaledMotion {
    /// `"absolute"`: the particle's whole motion has the mass `rho s^3 mass_scale`, and its
    /// forces reach the core only through the tied particles' terms (the behaviour before
    /// the key existed). Under a press the active region moves as one heavy lump.
    #[default]
    Absolute,
    /// `"deviation"`: only the deviation `d_p` has the scaled mass; the particle's share of the
    /// core's motion has the core's inertia (which already carries the whole layer's mass,
    /// [`HybridModel::layer_mass_on_core_kg`]). The generalised coordinates are the core nodes
    /// and the deviations, with the kinetic energy `1/2 v_c^T M_c v_c + 1/2 sum_p m_s |d_p'|^2`
    /// (both masses lumped): every active particle's force `f_p` drives its deviation and,
    /// with its tie weights, the core nodes (`d x_p / d x_k = w_pk`). A selective mass
    /// scaling: the stiff modes inside the active region stay slow enough for the step, the
    /// wall's motion under the probe keeps its real (core) inertia. Statics are unchanged;
    /// linear momentum is the core's, `sum_k M_k v_k` (translation moves the core and leaves
    /// `d` alone).
    Deviation,
}

impl ScaledMotion {
    /// Parses `"absolute"` or `"deviation"`.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.scaled_motion` for anything else.
    pub fn parse(text: &str) -> Result<Self, ModelError> {
        match text.trim() {
            "absolute" => Ok(Self::Absolute),
            "deviation" => Ok(Self::Deviation),
            t => Err(ModelError::field(
                "hybrid.scaled_motion",
                format!("must be \"absolute\" or \"deviation\", got {t:?}"),
            )),
        }
    }
}

impl std::fmt::Display for ScaledMotion {
    /// As the scene writes it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Absolute => "absolute",
            Self::Deviation => "deviation",
        })
    }
}

/// What carries the stiffness of the particle layer where its particles are not simulated
/// (`hybrid.inactive_layer`).
///
/// The seed (section 6) simulates the particles near the contact only; the others follow the
/// core by interpolation, at no cost and without their stiffness. With a core converged under
/// refinement that leaves the wall 30-40 % soft away from the probe (`docs/accuracy.md`, "The
/// hybrid's static force rests on its coarse core").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InactiveLayer {
    /// `"tied"`: the seed's model. The FEM core is the inner `core_fraction` of the wall; every
    /// particle is tied to the core tetrahedron nearest to it (extrapolating its affine map)
    /// and adds no stiffness while inactive.
    #[default]
    Tied,
    /// `"elements"` (not in the seed): the FEM covers the whole wall (its elements outside
    /// `core_fraction` are the *layer elements*), every particle lies in an element and follows
    /// its interpolation (continuous across the elements), and each element's energy counts in
    /// proportion to the share of its particles whose meshfree terms are not simulated: where
    /// the particles are active their terms take over the elements' energy, elsewhere the
    /// elements carry it (a partition of the wall's energy between the two discretisations).
    Elements,
}

impl InactiveLayer {
    /// Parses `"tied"` or `"elements"`.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.inactive_layer` for anything else.
    pub fn parse(text: &str) -> Result<Self, ModelError> {
        match text.trim() {
            "tied" => Ok(Self::Tied),
            "elements" => Ok(Self::Elements),
            t => Err(ModelError::field(
                "hybrid.inactive_layer",
                format!("must be \"tied\" or \"elements\", got {t:?}"),
            )),
        }
    }
}

impl std::fmt::Display for InactiveLayer {
    /// As the scene writes it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Tied => "tied",
            Self::Elements => "elements",
        })
    }
}

/// `hybrid.core_stiffness_margin` when `core_step = "implicit"` does not give it: the factor
/// on the rest stiffness in the implicit core's matrix. Measured on `lv-hybrid` with
/// `scaled_motion = "deviation"` (`hybrid_bench`'s instant 1 mm press, 2 000 active
/// particles): 1 and 2 diverge within 2 ms, 4 holds; the lv-probe press reads +3.8 / -3.3 %
/// at 4 and +4.1 / -3.5 % at 2 (`docs/accuracy.md`).
pub const DEFAULT_CORE_STIFFNESS_MARGIN: f64 = 4.0;

/// How the hybrid core steps (`hybrid.core_step`, `hybrid.core_stiffness_margin`). Not in the
/// seed (which steps everything explicitly).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum CoreStep {
    /// `"explicit"`: symplectic Euler with the particles, the sub-step bounded by the core's
    /// critical step too (the behaviour before the key existed).
    #[default]
    Explicit,
    /// `"implicit"`: the linearly implicit step of [`ImplicitCore`], its matrix frozen at rest
    /// with the core's and the condensed layer's stiffness times `margin` (in `[1, 100]`):
    /// the sub-steps follow the particles' critical step alone, and `core_mass_scale = "auto"`
    /// is 1 (the body's real inertia).
    Implicit {
        /// Factor on the rest stiffness in the frozen matrix.
        margin: f64,
    },
}

impl CoreStep {
    /// The step named `name` (`"explicit"` or `"implicit"`), with `margin` for the implicit one
    /// ([`DEFAULT_CORE_STIFFNESS_MARGIN`] when `None`; checked by [`HybridParams::validate`]).
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.core_step` for another name, and
    /// `hybrid.core_stiffness_margin` when a margin comes with `"explicit"`.
    pub fn parse(name: &str, margin: Option<f64>) -> Result<Self, ModelError> {
        match (name.trim(), margin) {
            ("explicit", None) => Ok(Self::Explicit),
            ("explicit", Some(_)) => Err(ModelError::field(
                "hybrid.core_stiffness_margin",
                "is only for hybrid.core_step = \"implicit\"",
            )),
            ("implicit", m) => Ok(Self::Implicit {
                margin: m.unwrap_or(DEFAULT_CORE_STIFFNESS_MARGIN),
            }),
            (t, _) => Err(ModelError::field(
                "hybrid.core_step",
                format!("must be \"explicit\" or \"implicit\", got {t:?}"),
            )),
        }
    }
}

impl std::fmt::Display for CoreMassScale {
    /// As the scene writes it: `uniform`, `auto` or the number.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Uniform => f.write_str("uniform"),
            Self::Auto => f.write_str("auto"),
            Self::Fixed(v) => write!(f, "{v}"),
        }
    }
}

impl CoreMassScale {
    /// Parses `"auto"`, `"uniform"` or a number (checked by [`HybridParams::validate`]).
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `hybrid.core_mass_scale` for anything else.
    pub fn parse(text: &str) -> Result<Self, ModelError> {
        match text.trim() {
            "auto" => Ok(Self::Auto),
            "uniform" => Ok(Self::Uniform),
            t => t.parse().map(Self::Fixed).map_err(|_| {
                ModelError::field(
                    "hybrid.core_mass_scale",
                    format!("must be a number, \"auto\" or \"uniform\", got {t:?}"),
                )
            }),
        }
    }
}

impl HybridParams {
    /// The probe's penalty on one particle, N/m: `contact_stiffness_pa_per_m * spacing_m^2`
    /// when the penalty is given per area, else `contact_stiffness_n_per_m`.
    pub fn particle_contact_stiffness_n_per_m(&self) -> f64 {
        self.contact_stiffness_pa_per_m
            .map_or(self.contact_stiffness_n_per_m, |k| {
                k * self.meshfree.spacing_m * self.meshfree.spacing_m
            })
    }
}

impl Default for HybridParams {
    fn default() -> Self {
        Self {
            meshfree: MeshfreeParams::default(),
            core_fraction: 0.4,
            surface_target_tets: 4000,
            activation_radius_m: 4e-3,
            release_radius_m: 6e-3,
            release_tolerance_m: 2e-5,
            max_active_particles: 2000,
            contact_stiffness_n_per_m: 5.0,
            contact_stiffness_pa_per_m: None,
            mass_scale: 1.0,
            core_mass_scale: CoreMassScale::Uniform,
            scaled_motion: ScaledMotion::Absolute,
            core_step: CoreStep::Explicit,
            inactive_layer: InactiveLayer::Tied,
            core_order: 1,
            safety_factor: 0.9,
            max_substeps: 200,
        }
    }
}

impl HybridParams {
    /// Checks every value.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming the `hybrid.*` field that is out of range.
    pub fn validate(&self) -> Result<(), ModelError> {
        self.check_values()?;
        self.check_core_order()?;
        self.check_limits()
    }

    /// The lengths, stiffnesses, ratios and mass scales.
    fn check_values(&self) -> Result<(), ModelError> {
        let pos = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ModelError::field(
                    format!("hybrid.{name}"),
                    format!("must be finite and positive, got {v}"),
                ))
            }
        };
        pos("spacing_m", self.meshfree.spacing_m)?;
        pos("activation_radius_m", self.activation_radius_m)?;
        pos("release_radius_m", self.release_radius_m)?;
        pos("release_tolerance_m", self.release_tolerance_m)?;
        pos("contact_stiffness_n_per_m", self.contact_stiffness_n_per_m)?;
        if let Some(k) = self.contact_stiffness_pa_per_m {
            pos("contact_stiffness_pa_per_m", k)?;
        }
        if !(self.meshfree.smoothing_ratio >= 0.9 && self.meshfree.smoothing_ratio <= 2.0) {
            return Err(ModelError::field(
                "hybrid.smoothing_ratio",
                format!("must be in [0.9, 2], got {}", self.meshfree.smoothing_ratio),
            ));
        }
        if !(self.meshfree.hourglass_coefficient >= 0.0
            && self.meshfree.hourglass_coefficient <= 100.0)
        {
            return Err(ModelError::field(
                "hybrid.hourglass_coefficient",
                "must be in [0, 100]",
            ));
        }
        if !(self.core_fraction > 0.05 && self.core_fraction < 0.95) {
            return Err(ModelError::field(
                "hybrid.core_fraction",
                format!("must be in (0.05, 0.95), got {}", self.core_fraction),
            ));
        }
        if self.release_radius_m < self.activation_radius_m {
            return Err(ModelError::field(
                "hybrid.release_radius_m",
                "must not be smaller than hybrid.activation_radius_m",
            ));
        }
        if !(self.mass_scale >= 1.0 && self.mass_scale <= 1e6) {
            return Err(ModelError::field(
                "hybrid.mass_scale",
                "must be in [1, 1e6]",
            ));
        }
        if let CoreMassScale::Fixed(c) = self.core_mass_scale
            && !(1.0..=1e6).contains(&c)
        {
            return Err(ModelError::field(
                "hybrid.core_mass_scale",
                format!("must be in [1, 1e6], got {c}"),
            ));
        }
        if let CoreStep::Implicit { margin } = self.core_step
            && !(1.0..=100.0).contains(&margin)
        {
            return Err(ModelError::field(
                "hybrid.core_stiffness_margin",
                format!("must be in [1, 100], got {margin}"),
            ));
        }
        Ok(())
    }

    /// The core's element order for the inactive layer.
    fn check_core_order(&self) -> Result<(), ModelError> {
        match (self.inactive_layer, self.core_order) {
            (InactiveLayer::Elements, 1 | 2) | (InactiveLayer::Tied, 1) => {}
            (InactiveLayer::Tied, o) => {
                return Err(ModelError::field(
                    "mesh.order",
                    format!(
                        "the hybrid core with hybrid.inactive_layer = \"tied\" uses linear tetrahedra (order = 1), got {o}"
                    ),
                ));
            }
            (InactiveLayer::Elements, o) => {
                return Err(ModelError::field(
                    "mesh.order",
                    format!("must be 1 or 2, got {o}"),
                ));
            }
        }
        Ok(())
    }

    /// The step's safety factor and the count limits.
    fn check_limits(&self) -> Result<(), ModelError> {
        if !(self.safety_factor > 0.0 && self.safety_factor <= 1.0) {
            return Err(ModelError::field(
                "hybrid.safety_factor",
                "must be in (0, 1]",
            ));
        }
        if self.max_active_particles == 0 || self.max_active_particles > 1_000_000 {
            return Err(ModelError::field(
                "hybrid.max_active_particles",
                "must be in 1..=1000000",
            ));
        }
        if self.max_substeps == 0 || self.max_substeps > 10_000 {
            return Err(ModelError::field(
                "hybrid.max_substeps",
                "must be in 1..=10000",
            ));
        }
        if !(100..=200_000).contains(&self.surface_target_tets) {
            return Err(ModelError::field(
                "hybrid.surface_target_tets",
                "must be in 100..=200000",
            ));
        }
        Ok(())
    }
}
