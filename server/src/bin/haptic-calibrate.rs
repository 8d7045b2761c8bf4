//! `haptic-calibrate SCENE`: computes the spring-constant lookup table of a mass-spring scene
//! (haptic subdivision, Zhang, Payandeh & Dill section 3.2.4) and writes it beside the scene
//! (its `mass_spring.calibration_file`), showing progress. A valid table is kept unless
//! `--force`. `SCENE` is a scene file, or a built-in scene name with `--out FILE`.

use std::io::Write as _;
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;

/// Calibrate the subdivided spring constants of a mass-spring scene.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Scene file (TOML), or a built-in scene name.
    scene: String,
    /// Where to write the table [default: the scene's calibration_file beside it].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Worker threads [default: every core].
    #[arg(long)]
    threads: Option<usize>,
    /// Recompute even when the table is valid.
    #[arg(long)]
    force: bool,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let path = PathBuf::from(&args.scene);
    let scene = if path.exists() {
        haptic_model::scene::load_scene_file(&path)
    } else {
        haptic_model::scene::load_builtin(&args.scene)
    }
    .with_context(|| format!("loading {}", args.scene))?;
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    eprintln!("calibrating {} on {threads} thread(s) ...", scene.name);
    let last = std::sync::Mutex::new(0usize);
    let report = haptic_server::calibrate::calibrate_scene(
        &scene,
        args.out.as_deref(),
        threads,
        args.force,
        &|done, total, elapsed| {
            let pct = 100 * done / total.max(1);
            let mut l = last.lock().unwrap_or_else(|e| e.into_inner());
            if pct > *l || done == total {
                *l = pct;
                let eta = elapsed / done as f64 * (total - done) as f64;
                eprint!(
                    "\r  {done}/{total} nodes ({pct} %), {elapsed:.0} s, about {eta:.0} s left   "
                );
                let _ = std::io::stderr().flush();
            }
        },
    )?;
    if report.computed {
        eprintln!();
        println!(
            "wrote {} ({} nodes in {:.1} s; K'_h/K_h from {:.3} to {:.3})",
            report.path.display(),
            report.nodes,
            report.seconds,
            report.scale_range.0,
            report.scale_range.1
        );
    } else {
        println!(
            "{} is up to date ({} nodes); --force recomputes it",
            report.path.display(),
            report.nodes
        );
    }
    Ok(())
}
