//! Helpers shared by the benchmarks (`precision`, `step`, `micro`) and the examples that
//! measure (`soak`, `smoothing_study`, `lv_study`, `export_peer_case`): the method list, scene
//! builders for the LV at a chosen resolution, the LV probe press ([`lv_press`]), a driver for
//! dynamic runs under constant loads, wall-time percentiles ([`TickTimes`]), output folders and
//! the git commit.
//!
//! Each binary includes this module with `mod common;` (examples with
//! `#[path = "../benches/common/mod.rs"]`) and uses only part of it.
#![allow(dead_code)]

pub mod lv_press;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use haptic_model::DVec3;
use haptic_model::contact::{Probe, ProbeParams};
use haptic_model::element::FemModel;
use haptic_model::integrate::{self, FemState, IntegratorKind, IntegratorParams, Stepper};
use haptic_model::material::MaterialModel;
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate;
use haptic_model::scene::{Scene, load_builtin};
use hdrhistogram::Histogram;

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

/// The workspace root (two levels above this package).
pub fn workspace_root() -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    root.canonicalize().unwrap_or(root)
}

/// Where results go when nothing else is asked: `target/bench/` under the workspace root, so
/// that a benchmark run leaves the work tree clean (`--publish` writes into `docs/` instead).
pub fn default_out_dir() -> PathBuf {
    workspace_root().join("target/bench")
}

/// Wall times of repeated operations (servo ticks, force evaluations, solves) in an HDR
/// histogram with microsecond resolution: 1 us to 60 s at 3 significant digits, the bounds of
/// the server's servo statistics. Recording does not allocate (values beyond 60 s saturate), so
/// the soak can record every tick of an hour; percentiles are computed in one place.
pub struct TickTimes {
    hist: Histogram<u64>,
}

/// Median, 99th percentile and maximum of a [`TickTimes`], us (NaN when nothing was recorded).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Percentiles {
    /// Median, us.
    pub p50_us: f64,
    /// 99th percentile, us.
    pub p99_us: f64,
    /// Largest value, us.
    pub max_us: f64,
}

impl Default for TickTimes {
    fn default() -> Self {
        Self::new()
    }
}

impl TickTimes {
    /// An empty histogram.
    pub fn new() -> Self {
        Self {
            hist: Histogram::new_with_bounds(1, 60_000_000, 3).expect("static histogram bounds"),
        }
    }

    /// Records one wall time, rounded to the microsecond.
    pub fn record(&mut self, elapsed: Duration) {
        let us = (elapsed.as_nanos() + 500) / 1000;
        self.hist
            .saturating_record(u64::try_from(us).unwrap_or(u64::MAX));
    }

    /// Number of recorded times.
    pub fn len(&self) -> u64 {
        self.hist.len()
    }

    /// Whether nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.hist.is_empty()
    }

    /// p50 / p99 / max, us.
    pub fn percentiles(&self) -> Percentiles {
        if self.hist.is_empty() {
            return Percentiles {
                p50_us: f64::NAN,
                p99_us: f64::NAN,
                max_us: f64::NAN,
            };
        }
        Percentiles {
            p50_us: self.hist.value_at_quantile(0.5) as f64,
            p99_us: self.hist.value_at_quantile(0.99) as f64,
            max_us: self.hist.max() as f64,
        }
    }

    /// Number of recorded times of at least `us` microseconds (exact below 2 048 us; above,
    /// to the histogram's 3 significant digits).
    pub fn count_at_least_us(&self, us: u64) -> u64 {
        if self.hist.is_empty() || us > self.hist.max() {
            return 0;
        }
        self.hist.count_between(us, self.hist.max())
    }

    /// Forgets every recorded time (keeps the allocation).
    pub fn reset(&mut self) {
        self.hist.reset();
    }
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
/// epicardium touchable; with symplectic Euler instead of the scene's backward Euler on the
/// rest factor, so that a scene built on a large mesh factorises nothing unless its caller
/// chooses backward Euler (and its linear solver: the rest factor of the built-in scene is
/// kept for it).
pub fn lv_scene_on(mesh: TetMesh) -> Scene {
    let mut scene = load_builtin("lv").expect("built-in lv scene");
    scene.integrator.kind = haptic_model::integrate::IntegratorKind::SymplecticEuler;
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

/// The built-in `lv` scene on `lv_shell(tets)`, with quadratic (10-node) elements if
/// `quadratic`.
pub fn lv_scene_order(tets: usize, quadratic: bool) -> Scene {
    if quadratic {
        lv_scene_on(generate::lv_shell_quadratic(tets))
    } else {
        lv_scene(tets)
    }
}

/// The `lv_h1.msh` scene of `deploy/scenes/` (17 924 tets), if the shared data is present.
pub fn lv_h1_scene() -> Option<Scene> {
    haptic_model::scene::load_scene_file(&workspace_root().join("deploy/scenes/lv_h1.toml")).ok()
}

/// Result of [`run_loaded_with`].
pub struct LoadedRun {
    /// Final positions, m.
    pub x: Vec<DVec3>,
    /// Wall time of every servo tick.
    pub ticks: TickTimes,
    /// Sub-steps per tick.
    pub substeps: u32,
    /// Whether the run stayed finite and below the divergence speed.
    pub stable: bool,
    /// Simulated time when the run stopped, s.
    pub time_s: f64,
}

/// Runs `fem` (built on `mesh`) dynamically for `total_s` under the dead nodal load `f_ext`
/// (N), ramped in with a smoothstep over `ramp_s`, with the servo tick of `params` divided into
/// the sub-steps that keep each step below its safety factor times the critical step of its
/// integrator. Each sub-step is the library's [`Stepper`], as in `FemBody::tick` without a
/// probe: internal forces ([`Stepper::add_internal_forces`]: elastic, plus viscous for the
/// explicit schemes), the external load, then [`Stepper::step`]. The probe the stepper asks
/// for has no touchable surface, so it is never in contact and its coupling completion does
/// nothing. After the ramp the run stops early once it is at steady state: the largest nodal
/// speed times 0.1 s is below 1e-4 of the largest displacement. Returns `Err` when the plan is
/// refused.
pub fn run_loaded_with(
    fem: &FemModel,
    mesh: &TetMesh,
    params: &IntegratorParams,
    f_ext: &[DVec3],
    ramp_s: f64,
    total_s: f64,
) -> Result<LoadedRun, String> {
    let crit = integrate::critical_time_step(fem, params.kind);
    let plan = integrate::plan_steps(params, crit).map_err(|e| e.to_string())?;
    let h = plan.sub_dt_s;
    let mut stepper = Stepper::new(fem, mesh, params, &plan, None).map_err(|e| e.to_string())?;
    let mut probe = Probe::new(ProbeParams::default(), Vec::new(), fem.rest());
    let n = fem.node_count();
    let mut state = FemState {
        x: fem.rest().to_vec(),
        v: vec![DVec3::ZERO; n],
        time_s: 0.0,
    };
    let mut f = vec![DVec3::ZERO; n];
    let mut scratch = haptic_model::element::ForceScratch::new(n);
    let ticks = (total_s / params.tick_s).round() as usize;
    let mut tick_times = TickTimes::new();
    let mut stable = true;
    let mut time_s = 0.0;
    'outer: for k in 0..ticks {
        let t0 = Instant::now();
        for s in 0..plan.substeps {
            let t = k as f64 * params.tick_s + s as f64 * h;
            let scale = smoothstep(t / ramp_s);
            f.iter_mut().zip(f_ext).for_each(|(f, e)| *f = *e * scale);
            stepper.add_internal_forces(fem, &state.x, &state.v, &mut f, &mut scratch);
            let max_v2 = stepper
                .step(fem, &f, &mut probe, &mut state)
                .max_speed2_m2_per_s2;
            if max_v2.is_nan() || max_v2 > 1e4 {
                stable = false;
                break 'outer;
            }
        }
        tick_times.record(t0.elapsed());
        let t = (k + 1) as f64 * params.tick_s;
        if t > ramp_s && k % 10 == 0 {
            let vmax = state.v.iter().map(|v| v.length()).fold(0.0, f64::max);
            let umax = state
                .x
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
        x: state.x,
        ticks: tick_times,
        substeps: plan.substeps,
        stable,
        time_s,
    })
}

/// The epicardium points where the `lv-probe` surface-displacement error is read, m, on the
/// analytic epicardium (the ellipsoid of semi-axes 10, 10, 20 mm of `../shared/data/lv`): the
/// contact point of the lv-probe line (9.682 mm from the axis at z = -5 mm), 5 points each
/// way along the circumference (arcs 0.48 to 4.3 mm) and 5 each way along the meridian
/// (z = -5 mm +- 0.5 to 4.2 mm). Each body locates them on its own surface by the closest
/// point. Shared by `lv_study reference --surface` (the reference) and the benchmark.
pub fn surface_sample_points_m() -> Vec<DVec3> {
    let radius_at = |z: f64| 0.010 * (1.0 - (z / 0.020).powi(2)).sqrt();
    let r = radius_at(PROBE_Z_M);
    let mut points = vec![DVec3::new(r, 0.0, PROBE_Z_M)];
    for a in [0.05, 0.1, 0.175, 0.26, 0.44] {
        for s in [-1.0, 1.0] {
            let t: f64 = s * a;
            points.push(DVec3::new(r * t.cos(), r * t.sin(), PROBE_Z_M));
        }
    }
    for dz in [0.5e-3, 1e-3, 1.7e-3, 2.5e-3, 4.2e-3] {
        for s in [-1.0, 1.0] {
            let z = PROBE_Z_M + s * dz;
            points.push(DVec3::new(radius_at(z), 0.0, z));
        }
    }
    points
}
