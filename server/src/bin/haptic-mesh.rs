//! `haptic-mesh SURFACE --out DIR`: a closed surface mesh (STL, OBJ, PLY; optionally an inner
//! cavity surface) becomes a tetrahedral Gmsh mesh with named physical groups and a scene file
//! (`DIR/NAME.msh`, `DIR/NAME.toml`), checked by loading it as the daemon would. Gmsh (Debian's
//! `gmsh` package; `tests/install-gmsh.sh`) fills the volume: it is looked for first, and
//! nothing is written without it. A run that fails leaves no work folder behind, nor `DIR` when
//! it made it.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use haptic_server::surface_mesh::{
    ClampRule, SurfaceMesh, VolumeOptions, VolumeSummary, check_closed, mesh_volume, read_surface,
};

/// Turn a closed organ surface into a tetrahedral mesh and a scene.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Closed outer surface (.stl, .obj or .ply).
    surface: PathBuf,
    /// Closed inner surface of a cavity inside it (same formats).
    #[arg(long)]
    inner: Option<PathBuf>,
    /// Output directory (NAME.msh and NAME.toml).
    #[arg(long)]
    out: PathBuf,
    /// Scene and file name (default: the surface file's stem).
    #[arg(long)]
    name: Option<String>,
    /// Clamp the outer triangles whose vertices all lie at or below this z (surface unit).
    #[arg(long, allow_hyphen_values = true, conflicts_with = "clamp_above_z")]
    clamp_below_z: Option<f64>,
    /// Clamp the outer triangles whose vertices all lie at or above this z (surface unit).
    #[arg(long, allow_hyphen_values = true)]
    clamp_above_z: Option<f64>,
    /// Largest tetrahedron edge inside, surface unit (default: from the surface's triangles).
    #[arg(long)]
    max_size: Option<f64>,
    /// Length unit of the surface's coordinates: m, cm or mm.
    #[arg(long, default_value = "mm", value_parser = ["m", "cm", "mm"])]
    unit: String,
    /// Young's modulus of the scene's material, Pa.
    #[arg(long, default_value_t = 14_500.0)]
    youngs_modulus_pa: f64,
    /// Poisson ratio of the scene's material.
    #[arg(long, default_value_t = 0.45)]
    poisson_ratio: f64,
    /// Gmsh executable.
    #[arg(long, default_value = "gmsh")]
    gmsh: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    // Gmsh first: without it nothing can be made, so nothing is written.
    if let Err(e) = std::process::Command::new(&args.gmsh)
        .arg("--version")
        .stdin(std::process::Stdio::null())
        .output()
    {
        anyhow::bail!(
            "cannot run {} ({e}): haptic-mesh needs Gmsh, e.g. Debian's package \
             (`sudo apt-get install gmsh`, or `sudo bash tests/install-gmsh.sh` from the \
             repository), or pass --gmsh PATH; nothing was written",
            args.gmsh.display()
        );
    }
    let made_out = !args.out.exists();
    let result = run(&args);
    if result.is_err() && made_out {
        // Do not leave a half-made output folder this run created.
        let _ = std::fs::remove_dir_all(&args.out);
    }
    result
}

/// The clamp rule and the scene's name from the arguments, every option checked.
fn checked_options(args: &Args) -> anyhow::Result<(ClampRule, String)> {
    let clamp = match (args.clamp_below_z, args.clamp_above_z) {
        (Some(z), None) => ClampRule::BelowZ(z),
        (None, Some(z)) => ClampRule::AboveZ(z),
        _ => anyhow::bail!(
            "say which part of the surface is held: --clamp-below-z Z or --clamp-above-z Z"
        ),
    };
    anyhow::ensure!(
        args.youngs_modulus_pa.is_finite() && args.youngs_modulus_pa > 0.0,
        "--youngs-modulus-pa must be positive"
    );
    anyhow::ensure!(
        args.poisson_ratio.is_finite() && (0.0..0.5).contains(&args.poisson_ratio),
        "--poisson-ratio must be in [0, 0.5)"
    );
    if let Some(h) = args.max_size {
        anyhow::ensure!(h.is_finite() && h > 0.0, "--max-size must be positive");
    }
    let name = match &args.name {
        Some(n) => n.clone(),
        None => args
            .surface
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .context("the surface path has no file name")?,
    };
    anyhow::ensure!(
        !name.is_empty()
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_".contains(c)),
        "--name {name:?}: use letters, digits, '-' and '_'"
    );

    Ok((clamp, name))
}

/// Reads a surface, checks that it is closed and manifold, and reports its size.
fn read_closed(path: &std::path::Path, what: &str) -> anyhow::Result<SurfaceMesh> {
    eprintln!("reading {what}{} ...", path.display());
    let mesh = read_surface(path)?;
    check_closed(&mesh, path)?;
    eprintln!(
        "  {} vertices, {} triangles, closed and manifold",
        mesh.vertices.len(),
        mesh.triangles.len()
    );
    Ok(mesh)
}

fn run(args: &Args) -> anyhow::Result<()> {
    let (clamp, name) = checked_options(args)?;
    let outer = read_closed(&args.surface, "")?;
    let inner = match &args.inner {
        Some(p) => Some(read_closed(p, "the cavity ")?),
        None => None,
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let msh = args.out.join(format!("{name}.msh"));
    eprintln!("meshing the volume with {} ...", args.gmsh.display());
    let t = std::time::Instant::now();
    let summary = mesh_volume(
        &outer,
        inner.as_ref(),
        &VolumeOptions {
            clamp,
            max_size: args.max_size,
            gmsh: args.gmsh.clone(),
        },
        &msh,
        |line| {
            if line.contains("nodes") || line.contains("Meshing") || line.contains("Optimiz") {
                eprintln!("  gmsh {line}");
            }
        },
    )?;
    eprintln!("  done in {:.1} s", t.elapsed().as_secs_f64());

    let scene_path = args.out.join(format!("{name}.toml"));
    let scene = scene_text(args, &name, &summary);
    std::fs::write(&scene_path, scene)
        .with_context(|| format!("writing {}", scene_path.display()))?;
    eprintln!("checking the scene as the daemon loads it ...");
    let loaded = haptic_model::scene::load_scene_file(&scene_path)
        .with_context(|| format!("the generated scene {} does not load", scene_path.display()))?;
    println!(
        "{}: {} nodes, {} tetrahedra; scene {}",
        msh.display(),
        loaded.mesh.node_count(),
        loaded.mesh.tet_count(),
        scene_path.display()
    );
    Ok(())
}

/// The scene file for the meshed volume: `name`'s mesh, the material of the arguments, the
/// shipped integrator and probe defaults.
fn scene_text(args: &Args, name: &str, summary: &VolumeSummary) -> String {
    format!(
        "# Made by haptic-mesh from {surface} ({outer} outer triangles: {base} clamped as BASE, the\n\
         # rest touchable as OUTER{cavity}).\n\
         name = \"{name}\"\n\
         description = \"{name}: volume meshed by Gmsh from {surface}\"\n\n\
         [mesh]\nfile = \"{name}.msh\"\nlength_unit = \"{unit}\"\n\n\
         [material]\nyoungs_modulus_pa = {e:?}\npoisson_ratio = {nu:?}\n\
         density_kg_per_m3 = 1060.0\nphi_pa_s = 0.05\npsi_pa_s = 0.05\nmass_damping_per_s = 5.0\n\n\
         [boundary]\nclamped = [\"BASE\"]\ntouchable = [\"OUTER\"]\n\n\
         [integrator]\nkind = \"symplectic-euler\"\ntick_s = 0.001\nsubsteps = \"auto\"\n\
         max_substeps = 64\nsafety_factor = 0.9\n\n\
         [probe]\nradius_m = 0.002\ncoupling_stiffness_n_per_m = 300.0\n\
         coupling_damping_n_s_per_m = 0.05\nmax_force_n = 10.0\n",
        surface = args.surface.display(),
        outer = summary.outer_triangles,
        base = summary.base_triangles,
        cavity = if summary.inner_triangles > 0 {
            format!(
                "; a cavity of {} triangles as INNER",
                summary.inner_triangles
            )
        } else {
            String::new()
        },
        unit = args.unit,
        e = args.youngs_modulus_pa,
        nu = args.poisson_ratio,
    )
}
