//! The mass-spring calibrations behind `haptic-calibrate`: computes a scene's tables on every
//! core, with progress, and writes them where the scene reads them, beside the scene file:
//!
//! - the **organ table** (`mass_spring.organ_file`, when the scene gives a `reference_file`):
//!   the contact factor that makes the probe force follow the organ's reference
//!   ([`haptic_model::mass_spring::organ::calibrate_organ`]);
//! - the **subdivision table** (`mass_spring.calibration_file`, when the scene subdivides with
//!   calibrated springs): `K'_h / K_h` keeping the force before and after subdivision (eq. 4 of
//!   Zhang, Payandeh & Dill; [`haptic_model::mass_spring::calibration::calibrate`]).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use haptic_model::ModelError;
use haptic_model::mass_spring::calibration::calibrate;
use haptic_model::mass_spring::organ::{OrganSetup, calibrate_organ};
use haptic_model::scene::{Scene, TableState};

/// Which table a [`TableReport`] (or a progress call) is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TableKind {
    /// The organ table (`mass_spring.organ_file`).
    Organ,
    /// The subdivision table (`mass_spring.calibration_file`).
    Subdivision,
}

impl TableKind {
    /// A short name for messages.
    pub fn name(self) -> &'static str {
        match self {
            Self::Organ => "organ table",
            Self::Subdivision => "subdivision table",
        }
    }

    /// What the table is computed per: "sites" (the organ table's nodes and edge midpoints)
    /// or "nodes".
    pub fn unit(self) -> &'static str {
        match self {
            Self::Organ => "sites",
            Self::Subdivision => "nodes",
        }
    }
}

/// What [`calibrate_scene`] did with one table.
#[derive(Debug, Clone, PartialEq)]
pub struct TableReport {
    /// Which table.
    pub kind: TableKind,
    /// The file written (or found up to date).
    pub path: PathBuf,
    /// Whether the table was computed (false: the file was valid and `force` not given).
    pub computed: bool,
    /// Calibrated nodes (the organ table: sites, [`TableKind::unit`]).
    pub nodes: usize,
    /// Wall time, s.
    pub seconds: f64,
    /// Smallest and largest factor in the table (`K'_h / K_h`, or the contact factor).
    pub factor_range: (f64, f64),
}

/// Where [`calibrate_scene`] writes: `None` for a table beside the scene file (its scene
/// field's name); a built-in scene needs both paths it uses.
#[derive(Debug, Clone, Copy, Default)]
pub struct Outputs<'a> {
    /// The subdivision table's file.
    pub subdivision: Option<&'a Path>,
    /// The organ table's file.
    pub organ: Option<&'a Path>,
}

/// Computes the calibration tables `scene` needs (module documentation) and writes each to
/// its output (default: its file beside the scene file), unless the table there is already
/// valid and `force` is false. `progress(table, done, total, elapsed_s)` is called after each
/// node.
///
/// # Errors
/// [`ModelError::SceneField`] when the scene is not a mass-spring scene or needs no table,
/// or when a built-in scene is given without the output paths; the calibrations' errors;
/// [`ModelError::Io`] when a file cannot be written.
pub fn calibrate_scene(
    scene: &Scene,
    out: Outputs<'_>,
    threads: usize,
    force: bool,
    progress: &(dyn Fn(TableKind, usize, usize, f64) + Sync),
) -> Result<Vec<TableReport>, ModelError> {
    let ms = scene.mass_spring.as_ref().ok_or_else(|| {
        ModelError::field(
            "model.family",
            "only a \"mass-spring\" scene has calibration tables",
        )
    })?;
    let subdivides = !matches!(ms.table, TableState::NotNeeded);
    if !subdivides && ms.organ.is_none() {
        return Err(ModelError::field(
            "mass_spring.springs",
            "the scene has no reference_file and does not subdivide with calibrated springs (rings = 0 or springs = \"unchanged\"): nothing to calibrate",
        ));
    }
    let mut reports = Vec::new();
    if ms.organ.is_some() {
        reports.push(organ_table(scene, out, threads, force, progress)?);
    }
    if subdivides {
        reports.push(subdivision_table(scene, out, threads, force, progress)?);
    }
    Ok(reports)
}

/// The organ table of [`calibrate_scene`].
fn organ_table(
    scene: &Scene,
    out: Outputs<'_>,
    threads: usize,
    force: bool,
    progress: &(dyn Fn(TableKind, usize, usize, f64) + Sync),
) -> Result<TableReport, ModelError> {
    let Some((ms, organ)) = scene
        .mass_spring
        .as_ref()
        .and_then(|ms| Some((ms, ms.organ.as_ref()?)))
    else {
        return Err(ModelError::field(
            "mass_spring.organ_file",
            "not a mass-spring scene with an organ table",
        ));
    };
    let target = |given: Option<&Path>, beside: Option<&PathBuf>, field: &str, flag: &str| {
        given
            .map(Path::to_path_buf)
            .or_else(|| beside.cloned())
            .ok_or_else(|| {
                ModelError::field(
                    field,
                    format!(
                        "a built-in scene's table is compiled into the library: give {flag} FILE"
                    ),
                )
            })
    };
    let path = target(
        out.organ,
        organ.path.as_ref(),
        "mass_spring.organ_file",
        "--organ-out",
    )?;
    let start = Instant::now();
    let report = match (&organ.table, force || out.organ.is_some()) {
        (Ok(t), false) => TableReport {
            kind: TableKind::Organ,
            path,
            computed: false,
            nodes: t.site_count(),
            seconds: 0.0,
            factor_range: organ_range(t),
        },
        _ => {
            let subdivision_table = match &ms.table {
                TableState::Ready(t) => Some(t),
                _ => None,
            };
            let setup = OrganSetup {
                params: &ms.params,
                probe: scene.probe,
                integrator: &scene.integrator,
                subdivision_table,
            };
            let table = calibrate_organ(
                &ms.surface,
                setup,
                (&organ.reference, organ.axis),
                threads,
                &|done, total| {
                    progress(TableKind::Organ, done, total, start.elapsed().as_secs_f64())
                },
            )?;
            let description = table_description(
                scene,
                format!(
                    "probe radius {} m; reference {} along ({}, {}, {})",
                    scene.probe.radius_m,
                    organ
                        .reference
                        .points()
                        .iter()
                        .map(|q| q.name.as_str())
                        .collect::<Vec<_>>()
                        .join(" "),
                    organ.axis.x,
                    organ.axis.y,
                    organ.axis.z,
                ),
            );
            write_atomically(&path, &table.to_text(&description))?;
            TableReport {
                kind: TableKind::Organ,
                path,
                computed: true,
                nodes: table.site_count(),
                seconds: start.elapsed().as_secs_f64(),
                factor_range: organ_range(&table),
            }
        }
    };
    Ok(report)
}

/// A calibration table's description line: the scene, its surface and spring constants, then
/// `specifics` (what else the table depends on), and how to recompute it.
fn table_description(scene: &Scene, specifics: String) -> String {
    let Some(ms) = scene.mass_spring.as_ref() else {
        return specifics;
    };
    let p = &ms.params;
    format!(
        "scene {}: {} nodes, {} triangles; K_h = {} N/m, K_m = {} N/m, {specifics}\nwritten by haptic-calibrate; recompute with `haptic-calibrate SCENE_FILE`",
        scene.name,
        ms.surface.node_count(),
        ms.surface.triangle_count(),
        p.home_spring_n_per_m,
        p.mesh_spring_n_per_m,
    )
}

/// The subdivision table of [`calibrate_scene`].
fn subdivision_table(
    scene: &Scene,
    out: Outputs<'_>,
    threads: usize,
    force: bool,
    progress: &(dyn Fn(TableKind, usize, usize, f64) + Sync),
) -> Result<TableReport, ModelError> {
    let Some(ms) = scene.mass_spring.as_ref() else {
        return Err(ModelError::field("model.family", "not a mass-spring scene"));
    };
    let path = match (out.subdivision, &ms.calibration_path) {
        (Some(p), _) => p.to_path_buf(),
        (None, Some(p)) => p.clone(),
        (None, None) => {
            return Err(ModelError::field(
                "mass_spring.calibration_file",
                "a built-in scene's table is compiled into the library: give --out FILE",
            ));
        }
    };
    let start = Instant::now();
    if !force
        && out.subdivision.is_none()
        && let TableState::Ready(t) = &ms.table
    {
        return Ok(TableReport {
            kind: TableKind::Subdivision,
            path,
            computed: false,
            nodes: calibrated_nodes(t),
            seconds: 0.0,
            factor_range: scale_range(t),
        });
    }
    let table = calibrate(
        &ms.surface,
        &ms.params,
        ms.contact,
        threads,
        &|done, total| {
            progress(
                TableKind::Subdivision,
                done,
                total,
                start.elapsed().as_secs_f64(),
            )
        },
    )?;
    let p = &ms.params;
    let description = table_description(
        scene,
        format!(
            "K'_m/K'_h = {}, {} ring(s), vertex rule {}, contact {:?}",
            p.subdivision.km_over_kh_after,
            p.subdivision.rings,
            p.subdivision.vertex_rule.name(),
            ms.contact,
        ),
    );
    write_atomically(&path, &table.to_text(&description))?;
    Ok(TableReport {
        kind: TableKind::Subdivision,
        nodes: calibrated_nodes(&table),
        factor_range: scale_range(&table),
        path,
        computed: true,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Writes `text` to `path` through a temporary file beside it.
fn write_atomically(path: &Path, text: &str) -> Result<(), ModelError> {
    let io = |source| ModelError::Io {
        path: path.display().to_string(),
        source,
    };
    let tmp = path.with_extension("csv.tmp");
    std::fs::File::create(&tmp)
        .and_then(|mut f| f.write_all(text.as_bytes()))
        .map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

fn calibrated_nodes(t: &haptic_model::mass_spring::CalibrationTable) -> usize {
    (0..t.node_count() as u32)
        .filter(|&i| t.node(i).is_some())
        .count()
}

fn scale_range(t: &haptic_model::mass_spring::CalibrationTable) -> (f64, f64) {
    (0..t.node_count() as u32)
        .filter_map(|i| t.node(i))
        .flat_map(|r| r.kh_scale)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), a| {
            (lo.min(a), hi.max(a))
        })
}

fn organ_range(t: &haptic_model::mass_spring::OrganTable) -> (f64, f64) {
    (0..t.site_count() as u32)
        .filter_map(|i| t.row(i))
        .flat_map(|r| r.factor.iter().chain(&r.factor_subdivided).copied())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), a| {
            (lo.min(a), hi.max(a))
        })
}
