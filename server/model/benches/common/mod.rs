//! Helpers shared by the `precision` and `micro` benchmarks: the method list, scene builders for
//! the LV at a chosen resolution, a driver for dynamic runs under constant loads, timing
//! statistics and the git commit.
//!
//! Each bench binary includes this module with `mod common;` and uses only part of it.
#![allow(dead_code)]

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::integrate::implicit::ImplicitSolver;
use haptic_model::integrate::{self, IntegratorKind, IntegratorParams, explicit};
use haptic_model::material::MaterialModel;
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate;
use haptic_model::scene::{Scene, load_builtin};

/// The time integrators the benchmarks compare, in one place: a new integrator is one line here
/// (its name comes from [`IntegratorKind::name`]).
pub const INTEGRATORS: &[IntegratorKind] = &[
    IntegratorKind::SemiImplicit,
    IntegratorKind::SymplecticEuler,
    IntegratorKind::BackwardEuler,
];

/// Backward Euler: the CG iteration caps swept (`IntegratorParams::cg_max_iterations`).
pub const CG_ITERATIONS: &[u32] = &[5, 10, 20];

/// The material models the benchmarks compare (label from [`MaterialModel::scene_name`]).
pub const MATERIALS: &[MaterialModel] = &[
    MaterialModel::StVenantKirchhoff,
    MaterialModel::Corotational,
    MaterialModel::StableNeoHookean,
];

/// Probe centre x at first contact in the LV scenes: the epicardium at z = -5 mm is at 9.682 mm
/// from the axis, plus the 2 mm probe radius.
pub const CONTACT_X_M: f64 = 0.011_682;
/// Probe centre z in the LV scenes, m.
pub const PROBE_Z_M: f64 = -0.005;

/// The LV probe's device position at indentation `depth_m` (m) along -x.
pub fn device_at(depth_m: f64) -> DVec3 {
    DVec3::new(CONTACT_X_M - depth_m, 0.0, PROBE_Z_M)
}

/// `git rev-parse --short HEAD`, or "unknown".
pub fn git_commit() -> String {
    std::process::Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown".into())
}

/// Median / p99 / max of a sample (sorted in place). NaN for an empty sample.
pub fn stats(times: &mut [f64]) -> (f64, f64, f64) {
    if times.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    times.sort_by(f64::total_cmp);
    let p = |q: f64| times[((times.len() - 1) as f64 * q).round() as usize];
    (p(0.5), p(0.99), times[times.len() - 1])
}

/// `0` at `t <= 0`, `1` at `t >= 1`, smooth (C1) in between.
pub fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Derivative of [`smoothstep`] with respect to `t`.
pub fn smoothstep_rate(t: f64) -> f64 {
    if (0.0..=1.0).contains(&t) {
        6.0 * t * (1.0 - t)
    } else {
        0.0
    }
}

/// The built-in `lv` scene (material, probe, integrator settings) on `mesh`: base clamped,
/// epicardium touchable.
pub fn lv_scene_on(mesh: TetMesh) -> Scene {
    let mut scene = load_builtin("lv").expect("built-in lv scene");
    scene.clamped_nodes = mesh
        .nodes_of_surfaces(&["BASE".to_string()], "boundary.clamped")
        .expect("BASE surface");
    scene.touchable = mesh.surface("EPI").expect("EPI surface").triangles.clone();
    scene.mesh = mesh;
    scene
}

/// The built-in `lv` scene with the structured LV mesh at about `target_tets` tetrahedra.
pub fn lv_scene(target_tets: usize) -> Scene {
    lv_scene_on(generate::lv_shell(target_tets))
}

/// The `lv_h1.msh` scene of `deploy/scenes/` (17 924 tets), if the shared data is present.
pub fn lv_h1_scene() -> Option<Scene> {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes/lv_h1.toml");
    haptic_model::scene::load_scene_file(&path).ok()
}

/// Result of [`run_loaded`].
pub struct LoadedRun {
    /// Final positions, m.
    pub x: Vec<DVec3>,
    /// Wall time of every servo tick, us.
    pub tick_us: Vec<f64>,
    /// Sub-steps per tick.
    pub substeps: u32,
    /// Whether the run stayed finite and below the divergence speed.
    pub stable: bool,
    /// Simulated time when the run stopped, s.
    pub time_s: f64,
}

/// [`run_loaded_with`] with the default CG settings.
pub fn run_loaded(
    fem: &FemModel,
    kind: IntegratorKind,
    safety: f64,
    f_ext: &[DVec3],
    ramp_s: f64,
    total_s: f64,
) -> Result<LoadedRun, String> {
    let params = IntegratorParams {
        kind,
        safety_factor: safety,
        max_substeps: 2000,
        ..IntegratorParams::default()
    };
    run_loaded_with(fem, &params, f_ext, ramp_s, total_s)
}

/// Runs `fem` dynamically for `total_s` under the dead nodal load `f_ext` (N), ramped in with
/// a smoothstep over `ramp_s`, with the servo tick of `params` divided into the sub-steps that
/// keep each step below its safety factor times the critical step of its integrator. The same
/// per-sub-step work as `Simulation::tick` without a probe: internal forces (elastic, plus
/// viscous for the explicit schemes), external load, then `explicit::integrate_nodes` or
/// `ImplicitSolver::step` (backward Euler, CG capped at `params.cg_max_iterations`). After the
/// ramp the run stops early once it is at steady state: the largest nodal speed times 0.1 s is
/// below 1e-4 of the largest displacement. Returns `Err` when the plan is refused.
pub fn run_loaded_with(
    fem: &FemModel,
    params: &IntegratorParams,
    f_ext: &[DVec3],
    ramp_s: f64,
    total_s: f64,
) -> Result<LoadedRun, String> {
    let kind = params.kind;
    let crit = integrate::critical_time_step(fem, kind);
    let plan = integrate::plan_steps(params, crit).map_err(|e| e.to_string())?;
    let h = plan.sub_dt_s;
    let a_inv = if kind == IntegratorKind::SemiImplicit {
        explicit::semi_implicit_inverses(fem, h)
    } else {
        Vec::new()
    };
    let mut implicit =
        (kind == IntegratorKind::BackwardEuler).then(|| ImplicitSolver::new(fem, h, params));
    let n = fem.node_count();
    let mut x = fem.rest().to_vec();
    let mut v = vec![DVec3::ZERO; n];
    let mut f = vec![DVec3::ZERO; n];
    let ticks = (total_s / params.tick_s).round() as usize;
    let mut tick_us = Vec::with_capacity(ticks);
    let mut stable = true;
    let mut time_s = 0.0;
    'outer: for k in 0..ticks {
        let t0 = Instant::now();
        for s in 0..plan.substeps {
            let t = k as f64 * params.tick_s + s as f64 * h;
            let scale = smoothstep(t / ramp_s);
            f.iter_mut().zip(f_ext).for_each(|(f, e)| *f = *e * scale);
            let max_v2 = match &mut implicit {
                // Backward Euler treats the viscous force implicitly inside its solve.
                Some(solver) => {
                    fem.add_internal_forces(&x, None, &mut f);
                    solver.step(fem, &f, None, &mut x, &mut v)
                }
                None => {
                    fem.add_internal_forces(&x, Some(&v), &mut f);
                    explicit::integrate_nodes(kind, fem, &a_inv, h, &f, &mut x, &mut v)
                }
            };
            if max_v2.is_nan() || max_v2 > 1e4 {
                stable = false;
                break 'outer;
            }
        }
        tick_us.push(t0.elapsed().as_secs_f64() * 1e6);
        let t = (k + 1) as f64 * params.tick_s;
        if t > ramp_s && k % 10 == 0 {
            let vmax = v.iter().map(|v| v.length()).fold(0.0, f64::max);
            let umax = x
                .iter()
                .zip(fem.rest())
                .map(|(x, r)| (*x - *r).length())
                .fold(0.0, f64::max);
            if vmax * 0.1 < 1e-4 * umax {
                time_s = t;
                break;
            }
        }
        time_s = t;
    }
    Ok(LoadedRun {
        x,
        tick_us,
        substeps: plan.substeps,
        stable,
        time_s,
    })
}
