//! The README's results table (issue 46, section 6): shipped left-ventricle scenes pressed at the
//! lv-probe point (a 2 mm sphere along -x at y = 0, z = -5 mm) through `SoftBody::tick` as the
//! servo drives them ([`haptic_model::press::staircase`]: a 0.5 s ramp and a 1.5 s hold per
//! depth, the force averaged over the hold's last second), each held force compared with the
//! rigid-sphere reference of the scene's material at the same device depth
//! (`server/model/benches/precision/lv_sphere_reference.csv`, rows with
//! `depth_convention = device`: the sphere's travel plus the virtual coupling's stretch), with
//! the hold's steadiness (largest tick-to-tick change, % of the held force) and the tick p50/p99
//! of the whole run on this machine. Prints a markdown table; `--plot FILE.png` also draws force
//! against depth for the first six scenes with the references' points and uncertainty bars.
//!
//! A scene is a built-in name or a `.toml` file, optionally followed by `:MATERIAL` to run it
//! with another constitutive model (same Lamé parameters), e.g. `lv:stable-neo-hookean`. The
//! mass-spring family has no material: it is compared with the stable neo-Hookean reference
//! (the organ it is calibrated to). A depth without a reference row for the material shows `-`
//! (St. Venant-Kirchhoff has no equilibrium under a rigid sphere past about 1.7 mm).
//!
//! Run: `cargo run --release -p haptic-model --example scene_table -- --scenes
//! lv,lv:stable-neo-hookean,deploy/scenes/lv_h1_condensed.toml,lv-hybrid,lv-surface-springs
//! --plot out/scene-table.png`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Parser;
use haptic_model::material::MaterialModel;
use haptic_model::press::{self, HoldParams, HoldReport, PressLine};
use haptic_model::scene::{ModelFamily, Scene, load_builtin, load_scene_file};

/// Presses shipped LV scenes at the lv-probe point and compares them with the sphere reference.
#[derive(Debug, Parser)]
#[command(name = "scene_table")]
struct Args {
    /// Scenes: built-in names or .toml files, each optionally `:MATERIAL`.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "lv,lv:stable-neo-hookean,lv-hybrid,lv-surface-springs"
    )]
    scenes: Vec<String>,
    /// Device depths past first contact, mm.
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2,3")]
    depths: Vec<f64>,
    /// The reference CSV (columns material, depth_convention, depth_mm, force_n,
    /// uncertainty_n, ...).
    #[arg(long, default_value = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/benches/precision/lv_sphere_reference.csv"
    ))]
    reference: PathBuf,
    /// Also draw force against depth into this PNG.
    #[arg(long)]
    plot: Option<PathBuf>,
}

/// One reference row: material, device depth (m), force (N), uncertainty (N).
#[derive(Debug, Clone)]
struct RefPoint {
    material: String,
    depth_m: f64,
    force_n: f64,
    uncertainty_n: f64,
}

/// One pressed scene.
struct Pressed {
    label: String,
    material: String,
    holds: Vec<HoldReport>,
    tick_p50_s: f64,
    tick_p99_s: f64,
}

fn main() {
    if let Err(e) = run(Args::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(args: Args) -> anyhow::Result<()> {
    if args.depths.is_empty() || args.depths.iter().any(|d| !(d.is_finite() && *d > 0.0)) {
        bail!(
            "--depths: expected positive depths in mm, got {:?}",
            args.depths
        );
    }
    let reference = read_reference(&args.reference)?;
    println!(
        "machine: {}; reference: {}",
        cpu_model(),
        args.reference.display()
    );
    let mut pressed = Vec::new();
    for spec in &args.scenes {
        let p = press_scene(spec, &args.depths)?;
        eprintln!("{}: done", p.label);
        pressed.push(p);
    }
    print_table(&pressed, &args.depths, &reference);
    if let Some(path) = &args.plot {
        plot(path, &pressed, &reference)?;
        println!(
            "wrote {} (the first {} of {} scenes)",
            path.display(),
            pressed.len().min(MAX_PLOTTED),
            pressed.len()
        );
    }
    Ok(())
}

/// The reference rows of the device convention.
fn read_reference(path: &Path) -> anyhow::Result<Vec<RefPoint>> {
    let mut reader = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .from_path(path)
        .with_context(|| format!("reading the reference {}", path.display()))?;
    let headers = reader.headers()?.clone();
    let col = |name: &str| {
        headers
            .iter()
            .position(|h| h == name)
            .with_context(|| format!("{}: no column {name}", path.display()))
    };
    let (m, c, d, f, u) = (
        col("material")?,
        col("depth_convention")?,
        col("depth_mm")?,
        col("force_n")?,
        col("uncertainty_n")?,
    );
    let mut rows = Vec::new();
    for (k, record) in reader.records().enumerate() {
        let record = record?;
        if &record[c] != "device" {
            continue;
        }
        let num = |i: usize| -> anyhow::Result<f64> {
            record[i]
                .parse::<f64>()
                .with_context(|| format!("{} row {}: column {i}", path.display(), k + 2))
        };
        rows.push(RefPoint {
            material: record[m].to_string(),
            depth_m: num(d)? * 1e-3,
            force_n: num(f)?,
            uncertainty_n: num(u)?,
        });
    }
    Ok(rows)
}

/// `NAME[:MATERIAL]` loaded, with its material switched if asked.
fn load(spec: &str) -> anyhow::Result<(Scene, String)> {
    let (name, material) = match spec.split_once(':') {
        Some((n, m)) => (n, Some(m)),
        None => (spec, None),
    };
    let mut scene = if name.ends_with(".toml") {
        load_scene_file(Path::new(name))
    } else {
        load_builtin(name)
    }
    .with_context(|| format!("scene {spec}"))?;
    let label = match material {
        Some(m) => {
            scene.material.model = MaterialModel::from_scene_name(m)
                .with_context(|| format!("{spec}: unknown material {m:?}"))?;
            format!("{} ({m})", scene.name)
        }
        None => scene.name.clone(),
    };
    Ok((scene, label))
}

fn press_scene(spec: &str, depths_mm: &[f64]) -> anyhow::Result<Pressed> {
    let (scene, label) = load(spec)?;
    let material = match scene.family {
        ModelFamily::MassSpring => MaterialModel::StableNeoHookean.scene_name(),
        _ => scene.material.model.scene_name(),
    }
    .to_string();
    let t0 = Instant::now();
    let mut body = haptic_model::build_body(&scene).with_context(|| format!("building {spec}"))?;
    eprintln!("{label}: set-up {:.2} s", t0.elapsed().as_secs_f64());
    let info = body.info();
    let line = PressLine::lv_probe(info.probe_radius_m);
    let depths: Vec<f64> = depths_mm.iter().map(|d| d * 1e-3).collect();
    let (holds, trace) = press::staircase(
        body.as_mut(),
        &line,
        &depths,
        &HoldParams::default(),
        info.tick_s,
    )
    .with_context(|| format!("pressing {spec}"))?;
    Ok(Pressed {
        label,
        material,
        holds,
        tick_p50_s: trace.tick_quantile_s(0.5),
        tick_p99_s: trace.tick_quantile_s(0.99),
    })
}

fn reference_at<'a>(
    reference: &'a [RefPoint],
    material: &str,
    depth_m: f64,
) -> Option<&'a RefPoint> {
    reference
        .iter()
        .find(|r| r.material == material && (r.depth_m - depth_m).abs() < 1e-9)
}

fn print_table(pressed: &[Pressed], depths_mm: &[f64], reference: &[RefPoint]) {
    let heads: Vec<String> = depths_mm.iter().map(|d| format!("{d} mm")).collect();
    println!(
        "\n| scene | reference | {} | steadiness (worst hold) | tick p50 / p99 |",
        heads.join(" | ")
    );
    println!("|---|---|{}---|---|", "---|".repeat(depths_mm.len()));
    for p in pressed {
        let cells: Vec<String> = p
            .holds
            .iter()
            .map(
                |h| match reference_at(reference, &p.material, h.device_depth_m) {
                    Some(r) => format!(
                        "{:+.1} % ({:.2} mN)",
                        100.0 * (h.force_n / r.force_n - 1.0),
                        h.force_n * 1e3
                    ),
                    None => format!("- ({:.2} mN)", h.force_n * 1e3),
                },
            )
            .collect();
        let worst = p
            .holds
            .iter()
            .map(HoldReport::steadiness)
            .fold(0.0, f64::max);
        println!(
            "| {} | {} | {} | {:.2} % | {:.3} / {:.3} ms |",
            p.label,
            p.material,
            cells.join(" | "),
            100.0 * worst,
            p.tick_p50_s * 1e3,
            p.tick_p99_s * 1e3
        );
    }
    println!("\nreference (device depth mm: force mN +- uncertainty):");
    for r in reference {
        println!(
            "  {} {:.2}: {:.3} +- {:.3} ({:.1} %)",
            r.material,
            r.depth_m * 1e3,
            r.force_n * 1e3,
            r.uncertainty_n * 1e3,
            100.0 * r.uncertainty_n / r.force_n
        );
    }
}

/// The CPU's model name (Linux), for the table's caption.
fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".to_string())
}

/// DejaVu Sans, the font the benchmark's plots use (see benches/precision/plot.rs).
static DEJAVU_SANS: &[u8] = include_bytes!("../benches/precision/fonts/DejaVuSans.ttf");

/// Scenes drawn by `--plot` (the first ones given; the table has them all).
const MAX_PLOTTED: usize = 6;

/// Force (mN) against device depth (mm): one line per scene (the first [`MAX_PLOTTED`]), the
/// references as black points with their uncertainty as bars, up to the deepest press.
fn plot(path: &Path, pressed: &[Pressed], reference: &[RefPoint]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    plotters::style::register_font("sans-serif", FontStyle::Normal, DEJAVU_SANS)
        .map_err(|_| anyhow::anyhow!("the bundled font is not valid"))?;
    // Six scenes and the two references: at most eight labelled series.
    let pressed = &pressed[..pressed.len().min(MAX_PLOTTED)];
    let x1 = pressed
        .iter()
        .flat_map(|p| p.holds.iter().map(|h| h.device_depth_m * 1e3))
        .fold(0.0, f64::max)
        * 1.05;
    let y1 = pressed
        .iter()
        .flat_map(|p| p.holds.iter().map(|h| h.force_n * 1e3))
        .chain(
            reference
                .iter()
                .filter(|r| r.depth_m * 1e3 <= x1)
                .map(|r| (r.force_n + r.uncertainty_n) * 1e3),
        )
        .fold(0.0, f64::max)
        * 1.08;
    let root = BitMapBackend::new(path, (900, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Probe force at the lv-probe point: shipped scenes vs rigid-sphere reference",
            ("sans-serif", 20),
        )
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..x1, 0.0..y1)?;
    chart
        .configure_mesh()
        .x_desc("device depth past first contact (mm)")
        .y_desc("held force (mN)")
        .draw()?;
    for (k, p) in pressed.iter().enumerate() {
        let color = Palette99::pick(k).to_rgba();
        let mut pts = vec![(0.0, 0.0)];
        pts.extend(
            p.holds
                .iter()
                .map(|h| (h.device_depth_m * 1e3, h.force_n * 1e3)),
        );
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))?
            .label(p.label.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        chart.draw_series(pts.iter().map(|&q| Circle::new(q, 4, color.filled())))?;
    }
    for (material, marker) in [("stvk", 0), ("stable-neo-hookean", 1)] {
        let rows: Vec<&RefPoint> = reference
            .iter()
            .filter(|r| r.material == material && r.depth_m * 1e3 <= x1)
            .collect();
        if rows.is_empty() {
            continue;
        }
        let label = format!("reference, {material} (uncertainty bars)");
        let series = chart.draw_series(rows.iter().map(|r| {
            let (x, y, u) = (r.depth_m * 1e3, r.force_n * 1e3, r.uncertainty_n * 1e3);
            PathElement::new(vec![(x, y - u), (x, y + u)], BLACK.stroke_width(2))
        }))?;
        series.label(label).legend(move |(x, y)| {
            if marker == 0 {
                Cross::new((x + 10, y), 5, BLACK.stroke_width(2)).into_dyn()
            } else {
                TriangleMarker::new((x + 10, y), 5, BLACK.filled()).into_dyn()
            }
        });
        if marker == 0 {
            chart.draw_series(rows.iter().map(|r| {
                Cross::new((r.depth_m * 1e3, r.force_n * 1e3), 5, BLACK.stroke_width(2))
            }))?;
        } else {
            chart.draw_series(rows.iter().map(|r| {
                TriangleMarker::new((r.depth_m * 1e3, r.force_n * 1e3), 5, BLACK.filled())
            }))?;
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}
