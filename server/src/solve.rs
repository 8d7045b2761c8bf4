//! Static solutions of scene files for reference and inspection (`haptic-solve`): the scene's
//! loads applied in increments, Newton at each increment ([`haptic_model::statics`]) with the
//! follower pressures' load stiffness, results written
//! as `nodes.csv` and a ParaView `.vtu` in the scene's length unit; and static indentations by
//! the scene's probe sphere ([`indent_scene`], [`haptic_model::indent`]) written as
//! `indent.csv` and one `.vtu` per depth.

use std::path::Path;

use haptic_cli::vtu::{self, Cells, DataArray, Grid, Layout, Values, VtuError};
use haptic_model::indent::{IndentParams, IndentPoint, Indenter, indent};
use haptic_model::mesh::TetMesh;
use haptic_model::scene::{ModelFamily, Scene};
use haptic_model::statics::{StaticParams, solve_scene_loads};
use haptic_model::{DVec3, ModelError};

/// What a static solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveReport {
    /// Load increments.
    pub load_steps: usize,
    /// Newton iterations over all increments and penalty stages.
    pub newton_iterations: usize,
    /// Solves at full load after the increments (penalty stages or volume passes, see
    /// [`haptic_model::statics::solve_scene_loads`]).
    pub constraint_passes: usize,
    /// Largest element volume change `|J_c - 1|` at the end (mean-dilatation Guccione; 0
    /// otherwise).
    pub worst_volume_change: f64,
    /// Final free residual `|f_int(x) + f_ext(x)|` with the loads evaluated at the final
    /// configuration (follower pressure included), N.
    pub residual_n: f64,
    /// `residual_n` relative to the norm of the final external load.
    pub relative_residual: f64,
    /// Largest nodal displacement, m.
    pub max_displacement_m: f64,
}

/// Settings of [`solve_scene`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveParams {
    /// Load increments (>= 1).
    pub load_steps: usize,
    /// Relative residual the solve must reach (against the external load norm).
    pub rel_tol: f64,
    /// Largest Newton iteration count per increment.
    pub max_iterations: usize,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            load_steps: 1,
            rel_tol: 1e-9,
            max_iterations: 50,
        }
    }
}

/// Solves the scene's static equilibrium under its `[loads]`, applied in `params.load_steps`
/// equal increments, Newton at each ([`solve_scene_loads`]: follower pressures with their load
/// stiffness, the volume constraint of a nearly incompressible material); `progress` sees each
/// increment or stage with its Newton iterations. The reported residual is recomputed with
/// every load at the final shape. Returns the node positions, m.
///
/// # Errors
/// [`ModelError::InvalidInput`] when the scene has no loads; [`ModelError::NoConvergence`]
/// naming the increment or penalty stage at which Newton failed and why.
pub fn solve_scene(
    scene: &Scene,
    params: &SolveParams,
    progress: &mut dyn FnMut(&str, usize),
) -> Result<(Vec<DVec3>, SolveReport), ModelError> {
    if scene.loads.is_empty() {
        return Err(ModelError::InvalidInput(
            "the scene has no [loads] (gravity, pressure or point forces): nothing to solve".into(),
        ));
    }
    let newton = StaticParams {
        rel_tol: params.rel_tol,
        max_iterations: params.max_iterations,
        ..StaticParams::default()
    };
    let (x, path) = solve_scene_loads(scene, params.load_steps, &newton, progress)?;
    let norm = |f: &[DVec3]| f.iter().map(|a| a.length_squared()).sum::<f64>().sqrt();
    let mut report = SolveReport {
        load_steps: params.load_steps.max(1),
        newton_iterations: path.newton_iterations,
        constraint_passes: path.constraint_passes,
        worst_volume_change: path.worst_volume_change,
        residual_n: 0.0,
        relative_residual: 0.0,
        max_displacement_m: 0.0,
    };
    // The true residual, every load evaluated at the final shape.
    let f = scene.external_forces(&x);
    report.residual_n = path.residual_n;
    report.relative_residual = report.residual_n / norm(&f).max(f64::MIN_POSITIVE);
    report.max_displacement_m = x
        .iter()
        .zip(&scene.mesh.nodes)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    Ok((x, report))
}

/// Writes `nodes.csv` and `solution.vtu` into `dir` (created if needed), in the scene's length
/// unit.
///
/// # Errors
/// [`ModelError::Io`] when a file cannot be written.
pub fn write_solution(dir: &Path, scene: &Scene, x: &[DVec3]) -> Result<(), ModelError> {
    std::fs::create_dir_all(dir).map_err(|e| ModelError::Io {
        path: dir.display().to_string(),
        source: e,
    })?;
    haptic_model::mesh::export::write_nodes_csv(
        &dir.join("nodes.csv"),
        &scene.mesh.nodes,
        x,
        scene.length_unit_m,
    )?;
    write_mesh_vtu(
        &dir.join("solution.vtu"),
        &scene.mesh,
        x,
        scene.length_unit_m,
    )
}

/// Writes a VTK XML unstructured grid (`.vtu`, ASCII, [`haptic_cli::vtu`]) of the tetrahedra
/// at the current positions `x` (m, one per node), with point data `displacement` (x - rest)
/// and cell data `volume_ratio` ([`TetMesh::volume_ratios`]). Coordinates and displacements
/// are divided by `length_unit_m`; numbers are written with 13 significant digits.
///
/// # Errors
/// [`ModelError::Io`] when the file cannot be written; [`ModelError::InvalidMesh`] when `x`
/// does not match the mesh.
pub fn write_mesh_vtu(
    path: &Path,
    mesh: &TetMesh,
    x: &[DVec3],
    length_unit_m: f64,
) -> Result<(), ModelError> {
    if x.len() != mesh.nodes.len() {
        return Err(ModelError::InvalidMesh(format!(
            "{} positions for {} nodes",
            x.len(),
            mesh.nodes.len()
        )));
    }
    let s = 1.0 / length_unit_m;
    let points: Vec<f64> = x.iter().flat_map(|p| (*p * s).to_array()).collect();
    let displacement: Vec<f64> = x
        .iter()
        .zip(&mesh.nodes)
        .flat_map(|(p, r)| ((*p - *r) * s).to_array())
        .collect();
    let ratios = mesh.volume_ratios(x);
    // Quadratic elements: VTK_QUADRATIC_TETRA, whose mid-edge node order is ours.
    let mut connectivity = Vec::with_capacity(mesh.tets.len() * 10);
    let mut offsets = Vec::with_capacity(mesh.tets.len());
    for (k, t) in mesh.tets.iter().enumerate() {
        connectivity.extend(t.iter().map(|&i| i64::from(i)));
        if let Some(m) = mesh.tet_edge_nodes.get(k) {
            connectivity.extend(m.iter().map(|&i| i64::from(i)));
        }
        offsets.push(connectivity.len() as i64);
    }
    let cell_type = if mesh.is_quadratic() {
        vtu::VTK_QUADRATIC_TETRA
    } else {
        vtu::VTK_TETRA
    };
    let types = vec![cell_type; mesh.tets.len()];
    let rows = |name, components, values| DataArray {
        name,
        components,
        values: Values::F64(values),
        layout: Layout::Rows,
    };
    let grid = Grid {
        version: vtu::Version::V1_0,
        points: rows(None, 3, &points),
        cells: Cells {
            connectivity: Values::I64(&connectivity),
            offsets: Values::I64(&offsets),
            types: Values::U8(&types),
            layout: Layout::Rows,
        },
        point_data: vec![rows(Some("displacement"), 3, &displacement)],
        cell_data: vec![rows(Some("volume_ratio"), 1, &ratios)],
        data_first: true,
    };
    vtu::write_vtu(path, &grid).map_err(|e| match e {
        VtuError::Io { path, source } => ModelError::Io {
            path: path.display().to_string(),
            source,
        },
        VtuError::Shape(m) => ModelError::InvalidMesh(m),
    })
}

/// A static sphere indentation of a scene (`haptic-solve --indent`), in metres.
#[derive(Debug, Clone, PartialEq)]
pub struct IndentRequest {
    /// Start centre of the probe sphere, clear of the body, m.
    pub from_m: DVec3,
    /// Indentation direction (any length but zero).
    pub direction: DVec3,
    /// Depths below first contact, increasing, m.
    pub depths_m: Vec<f64>,
    /// Largest number of Newton iterations per depth increment (the CLI's
    /// `--max-iterations`).
    pub max_iterations: usize,
}

/// The static indentation of `scene` by a rigid frictionless sphere of the scene's probe radius
/// (`[probe] radius_m`) over its touchable surface, at every depth of `request`
/// ([`haptic_model::indent::indent`]: the touchable nodes constrained exactly by an active
/// set, contact points inside triangles coarser than the sphere; the scene's material, fibres
/// and clamps; `[loads]` are ignored) with at most `request.max_iterations` Newton iterations
/// per depth increment. `progress` sees each converged depth.
///
/// # Errors
/// [`ModelError::InvalidInput`] for a scene that is not of the FEM family, a scene without a
/// touchable surface, or a bad request (see [`haptic_model::indent::indent`]);
/// [`ModelError::NoConvergence`] naming the depth that failed and why.
pub fn indent_scene(
    scene: &Scene,
    request: &IndentRequest,
    progress: &mut dyn FnMut(&IndentPoint),
) -> Result<Vec<IndentPoint>, ModelError> {
    if scene.family != ModelFamily::Fem {
        return Err(ModelError::InvalidInput(format!(
            "indentation solves the FEM family; scene {:?} is of the {} family",
            scene.name,
            scene.family.name()
        )));
    }
    if scene.touchable.is_empty() {
        return Err(ModelError::InvalidInput(format!(
            "scene {:?} has no touchable surface for the sphere to press on",
            scene.name
        )));
    }
    let fem = scene.fem_model()?;
    let indenter = Indenter {
        radius_m: scene.probe.radius_m,
        from_m: request.from_m,
        direction: request.direction,
    };
    let mut params = IndentParams::default();
    params.newton.max_iterations = request.max_iterations;
    indent(
        &fem,
        &scene.touchable,
        &indenter,
        &request.depths_m,
        &params,
        progress,
    )
}

/// Name of the `.vtu` file of the `k`-th depth (0-based) of an indentation.
pub fn indent_vtu_name(k: usize) -> String {
    format!("indent_{:03}.vtu", k + 1)
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> ModelError {
    let path = path.display().to_string();
    move |e| ModelError::Io { path, source: e }
}

/// Writes `dir/indent.csv` (`depth,fx,fy,fz,contact_radius`: depth and contact radius in the
/// scene's length unit, the force of the body on the sphere in N, one row per point), creating
/// `dir` if needed; [`write_indent_vtu`] writes each point's mesh.
///
/// # Errors
/// [`ModelError::Io`] when the file cannot be written.
pub fn write_indent_csv(
    dir: &Path,
    scene: &Scene,
    points: &[IndentPoint],
) -> Result<(), ModelError> {
    use std::fmt::Write as _;
    std::fs::create_dir_all(dir).map_err(io_error(dir))?;
    let s = 1.0 / scene.length_unit_m;
    let mut csv = String::from("depth,fx,fy,fz,contact_radius\n");
    for p in points {
        let f = p.force_on_sphere_n;
        let _ = writeln!(
            csv,
            "{:.9e},{:.9e},{:.9e},{:.9e},{:.9e}",
            p.depth_m * s,
            f.x,
            f.y,
            f.z,
            p.contact_radius_m * s
        );
    }
    let path = dir.join("indent.csv");
    std::fs::write(&path, csv).map_err(io_error(&path))
}

/// Writes the deformed mesh of the `k`-th point (0-based) as `dir/`[`indent_vtu_name`]`(k)`.
///
/// # Errors
/// [`ModelError::Io`] when the file cannot be written.
pub fn write_indent_vtu(
    dir: &Path,
    scene: &Scene,
    k: usize,
    point: &IndentPoint,
) -> Result<(), ModelError> {
    write_mesh_vtu(
        &dir.join(indent_vtu_name(k)),
        &scene.mesh,
        &point.x_m,
        scene.length_unit_m,
    )
}
