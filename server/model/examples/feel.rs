//! How a scene feels through the servo's interface ([`haptic_model::press`]): the staircase
//! press (ramp 0.5 s, hold 1.5 s per depth), the demo's constant-speed press and hold, or the
//! left ventricle's half-turn stroke, on any built-in scene or scene file, printed as a table
//! (force, steadiness, sphere depth, tick p50/p99). Prints only.
//!
//! Run: `cargo run --release -p haptic-model --example feel -- --scene lv staircase --depths
//! 0.25,0.5,1,1.5,2,3,4`, `... -- --scene lv-hybrid demo`, `... -- --scene-file
//! deploy/scenes/lv_h1_condensed.toml stroke --depth 2 --speed 20`.
//!
//! Checks that a change alters no output: `--digest FILE` writes every tick's device force,
//! contact stiffness and proxy position (`{:.17e}`) to FILE and prints one FNV-1a hash of their
//! bit patterns last (an FEM body then prepares a following region blocking, so that it swaps
//! at the same tick in every run: never time `--digest` runs); `--dump-scene` prints the parsed
//! scene (`{:#?}`) and exits. `--threads N` hands the body a tick pool of `N - 1` workers (the
//! coarse companion of a following region then ticks beside it: the digest must not change)
//! and prints the pool's statistics after the run.

#[path = "common/press_protocol.rs"]
mod press_protocol;

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use clap::Parser;
use haptic_model::body::{
    BodyInfo, BodyStats, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput, TickOutput,
};
use haptic_model::pool::TickPool;
use haptic_model::press::{self, HoldParams, HoldReport, PressLine, PressTrace};
use haptic_model::scene::{ModelFamily, Scene, load_builtin, load_scene_file};
use haptic_model::{DVec3, ModelError};
use press_protocol::Protocol;

/// How a scene feels under a scripted press (prints only).
#[derive(Debug, Parser)]
#[command(name = "feel")]
struct Args {
    /// A built-in scene.
    #[arg(long, default_value = "lv", conflicts_with = "scene_file")]
    scene: String,
    /// A scene file instead of a built-in.
    #[arg(long)]
    scene_file: Option<PathBuf>,
    /// Line start, mm (default: the lv-probe line, 15,0,-5, whose depth zero is the analytic
    /// epicardium). With another start the depth zero is the body's rest surface.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    from: Option<DVec3>,
    /// Line direction (default -1,0,0).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    direction: Option<DVec3>,
    /// Print every tick's force (ms, device depth mm, sphere depth mm, |F| mN).
    #[arg(long)]
    trace: bool,
    /// Write every tick's force, contact stiffness and proxy position to this file and print
    /// an FNV-1a hash of their bits last (the no-change check; not for timing).
    #[arg(long)]
    digest: Option<PathBuf>,
    /// Print the parsed scene and exit.
    #[arg(long)]
    dump_scene: bool,
    /// Threads of the body's tick, the servo's included: `N - 1` tick-pool workers (no start
    /// hook: unpinned, normal priority) handed to the body. 1: no pool.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=16))]
    threads: u16,
    #[command(subcommand)]
    protocol: Option<Protocol>,
}

fn main() {
    if let Err(e) = run(Args::parse()) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run(args: Args) -> Result<(), String> {
    let scene: Scene = match &args.scene_file {
        Some(p) => load_scene_file(p),
        None => load_builtin(&args.scene),
    }
    .map_err(|e| e.to_string())?;
    if args.dump_scene {
        println!("{scene:#?}");
        return Ok(());
    }
    let protocol = args
        .protocol
        .ok_or("a protocol is required (staircase, demo or stroke)")?;
    let t0 = Instant::now();
    let mut body = match &args.digest {
        Some(path) => Box::new(Digest::new(build_deterministic(&scene)?, path)?),
        None => haptic_model::build_body(&scene).map_err(|e| e.to_string())?,
    };
    let pool = if args.threads > 1 {
        let workers = usize::from(args.threads) - 1;
        let pool = TickPool::new(workers, Arc::new(|_| {})).map_err(|e| e.to_string())?;
        body.set_tick_pool(Arc::clone(&pool));
        Some(pool)
    } else {
        None
    };
    let info = body.info();
    println!(
        "scene {} ({} family): set-up {:.2} s, tick {} ms, probe radius {} mm, {} thread(s) (the body wants {})",
        scene.name,
        info.family,
        t0.elapsed().as_secs_f64(),
        info.tick_s * 1e3,
        info.probe_radius_m * 1e3,
        args.threads,
        body.wants_threads()
    );
    let r = info.probe_radius_m;
    let line = match (&args.from, &args.direction) {
        (None, None) => PressLine::lv_probe(r),
        (from, dir) => {
            let from = from.unwrap_or(DVec3::new(15.0, 0.0, -5.0)) * 1e-3;
            let dir = dir.unwrap_or(DVec3::NEG_X);
            PressLine::from_rest_surface(body.as_ref(), from, dir, r).map_err(|e| e.to_string())?
        }
    };
    let tick = info.tick_s;
    let trace = run_protocol(protocol, body.as_mut(), &line, r, tick)?;
    let (slowest, _) = trace
        .tick_wall_s
        .iter()
        .enumerate()
        .fold((0, 0.0), |m, (k, &t)| if t > m.1 { (k, t) } else { m });
    println!(
        "ticks: {} in all, p50 {:.1} us, p99 {:.1} us, max {:.1} us (tick {slowest})",
        trace.tick_wall_s.len(),
        trace.tick_quantile_s(0.5) * 1e6,
        trace.tick_quantile_s(0.99) * 1e6,
        trace.tick_quantile_s(1.0) * 1e6
    );
    if let Some(pool) = &pool {
        let s = pool.stats();
        println!(
            "tick pool: {} threads, {} jobs, parts on the caller {} / on workers {}, longest wait {} us",
            pool.threads(),
            s.jobs,
            s.parts_on_caller,
            s.parts_on_workers,
            s.longest_wait_us
        );
    }
    if args.trace {
        print_trace(&trace, &line, tick);
    }
    drop(body); // a digest body prints its hash when dropped: last
    Ok(())
}

/// Runs `protocol` on `body` along `line` (probe radius `r` m, tick `tick` s), printing its
/// holds (and the slide of a stroke); the trace.
fn run_protocol(
    protocol: Protocol,
    body: &mut dyn SoftBody,
    line: &PressLine,
    r: f64,
    tick: f64,
) -> Result<PressTrace, String> {
    let trace = match protocol {
        Protocol::Staircase {
            depths,
            ramp_s,
            hold_s,
        } => {
            let depths: Vec<f64> = depths.iter().map(|d| d * 1e-3).collect();
            let params = HoldParams {
                ramp_s,
                hold_s,
                average_s: (hold_s * 2.0 / 3.0).min(hold_s),
            };
            let (holds, trace) =
                press::staircase(body, line, &depths, &params, tick).map_err(|e| e.to_string())?;
            print_holds(&holds);
            trace
        }
        Protocol::Demo {
            depth,
            speed,
            hold_s,
        } => {
            let (hold, trace) =
                press::constant_speed_press(body, line, depth * 1e-3, speed * 1e-3, hold_s, tick)
                    .map_err(|e| e.to_string())?;
            print_holds(&[hold]);
            trace
        }
        Protocol::Stroke { depth, speed } => {
            let (s, trace) = press::lv_half_turn(body, r, depth * 1e-3, speed * 1e-3, tick)
                .map_err(|e| e.to_string())?;
            print_holds(&[s.hold]);
            println!(
                "slide: {} ticks ({} in contact), |F| {:.3} to {:.3} mN, largest tick-to-tick \
             change {:.3} mN = {:.1} % of the hold force",
                s.slide_ticks,
                s.contact_ticks,
                s.force_min_n * 1e3,
                s.force_max_n * 1e3,
                s.max_tick_change_n * 1e3,
                100.0 * s.max_tick_change_n / s.hold.force_n
            );
            trace
        }
    };
    Ok(trace)
}

/// The scene's body as [`haptic_model::build_body`] builds it, except that an FEM body
/// prepares a following region blocking (deterministic swaps, for `--digest`).
fn build_deterministic(scene: &Scene) -> Result<Box<dyn SoftBody>, String> {
    if scene.family == ModelFamily::Fem && scene.realtime {
        let mut sim = haptic_model::fem::FemBody::new(scene).map_err(|e| e.to_string())?;
        sim.set_blocking_region_preparation(true);
        Ok(Box::new(sim))
    } else {
        haptic_model::build_body(scene).map_err(|e| e.to_string())
    }
}

/// A body that forwards every call and records each tick's output (`--digest`): the values
/// as `{:.17e}` to a file, their bit patterns into one FNV-1a hash printed on drop.
struct Digest {
    inner: Box<dyn SoftBody>,
    out: BufWriter<File>,
    hash: u64,
    ticks: u64,
}

impl Digest {
    fn new(inner: Box<dyn SoftBody>, path: &PathBuf) -> Result<Self, String> {
        let file = File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(Self {
            inner,
            out: BufWriter::new(file),
            hash: 0xcbf2_9ce4_8422_2325,
            ticks: 0,
        })
    }

    fn record(&mut self, o: &TickOutput) {
        let f = o.force_on_device_n.to_array();
        let p = o.proxy_position_m.to_array();
        let values = f.iter().chain(&o.contact_stiffness_n_per_m).chain(&p);
        let mut line = String::new();
        for v in values {
            for b in v.to_bits().to_le_bytes() {
                self.hash = (self.hash ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
            }
            line.push_str(&format!("{v:.17e} "));
        }
        // A failed write shows as a short file next to the hash, which covers every tick.
        let _ = writeln!(self.out, "{}", line.trim_end());
        self.ticks += 1;
    }
}

impl Drop for Digest {
    fn drop(&mut self) {
        let _ = self.out.flush();
        println!("digest: {} ticks, FNV-1a {:016x}", self.ticks, self.hash);
    }
}

impl SoftBody for Digest {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        let o = self.inner.tick(input)?;
        self.record(&o);
        Ok(o)
    }

    fn add_point_load(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
    ) -> Result<(), ModelError> {
        self.inner.add_point_load(point_m, force_n, duration_s)
    }

    fn surface_topology(&self) -> SurfaceTopology<'_> {
        self.inner.surface_topology()
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        self.inner.surface_capacity()
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        self.inner.write_surface_positions(out)
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        self.inner.write_surface_rest_positions(out)
    }

    fn stats(&self) -> BodyStats {
        self.inner.stats()
    }

    fn info(&self) -> BodyInfo {
        self.inner.info()
    }

    fn wants_threads(&self) -> usize {
        self.inner.wants_threads()
    }

    fn set_tick_pool(&mut self, pool: Arc<TickPool>) {
        self.inner.set_tick_pool(pool);
    }
}

/// `X,Y,Z` as a vector.
fn parse_vec3(s: &str) -> Result<DVec3, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|c| c.trim().parse::<f64>().map_err(|e| format!("{c:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(DVec3::new(x, y, z)),
        _ => Err(format!("{s:?}: expected three finite numbers X,Y,Z")),
    }
}

fn print_holds(holds: &[HoldReport]) {
    println!(
        "device depth mm | sphere depth mm | |F| mN (mean) | min..max mN | largest tick change mN (% of mean) | contact ticks"
    );
    for h in holds {
        println!(
            "{:>15.3} | {:>15.4} | {:>13.4} | {:.3}..{:.3} | {:.4} ({:.2} %) | {}/{}",
            h.device_depth_m * 1e3,
            h.sphere_depth_m * 1e3,
            h.force_n * 1e3,
            h.force_min_n * 1e3,
            h.force_max_n * 1e3,
            h.max_tick_change_n * 1e3,
            100.0 * h.steadiness(),
            h.contact_ticks,
            h.hold_ticks
        );
    }
}

fn print_trace(trace: &PressTrace, line: &PressLine, tick_s: f64) {
    println!("ms,device_depth_mm,sphere_depth_mm,force_mn");
    for k in 0..trace.force_n.len() {
        println!(
            "{:.0},{:.4},{:.4},{:.4}",
            (k + 1) as f64 * tick_s * 1e3,
            line.depth_of(trace.device_m[k]) * 1e3,
            line.depth_of(trace.proxy_m[k]) * 1e3,
            trace.force_n[k].length() * 1e3
        );
    }
}
