//! Static solutions of scene files for reference and inspection (`haptic-solve`): the scene's
//! loads applied in increments, Newton at each increment ([`haptic_model::statics`]), follower
//! pressures by a fixed point on the load, results written as `nodes.csv` and a ParaView `.vtu`
//! in the scene's length unit.

use std::path::Path;

use haptic_model::fem::FemModel;
use haptic_model::scene::Scene;
use haptic_model::sim::static_external_forces;
use haptic_model::statics::{StaticParams, solve_static};
use haptic_model::{DVec3, ModelError};

/// What a static solve did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveReport {
    /// Load increments.
    pub load_steps: usize,
    /// Newton iterations over all increments.
    pub newton_iterations: usize,
    /// Final free residual, N.
    pub residual_n: f64,
    /// Largest nodal displacement, m.
    pub max_displacement_m: f64,
}

/// Solves the scene's static equilibrium under its `[loads]` with `load_steps` increments
/// (each increment re-evaluates follower pressures until the load changes by less than 1e-8
/// relative, at most 20 times). Returns the node positions, m.
///
/// # Errors
/// [`ModelError::InvalidInput`] when the scene has no loads; [`ModelError::NoConvergence`]
/// when Newton fails at some increment (the message names it).
pub fn solve_scene(
    scene: &Scene,
    load_steps: usize,
) -> Result<(Vec<DVec3>, SolveReport), ModelError> {
    if scene.loads.is_empty() {
        return Err(ModelError::InvalidInput(
            "the scene has no [loads] (gravity, pressure or point forces): nothing to solve".into(),
        ));
    }
    let mut fem = FemModel::with_smoothing(&scene.mesh, scene.material, scene.strain_smoothing)?;
    fem.clamp_nodes(&scene.clamped_nodes);
    let follower = scene.loads.pressure.iter().any(|p| p.follower);
    let steps = load_steps.max(1);
    let mut x = scene.mesh.nodes.clone();
    let mut report = SolveReport {
        load_steps: steps,
        newton_iterations: 0,
        residual_n: 0.0,
        max_displacement_m: 0.0,
    };
    let params = StaticParams {
        rel_tol: 1e-9,
        ..StaticParams::default()
    };
    for k in 1..=steps {
        let scale = k as f64 / steps as f64;
        let mut previous: Option<Vec<DVec3>> = None;
        for _ in 0..if follower { 20 } else { 1 } {
            let f: Vec<DVec3> = static_external_forces(scene, &x)
                .into_iter()
                .map(|v| v * scale)
                .collect();
            if let Some(p) = &previous {
                let change: f64 = f
                    .iter()
                    .zip(p)
                    .map(|(a, b)| (*a - *b).length_squared())
                    .sum::<f64>()
                    .sqrt();
                let size: f64 = f.iter().map(|a| a.length_squared()).sum::<f64>().sqrt();
                if change <= 1e-8 * size {
                    break;
                }
            }
            let r = solve_static(&fem, &f, &mut x, &params).map_err(|e| {
                ModelError::NoConvergence(format!("load increment {k}/{steps}: {e}"))
            })?;
            report.newton_iterations += r.iterations;
            report.residual_n = r.residual_n;
            previous = Some(f);
        }
    }
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
    haptic_model::export::write_nodes_csv(
        &dir.join("nodes.csv"),
        &scene.mesh.nodes,
        x,
        scene.length_unit_m,
    )?;
    haptic_model::export::write_vtu(
        &dir.join("solution.vtu"),
        &scene.mesh,
        x,
        scene.length_unit_m,
    )
}
