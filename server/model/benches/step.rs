//! Step-time benchmark (issue 2, section 10): median / p99 / max wall time of a full servo tick
//! (all sub-steps) and of one internal-force evaluation, on one thread, for the LV meshes of
//! `../shared/data/lv/` and the built-in `lv`, with the three integrators (backward Euler also
//! reports its mean CG iterations per tick), while the probe presses the epicardium (the haptic
//! case: contact and implicit coupling active), with each contact model the integrator carries
//! (the Hertz patch, the sphere and the patch under every integrator; the sphere is implicit
//! under backward Euler), backward Euler also with the rest matrix factorised once on the whole
//! body (`linear_solver = "rest-cholesky"`, the built-in `lv`'s default; Hertz patch and
//! sphere), and for the condensed `lv_h1` scene
//! (backward Euler only).
//!
//! Run: `cargo bench -p haptic-model --bench step` (add `-- --quick` for fewer ticks).
//! Writes `target/bench/step.csv` (or `--out DIR`) and prints a table. Medians and ratios
//! measured in one run are what to quote: these 2-core machines are shared and noisy.

mod common;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use clap::Parser;
use common::TickTimes;
use haptic_model::DVec3;
use haptic_model::contact::ContactModel;
use haptic_model::fem::{FemBody, TickInput};
use haptic_model::integrate::{IntegratorKind, LinearSolver};
use haptic_model::scene::{Scene, load_builtin, load_scene_file};
use serde::Serialize;

/// Step-time benchmark: servo tick and force evaluation per LV mesh and integrator.
#[derive(Debug, Parser)]
#[command(name = "step")]
struct Args {
    /// Fewer ticks: 50 force evaluations and at most 500 ticks (3 s of wall time) per run,
    /// instead of 300 and 2000 (15 s).
    #[arg(long)]
    quick: bool,
    /// Folder of step.csv [default: target/bench of the workspace].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Passed by `cargo bench` to every harness-less benchmark; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// One row of `step.csv`.
#[derive(Debug, Serialize)]
struct StepRow<'a> {
    scene: &'a str,
    integrator: &'static str,
    contact: &'static str,
    nodes: usize,
    tets: usize,
    substeps: u32,
    critical_dt_s: f64,
    tick_p50_us: f64,
    tick_p99_us: f64,
    tick_max_us: f64,
    force_eval_p50_us: f64,
    realtime_factor: f64,
    ticks: u64,
    cg_iterations_mean: f64,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let quick = args.quick;
    let root = common::workspace_root();
    let scenes = load_scenes(&root);
    let out = args.out.unwrap_or_else(common::default_out_dir);
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let path = out.join("step.csv");
    let mut csv = csv::Writer::from_path(&path)?;
    print_header();
    for (name, scene) in &scenes {
        for kind in [
            IntegratorKind::SemiImplicit,
            IntegratorKind::SymplecticEuler,
            IntegratorKind::BackwardEuler,
        ] {
            // Backward Euler also with the rest matrix factorised once on the whole body
            // (`integrator.linear_solver = "rest-cholesky"`), with the default contact and the
            // sphere.
            let rest_factor =
                kind == IntegratorKind::BackwardEuler && scene.active_region.is_none();
            let runs = [
                (ContactModel::PatchHertz, LinearSolver::Cg),
                (ContactModel::Sphere, LinearSolver::Cg),
                (ContactModel::Patch, LinearSolver::Cg),
                (ContactModel::PatchHertz, LinearSolver::RestCholesky),
                (ContactModel::Sphere, LinearSolver::RestCholesky),
            ];
            for (contact, solver) in runs {
                if solver == LinearSolver::RestCholesky && !rest_factor {
                    continue;
                }
                // A condensed region runs backward Euler only.
                let condensed_other =
                    scene.active_region.is_some() && kind != IntegratorKind::BackwardEuler;
                if condensed_other {
                    continue;
                }
                let mut sc = scene.clone();
                sc.integrator.kind = kind;
                sc.probe.contact = contact;
                sc.integrator.linear_solver = solver;
                sc.integrator.max_substeps = 1000;
                let mut sim = match FemBody::new(&sc) {
                    Ok(s) => s,
                    Err(e) => {
                        eprintln!("{name} {kind:?}: {e}");
                        continue;
                    }
                };
                let row = measure(name, (kind, contact, solver), &mut sim, quick);
                print_row(&row);
                csv.serialize(&row)?;
            }
        }
    }
    csv.flush()?;
    println!("wrote {}", path.display());
    Ok(())
}

/// The built-in `lv` and the deploy LV scenes that load (the others are reported and skipped).
fn load_scenes(root: &std::path::Path) -> Vec<(String, Scene)> {
    let mut scenes: Vec<(String, Scene)> = vec![(
        "lv (built-in)".into(),
        load_builtin("lv").expect("built-in lv"),
    )];
    for f in ["lv_h3", "lv_h2", "lv_h1", "lv_h1_condensed"] {
        let path = root.join(format!("deploy/scenes/{f}.toml"));
        match load_scene_file(&path) {
            Ok(s) => scenes.push((
                match f.strip_suffix("_condensed") {
                    Some(mesh) => format!("{mesh} condensed"),
                    None => format!("{f}.msh"),
                },
                s,
            )),
            Err(e) => eprintln!("skipping {f}: {e}"),
        }
    }
    scenes
}

fn print_header() {
    println!(
        "{:<15} {:<19} {:<7} {:>6} {:>6} {:>4} {:>11} {:>10} {:>10} {:>10} {:>11} {:>8} {:>6}",
        "scene",
        "integrator",
        "contact",
        "nodes",
        "tets",
        "sub",
        "dt_crit_s",
        "tick p50",
        "tick p99",
        "tick max",
        "force p50",
        "RT x",
        "CG"
    );
}

/// Times the force evaluation and the ticks of `sim`, built for `(kind, contact, solver)`.
fn measure<'a>(
    name: &'a str,
    (kind, contact, solver): (IntegratorKind, ContactModel, LinearSolver),
    sim: &mut FemBody,
    quick: bool,
) -> StepRow<'a> {
    let n = sim.fem().node_count();
    let fe = force_eval_times(sim, quick);
    // Full ticks while pressing 6 mm along -x at the equator (z = -5 mm).
    let budget_s = if quick { 3.0 } else { 15.0 };
    let max_ticks = if quick { 500 } else { 2000 };
    let mut times = TickTimes::new();
    let mut cg_iterations = 0u64;
    let wall = Instant::now();
    for k in 0..max_ticks {
        let depth = 0.006 * (k as f64 / 1000.0).min(1.0);
        let input = TickInput {
            device_position_m: Some(DVec3::new(0.014 - depth, 0.0, -0.005)),
            device_velocity_m_per_s: DVec3::new(-0.006, 0.0, 0.0),
        };
        let t = Instant::now();
        sim.tick(&input).expect("tick");
        times.record(t.elapsed());
        cg_iterations += u64::from(sim.cg_stats().iterations);
        if wall.elapsed().as_secs_f64() > budget_s {
            break;
        }
    }
    let plan = sim.plan();
    let tick = times.percentiles();
    StepRow {
        scene: name,
        integrator: match (kind, solver) {
            (IntegratorKind::BackwardEuler, LinearSolver::RestCholesky) => "backward-euler/rest",
            _ => kind.name(),
        },
        contact: contact.name(),
        nodes: n,
        tets: sim.fem().tets().len(),
        substeps: plan.substeps,
        critical_dt_s: plan.critical_dt_s,
        tick_p50_us: tick.p50_us,
        tick_p99_us: tick.p99_us,
        tick_max_us: tick.max_us,
        force_eval_p50_us: fe.percentiles().p50_us,
        realtime_factor: 1000.0 / tick.p50_us,
        ticks: times.len(),
        cg_iterations_mean: cg_iterations as f64 / times.len() as f64,
    }
}

/// Force evaluation alone.
fn force_eval_times(sim: &FemBody, quick: bool) -> TickTimes {
    let n = sim.fem().node_count();
    let mut f = vec![DVec3::ZERO; n];
    let mut scratch = haptic_model::element::ForceScratch::new(n);
    let mut fe = TickTimes::new();
    for _ in 0..if quick { 50 } else { 300 } {
        f.iter_mut().for_each(|v| *v = DVec3::ZERO);
        let t = Instant::now();
        // In the scene's precision (single on the lv_h* scenes).
        sim.fem().add_internal_forces_with(
            &sim.state().x,
            Some(&sim.state().v),
            &mut f,
            &mut scratch,
        );
        fe.record(t.elapsed());
    }
    fe
}

fn print_row(row: &StepRow<'_>) {
    println!(
        "{:<15} {:<19} {:<7} {:>6} {:>6} {:>4} {:>11.3e} {:>8.0}us {:>8.0}us {:>8.0}us {:>9.0}us {:>8.2} {:>6.1}",
        row.scene,
        row.integrator,
        row.contact,
        row.nodes,
        row.tets,
        row.substeps,
        row.critical_dt_s,
        row.tick_p50_us,
        row.tick_p99_us,
        row.tick_max_us,
        row.force_eval_p50_us,
        row.realtime_factor,
        row.cg_iterations_mean
    );
}
