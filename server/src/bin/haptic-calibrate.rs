//! `haptic-calibrate SCENE`: computes the spring-constant lookup table of a mass-spring scene
//! (haptic subdivision, Zhang, Payandeh & Dill section 3.2.4) and writes it beside the scene
//! (its `mass_spring.calibration_file`), showing progress. A valid table is kept unless
//! `--force`. `SCENE` is a scene file, or a built-in scene name with `--out FILE`.

use std::io::Write as _;
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use haptic_server::calibrate::{Outputs, TableKind, calibrate_scene};

/// Calibrate the subdivided spring constants of a mass-spring scene.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Scene file (TOML), or a built-in scene name.
    scene: String,
    /// Where to write the subdivision table [default: the scene's calibration_file beside it].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Where to write the organ table [default: the scene's organ_file beside it].
    #[arg(long)]
    organ_out: Option<PathBuf>,
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
    let last = std::sync::Mutex::new((TableKind::Organ, usize::MAX));
    let outputs = Outputs {
        subdivision: args.out.as_deref(),
        organ: args.organ_out.as_deref(),
    };
    let reports = calibrate_scene(
        &scene,
        outputs,
        threads,
        args.force,
        &|kind, done, total, elapsed| {
            let pct = 100 * done / total.max(1);
            let mut l = last.lock().unwrap_or_else(|e| e.into_inner());
            if (kind, pct) != *l || done == total {
                *l = (kind, pct);
                let eta = elapsed / done as f64 * (total - done) as f64;
                eprint!(
                    "\r  {}: {done}/{total} {} ({pct} %), {elapsed:.0} s, about {eta:.0} s left   ",
                    kind.name(),
                    kind.unit()
                );
                let _ = std::io::stderr().flush();
                if done == total {
                    eprintln!();
                }
            }
        },
    )?;
    for r in reports {
        let factor = match r.kind {
            TableKind::Organ => "contact factor",
            TableKind::Subdivision => "K'_h/K_h",
        };
        if r.computed {
            println!(
                "wrote {} {} ({} {} in {:.1} s; {factor} from {:.3} to {:.3})",
                r.kind.name(),
                r.path.display(),
                r.nodes,
                r.kind.unit(),
                r.seconds,
                r.factor_range.0,
                r.factor_range.1
            );
        } else {
            println!(
                "{} {} is up to date ({} {}); --force recomputes it",
                r.kind.name(),
                r.path.display(),
                r.nodes,
                r.kind.unit()
            );
        }
    }
    Ok(())
}
