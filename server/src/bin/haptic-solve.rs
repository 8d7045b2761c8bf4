//! `haptic-solve SCENE --out DIR`: static equilibrium of a scene under its `[loads]`, written
//! as `DIR/nodes.csv` (`id,x0,y0,z0,x,y,z`) and `DIR/solution.vtu`, in the scene's length unit.
//!
//! `haptic-solve SCENE --indent --from X,Y,Z --direction DX,DY,DZ --depths D1,D2,... --out
//! DIR`: the static indentation of the scene by its probe sphere (rigid, frictionless), written
//! as `DIR/indent.csv` (`depth,fx,fy,fz,contact_radius`) and `DIR/indent_NNN.vtu` per depth.
//! Positions and depths are in the scene's length unit, forces in N (on the sphere).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Parser;
use haptic_cli::vec3::parse_vec3;
use haptic_model::DVec3;
use haptic_model::scene::Scene;
use haptic_server::solve::{
    IndentRequest, SolveParams, indent_scene, indent_vtu_name, solve_scene, write_indent_csv,
    write_indent_vtu, write_solution,
};

/// Static equilibrium of a scene (Newton, sparse Cholesky, load stepping), or its static
/// indentation by the probe sphere.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Scene file (TOML), or the name of a built-in scene (`lv`, ...).
    scene: String,
    /// Output directory.
    #[arg(long, default_value = "solve-out")]
    out: PathBuf,
    /// Load increments.
    #[arg(long, default_value_t = 1)]
    load_steps: usize,
    /// Largest number of Newton iterations per load increment.
    #[arg(long, default_value_t = SolveParams::default().max_iterations)]
    max_iterations: usize,
    /// Indent the body with the scene's probe sphere instead of applying its `[loads]`.
    #[arg(long, requires_all = ["from", "direction", "depths"])]
    indent: bool,
    /// Start centre of the sphere, clear of the body: X,Y,Z in the scene's length unit.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true, requires = "indent")]
    from: Option<[f64; 3]>,
    /// Indentation direction DX,DY,DZ (normalised).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true, requires = "indent")]
    direction: Option<[f64; 3]>,
    /// Depths below first contact, increasing, in the scene's length unit: D1,D2,...
    #[arg(long, value_delimiter = ',', num_args = 1, requires = "indent")]
    depths: Option<Vec<f64>>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let path = Path::new(&args.scene);
    let scene = if path.exists() || args.scene.ends_with(".toml") {
        haptic_model::scene::load_scene_file(path)
    } else {
        haptic_model::scene::load_builtin(&args.scene)
    }
    .with_context(|| format!("loading {}", args.scene))?;
    if args.indent {
        run_indent(&args, &scene)
    } else {
        run_loads(&args, &scene)
    }
}

fn run_loads(args: &Args, scene: &Scene) -> anyhow::Result<()> {
    eprintln!(
        "solving {} ({} nodes, {} tets) in {} load step(s) ...",
        scene.name,
        scene.mesh.node_count(),
        scene.mesh.tet_count(),
        args.load_steps
    );
    let t = std::time::Instant::now();
    let params = SolveParams {
        load_steps: args.load_steps,
        max_iterations: args.max_iterations,
        ..Default::default()
    };
    let (x, r) = solve_scene(scene, &params, &mut |label, iterations| {
        eprintln!(
            "  {label}: converged in {iterations} Newton iterations, {:.1} s",
            t.elapsed().as_secs_f64()
        );
    })?;
    write_solution(&args.out, scene, &x)?;
    println!(
        "converged: {} Newton iterations in {} load step(s){}, residual {:.3e} N ({:.1e} of the load, loads at the final shape), max displacement {:.6} (scene unit) in {:.2} s",
        r.newton_iterations,
        r.load_steps,
        if r.constraint_passes > 0 {
            format!(
                " and {} full-load pass(es) for the volume (largest element volume change {:.1e})",
                r.constraint_passes, r.worst_volume_change
            )
        } else {
            String::new()
        },
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

fn run_indent(args: &Args, scene: &Scene) -> anyhow::Result<()> {
    let unit = scene.length_unit_m;
    let depths = args.depths.clone().unwrap_or_default();
    if depths.is_empty() {
        bail!("--indent needs at least one depth in --depths");
    }
    let request = IndentRequest {
        from_m: DVec3::from_array(args.from.context("--indent needs --from")?) * unit,
        direction: DVec3::from_array(args.direction.context("--indent needs --direction")?),
        depths_m: depths.iter().map(|d| d * unit).collect(),
        max_iterations: args.max_iterations,
    };
    eprintln!(
        "indenting {} ({} nodes, {} tets, {} touchable triangles) with a rigid sphere of radius {} (scene unit) at {} depth(s) ...",
        scene.name,
        scene.mesh.node_count(),
        scene.mesh.tet_count(),
        scene.touchable.len(),
        scene.probe.radius_m / unit,
        depths.len()
    );
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let t = std::time::Instant::now();
    let mut done = Vec::new();
    let mut write_error = None;
    let result = indent_scene(scene, &request, &mut |p| {
        let f = p.force_on_sphere_n;
        eprintln!(
            "  depth {:.4}: force ({:.4e}, {:.4e}, {:.4e}) N, |F| {:.4e} N, contact radius {:.4}, {} nodes and {} contact points carrying force, {} multiplier updates, {} Newton iterations, {:.1} s",
            p.depth_m / unit,
            f.x,
            f.y,
            f.z,
            f.length(),
            p.contact_radius_m / unit,
            p.nodes_in_contact,
            p.points_in_contact,
            p.augmentations,
            p.newton_iterations,
            t.elapsed().as_secs_f64()
        );
        // Each depth's files as soon as it converges: a later failure keeps them.
        let written = write_indent_vtu(&args.out, scene, done.len(), p);
        done.push(p.clone());
        if let Err(e) = written.and_then(|()| write_indent_csv(&args.out, scene, &done)) {
            write_error.get_or_insert(e);
        }
    });
    if let Some(e) = write_error {
        return Err(e).context("writing the indentation output");
    }
    match result {
        Ok(points) => {
            println!(
                "converged at all {} depths in {:.2} s; wrote {} and {} .. {}",
                points.len(),
                t.elapsed().as_secs_f64(),
                args.out.join("indent.csv").display(),
                indent_vtu_name(0),
                indent_vtu_name(points.len() - 1)
            );
            Ok(())
        }
        Err(e) => {
            if !done.is_empty() {
                eprintln!(
                    "the {} converged depth(s) are in {}",
                    done.len(),
                    args.out.join("indent.csv").display()
                );
            }
            Err(e).context("indentation failed")
        }
    }
}
