//! The mass-spring family with haptic subdivision (J. Zhang, S. Payandeh, J. Dill, *Haptic
//! Subdivision: an Approach to Defining Level-of-detail in Haptic Rendering*; "the paper"
//! below, seed 003): a surface of nodes joined by mesh springs `K_m` along the triangle edges,
//! each node tied to its rest position by a home spring `K_h` and damped by `K_d` (eq. 1-2);
//! around the contact node the surface is Loop-subdivided at run time, one level over an
//! n-ring (section 3.1), with masses `m' = m N / N'` (eq. 3) and spring constants from a
//! table calibrated offline at a fixed ratio `K'_m / K'_h` so that the contact force versus
//! displacement stays what it was before subdivision (eq. 4, section 3.2.4).
//!
//! - [`surface`]: the coarse triangle surface and its adjacency (valence, rings, element size).
//! - [`loop_rules`]: Loop's weights: type-1 (vertex, `beta(K)`) and type-2 (edge) stencils.
//! - [`refine`]: which coarse triangles are split, crack-free closure, levels, the mixed-level
//!   triangles and springs, over stable node slots.
//! - `mixed`: the body's mixed-level mesh (springs, triangles, active nodes), edited locally
//!   at each event.
//! - [`network`]: eq. 2's elastic part, energies, the Gershgorin bound for the stable step,
//!   the static press (the paper's experiment).
//! - [`calibration`]: the lookup table of `K'_h / K_h` over normalized contact displacement
//!   `x / L`, its computation for any mesh, and its cache file.
//! - [`contact_rest`]: where the probe meets the surface at rest (the kernel patch's plane
//!   through the surface the nodes sample, not inside it).
//! - [`organ`]: the contact factor that makes the probe force follow the organ's reference
//!   (the calibration's target extended from the coarse surface to the organ).
//! - [`body`]: [`MassSpringBody`], the family's [`crate::body::SoftBody`].
//!
//! Owns: the family. May use: [`crate::mesh`] (triangle splitting), [`crate::contact`] (the
//! probe: the same sphere, proxy and virtual coupling as the FEM), [`crate::integrate`] (the
//! servo tick settings), [`crate::loads`] (point loads), [`crate::body`] (the interface it
//! implements). Built by [`crate::build_body`] from a scene's `[mass_spring]` section.

pub mod body;
pub mod calibration;
pub mod contact_rest;
pub mod loop_rules;
mod mixed;
pub mod network;
pub mod organ;
pub mod refine;
pub(crate) mod section;
pub mod surface;

pub use body::MassSpringBody;
pub use calibration::{CalibrationTable, ContactShape};
pub use organ::{OrganReference, OrganTable};
pub use section::{MassSpringScene, OrganScene, TableState};
pub use surface::SpringSurface;

use crate::ModelError;

/// How the rest positions of the original (type-1) nodes of a subdivided area are set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum VertexRule {
    /// They keep their coarse rest position (`"keep"`, the default): only the new type-2 nodes
    /// take Loop's edge rule. A node the user touches does not move when its area is
    /// subdivided, so the force does not jump; on a flat regular mesh (the paper's experiment)
    /// this is Loop's scheme exactly.
    #[default]
    Keep,
    /// Loop's vertex rule with `beta(K)` (`"loop"`): the area takes Loop's smoother shape, which
    /// on a curved surface pulls the original nodes inward by about `3 L^2 / (16 R)` (valence
    /// 6, curvature radius R) at the moment of subdivision.
    Loop,
}

impl VertexRule {
    /// The scene-file name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Keep => "keep",
            Self::Loop => "loop",
        }
    }

    /// Parses a scene-file name.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Keep, Self::Loop]
            .into_iter()
            .find(|r| r.name() == name)
    }
}

/// Which spring constants a subdivided area gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SpringRule {
    /// From the calibrated lookup table (`"calibrated"`, the default; section 3.2.4).
    #[default]
    Calibrated,
    /// The coarse constants unchanged (`"unchanged"`): the area becomes stiffer, as the
    /// paper's section 3.2.3 warns ("there are more springs preventing the surface from
    /// deforming").
    Unchanged,
    /// The home springs scaled by the node count, `K'_h = K_h N / N'` (eq. 5), the mesh
    /// springs unchanged, `K'_m = K_m` (`"area"`): a home spring stands for the foundation under
    /// its node's share of the area, and a triangulated membrane's stiffness does not depend
    /// on its edge length, so the subdivided area discretises the same surface. The force
    /// then still differs from the coarse surface's by up to about 20 % (the probe's patch
    /// straddles the area's border); the organ table ([`crate::mass_spring::organ`]) gives
    /// each configuration its own contact factor.
    Area,
}

impl SpringRule {
    /// The scene-file name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Calibrated => "calibrated",
            Self::Unchanged => "unchanged",
            Self::Area => "area",
        }
    }

    /// Parses a scene-file name.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Calibrated, Self::Unchanged, Self::Area]
            .into_iter()
            .find(|r| r.name() == name)
    }
}

/// Run-time subdivision settings (scene section `[mass_spring]`, keys `rings` ...).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SubdivisionParams {
    /// Rings around the contact node that are subdivided: 0 (never), 1 ("one-ring
    /// subdivision"), 2, ... (section 3.2).
    pub rings: u32,
    /// Spring constants of a subdivided area.
    pub springs: SpringRule,
    /// The fixed ratio `K'_m / K'_h` of the calibrated constants (section 3.2.4: keep it equal
    /// to `K_m / K_h` to keep the shape of deformation).
    pub km_over_kh_after: f64,
    /// Rest positions of the original nodes of a subdivided area.
    pub vertex_rule: VertexRule,
    /// Time a former contact node keeps its area subdivided after the probe left it, s
    /// (then the area is coarsened).
    pub coarsen_delay_s: f64,
}

/// Parameters of a mass-spring surface (eq. 1-3). SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MassSpringParams {
    /// Mesh spring constant `K_m` of the coarse mesh, N/m.
    pub mesh_spring_n_per_m: f64,
    /// Home spring constant `K_h`, N/m.
    pub home_spring_n_per_m: f64,
    /// Damping `K_d` of a coarse node (force `-K_d v`), N s/m; a subdivided node gets
    /// `K_d m' / m` (the same damping per unit mass).
    pub damping_n_s_per_m: f64,
    /// Mass `m` of a coarse node, kg.
    pub node_mass_kg: f64,
    /// Run-time subdivision.
    pub subdivision: SubdivisionParams,
}

impl MassSpringParams {
    /// The paper's experiment (section 3.2.2): `K_h = K_m = 0.06 N/mm`, no damping, a node
    /// mass of 1 g (the paper gives none), one-ring subdivision with the calibrated table.
    pub fn paper() -> Self {
        Self {
            mesh_spring_n_per_m: 60.0,
            home_spring_n_per_m: 60.0,
            damping_n_s_per_m: 0.0,
            node_mass_kg: 1e-3,
            subdivision: SubdivisionParams {
                rings: 1,
                springs: SpringRule::Calibrated,
                km_over_kh_after: 1.0,
                vertex_rule: VertexRule::Keep,
                coarsen_delay_s: 0.2,
            },
        }
    }

    /// Checks every value; errors name the scene field (`mass_spring.<key>`).
    ///
    /// # Errors
    /// [`ModelError::SceneField`] for a non-finite, non-positive (negative for damping and the
    /// delay) value, or more than [`MAX_RINGS`] rings.
    pub fn validate(&self) -> Result<(), ModelError> {
        let positive = [
            ("mass_spring.mesh_spring_n_per_m", self.mesh_spring_n_per_m),
            ("mass_spring.home_spring_n_per_m", self.home_spring_n_per_m),
            ("mass_spring.node_mass_kg", self.node_mass_kg),
            (
                "mass_spring.km_over_kh_after",
                self.subdivision.km_over_kh_after,
            ),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(ModelError::field(
                    field,
                    format!("must be a finite number > 0, got {v}"),
                ));
            }
        }
        let non_negative = [
            ("mass_spring.damping_n_s_per_m", self.damping_n_s_per_m),
            (
                "mass_spring.coarsen_delay_s",
                self.subdivision.coarsen_delay_s,
            ),
        ];
        for (field, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(ModelError::field(
                    field,
                    format!("must be a finite number >= 0, got {v}"),
                ));
            }
        }
        if self.subdivision.rings > MAX_RINGS {
            return Err(ModelError::field(
                "mass_spring.rings",
                format!("must be in 0..={MAX_RINGS}, got {}", self.subdivision.rings),
            ));
        }
        Ok(())
    }
}

/// Largest number of rings a scene may subdivide around a contact node.
pub const MAX_RINGS: u32 = 6;

/// A vector of `n` copies of `value` whose memory is written now. A zeroed allocation is
/// mapped lazily by the OS, so the first event that reaches a page of it (on the servo thread)
/// would take a page fault; the benchmark's events at random nodes of large surfaces did.
pub(crate) fn prefaulted<T: Copy>(value: T, n: usize) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    // Keeps the allocation and the fill from being merged into one lazily zeroed allocation.
    std::hint::black_box(&mut v);
    v.resize(n, value);
    v
}

/// An empty vector with room for `n` elements, its memory written now (as [`prefaulted`]).
pub(crate) fn prefaulted_capacity<T: Copy>(filler: T, n: usize) -> Vec<T> {
    let mut v = prefaulted(filler, n);
    v.clear();
    v
}
