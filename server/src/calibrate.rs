//! The mass-spring calibration behind `haptic-calibrate`: computes the spring-constant lookup
//! table of a scene ([`haptic_model::mass_spring::calibration::calibrate`], on every core, with
//! progress) and writes it where the scene reads it, beside the scene file.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use haptic_model::ModelError;
use haptic_model::mass_spring::calibration::calibrate;
use haptic_model::scene::{Scene, TableState};

/// What [`calibrate_scene`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrateReport {
    /// The table file written (or found up to date).
    pub path: PathBuf,
    /// Whether the table was computed (false: the file was valid and `force` not given).
    pub computed: bool,
    /// Calibrated nodes.
    pub nodes: usize,
    /// Wall time, s.
    pub seconds: f64,
    /// Smallest and largest `K'_h / K_h` in the table.
    pub scale_range: (f64, f64),
}

/// Computes the calibration table of `scene` and writes it to `out` (default: the scene's
/// `calibration_file` beside the scene file), unless the table there is already valid and
/// `force` is false. `progress(done, total, elapsed_s)` is called after each node.
///
/// # Errors
/// [`ModelError::SceneField`] when the scene is not a mass-spring scene that subdivides with
/// calibrated springs, or when a built-in scene is given without `out`; the calibration's
/// errors; [`ModelError::Io`] when the file cannot be written.
pub fn calibrate_scene(
    scene: &Scene,
    out: Option<&Path>,
    threads: usize,
    force: bool,
    progress: &(dyn Fn(usize, usize, f64) + Sync),
) -> Result<CalibrateReport, ModelError> {
    let ms = scene.mass_spring.as_ref().ok_or_else(|| {
        ModelError::field(
            "model.family",
            "only a \"mass-spring\" scene has a calibration table",
        )
    })?;
    if matches!(ms.table, TableState::NotNeeded) {
        return Err(ModelError::field(
            "mass_spring.springs",
            "the scene does not subdivide with calibrated springs (rings = 0 or springs = \"unchanged\"): nothing to calibrate",
        ));
    }
    let path = match (out, &ms.calibration_path) {
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
        && out.is_none()
        && let TableState::Ready(t) = &ms.table
    {
        return Ok(CalibrateReport {
            path,
            computed: false,
            nodes: (0..t.node_count() as u32)
                .filter(|&i| t.node(i).is_some())
                .count(),
            seconds: 0.0,
            scale_range: scale_range(t),
        });
    }
    let table = calibrate(
        &ms.surface,
        &ms.params,
        ms.contact,
        threads,
        &|done, total| progress(done, total, start.elapsed().as_secs_f64()),
    )?;
    let p = &ms.params;
    let description = format!(
        "scene {}: {} nodes, {} triangles; K_h = {} N/m, K_m = {} N/m, K'_m/K'_h = {}, {} ring(s), vertex rule {}, contact {:?}\nwritten by haptic-calibrate; recompute with `haptic-calibrate SCENE_FILE`",
        scene.name,
        ms.surface.node_count(),
        ms.surface.triangle_count(),
        p.home_spring_n_per_m,
        p.mesh_spring_n_per_m,
        p.subdivision.km_over_kh_after,
        p.subdivision.rings,
        p.subdivision.vertex_rule.name(),
        ms.contact,
    );
    let text = table.to_text(&description);
    let io = |source| ModelError::Io {
        path: path.display().to_string(),
        source,
    };
    let tmp = path.with_extension("csv.tmp");
    std::fs::File::create(&tmp)
        .and_then(|mut f| f.write_all(text.as_bytes()))
        .map_err(io)?;
    std::fs::rename(&tmp, &path).map_err(io)?;
    Ok(CalibrateReport {
        nodes: (0..table.node_count() as u32)
            .filter(|&i| table.node(i).is_some())
            .count(),
        scale_range: scale_range(&table),
        path,
        computed: true,
        seconds: start.elapsed().as_secs_f64(),
    })
}

fn scale_range(t: &haptic_model::mass_spring::CalibrationTable) -> (f64, f64) {
    (0..t.node_count() as u32)
        .filter_map(|i| t.node(i))
        .flat_map(|r| r.kh_scale)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), a| {
            (lo.min(a), hi.max(a))
        })
}
