//! Tick time with one and two tools (issue 50, "Measure"): a scene pressed 1 mm by one tool on
//! the lv-probe line (along -x at z = -5 mm), or by that tool and a second on the mirrored line
//! (along +x from the other side), through `SoftBody::tick_tools` with the body's slots; a
//! 0.5 s ramp and a 1.5 s hold, the tool counts alternating round by round. Prints tick p50 /
//! p99 per run and the medians.
//!
//! `cargo run --release -p haptic-model --example tools_bench -- --scene lv --rounds 3`

use std::time::Instant;

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::body::{MAX_TOOLS, TickInput, TickOutput};
use haptic_model::press::{PressLine, quantile};
use haptic_model::scene::load_builtin;

/// Command line.
#[derive(Parser)]
#[command(about = "Tick time with one and two tools")]
struct Args {
    /// A built-in scene.
    #[arg(long, default_value = "lv")]
    scene: String,
    /// Rounds (each runs one and two tools).
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// Device depth past first contact, mm.
    #[arg(long, default_value_t = 1.0)]
    depth_mm: f64,
}

/// One run with `tools` tools: tick p50 and p99, s.
fn run(scene: &str, tools: usize, depth_m: f64) -> Result<(f64, f64), String> {
    let scene = load_builtin(scene).map_err(|e| e.to_string())?;
    let mut body = haptic_model::build_body(&scene).map_err(|e| e.to_string())?;
    let slots = body.max_tools();
    if slots < tools {
        return Err(format!("{} takes {slots} tool(s)", scene.name));
    }
    let info = body.info();
    let first = PressLine::lv_probe(info.probe_radius_m);
    // The mirror of the lv-probe line through the ventricle's axis.
    let second = PressLine {
        start_m: first.start_m * DVec3::new(-1.0, 1.0, 1.0),
        direction: first.direction * DVec3::new(-1.0, 1.0, 1.0),
        ..first
    };
    let (ramp, hold) = (500, 1500);
    let mut inputs = [TickInput::default(); MAX_TOOLS];
    let mut outputs = [TickOutput::default(); MAX_TOOLS];
    let mut times = Vec::with_capacity(ramp + hold);
    for k in 0..ramp + hold {
        let depth = depth_m * (k.min(ramp) as f64 / ramp as f64);
        for (slot, line) in [&first, &second].into_iter().enumerate().take(tools) {
            inputs[slot].device_position_m = Some(line.device_at(depth));
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
    let (p50, p99) = (quantile(&times, 0.5), quantile(&times, 0.99));
    println!(
        "| {} | {tools} | {:.0} / {:.0} us | {force} |",
        scene.name,
        p50 * 1e6,
        p99 * 1e6
    );
    Ok((p50, p99))
}

fn main() -> Result<(), String> {
    let args = Args::parse();
    println!("| scene | tools | tick p50 / p99 | held force per tool |");
    println!("|---|---|---|---|");
    let mut results = [Vec::new(), Vec::new()];
    for round in 0..args.rounds {
        let order = if round % 2 == 0 { [1, 2] } else { [2, 1] };
        for tools in order {
            results[tools - 1].push(run(&args.scene, tools, args.depth_mm * 1e-3)?);
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
