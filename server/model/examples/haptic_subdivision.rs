//! The experiment of Zhang, Payandeh & Dill, *Haptic Subdivision* (seed 003), section 3.2, on
//! our model, and the springs scenes against their organs' references.
//!
//! - `paper`: the paper's regular equilateral triangular mesh (element size L = 30 mm,
//!   `K_h = K_m = 0.06 N/mm`), the central node C displaced by x along the normal (point
//!   contact, static equilibrium, everything else free; the mesh eight rings wide, the local
//!   problem the calibration's patch of the subdivided rings plus three, its outer ring held):
//!   - Fig. 5: the contact force F_c against x / L before subdivision;
//!   - Fig. 6 (one-ring) and 7 (two-ring): `K'_m / K_m` that restores F_c after subdivision
//!     with `K'_h` unchanged, and with `K'_h = K_h N / N'` (eq. 5);
//!   - Fig. 8-11: `K'_h / K_h` and `K'_m / K_m` at fixed ratios `K'_m / K'_h` = 4, 1, 0.25,
//!     one- and two-ring (section 3.2.4);
//!   - the stiffening without the table (`K' = K`), and the patch-size convergence (three
//!     against six rings of margin).
//!
//!   CSV files and plots (PNG and SVG) go to `target/bench/` (or `--out DIR`); `--publish`
//!   writes them over the committed ones in `docs/bench/` and `docs/`.
//! - `reference`: the FEM reference of a springs scene's press points (the CSV its
//!   `reference_file` names) from the exact-sphere runs of `springs_reference/run.sh`: per point
//!   and mesh level the force against the sphere's depth below the analytic surface (the mesh's
//!   own first contact corrected to it), interpolated at the reference depths; the finest level's
//!   force, an uncertainty from the last refinement's change, and the device depth with the
//!   scenes' 300 N/m coupling.
//! - `feel`: the scene pressed at each reference point (staircase holds, subdivided and
//!   never subdivided), its force against the reference at the measured sphere depth.
//!
//! Run: `cargo run --release -p haptic-model --example haptic_subdivision -- paper`.

#[path = "../benches/common/mod.rs"]
mod common;
#[path = "springs_reference/organ.rs"]
mod organ;

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{Context as _, anyhow};
use clap::{Parser, Subcommand};
use haptic_model::mass_spring::calibration::{ContactShape, LocalPatch, PATCH_EXTRA_RINGS};
use haptic_model::mass_spring::{SpringSurface, VertexRule};
use plotters::prelude::*;

/// The haptic-subdivision experiment (seed 003, section 3.2) and the organ references.
#[derive(Debug, Parser)]
#[command(name = "haptic_subdivision")]
struct Args {
    #[command(subcommand)]
    run: Run,
}

#[derive(Debug, Subcommand)]
enum Run {
    /// Figures 5-11 of the paper: CSV and plots.
    Paper {
        /// Folder for the CSV files and plots [default: target/bench of the workspace].
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the CSV files into docs/bench/ and the plots into docs/.
        #[arg(long, conflicts_with = "out")]
        publish: bool,
    },
    /// The reference CSV of a springs scene's press points from the FEM runs of
    /// `springs_reference/run.sh` (two or more mesh levels).
    Reference {
        /// lv or hemisphere: the points file `springs_reference/<body>_points.csv`.
        #[arg(long)]
        body: String,
        /// The runs' folder [default: target/springs-reference/<body>].
        #[arg(long)]
        dir: Option<PathBuf>,
        /// Another points file [default: springs_reference/<body>_points.csv].
        #[arg(long)]
        points: Option<PathBuf>,
        /// The mesh levels (hmin, mm, as run.sh names them), coarse to fine.
        #[arg(long, value_delimiter = ',')]
        levels: Vec<String>,
        /// Sphere depths below the analytic surface, mm.
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "0.1,0.25,0.5,0.75,1,1.25,1.5,2,2.5,3,3.5,4"
        )]
        depths: Vec<f64>,
        /// The scenes' virtual coupling stiffness, N/m (for the device depths).
        #[arg(long, default_value_t = 300.0)]
        coupling: f64,
        /// The CSV to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// A springs scene pressed at its reference points (staircase holds), subdivided and not:
    /// force against the reference at the measured sphere depth.
    Feel {
        /// A built-in scene.
        #[arg(long)]
        scene: Option<String>,
        /// A scene file.
        #[arg(long, conflicts_with = "scene")]
        scene_file: Option<PathBuf>,
        /// Device depths, mm.
        #[arg(long, value_delimiter = ',', default_value = "0.25,0.5,1,1.5,2,3,4")]
        depths: Vec<f64>,
        /// Hold at each depth, s (ramps of 0.5 s).
        #[arg(long, default_value_t = 1.5)]
        hold_s: f64,
    },
    /// Recomputes some rows of a scene file's eq. 4 table (`calibration_file`) in place: the
    /// given nodes, or every node with a sample the calibration could not match (its
    /// displacement then repeats the previous one's, plus 1e-9); the key and the other rows are
    /// kept (the table's definition is unchanged: use `haptic-calibrate` when it is not).
    Recalibrate {
        /// The scene file whose `calibration_file` is rewritten.
        #[arg(long)]
        scene_file: PathBuf,
        /// Nodes to recompute [default: the nodes with an unmatched sample].
        #[arg(long, value_delimiter = ',')]
        nodes: Vec<u32>,
        /// Threads [default: the cores].
        #[arg(long)]
        threads: Option<usize>,
    },
}

/// Element size of the paper's mesh, m.
const L_M: f64 = 0.03;
/// `K_h = K_m = 0.06 N/mm`, in N/m.
const K_N_PER_M: f64 = 60.0;
/// x / L of the curves.
fn xs() -> Vec<f64> {
    (1..=40).map(|k| k as f64 * 0.025).collect()
}

fn main() -> anyhow::Result<()> {
    match Args::parse().run {
        Run::Paper { out, publish } => {
            let root = common::workspace_root();
            let (data, plots) = if publish {
                (root.join("docs/bench"), root.join("docs"))
            } else {
                let o = out.unwrap_or_else(common::default_out_dir);
                (o.clone(), o)
            };
            paper(&data, &plots)
        }
        Run::Reference {
            body,
            dir,
            points,
            levels,
            depths,
            coupling,
            out,
        } => {
            let root = common::workspace_root();
            let here = root.join("server/model/examples/springs_reference");
            let dir = dir.unwrap_or_else(|| root.join("target/springs-reference").join(&body));
            organ::reference(
                &points.unwrap_or_else(|| here.join(format!("{body}_points.csv"))),
                &dir,
                &levels,
                &depths,
                coupling,
                &out,
            )
        }
        Run::Feel {
            scene,
            scene_file,
            depths,
            hold_s,
        } => organ::feel(scene.as_deref(), scene_file.as_ref(), &depths, hold_s),
        Run::Recalibrate {
            scene_file,
            nodes,
            threads,
        } => organ::recalibrate(&scene_file, &nodes, threads),
    }
}

/// One curve: label and (x / L, value) points (NaN where there is no value).
type Curve = (String, Vec<(f64, f64)>);

type CsvFile = csv::Writer<std::fs::File>;

fn paper(data: &Path, plots: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(data)?;
    std::fs::create_dir_all(plots)?;
    let surface = SpringSurface::regular_hexagon(L_M, 8);
    let k = (K_N_PER_M, K_N_PER_M);
    let shape = ContactShape::Point;
    let xs = xs();
    let f = fig5(data, plots, &surface, &xs)?;
    // Fig. 6-7, the stiffening, Fig. 8-11.
    let mut fig67 = csv::Writer::from_path(data.join("haptic-subdivision-fig6-7.csv"))?;
    fig67.write_record([
        "rings",
        "x_over_l",
        "km_ratio_kh_unchanged",
        "km_ratio_kh_eq5",
        "force_ratio_unchanged_springs",
    ])?;
    let mut fig811 = csv::Writer::from_path(data.join("haptic-subdivision-fig8-11.csv"))?;
    fig811.write_record([
        "rings",
        "km_over_kh_after",
        "x_over_l",
        "kh_ratio",
        "km_ratio",
    ])?;
    let mut kh_curves: [Vec<Curve>; 2] = Default::default();
    let mut km_curves: [Vec<Curve>; 2] = Default::default();
    for rings in [1u32, 2] {
        let mut p = LocalPatch::new(&surface, 0, rings, VertexRule::Keep, shape, k)?;
        fig67_rings(&mut p, rings, (&xs, &f), &mut fig67, plots)?;
        let r = rings as usize - 1;
        fig811_rings(
            &mut p,
            rings,
            (&xs, &f),
            &mut fig811,
            (&mut kh_curves[r], &mut km_curves[r]),
        )?;
    }
    fig67.flush()?;
    fig811.flush()?;
    fig811_plots(plots, &kh_curves, &km_curves)?;
    println!(
        "wrote {}/haptic-subdivision-fig*.csv and {}/haptic-subdivision-fig*.png/.svg",
        data.display(),
        plots.display()
    );
    Ok(())
}

/// Fig. 5 and the convergence of the local problem: the contact force before subdivision at
/// `xs` (times L), N.
fn fig5(
    data: &Path,
    plots: &Path,
    surface: &SpringSurface,
    xs: &[f64],
) -> anyhow::Result<Vec<f64>> {
    let k = (K_N_PER_M, K_N_PER_M);
    let shape = ContactShape::Point;
    // Fig. 5 and the convergence of the local problem.
    let coarse = |margin: u32| -> anyhow::Result<Vec<f64>> {
        let p = LocalPatch::with_margin(surface, 0, 1, margin, VertexRule::Keep, shape, k)?;
        let mut x = p.coarse_rest();
        xs.iter()
            .map(|r| Ok(p.coarse_press(r * L_M, &mut x)?))
            .collect()
    };
    let f = coarse(PATCH_EXTRA_RINGS)?;
    let f_wide = coarse(6)?;
    let patch_error = f
        .iter()
        .zip(&f_wide)
        .map(|(a, b)| ((a - b) / b).abs())
        .fold(0.0, f64::max);
    println!(
        "Fig. 5: F_c(x = L) = {:.4} N; K_h x = {:.4} N; local problem {} vs 6 rings of margin: max relative difference {:.2e}",
        f[f.len() - 1],
        K_N_PER_M * L_M,
        PATCH_EXTRA_RINGS + 1,
        patch_error
    );
    let mut fig5 = csv::Writer::from_path(data.join("haptic-subdivision-fig5.csv"))?;
    fig5.write_record(["x_over_l", "force_n", "force_n_wide_patch"])?;
    for ((x, a), b) in xs.iter().zip(&f).zip(&f_wide) {
        fig5.write_record([x.to_string(), a.to_string(), b.to_string()])?;
    }
    fig5.flush()?;
    line_plot(
        &plots.join("haptic-subdivision-fig5"),
        "Fig. 5: contact force before subdivision (L = 30 mm, K_h = K_m = 0.06 N/mm)",
        "F_c (N)",
        &[(
            "F_c".into(),
            xs.iter().copied().zip(f.iter().copied()).collect(),
        )],
    )?;
    Ok(f)
}

/// Fig. 6-7 for a `rings` subdivision: the K'_m / K_m restoring the coarse forces `f` at `xs`
/// with K'_h unchanged and with eq. 5, and the stiffening with unchanged springs.
fn fig67_rings(
    p: &mut LocalPatch,
    rings: u32,
    (xs, f): (&[f64], &[f64]),
    fig67: &mut CsvFile,
    plots: &Path,
) -> anyhow::Result<()> {
    let k = (K_N_PER_M, K_N_PER_M);
    let (n, n_after) = p.area_node_counts();
    let eq5 = K_N_PER_M * n as f64 / n_after as f64;
    let mut unchanged = Vec::new();
    let mut kh_fixed = Vec::new();
    let mut kh_eq5 = Vec::new();
    let (mut s1, mut s2) = (1.0, 10.0);
    let mut x1 = p.fine_rest();
    let mut x2 = p.fine_rest();
    let mut x3 = p.fine_rest();
    for (i, &r) in xs.iter().enumerate() {
        let depth = r * L_M;
        let (f_same, _) = p.fine_press(k, depth, &mut x3)?;
        unchanged.push(f_same / f[i]);
        let a = p.match_force(f[i], depth, |s| (K_N_PER_M, s * K_N_PER_M), s1, &mut x1)?;
        kh_fixed.push(a.map_or(f64::NAN, |v| v.0));
        s1 = a.map_or(s1, |v| v.0);
        let b = p.match_force(f[i], depth, |s| (eq5, s * K_N_PER_M), s2, &mut x2)?;
        kh_eq5.push(b.map_or(f64::NAN, |v| v.0));
        s2 = b.map_or(s2, |v| v.0);
        fig67.write_record([
            rings.to_string(),
            r.to_string(),
            kh_fixed[i].to_string(),
            kh_eq5[i].to_string(),
            unchanged[i].to_string(),
        ])?;
    }
    println!(
        "{rings}-ring (N = {n}, N' = {n_after}): K' = K stiffens F_c by {:.0} % at x = 0.1 L, {:.0} % at L (max {:.0} %); K'_m/K_m with K'_h unchanged {:.3} .. {:.3}; with eq. 5 {:.1} at x = {} L, {:.3} at L",
        (unchanged[3] - 1.0) * 100.0,
        (unchanged[unchanged.len() - 1] - 1.0) * 100.0,
        unchanged
            .iter()
            .fold(0.0f64, |m, v| m.max(*v) - 0.0)
            .max(1.0)
            * 100.0
            - 100.0,
        kh_fixed.iter().copied().fold(f64::INFINITY, f64::min),
        kh_fixed.iter().copied().fold(0.0, f64::max),
        kh_eq5
            .iter()
            .copied()
            .find(|v| v.is_finite())
            .unwrap_or(f64::NAN),
        xs[kh_eq5.iter().position(|v| v.is_finite()).unwrap_or(0)],
        kh_eq5[kh_eq5.len() - 1],
    );
    // Log scale: the eq. 5 curve runs to infinity at small x (drawn as log10).
    line_plot(
        &plots.join(format!("haptic-subdivision-fig{}", 5 + rings)),
        &format!(
            "Fig. {}: K'_m / K_m restoring F_c, {} subdivision",
            5 + rings,
            if rings == 1 { "one-ring" } else { "two-ring" }
        ),
        "log10(K'_m / K_m)",
        &[
            (
                "K'_h = K_h N / N' (eq. 5)".into(),
                xs.iter()
                    .copied()
                    .zip(kh_eq5.iter().map(|v| v.log10()))
                    .collect(),
            ),
            (
                "K'_h = K_h".into(),
                xs.iter()
                    .copied()
                    .zip(kh_fixed.iter().map(|v| v.log10()))
                    .collect(),
            ),
        ],
    )?;
    Ok(())
}

/// Fig. 8-11 data for a `rings` subdivision: K'_h / K_h and K'_m / K_m restoring the coarse
/// forces `f` at fixed K'_m / K'_h ratios, appended to `curves` (K'_h, K'_m).
fn fig811_rings(
    p: &mut LocalPatch,
    rings: u32,
    (xs, f): (&[f64], &[f64]),
    fig811: &mut CsvFile,
    (kh_curves, km_curves): (&mut Vec<Curve>, &mut Vec<Curve>),
) -> anyhow::Result<()> {
    for ratio in [4.0, 1.0, 0.25] {
        let mut x = p.fine_rest();
        let mut a = 1.0;
        let mut kh = Vec::new();
        let mut km = Vec::new();
        for (i, &r) in xs.iter().enumerate() {
            let m = p.match_force(
                f[i],
                r * L_M,
                |s| (s * K_N_PER_M, ratio * s * K_N_PER_M),
                a,
                &mut x,
            )?;
            let v = m.map_or(f64::NAN, |m| m.0);
            a = m.map_or(a, |m| m.0);
            kh.push((r, v));
            km.push((r, v * ratio));
            fig811.write_record([
                rings.to_string(),
                ratio.to_string(),
                r.to_string(),
                v.to_string(),
                (v * ratio).to_string(),
            ])?;
        }
        let label = format!("K'_m / K'_h = {ratio}");
        kh_curves.push((label.clone(), kh));
        km_curves.push((label, km));
    }
    Ok(())
}

/// Fig. 8-11 plots and their summary lines.
fn fig811_plots(
    plots: &Path,
    kh_curves: &[Vec<Curve>; 2],
    km_curves: &[Vec<Curve>; 2],
) -> anyhow::Result<()> {
    for rings in [1usize, 2] {
        let which = if rings == 1 { "one-ring" } else { "two-ring" };
        let (fh, fm) = if rings == 1 { (8, 9) } else { (10, 11) };
        line_plot(
            &plots.join(format!("haptic-subdivision-fig{fh}")),
            &format!("Fig. {fh}: K'_h / K_h at fixed K'_m / K'_h, {which}"),
            "K'_h / K_h",
            &kh_curves[rings - 1],
        )?;
        line_plot(
            &plots.join(format!("haptic-subdivision-fig{fm}")),
            &format!("Fig. {fm}: K'_m / K_m at fixed K'_m / K'_h, {which}"),
            "K'_m / K_m",
            &km_curves[rings - 1],
        )?;
        for (label, c) in &kh_curves[rings - 1] {
            let v: Vec<f64> = c.iter().map(|p| p.1).collect();
            println!(
                "{which} {label}: K'_h/K_h {:.3} at x = 0.025 L, min {:.3}, {:.3} at L",
                v[0],
                v.iter().copied().fold(f64::INFINITY, f64::min),
                v[v.len() - 1]
            );
        }
    }
    Ok(())
}

/// DejaVu Sans (the precision benchmark's font, see `benches/precision/plot.rs`).
static DEJAVU_SANS: &[u8] = include_bytes!("../benches/precision/fonts/DejaVuSans.ttf");

fn register_font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            plotters::style::register_font("sans-serif", FontStyle::Normal, DEJAVU_SANS)
                .map_err(|_| "the font is not valid".to_string())
        })
        .clone()
        .map_err(|e| anyhow!(e))
}

/// Curves against x / L, `base.png` and `base.svg`.
fn line_plot(base: &Path, title: &str, ylabel: &str, curves: &[Curve]) -> anyhow::Result<()> {
    register_font()?;
    let finite = curves
        .iter()
        .flat_map(|c| c.1.iter())
        .filter(|p| p.1.is_finite());
    let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
        (lo.min(p.1), hi.max(p.1))
    });
    let pad = 0.08 * (hi - lo.min(0.0)).max(1e-9);
    let (lo, hi) = (lo.min(0.0) - if lo < 0.0 { pad } else { 0.0 }, hi + pad);
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    draw(
        BitMapBackend::new(&png, (720, 480)).into_drawing_area(),
        title,
        ylabel,
        curves,
        (lo, hi),
    )
    .with_context(|| format!("drawing {}", png.display()))?;
    draw(
        SVGBackend::new(&svg, (720, 480)).into_drawing_area(),
        title,
        ylabel,
        curves,
        (lo, hi),
    )
    .with_context(|| format!("drawing {}", svg.display()))?;
    Ok(())
}

fn draw<DB: DrawingBackend>(
    area: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    ylabel: &str,
    curves: &[Curve],
    (lo, hi): (f64, f64),
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    let colours = [BLUE, RED, GREEN, MAGENTA, BLACK];
    area.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
    let mut chart = ChartBuilder::on(&area)
        .caption(title, ("sans-serif", 17))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..1.0, lo..hi)
        .map_err(|e| anyhow!("{e}"))?;
    chart
        .configure_mesh()
        .x_desc("x / L (displacement of node C over the element size)")
        .y_desc(ylabel)
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    for (k, (label, points)) in curves.iter().enumerate() {
        let colour = colours[k % colours.len()];
        let pts: Vec<(f64, f64)> = points.iter().copied().filter(|p| p.1.is_finite()).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
            .map_err(|e| anyhow!("{e}"))?
            .label(label.as_str())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 2, colour.filled())))
            .map_err(|e| anyhow!("{e}"))?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(|e| anyhow!("{e}"))?;
    area.present().map_err(|e| anyhow!("{e}"))?;
    Ok(())
}
