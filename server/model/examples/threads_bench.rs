//! Element forces in parts on two threads (issue 48 sections 1 and 3): a scene's force model (the
//! body's, or the active region's of a condensed scene) pressed `--depth-mm` at the equator,
//! then blocks of `--block` elastic force evaluations (`FemModel::add_internal_forces_in`)
//! alternating between the variants, and p50 / p99 per variant with their ratio to one thread:
//!
//! - `1 thread`: one part (the one-core path);
//! - `2 parts, 1 thread`: the cut's own cost (two parts one after the other);
//! - `2 threads`: two parts, the second on another thread: `--threads-impl scoped` (default)
//!   spawns a scoped thread per evaluation (a stand-in until the tick pool has workers; its
//!   cost is the `spawn only` row), `pool` runs them on `TickPool::new(1, ..)` (one worker:
//!   with the serial skeleton that is one thread);
//! - `spawn only`: an empty scoped thread spawned and joined (the stand-in's overhead).
//!
//! `--double` runs the scene's model in double precision (the double-precision kernel's cut:
//! lane halves of the tetrahedra, halves of the Morton curve of the smoothing domains).
//!
//! `cargo run --release -p haptic-model --example threads_bench -- --blocks 3 --plain`
//! `cargo run --release -p haptic-model --example threads_bench -- --blocks 3 --double --threads-impl pool`

use std::sync::Arc;
use std::time::Instant;

use clap::{Parser, ValueEnum};
use haptic_model::DVec3;
use haptic_model::body::TickInput;
use haptic_model::element::{ForceScratch, PartRunner};
use haptic_model::fem::FemBody;
use haptic_model::pool::{StartHook, TickPool};
use haptic_model::scene::load_scene_file;

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ThreadsImpl {
    /// A scoped thread spawned per evaluation (the stand-in).
    Scoped,
    /// `TickPool::new(1, ..)`.
    Pool,
}

#[derive(Parser)]
struct Args {
    /// Scene file.
    #[arg(long, default_value = "deploy/scenes/lv_h1.toml")]
    scene_file: String,
    /// Press depth below the rest surface at the equator on +x, mm.
    #[arg(long, default_value_t = 3.0)]
    depth_mm: f64,
    /// Blocks per variant.
    #[arg(long, default_value_t = 10)]
    blocks: usize,
    /// Force evaluations per block.
    #[arg(long, default_value_t = 200)]
    block: usize,
    /// Linear tetrahedra without strain smoothing (the scene's mesh and material): the
    /// tetrahedra's cut (lane halves) instead of the smoothing domains' (batch ranges).
    #[arg(long)]
    plain: bool,
    /// Double-precision forces (`force_precision = "double"`) instead of the scene's.
    #[arg(long)]
    double: bool,
    /// Pin the one-part runs to the AVX2 build (two parts run it always): separates the cut's
    /// cost from the instruction set's on an AVX-512 CPU.
    #[arg(long)]
    avx2: bool,
    /// What runs the second part.
    #[arg(long, value_enum, default_value_t = ThreadsImpl::Scoped)]
    threads_impl: ThreadsImpl,
}

#[path = "common/part_runners.rs"]
mod part_runners;
use part_runners::{Scoped, Serial};

/// A variant: its name and what runs its parts (`None`: an empty scoped spawn).
type Variant = (&'static str, Option<Box<dyn PartRunner>>);

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let sim = pressed(&args)?;
    let body = sim.fem();
    let model = sim.stepper().force_model(body);
    let n = model.node_count();
    println!(
        "{}: force model {} nodes, {} elements; single precision {}",
        args.scene_file,
        n,
        model.element_count(),
        model.single_precision()
    );
    if let Some((touched, shared)) = model.force_part_nodes(2) {
        println!("2 parts touch {touched} nodes, {shared} of them shared (summed after the parts)");
    }
    let pool: Box<dyn PartRunner> = match args.threads_impl {
        ThreadsImpl::Scoped => Box::new(Scoped),
        ThreadsImpl::Pool => {
            let hook: StartHook = Arc::new(|_| {});
            Box::new(Arc::into_inner(TickPool::new(1, hook)?).expect("a new pool"))
        }
    };
    let two = match args.threads_impl {
        ThreadsImpl::Scoped => "2 threads (scoped stand-in)",
        ThreadsImpl::Pool => "2 threads (TickPool::new(1))",
    };
    let variants: Vec<Variant> = vec![
        ("1 thread", Some(Box::new(Serial(1)))),
        ("2 parts, 1 thread", Some(Box::new(Serial(2)))),
        (two, Some(pool)),
        ("spawn only", None),
    ];
    let samples = measure(&args, &sim, &variants);
    report(&variants, &samples);
    Ok(())
}

/// The scene pressed `depth_mm` at the equator on +x over 200 ticks.
fn pressed(args: &Args) -> anyhow::Result<FemBody> {
    let mut scene = load_scene_file(std::path::Path::new(&args.scene_file))?;
    if args.plain {
        scene.strain_smoothing = haptic_model::element::StrainSmoothing::None;
    }
    if args.double {
        scene.integrator.single_precision_forces = false;
    }
    let mut sim = FemBody::new(&scene)?;
    sim.set_blocking_region_preparation(true);
    for k in 0..200 {
        let s = (k as f64 / 150.0).min(1.0);
        let depth = 1e-3 * args.depth_mm * s * s * (3.0 - 2.0 * s);
        sim.tick(&TickInput {
            device_position_m: Some(DVec3::new(0.011_682 - depth, 0.0, -0.005)),
            device_velocity_m_per_s: DVec3::ZERO,
        })?;
    }
    Ok(sim)
}

/// Per variant, the time of every evaluation (us), blocks alternating between the variants.
fn measure(args: &Args, sim: &FemBody, variants: &[Variant]) -> Vec<Vec<f64>> {
    let mut model = sim.stepper().force_model(sim.fem()).clone();
    if args.avx2 {
        model
            .pin_single_precision_isa(haptic_model::element::SingleIsa::Avx2)
            .expect("single precision on an AVX2 CPU");
    }
    let x = &sim.state().x;
    let n = model.node_count();
    let mut f = vec![DVec3::ZERO; n];
    let mut scratch = ForceScratch::with_parts(n, 2);
    let mut samples = vec![Vec::with_capacity(args.blocks * args.block); variants.len()];
    for _ in 0..args.blocks {
        for ((_, runner), out) in variants.iter().zip(&mut samples) {
            for _ in 0..args.block {
                f.iter_mut().for_each(|v| *v = DVec3::ZERO);
                let t = Instant::now();
                match runner {
                    Some(r) => {
                        model.add_internal_forces_in(r.as_ref(), x, None, &mut f, &mut scratch)
                    }
                    None => std::thread::scope(|s| s.spawn(|| ()).join().expect("empty")),
                }
                out.push(t.elapsed().as_secs_f64() * 1e6);
                std::hint::black_box(&f);
            }
        }
    }
    samples
}

/// p50 and p99 per variant and the ratio of one thread's p50 to each.
fn report(variants: &[Variant], samples: &[Vec<f64>]) {
    let pct = |s: &[f64], q: f64| {
        let mut s = s.to_vec();
        s.sort_by(f64::total_cmp);
        s[((s.len() - 1) as f64 * q).round() as usize]
    };
    let base = pct(&samples[0], 0.5);
    println!("| variant | evaluations | p50 (us) | p99 (us) | one thread's p50 / p50 |");
    println!("|---|---|---|---|---|");
    for ((name, _), s) in variants.iter().zip(samples) {
        let (p50, p99) = (pct(s, 0.5), pct(s, 0.99));
        println!(
            "| {name} | {} | {p50:.1} | {p99:.1} | {:.2} |",
            s.len(),
            base / p50
        );
    }
}
