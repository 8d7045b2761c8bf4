//! Probe-force curves of the LV press on chosen meshes, printed only: the studies behind
//! `docs/accuracy.md` ("Which LV mesh is converged", the dynamic check of the quadratic
//! meshes), outside the work-precision benchmark. The press is the `precision` benchmark's
//! (`benches/common/lv_press.rs`): the probe centre moves along -x at z = -5 mm to the depths
//! 0.5 to 3 mm below first contact.
//!
//! - `static`: the static equilibrium with the probe coupling per depth on each `--mesh`
//!   (linear or quadratic elements on the structured LV, or `lv_h1.msh`), optionally with
//!   another Poisson ratio (E fixed), other depths or strain smoothing.
//! - `sphere`: the press with a rigid sphere (exact contact) on three or more meshes with the
//!   Richardson extrapolation and its uncertainty per depth, per material. Meshes may be Gmsh
//!   files (`FILE.msh:ORDER`, in mm, groups BASE and EPI), for example the LV refined around
//!   the contact point by `examples/lv_probe_refined.geo`:
//!   `gmsh server/model/examples/lv_probe_refined.geo -3 -format msh22 -setnumber hmin 0.6
//!   -setnumber hmax 3 -o lvr_0.6.msh`.
//! - `reference`: the converged sphere reference from `haptic-solve --indent` runs on three
//!   or more meshes refined under the probe (their `indent.csv`), at the `lv-probe` device
//!   depths, by Richardson extrapolation with its uncertainty; with `--servo`, the default
//!   scene's servo error against it (docs/accuracy.md, "A converged sphere reference").
//! - `dynamic`: the dynamic press (`FemBody::tick`, ramps and holds) with each `--run`'s
//!   mesh and integrator, and its median tick.
//!
//! Run: `cargo run --release -p haptic-model --example lv_study -- static --mesh 1000:2,h1:1`
//! or `... -- dynamic --run 500:2:symplectic-euler:0.9`; `--help` for the options.

#[path = "../benches/common/mod.rs"]
mod common;

use std::str::FromStr;
use std::time::Instant;

use clap::{Parser, Subcommand};
use common::lv_press::{DEPTHS_MM, probe_dynamic, probe_sphere_at, probe_static_at, richardson};
use haptic_model::element::StrainSmoothing;
use haptic_model::integrate::IntegratorKind;
use haptic_model::material::MaterialModel;
use haptic_model::scene::Scene;

/// Probe-force curves of the LV press on chosen meshes (prints only).
#[derive(Debug, Parser)]
#[command(name = "lv_study")]
struct Args {
    #[command(subcommand)]
    study: Study,
}

#[derive(Debug, Subcommand)]
enum Study {
    /// Static probe curves: the discretisation error of linear and quadratic elements.
    Static {
        /// Meshes, comma-separated: TETS:ORDER with TETS the target element count of the
        /// structured LV (or `h1` for lv_h1.msh, 17 924 tets) and ORDER 1 (linear) or 2
        /// (quadratic).
        #[arg(long, value_delimiter = ',', default_value = "1000:1,1000:2,2000:2")]
        mesh: Vec<MeshSpec>,
        /// Poisson ratio instead of the scene's (Young's modulus kept) [default: the lv
        /// scene's].
        #[arg(long)]
        nu: Option<f64>,
        /// Depths below first contact, mm, increasing, comma-separated [default: 0.5, 1, 1.5,
        /// 2, 2.5, 3].
        #[arg(long, value_delimiter = ',')]
        depths: Vec<f64>,
        /// Strain smoothing (none, edge, ...) instead of the scene's [default: the lv scene's].
        #[arg(long, value_parser = parse_smoothing)]
        smoothing: Option<StrainSmoothing>,
        /// Print the force of every patch iteration.
        #[arg(long)]
        debug: bool,
    },
    /// The press with a rigid sphere (exact contact, static, converged per depth) on three or
    /// more meshes, coarse to fine, with the Richardson extrapolation of the last three and
    /// its uncertainty per depth, for each material; with `--patch`, the kernel-patch static
    /// curve on the finest mesh for comparison.
    Sphere {
        /// Meshes, coarse to fine, as in `static --mesh`, or Gmsh files of the LV in mm with
        /// groups BASE and EPI as FILE.msh:ORDER.
        #[arg(long, value_delimiter = ',', default_value = "500:2,1000:2,2000:2")]
        mesh: Vec<MeshSpec>,
        /// Materials by scene name [default: stvk, corotational, stable-neo-hookean].
        #[arg(long, value_delimiter = ',')]
        material: Vec<String>,
        /// Also solve the kernel-patch static press on the finest mesh.
        #[arg(long)]
        patch: bool,
        /// Device depths below first contact, mm, increasing [default: 0.5, 1, ..., 3].
        #[arg(long, value_delimiter = ',')]
        depths: Vec<f64>,
    },
    /// The converged sphere reference from `haptic-solve --indent` runs on three or more
    /// meshes (coarse to fine) of the LV pressed along the lv-probe line (`--from 15,0,-5
    /// --direction -1,0,0`): each run's `indent.csv` (sphere depths below first contact, no
    /// coupling) becomes a curve of device depths below the lv-probe contact point (the
    /// sphere pulled by the lv coupling, as in `sphere`), interpolated at `--depths`, and
    /// Richardson's extrapolation of the last three meshes gives the reference force and its
    /// uncertainty per depth.
    Reference {
        /// The meshes of the runs, coarse to fine, as in `sphere --mesh` (FILE.msh:ORDER).
        #[arg(long, value_delimiter = ',', required = true)]
        mesh: Vec<MeshSpec>,
        /// Each mesh's `indent.csv`, same order.
        #[arg(long, value_delimiter = ',', required = true)]
        csv: Vec<std::path::PathBuf>,
        /// Each mesh's size under the probe (any unit: only ratios matter), same order
        /// [default: the cube root of the mean element volume].
        #[arg(long, value_delimiter = ',')]
        h: Vec<f64>,
        /// Device depths below first contact, mm [default: 0.5, 1, 1.5].
        #[arg(long, value_delimiter = ',')]
        depths: Vec<f64>,
        /// Also run the servo on the built-in `lv` scene (the default configuration) through
        /// the `lv-probe` staircase and report its force error against the reference at each
        /// depth, or "below uncertainty" where the difference is within the reference's
        /// uncertainty.
        #[arg(long)]
        servo: bool,
        /// With `--servo`: run this scene file instead of the built-in `lv` (its probe must
        /// press along the `lv-probe` line, e.g. `deploy/scenes/lv_h1_es.toml`).
        #[arg(long, requires = "servo")]
        servo_scene: Option<std::path::PathBuf>,
        /// The material of the meshes (and of the servo run) by scene name [default: the lv
        /// scene's, stvk].
        #[arg(long)]
        material: Option<String>,
        /// Also extrapolate the epicardium's displacement at the benchmark's sample points
        /// (`common::surface_sample_points_m`) from each run's `indent_NNN.vtu` (beside its
        /// `indent.csv`) and write it to this CSV: device depth, point, rest position and the
        /// extrapolated displacement (mm) with its uncertainty (mm, the norm of the
        /// components' grid convergence indices).
        #[arg(long)]
        surface: Option<std::path::PathBuf>,
    },
    /// Dynamic probe curves with chosen integrators.
    Dynamic {
        /// Runs, comma-separated: TETS:ORDER:INTEGRATOR[:SAFETY[:CG]] with the mesh as in
        /// `static --mesh` (structured LV only), the integrator's scene name, the safety
        /// factor on the critical step (default 0.5) and the CG cap (default 20).
        #[arg(long, value_delimiter = ',', default_value = "300:2:semi-implicit:0.5")]
        run: Vec<DynamicRun>,
        /// Backward Euler runs with `integrator.linear_solver = "rest-cholesky"` and this
        /// `integrator.stiffness_margin` (the tick matrix frozen at rest, factorised once).
        #[arg(long)]
        prefactored_margin: Option<f64>,
    },
}

/// A mesh of the study: the structured LV at about `tets` elements, or `lv_h1.msh`.
#[derive(Debug, Clone)]
struct MeshSpec {
    /// Target element count; `None` for `lv_h1.msh`.
    tets: Option<usize>,
    quadratic: bool,
    /// A Gmsh file of the LV in mm (physical groups BASE and EPI) instead.
    file: Option<std::path::PathBuf>,
}

impl FromStr for MeshSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (tets, order) = s
            .rsplit_once(':')
            .ok_or_else(|| format!("{s:?}: expected TETS:ORDER or FILE.msh:ORDER"))?;
        let quadratic = match order {
            "1" => false,
            "2" => true,
            o => return Err(format!("order {o:?}: expected 1 or 2")),
        };
        if tets.ends_with(".msh") {
            return Ok(Self {
                tets: None,
                quadratic,
                file: Some(tets.into()),
            });
        }
        let tets = match tets {
            "h1" => None,
            n => Some(n.parse().map_err(|e| format!("{n:?}: {e}"))?),
        };
        Ok(Self {
            tets,
            quadratic,
            file: None,
        })
    }
}

impl MeshSpec {
    /// The built-in `lv` scene on this mesh.
    fn scene(&self) -> Scene {
        if let Some(file) = &self.file {
            let text = format!(
                "name = \"lv-file\"\n[mesh]\nfile = {:?}\nlength_unit = \"mm\"\norder = {}\n[material]\nyoungs_modulus_pa = 14500.0\npoisson_ratio = 0.45\ndensity_kg_per_m3 = 1060.0\n[boundary]\nclamped = [\"BASE\"]\ntouchable = [\"EPI\"]\n",
                file.display().to_string(),
                if self.quadratic { 2 } else { 1 }
            );
            let scene = haptic_model::scene::parse_scene_toml(&text, std::path::Path::new("."))
                .unwrap_or_else(|e| panic!("{}: {e}", file.display()));
            return common::lv_scene_on(scene.mesh);
        }
        match self.tets {
            Some(tets) => common::lv_scene_order(tets, self.quadratic),
            None => {
                let mesh = common::lv_h1_scene().expect("lv_h1.msh").mesh;
                common::lv_scene_on(if self.quadratic {
                    mesh.to_quadratic()
                } else {
                    mesh
                })
            }
        }
    }

    fn label(&self) -> String {
        if let Some(file) = &self.file {
            return format!(
                "{} order {}",
                file.display(),
                if self.quadratic { 2 } else { 1 }
            );
        }
        let tets = self.tets.map_or("h1".into(), |t| t.to_string());
        format!("{tets} tets order {}", if self.quadratic { 2 } else { 1 })
    }
}

/// A dynamic run: mesh, integrator, safety factor and CG cap.
#[derive(Debug, Clone)]
struct DynamicRun {
    spec: String,
    tets: usize,
    quadratic: bool,
    kind: IntegratorKind,
    safety_factor: f64,
    cg_max_iterations: u32,
}

impl FromStr for DynamicRun {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let f: Vec<&str> = s.split(':').collect();
        if !(3..=5).contains(&f.len()) {
            return Err(format!(
                "{s:?}: expected TETS:ORDER:INTEGRATOR[:SAFETY[:CG]]"
            ));
        }
        let mesh: MeshSpec = format!("{}:{}", f[0], f[1]).parse()?;
        let tets = mesh
            .tets
            .ok_or_else(|| format!("{s:?}: dynamic runs take a structured LV size"))?;
        let kind =
            IntegratorKind::from_name(f[2]).ok_or_else(|| format!("integrator {:?}", f[2]))?;
        let parse_err = |v: &str| format!("{s:?}: {v:?} is not a number");
        Ok(Self {
            spec: s.into(),
            tets,
            quadratic: mesh.quadratic,
            kind,
            safety_factor: f
                .get(3)
                .map_or(Ok(0.5), |v| v.parse().map_err(|_| parse_err(v)))?,
            cg_max_iterations: f
                .get(4)
                .map_or(Ok(20), |v| v.parse().map_err(|_| parse_err(v)))?,
        })
    }
}

fn parse_smoothing(s: &str) -> Result<StrainSmoothing, String> {
    StrainSmoothing::from_name(s).ok_or_else(|| format!("unknown strain smoothing {s:?}"))
}

fn main() {
    match Args::parse().study {
        Study::Static {
            mesh,
            nu,
            depths,
            smoothing,
            debug,
        } => {
            let depths = if depths.is_empty() {
                DEPTHS_MM.to_vec()
            } else {
                depths
            };
            static_study(&mesh, nu, &depths, smoothing, debug);
        }
        Study::Sphere {
            mesh,
            material,
            patch,
            depths,
        } => {
            let depths = if depths.is_empty() {
                DEPTHS_MM.to_vec()
            } else {
                depths
            };
            sphere_study(&mesh, &material, patch, &depths)
        }
        Study::Reference {
            mesh,
            csv,
            h,
            depths,
            servo,
            servo_scene,
            material,
            surface,
        } => {
            let depths = if depths.is_empty() {
                vec![0.5, 1.0, 1.5]
            } else {
                depths
            };
            let material = match material.as_deref().map(MaterialModel::from_scene_name) {
                None => None,
                Some(Some(m)) => Some(m),
                Some(None) => {
                    eprintln!("lv_study reference: unknown material {material:?}");
                    std::process::exit(2);
                }
            };
            if let Err(e) = reference_study(
                &mesh,
                &csv,
                &h,
                &depths,
                servo.then_some(servo_scene.as_deref()),
                material,
                surface.as_deref(),
            ) {
                eprintln!("lv_study reference: {e}");
                std::process::exit(1);
            }
        }
        Study::Dynamic {
            run,
            prefactored_margin,
        } => dynamic_study(&run, prefactored_margin),
    }
}

/// The `static` study (see [`Study::Static`]).
fn static_study(
    mesh: &[MeshSpec],
    nu: Option<f64>,
    depths: &[f64],
    smoothing: Option<StrainSmoothing>,
    debug: bool,
) {
    for m in mesh {
        let mut scene = m.scene();
        if let Some(s) = smoothing {
            scene.strain_smoothing = s;
        }
        if let Some(nu) = nu {
            let mat = &mut scene.material;
            let e = mat.youngs_modulus_pa();
            mat.lambda_pa = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
            mat.mu_pa = e / (2.0 * (1.0 + nu));
        }
        let t = Instant::now();
        let c = probe_static_at(&scene, depths, debug);
        println!(
            "lv-study {}: {} nodes, {:.1} s: {:?}",
            m.label(),
            scene.mesh.node_count(),
            t.elapsed().as_secs_f64(),
            c.map(|c| c.forces_n)
        );
    }
}

/// The `dynamic` study (see [`Study::Dynamic`]).
fn dynamic_study(run: &[DynamicRun], prefactored_margin: Option<f64>) {
    for r in run {
        let mut scene = common::lv_scene_order(r.tets, r.quadratic);
        scene.integrator.kind = r.kind;
        scene.integrator.safety_factor = r.safety_factor;
        scene.integrator.cg_max_iterations = r.cg_max_iterations;
        scene.integrator.max_substeps = 1000;
        // Backward Euler with CG unless the rest factor is asked for (the built-in
        // scene's own solver is the rest factor).
        scene.integrator.linear_solver = haptic_model::integrate::LinearSolver::Cg;
        if let Some(margin) = prefactored_margin {
            scene.integrator.linear_solver = haptic_model::integrate::LinearSolver::RestCholesky;
            scene.integrator.stiffness_margin = margin;
        }
        match probe_dynamic(&scene, false) {
            Ok((c, ticks, sub)) => println!(
                "lv-dyn {}: {} nodes, {sub} sub-steps, tick p50 {:.0} us: {:?}",
                r.spec,
                scene.mesh.node_count(),
                ticks.percentiles().p50_us,
                c.forces_n
            ),
            Err(e) => println!("lv-dyn {}: {e}", r.spec),
        }
    }
}

/// The `sphere` study (see [`Study::Sphere`]).
fn sphere_study(meshes: &[MeshSpec], materials: &[String], patch: bool, depths: &[f64]) {
    assert!(
        meshes.len() >= 3,
        "the sphere study needs three or more meshes"
    );
    assert!(
        meshes.iter().all(|m| m.tets.is_some() || m.file.is_some()),
        "the sphere study runs on the structured LV or Gmsh files"
    );
    let materials: Vec<MaterialModel> = if materials.is_empty() {
        common::MATERIALS.to_vec()
    } else {
        materials
            .iter()
            .map(|m| MaterialModel::from_scene_name(m).unwrap_or_else(|| panic!("material {m:?}")))
            .collect()
    };
    for model in materials {
        let mut curves = Vec::new();
        let mut sizes = Vec::new();
        for m in meshes {
            let mut scene = m.scene();
            scene.material.model = model;
            let t = Instant::now();
            match probe_sphere_at(&scene, depths) {
                Ok(c) => {
                    println!(
                        "lv-sphere {} {}: {} tets, {} nodes, {:.1} s: {:?} N",
                        model.scene_name(),
                        m.label(),
                        scene.mesh.tet_count(),
                        scene.mesh.node_count(),
                        t.elapsed().as_secs_f64(),
                        c.forces_n
                    );
                    // Mesh size: the cube root of the mean element volume (same body).
                    sizes.push((scene.mesh.tet_count() as f64).powf(-1.0 / 3.0));
                    curves.push(c.forces_n);
                }
                Err(e) => {
                    println!(
                        "lv-sphere {} {}: FAILED: {e}",
                        model.scene_name(),
                        m.label()
                    );
                    break;
                }
            }
        }
        if curves.len() >= 3 {
            let k = curves.len();
            let h = [sizes[k - 3], sizes[k - 2], sizes[k - 1]];
            println!(
                "lv-sphere {} extrapolated (last three meshes, h relative to the finest {:.3}/{:.3}/1):",
                model.scene_name(),
                h[0] / h[2],
                h[1] / h[2]
            );
            println!("  depth mm | finest N | extrapolated N | uncertainty N (%) | order");
            for (j, d) in depths.iter().enumerate() {
                let f = [curves[k - 3][j], curves[k - 2][j], curves[k - 1][j]];
                let e = richardson(h, f);
                println!(
                    "  {d:.1} | {:.5} | {:.5} | {:.5} ({:.1} %) | {}",
                    f[2],
                    e.value,
                    e.uncertainty,
                    100.0 * e.uncertainty / e.value,
                    e.order
                        .map_or("none (not asymptotic)".into(), |p| format!("{p:.2}"))
                );
            }
        }
        if patch {
            let m = meshes.last().expect("meshes");
            let mut scene = m.scene();
            scene.material.model = model;
            let c = probe_static_at(&scene, depths, false);
            println!(
                "lv-patch {} {}: {:?}",
                model.scene_name(),
                m.label(),
                c.map(|c| c.forces_n)
            );
        }
    }
}

/// The rows of an `indent.csv`: sphere depth below first contact (mm), the force on the sphere
/// along the press (+x, N) and its magnitude (N).
fn read_indent_csv(path: &std::path::Path) -> Result<Vec<(f64, f64, f64)>, String> {
    let mut reader =
        csv::Reader::from_path(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut rows = Vec::new();
    for record in reader.records() {
        let r = record.map_err(|e| format!("{}: {e}", path.display()))?;
        let field = |k: usize| -> Result<f64, String> {
            r.get(k)
                .and_then(|v| v.trim().parse::<f64>().ok())
                .ok_or_else(|| {
                    format!("{}: row {:?}: field {k} is not a number", path.display(), r)
                })
        };
        let f = glam::DVec3::new(field(1)?, field(2)?, field(3)?);
        rows.push((field(0)?, f.x, f.length()));
    }
    if rows.len() < 2 || rows.windows(2).any(|w| w[1].0 <= w[0].0) {
        return Err(format!(
            "{}: needs two or more rows of increasing depth",
            path.display()
        ));
    }
    Ok(rows)
}

/// The value at `x` of the quadratic through the three points of `pts` (sorted by `x`, two or
/// more) nearest to it (linear with two); `None` outside their range.
fn interpolate(pts: &[(f64, f64)], x: f64) -> Option<f64> {
    let (first, last) = (pts.first()?.0, pts.last()?.0);
    if !(first <= x && x <= last) {
        return None;
    }
    if pts.len() == 2 {
        let ((x0, y0), (x1, y1)) = (pts[0], pts[1]);
        return Some(y0 + (y1 - y0) * (x - x0) / (x1 - x0));
    }
    let i = pts.partition_point(|p| p.0 < x).clamp(1, pts.len() - 1);
    // The three points around the bracket [i - 1, i], the nearer third.
    let start = if i == 1 {
        0
    } else if i + 1 == pts.len() || (x - pts[i - 2].0) < (pts[i + 1].0 - x) {
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

/// The `reference` study (see [`Study::Reference`]).
fn reference_study(
    meshes: &[MeshSpec],
    csvs: &[std::path::PathBuf],
    h: &[f64],
    depths: &[f64],
    servo: Option<Option<&std::path::Path>>,
    material: Option<MaterialModel>,
    surface: Option<&std::path::Path>,
) -> Result<(), String> {
    let points = common::surface_sample_points_m();
    // Per mesh: per device depth, the displacement at each sample point (m).
    let mut surfaces: Vec<Vec<Vec<glam::DVec3>>> = Vec::new();
    if meshes.len() < 3 || meshes.len() != csvs.len() || !(h.is_empty() || h.len() == meshes.len())
    {
        return Err(format!(
            "three or more meshes, one indent.csv each (and one size each, or none): got {} meshes, {} files, {} sizes",
            meshes.len(),
            csvs.len(),
            h.len()
        ));
    }
    let mut curves = Vec::new();
    let mut sizes = Vec::new();
    for (k, (m, path)) in meshes.iter().zip(csvs).enumerate() {
        let MeshCurve { scene, device, at } = mesh_curve(m, path, material, depths)?;
        sizes.push(
            h.get(k)
                .copied()
                .unwrap_or((scene.mesh.tet_count() as f64).powf(-1.0 / 3.0)),
        );
        curves.push(at);
        if surface.is_some() {
            surfaces.push(surface_at_depths(&scene, path, &device, depths, &points)?);
        }
    }
    let k = curves.len();
    let hh = [sizes[k - 3], sizes[k - 2], sizes[k - 1]];
    println!(
        "reference (Richardson through the last three meshes, h ratios {:.3} : {:.3} : 1):",
        hh[0] / hh[2],
        hh[1] / hh[2]
    );
    let reference = reference_table(depths, &curves, hh);
    if let Some(out) = surface {
        write_surface_reference(out, hh, depths, &points, &surfaces)?;
    }
    if let Some(scene) = servo {
        servo_against_reference(depths, &reference, scene, material)?;
    }
    Ok(())
}

/// One mesh of the `reference` study.
struct MeshCurve {
    scene: Scene,
    /// The `indent.csv` rows as (device depth mm, force magnitude N).
    device: Vec<(f64, f64)>,
    /// The force at each requested device depth, N.
    at: Vec<f64>,
}

/// One mesh of the `reference` study: its scene (with `material`), its `indent.csv` at `path`
/// and the force at each of `depths` (mm).
fn mesh_curve(
    m: &MeshSpec,
    path: &std::path::Path,
    material: Option<MaterialModel>,
    depths: &[f64],
) -> Result<MeshCurve, String> {
    use common::{CONTACT_X_M, device_at};
    use haptic_model::indent::{IndentParams, Indenter, contact_distance};
    let mut scene = m.scene();
    if let Some(model) = material {
        scene.material.model = model;
    }
    let fem = scene.fem_model().map_err(|e| e.to_string())?;
    let from = device_at(-1e-3);
    let indenter = Indenter {
        radius_m: scene.probe.radius_m,
        from_m: from,
        direction: glam::DVec3::new(-1.0, 0.0, 0.0),
    };
    let t0 = contact_distance(&fem, &scene.touchable, &indenter, &IndentParams::default())
        .map_err(|e| e.to_string())?;
    // indent.csv's depth zero is this mesh's first contact, `1 mm - t0` before the
    // lv-probe contact point CONTACT_X_M.
    let offset_mm = (1e-3 - t0) * 1e3;
    let kc = scene.probe.coupling_stiffness_n_per_m;
    let rows = read_indent_csv(path)?;
    // The device sits `F_x / k` beyond the sphere along the press; the force is reported
    // as the dynamic runs report it, by its magnitude.
    let device: Vec<(f64, f64)> = rows
        .iter()
        .map(|&(s, fx, f)| (s - offset_mm + fx / kc * 1e3, f))
        .collect();
    println!(
        "mesh {} ({} tets, {} nodes): first contact {:+.4} mm from x = {:.3} mm; sphere depth mm -> force N: {}",
        m.label(),
        scene.mesh.tet_count(),
        scene.mesh.node_count(),
        -offset_mm,
        CONTACT_X_M * 1e3,
        rows.iter()
            .map(|(s, _, f)| format!("{s}: {f:.5e}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let at: Vec<f64> = depths
        .iter()
        .map(|&d| {
            interpolate(&device, d).ok_or_else(|| {
                format!(
                    "{}: device depth {d} mm is outside the solved range {:.3} to {:.3} mm",
                    path.display(),
                    device[0].0,
                    device[device.len() - 1].0
                )
            })
        })
        .collect::<Result<_, _>>()?;
    Ok(MeshCurve { scene, device, at })
}

/// Prints the table of the `reference` study: each mesh's force and the extrapolation through
/// the last three (sizes `hh`) at each device depth; the extrapolations.
fn reference_table(
    depths: &[f64],
    curves: &[Vec<f64>],
    hh: [f64; 3],
) -> Vec<common::lv_press::Extrapolated> {
    let k = curves.len();
    println!(
        "| device depth, mm | {} | extrapolated, mN | uncertainty, mN (%) | observed order |",
        (0..k)
            .map(|i| format!("mesh {}, mN", i + 1))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let mut reference = Vec::new();
    for (j, d) in depths.iter().enumerate() {
        let f = [curves[k - 3][j], curves[k - 2][j], curves[k - 1][j]];
        let e = richardson(hh, f);
        reference.push(e);
        println!(
            "| {d} | {} | {:.4} | {:.4} ({:.1} %) | {} |",
            (0..k)
                .map(|i| format!("{:.4}", curves[i][j] * 1e3))
                .collect::<Vec<_>>()
                .join(" | "),
            e.value * 1e3,
            e.uncertainty * 1e3,
            100.0 * e.uncertainty / e.value,
            e.order
                .map_or("none (not asymptotic)".into(), |p| format!("{p:.2}"))
        );
    }
    reference
}

/// The displacement (m) at each of `points` on `scene`'s touchable surface at each device
/// depth of `depths` (mm), from the `indent_NNN.vtu` files beside `csv` (one per row of
/// `device`, the rows' device depths and forces), interpolated between the solved depths as
/// the forces are.
fn surface_at_depths(
    scene: &Scene,
    csv: &std::path::Path,
    device: &[(f64, f64)],
    depths: &[f64],
    points: &[glam::DVec3],
) -> Result<Vec<Vec<glam::DVec3>>, String> {
    let rest = &scene.mesh.nodes;
    let sampler = haptic_model::contact::SurfaceSampler::new(rest, &scene.touchable, points);
    let worst = sampler.distance_m().iter().fold(0.0f64, |a, d| a.max(*d));
    if worst > 0.2e-3 {
        return Err(format!(
            "a sample point lies {:.3} mm from the touchable surface of {}",
            worst * 1e3,
            csv.display()
        ));
    }
    let dir = csv.parent().unwrap_or(std::path::Path::new("."));
    let mut rows = Vec::with_capacity(device.len());
    for k in 0..device.len() {
        let file = dir.join(format!("indent_{:03}.vtu", k + 1));
        let u_scene = read_vtu_displacement(&file, rest.len())?;
        let x: Vec<glam::DVec3> = rest
            .iter()
            .zip(&u_scene)
            .map(|(r, u)| *r + *u * scene.length_unit_m)
            .collect();
        rows.push(sampler.displacements(rest, &x));
    }
    depths
        .iter()
        .map(|&d| {
            (0..points.len())
                .map(|p| {
                    let mut u = [0.0; 3];
                    for (c, uc) in u.iter_mut().enumerate() {
                        let series: Vec<(f64, f64)> = device
                            .iter()
                            .zip(&rows)
                            .map(|((dd, _), r)| (*dd, r[p][c]))
                            .collect();
                        *uc = interpolate(&series, d).ok_or_else(|| {
                            format!("device depth {d} mm outside {}'s runs", csv.display())
                        })?;
                    }
                    Ok(glam::DVec3::from_array(u))
                })
                .collect()
        })
        .collect()
}

/// The `displacement` point array of a `.vtu` written by `haptic-solve` (scene units), `n` nodes.
fn read_vtu_displacement(path: &std::path::Path, n: usize) -> Result<Vec<glam::DVec3>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let start = text
        .find("Name=\"displacement\"")
        .and_then(|i| text[i..].find('>').map(|j| i + j + 1))
        .ok_or_else(|| format!("{}: no displacement array", path.display()))?;
    let end = start
        + text[start..]
            .find("</DataArray>")
            .ok_or_else(|| format!("{}: unterminated displacement array", path.display()))?;
    let values: Vec<f64> = text[start..end]
        .split_whitespace()
        .map(|v| v.parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if values.len() != 3 * n {
        return Err(format!(
            "{}: {} displacement values for {n} nodes",
            path.display(),
            values.len()
        ));
    }
    Ok(values
        .chunks_exact(3)
        .map(|c| glam::DVec3::new(c[0], c[1], c[2]))
        .collect())
}

/// Richardson's extrapolation of each point's displacement through the last three meshes,
/// written as CSV (mm): `device_depth_mm,point,x_mm,y_mm,z_mm,ux_mm,uy_mm,uz_mm,uncertainty_mm`.
fn write_surface_reference(
    out: &std::path::Path,
    h: [f64; 3],
    depths: &[f64],
    points: &[glam::DVec3],
    surfaces: &[Vec<Vec<glam::DVec3>>],
) -> Result<(), String> {
    let k = surfaces.len();
    let mut text =
        String::from("device_depth_mm,point,x_mm,y_mm,z_mm,ux_mm,uy_mm,uz_mm,uncertainty_mm\n");
    println!("surface reference (Richardson per point and component, mm):");
    for (j, d) in depths.iter().enumerate() {
        let mut worst: (f64, f64) = (0.0, 0.0);
        for (p, x) in points.iter().enumerate() {
            let mut u = [0.0; 3];
            let mut unc2 = 0.0;
            for (c, uc) in u.iter_mut().enumerate() {
                let f = [
                    surfaces[k - 3][j][p][c],
                    surfaces[k - 2][j][p][c],
                    surfaces[k - 1][j][p][c],
                ];
                let e = richardson(h, f);
                *uc = e.value;
                unc2 += e.uncertainty * e.uncertainty;
            }
            let u = glam::DVec3::from_array(u);
            let unc = unc2.sqrt();
            worst = (worst.0.max(u.length()), worst.1.max(unc));
            text.push_str(&format!(
                "{d},{p},{:.6},{:.6},{:.6},{:.8},{:.8},{:.8},{:.8}\n",
                x.x * 1e3,
                x.y * 1e3,
                x.z * 1e3,
                u.x * 1e3,
                u.y * 1e3,
                u.z * 1e3,
                unc * 1e3
            ));
        }
        println!(
            "  device depth {d} mm: largest displacement {:.4} mm, largest uncertainty {:.4} mm",
            worst.0 * 1e3,
            worst.1 * 1e3
        );
    }
    std::fs::write(out, text).map_err(|e| format!("{}: {e}", out.display()))
}

/// The servo of `scene_file` (default: the built-in `lv` scene) through the `lv-probe`
/// staircase against the reference at the depths both have.
fn servo_against_reference(
    depths: &[f64],
    reference: &[common::lv_press::Extrapolated],
    scene_file: Option<&std::path::Path>,
    material: Option<MaterialModel>,
) -> Result<(), String> {
    let mut scene = match scene_file {
        Some(path) => haptic_model::scene::load_scene_file(path),
        None => haptic_model::scene::load_builtin("lv"),
    }
    .map_err(|e| e.to_string())?;
    if let Some(model) = material {
        scene.material.model = model;
    }
    let mut sim = haptic_model::fem::FemBody::new(&scene).map_err(|e| e.to_string())?;
    let tick = sim.tick_s();
    let (curve, ticks) = common::lv_press::probe_dynamic_body(&mut sim, tick, false)?;
    let forces = curve.forces_n;
    println!(
        "servo: {} ({} elements, {}, {} contact), tick p50 {:.0} us on this machine",
        scene.name,
        scene.mesh.tet_count(),
        scene.material.model.scene_name(),
        haptic_model::integrate::resolve_contact_model(scene.probe.contact).name(),
        ticks.percentiles().p50_us
    );
    println!("| device depth, mm | servo, mN | reference, mN | servo error |");
    for (d, e) in depths.iter().zip(reference) {
        let Some(j) = DEPTHS_MM.iter().position(|x| (x - d).abs() < 1e-9) else {
            continue;
        };
        let f = forces[j];
        let error = if (f - e.value).abs() <= e.uncertainty {
            format!(
                "below uncertainty (+-{:.1} %)",
                100.0 * e.uncertainty / e.value
            )
        } else {
            format!(
                "{:+.1} % (+-{:.1} %)",
                100.0 * (f - e.value) / e.value,
                100.0 * e.uncertainty / e.value
            )
        };
        println!(
            "| {d} | {:.3} | {:.3} +- {:.3} | {error} |",
            f * 1e3,
            e.value * 1e3,
            e.uncertainty * 1e3
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::interpolate;

    #[test]
    fn interpolation_is_exact_for_quadratics_and_refuses_outside() {
        let pts: Vec<(f64, f64)> = [0.0, 0.25, 0.5, 1.0, 1.5]
            .iter()
            .map(|&x| (x, 2.0 + 3.0 * x - x * x))
            .collect();
        for x in [0.0, 0.1, 0.3, 0.7, 1.2, 1.5] {
            let y = interpolate(&pts, x).expect("inside");
            assert!((y - (2.0 + 3.0 * x - x * x)).abs() < 1e-12, "{x}: {y}");
        }
        assert_eq!(interpolate(&pts, 1.6), None);
        assert_eq!(interpolate(&pts, -0.1), None);
    }
}
