//! `haptic-solve SCENE.toml --out DIR`: static equilibrium of a scene under its `[loads]`,
//! written as `DIR/nodes.csv` (`id,x0,y0,z0,x,y,z`) and `DIR/solution.vtu`, in the scene's
//! length unit.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;

/// Static equilibrium of a scene file (Newton, sparse Cholesky, load stepping).
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Scene file (TOML) with a [loads] section.
    scene: PathBuf,
    /// Output directory.
    #[arg(long, default_value = "solve-out")]
    out: PathBuf,
    /// Load increments.
    #[arg(long, default_value_t = 1)]
    load_steps: usize,
    /// Largest number of frozen-load Newton solves per increment with a follower pressure.
    #[arg(long, default_value_t = haptic_server::solve::SolveParams::default().max_follower_passes)]
    max_follower_passes: usize,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let scene = haptic_model::scene::load_scene_file(&args.scene)
        .with_context(|| format!("loading {}", args.scene.display()))?;
    eprintln!(
        "solving {} ({} nodes, {} tets) in {} load step(s) ...",
        scene.name,
        scene.mesh.node_count(),
        scene.mesh.tet_count(),
        args.load_steps
    );
    let t = std::time::Instant::now();
    let params = haptic_server::solve::SolveParams {
        load_steps: args.load_steps,
        max_follower_passes: args.max_follower_passes,
        ..Default::default()
    };
    let (x, r) = haptic_server::solve::solve_scene(&scene, &params)?;
    haptic_server::solve::write_solution(&args.out, &scene, &x)?;
    println!(
        "converged: {} Newton iterations in {} load pass(es), residual {:.3e} N ({:.1e} of the load, loads at the final shape), max displacement {:.6} (scene unit) in {:.2} s",
        r.newton_iterations,
        r.load_passes,
        r.residual_n,
        r.relative_residual,
        r.max_displacement_m / scene.length_unit_m,
        t.elapsed().as_secs_f64()
    );
    println!(
        "wrote {} and {}",
        args.out.join("nodes.csv").display(),
        args.out.join("solution.vtu").display()
    );
    Ok(())
}
