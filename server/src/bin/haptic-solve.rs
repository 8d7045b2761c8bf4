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
    let (x, r) = haptic_server::solve::solve_scene(&scene, args.load_steps)?;
    haptic_server::solve::write_solution(&args.out, &scene, &x)?;
    println!(
        "converged: {} Newton iterations, residual {:.3e} N, max displacement {:.6} (scene unit) in {:.2} s",
        r.newton_iterations,
        r.residual_n,
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
