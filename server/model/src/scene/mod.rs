//! Scenes: a mesh, a material, boundary conditions, an integrator and a probe.
//!
//! A scene is a TOML text (a file, or one of the built-in texts of [`builtin_scene_toml`])
//! parsed with serde (unknown fields rejected), then validated into a [`Scene`] in SI units.
//! Errors name the offending field by its dotted path (`material.poisson_ratio`). Format:
//!
//! ```toml
//! name = "lv-h1"                 # optional; default: the file stem, or "custom"
//! description = "..."            # optional
//! [mesh]
//! file = "../../../shared/data/lv/lv_h1.msh"  # Gmsh 2.2/4.1, relative to the scene's directory
//! length_unit = "mm"             # "m" | "cm" | "mm" | "um"; default "m"
//! # or builtin = "lv" (target_tets, default 2000 when a user scene names it; the built-in "lv" scene sets 1000), "ellipsoids" (inner_semi_axes,
//! # outer_semi_axes in length_unit, default (6,6,12) and (10,10,16) mm; target_tets, default
//! # 188), "sphere" (inner_radius, outer_radius in length_unit; target_tets, default 5000) or
//! # "box" (size = [x, y, z] in length_unit, cells = [nx, ny, nz]), or "hemisphere" (a surface
//! # for the mass-spring family: outer_radius, edge_length in length_unit)
//! order = 1                      # element order: 1 = linear tets (default), 2 = quadratic
//!                                # 10-node tets made by adding a node at every edge midpoint
//!                                # (built-in shells: boundary mid-edge nodes on the surfaces)
//! strain_smoothing = "none"      # linear tets only: "edge" = edge-based smoothed FEM
//!                                # (ES-FEM-T4: softer, far less bending/shear locking)
//! [material]                     # youngs_modulus_pa + poisson_ratio, OR lambda_pa + mu_pa
//! model = "stvk"                 # default; or "corotational", "stable-neo-hookean"
//! youngs_modulus_pa = 14500.0
//! poisson_ratio = 0.45           # in (-1, 0.5)
//! phi_pa_s = 0.05                # default 0
//! psi_pa_s = 0.05                # default 0
//! density_kg_per_m3 = 1060.0     # required
//! mass_damping_per_s = 5.0       # default 0
//! [boundary]
//! clamped = ["BASE"]             # surface or node-group names; default none
//! touchable = ["EPI"]            # surface names; default: boundary faces not entirely clamped
//! [integrator]                   # optional, defaults shown
//! kind = "semi-implicit"         # or "symplectic-euler", "backward-euler"
//! tick_s = 0.001                 # in (0, 0.1]
//! substeps = "auto"              # or an integer in 1..=max_substeps
//! max_substeps = 64
//! safety_factor = 0.5            # in (0, 1]
//! cg_max_iterations = 20         # backward Euler: CG iterations per step, 1..=10000
//! cg_tolerance = 0.001           # backward Euler: relative CG residual, in (0, 1)
//! force_precision = "double"     # or "single": linear StVK tets only, standard or edge-smoothed (FemModel::set_single_precision)
//! [loads]                        # optional; default: no load
//! gravity_m_per_s2 = [0.0, 0.0, -9.81]
//! [[loads.pressure]]             # any number; positive pushes into the body
//! surfaces = ["ENDO"]
//! pressure_pa = 1000.0
//! follower = false               # true: recomputed from the current geometry each sub-step
//! [[loads.point]]                # any number; permanent, on the closest free boundary triangle
//! point_m = [0.0, 0.01, 0.0]
//! force_n = [0.0, -0.05, 0.0]
//! [active_region]                # optional; backward Euler only: simulate the tetrahedra
//! centre_m = [0.0097, 0.0, -0.005] # with a node within radius_m of centre_m (rest, metres)
//! radius_m = 0.008               # and condense the rest statically (crate::integrate::condensed)
//! stiffness_margin = 2.0         # factor on the rest stiffness of the frozen tick matrix
//! [model]                        # optional
//! family = "fem"                 # or "mass-spring": then [mass_spring] instead of [material],
//!                                # no [loads] or [active_region] (docs/scenes.md)
//! [mass_spring]                  # mass-spring only (crate::mass_spring)
//! mesh_spring_n_per_m = 60.0     # K_m, eq. 2 of seed 003
//! home_spring_n_per_m = 60.0     # K_h
//! damping_n_s_per_m = 0.2        # K_d, default 0
//! node_mass_kg = 0.001           # m
//! rings = 1                      # n-ring subdivision at the contact node, 0..=6, default 1
//! springs = "calibrated"         # or "unchanged"
//! km_over_kh_after = 1.0         # K'_m / K'_h, default K_m / K_h
//! vertex_rule = "keep"           # or "loop"
//! coarsen_delay_s = 0.2
//! calibration_file = "NAME.calibration.csv"  # beside the scene; computed by haptic-calibrate
//! [probe]                        # optional, defaults shown
//! radius_m = 0.002
//! coupling_stiffness_n_per_m = 300.0
//! coupling_damping_n_s_per_m = 0.05
//! max_force_n = 10.0
//! max_tools = 2                  # tools (device streams) at once, 1..=4; default 2 on FEM
//!                                # bodies without a following region, else 1 (docs/scenes.md)
//! [[probe.tool]]                 # optional, at most max_tools: a named tool takes slot k
//! id = "grasper"                 # (its index here); unique, 1..=64 characters
//! radius_m = 0.003               # optional overrides of [probe] for this tool
//! max_force_n = 5.0
//! ```
//!
//! Built-in scenes are string constants ([`builtin`]; the library reads no file outside
//! itself); identical copies live in `deploy/scenes/` for users to edit. The full format with
//! every default and limit is in `docs/scenes.md`.
//!
//! Owns: scene data, its TOML schema (`raw`) and the built-ins. May use: [`crate::mesh`]
//! (readers and generators), and the parameter types of [`crate::material`],
//! [`crate::element`], [`crate::integrate`], [`crate::contact`], [`crate::loads`]. Used by
//! [`crate::build_body`], which builds a body from a [`Scene`].

use std::path::Path;

use glam::DVec3;

use crate::ModelError;
use crate::contact::ProbeParams;
use crate::element::{FemModel, FibreField, FibreRule, StrainSmoothing};
use crate::integrate::IntegratorParams;
use crate::integrate::condensed::ActiveRegion;
use crate::loads::{SceneLoads, static_dead_forces, static_external_forces};
use crate::material::MaterialParams;
use crate::mesh::TetMesh;

pub mod builtin;
mod raw;
mod toml_errors;

pub use crate::hybrid::HybridScene;
pub use crate::mass_spring::{MassSpringScene, OrganScene, TableState};
pub use builtin::{builtin_calibration, builtin_scene_names, builtin_scene_toml};
pub use raw::{MAX_GRAVITY_M_PER_S2, MAX_PRESSURE_PA, MAX_SCENE_POINT_FORCE_N};
pub use toml_errors::describe_toml_error;

/// The names `[mesh] builtin` accepts (the generated meshes; scene-file documentation above).
/// The parser's error for an unknown name lists the same names (checked by the README test).
pub const BUILTIN_MESHES: [&str; 5] = ["lv", "ellipsoids", "sphere", "box", "hemisphere"];

/// The model family a scene asks for (section `[model] family`): which [`crate::body::SoftBody`]
/// implementation [`crate::build_body`] builds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ModelFamily {
    /// The tetrahedral FEM body ([`crate::fem::FemBody`]; `"fem"`, the default).
    #[default]
    Fem,
    /// The mass-spring surface with run-time Loop subdivision
    /// ([`crate::mass_spring::MassSpringBody`]; `"mass-spring"`, section `[mass_spring]`).
    MassSpring,
    /// The seeds' hybrid FEM core + meshfree particle layer ([`crate::hybrid::HybridBody`];
    /// `"hybrid"`, section `[hybrid]`).
    Hybrid,
}

impl ModelFamily {
    /// Every family, for error messages and listings.
    pub const ALL: &'static [ModelFamily] = &[
        ModelFamily::Fem,
        ModelFamily::MassSpring,
        ModelFamily::Hybrid,
    ];

    /// The scene-file name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Fem => "fem",
            Self::MassSpring => "mass-spring",
            Self::Hybrid => "hybrid",
        }
    }

    /// Parses a scene-file name; `None` if unknown.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|f| f.name() == name)
    }
}

/// The rule-based fibre field of a scene (`[material.fibres]`): the surfaces where the
/// transmural coordinate is 0 and 1, and the helix rule ([`crate::element::fibres`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FibreSpec {
    /// Surface with transmural coordinate 0 (default `ENDO`).
    pub endo_surface: String,
    /// Surface with transmural coordinate 1 (default `EPI`).
    pub epi_surface: String,
    /// Helix angles and long axis.
    pub rule: FibreRule,
}

/// The tools (device streams) a scene takes at once (`[probe] max_tools`, `[[probe.tool]]`;
/// issue 50): each tool has its own proxy, coupling and contact, all acting on the body in the
/// same tick.
#[derive(Debug, Clone, PartialEq)]
pub struct ToolSpec {
    /// Tools at once, `1..=`[`crate::body::MAX_TOOLS`]: the parser's default is
    /// [`DEFAULT_MAX_TOOLS`] where the body carries several tools, else 1.
    pub max_tools: usize,
    /// Named tools: the tool `named[k].id` takes slot `k` with its own probe parameters;
    /// unnamed tools take the other slots with the scene's `[probe]`. At most `max_tools`.
    pub named: Vec<NamedTool>,
}

impl Default for ToolSpec {
    /// One tool, none named.
    fn default() -> Self {
        Self {
            max_tools: 1,
            named: Vec::new(),
        }
    }
}

/// A tool the scene names (`[[probe.tool]]`), with the probe parameters it overrides.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTool {
    /// Tool id (non-empty, at most [`MAX_TOOL_ID_CHARS`] characters, no control character,
    /// unique in the scene), sent by a device stream in its first sample.
    pub id: String,
    /// The scene's `[probe]` with this tool's `radius_m` and `max_force_n`.
    pub probe: ProbeParams,
}

/// `[probe] max_tools` when a scene does not set it, on the bodies that carry several tools
/// (FEM without a following active region).
pub const DEFAULT_MAX_TOOLS: usize = 2;

/// Longest tool id, in characters.
pub const MAX_TOOL_ID_CHARS: usize = 64;

/// A validated scene, ready to build a body ([`crate::build_body`]). SI units.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Scene name (built-in name or the file's `name`).
    pub name: String,
    /// One-line description, with the source of the parameters.
    pub description: String,
    /// The model family to build (`[model] family`).
    pub family: ModelFamily,
    /// Whether the scene may run in the haptic loop (`[model] realtime`, default true);
    /// false for static benchmarks that only `haptic-solve` solves ([`crate::build_body`]
    /// refuses them).
    pub realtime: bool,
    /// Why the scene is an offline reference (`[model] offline`, a sentence for the operator:
    /// its tick takes longer than the 1 kHz loop allows, and what to run instead), or `None`.
    /// The model builds and ticks such a scene for its tools (`feel`, `scene_table`, the
    /// benchmarks); the daemon refuses a session of it with this reason.
    pub offline: Option<String>,
    /// The mesh in metres.
    pub mesh: TetMesh,
    /// Strain smoothing of linear elements (`[mesh] strain_smoothing`).
    pub strain_smoothing: StrainSmoothing,
    /// Material.
    pub material: MaterialParams,
    /// Integrator settings.
    pub integrator: IntegratorParams,
    /// Haptic probe settings (of every tool the scene does not name).
    pub probe: ProbeParams,
    /// The tools the body takes at once and the named ones (`[probe] max_tools`,
    /// `[[probe.tool]]`).
    pub tools: ToolSpec,
    /// Nodes fixed at their rest position (clamped), sorted, distinct.
    pub clamped_nodes: Vec<u32>,
    /// Triangles the probe can touch, outward oriented.
    pub touchable: Vec<[u32; 3]>,
    /// The scene file's length unit in metres (1e-3 for "mm"); outputs for users use it.
    pub length_unit_m: f64,
    /// External loads: gravity, surface pressure, point forces (section `[loads]`).
    pub loads: SceneLoads,
    /// Contact-local active region (section `[active_region]`): backward Euler on its elements
    /// with the rest of the body condensed ([`crate::integrate::condensed`]); `None` simulates everything.
    pub active_region: Option<ActiveRegion>,
    /// The fibre field of an anisotropic material (`[material.fibres]`), built on the mesh by
    /// [`Scene::fem_model`].
    pub fibres: Option<FibreSpec>,
    /// The mass-spring surface (section `[mass_spring]`): present exactly when `family` is
    /// [`ModelFamily::MassSpring`] (the parser guarantees it). A mass-spring scene has no
    /// `[material]` (`material` is then the default, unused) and no `[loads]`; its `mesh` is
    /// the spring surface itself (the touchable triangles of the mesh the scene names, no
    /// tetrahedra), `touchable` its triangles and `clamped_nodes` its fixed nodes.
    pub mass_spring: Option<MassSpringScene>,
    /// The hybrid model (section `[hybrid]`): present exactly when `family` is
    /// [`ModelFamily::Hybrid`]. `mesh` is then the whole wall (for listings); the body builds
    /// its own core and particle layer from the geometry.
    pub hybrid: Option<HybridScene>,
    /// The coarse whole-body companion of a following active region
    /// (`[active_region] fallback_target_tets`): the same scene on the built-in mesh at that
    /// many quadratic tetrahedra, backward Euler on its whole-body rest factor. It answers the
    /// probe where the region does not hold the contact ([`crate::fem::FemBody`], "The
    /// coarse companion").
    pub fallback: Option<Box<Scene>>,
}

impl Scene {
    /// The FEM model of the scene: elements of its mesh with its material and strain
    /// smoothing, clamped nodes, and the fibre field of an anisotropic material (the Laplace
    /// rule of [`FibreField::laplace`] between the scene's endocardial and epicardial
    /// surfaces).
    ///
    /// # Errors
    /// As [`FemModel::with_smoothing`] and [`FibreField::laplace`].
    pub fn fem_model(&self) -> Result<FemModel, ModelError> {
        let mut fem = FemModel::with_smoothing(&self.mesh, self.material, self.strain_smoothing)?;
        fem.set_single_precision(self.integrator.single_precision_forces)?;
        fem.clamp_nodes(&self.clamped_nodes);
        if let Some(spec) = &self.fibres {
            let nodes =
                |name: &str, field: &str| self.mesh.nodes_of_surfaces(&[name.to_string()], field);
            let endo = nodes(&spec.endo_surface, "material.fibres.endo")?;
            let epi = nodes(&spec.epi_surface, "material.fibres.epi")?;
            let field = FibreField::laplace(&fem, &endo, &epi, spec.rule)?;
            fem.set_fibres(field);
        }
        Ok(fem)
    }

    /// External nodal forces (N, one per mesh node) of the scene's loads at positions `x` (m),
    /// for static solves: see [`static_external_forces`]. The same forces a dynamic body
    /// applies.
    ///
    /// # Panics
    /// If `x` is shorter than the mesh's node count.
    pub fn external_forces(&self, x: &[DVec3]) -> Vec<DVec3> {
        static_external_forces(&self.loads, &self.mesh, self.material.density_kg_per_m3, x)
    }

    /// The scene's loads that do not follow the body (N, one per mesh node): see
    /// [`static_dead_forces`].
    pub fn dead_forces(&self) -> Vec<DVec3> {
        static_dead_forces(&self.loads, &self.mesh, self.material.density_kg_per_m3)
    }

    /// The probe parameters of tool slot `slot`: a named tool's, else the scene's `[probe]`.
    pub fn tool_probe(&self, slot: usize) -> ProbeParams {
        self.tools.named.get(slot).map_or(self.probe, |t| t.probe)
    }

    /// The slot of the tool named `id` (its index in `[[probe.tool]]`), `None` if unnamed.
    pub fn tool_slot(&self, id: &str) -> Option<usize> {
        self.tools.named.iter().position(|t| t.id == id)
    }
}

/// Loads and validates the built-in scene `name` (see [`builtin_scene_names`]).
///
/// # Errors
/// [`ModelError::UnknownScene`] listing the known names if `name` is not a built-in; otherwise
/// the errors of [`parse_scene_toml`] (which would be a bug in the built-in text).
pub fn load_builtin(name: &str) -> Result<Scene, ModelError> {
    let Some(text) = builtin_scene_toml(name) else {
        let known = builtin_scene_names()
            .iter()
            .map(|b| b.0)
            .collect::<Vec<_>>()
            .join(", ");
        return Err(ModelError::UnknownScene(name.to_string(), known));
    };
    raw::parse_scene(text, Path::new("."), name, raw::Origin::Builtin)
}

/// Reads and validates a scene file. Relative mesh paths are resolved against the file's
/// directory; the scene name defaults to the file stem.
///
/// # Errors
/// [`ModelError::Io`] if the scene or mesh file cannot be read; otherwise as
/// [`parse_scene_toml`].
pub fn load_scene_file(path: &Path) -> Result<Scene, ModelError> {
    let text = std::fs::read_to_string(path).map_err(|source| ModelError::Io {
        path: path.display().to_string(),
        source,
    })?;
    let base_dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("custom");
    raw::parse_scene(&text, base_dir, stem, raw::Origin::File)
}

/// Parses and validates a scene TOML text. `base_dir`: directory against which a relative
/// `mesh.file` is resolved. The name defaults to `custom`.
///
/// # Errors
/// [`ModelError::SceneSyntax`] (with its line and column) for text that is not TOML;
/// [`ModelError::SceneField`] naming the dotted field for unknown keys, wrongly typed,
/// missing, non-finite, out-of-range or contradictory values and unknown surface names;
/// [`ModelError::Io`] (with the path) if the mesh file cannot be read, and the errors of
/// [`crate::mesh::gmsh::load_msh`] if it cannot be parsed.
pub fn parse_scene_toml(text: &str, base_dir: &Path) -> Result<Scene, ModelError> {
    raw::parse_scene(text, base_dir, "custom", raw::Origin::File)
}

// ----- raw (serde) form -----
