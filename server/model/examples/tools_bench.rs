//! Tick time with one and two tools (issue 50, "Measure"): a scene pressed 1 mm by one tool on
//! the lv-probe line (along -x at z = -5 mm), or by that tool and a second on the mirrored line
//! (along +x from the other side), through `SoftBody::tick_tools` with the body's slots; a
//! 0.5 s ramp and a 1.5 s hold, the tool counts alternating round by round. Prints tick p50 /
//! p99 per run and the medians.
//!
//! `--scene` is a built-in name or a scene file. A following region (`lv_h1_condensed.toml`)
//! runs as a servo would (regions prepared off the tick, the coarse companion on a second
//! pool thread) after a warm-up that waits for the region of the run's tools (one ball per
//! tool, prepared with the devices 1 mm off the surface); its tiles are off, so the worker is
//! idle while the ticks are timed.
//!
//! `cargo run --release -p haptic-model --example tools_bench -- --scene lv --rounds 3`

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::body::{MAX_TOOLS, SoftBody, TickInput, TickOutput};
use haptic_model::fem::FemBody;
use haptic_model::integrate::condensed::TileMode;
use haptic_model::pool::TickPool;
use haptic_model::press::{PressLine, quantile};
use haptic_model::scene::{Scene, load_builtin, load_scene_file};

/// Command line.
#[derive(Parser)]
#[command(about = "Tick time with one and two tools")]
struct Args {
    /// A built-in scene, or a scene file (a path ending in `.toml`).
    #[arg(long, default_value = "lv")]
    scene: String,
    /// Rounds (each runs one and two tools).
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// Device depth past first contact, mm.
    #[arg(long, default_value_t = 1.0)]
    depth_mm: f64,
    /// The second tool stays 1 mm off the surface (connected, not in contact): what the
    /// second tool's region costs without its contact.
    #[arg(long)]
    second_hovers: bool,
}

/// The scene `name`: a file when it ends in `.toml`, else a built-in; a following region's
/// tiles off.
fn scene_of(name: &str) -> Result<Scene, String> {
    let mut scene = if name.ends_with(".toml") {
        load_scene_file(Path::new(name))
    } else {
        load_builtin(name)
    }
    .map_err(|e| e.to_string())?;
    if let Some(r) = scene.active_region.as_mut().filter(|r| r.follow) {
        r.tiles = TileMode::Off;
    }
    Ok(scene)
}

/// The body of `scene` with the pool it asks for; a following region warmed up for `lines`:
/// ticks waiting for each region with the devices 1 mm before contact until it has a ball per
/// line, then preparation off the tick again.
fn body_of(scene: &Scene, lines: &[PressLine]) -> Result<Box<dyn SoftBody>, String> {
    let follows = scene.active_region.is_some_and(|r| r.follow);
    let mut body: Box<dyn SoftBody> = if follows {
        let mut fem = FemBody::new(scene).map_err(|e| e.to_string())?;
        fem.set_blocking_region_preparation(true);
        let inputs: Vec<TickInput> = lines
            .iter()
            .map(|l| TickInput {
                device_position_m: Some(l.device_at(-1e-3)),
                ..TickInput::default()
            })
            .collect();
        let mut out = vec![TickOutput::default(); lines.len()];
        for _ in 0..200 {
            fem.tick_tools(&inputs, &mut out)
                .map_err(|e| e.to_string())?;
        }
        let balls = fem.follow_stats().map_or(0, |f| f.balls);
        if balls != lines.len() {
            return Err(format!(
                "the region has {balls} balls for {} tools",
                lines.len()
            ));
        }
        fem.set_blocking_region_preparation(false);
        report_region(&fem);
        Box::new(fem)
    } else {
        haptic_model::build_body(scene).map_err(|e| e.to_string())?
    };
    if body.wants_threads() > 1 {
        let pool =
            TickPool::new(body.wants_threads() - 1, Arc::new(|_| {})).map_err(|e| e.to_string())?;
        body.set_tick_pool(pool);
    }
    Ok(body)
}

/// Prints the size of a following region after its warm-up and its largest preparation time
/// (on stderr: the table stays on stdout).
fn report_region(fem: &FemBody) {
    let (Some(c), Some(f)) = (fem.condensed(), fem.follow_stats()) else {
        return;
    };
    let z = c.sizes();
    eprintln!(
        "region of {} ball(s): {} active tets, {} interface nodes, {} equations, {:.1} MB, prepared in {:.2} s at most",
        f.balls,
        z.active_tets,
        z.interface_nodes,
        z.equations,
        c.memory_bytes() as f64 / 1e6,
        f.max_prepare_s
    );
}

/// One run with `tools` tools: tick p50 and p99, s.
fn run(scene: &Scene, tools: usize, depth_m: f64, hover: bool) -> Result<(f64, f64), String> {
    let first = PressLine::lv_probe(scene.probe.radius_m);
    // The mirror of the lv-probe line through the ventricle's axis.
    let second = PressLine {
        start_m: first.start_m * DVec3::new(-1.0, 1.0, 1.0),
        direction: first.direction * DVec3::new(-1.0, 1.0, 1.0),
        ..first
    };
    let lines = [first, second];
    let mut body = body_of(scene, &lines[..tools])?;
    let slots = body.max_tools();
    if slots < tools {
        return Err(format!("{} takes {slots} tool(s)", scene.name));
    }
    let (ramp, hold) = (500, 1500);
    let mut inputs = [TickInput::default(); MAX_TOOLS];
    let mut outputs = [TickOutput::default(); MAX_TOOLS];
    let mut times = Vec::with_capacity(ramp + hold);
    for k in 0..ramp + hold {
        let depth = depth_m * (k.min(ramp) as f64 / ramp as f64);
        for (slot, line) in lines.iter().enumerate().take(tools) {
            let d = if hover && slot == 1 { -1e-3 } else { depth };
            inputs[slot].device_position_m = Some(line.device_at(d));
        }
        let t0 = Instant::now();
        body.tick_tools(&inputs[..slots], &mut outputs[..slots])
            .map_err(|e| e.to_string())?;
        times.push(t0.elapsed().as_secs_f64());
    }
    let force = outputs[..tools]
        .iter()
        .map(|o| format!("{:.2} mN", o.force_on_device_n.length() * 1e3))
        .collect::<Vec<_>>()
        .join(" / ");
    let stats = body.stats();
    let (p50, p99) = (quantile(&times, 0.5), quantile(&times, 0.99));
    println!(
        "| {} | {tools} | {:.0} / {:.0} us | {force} | {} swaps, {} companion ticks |",
        scene.name,
        p50 * 1e6,
        p99 * 1e6,
        stats.region_swaps,
        stats.companion_ticks,
    );
    Ok((p50, p99))
}

fn main() -> Result<(), String> {
    let args = Args::parse();
    let scene = scene_of(&args.scene)?;
    println!("| scene | tools | tick p50 / p99 | held force per tool | region |");
    println!("|---|---|---|---|---|");
    let mut results = [Vec::new(), Vec::new()];
    for round in 0..args.rounds {
        let order = if round % 2 == 0 { [1, 2] } else { [2, 1] };
        for tools in order {
            let depth = args.depth_mm * 1e-3;
            results[tools - 1].push(run(&scene, tools, depth, args.second_hovers)?);
        }
    }
    println!();
    for (k, rs) in results.iter().enumerate() {
        let p50: Vec<f64> = rs.iter().map(|r| r.0).collect();
        let p99: Vec<f64> = rs.iter().map(|r| r.1).collect();
        println!(
            "{} tool(s): p50 median {:.0} us, p99 median {:.0} us",
            k + 1,
            quantile(&p50, 0.5) * 1e6,
            quantile(&p99, 0.5) * 1e6
        );
    }
    Ok(())
}
