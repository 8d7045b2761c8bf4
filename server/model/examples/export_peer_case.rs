//! Exports the case of the peer measurement (issue 3, section 4) and times our StVK force on it:
//! `lv_h1.msh` read by our Gmsh reader (converted to m), a smooth analytic deformation, our
//! elastic forces (no viscosity) and the median time of `FemModel::add_internal_forces` on one
//! thread; with `--threads 2` also of `FemModel::add_internal_forces_in` in two parts on a tick
//! pool of one worker (issue 48 s3), whose forces must match the one-thread ones within 1e-12
//! of the largest nodal force. `server/model/benches/peer/run_peer.sh` runs this, then the peer
//! on the same data.
//!
//! Run: `cargo run --release -p haptic-model --example export_peer_case -- OUT_DIR [REPEATS]
//! [--threads 2]`. Writes `OUT_DIR/nodes.txt` (rest x y z per line, m), `tets.txt` (4
//! zero-based node indices), `deformed.txt` (x y z, m), `ours_force.txt` (fx fy fz, N) and
//! `ours.json` (material, timing; `force_median_us_threads`, `threads` with `--threads 2`).

#[path = "../benches/common/mod.rs"]
mod common;

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use clap::Parser;
use common::TickTimes;
use haptic_model::DVec3;
use haptic_model::element::{FemModel, ForceScratch};
use haptic_model::material::MaterialParams;
use haptic_model::mesh::gmsh::load_msh;
use haptic_model::pool::TickPool;

/// Exports the peer measurement's case (lv_h1.msh, a smooth deformation, our StVK forces) and
/// times our force evaluation on it.
#[derive(Debug, Parser)]
#[command(name = "export_peer_case")]
struct Args {
    /// Output folder.
    #[arg(default_value = "target/peer-case")]
    out: PathBuf,
    /// Timed force evaluations.
    #[arg(default_value_t = 200)]
    repeats: u32,
    /// Threads of the second timing (2: two parts on a tick pool of one worker, unpinned; the
    /// caller's scheduling class); 1 times one thread only.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=2))]
    threads: u32,
}

fn main() {
    let Args {
        out,
        repeats,
        threads,
    } = Args::parse();
    let msh = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/lv/lv_h1.msh");
    let mut mesh = load_msh(&msh).unwrap_or_else(|e| panic!("reading {}: {e}", msh.display()));
    mesh.scale(1e-3);
    // E = 14.5 kPa, nu = 0.45 (the lv scenes), elastic only.
    let (e, nu) = (14.5e3, 0.45);
    let fem = FemModel::new(&mesh, MaterialParams::from_youngs(e, nu, 1060.0)).expect("FEM");
    // Smooth analytic deformation (m): a twist about z, a bulge and a shear, a few per cent of
    // strain over the 20 mm body.
    let x: Vec<DVec3> = mesh
        .nodes
        .iter()
        .map(|p| {
            let s = p / 0.01;
            let twist = 0.15 * s.z;
            let (c, sn) = (twist.cos(), twist.sin());
            let q = DVec3::new(c * p.x - sn * p.y, sn * p.x + c * p.y, p.z);
            q + DVec3::new(
                0.0008 * (1.3 * s.y).sin() + 0.0005 * s.z * s.x,
                0.0006 * (0.9 * s.z).cos() * s.x,
                0.0007 * (s.x * s.y) + 0.0004 * (1.1 * s.z).sin(),
            )
        })
        .collect();
    let mut f = vec![DVec3::ZERO; x.len()];
    let mut times = TickTimes::new();
    for _ in 0..repeats {
        f.iter_mut().for_each(|v| *v = DVec3::ZERO);
        let t = Instant::now();
        fem.add_internal_forces(&x, None, &mut f);
        times.record(t.elapsed());
        std::hint::black_box(&f);
    }
    let median = times.percentiles().p50_us;
    let parallel = (threads > 1).then(|| time_in_parts(&fem, &x, &f, repeats, threads as usize));
    std::fs::create_dir_all(&out).expect("creating the output directory");
    let lines = |v: &[DVec3]| {
        v.iter().fold(String::new(), |mut s, p| {
            let _ = writeln!(s, "{:.17e} {:.17e} {:.17e}", p.x, p.y, p.z);
            s
        })
    };
    std::fs::write(out.join("nodes.txt"), lines(&mesh.nodes)).expect("nodes");
    std::fs::write(out.join("deformed.txt"), lines(&x)).expect("deformed");
    std::fs::write(out.join("ours_force.txt"), lines(&f)).expect("forces");
    let tets = mesh.tets.iter().fold(String::new(), |mut s, t| {
        let _ = writeln!(s, "{} {} {} {}", t[0], t[1], t[2], t[3]);
        s
    });
    std::fs::write(out.join("tets.txt"), tets).expect("tets");
    let mut info = serde_json::json!({
        "youngs_modulus_pa": e,
        "poisson_ratio": nu,
        "lambda_pa": fem.material().lambda_pa,
        "mu_pa": fem.material().mu_pa,
        "nodes": mesh.node_count(),
        "tets": mesh.tet_count(),
        "repeats": repeats,
        "force_median_us": median,
        "elastic_energy_j": fem.elastic_energy(&x),
    });
    if let Some(median_threads) = parallel {
        info["threads"] = threads.into();
        info["force_median_us_threads"] = median_threads.into();
    }
    std::fs::write(out.join("ours.json"), info.to_string() + "\n").expect("ours.json");
    println!(
        "ours: {} nodes, {} tets, StVK force median {median:.1} us over {repeats} runs; wrote {}",
        mesh.node_count(),
        mesh.tet_count(),
        out.display()
    );
    if let Some(median_threads) = parallel {
        println!(
            "ours: the same in {threads} parts on {threads} threads, median {median_threads:.1} us"
        );
    }
}

/// The median time (us) of `repeats` evaluations of `fem`'s elastic forces at `x` in `threads`
/// parts on a tick pool of `threads - 1` workers; exits with an error when the forces differ
/// from the one-thread `f` by more than 1e-12 of its largest nodal force.
fn time_in_parts(fem: &FemModel, x: &[DVec3], f: &[DVec3], repeats: u32, threads: usize) -> f64 {
    let pool = TickPool::new(threads - 1, Arc::new(|_| {})).expect("a tick pool");
    let mut scratch = ForceScratch::with_parts(x.len(), threads);
    let mut fp = vec![DVec3::ZERO; x.len()];
    let mut times = TickTimes::new();
    for _ in 0..repeats.max(1) {
        fp.iter_mut().for_each(|v| *v = DVec3::ZERO);
        let t = Instant::now();
        fem.add_internal_forces_in(&*pool, x, None, &mut fp, &mut scratch);
        times.record(t.elapsed());
        std::hint::black_box(&fp);
    }
    let largest = f.iter().map(|v| v.length()).fold(0.0, f64::max);
    let worst = f
        .iter()
        .zip(&fp)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    if worst > 1e-12 * largest {
        eprintln!(
            "the forces in {threads} parts differ from one thread's by {worst:.3e} N (largest {largest:.3e} N)"
        );
        std::process::exit(1);
    }
    times.percentiles().p50_us
}
