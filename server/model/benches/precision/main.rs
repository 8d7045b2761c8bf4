//! Run time versus error (issue 3, section 4): scenarios x methods x resolutions x settings,
//! one row per run in `precision.csv` and `.json` ([`report`]), and a work-precision plot per
//! scenario, `precision-<scenario>.png` / `.svg` ([`plot`]), and the README-sized plot of the
//! LV press with the shipped scenes and the Pareto front, `precision-lv-probe-readme.png` /
//! `.svg` ([`readme`]).
//!
//! Scenarios, one file each: [`lame`] (thick sphere, analytic), [`cantilever`]
//! (Bisshopp-Drucker), [`lv_probe`] (the probe pressed into the LV, converged static
//! reference), and [`lv_h1`] (the same press on `lv_h1.msh`, run alone). Methods
//! ([`method::methods`]): the static Newton solve; semi-implicit and symplectic Euler at safety
//! factors on the critical step; backward Euler with CG capped at 5, 10 and 20 iterations; all
//! on St. Venant-Kirchhoff, and the corotational and stable Neo-Hookean materials with the
//! static solve, semi-implicit at 0.5 and backward Euler with 20 CG iterations (Lamé and
//! cantilever; `lv-probe` runs the materials with a converged sphere reference, see
//! [`lv_probe::LV_MATERIALS`]).
//!
//! Results and plots go to `target/bench/` (or `--out DIR`); `--publish` writes them over the
//! committed ones (`docs/bench/` and `docs/`). `--replot` redraws the plots from results
//! already written, by default the committed `docs/bench/precision.json` and
//! `precision-lv-h1.json`, and runs nothing. `--help` lists the options.
//!
//! Run: `cargo bench -p haptic-model --bench precision` (hours: the full suite; the LV
//! reference static solve takes minutes the first time, then it is cached in `target/bench/`),
//! `-- --quick` for a subset of about a minute, `-- --scenario NAME` for one scenario.

mod cantilever;
#[path = "../common/mod.rs"]
mod common;
mod lame;
mod lv_h1;
mod lv_probe;
mod method;
mod plot;
mod readme;
mod report;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use clap::{Parser, ValueEnum};

/// Work-precision benchmark: error against wall time per simulated ms, per scenario.
#[derive(Debug, Parser)]
#[command(name = "precision")]
struct Args {
    /// Run only this scenario (its rows are then the only ones in the output files). Without
    /// it: lame, cantilever and lv-probe. lv-h1 is never part of the full run and writes its own
    /// files, precision-lv-h1.*.
    #[arg(long, value_enum)]
    scenario: Option<Run>,
    /// A subset of about a minute (once the LV reference is cached): fewer meshes, methods and
    /// materials, shorter runs.
    #[arg(long)]
    quick: bool,
    /// lv-h1: which rows to run (all, the condensed ones only, or the shipped lv_h1 scenes
    /// only).
    #[arg(long, value_enum, default_value_t = LvH1Rows::All)]
    lv_h1_rows: LvH1Rows,
    /// lv-probe: which rows to run (all, or the mass-spring ones only: a few seconds once the
    /// reference is cached; not with --publish, whose results must be the full run).
    #[arg(long, value_enum, default_value_t = LvProbeRows::All, conflicts_with = "publish")]
    lv_probe_rows: LvProbeRows,
    /// Redraw the plots from results already written and run no scenario: precision.<ext> and
    /// precision-lv-h1.<ext> of --from.
    #[arg(long, conflicts_with_all = ["scenario", "quick"])]
    replot: bool,
    /// --replot: the folder of the results to read [default: docs/bench, the committed ones].
    #[arg(long, requires = "replot")]
    from: Option<PathBuf>,
    /// --replot: read the .csv files instead of the .json files.
    #[arg(long, value_enum, requires = "replot", default_value_t = Format::Json)]
    format: Format,
    /// Folder for results and plots [default: target/bench of the workspace]. A relative path
    /// is taken from the current folder, which under `cargo bench` is server/model.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write results into docs/bench/ and plots into docs/, over the committed ones, instead of
    /// --out. Not with --quick, whose subset would replace the full results.
    #[arg(long, conflicts_with_all = ["out", "quick"])]
    publish: bool,
    /// Passed by `cargo bench` to every harness-less benchmark; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// A scenario `--scenario` can name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Run {
    Lame,
    Cantilever,
    LvProbe,
    LvH1,
}

/// Which rows of `lv-h1` to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LvH1Rows {
    /// Condensed, standard and edge-smoothed rows.
    All,
    /// The condensed rows only.
    Condensed,
    /// The shipped lv_h1 scenes only, as their files configure them.
    Scenes,
}

/// Which rows of `lv-probe` to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LvProbeRows {
    /// The FEM rows and the mass-spring rows.
    All,
    /// The mass-spring rows only (`lv-surface-springs` with and without subdivision).
    MassSpring,
    /// The hybrid rows only (`lv-hybrid`, seed and corrected variants).
    Hybrid,
    /// The contact-model rows only (the built-in `lv` with each probe contact model).
    Contact,
}

/// Results format read by `--replot`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Format {
    Json,
    Csv,
}

/// What the scenarios take from the command line.
pub struct Config {
    /// `--quick`: the subset.
    pub quick: bool,
    /// `--lv-h1-rows`.
    pub lv_h1_rows: LvH1Rows,
    /// `--lv-probe-rows`.
    pub lv_probe_rows: LvProbeRows,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let root = common::workspace_root();
    // Results and plots: published over the committed ones, or into the output folder.
    let (data_dir, plot_dir) = if args.publish {
        (root.join("docs/bench"), root.join("docs"))
    } else {
        let out = args.out.clone().unwrap_or_else(common::default_out_dir);
        (out.clone(), out)
    };
    if args.replot {
        let from = args.from.clone().unwrap_or_else(|| root.join("docs/bench"));
        return replot(&from, args.format, &plot_dir);
    }
    let cfg = Config {
        quick: args.quick,
        lv_h1_rows: args.lv_h1_rows,
        lv_probe_rows: args.lv_probe_rows,
    };
    let commit = common::git_commit();
    let wall = Instant::now();
    let h1_only = args.scenario == Some(Run::LvH1);
    let rows = if h1_only {
        lv_h1::run(&cfg)
    } else {
        let run = |s: Run| args.scenario.is_none_or(|o| o == s);
        let mut rows = Vec::new();
        if run(Run::Lame) {
            lame::run(cfg.quick, &mut rows);
        }
        if run(Run::Cantilever) {
            cantilever::run(cfg.quick, &mut rows);
        }
        if run(Run::LvProbe) {
            lv_probe::run(&cfg, &mut rows);
        }
        rows
    };
    // Results first: a plot that fails must not lose hours of runs.
    let stem = if h1_only {
        "precision-lv-h1"
    } else {
        "precision"
    };
    // Publishing one scenario of the main file replaces that scenario's rows and keeps the
    // others' (with the commits they were measured at); the plots are drawn from all of them.
    let mut rows = rows;
    if args.publish && !h1_only && args.scenario.is_some() {
        let path = data_dir.join("precision.json");
        let kept: Vec<report::Row> = report::read(&path)
            .with_context(|| format!("keeping the other scenarios' rows of {}", path.display()))?
            .into_iter()
            .filter(|old| rows.iter().all(|r| r.scenario != old.scenario))
            .collect();
        println!(
            "publishing: {} rows of the other scenarios kept from {}",
            kept.len(),
            path.display()
        );
        rows.splice(0..0, kept);
    }
    let (csv, json) = report::write_rows(&rows, &commit, &data_dir, stem)?;
    println!(
        "wrote {} rows to {} and {} ({:.1} s)",
        rows.len(),
        csv.display(),
        json.display(),
        wall.elapsed().as_secs_f64()
    );
    report_plot(if h1_only {
        plot::lv_h1(&rows, &plot_dir)?.into_iter().collect()
    } else {
        plot::scenarios(&rows, &plot_dir)?
    });
    readme_plot(&data_dir, Format::Json, &plot_dir)
}

/// The README plot ([`readme::readme`]) from the results in `from`: `precision.<ext>` and, if
/// present, `precision-lv-h1.<ext>` (a missing file is skipped with a note).
fn readme_plot(from: &Path, format: Format, plot_dir: &Path) -> anyhow::Result<()> {
    let ext = match format {
        Format::Json => "json",
        Format::Csv => "csv",
    };
    let mut rows = Vec::new();
    for stem in ["precision", "precision-lv-h1"] {
        let path = from.join(format!("{stem}.{ext}"));
        if path.exists() {
            rows.extend(report::read(&path)?);
        } else {
            eprintln!(
                "{} not found: its rows are not in the README plot",
                path.display()
            );
        }
    }
    report_plot(readme::readme(&rows, plot_dir)?.into_iter().collect());
    Ok(())
}

/// Redraws every plot from the results in `from` into `plot_dir`, running nothing.
fn replot(from: &Path, format: Format, plot_dir: &Path) -> anyhow::Result<()> {
    let ext = match format {
        Format::Json => "json",
        Format::Csv => "csv",
    };
    let main = from.join(format!("precision.{ext}"));
    let rows = report::read(&main)?;
    report_plot(plot::scenarios(&rows, plot_dir)?);
    let h1 = from.join(format!("precision-lv-h1.{ext}"));
    if h1.exists() {
        let rows = report::read(&h1).with_context(|| format!("replotting {}", h1.display()))?;
        report_plot(plot::lv_h1(&rows, plot_dir)?.into_iter().collect());
    } else {
        eprintln!("{} not found: lv-h1 plot skipped", h1.display());
    }
    readme_plot(from, format, plot_dir)
}

/// Prints the plots written.
fn report_plot(bases: Vec<PathBuf>) {
    for base in bases {
        println!("plot {}.png/.svg", base.display());
    }
}
