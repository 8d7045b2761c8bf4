//! One row per benchmark run ([`Row`]), written to `<stem>.csv` and `<stem>.json` and read
//! back (for `--replot`) with serde: the `csv` crate and `serde_json`. The columns are those of
//! the committed `docs/bench/precision.csv`, so its older files still read; a number that was
//! not measured (NaN) is an empty CSV field and a JSON `null`.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write as _};
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use haptic_model::element::StrainSmoothing;
use haptic_model::material::MaterialModel;
use haptic_model::mesh::TetMesh;
use serde::{Deserialize, Serialize};

use crate::common::TickTimes;

/// The work-precision scenarios a row belongs to (`lv-h1` rows are `lv-probe` rows on another
/// mesh).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scenario {
    /// Thick sphere under inner pressure against the analytic Lamé solution.
    Lame,
    /// Cantilever under a tip load against Bisshopp-Drucker's elastica.
    Cantilever,
    /// The probe pressed into the LV against a converged static reference.
    LvProbe,
}

impl Scenario {
    /// The name in the results and plot file names.
    pub fn name(self) -> &'static str {
        match self {
            Self::Lame => "lame",
            Self::Cantilever => "cantilever",
            Self::LvProbe => "lv-probe",
        }
    }
}

/// Element technology of a row.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Model {
    /// Linear tetrahedra.
    Fem,
    /// Quadratic (10-node) tetrahedra.
    FemT10,
    /// Linear tetrahedra with edge-based strain smoothing.
    FemEs,
    /// The mass-spring surface (seed 003), `tets` = 0.
    MassSpring,
    /// The seeds' hybrid model (FEM core + meshfree particle layer), `tets` = the core's.
    Hybrid,
}

/// One benchmark run: a column per field, in this order.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Row {
    pub scenario: Scenario,
    pub model: Model,
    /// Material model (scene name).
    pub material: String,
    pub integrator: String,
    /// Curve label in the plot: integrator plus the setting that distinguishes curves.
    pub method: String,
    pub nodes: usize,
    pub tets: usize,
    pub settings: String,
    #[serde(with = "missing")]
    pub step_p50_us: f64,
    #[serde(with = "missing")]
    pub step_p99_us: f64,
    #[serde(with = "missing")]
    pub step_max_us: f64,
    #[serde(with = "missing")]
    pub realtime_factor: f64,
    /// Relative L2 displacement error (`lame`); `lv-probe` (St. Venant-Kirchhoff rows): the
    /// surface-displacement error at the sample points, the larger of the 0.5 and 1 mm holds.
    #[serde(with = "missing")]
    pub rel_l2_error: f64,
    /// Largest nodal displacement error (`lame`), or largest sample-point error (`lv-probe`), m.
    #[serde(with = "missing")]
    pub max_nodal_error_m: f64,
    #[serde(with = "missing")]
    pub probe_force_error: f64,
    /// `lv-probe`: the force reference's relative uncertainty (largest over its depths); missing
    /// in older files.
    #[serde(with = "missing", default = "not_measured")]
    pub force_reference_uncertainty: f64,
    /// `lv-probe`: the force is within the reference's uncertainty at every depth, so the error
    /// is shown as "below uncertainty" (and plotted at the uncertainty), not as a number.
    #[serde(default)]
    pub force_below_uncertainty: bool,
    #[serde(with = "missing")]
    pub observable_error: f64,
    pub observable: String,
    pub reference: String,
    pub stable: bool,
    /// Commit of the run; set by [`write_rows`] unless kept from an earlier file.
    pub commit: String,
}

/// The value of a column that older files lack: not measured.
fn not_measured() -> f64 {
    f64::NAN
}

/// NaN (not measured) as `None`: an empty CSV field, a JSON `null`; and back.
mod missing {
    use serde::{Deserialize as _, Deserializer, Serialize as _, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        v.is_finite().then_some(*v).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }
}

impl Row {
    /// A row of `method` on `mesh`; quadratic elements get their own curves in the plots
    /// (method suffix " T10").
    pub fn new(scenario: Scenario, method: String, integrator: &str, mesh: &TetMesh) -> Self {
        let quadratic = mesh.is_quadratic();
        Self {
            nodes: mesh.node_count(),
            tets: mesh.tet_count(),
            model: if quadratic { Model::FemT10 } else { Model::Fem },
            ..Self::blank(
                scenario,
                if quadratic {
                    format!("{method} T10")
                } else {
                    method
                },
                integrator,
            )
        }
    }

    /// A row with no mesh and no results yet.
    pub fn blank(scenario: Scenario, method: String, integrator: &str) -> Self {
        Self {
            scenario,
            model: Model::Fem,
            material: MaterialModel::StVenantKirchhoff.scene_name().into(),
            integrator: integrator.into(),
            method,
            nodes: 0,
            tets: 0,
            settings: String::new(),
            step_p50_us: f64::NAN,
            step_p99_us: f64::NAN,
            step_max_us: f64::NAN,
            realtime_factor: f64::NAN,
            rel_l2_error: f64::NAN,
            max_nodal_error_m: f64::NAN,
            probe_force_error: f64::NAN,
            force_reference_uncertainty: f64::NAN,
            force_below_uncertainty: false,
            observable_error: f64::NAN,
            observable: String::new(),
            reference: String::new(),
            stable: false,
            commit: String::new(),
        }
    }

    /// Sets the material column.
    pub fn material(mut self, model: MaterialModel) -> Self {
        self.material = model.scene_name().into();
        self
    }

    /// Marks a row of edge-smoothed linear elements: method suffix " ES" (its own curve in the
    /// plots) and model `fem-es`.
    pub fn smoothed(mut self, smoothing: StrainSmoothing) -> Self {
        if smoothing != StrainSmoothing::None {
            self.method = format!("{} ES", self.method);
            self.model = Model::FemEs;
        }
        self
    }

    /// Tick time percentiles and the real-time factor for servo ticks of `tick_s`.
    pub fn set_times(&mut self, ticks: &TickTimes, tick_s: f64) {
        let p = ticks.percentiles();
        self.step_p50_us = p.p50_us;
        self.step_p99_us = p.p99_us;
        self.step_max_us = p.max_us;
        self.realtime_factor = tick_s * 1e6 / p.p50_us;
    }

    /// The time of a static solve (one measurement: p50 = p99 = max), us.
    pub fn set_solve_time(&mut self, us: f64) {
        (self.step_p50_us, self.step_p99_us, self.step_max_us) = (us, us, us);
    }

    /// The error the scenario's plot shows; an `lv-probe` force below the reference's
    /// uncertainty at every depth is drawn at the uncertainty.
    pub fn plot_error(&self) -> f64 {
        match self.scenario {
            Scenario::Lame => self.rel_l2_error,
            Scenario::Cantilever => self.observable_error,
            Scenario::LvProbe if self.force_below_uncertainty => self.force_reference_uncertainty,
            Scenario::LvProbe => self.probe_force_error,
        }
    }

    /// The probe-force error as text: `"below uncertainty (+-U %)"` or `"E % (+-U %)"`, or the
    /// plain percentage where the reference has no uncertainty.
    pub fn force_error_text(&self) -> String {
        let u = self.force_reference_uncertainty;
        if self.force_below_uncertainty {
            format!("below uncertainty (+-{:.1} %)", 100.0 * u)
        } else if u.is_finite() {
            format!(
                "{:.1} % (+-{:.1} %)",
                100.0 * self.probe_force_error,
                100.0 * u
            )
        } else {
            format!("{:.1} %", 100.0 * self.probe_force_error)
        }
    }

    /// One line of the console table.
    pub fn print(&self) {
        println!(
            "{:<10} {:<40} {:>6} {:>6} {:<30} p50 {:>9.1} us p99 {:>9.1} us RTx {:>7.2} L2 {:>9.3e} max {:>9.3e} m force {} obs {:>9.3e} {} | {} {}",
            self.scenario.name(),
            self.method,
            self.nodes,
            self.tets,
            self.settings,
            self.step_p50_us,
            self.step_p99_us,
            self.realtime_factor,
            self.rel_l2_error,
            self.max_nodal_error_m,
            self.force_error_text(),
            self.observable_error,
            self.observable,
            self.reference,
            if self.stable { "stable" } else { "UNSTABLE" }
        );
    }
}

/// Writes `rows` to `dir/<stem>.csv` and `dir/<stem>.json`, each row without a commit marked
/// with `commit` (rows kept from an earlier file keep theirs); returns the two paths.
///
/// # Errors
/// Creating the folder or writing either file.
pub fn write_rows(
    rows: &[Row],
    commit: &str,
    dir: &Path,
    stem: &str,
) -> anyhow::Result<(PathBuf, PathBuf)> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let rows: Vec<Row> = rows
        .iter()
        .map(|r| Row {
            commit: if r.commit.is_empty() {
                commit.into()
            } else {
                r.commit.clone()
            },
            ..r.clone()
        })
        .collect();
    let csv_path = dir.join(format!("{stem}.csv"));
    let mut csv = csv::Writer::from_path(&csv_path)
        .with_context(|| format!("creating {}", csv_path.display()))?;
    for r in &rows {
        csv.serialize(r)?;
    }
    csv.flush()?;
    let json_path = dir.join(format!("{stem}.json"));
    let mut json = BufWriter::new(
        File::create(&json_path).with_context(|| format!("creating {}", json_path.display()))?,
    );
    serde_json::to_writer_pretty(&mut json, &rows)?;
    json.write_all(b"\n")?;
    json.flush()?;
    Ok((csv_path, json_path))
}

/// Reads the rows of a results file written by [`write_rows`] (or committed in `docs/bench/`): JSON
/// or CSV by the file's extension.
///
/// # Errors
/// Another extension, an unreadable file, or a row that does not parse.
pub fn read(path: &Path) -> anyhow::Result<Vec<Row>> {
    let context = || format!("reading {}", path.display());
    match path.extension().and_then(|e| e.to_str()) {
        Some("json") => {
            let file = File::open(path).with_context(context)?;
            serde_json::from_reader(BufReader::new(file)).with_context(context)
        }
        Some("csv") => csv::Reader::from_path(path)
            .with_context(context)?
            .deserialize()
            .collect::<Result<_, _>>()
            .with_context(context),
        _ => bail!("{}: expected a .json or .csv file", path.display()),
    }
}
