//! Step-time benchmark (issue 2, section 10): median / p99 / max wall time of a full servo tick
//! (all sub-steps) and of one internal-force evaluation, on one thread, for the LV meshes of
//! `../shared/data/lv/` and the built-in `lv`, with the three integrators (backward Euler also
//! reports its mean CG iterations per tick), while the probe presses the epicardium (the haptic
//! case: contact, patch and implicit coupling active).
//!
//! Run: `cargo bench -p haptic-model --bench step` (add `-- --quick` for fewer ticks).
//! Writes `target/bench/step.csv` and prints a table. Medians and ratios measured in one run are
//! what to quote: these 2-core machines are shared and noisy.

use std::path::Path;
use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::integrate::IntegratorKind;
use haptic_model::scene::{Scene, load_builtin, load_scene_file};
use haptic_model::sim::{Simulation, TickInput};

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut scenes: Vec<(String, Scene)> = vec![(
        "lv (built-in)".into(),
        load_builtin("lv").expect("built-in lv"),
    )];
    for f in ["lv_h3", "lv_h2", "lv_h1"] {
        let path = root.join(format!("deploy/scenes/{f}.toml"));
        match load_scene_file(&path) {
            Ok(s) => scenes.push((format!("{f}.msh"), s)),
            Err(e) => eprintln!("skipping {f}: {e}"),
        }
    }
    let mut csv = String::from(
        "scene,integrator,nodes,tets,substeps,critical_dt_s,tick_p50_us,tick_p99_us,tick_max_us,force_eval_p50_us,realtime_factor,ticks,cg_iterations_mean\n",
    );
    println!(
        "{:<15} {:<17} {:>6} {:>6} {:>4} {:>11} {:>10} {:>10} {:>10} {:>11} {:>8} {:>6}",
        "scene",
        "integrator",
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
    for (name, scene) in &scenes {
        for kind in [
            IntegratorKind::SemiImplicit,
            IntegratorKind::SymplecticEuler,
            IntegratorKind::BackwardEuler,
        ] {
            let mut sc = scene.clone();
            sc.integrator.kind = kind;
            sc.integrator.max_substeps = 1000;
            let mut sim = match Simulation::new(&sc) {
                Ok(s) => s,
                Err(e) => {
                    eprintln!("{name} {kind:?}: {e}");
                    continue;
                }
            };
            // Force evaluation alone.
            let n = sim.fem().node_count();
            let mut f = vec![DVec3::ZERO; n];
            let mut fe = Vec::new();
            for _ in 0..if quick { 50 } else { 300 } {
                f.iter_mut().for_each(|v| *v = DVec3::ZERO);
                let t = Instant::now();
                sim.fem()
                    .add_internal_forces(&sim.state().x, Some(&sim.state().v), &mut f);
                fe.push(t.elapsed().as_secs_f64() * 1e6);
            }
            fe.sort_by(f64::total_cmp);
            // Full ticks while pressing 6 mm along -x at the equator (z = -5 mm).
            let budget_s = if quick { 3.0 } else { 15.0 };
            let max_ticks = if quick { 500 } else { 2000 };
            let mut times = Vec::with_capacity(max_ticks);
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
                times.push(t.elapsed().as_secs_f64() * 1e6);
                cg_iterations += u64::from(sim.cg_stats().iterations);
                if wall.elapsed().as_secs_f64() > budget_s {
                    break;
                }
            }
            times.sort_by(f64::total_cmp);
            let plan = sim.plan();
            let p50 = percentile(&times, 0.5);
            let rt = 1000.0 / p50;
            let cg_mean = cg_iterations as f64 / times.len() as f64;
            println!(
                "{:<15} {:<17} {:>6} {:>6} {:>4} {:>11.3e} {:>8.0}us {:>8.0}us {:>8.0}us {:>9.0}us {:>8.2} {:>6.1}",
                name,
                kind.name(),
                n,
                sim.fem().tets().len(),
                plan.substeps,
                plan.critical_dt_s,
                p50,
                percentile(&times, 0.99),
                times[times.len() - 1],
                percentile(&fe, 0.5),
                rt,
                cg_mean
            );
            csv.push_str(&format!(
                "{name},{},{n},{},{},{:.6e},{p50:.1},{:.1},{:.1},{:.1},{rt:.3},{},{cg_mean:.2}\n",
                kind.name(),
                sim.fem().tets().len(),
                plan.substeps,
                plan.critical_dt_s,
                percentile(&times, 0.99),
                times[times.len() - 1],
                percentile(&fe, 0.5),
                times.len()
            ));
        }
    }
    let out = root.join("target/bench");
    std::fs::create_dir_all(&out).expect("creating target/bench");
    std::fs::write(out.join("step.csv"), csv).expect("writing step.csv");
    println!("wrote {}", out.join("step.csv").display());
}
