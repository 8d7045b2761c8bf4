//! Hybrid model measurements (issue 13): preprocessing time and memory of a hybrid scene, and
//! the tick time with a given number of active particles (probe pressed into the outer
//! surface, regions activated until the count is reached, tick timed while holding).
//!
//! `cargo run --release -p haptic-model --example hybrid_bench -- --scene lv-hybrid --active 200,600,2000`
//!
//! Prints one CSV row per active count: scene, variant, particles, active, substeps, ticks,
//! median_us, p99_us. The machine is shared: quote medians.

use std::sync::Arc;
use std::time::Instant;

#[path = "common/hybrid_overrides.rs"]
mod hybrid_overrides;

use clap::Parser;
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::hybrid::{HybridBody, HybridModel};
use haptic_model::meshfree::MeshfreeVariant;
use haptic_model::pool::{PoolStats, TickPool};
use haptic_model::scene::{Scene, load_builtin};
use hybrid_overrides::HybridOverrides;

#[derive(Parser)]
struct Args {
    /// Built-in hybrid scene.
    #[arg(long, default_value = "lv-hybrid")]
    scene: String,
    /// Active particle counts to time, comma separated.
    #[arg(long, default_value = "200,600,2000", value_delimiter = ',')]
    active: Vec<usize>,
    #[command(flatten)]
    hybrid: HybridOverrides,
    /// Ticks timed per count.
    #[arg(long, default_value_t = 400)]
    ticks: usize,
    /// Sub-steps per tick override (a study of the explicit step: the critical step bound is
    /// ignored; the run stops with an error if it diverges).
    #[arg(long)]
    substeps: Option<u32>,
    /// Also estimate the true critical step of each active system (power iteration on
    /// `M^-1 K`, `HybridBody::max_eigenvalue_estimate`) and print it beside the bound.
    #[arg(long)]
    estimate_critical_step: bool,
    /// Run the term block's general force loop instead of the stencil loop.
    #[arg(long)]
    general_loop: bool,
    /// Threads of the tick, the caller's included: `N - 1` tick-pool workers (unpinned, the
    /// caller's scheduling class: run under `chrt` to give both the real-time priority) handed
    /// to each body, as `feel --threads` does. 1: no pool (the one-core path).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=16))]
    threads: u16,
    /// Pace the timed ticks at 1 kHz as the servo does (sleep until each tick's deadline), so
    /// the pool's workers park between ticks; without it the ticks run back to back.
    #[arg(long)]
    paced: bool,
}

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

/// Prints the power-iteration estimate of the critical step of `body`'s current active system
/// beside the bound the body steps with (`state`: "at rest" or "pressed").
fn print_estimate(body: &mut HybridBody, state: &str) -> anyhow::Result<()> {
    let active = body.active_particles().len();
    let e = body.max_eigenvalue_estimate(5000, 1e-5)?;
    // The probe penalty adds at most k / m per particle in contact.
    let k_over_m =
        body.model().params.particle_contact_stiffness_n_per_m() / body.particle_mass_kg();
    let with_probe = 2.0 / (e.lambda_per_s2 + k_over_m).sqrt();
    eprintln!(
        "  {active} active, {state}: critical step bound {:.3e} s; power-iteration estimate {:.3e} s ({} iterations, change {:.1e}), {:.3e} s with the probe penalty: {:.2} times the bound",
        body.critical_step_bound_s(),
        e.critical_step_s,
        e.iterations,
        e.relative_change,
        with_probe,
        with_probe / body.critical_step_bound_s()
    );
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut scene = load_builtin(&args.scene)?;
    args.hybrid.apply(&mut scene)?;
    let variant = scene
        .hybrid
        .as_ref()
        .expect("a hybrid scene")
        .params
        .meshfree
        .variant;
    let (model, prep_s) = prepare(&args.scene, &scene)?;
    let clamped = model.clamped_core_nodes();
    let pool = if args.threads > 1 {
        let workers = usize::from(args.threads) - 1;
        Some(TickPool::new(workers, Arc::new(|_| {}))?)
    } else {
        None
    };
    println!(
        "scene,variant,particles,active,threads,substeps,core_substeps,ticks,median_us,p99_us,prep_s"
    );
    for &target in &args.active {
        let run = (variant, prep_s, pool.as_ref());
        press_target(&args, &scene, &model, &clamped, target, run)?;
    }
    Ok(())
}

/// Preprocesses the hybrid model of `scene` (named `name`), reporting its stages, sizes and
/// memory: `(model, preprocessing wall time s)`.
fn prepare(name: &str, scene: &Scene) -> anyhow::Result<(HybridModel, f64)> {
    let rss0 = rss_kib();
    let t0 = Instant::now();
    let model = haptic_model::prepare_hybrid(scene, &mut |s, f| {
        eprintln!(
            "  preprocessing {:5.1} % {s} ({:.2} s)",
            100.0 * f,
            t0.elapsed().as_secs_f64()
        )
    })?;
    let prep_s = t0.elapsed().as_secs_f64();
    let rss1 = rss_kib();
    eprintln!(
        "{}: {} layer particles + {} anchors, {} core tets, {} outer vertices; preprocessing {:.3} s; model {:.1} MiB (RSS +{:.1} MiB); particle dt {:.3e} s (unit mass scale)",
        name,
        model.layer_count,
        model.cloud.len() - model.layer_count,
        model.core_mesh.tets.len(),
        model.outer_rest_m.len(),
        prep_s,
        model.memory_bytes() as f64 / (1 << 20) as f64,
        (rss1 - rss0) as f64 / 1024.0,
        model.particle_dt_s
    );
    Ok((model, prep_s))
}

/// Activates `target` particles around the free wall's outer vertex, presses 1 mm and prints
/// the tick times as a CSV line (and the work counts on stderr).
fn press_target(
    args: &Args,
    scene: &Scene,
    model: &HybridModel,
    clamped: &[u32],
    target: usize,
    (variant, prep_s, pool): (MeshfreeVariant, f64, Option<&Arc<TickPool>>),
) -> anyhow::Result<()> {
    let mut p = model.params;
    p.max_active_particles = target;
    let mut m2 = model.clone();
    m2.params = p;
    let mut body = HybridBody::new(
        m2,
        clamped,
        scene.probe,
        scene.integrator.tick_s,
        &scene.name,
    )?;
    if let Some(pool) = pool {
        body.set_tick_pool(Arc::clone(pool));
    }
    // Touch point: the outer vertex at the largest x (the free wall), pressed 1 mm in.
    let m = body.model();
    let v = (0..m.outer_rest_m.len())
        .max_by(|&a, &b| m.outer_rest_m[a].x.total_cmp(&m.outer_rest_m[b].x))
        .expect("vertices");
    let surf = m.outer_rest_m[v];
    let normal = (surf - m.centre_m).normalize();
    let radius = scene.probe.radius_m;
    body.hold_regions(true);
    let mut r = 0.5e-3;
    while body.active_particles().len() < target && r < 0.05 {
        body.activate_near(surf, r);
        r += 0.1e-3;
    }
    let active = body.active_particles().len();
    if args.estimate_critical_step {
        print_estimate(&mut body, "at rest")?;
    }
    body.set_stencil_loop(!args.general_loop);
    if let Some(n) = args.substeps {
        body.override_substeps(n)?;
    }
    let device = surf + normal * (radius - 1e-3);
    let input = TickInput {
        device_position_m: Some(device),
        device_velocity_m_per_s: Default::default(),
    };
    // The first tick refills the terms of the new active set (and refactors an implicit
    // core): the cost of an activation change.
    let t = Instant::now();
    body.tick(&input)?;
    let first_us = t.elapsed().as_secs_f64() * 1e6;
    for _ in 0..49 {
        body.tick(&input)?;
    }
    if args.estimate_critical_step {
        print_estimate(&mut body, "pressed 1 mm")?;
    }
    let before = pool.map(|p| p.stats());
    let times = timed_ticks(args, &mut body, &input, scene.integrator.tick_s)?;
    eprintln!(
        "  terms and tied particles: {:?}; first tick (terms refilled) {first_us:.0} us; stencil layout (grid cells, groups): {:?}; core_mass_scale {:.1}; implicit core {:.1} MiB",
        body.work_counts(),
        body.stencil_layout(),
        body.core_mass_scale(),
        body.implicit_core_memory_bytes() as f64 / (1024.0 * 1024.0)
    );
    if let (Some(pool), Some(before)) = (pool, before) {
        print_pool_split(pool, before);
    }
    let med = times[times.len() / 2];
    let p99 = times[(times.len() * 99) / 100];
    println!(
        "{},{},{},{},{},{},{},{},{:.1},{:.1},{:.3}",
        args.scene,
        variant.name(),
        model.layer_count,
        active,
        args.threads,
        body.substeps().0,
        body.substeps().2,
        args.ticks,
        med,
        p99,
        prep_s
    );
    Ok(())
}

/// `args.ticks` ticks of `body` under `input` (paced at `tick_s` with `--paced`), each one's
/// time in us, sorted.
fn timed_ticks(
    args: &Args,
    body: &mut HybridBody,
    input: &TickInput,
    tick_s: f64,
) -> anyhow::Result<Vec<f64>> {
    let mut times = Vec::with_capacity(args.ticks);
    let period = std::time::Duration::from_secs_f64(tick_s);
    let mut deadline = Instant::now();
    for _ in 0..args.ticks {
        if args.paced {
            deadline += period;
            if let Some(wait) = deadline.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        let t = Instant::now();
        body.tick(input)?;
        times.push(t.elapsed().as_secs_f64() * 1e6);
    }
    times.sort_by(f64::total_cmp);
    Ok(times)
}

/// The pool's jobs and parts since `before` (who ran the timed ticks' parts).
fn print_pool_split(pool: &TickPool, before: PoolStats) {
    let a = pool.stats();
    eprintln!(
        "  pool over the timed ticks: {} jobs, parts on the caller {} / on workers {}, longest wait {} us",
        a.jobs - before.jobs,
        a.parts_on_caller - before.parts_on_caller,
        a.parts_on_workers - before.parts_on_workers,
        a.longest_wait_us
    );
}
