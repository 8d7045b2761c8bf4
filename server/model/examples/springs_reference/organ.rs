//! The organ side of `haptic_subdivision`: the FEM reference of a mass-spring scene at its press
//! points (`reference`, from the runs of `run.sh` beside this file) and how the scene's probe
//! force follows it (`feel`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context as _, anyhow, bail};
use haptic_model::DVec3;
use haptic_model::body::SoftBody;
use haptic_model::indent::{IndentParams, Indenter, contact_distance};
use haptic_model::mass_spring::calibration::{
    CalibrationTable, NodeCalibration, calibrate_node_with, surface_contact_rest,
};
use haptic_model::mass_spring::organ::REFERENCE_COLUMNS;
use haptic_model::mass_spring::{MassSpringBody, OrganReference};
use haptic_model::press::{self, HoldParams, PressLine};
use haptic_model::scene::{Scene, load_builtin, load_scene_file};

/// A press point of `lv_points.csv` / `hemisphere_points.csv`.
#[derive(Debug, Clone)]
pub struct Point {
    pub name: String,
    pub position_m: DVec3,
    pub direction: DVec3,
}

/// Reads a points file (`name,x_mm,y_mm,z_mm,dx,dy,dz`, `#` comments).
pub fn read_points(path: &Path) -> anyhow::Result<Vec<Point>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}", path.display()))?;
    let mut out = Vec::new();
    for line in text.lines().filter(|l| !l.starts_with('#')).skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 7 {
            bail!("{}: bad line `{line}`", path.display());
        }
        let v: Vec<f64> = f[1..]
            .iter()
            .map(|s| s.trim().parse())
            .collect::<Result<_, _>>()?;
        out.push(Point {
            name: f[0].to_string(),
            position_m: DVec3::new(v[0], v[1], v[2]) * 1e-3,
            direction: DVec3::new(v[3], v[4], v[5]).normalize(),
        });
    }
    Ok(out)
}

/// Reads an `indent.csv` (`depth,fx,fy,fz,contact_radius`, depth in the scene's unit).
fn read_indent(path: &Path, unit_m: f64) -> anyhow::Result<Vec<(f64, DVec3)>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}", path.display()))?;
    text.lines()
        .skip(1)
        .map(|l| {
            let v: Vec<f64> = l
                .split(',')
                .map(|s| s.trim().parse())
                .collect::<Result<_, _>>()?;
            Ok((v[0] * unit_m, DVec3::new(v[1], v[2], v[3])))
        })
        .collect()
}

/// Quadratic (three-point Lagrange) interpolation of `(x, y)` points at `x`, through the
/// bracketing pair and its nearer neighbour; `None` outside.
fn lagrange(pts: &[(f64, f64)], x: f64) -> Option<f64> {
    let n = pts.len();
    if n < 3 || x < pts[0].0 || x > pts[n - 1].0 {
        return None;
    }
    let i = pts.partition_point(|p| p.0 < x).clamp(1, n - 1);
    let start = if i == 1 {
        0
    } else if i + 1 == n || (x - pts[i - 2].0) < (pts[i + 1].0 - x) {
        i - 2
    } else {
        i - 1
    };
    let p = &pts[start..start + 3];
    Some(
        (0..3)
            .map(|a| {
                let l: f64 = (0..3)
                    .filter(|&b| b != a)
                    .map(|b| (x - p[b].0) / (p[a].0 - p[b].0))
                    .product();
                l * p[a].1
            })
            .sum(),
    )
}

/// One mesh level's curve at a point: `(analytic sphere depth m, |F| N, F along the press N)`.
fn level_curve(dir: &Path, point: &Point, hmin: &str) -> anyhow::Result<Vec<(f64, f64, f64)>> {
    let tag = format!("{}_{hmin}", point.name);
    let scene = load_scene_file(&dir.join(format!("{tag}.toml")))?;
    let fem = scene.fem_model()?;
    let r = scene.probe.radius_m;
    let indenter = Indenter {
        radius_m: r,
        from_m: point.position_m - point.direction * (r + 1e-3),
        direction: point.direction,
    };
    // indent.csv's depth zero is the mesh's first contact, `t0` along the line from the start;
    // the analytic surface's is 1 mm.
    let t0 = contact_distance(&fem, &scene.touchable, &indenter, &IndentParams::default())?;
    let offset = t0 - 1e-3;
    let rows = read_indent(
        &dir.join(format!("indent_{tag}/indent.csv")),
        scene.length_unit_m,
    )?;
    eprintln!(
        "  {tag}: {} nodes, first contact {:+.4} mm from the analytic surface, {} depths",
        scene.mesh.node_count(),
        offset * 1e3,
        rows.len()
    );
    // The mesh's first contact carries no force: the curve starts there (a mesh touched a
    // little after the analytic surface still gives the first reference depths).
    Ok(std::iter::once((offset, 0.0, 0.0))
        .chain(
            rows.iter()
                .map(|&(s, f)| (s + offset, f.length(), -f.dot(point.direction))),
        )
        .collect())
}

/// The `reference` subcommand: the reference CSV of the points at `depths_mm` (analytic sphere
/// depths) from the runs in `dir` at the mesh levels `levels` (coarse to fine).
pub fn reference(
    points_csv: &Path,
    dir: &Path,
    levels: &[String],
    depths_mm: &[f64],
    coupling_n_per_m: f64,
    out: &Path,
) -> anyhow::Result<()> {
    let points = read_points(points_csv)?;
    let mut text = String::new();
    writeln!(
        text,
        "# FEM reference of the points of {} (stable neo-Hookean, E = 14.5 kPa, nu = 0.45; exact rigid sphere, static; quadratic tetrahedra refined under each point, hmin {} mm)",
        points_csv
            .file_name()
            .map_or(String::new(), |n| n.to_string_lossy().into()),
        levels.join(" / ")
    )?;
    writeln!(
        text,
        "# written by `haptic_subdivision reference` from server/model/examples/springs_reference/run.sh; force_n is the finest level's force magnitude, uncertainty_n |finest - coarser| x {UNCERTAINTY_FACTOR} (module docs), device_depth_mm the sphere depth plus the {coupling_n_per_m} N/m coupling's stretch"
    )?;
    writeln!(
        text,
        "{REFERENCE_COLUMNS},{}",
        levels
            .iter()
            .map(|h| format!("force_hmin_{h}_n"))
            .collect::<Vec<_>>()
            .join(",")
    )?;
    for p in &points {
        let curves: Vec<Vec<(f64, f64, f64)>> = levels
            .iter()
            .map(|h| level_curve(dir, p, h))
            .collect::<anyhow::Result<_>>()?;
        for &d in depths_mm {
            let s = d * 1e-3;
            let at = |c: &[(f64, f64, f64)], pick: fn(&(f64, f64, f64)) -> f64| {
                let pts: Vec<(f64, f64)> = c.iter().map(|q| (q.0, pick(q))).collect();
                lagrange(&pts, s)
                    .ok_or_else(|| anyhow!("{}: depth {d} mm outside the solved depths", p.name))
            };
            let forces: Vec<f64> = curves
                .iter()
                .map(|c| at(c, |q| q.1))
                .collect::<anyhow::Result<_>>()?;
            let fine = curves.last().context("no level")?;
            let along = at(fine, |q| q.2)?;
            let f = *forces.last().context("no level")?;
            let unc = if forces.len() > 1 {
                UNCERTAINTY_FACTOR * (f - forces[forces.len() - 2]).abs()
            } else {
                0.0
            };
            let q = p.position_m * 1e3;
            writeln!(
                text,
                "{},{:.6},{:.6},{:.6},{:.9},{:.9},{:.9},{d},{f:.6e},{unc:.3e},{:.6},{}",
                p.name,
                q.x,
                q.y,
                q.z,
                p.direction.x,
                p.direction.y,
                p.direction.z,
                d + along / coupling_n_per_m * 1e3,
                forces
                    .iter()
                    .map(|f| format!("{f:.6e}"))
                    .collect::<Vec<_>>()
                    .join(",")
            )?;
        }
    }
    OrganReference::parse(&text, "generated").context("the generated reference")?;
    std::fs::write(out, &text).with_context(|| format!("{}", out.display()))?;
    println!("wrote {}", out.display());
    Ok(())
}

/// The uncertainty of the two-level reference in units of the last level's change (module
/// documentation of the script: on the lv-probe line the forces kept falling by about the
/// same step at each refinement, so the finest level is taken to be about two steps off).
pub const UNCERTAINTY_FACTOR: f64 = 2.0;

/// What one press point felt like: per depth `(sphere depth m, force N, reference N at that
/// sphere depth, steadiness)`.
pub struct PointFeel {
    pub name: String,
    pub rows: Vec<(f64, f64, f64, f64)>,
}

/// Presses `body_of()` at every point of `reference` along its line to each of `depths_m`
/// (device depths; staircase with `params`), and reads the reference at the measured sphere
/// depths.
pub fn press_points(
    body_of: &dyn Fn() -> anyhow::Result<Box<dyn SoftBody>>,
    reference: &OrganReference,
    depths_m: &[f64],
    params: &HoldParams,
) -> anyhow::Result<Vec<PointFeel>> {
    let mut out = Vec::new();
    for p in reference.points() {
        let mut body = body_of()?;
        let info = body.info();
        let line = PressLine::at_surface_point(p.position_m, p.direction, info.probe_radius_m);
        let (holds, _) = press::staircase(body.as_mut(), &line, depths_m, params, info.tick_s)?;
        out.push(PointFeel {
            name: p.name.clone(),
            rows: holds
                .iter()
                .map(|h| {
                    (
                        h.sphere_depth_m,
                        h.force_n,
                        p.force_at(h.sphere_depth_m),
                        h.steadiness(),
                    )
                })
                .collect(),
        });
    }
    Ok(out)
}

/// The scene's mass-spring body with `rings` overriding its subdivision (0: never subdivide).
pub fn body_with_rings(scene: &Scene, rings: Option<u32>) -> anyhow::Result<Box<dyn SoftBody>> {
    let ms = scene.mass_spring.as_ref().context("a mass-spring scene")?;
    let mut params = ms.params;
    if let Some(r) = rings {
        params.subdivision.rings = r;
    }
    let table = if params.subdivision.rings == 0 {
        None
    } else {
        ms.table()?
    };
    let mut body = MassSpringBody::new(
        ms.surface.clone(),
        &params,
        table,
        scene.probe,
        &scene.integrator,
        &scene.name,
    )?;
    if let Some(o) = &ms.organ {
        body = body.with_organ_table(o.table()?)?;
    }
    Ok(Box::new(body))
}

/// The `feel` subcommand: the scene pressed at its reference points, subdivided and not.
pub fn feel(
    scene: Option<&str>,
    scene_file: Option<&PathBuf>,
    depths_mm: &[f64],
    hold_s: f64,
) -> anyhow::Result<()> {
    let scene = match (scene, scene_file) {
        (_, Some(f)) => load_scene_file(f)?,
        (Some(n), None) => load_builtin(n)?,
        (None, None) => bail!("give --scene or --scene-file"),
    };
    let ms = scene.mass_spring.as_ref().context("a mass-spring scene")?;
    let organ = ms
        .organ
        .as_ref()
        .context("the scene has no reference_file")?;
    let depths: Vec<f64> = depths_mm.iter().map(|d| d * 1e-3).collect();
    let params = HoldParams {
        ramp_s: 0.5,
        hold_s,
        average_s: hold_s * 2.0 / 3.0,
    };
    for rings in [None, Some(0)] {
        let label = match rings {
            None => format!("{} ring(s), subdivided", ms.params.subdivision.rings),
            Some(_) => "never subdivided (rings = 0)".to_string(),
        };
        println!("== {} {label}", scene.name);
        let feel = press_points(
            &|| body_with_rings(&scene, rings),
            &organ.reference,
            &depths,
            &params,
        )?;
        let mut worst: f64 = 0.0;
        let mut unsteady: f64 = 0.0;
        for p in &feel {
            let cells: Vec<String> = p
                .rows
                .iter()
                .map(|&(s, f, r, st)| {
                    let e = f / r - 1.0;
                    if s >= 0.2e-3 {
                        worst = worst.max(e.abs());
                    }
                    unsteady = unsteady.max(st);
                    format!("{:.2} mm {:.3} mN {:+.1} %", s * 1e3, f * 1e3, 100.0 * e)
                })
                .collect();
            println!("  {:>9}: {}", p.name, cells.join(" | "));
        }
        println!(
            "  largest error {:.1} % (sphere depth >= 0.2 mm), largest tick-to-tick change {:.2} % of the hold force",
            100.0 * worst,
            100.0 * unsteady
        );
    }
    Ok(())
}

/// Whether a row of the eq. 4 table has a sample the calibration could not match (it then
/// repeats the previous displacement plus 1e-9: `calibrate_node_with`).
fn has_unmatched_sample(row: &NodeCalibration) -> bool {
    row.x_over_l.windows(2).any(|w| w[1] - w[0] < 1e-8)
}

/// The `recalibrate` subcommand: the rows `nodes` (default: those with an unmatched sample) of
/// the scene file's eq. 4 table computed again, the rest and the key kept, the file rewritten
/// with its comment lines.
pub fn recalibrate(scene_file: &Path, nodes: &[u32], threads: Option<usize>) -> anyhow::Result<()> {
    let scene = load_scene_file(scene_file)?;
    let ms = scene.mass_spring.as_ref().context("a mass-spring scene")?;
    let table = ms.table()?.context("the scene has no eq. 4 table")?;
    let path = ms
        .calibration_path
        .clone()
        .context("the scene file's calibration_file")?;
    let nodes: Vec<u32> = if nodes.is_empty() {
        (0..table.node_count() as u32)
            .filter(|&i| table.node(i).is_some_and(has_unmatched_sample))
            .collect()
    } else {
        nodes.to_vec()
    };
    println!("recalibrating {} nodes: {nodes:?}", nodes.len());
    let contact = surface_contact_rest(&ms.surface, ms.contact);
    let next = AtomicUsize::new(0);
    let done: Mutex<Vec<(u32, anyhow::Result<NodeCalibration>)>> = Mutex::new(Vec::new());
    let threads =
        threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, usize::from));
    std::thread::scope(|scope| {
        for _ in 0..threads.max(1) {
            scope.spawn(|| {
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&node) = nodes.get(k) else { break };
                    let row = calibrate_node_with(
                        &ms.surface,
                        &ms.params,
                        ms.contact,
                        node,
                        contact.as_ref(),
                    )
                    .map_err(anyhow::Error::from);
                    if let Ok(mut d) = done.lock() {
                        d.push((node, row));
                        println!("{} / {} nodes", d.len(), nodes.len());
                    }
                }
            });
        }
    });
    let mut rows: Vec<Option<NodeCalibration>> = (0..table.node_count() as u32)
        .map(|i| table.node(i).copied())
        .collect();
    for (node, row) in done
        .into_inner()
        .map_err(|_| anyhow!("a thread panicked"))?
    {
        let row = row.with_context(|| format!("node {node}"))?;
        let (lo, hi) = row
            .kh_scale
            .iter()
            .fold((f64::INFINITY, 0.0_f64), |(a, b), &s| (a.min(s), b.max(s)));
        println!(
            "node {node}: K'_h/K_h {lo:.3}-{hi:.3}{}",
            if has_unmatched_sample(&row) {
                " (a sample still unmatched)"
            } else {
                ""
            }
        );
        rows[node as usize] = Some(row);
    }
    let old = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
    let mut description: Vec<String> = old
        .lines()
        .filter_map(|l| l.strip_prefix("# "))
        .filter(|l| {
            !(l.starts_with("key ")
                || l.starts_with("nodes ")
                || l.starts_with("haptic-model mass-spring calibration table"))
        })
        .map(str::to_string)
        .collect();
    // Not starting with "nodes " or "key ": the parser reads those lines.
    description.push(format!(
        "recomputed by `haptic_subdivision recalibrate`: the rows of nodes {}",
        compact_list(&nodes)
    ));
    let new = CalibrationTable::from_rows(table.key(), rows);
    std::fs::write(&path, new.to_text(&description.join("\n")))?;
    println!("wrote {}", path.display());
    Ok(())
}

/// `1,2,3,7` as `1-3,7`.
fn compact_list(nodes: &[u32]) -> String {
    let mut v = nodes.to_vec();
    v.sort_unstable();
    let mut out: Vec<String> = Vec::new();
    let mut k = 0;
    while k < v.len() {
        let mut j = k;
        while j + 1 < v.len() && v[j + 1] == v[j] + 1 {
            j += 1;
        }
        out.push(if j > k {
            format!("{}-{}", v[k], v[j])
        } else {
            v[k].to_string()
        });
        k = j + 1;
    }
    out.join(",")
}
