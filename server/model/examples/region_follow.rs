//! Strokes the probe across the epicardium of a following condensed scene (issue 20): from the
//! equator point on +x (z = -5 mm) around the ventricle to -x, pressed `--depth-mm` deep at
//! `--speed-mm-s`, and reports the region swaps, preparation times, tick times and the force's
//! continuity at the swaps.
//!
//! `cargo run --release -p haptic-model --example region_follow -- --speed-mm-s 2 --paced`
//!
//! `--paced` runs the ticks on 1 ms deadlines, as the servo does, so the worker prepares
//! regions in real time; without it the ticks run back to back (faster than real time: a
//! harder test of the worker); `--blocking` makes every tick that requests a region wait for
//! it (deterministic, as in the tests).
//!
//! A scene with `active_region.tiles = "background"` builds its region cache while the
//! probe strokes; `--wait-tiles` waits for the whole cache before the press (the cache's
//! steady state), `--no-tiles` turns the cache off (every region prepared on demand).
//!
//! `cargo run --release -p haptic-model --example region_follow -- --speed-mm-s 20 --paced --hold-end-s 3 --wait-tiles`

use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::fem::FemBody;
use haptic_model::integrate::condensed::TileMode;
use haptic_model::pool::TickPool;
use haptic_model::scene::load_scene_file;

#[derive(Parser)]
struct Args {
    /// Scene file with `[active_region] follow = true`.
    #[arg(long, default_value = "deploy/scenes/lv_h1_condensed.toml")]
    scene: String,
    /// Sliding speed along the surface, mm/s.
    #[arg(long, default_value_t = 2.0)]
    speed_mm_s: f64,
    /// Indentation of the device point below the rest surface, mm.
    #[arg(long, default_value_t = 1.0)]
    depth_mm: f64,
    /// Arc to stroke, degrees around the long axis (180: to the other side).
    #[arg(long, default_value_t = 180.0)]
    arc_deg: f64,
    /// Tick on 1 ms deadlines (real time).
    #[arg(long)]
    paced: bool,
    /// Wait for every requested region (deterministic).
    #[arg(long)]
    blocking: bool,
    /// Hold at the end of the stroke this long, s (for a region to arrive and settle).
    #[arg(long, default_value_t = 0.3)]
    hold_end_s: f64,
    /// Run without the scene's coarse companion (`active_region.fallback_target_tets`).
    #[arg(long)]
    no_fallback: bool,
    /// Wait until the region cache (`active_region.tiles = "background"`) is complete before
    /// the press.
    #[arg(long)]
    wait_tiles: bool,
    /// Wait this long after set-up before the press, s (the worker reads the region cache's
    /// tiles meanwhile, nearest the press first, without waiting for the whole cache).
    #[arg(long, default_value_t = 0.0)]
    wait_s: f64,
    /// Centre the worker's tile work on the stroke's point this many degrees round (for
    /// example half the arc) from set-up on, instead of the press: with a memory limit the
    /// tiles kept then cover both ends of the stroke.
    #[arg(long)]
    focus_arc_deg: Option<f64>,
    /// After the waits, pause the worker's background tile work (builds and reads back;
    /// requests are still answered), so that a stroke's requests never wait for a build.
    #[arg(long)]
    pause_tiles: bool,
    /// Turn the scene's region cache off (`active_region.tiles = "off"`).
    #[arg(long)]
    no_tiles: bool,
    /// Write one row per tick (`t_s,force_mN,companion_weight,swaps`) to this CSV file.
    #[arg(long)]
    csv: Option<std::path::PathBuf>,
    /// Threads of the tick: the caller plus `threads - 1` tick-pool workers, as the daemon's
    /// `[servo] threads` gives a session (the region's worker thread comes on top). As the
    /// daemon's automatic count does, the workers the machine's cores cannot hold beside the
    /// body's background threads (a region cache filling) are lent out (parked) meanwhile.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    threads: u32,
    /// Give the ticking thread and the tick-pool workers `SCHED_FIFO` at this priority after
    /// set-up, as the daemon gives its servo thread and workers (`[servo] realtime`); the
    /// region's worker thread, started during set-up, keeps normal scheduling as in the
    /// daemon (where the body is built off the servo thread). Needs the privilege to do so.
    #[arg(long, value_parser = clap::value_parser!(i32).range(1..=99))]
    fifo: Option<i32>,
    /// Read the region cache's tiles from this directory and write the ones built to it
    /// (the daemon's `region_cache_dir`): a second run reads what the first wrote.
    #[arg(long)]
    region_cache: Option<std::path::PathBuf>,
    /// Tiles kept in memory at most, MiB (the daemon's `region_cache_memory_bytes`; default
    /// 2 048): beyond it those farthest from the probe wait on disk.
    #[arg(long)]
    tile_memory_mb: Option<u64>,
}

/// Epicardium radius at z = -5 mm of the LV (10 x 10 x 20 mm ellipsoid), m.
const EPI_R_M: f64 = 0.009_682;
const Z_M: f64 = -0.005;

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (mut sim, probe_r) = set_up(&args)?;
    let fifo = args.fifo;
    if let Some(priority) = fifo {
        set_fifo(priority)?;
    }
    let pool = (args.threads > 1)
        .then(|| {
            TickPool::new(
                args.threads as usize - 1,
                Arc::new(move |_| {
                    if let Some(priority) = fifo {
                        // A worker that cannot follow runs with normal scheduling; the
                        // servo thread's own call above already proved the privilege.
                        let _ = set_fifo(priority);
                    }
                }),
            )
        })
        .transpose()?;
    if let Some(pool) = &pool {
        sim.set_tick_pool(Arc::clone(pool));
    }
    let path = Path::new(&args, probe_r);
    let trace = run(&args, &mut sim, pool.as_deref(), &path)?;
    report(&args, &sim, &path, &trace);
    if let Some(csv) = &args.csv {
        write_csv(csv, &trace)?;
    }
    Ok(())
}

/// Loads the scene with its region following (and without its companion on request) and
/// builds the body, reporting the stages; `(body, probe radius m)`.
fn set_up(args: &Args) -> anyhow::Result<(FemBody, f64)> {
    let t = Instant::now();
    let mut scene = load_scene_file(std::path::Path::new(&args.scene))?;
    eprintln!(
        "scene loaded in {:.2} s: {} nodes, {} tets; peak memory {:.0} MB",
        t.elapsed().as_secs_f64(),
        scene.mesh.nodes.len(),
        scene.mesh.tets.len(),
        peak_memory_mb()
    );
    let region = scene
        .active_region
        .as_mut()
        .ok_or_else(|| anyhow::anyhow!("{} has no [active_region]", args.scene))?;
    region.follow = true;
    if args.no_tiles {
        region.tiles = TileMode::Off;
    }
    if args.no_fallback {
        scene.fallback = None;
    }
    let t = Instant::now();
    let options = haptic_model::BodyOptions {
        region_cache: args.region_cache.clone().map(|dir| {
            haptic_model::integrate::follow::RegionCacheDir {
                dir,
                max_bytes: haptic_model::integrate::follow::DEFAULT_REGION_CACHE_MAX_BYTES,
                memory_bytes: args.tile_memory_mb.map_or(
                    haptic_model::integrate::follow::DEFAULT_REGION_CACHE_MEMORY_BYTES,
                    |mb| mb << 20,
                ),
            }
        }),
        region_cache_report: Some(haptic_model::integrate::follow::RegionCacheReport(
            std::sync::Arc::new(|e: &str| eprintln!("region cache: {e}")),
        )),
        region_cache_fill_only: false,
    };
    let mut sim = FemBody::new_with_options(&scene, &options, &mut |stage, fraction| {
        eprintln!(
            "  {:6.2} s {:3.0} % {stage} (peak memory {:.0} MB)",
            t.elapsed().as_secs_f64(),
            100.0 * fraction,
            peak_memory_mb()
        );
    })?;
    eprintln!(
        "set-up {:.2} s; first region {:?}, {:.1} MB",
        t.elapsed().as_secs_f64(),
        sim.condensed().map(|c| c.sizes()),
        sim.follow_stats()
            .map_or(0.0, |s| s.region_bytes as f64 / 1e6)
    );
    if let Some(deg) = args.focus_arc_deg {
        let a = deg.to_radians();
        sim.focus_region_tiles(DVec3::new(EPI_R_M * a.cos(), EPI_R_M * a.sin(), Z_M));
    }
    if args.wait_tiles {
        wait_for_tiles(&sim);
    }
    if args.wait_s > 0.0 {
        std::thread::sleep(Duration::from_secs_f64(args.wait_s));
        let s = sim.follow_stats().unwrap_or_default();
        eprintln!(
            "after {} s more: {} of {} tiles built or read, {:.0} MB in memory",
            args.wait_s,
            s.tiles_built,
            s.tiles,
            s.tile_cache_bytes as f64 / 1e6
        );
    }
    if args.pause_tiles {
        sim.set_region_preparation_paused(true);
    }
    sim.set_blocking_region_preparation(args.blocking);
    Ok((sim, scene.probe.radius_m))
}

/// Waits until every tile of the region cache is built (or failed), reporting progress.
fn wait_for_tiles(sim: &FemBody) {
    let t = Instant::now();
    let mut last = u64::MAX;
    let (mut seen, mut changed) = (u64::MAX, Instant::now());
    loop {
        let s = sim.follow_stats().unwrap_or_default();
        if s.tiles_built + s.failed >= s.tiles {
            eprintln!(
                "tile cache complete after {:.1} s more: {} tiles built ({} read from disk, {} written, {} refused; {} failed), {:.0} MB, {:.1} s of builds; peak memory {:.0} MB",
                t.elapsed().as_secs_f64(),
                s.tiles_built,
                s.tiles_loaded,
                s.tiles_stored,
                s.tiles_refused,
                s.failed,
                s.tile_cache_bytes as f64 / 1e6,
                s.tile_build_s,
                peak_memory_mb()
            );
            return;
        }
        // Background builds stop at the memory limit when the directory is full or there is
        // none (tiles without a file are not built ahead): no tile for a minute (a build
        // takes 8-24 s on the 100 000-tet LV) means nothing more will come.
        if s.tiles_built != seen {
            (seen, changed) = (s.tiles_built, Instant::now());
        }
        if changed.elapsed() > Duration::from_secs(60) {
            eprintln!(
                "tile cache stopped at {} of {} tiles after {:.1} s, none for a minute ({:.0} MB \
                 in memory: the memory limit, with no room in the directory)",
                s.tiles_built,
                s.tiles,
                t.elapsed().as_secs_f64(),
                s.tile_cache_bytes as f64 / 1e6
            );
            return;
        }
        if s.tiles_built != last && s.tiles_built.is_multiple_of(10) {
            eprintln!(
                "  {:6.1} s: {}/{} tiles",
                t.elapsed().as_secs_f64(),
                s.tiles_built,
                s.tiles
            );
            last = s.tiles_built;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The device path: press, settle, stroke around the long axis, hold.
struct Path {
    probe_r: f64,
    depth_mm: f64,
    ring: f64,
    omega: f64,
    press_s: f64,
    settle_s: f64,
    stroke_s: f64,
    /// Ticks of the whole run.
    total: usize,
}

impl Path {
    fn new(args: &Args, probe_r: f64) -> Self {
        let ring = EPI_R_M + probe_r - args.depth_mm * 1e-3;
        let omega = args.speed_mm_s * 1e-3 / EPI_R_M;
        let arc = args.arc_deg.to_radians();
        let (press_s, settle_s) = (0.3, 0.3);
        let stroke_s = arc / omega;
        let total = ((press_s + settle_s + stroke_s + args.hold_end_s) * 1e3).ceil() as usize;
        Self {
            probe_r,
            depth_mm: args.depth_mm,
            ring,
            omega,
            press_s,
            settle_s,
            stroke_s,
            total,
        }
    }

    /// Device position and velocity at `t_s`.
    fn at(&self, t_s: f64) -> (DVec3, DVec3) {
        let (press_s, settle_s, ring) = (self.press_s, self.settle_s, self.ring);
        let (theta, radius, speed) = if t_s < press_s {
            let s = t_s / press_s;
            (
                0.0,
                EPI_R_M + self.probe_r + 0.5e-3 - s * (0.5e-3 + self.depth_mm * 1e-3),
                0.0,
            )
        } else if t_s < press_s + settle_s {
            (0.0, ring, 0.0)
        } else {
            let ts = (t_s - press_s - settle_s).min(self.stroke_s);
            let moving = t_s - press_s - settle_s < self.stroke_s;
            (
                self.omega * ts,
                ring,
                if moving { self.omega * ring } else { 0.0 },
            )
        };
        let p = DVec3::new(radius * theta.cos(), radius * theta.sin(), Z_M);
        let vel = DVec3::new(-theta.sin(), theta.cos(), 0.0) * speed;
        (p, vel)
    }
}

/// Per-tick records of the run.
struct Trace {
    weights: Vec<f64>,
    ticks_us: Vec<f64>,
    forces: Vec<DVec3>,
    swap_ticks: Vec<usize>,
    /// The hand-over's time at each swap tick, us (`FollowStats::last_hand_over_s`).
    hand_over_us: Vec<f64>,
    lost_contact: usize,
    /// Ticks run with tick-pool workers lent out ([`lend_workers`]).
    lent_ticks: usize,
    /// Ticks of the stroke in contact, and those of them the companion answered (weight > 0).
    contact_ticks: usize,
    companion_ticks: usize,
}

/// Lends out the workers of `pool` that `cores` cannot hold beside the body's `background`
/// threads, as the daemon's automatic thread count does (docs/deploy.md, "Cores per
/// session"); whether some are lent out.
fn lend_workers(pool: &TickPool, cores: usize, background: usize) -> bool {
    let working = cores.saturating_sub(background).max(1);
    pool.set_active_workers(working - 1) + 1 < pool.threads()
}

/// Runs the path's ticks (paced on request) on `pool`'s threads.
fn run(
    args: &Args,
    sim: &mut FemBody,
    pool: Option<&TickPool>,
    path: &Path,
) -> anyhow::Result<Trace> {
    let total = path.total;
    let mut tr = Trace {
        weights: Vec::with_capacity(total),
        ticks_us: Vec::with_capacity(total),
        forces: Vec::with_capacity(total),
        swap_ticks: Vec::new(),
        hand_over_us: Vec::new(),
        lost_contact: 0,
        lent_ticks: 0,
        contact_ticks: 0,
        companion_ticks: 0,
    };
    let cores = std::thread::available_parallelism().map_or(1, usize::from);
    let mut lent = false;
    let mut last_swaps = 0;
    let start = Instant::now();
    for k in 0..total {
        let t_s = k as f64 * 1e-3;
        let (p, vel) = path.at(t_s);
        if args.paced {
            // Sleep, then spin the last 150 us, as the daemon's servo does (a thread that
            // spun through every idle microsecond under SCHED_FIFO would run into the
            // kernel's real-time throttling: 50 ms stalls).
            let due = start + Duration::from_micros(1000 * k as u64);
            let left = due.saturating_duration_since(Instant::now());
            if left > Duration::from_micros(300) {
                std::thread::sleep(left - Duration::from_micros(150));
            }
            while Instant::now() < due {
                std::hint::spin_loop();
            }
        }
        // Asked every 100 ticks, as the daemon's servo does at each statistics window.
        if let Some(pool) = pool.filter(|_| k % 100 == 0) {
            lent = lend_workers(pool, cores, sim.background_threads());
        }
        tr.lent_ticks += usize::from(lent);
        let t0 = Instant::now();
        let out = sim.tick(&TickInput {
            device_position_m: Some(p),
            device_velocity_m_per_s: vel,
        })?;
        tr.ticks_us.push(t0.elapsed().as_secs_f64() * 1e6);
        tr.forces.push(out.force_on_device_n);
        let weight = sim.fallback_stats().map_or(0.0, |f| f.weight);
        tr.weights.push(weight);
        if t_s >= path.press_s + path.settle_s {
            tr.lost_contact += usize::from(!out.in_contact);
            tr.contact_ticks += usize::from(out.in_contact);
            tr.companion_ticks += usize::from(out.in_contact && weight > 0.0);
        }
        let stats = sim.follow_stats().unwrap_or_default();
        if stats.swaps != last_swaps {
            tr.swap_ticks.push(k);
            tr.hand_over_us.push(stats.last_hand_over_s * 1e6);
            last_swaps = stats.swaps;
        }
    }
    Ok(tr)
}

/// Prints the run's summary.
fn report(args: &Args, sim: &FemBody, path: &Path, tr: &Trace) {
    let (press_s, settle_s, total) = (path.press_s, path.settle_s, path.total);
    let (ticks_us, forces, swap_ticks) = (&tr.ticks_us, &tr.forces, &tr.swap_ticks);
    let lost_contact = tr.lost_contact;
    let stats = sim.follow_stats().unwrap_or_default();
    let pct = |q: f64| quantile(ticks_us, q);
    let jump = |k: usize| {
        let (a, b) = (forces[k - 1], forces[k]);
        (b - a).length() / a.length().max(1e-9)
    };
    let stroke = ((press_s + settle_s) * 1e3) as usize..total;
    let max_jump_other = stroke
        .clone()
        .filter(|k| !swap_ticks.contains(k))
        .map(jump)
        .fold(0.0, f64::max);
    let swap_jumps: Vec<f64> = swap_ticks.iter().map(|&k| jump(k)).collect();
    let max_swap_jump = swap_jumps.iter().copied().fold(0.0, f64::max);
    let swap_us: Vec<f64> = swap_ticks.iter().map(|&k| ticks_us[k]).collect();
    let fmag: Vec<f64> = forces[stroke.clone()].iter().map(|f| f.length()).collect();
    println!(
        "speed {} mm/s, depth {} mm, {} ticks ({}): swaps {}, rejected {}, prepared {}, failed {}",
        args.speed_mm_s,
        args.depth_mm,
        total,
        if args.blocking {
            "blocking"
        } else if args.paced {
            "paced 1 ms"
        } else {
            "back to back"
        },
        stats.swaps,
        stats.rejected,
        stats.prepared,
        stats.failed
    );
    println!(
        "preparation last {:.3} s, max {:.3} s; region {:.1} MB; final centre {:.2?} mm",
        stats.last_prepare_s,
        stats.max_prepare_s,
        stats.region_bytes as f64 / 1e6,
        (stats.centre_m * 1e3).to_array()
    );
    let stroke_us: Vec<f64> = ticks_us[stroke.clone()].to_vec();
    println!(
        "tick p50 {:.0} us, p99 {:.0} us, max {:.0} us at tick {} ({} thread(s)); swap ticks max {:.0} us; stroke and hold: p50 {:.0} us, {} of {} ticks over 1 ms",
        pct(0.5),
        pct(0.99),
        pct(1.0),
        ticks_us
            .iter()
            .enumerate()
            .fold((0, 0.0), |a, (k, &t)| if t > a.1 { (k, t) } else { a })
            .0,
        args.threads,
        swap_us.iter().copied().fold(0.0, f64::max),
        quantile(&stroke_us, 0.5),
        stroke_us.iter().filter(|&&t| t > 1e3).count(),
        stroke_us.len()
    );
    if tr.lent_ticks > 0 {
        println!(
            "tick-pool workers lent to the region cache's fill for {} of {} ticks ({} cores)",
            tr.lent_ticks,
            total,
            std::thread::available_parallelism().map_or(1, usize::from)
        );
    }
    print_swap_ticks(tr);
    println!(
        "stroke: contact lost on {lost_contact} ticks; |F| {:.2}..{:.2} mN; largest tick-to-tick change {:.2} % at swaps, {:.2} % elsewhere",
        fmag.iter().copied().fold(f64::INFINITY, f64::min) * 1e3,
        fmag.iter().copied().fold(0.0, f64::max) * 1e3,
        max_swap_jump * 100.0,
        max_jump_other * 100.0
    );
    println!(
        "stroke: companion share {:.1} % ({} of {} contact ticks); largest tick-to-tick change {:.2} %",
        100.0 * tr.companion_ticks as f64 / tr.contact_ticks.max(1) as f64,
        tr.companion_ticks,
        tr.contact_ticks,
        100.0 * max_swap_jump.max(max_jump_other)
    );
    report_tiles(&stats);
    if let Some(fb) = sim.fallback_stats() {
        println!(
            "coarse companion ({} tets): answered {} ticks, final weight {:.2}; force at the end {:.2} mN",
            fb.elements,
            fb.ticks_answered,
            fb.weight,
            forces.last().map_or(0.0, |f| f.length() * 1e3)
        );
    }
}

/// Each swap tick's time, its hand-over's and the next tick's, us (nothing without swaps).
fn print_swap_ticks(tr: &Trace) {
    let at_swaps: Vec<String> = tr
        .swap_ticks
        .iter()
        .zip(&tr.hand_over_us)
        .map(|(&k, h)| {
            let next = tr.ticks_us.get(k + 1).copied().unwrap_or(f64::NAN);
            format!("{:.0} ({h:.0} hand-over; next {next:.0})", tr.ticks_us[k])
        })
        .collect();
    if !at_swaps.is_empty() {
        println!("swap ticks, us: {}", at_swaps.join(", "));
    }
}

/// One row per tick: `t_s,force_mN,companion_weight,swaps`.
fn write_csv(path: &std::path::Path, tr: &Trace) -> anyhow::Result<()> {
    let (forces, weights, swap_ticks) = (&tr.forces, &tr.weights, &tr.swap_ticks);
    let mut text = String::from("t_s,force_mN,companion_weight,swaps\n");
    let mut swaps = 0;
    for (k, (f, w)) in forces.iter().zip(weights).enumerate() {
        swaps += usize::from(swap_ticks.contains(&k));
        text += &format!(
            "{:.3},{:.4},{:.3},{swaps}\n",
            k as f64 * 1e-3,
            f.length() * 1e3,
            w
        );
    }
    std::fs::write(path, text)?;
    Ok(())
}

/// Gives the calling thread `SCHED_FIFO` at `priority` (1-99).
fn set_fifo(priority: i32) -> anyhow::Result<()> {
    use thread_priority::{
        RealtimeThreadSchedulePolicy, ThreadPriority, ThreadPriorityValue, ThreadSchedulePolicy,
        set_thread_priority_and_policy, thread_native_id,
    };
    let value = u8::try_from(priority)
        .ok()
        .and_then(|p| ThreadPriorityValue::try_from(p).ok())
        .ok_or_else(|| anyhow::anyhow!("SCHED_FIFO priority {priority} out of range"))?;
    set_thread_priority_and_policy(
        thread_native_id(),
        ThreadPriority::Crossplatform(value),
        ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
    )
    .map_err(|e| anyhow::anyhow!("SCHED_FIFO priority {priority} refused: {e:?}"))
}

/// The `q` quantile of `values` (nearest rank below; 0 for none).
fn quantile(values: &[f64], q: f64) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted
        .get(((sorted.len().max(1) - 1) as f64 * q) as usize)
        .copied()
        .unwrap_or(0.0)
}

/// Peak resident memory of this process (VmHWM), MB; 0 where /proc is not readable.
fn peak_memory_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1e3)
}

/// The region cache's line of [`report`] (scenes with tiles).
fn report_tiles(stats: &haptic_model::integrate::follow::FollowStats) {
    if stats.tiles > 0 {
        println!(
            "tiles: {} centres, {} built ({:.0} MB in memory, {:.1} s of builds), {} hits, {} misses ({} answered during a build, {} of them read from disk); {} dropped from memory, {} read back; {} swaps beyond a ring; peak memory {:.0} MB",
            stats.tiles,
            stats.tiles_built,
            stats.tile_cache_bytes as f64 / 1e6,
            stats.tile_build_s,
            stats.tile_hits,
            stats.tile_misses,
            stats.answered_while_building,
            stats.read_while_building,
            stats.tiles_dropped,
            stats.tiles_reloaded,
            stats.unmapped_swaps,
            peak_memory_mb()
        );
    }
}
