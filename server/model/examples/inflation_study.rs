//! Mesh study of the Land et al. (2015) LV passive-inflation benchmark, problem 2 (Proc. R. Soc.
//! A 471:20150641): the shipped scene `deploy/scenes/lv_guccione_inflation.toml` (built-in LV,
//! quadratic, Guccione C = 10 kPa, b = 1, base clamped, 10 kPa follower pressure on ENDO) at
//! several mesh sizes and volumetric treatments; prints and writes (`target/bench/inflation.csv`
//! or `--out DIR`) the deformed apex z of the endocardium and epicardium, the wall's volume
//! change and the solve cost, and a Richardson estimate from the three finest meshes.
//!
//! ```sh
//! cargo run --release -p haptic-model --example inflation_study -- --tets 500,1000,2000,4000
//! cargo run --release -p haptic-model --example inflation_study -- --tets 1000,2000 --volumetric point
//! ```

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::scene::parse_scene_toml;
use haptic_model::statics::{StaticParams, solve_scene_loads};

#[derive(Parser, Debug)]
#[command(about = "Mesh study of the LV inflation benchmark (Land et al. 2015, problem 2)")]
struct Args {
    /// Target element counts of the built-in LV (quadratic), increasing.
    #[arg(long, value_delimiter = ',', default_value = "500,1000,2000,4000")]
    tets: Vec<usize>,
    /// Volumetric treatments: `mean-dilatation`, `point`.
    #[arg(long, value_delimiter = ',', default_value = "mean-dilatation")]
    volumetric: Vec<String>,
    /// Penalty bulk modulus, Pa.
    #[arg(long, default_value_t = 1e7)]
    bulk_modulus_pa: f64,
    /// Load increments.
    #[arg(long, default_value_t = 10)]
    load_steps: usize,
    /// Output directory (default `target/bench`).
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(serde::Serialize)]
struct Row {
    volumetric: String,
    tets: usize,
    nodes: usize,
    endo_apex_z_mm: f64,
    epi_apex_z_mm: f64,
    wall_volume_change: f64,
    newton_iterations: usize,
    seconds: f64,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let scene_path = root.join("deploy/scenes/lv_guccione_inflation.toml");
    let template = std::fs::read_to_string(&scene_path)?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| root.join("target/bench"));
    std::fs::create_dir_all(&out)?;
    let csv_path = out.join("inflation.csv");
    let mut csv = csv::Writer::from_path(&csv_path)?;
    println!(
        "{:<16} {:>6} {:>7} {:>14} {:>14} {:>12} {:>7} {:>8}",
        "volumetric", "tets", "nodes", "endo apex z", "epi apex z", "dV/V", "Newton", "time"
    );
    for vol in &args.volumetric {
        let mut rows: Vec<Row> = Vec::new();
        for &tets in &args.tets {
            let row = solve_row(&args, (&template, &scene_path), vol, tets)?;
            csv.serialize(&row)?;
            csv.flush()?;
            rows.push(row);
        }
        richardson_lines(vol, &rows);
    }
    println!("wrote {}", csv_path.display());
    Ok(())
}

/// Solves the inflation of the scene `template` (read from `scene_path`) with `vol` and about
/// `tets` tets, prints its row and returns it.
fn solve_row(
    args: &Args,
    (template, scene_path): (&str, &Path),
    vol: &str,
    tets: usize,
) -> anyhow::Result<Row> {
    let text = template
        .replace("target_tets = 2000", &format!("target_tets = {tets}"))
        .replace(
            "volumetric = \"mean-dilatation\"",
            &format!("volumetric = \"{vol}\""),
        )
        .replace(
            "bulk_modulus_pa = 1.0e7",
            &format!("bulk_modulus_pa = {:e}", args.bulk_modulus_pa),
        );
    let scene = parse_scene_toml(&text, scene_path.parent().unwrap())?;
    let fem = scene.fem_model()?;
    let rest = &scene.mesh.nodes;
    let nearest = |p: DVec3| {
        (0..rest.len())
            .min_by(|&a, &b| (rest[a] - p).length().total_cmp(&(rest[b] - p).length()))
            .unwrap()
    };
    let endo = nearest(DVec3::new(0.0, 0.0, -17e-3));
    let epi = nearest(DVec3::new(0.0, 0.0, -20e-3));
    anyhow::ensure!(
        (rest[endo] - DVec3::new(0.0, 0.0, -17e-3)).length() < 1e-9
            && (rest[epi] - DVec3::new(0.0, 0.0, -20e-3)).length() < 1e-9,
        "the mesh has no node at an apex"
    );
    let t = Instant::now();
    let params = StaticParams {
        rel_tol: 1e-8,
        ..StaticParams::default()
    };
    let (x, report) = solve_scene_loads(&scene, args.load_steps, &params, &mut |label, its| {
        eprintln!(
            "  {vol} {tets}: {label}: {its} Newton iterations, {:.1} s",
            t.elapsed().as_secs_f64()
        )
    })
    .map_err(|e| anyhow::anyhow!("{vol}, {tets} tets: {e}"))?;
    let iterations = report.newton_iterations;
    let row = Row {
        volumetric: vol.to_string(),
        tets: scene.mesh.tet_count(),
        nodes: scene.mesh.node_count(),
        endo_apex_z_mm: x[endo].z * 1e3,
        epi_apex_z_mm: x[epi].z * 1e3,
        wall_volume_change: fem.deformed_volume_m3(&x) / fem.deformed_volume_m3(rest) - 1.0,
        newton_iterations: iterations,
        seconds: t.elapsed().as_secs_f64(),
    };
    println!(
        "{:<16} {:>6} {:>7} {:>11.4} mm {:>11.4} mm {:>12.2e} {:>7} {:>6.1} s",
        row.volumetric,
        row.tets,
        row.nodes,
        row.endo_apex_z_mm,
        row.epi_apex_z_mm,
        row.wall_volume_change,
        row.newton_iterations,
        row.seconds
    );
    Ok(row)
}

/// Richardson from the three finest meshes of `rows` (h ~ tets^(-1/3)), one line per apex.
fn richardson_lines(vol: &str, rows: &[Row]) {
    if let [.., a, b, c] = rows {
        for (name, get) in [
            ("endo", (|r: &Row| r.endo_apex_z_mm) as fn(&Row) -> f64),
            ("epi", |r: &Row| r.epi_apex_z_mm),
        ] {
            let (h1, h2, h3) = (
                (a.tets as f64).powf(-1.0 / 3.0),
                (b.tets as f64).powf(-1.0 / 3.0),
                (c.tets as f64).powf(-1.0 / 3.0),
            );
            let (f1, f2, f3) = (get(a), get(b), get(c));
            let (r12, r23) = (h1 / h2, h2 / h3);
            // Observed order from the three (ratios close to each other).
            let ratio = (f1 - f2) / (f2 - f3);
            let order = if ratio > 0.0 {
                ratio.ln() / (0.5 * (r12 + r23)).ln()
            } else {
                f64::NAN
            };
            let extrapolated = if order.is_finite() && order > 0.0 {
                f3 + (f3 - f2) / (r23.powf(order) - 1.0)
            } else {
                f64::NAN
            };
            println!(
                "{vol}: {name} apex z: finest {f3:.4} mm, observed order {order:.2}, Richardson {extrapolated:.4} mm (|finest - extrapolated| {:.4} mm)",
                (f3 - extrapolated).abs()
            );
        }
    }
}
