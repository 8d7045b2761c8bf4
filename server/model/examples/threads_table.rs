//! Tick time at one and more threads, interleaved in one run (issue 48 section 1): each scene
//! built afresh for every run, handed a tick pool of `T - 1` workers (none for one thread) and
//! pressed at the lv-probe point (`haptic_model::press::staircase`: 0.5 s ramp and 1.5 s hold
//! per depth), the thread counts alternating round by round (the order reversed every other
//! round). Prints a row per run (set-up, tick p50 / p99, ticks over the 1 ms budget, the pool's
//! parts on its workers), then per scene and thread count the medians over the rounds and the
//! p50 speed-up against the first thread count.
//!
//! The pool's workers run at the caller's priority, unpinned: on a shared machine run it under
//! `chrt -f 10` (SCHED_FIFO, as the daemon's realtime servo; its workers take the servo's
//! priority) or a worker preempted while it holds a part stalls the tick.
//!
//! `cargo run --release -p haptic-model --example threads_table -- --scenes lv,lv-hybrid --rounds 1 --depths 0.5`

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use clap::Parser;
use haptic_model::pool::TickPool;
use haptic_model::press::{self, HoldParams, PressLine, quantile};
use haptic_model::scene::{Scene, load_builtin, load_scene_file};

/// Command line.
#[derive(Parser)]
#[command(about = "Tick time of scenes at one and more threads, interleaved")]
struct Args {
    /// Scenes: built-in names or .toml files.
    #[arg(long, value_delimiter = ',', default_value = "lv-hybrid")]
    scenes: Vec<String>,
    /// Thread counts (the servo's included), the first the baseline of the speed-up.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    threads: Vec<usize>,
    /// Rounds (each runs every thread count once per scene).
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// Device depths past first contact, mm.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    depths: Vec<f64>,
}

/// One run's figures.
struct Run {
    setup_s: f64,
    p50_s: f64,
    p99_s: f64,
    over_budget: usize,
    ticks: usize,
}

fn load(name: &str) -> Result<Scene, String> {
    let scene = if name.ends_with(".toml") {
        load_scene_file(Path::new(name))
    } else {
        load_builtin(name)
    };
    scene.map_err(|e| format!("{name}: {e}"))
}

/// Builds `scene` with `threads` threads and presses it; prints the run's row.
fn run(scene: &Scene, threads: usize, depths_m: &[f64]) -> Result<Run, String> {
    let t0 = Instant::now();
    let mut body = haptic_model::build_body(scene).map_err(|e| e.to_string())?;
    let pool = (threads > 1)
        .then(|| TickPool::new(threads - 1, Arc::new(|_| {})))
        .transpose()
        .map_err(|e| e.to_string())?;
    if let Some(pool) = &pool {
        body.set_tick_pool(Arc::clone(pool));
    }
    let setup_s = t0.elapsed().as_secs_f64();
    let info = body.info();
    let line = PressLine::lv_probe(info.probe_radius_m);
    let holds = HoldParams {
        ramp_s: 0.5,
        hold_s: 1.5,
        average_s: 1.0,
    };
    let (_, trace) = press::staircase(body.as_mut(), &line, depths_m, &holds, info.tick_s)
        .map_err(|e| format!("{}: {e}", scene.name))?;
    let times = &trace.tick_wall_s;
    let r = Run {
        setup_s,
        p50_s: quantile(times, 0.5),
        p99_s: quantile(times, 0.99),
        over_budget: times.iter().filter(|&&t| t > 1e-3).count(),
        ticks: times.len(),
    };
    let workers = pool.map_or(0, |p| p.stats().parts_on_workers);
    println!(
        "| {} | {threads} | {:.2} s | {:.0} / {:.0} us | {} of {} | {workers} |",
        scene.name,
        r.setup_s,
        r.p50_s * 1e6,
        r.p99_s * 1e6,
        r.over_budget,
        r.ticks
    );
    Ok(r)
}

fn main() -> Result<(), String> {
    let args = Args::parse();
    if args.threads.is_empty() || args.threads.iter().any(|&t| !(1..=16).contains(&t)) {
        return Err("--threads: counts in 1..=16".into());
    }
    let depths_m: Vec<f64> = args.depths.iter().map(|d| d * 1e-3).collect();
    let scenes = args
        .scenes
        .iter()
        .map(|s| load(s))
        .collect::<Result<Vec<_>, _>>()?;
    println!("| scene | threads | set-up | tick p50 / p99 | ticks over 1 ms | parts on workers |");
    println!("|---|---|---|---|---|---|");
    let mut runs: Vec<Vec<Vec<Run>>> = scenes
        .iter()
        .map(|_| args.threads.iter().map(|_| Vec::new()).collect())
        .collect();
    for round in 0..args.rounds {
        for (s, scene) in scenes.iter().enumerate() {
            let mut order: Vec<usize> = (0..args.threads.len()).collect();
            if round % 2 == 1 {
                order.reverse();
            }
            for k in order {
                runs[s][k].push(run(scene, args.threads[k], &depths_m)?);
            }
        }
    }
    summary(&scenes, &args.threads, &runs);
    Ok(())
}

/// Medians over the rounds per scene and thread count, and the p50 speed-up.
fn summary(scenes: &[Scene], threads: &[usize], runs: &[Vec<Vec<Run>>]) {
    println!();
    println!(
        "| scene | threads | p50 median | p99 median | set-up median | over 1 ms (median) | p50 speed-up |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (scene, per_threads) in scenes.iter().zip(runs) {
        let median = |rs: &[Run], f: &dyn Fn(&Run) -> f64| {
            quantile(&rs.iter().map(f).collect::<Vec<_>>(), 0.5)
        };
        let base = median(&per_threads[0], &|r| r.p50_s);
        for (&t, rs) in threads.iter().zip(per_threads) {
            let p50 = median(rs, &|r| r.p50_s);
            println!(
                "| {} | {t} | {:.0} us | {:.0} us | {:.2} s | {:.0} | x{:.2} |",
                scene.name,
                p50 * 1e6,
                median(rs, &|r| r.p99_s) * 1e6,
                median(rs, &|r| r.setup_s),
                median(rs, &|r| r.over_budget as f64),
                base / p50
            );
        }
    }
}
