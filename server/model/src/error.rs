//! The model's error type. One enum for the whole library; the server maps it to gRPC statuses.

use thiserror::Error;

/// Everything that can go wrong while loading a scene or building and running a simulation.
#[derive(Debug, Error)]
pub enum ModelError {
    /// A scene file field is missing, malformed or out of range. `field` is the dotted TOML path
    /// (e.g. `material.poisson_ratio`).
    #[error("scene field `{field}`: {message}")]
    SceneField {
        /// Dotted path of the offending field.
        field: String,
        /// What is wrong with it.
        message: String,
    },
    /// The scene text is not valid TOML or has unknown fields.
    #[error("scene file is not valid: {0}")]
    SceneSyntax(String),
    /// A built-in scene name that does not exist.
    #[error("unknown built-in scene `{0}` (known: {1})")]
    UnknownScene(String, String),
    /// A mesh file could not be read or parsed. `line` is 1-based when known.
    #[error("mesh {path}: {message}{}", line.map(|l| format!(" (line {l})")).unwrap_or_default())]
    MeshFormat {
        /// File path or description.
        path: String,
        /// 1-based line number, when known.
        line: Option<usize>,
        /// What is wrong.
        message: String,
    },
    /// The mesh is geometrically unusable (degenerate or inverted tetrahedra, no elements, ...).
    #[error("invalid mesh: {0}")]
    InvalidMesh(String),
    /// An I/O error reading a file.
    #[error("reading {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// An explicit configuration cannot be stable: the time step needed exceeds what the
    /// configured sub-steps allow.
    #[error(
        "unstable configuration: {integrator} needs dt <= {critical_dt_s:.3e} s but the servo tick \
         {tick_s:.3e} s with at most {max_substeps} sub-steps gives {sub_dt_s:.3e} s; raise \
         integrator.max_substeps (or integrator.substeps, where the scene fixes it), use the \
         semi-implicit integrator, or coarsen the mesh"
    )]
    Unstable {
        /// Integrator name.
        integrator: &'static str,
        /// Critical time step in seconds.
        critical_dt_s: f64,
        /// Servo tick in seconds.
        tick_s: f64,
        /// Largest sub-step count allowed (the scene's `integrator.substeps` when it fixes
        /// the count).
        max_substeps: u32,
        /// Resulting sub-step in seconds.
        sub_dt_s: f64,
    },
    /// A run-time input was rejected (NaN, infinity, absurd magnitude); the state is untouched.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// A device input was rejected by the servo tick (static message: the tick never allocates).
    #[error("invalid device input: {0}")]
    InvalidDevice(&'static str),
    /// The dynamic simulation diverged (non-finite state or a nodal speed above the limit);
    /// the state is no longer meaningful and the session must be quarantined.
    #[error(
        "the simulation diverged at t = {time_s:.4} s (a nodal speed became non-finite or exceeded the limit)"
    )]
    Diverged {
        /// Simulated time of the failing tick, s.
        time_s: f64,
    },
    /// The preallocated point-load table is full.
    #[error("{0} point loads are already active")]
    LoadTableFull(usize),
    /// A mass-spring calibration table is missing, malformed or stale, or its computation
    /// failed. `path` names the file (empty when none).
    #[error("calibration table {path}: {message}")]
    Calibration {
        /// The table file.
        path: String,
        /// What is wrong, and what to run.
        message: String,
    },
    /// A solver did not converge.
    #[error("solver did not converge: {0}")]
    NoConvergence(String),
}

impl ModelError {
    /// Shorthand for [`ModelError::SceneField`].
    pub fn field(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self::SceneField {
            field: field.into(),
            message: message.into(),
        }
    }
}
