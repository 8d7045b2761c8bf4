//! Run time versus error (issue 3, section 4): scenarios x methods x resolutions x settings, one
//! row per run in `docs/bench/precision.csv` and `.json`, and a work-precision plot per scenario
//! (`docs/precision-<scenario>.png` / `.svg`): error against wall time per simulated
//! millisecond, log-log, one curve per method, with the 1 ms haptic budget and the 7 % force
//! just-noticeable difference drawn as lines.
//!
//! Methods ([`methods`]): the static Newton solve; semi-implicit and symplectic Euler at
//! safety factors on the critical step; backward Euler (one sub-step per 1 ms tick) with CG
//! capped at 5, 10 and 20 iterations; all on St. Venant-Kirchhoff, and the corotational and
//! stable Neo-Hookean materials with the static solve, semi-implicit at 0.5 and backward Euler
//! with 20 CG iterations (Lamé and cantilever, dynamic runs on the coarser meshes; `lv-probe`
//! is St. Venant-Kirchhoff only, see [`LV_MATERIALS`]).
//!
//! Scenarios:
//! - `lame`: thick sphere a = 7 mm, b = 10 mm, E = 10 kPa, nu = 0.3, p = 0.1 kPa on the inner
//!   surface (dead load from `statics::add_pressure_forces`), rollers on three inner axis nodes;
//!   dynamic run to steady state (load ramped in over 20 ms, 100 ms simulated, mass damping
//!   600 /s) with each integrator, and the static Newton solve as the method `static`; error of
//!   the final displacement field against the analytic Lamé solution.
//! - `cantilever`: beam 100 x 10 x 10 mm (E = 100 kPa, nu = 0.3, rho = 1000 kg/m^3), clamped
//!   at x = 0, dead tip load with alpha = P L^2 / (E I) = 1 spread over the tip face by area;
//!   observable: tip deflection v / L against Bisshopp-Drucker's 0.30172.
//! - `lv-probe`: the built-in `lv` scene (material, probe, coupling) on the structured LV mesh;
//!   the probe centre moves along -x at z = -5 mm from 11.98 mm (0.3 mm clear of contact) in
//!   steps to depths 0.5, 1, ..., 3 mm (contact at 11.68 mm: the epicardium at 9.68 mm plus the
//!   2 mm probe radius), each step a smoothstep ramp of 100 ms then a 100 ms hold; the force
//!   reported per depth is the mean device force over the last 50 ms of the hold. Reference:
//!   static equilibrium with the probe coupling (Newton per load, secant on the coupling force)
//!   at each depth on a finer mesh (`lv_shell(10000)`, 10 017 tets, cached in `target/bench/`;
//!   about 10 times the 948-tet default; the 18k-tet reference of earlier versions took longer
//!   than the whole run should). Errors:
//!   probe-force error = the largest relative force error over the depths; surface displacement
//!   error at 3 mm on the epicardial nodes, the reference interpolated barycentrically at the
//!   closest point of its rest epicardium.
//!
//! `lv-probe` also runs edge-smoothed linear elements (`StrainSmoothing::Edge`, method suffix
//! " ES") on the 2 000 and 5 000 target meshes. `--scenario lv-h1` runs `lv_h1.msh` with standard
//! and edge-smoothed elements into its own files ([`scenario_lv_h1`]); `--replot` redraws the
//! plots from `docs/bench/precision.json`.
//!
//! Run: `cargo bench -p haptic-model --bench precision` (the LV reference static solve takes
//! minutes the first time, then it is cached; `-- --quick` for a subset of about a minute; `-- --fresh-reference` to recompute the cached LV reference; `-- --scenario NAME`
//! for one scenario, which then is the only one in the output files).

mod common;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use common::{
    CG_ITERATIONS, INTEGRATORS, MATERIALS, device_at, git_commit, lv_scene, run_loaded_with,
    smoothstep, stats,
};
use haptic_model::DVec3;
use haptic_model::contact::{ContactSurface, Probe};
use haptic_model::element::{FemModel, StrainSmoothing};
use haptic_model::integrate::condensed::{ActiveRegion, DEFAULT_STIFFNESS_MARGIN};
use haptic_model::integrate::{IntegratorKind, IntegratorParams};
use haptic_model::loads::add_pressure_forces;
use haptic_model::material::{MaterialModel, MaterialParams};
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::{box_mesh, sphere_shell};
use haptic_model::scene::Scene;
use haptic_model::sim::{Simulation, TickInput};
use haptic_model::statics::{StaticParams, solve_static};

/// One benchmark run.
#[derive(Debug, Clone)]
struct Row {
    scenario: &'static str,
    /// Material model (scene name).
    material: &'static str,
    /// Curve label in the plot: integrator plus the setting that distinguishes curves.
    method: String,
    integrator: String,
    nodes: usize,
    tets: usize,
    settings: String,
    p50_us: f64,
    p99_us: f64,
    max_us: f64,
    realtime_factor: f64,
    rel_l2: f64,
    max_nodal_m: f64,
    probe_force_error: f64,
    observable_error: f64,
    observable: String,
    reference: String,
    stable: bool,
    /// `fem` (linear tetrahedra), `fem-t10` (quadratic) or `fem-es` (linear, edge-smoothed).
    model: &'static str,
}

impl Row {
    /// Marks a row of edge-smoothed linear elements: method suffix " ES" (its own curve in the
    /// plots) and model `fem-es`.
    fn smoothed(mut self, smoothing: StrainSmoothing) -> Self {
        if smoothing != StrainSmoothing::None {
            self.method = format!("{} ES", self.method);
            self.model = "fem-es";
        }
        self
    }

    fn new(scenario: &'static str, method: String, integrator: &str, mesh: &TetMesh) -> Self {
        // Quadratic elements get their own curves in the plots.
        let method = if mesh.is_quadratic() {
            format!("{method} T10")
        } else {
            method
        };
        Self {
            nodes: mesh.node_count(),
            tets: mesh.tet_count(),
            model: if mesh.is_quadratic() {
                "fem-t10"
            } else {
                "fem"
            },
            ..Self::blank(scenario, method, integrator)
        }
    }

    /// A row with no mesh and no results yet.
    fn blank(scenario: &'static str, method: String, integrator: &str) -> Self {
        Self {
            scenario,
            material: MaterialModel::StVenantKirchhoff.scene_name(),
            method,
            integrator: integrator.into(),
            nodes: 0,
            tets: 0,
            settings: String::new(),
            p50_us: f64::NAN,
            p99_us: f64::NAN,
            max_us: f64::NAN,
            realtime_factor: f64::NAN,
            rel_l2: f64::NAN,
            max_nodal_m: f64::NAN,
            probe_force_error: f64::NAN,
            observable_error: f64::NAN,
            observable: String::new(),
            reference: String::new(),
            stable: false,
            model: "fem",
        }
    }

    /// The plotted fields of the rows in a `precision.json` written by [`write_results`].
    fn read_for_plot(path: &Path) -> Result<Vec<Self>, Box<dyn std::error::Error>> {
        let rows: Vec<serde_json::Value> = serde_json::from_str(&std::fs::read_to_string(path)?)?;
        let num = |r: &serde_json::Value, k: &str| r[k].as_f64().unwrap_or(f64::NAN);
        Ok(rows
            .iter()
            .filter_map(|r| {
                let scenario = ["lame", "cantilever", "lv-probe"]
                    .into_iter()
                    .find(|s| r["scenario"] == *s)?;
                let mut row = Self::blank(
                    scenario,
                    r["method"].as_str()?.to_string(),
                    r["integrator"].as_str()?,
                );
                row.p50_us = num(r, "step_p50_us");
                row.rel_l2 = num(r, "rel_l2_error");
                row.probe_force_error = num(r, "probe_force_error");
                row.observable_error = num(r, "observable_error");
                row.stable = r["stable"].as_bool()?;
                Some(row)
            })
            .collect())
    }

    fn set_times(&mut self, ticks_us: &mut [f64], tick_s: f64) {
        let (p50, p99, max) = stats(ticks_us);
        self.p50_us = p50;
        self.p99_us = p99;
        self.max_us = max;
        self.realtime_factor = tick_s * 1e6 / p50;
    }

    /// The error the scenario's plot shows.
    fn plot_error(&self) -> f64 {
        match self.scenario {
            "lame" => self.rel_l2,
            "cantilever" => self.observable_error,
            _ => self.probe_force_error,
        }
    }

    fn print(&self) {
        println!(
            "{:<10} {:<40} {:>6} {:>6} {:<30} p50 {:>9.1} us p99 {:>9.1} us RTx {:>7.2} L2 {:>9.3e} max {:>9.3e} m force {:>9.3e} obs {:>9.3e} {} | {} {}",
            self.scenario,
            self.method,
            self.nodes,
            self.tets,
            self.settings,
            self.p50_us,
            self.p99_us,
            self.realtime_factor,
            self.rel_l2,
            self.max_nodal_m,
            self.probe_force_error,
            self.observable_error,
            self.observable,
            self.reference,
            if self.stable { "stable" } else { "UNSTABLE" }
        );
    }
}

fn num(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

fn csv_num(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.6e}")
    } else {
        String::new()
    }
}

fn csv_text(s: &str) -> String {
    format!("\"{}\"", s.replace('"', "'"))
}

/// One dynamic method: integrator with its step setting, and the material.
#[derive(Debug, Clone, Copy)]
struct Method {
    kind: IntegratorKind,
    /// Safety factor on the critical step (explicit schemes; backward Euler: one sub-step).
    sf: f64,
    /// CG iteration cap (backward Euler).
    cg: u32,
    material: MaterialModel,
}

impl Method {
    fn label(&self) -> String {
        let base = match self.kind {
            IntegratorKind::BackwardEuler => format!("{} cg={}", self.kind.name(), self.cg),
            k => format!("{} sf={}", k.name(), self.sf),
        };
        material_label(base, self.material)
    }

    /// "sub-steps at 0.5 dt_crit (3)" or "1 sub-step, CG <= 10 it."
    fn step_text(&self, substeps: u32) -> String {
        match self.kind {
            IntegratorKind::BackwardEuler => {
                format!("{substeps} sub-step(s), CG <= {} it.", self.cg)
            }
            _ => format!("auto sub-steps at {} dt_crit ({substeps})", self.sf),
        }
    }

    fn params(&self) -> IntegratorParams {
        IntegratorParams {
            kind: self.kind,
            safety_factor: self.sf,
            cg_max_iterations: self.cg,
            max_substeps: 2000,
            ..IntegratorParams::default()
        }
    }
}

/// `base`, with the material appended unless it is St. Venant-Kirchhoff.
fn material_label(base: String, m: MaterialModel) -> String {
    if m == MaterialModel::StVenantKirchhoff {
        base
    } else {
        format!("{base} [{}]", m.scene_name())
    }
}

/// The dynamic methods of a scenario: every integrator on St. Venant-Kirchhoff (explicit ones
/// at each safety factor of `safeties`, backward Euler at each CG cap of [`CG_ITERATIONS`]),
/// and the other materials with the default semi-implicit scheme at `sf` 0.5 and backward
/// Euler at the largest CG cap.
fn methods(safeties: &[f64]) -> Vec<Method> {
    let mut out = Vec::new();
    for &material in MATERIALS {
        let stvk = material == MaterialModel::StVenantKirchhoff;
        for &kind in INTEGRATORS {
            match kind {
                IntegratorKind::BackwardEuler => {
                    let caps: &[u32] = if stvk {
                        CG_ITERATIONS
                    } else {
                        &CG_ITERATIONS[CG_ITERATIONS.len() - 1..]
                    };
                    for &cg in caps {
                        out.push(Method {
                            kind,
                            sf: 1.0,
                            cg,
                            material,
                        });
                    }
                }
                IntegratorKind::SemiImplicit | IntegratorKind::SymplecticEuler => {
                    if !stvk && kind != IntegratorKind::SemiImplicit {
                        continue;
                    }
                    for &sf in safeties {
                        if !stvk && sf != 0.5 {
                            continue;
                        }
                        out.push(Method {
                            kind,
                            sf,
                            cg: 20,
                            material,
                        });
                    }
                }
            }
        }
    }
    out
}

/// Writes `rows` to `dir/<stem>.csv` and `.json`.
fn write_results(rows: &[Row], commit: &str, dir: &Path, stem: &str) {
    let mut csv = String::from(
        "scenario,model,material,integrator,method,nodes,tets,settings,step_p50_us,step_p99_us,step_max_us,realtime_factor,rel_l2_error,max_nodal_error_m,probe_force_error,observable_error,observable,reference,stable,commit\n",
    );
    let mut json = Vec::new();
    for r in rows {
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{commit}",
            r.scenario,
            r.model,
            r.material,
            r.integrator,
            csv_text(&r.method),
            r.nodes,
            r.tets,
            csv_text(&r.settings),
            csv_num(r.p50_us),
            csv_num(r.p99_us),
            csv_num(r.max_us),
            csv_num(r.realtime_factor),
            csv_num(r.rel_l2),
            csv_num(r.max_nodal_m),
            csv_num(r.probe_force_error),
            csv_num(r.observable_error),
            csv_text(&r.observable),
            csv_text(&r.reference),
            r.stable,
        );
        json.push(serde_json::json!({
            "scenario": r.scenario,
            "model": r.model,
            "material": r.material,
            "integrator": r.integrator,
            "method": r.method,
            "nodes": r.nodes,
            "tets": r.tets,
            "settings": r.settings,
            "step_p50_us": num(r.p50_us),
            "step_p99_us": num(r.p99_us),
            "step_max_us": num(r.max_us),
            "realtime_factor": num(r.realtime_factor),
            "rel_l2_error": num(r.rel_l2),
            "max_nodal_error_m": num(r.max_nodal_m),
            "probe_force_error": num(r.probe_force_error),
            "observable_error": num(r.observable_error),
            "observable": r.observable,
            "reference": r.reference,
            "stable": r.stable,
            "commit": commit,
        }));
    }
    std::fs::create_dir_all(dir).expect("creating docs/bench");
    std::fs::write(dir.join(format!("{stem}.csv")), csv).expect("writing the CSV");
    std::fs::write(
        dir.join(format!("{stem}.json")),
        serde_json::to_string_pretty(&json).expect("json") + "\n",
    )
    .expect("writing the JSON");
}

// ---------------------------------------------------------------- Lamé sphere

const LAME: (f64, f64, f64, f64, f64) = (7e-3, 10e-3, 10e3, 0.3, 100.0);

fn lame_u_r(r: f64) -> f64 {
    let (a, b, e, nu, p) = LAME;
    p * a.powi(3) / (e * (b.powi(3) - a.powi(3)))
        * ((1.0 - 2.0 * nu) * r + (1.0 + nu) * b.powi(3) / (2.0 * r * r))
}

/// Relative L2 and max nodal error of positions `x` against the analytic field, and the mean
/// inner radial displacement.
fn lame_errors(mesh: &TetMesh, x: &[DVec3]) -> (f64, f64, f64) {
    let (mut num2, mut den2, mut max_e) = (0.0, 0.0, 0.0f64);
    for (p, q) in mesh.nodes.iter().zip(x) {
        let exact = p.normalize() * lame_u_r(p.length());
        let e = (*q - *p - exact).length();
        num2 += e * e;
        den2 += exact.length_squared();
        max_e = max_e.max(e);
    }
    let inner: Vec<u32> = {
        let mut v: Vec<u32> = mesh
            .surface("INNER")
            .expect("INNER")
            .triangles
            .iter()
            .flatten()
            .copied()
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    };
    let mean_ur = inner
        .iter()
        .map(|&i| (x[i as usize] - mesh.nodes[i as usize]).dot(mesh.nodes[i as usize].normalize()))
        .sum::<f64>()
        / inner.len() as f64;
    ((num2 / den2).sqrt(), max_e, mean_ur)
}

fn scenario_lame(quick: bool, rows: &mut Vec<Row>) {
    let (a, b, e, nu, p) = LAME;
    // (target tets, quadratic elements)
    let targets: &[(usize, bool)] = if quick {
        &[(1000, false), (3000, false), (1000, true)]
    } else {
        &[
            (1000, false),
            (2000, false),
            (5000, false),
            (10000, false),
            (1000, true),
            (2000, true),
        ]
    };
    let safeties: &[f64] = if quick { &[0.5] } else { &[0.5, 0.25] };
    let all_methods = methods(safeties);
    let exact_inner = lame_u_r(a);
    let reference = format!("analytic u_r(a) = {:.4} mm", exact_inner * 1e3);
    for &(target, quadratic) in targets {
        let mesh = if quadratic {
            haptic_model::mesh::generate::sphere_shell_quadratic(a, b, target)
        } else {
            sphere_shell(a, b, target)
        };
        for &model in MATERIALS {
            let mut mat = MaterialParams::from_youngs(e, nu, 1000.0);
            mat.mass_damping_per_s = 300.0;
            mat.model = model;
            let mut fem = FemModel::new(&mesh, mat).expect("sphere FEM");
            let node = |name: &str| mesh.node_group(name).expect("node group").nodes[0] as usize;
            fem.set_constraint(node("INNER_PZ"), 0b011);
            fem.set_constraint(node("INNER_NZ"), 0b011);
            fem.set_constraint(node("INNER_PX"), 0b110);
            let mut f_ext = vec![DVec3::ZERO; mesh.node_count()];
            add_pressure_forces(
                &mesh.surface("INNER").expect("INNER").triangles,
                &mesh.nodes,
                p,
                &mut f_ext,
            );
            // Static: the discretisation error alone.
            let mut x = mesh.nodes.clone();
            let t = Instant::now();
            let rep = solve_static(&fem, &f_ext, &mut x, &StaticParams::default());
            let solve_us = t.elapsed().as_secs_f64() * 1e6;
            let mut row = Row::new(
                "lame",
                material_label("static".into(), model),
                "static",
                &mesh,
            );
            row.material = model.scene_name();
            row.settings = "Newton + sparse Cholesky; time = whole solve".into();
            row.p50_us = solve_us;
            row.p99_us = solve_us;
            row.max_us = solve_us;
            row.reference = reference.clone();
            let x_static = x.clone();
            if let Ok(rep) = rep {
                let (l2, max_e, mean) = lame_errors(&mesh, &x);
                row.rel_l2 = l2;
                row.max_nodal_m = max_e;
                row.observable_error = (mean - exact_inner).abs() / exact_inner;
                row.observable = format!(
                    "mean u_r(a) = {:.4} mm ({} Newton it.)",
                    mean * 1e3,
                    rep.iterations
                );
                row.stable = true;
            }
            row.print();
            rows.push(row);
            // The corotational force costs a polar decomposition per element (about 30 times
            // the StVK force): the other materials run dynamically on the two coarse meshes.
            let dynamic =
                model == MaterialModel::StVenantKirchhoff || (target <= 2000 && !quadratic);
            for m in all_methods
                .iter()
                .filter(|m| dynamic && m.material == model)
            {
                let mut row = Row::new("lame", m.label(), m.kind.name(), &mesh);
                row.material = model.scene_name();
                row.reference = reference.clone();
                match run_loaded_with(&fem, &m.params(), &f_ext, 0.02, 3.0) {
                    Err(e) => row.settings = format!("refused: {e}"),
                    Ok(mut run) => {
                        row.settings = format!(
                            "tick 1 ms, {}, alpha 300/s, {}",
                            m.step_text(run.substeps),
                            steady_text(run.time_s, 3.0)
                        );
                        row.set_times(&mut run.tick_us, 1e-3);
                        row.stable = run.stable && run.x.iter().all(|v| v.is_finite());
                        if row.stable {
                            let (l2, max_e, mean) = lame_errors(&mesh, &run.x);
                            row.rel_l2 = l2;
                            row.max_nodal_m = max_e;
                            row.observable_error = (mean - exact_inner).abs() / exact_inner;
                            let settle = rel_diff(&mesh.nodes, &run.x, &x_static);
                            row.observable = format!(
                                "mean u_r(a) = {:.4} mm; vs same-mesh static {:.2e}",
                                mean * 1e3,
                                settle
                            );
                        }
                    }
                }
                row.print();
                rows.push(row);
            }
        }
    }
}

/// "steady after T ms", or "not steady at the T ms cap".
fn steady_text(time_s: f64, cap_s: f64) -> String {
    if time_s >= cap_s - 1e-9 {
        format!("not steady at the {:.0} ms cap", cap_s * 1e3)
    } else {
        format!("steady after {:.0} ms", time_s * 1e3)
    }
}

/// `|x - y| / |y - rest|` over all nodes.
fn rel_diff(rest: &[DVec3], x: &[DVec3], y: &[DVec3]) -> f64 {
    let (mut n, mut d) = (0.0, 0.0);
    for ((r, x), y) in rest.iter().zip(x).zip(y) {
        n += (*x - *y).length_squared();
        d += (*y - *r).length_squared();
    }
    (n / d).sqrt()
}

// ---------------------------------------------------------------- cantilever

const BD_ALPHA1: f64 = 0.30172;

fn scenario_cantilever(quick: bool, rows: &mut Vec<Row>) {
    let (len, h, e, nu): (f64, f64, f64, f64) = (0.1, 0.01, 1e5, 0.3);
    let inertia = h.powi(4) / 12.0;
    let load = e * inertia / (len * len); // alpha = 1
    // (cells across, quadratic elements)
    let ns: &[(usize, bool)] = if quick {
        &[(2, false), (1, true)]
    } else {
        &[(2, false), (3, false), (4, false), (1, true), (2, true)]
    };
    let reference = format!("Bisshopp-Drucker v/L = {BD_ALPHA1}");
    let all_methods = methods(&[0.5]);
    for &(n, quadratic) in ns {
        for &model in MATERIALS {
            let mut mesh = box_mesh(DVec3::new(len, h, h), [10 * n, n, n]);
            if quadratic {
                mesh = mesh.to_quadratic();
            }
            let mut mat = MaterialParams::from_youngs(e, nu, 1000.0);
            mat.mass_damping_per_s = 60.0;
            mat.model = model;
            let mut fem = FemModel::new(&mesh, mat).expect("beam FEM");
            let clamped = mesh
                .nodes_of_surfaces(&["XMIN".to_string()], "clamped")
                .expect("XMIN");
            fem.clamp_nodes(&clamped);
            let tip = &mesh.surface("XMAX").expect("XMAX").triangles;
            let area: f64 = tip.iter().map(|t| tri_area(&mesh.nodes, t)).sum();
            let mut f_ext = vec![DVec3::ZERO; mesh.node_count()];
            for t in tip {
                let share = load * tri_area(&mesh.nodes, t) / area / 3.0;
                for &i in t {
                    f_ext[i as usize].z -= share;
                }
            }
            let tip_nodes = mesh
                .nodes_of_surfaces(&["XMAX".to_string()], "tip")
                .expect("XMAX");
            let deflection = |x: &[DVec3]| {
                -tip_nodes
                    .iter()
                    .map(|&i| x[i as usize].z - mesh.nodes[i as usize].z)
                    .sum::<f64>()
                    / tip_nodes.len() as f64
                    / len
            };
            // Static with 10 load increments.
            let mut x = mesh.nodes.clone();
            let t = Instant::now();
            let mut ok = true;
            for k in 1..=10 {
                let fk: Vec<DVec3> = f_ext.iter().map(|f| *f * (k as f64 / 10.0)).collect();
                if solve_static(
                    &fem,
                    &fk,
                    &mut x,
                    &StaticParams {
                        rel_tol: 1e-9,
                        ..StaticParams::default()
                    },
                )
                .is_err()
                {
                    ok = false;
                    break;
                }
            }
            let solve_us = t.elapsed().as_secs_f64() * 1e6;
            let mut row = Row::new(
                "cantilever",
                material_label("static".into(), model),
                "static",
                &mesh,
            );
            row.material = model.scene_name();
            row.settings = format!(
                "{}x{n}x{n} cells, 10 load steps, Newton; time = whole solve",
                10 * n
            );
            row.p50_us = solve_us;
            row.p99_us = solve_us;
            row.max_us = solve_us;
            row.reference = reference.clone();
            let static_v = deflection(&x);
            if ok {
                row.stable = true;
                row.observable_error = (static_v - BD_ALPHA1).abs() / BD_ALPHA1;
                row.observable = format!("v/L = {static_v:.5}");
            }
            row.print();
            rows.push(row);
            let cap = if quick { 1.0 } else { 3.0 };
            // The other materials (corotational: a polar decomposition per element) run
            // dynamically on the two coarser meshes only.
            let dynamic = model == MaterialModel::StVenantKirchhoff || n <= 3;
            for m in all_methods
                .iter()
                .filter(|m| dynamic && m.material == model)
            {
                let mut row = Row::new("cantilever", m.label(), m.kind.name(), &mesh);
                row.material = model.scene_name();
                row.reference = reference.clone();
                match run_loaded_with(&fem, &m.params(), &f_ext, 0.3, cap) {
                    Err(e) => row.settings = format!("refused: {e}"),
                    Ok(mut run) => {
                        row.settings = format!(
                            "{}x{n}x{n} cells, {}, alpha 60/s, {}",
                            10 * n,
                            m.step_text(run.substeps),
                            steady_text(run.time_s, cap)
                        );
                        row.set_times(&mut run.tick_us, 1e-3);
                        row.stable = run.stable && run.x.iter().all(|v| v.is_finite());
                        if row.stable {
                            let v = deflection(&run.x);
                            row.observable_error = (v - BD_ALPHA1).abs() / BD_ALPHA1;
                            row.observable =
                                format!("v/L = {v:.5} (static on this mesh {static_v:.5})");
                        }
                    }
                }
                row.print();
                rows.push(row);
            }
        }
    }
}

fn tri_area(x: &[DVec3], t: &[u32; 3]) -> f64 {
    let [a, b, c] = t.map(|i| x[i as usize]);
    0.5 * (b - a).cross(c - a).length()
}

// ---------------------------------------------------------------- LV probe

const DEPTHS_MM: [f64; 6] = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0];

/// Quasi-static probe solution on one mesh: device force per depth and the positions at the
/// last depth.
#[derive(Debug, Clone)]
struct ProbeCurve {
    forces_n: Vec<f64>,
    x_last: Vec<DVec3>,
}

/// Static equilibrium with the probe coupling at each depth of [`DEPTHS_MM`]: for a trial
/// coupling force `F`, the patch load `-F w_i n` (patch, weights, normal of the probe at the
/// current positions) is applied and the body solved statically; the probe then reports the
/// coupling force `k (r - s)` at the new positions. A bracketed regula falsi (Illinois) on `F`
/// makes the two agree. Returns `Err` if Newton or the iteration fails.
fn probe_static(scene: &Scene) -> Result<ProbeCurve, String> {
    probe_static_at(scene, &DEPTHS_MM)
}

/// [`probe_static`] at the given depths, mm (increasing).
fn probe_static_at(scene: &Scene, depths_mm: &[f64]) -> Result<ProbeCurve, String> {
    let mut fem = FemModel::with_smoothing(&scene.mesh, scene.material, scene.strain_smoothing)
        .map_err(|e| e.to_string())?;
    fem.clamp_nodes(&scene.clamped_nodes);
    let mut probe = Probe::new(scene.probe, scene.touchable.clone(), fem.rest());
    let n = fem.node_count();
    let mut x = fem.rest().to_vec();
    let params = StaticParams {
        rel_tol: 1e-8,
        ..StaticParams::default()
    };
    let mut forces = Vec::new();
    let mut f_prev = 0.0;
    // The last in-contact patch (nodes, weights) and normal: a trial force that pushes the
    // surface beyond the probe still needs a patch to act on.
    let mut patch: Vec<(u32, f64)> = Vec::new();
    let mut normal = DVec3::ZERO;
    let debug = std::env::var_os("PRECISION_DEBUG").is_some();
    let (kc, r) = (scene.probe.coupling_stiffness_n_per_m, scene.probe.radius_m);
    for (k, d) in depths_mm.iter().enumerate() {
        let device = device_at(d * 1e-3);
        let mut f = if k == 0 {
            0.005 * d / DEPTHS_MM[0]
        } else {
            f_prev * (d / depths_mm[k - 1])
        };
        // Outer: freeze the probe patch (nodes, weights, normal) at the current positions; inner:
        // find the force F whose patch load puts the body where the frozen patch plane gives
        // k (r - s) = F. Repeat until the patch stops changing the force.
        for outer in 0..=12 {
            let st = probe.update(&x, device, DVec3::ZERO);
            if st.in_contact {
                let (nodes, w) = probe.patch();
                patch.clear();
                patch.extend(nodes.iter().copied().zip(w.iter().copied()));
                normal = st.normal;
            }
            if patch.is_empty() {
                return Err(format!("no contact at depth {d} mm"));
            }
            let mut f_ext = vec![DVec3::ZERO; n];
            let mut g = |f: f64, x: &mut Vec<DVec3>| -> Result<f64, String> {
                f_ext.iter_mut().for_each(|v| *v = DVec3::ZERO);
                let mut centre = DVec3::ZERO;
                for &(i, w) in &patch {
                    f_ext[i as usize] = -normal * (f * w);
                }
                let backup = x.clone();
                if solve_static(&fem, &f_ext, x, &params).is_err() {
                    // No equilibrium under this patch load (the wall gives way under a dead
                    // load): the trial force is too large.
                    x.copy_from_slice(&backup);
                    return Ok(f);
                }
                for &(i, w) in &patch {
                    centre += x[i as usize] * w;
                }
                let phi = (kc * (r - (device - centre).dot(normal))).max(0.0);
                Ok(f - phi)
            };
            // g(F) = F - k (r - s(F)) increases with F: bracket, then Illinois.
            let (mut lo, mut hi) = (f / 1.1, f * 1.1);
            let mut glo = g(lo, &mut x)?;
            while glo > 0.0 {
                hi = lo;
                lo /= 1.25;
                glo = g(lo, &mut x)?;
            }
            let mut ghi = g(hi, &mut x)?;
            while ghi < 0.0 {
                (lo, glo) = (hi, ghi);
                hi *= 1.25;
                ghi = g(hi, &mut x)?;
                if hi > 100.0 {
                    return Err(format!("no bracket at depth {d} mm"));
                }
            }
            let mut side = 0i8;
            let mut fi = hi;
            for it in 0..=80 {
                if it == 80 {
                    return Err(format!("no convergence at depth {d} mm: F in [{lo}, {hi}]"));
                }
                fi = (lo * ghi - hi * glo) / (ghi - glo);
                let gf = g(fi, &mut x)?;
                if gf.abs() <= 1e-8 * fi.max(1e-3) || (hi - lo) <= 1e-10 * hi {
                    break;
                }
                if gf < 0.0 {
                    (lo, glo) = (fi, gf);
                    if side == -1 {
                        ghi *= 0.5;
                    }
                    side = -1;
                } else {
                    (hi, ghi) = (fi, gf);
                    if side == 1 {
                        glo *= 0.5;
                    }
                    side = 1;
                }
            }
            let change = (fi - f).abs() / fi;
            f = fi;
            if debug {
                eprintln!("depth {d} mm outer {outer}: F = {f:.6e} N, change {change:.2e}");
            }
            if outer > 0 && change < 3e-4 {
                break;
            }
            if outer == 12 {
                eprintln!(
                    "lv-probe static: patch iteration at depth {d} mm stopped at change {change:.2e}"
                );
            }
        }
        f_prev = f;
        forces.push(f);
    }
    Ok(ProbeCurve {
        forces_n: forces,
        x_last: x,
    })
}

/// The dynamic press protocol with `Simulation::tick`. Returns the curve and tick times, or
/// the error that stopped it (refused plan or divergence).
fn probe_dynamic(scene: &Scene, quick: bool) -> Result<(ProbeCurve, Vec<f64>, u32), String> {
    let mut sim = Simulation::new(scene).map_err(|e| e.to_string())?;
    let (ramp, hold) = if quick { (0.08, 0.08) } else { (0.1, 0.1) };
    let tick = sim.tick_s();
    let seg_ticks = ((ramp + hold) / tick).round() as usize;
    let mut ticks_us = Vec::with_capacity(seg_ticks * DEPTHS_MM.len());
    let mut forces = Vec::new();
    let mut prev = -0.3e-3;
    for d in DEPTHS_MM {
        let d = d * 1e-3;
        let mut sum = 0.0;
        let mut count = 0;
        for k in 0..seg_ticks {
            let t = (k + 1) as f64 * tick;
            let s = t / ramp;
            let depth = prev + (d - prev) * smoothstep(s);
            let rate = (d - prev) / ramp * common::smoothstep_rate(s);
            let input = TickInput {
                device_position_m: Some(device_at(depth)),
                device_velocity_m_per_s: DVec3::new(-rate, 0.0, 0.0),
            };
            let t0 = Instant::now();
            let out = sim.tick(&input).map_err(|e| e.to_string())?;
            ticks_us.push(t0.elapsed().as_secs_f64() * 1e6);
            if t > ramp + hold / 2.0 {
                sum += out.force_on_device_n.length();
                count += 1;
            }
        }
        forces.push(sum / count as f64);
        prev = d;
    }
    let substeps = sim.plan().substeps;
    sim.recover_far_field();
    Ok((
        ProbeCurve {
            forces_n: forces,
            x_last: sim.state().x.clone(),
        },
        ticks_us,
        substeps,
    ))
}

fn epi_nodes(mesh: &TetMesh) -> Vec<u32> {
    let mut v: Vec<u32> = mesh
        .surface("EPI")
        .expect("EPI")
        .triangles
        .iter()
        .flatten()
        .copied()
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// The converged reference: curve and the reference epicardium for interpolation.
struct LvReference {
    tets: usize,
    curve: ProbeCurve,
    rest: Vec<DVec3>,
    epi: ContactSurface,
}

impl LvReference {
    /// Relative L2 and max error (m) of the epicardial displacement at the last depth.
    fn surface_errors(&self, mesh: &TetMesh, x: &[DVec3]) -> (f64, f64) {
        let (mut n2, mut d2, mut max_e) = (0.0, 0.0, 0.0f64);
        for i in epi_nodes(mesh) {
            let p = mesh.nodes[i as usize];
            let sp = self
                .epi
                .closest_global(&self.rest, p)
                .expect("reference surface");
            let tri = self.epi.triangles[sp.triangle as usize];
            let u_ref: DVec3 = (0..3)
                .map(|k| {
                    (self.curve.x_last[tri[k] as usize] - self.rest[tri[k] as usize]) * sp.bary[k]
                })
                .sum();
            let e = (x[i as usize] - p - u_ref).length();
            n2 += e * e;
            d2 += u_ref.length_squared();
            max_e = max_e.max(e);
        }
        ((n2 / d2).sqrt(), max_e)
    }

    fn force_error(&self, forces: &[f64]) -> f64 {
        forces
            .iter()
            .zip(&self.curve.forces_n)
            .map(|(f, r)| (f - r).abs() / r)
            .fold(0.0, f64::max)
    }
}

/// The built-in `lv` scene on `lv_shell(tets)`, with quadratic elements if `quadratic`.
fn lv_scene_order(tets: usize, quadratic: bool) -> Scene {
    if quadratic {
        common::lv_scene_on(haptic_model::mesh::generate::lv_shell_quadratic(tets))
    } else {
        lv_scene(tets)
    }
}

fn lv_reference(
    (tets, quadratic): (usize, bool),
    model: MaterialModel,
    fresh: bool,
    cache_dir: &Path,
) -> LvReference {
    let mut scene = lv_scene_order(tets, quadratic);
    scene.material.model = model;
    // St. Venant-Kirchhoff keeps the key and file name it had before the other materials.
    let mut suffix = if model == MaterialModel::StVenantKirchhoff {
        String::new()
    } else {
        format!("_{}", model.scene_name())
    };
    if quadratic {
        suffix.push_str("_t10");
    }
    let key = format!(
        "lv_shell({tets}) E={} nu={} k={} r={} depths={DEPTHS_MM:?} nodes={}{suffix}",
        scene.material.youngs_modulus_pa(),
        scene.material.poisson_ratio(),
        scene.probe.coupling_stiffness_n_per_m,
        scene.probe.radius_m,
        scene.mesh.node_count()
    );
    let path = cache_dir.join(format!("lv_probe_reference_{tets}{suffix}.json"));
    let cached = (!fresh)
        .then(|| std::fs::read_to_string(&path).ok())
        .flatten()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .filter(|v| v["key"] == key.as_str())
        .map(|v| {
            let forces: Vec<f64> = serde_json::from_value(v["forces_n"].clone()).expect("forces");
            let xs: Vec<[f64; 3]> = serde_json::from_value(v["x_last"].clone()).expect("x");
            ProbeCurve {
                forces_n: forces,
                x_last: xs.into_iter().map(DVec3::from_array).collect(),
            }
        });
    let curve = match cached {
        Some(c) => {
            println!("lv-probe reference: cached {}", path.display());
            c
        }
        None => {
            let t = Instant::now();
            let c = probe_static(&scene).expect("lv-probe reference static solve");
            println!(
                "lv-probe reference ({}): static solve on {} tets took {:.1} s",
                model.scene_name(),
                scene.mesh.tet_count(),
                t.elapsed().as_secs_f64()
            );
            let v = serde_json::json!({
                "key": key,
                "forces_n": c.forces_n,
                "x_last": c.x_last.iter().map(|p| p.to_array()).collect::<Vec<_>>(),
            });
            std::fs::create_dir_all(cache_dir).expect("cache dir");
            std::fs::write(&path, v.to_string()).expect("writing reference cache");
            c
        }
    };
    println!(
        "lv-probe reference ({}) forces (N) at {DEPTHS_MM:?} mm: {:?}",
        model.scene_name(),
        curve
            .forces_n
            .iter()
            .map(|f| (f * 1e4).round() / 1e4)
            .collect::<Vec<_>>()
    );
    LvReference {
        tets: scene.mesh.tet_count(),
        epi: ContactSurface::new(
            scene.mesh.surface("EPI").expect("EPI").triangles.clone(),
            scene.mesh.node_count(),
        ),
        rest: scene.mesh.nodes,
        curve,
    }
}

/// The LV reference mesh: `lv_shell(2000)` (2 010 elements) with quadratic elements. The
/// former reference, linear elements on `lv_shell(10000)` (10 017 tets), is 20-30 % stiffer
/// than the quadratic solutions, which agree among themselves: linear tetrahedra lock in
/// the bending of the 3 mm wall (see the `static` rows and the README).
const LV_REFERENCE: (usize, bool) = (2000, true);

fn scenario_lv(quick: bool, fresh: bool, cache_dir: &Path, rows: &mut Vec<Row>) {
    let lv_materials: &[MaterialModel] = if quick { &MATERIALS[..1] } else { LV_MATERIALS };
    let references: Vec<(MaterialModel, LvReference, String)> = lv_materials
        .iter()
        .map(|&m| {
            let r = lv_reference(LV_REFERENCE, m, fresh, cache_dir);
            let text = format!(
                "static with probe coupling on lv_shell ({} {} tets, {}): F(3 mm) = {:.4} N",
                r.tets,
                if LV_REFERENCE.1 {
                    "quadratic"
                } else {
                    "linear"
                },
                m.scene_name(),
                r.curve.forces_n[DEPTHS_MM.len() - 1]
            );
            (m, r, text)
        })
        .collect();
    // The former reference (linear elements on lv_shell(10000)) against the new one.
    if !quick {
        let old = lv_reference(
            (10000, false),
            MaterialModel::StVenantKirchhoff,
            fresh,
            cache_dir,
        );
        let (_, reference, ref_text) = &references[0];
        let mesh = lv_scene(10000).mesh;
        let mut row = Row::new("lv-probe", "static".into(), "static", &mesh);
        row.reference = ref_text.clone();
        row.settings = "static with probe coupling per depth (the former reference; cached)".into();
        fill_lv_errors(&mut row, reference, &mesh, &old.curve, DEPTHS_MM.len() - 1);
        row.print();
        rows.push(row);
    }
    // (target tets, quadratic elements, strain smoothing)
    let (none, edge) = (StrainSmoothing::None, StrainSmoothing::Edge);
    let targets: &[(usize, bool, StrainSmoothing)] = if quick {
        &[(1000, false, none), (300, true, none)]
    } else {
        &[
            (1000, false, none),
            (2000, false, none),
            (5000, false, none),
            (2000, false, edge),
            (5000, false, edge),
            (300, true, none),
            (500, true, none),
            (1000, true, none),
        ]
    };
    // (safety factor, largest target it is run at: small steps on big meshes cost minutes).
    let safeties: &[f64] = if quick { &[0.5] } else { &[0.9, 0.5, 0.25] };
    let all_methods = methods(safeties);
    let last = DEPTHS_MM.len() - 1;
    for &(target, quadratic, smoothing) in targets {
        let mut base_scene = lv_scene_order(target, quadratic);
        base_scene.strain_smoothing = smoothing;
        for (model, reference, ref_text) in &references {
            let mut scene = base_scene.clone();
            scene.material.model = *model;
            // Static on this mesh: the discretisation error alone.
            let mut row = Row::new(
                "lv-probe",
                material_label("static".into(), *model),
                "static",
                &scene.mesh,
            )
            .smoothed(smoothing);
            row.material = model.scene_name();
            row.reference = ref_text.clone();
            row.settings = "static with probe coupling per depth; time = whole curve".into();
            let t = Instant::now();
            match probe_static(&scene) {
                Ok(c) => {
                    let us = t.elapsed().as_secs_f64() * 1e6;
                    (row.p50_us, row.p99_us, row.max_us) = (us, us, us);
                    fill_lv_errors(&mut row, reference, &scene.mesh, &c, last);
                }
                Err(e) => row.settings = format!("failed: {e}"),
            }
            row.print();
            rows.push(row);
            for m in all_methods.iter().filter(|m| m.material == *model) {
                let mut sc = scene.clone();
                sc.integrator.kind = m.kind;
                sc.integrator.safety_factor = m.sf;
                sc.integrator.cg_max_iterations = m.cg;
                sc.integrator.max_substeps = 1000;
                let mut row =
                    Row::new("lv-probe", m.label(), m.kind.name(), &scene.mesh).smoothed(smoothing);
                row.material = model.scene_name();
                row.reference = ref_text.clone();
                match probe_dynamic(&sc, quick) {
                    Ok((c, mut ticks, sub)) => {
                        row.settings =
                            format!("tick 1 ms, {}; staircase 0.5..3 mm", m.step_text(sub));
                        row.set_times(&mut ticks, sc.integrator.tick_s);
                        fill_lv_errors(&mut row, reference, &scene.mesh, &c, last);
                    }
                    Err(e) => row.settings = format!("{}: {e}", m.label()),
                }
                row.print();
                rows.push(row);
            }
        }
    }
}

/// Condensed rows of [`scenario_lv_h1`]: (strain smoothing, radius of the active region in
/// mm).
const CONDENSED_RUNS: &[(StrainSmoothing, f64)] = &[
    (StrainSmoothing::Edge, 5.0),
    (StrainSmoothing::Edge, 6.0),
    (StrainSmoothing::Edge, 7.0),
    (StrainSmoothing::Edge, 8.0),
    (StrainSmoothing::None, 7.0),
];

/// `lv-probe` on `lv_h1.msh` (17 924 linear tets; `--scenario lv-h1`, not part of the full
/// run, own output `docs/bench/precision-lv-h1.{csv,json,png,svg}`): standard and edge-smoothed
/// (ES-FEM-T4) elements, each with semi-implicit at 0.5 and symplectic Euler at 0.9 of the critical
/// step and backward Euler with CG capped at 5, and backward Euler on a contact-local active
/// region with the rest condensed ([`CONDENSED_RUNS`], `haptic_model::integrate::condensed`), against the
/// same converged reference as `lv-probe`. `LV_H1_ROWS=condensed` runs the condensed rows only.
/// Static curves on this mesh take minutes each (`--scenario lv-study`, README).
fn scenario_lv_h1(fresh: bool, cache_dir: &Path, rows: &mut Vec<Row>) {
    let Some(h1) = common::lv_h1_scene() else {
        eprintln!("lv_h1.msh not found: scenario lv-h1 skipped");
        return;
    };
    let model = MaterialModel::StVenantKirchhoff;
    let reference = lv_reference(LV_REFERENCE, model, fresh, cache_dir);
    let ref_text = format!(
        "static with probe coupling on lv_shell ({} quadratic tets, stvk): F(3 mm) = {:.4} N",
        reference.tets,
        reference.curve.forces_n[DEPTHS_MM.len() - 1]
    );
    let base = common::lv_scene_on(h1.mesh);
    // Semi-implicit at 0.5: at 0.9 it diverges on this mesh with standard elements (StVK
    // stiffens under the probe; ARCHITECTURE.md, "Safety factor 0.5").
    let runs = [
        (IntegratorKind::SemiImplicit, 0.5, 20),
        (IntegratorKind::SymplecticEuler, 0.9, 20),
        (IntegratorKind::BackwardEuler, 1.0, 5),
    ];
    for &(smoothing, radius_mm) in CONDENSED_RUNS {
        let mut sc = base.clone();
        sc.strain_smoothing = smoothing;
        sc.integrator.kind = IntegratorKind::BackwardEuler;
        sc.integrator.substeps = Some(1);
        // The contact point of the press: the probe centre at first contact minus its radius.
        sc.active_region = Some(ActiveRegion {
            centre_m: DVec3::new(
                common::CONTACT_X_M - sc.probe.radius_m,
                0.0,
                common::PROBE_Z_M,
            ),
            radius_m: radius_mm * 1e-3,
            stiffness_margin: DEFAULT_STIFFNESS_MARGIN,
        });
        // One label for every radius, so the radii form one work-precision curve.
        let method = "condensed backward-euler".to_string();
        let mut row =
            Row::new("lv-probe", method.clone(), "backward-euler", &sc.mesh).smoothed(smoothing);
        row.reference = ref_text.clone();
        let t0 = Instant::now();
        let sizes = match Simulation::new(&sc) {
            Ok(sim) => sim.condensed().map(|c| c.sizes()).unwrap_or_default(),
            Err(e) => {
                row.settings = format!("{method}: {e}");
                row.print();
                rows.push(row);
                continue;
            }
        };
        let setup_s = t0.elapsed().as_secs_f64();
        match probe_dynamic(&sc, false) {
            Ok((c, mut ticks, _)) => {
                row.settings = format!(
                    "lv_h1.msh, strain smoothing {}; tick 1 ms, active region r = {radius_mm} mm: one backward Euler step on the {} tets within it ({} equations, {} interface nodes, {} factor entries), the other {} condensed; set-up {setup_s:.1} s",
                    smoothing.name(),
                    sizes.active_tets,
                    sizes.equations,
                    sizes.interface_nodes,
                    sizes.factor_entries,
                    sc.mesh.tets.len() - sizes.active_tets,
                );
                row.set_times(&mut ticks, sc.integrator.tick_s);
                fill_lv_errors(&mut row, &reference, &sc.mesh, &c, DEPTHS_MM.len() - 1);
            }
            Err(e) => row.settings = format!("{method}: {e}"),
        }
        row.print();
        rows.push(row);
    }
    if std::env::var("LV_H1_ROWS").is_ok_and(|v| v == "condensed") {
        return;
    }
    for smoothing in [StrainSmoothing::None, StrainSmoothing::Edge] {
        for (kind, sf, cg) in runs {
            let m = Method {
                kind,
                sf,
                cg,
                material: model,
            };
            let mut sc = base.clone();
            sc.strain_smoothing = smoothing;
            sc.integrator.kind = kind;
            sc.integrator.safety_factor = sf;
            sc.integrator.cg_max_iterations = cg;
            sc.integrator.max_substeps = 1000;
            let mut row =
                Row::new("lv-probe", m.label(), kind.name(), &sc.mesh).smoothed(smoothing);
            row.reference = ref_text.clone();
            match probe_dynamic(&sc, false) {
                Ok((c, mut ticks, sub)) => {
                    row.settings = format!(
                        "lv_h1.msh, strain smoothing {}; tick 1 ms, {}; staircase 0.5..3 mm",
                        smoothing.name(),
                        m.step_text(sub)
                    );
                    row.set_times(&mut ticks, sc.integrator.tick_s);
                    fill_lv_errors(&mut row, &reference, &sc.mesh, &c, DEPTHS_MM.len() - 1);
                }
                Err(e) => row.settings = format!("{}: {e}", row.method),
            }
            row.print();
            rows.push(row);
        }
    }
}

/// Materials of the full `lv-probe` run. Each needs its own reference solve on the 10k-tet
/// mesh, which for the corotational material took longer than the whole run's budget, so
/// the other materials are compared on the Lamé and cantilever scenarios only (whose
/// references are analytic and small-strain, valid for all three).
const LV_MATERIALS: &[MaterialModel] = &[MaterialModel::StVenantKirchhoff];

fn fill_lv_errors(
    row: &mut Row,
    reference: &LvReference,
    mesh: &TetMesh,
    c: &ProbeCurve,
    last: usize,
) {
    let (l2, max_e) = reference.surface_errors(mesh, &c.x_last);
    row.rel_l2 = l2;
    row.max_nodal_m = max_e;
    row.probe_force_error = reference.force_error(&c.forces_n);
    let r = reference.curve.forces_n[last];
    row.observable_error = (c.forces_n[last] - r).abs() / r;
    row.observable = format!(
        "F(mm) = [{}] N",
        c.forces_n
            .iter()
            .map(|f| format!("{f:.4}"))
            .collect::<Vec<_>>()
            .join(" ")
    );
    row.stable = c.forces_n.iter().all(|f| f.is_finite()) && c.x_last.iter().all(|p| p.is_finite());
}

// ---------------------------------------------------------------- plots

const FONT_PATHS: [&str; 2] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
];

fn register_font() -> bool {
    for p in FONT_PATHS {
        if let Ok(bytes) = std::fs::read(p) {
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font(
                "sans-serif",
                plotters::style::FontStyle::Normal,
                bytes,
            )
            .is_ok()
            {
                return true;
            }
        }
    }
    false
}

fn plot_scenario(
    rows: &[Row],
    scenario: &str,
    ylabel: &str,
    base: &Path,
) -> Result<(), Box<dyn std::error::Error>> {
    let mut curves: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    for r in rows.iter().filter(|r| r.scenario == scenario && r.stable) {
        let (x, y) = (r.p50_us / 1000.0, r.plot_error());
        if x.is_finite() && x > 0.0 && y.is_finite() && y > 0.0 {
            curves.entry(r.method.clone()).or_default().push((x, y));
        }
    }
    if curves.is_empty() {
        return Ok(());
    }
    for pts in curves.values_mut() {
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    let all = curves.values().flatten();
    let (mut x0, mut x1, mut y0, mut y1) = (1.0f64, 1.0f64, 0.07f64, 0.07f64);
    for &(x, y) in all {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    let (x0, x1, y0, y1) = (x0 / 1.5, x1 * 1.5, y0 / 1.5, y1 * 1.5);
    let title = format!("{scenario}: error vs wall time per simulated ms");
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    {
        use plotters::prelude::*;
        let root = BitMapBackend::new(&png, (1250, 650)).into_drawing_area();
        draw_chart(root, &title, ylabel, &curves, (x0, x1, y0, y1))?;
        let root = SVGBackend::new(&svg, (1250, 650)).into_drawing_area();
        draw_chart(root, &title, ylabel, &curves, (x0, x1, y0, y1))?;
    }
    Ok(())
}

/// Element family of a method label: its base method (the label without the suffix) and
/// 0 = linear tets, 1 = quadratic (" T10"), 2 = edge-smoothed linear (" ES").
fn method_family(label: &str) -> (&str, usize) {
    if let Some(b) = label.strip_suffix(" T10") {
        (b, 1)
    } else if let Some(b) = label.strip_suffix(" ES") {
        (b, 2)
    } else {
        (label, 0)
    }
}

/// Draws one work-precision chart: the plot on the left, a legend panel on the right. Colour
/// = method (integrator and setting), marker = element family, so about 30 curves stay
/// readable with a dozen legend entries.
fn draw_chart<DB: plotters::prelude::DrawingBackend>(
    root: plotters::drawing::DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    ylabel: &str,
    curves: &BTreeMap<String, Vec<(f64, f64)>>,
    (x0, x1, y0, y1): (f64, f64, f64, f64),
) -> Result<(), Box<dyn std::error::Error>>
where
    DB::ErrorType: 'static,
{
    use plotters::prelude::*;
    // Tableau 10, then greys.
    const COLORS: [RGBColor; 12] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(127, 127, 127),
        RGBColor(188, 189, 34),
        RGBColor(23, 190, 207),
        RGBColor(60, 60, 60),
        RGBColor(170, 170, 170),
    ];
    root.fill(&WHITE)?;
    let (w, _) = root.dim_in_pixel();
    let (plot, legend) = root.split_horizontally(w.saturating_sub(350));
    let mut chart = ChartBuilder::on(&plot)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("wall time per simulated ms (ms); static: one whole solve")
        .y_desc(ylabel)
        .x_label_formatter(&|v| format!("{v:.3}"))
        .y_label_formatter(&|v| format!("{:.2}%", v * 100.0))
        .draw()?;
    let grey = RGBColor(120, 120, 120);
    let red = RGBColor(200, 60, 60);
    chart.draw_series(LineSeries::new(
        [(1.0, y0), (1.0, y1)],
        grey.stroke_width(2),
    ))?;
    chart.draw_series(LineSeries::new(
        [(x0, 0.07), (x1, 0.07)],
        red.stroke_width(2),
    ))?;
    let mut bases: Vec<&str> = curves.keys().map(|k| method_family(k).0).collect();
    bases.dedup();
    bases.sort_unstable();
    bases.dedup();
    let color_of = |base: &str| {
        let k = bases.iter().position(|b| *b == base).unwrap_or(0);
        COLORS[k % COLORS.len()]
    };
    for (name, pts) in curves {
        let (base, family) = method_family(name);
        let color = color_of(base);
        chart.draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))?;
        match family {
            0 => chart.draw_series(pts.iter().map(|&p| Cross::new(p, 5, color.stroke_width(2))))?,
            1 => chart.draw_series(pts.iter().map(|&p| Circle::new(p, 5, color.filled())))?,
            _ => chart.draw_series(
                pts.iter()
                    .map(|&p| TriangleMarker::new(p, 6, color.filled())),
            )?,
        };
    }
    // Legend panel (pixel coordinates).
    let font = ("sans-serif", 14).into_font();
    let black = BLACK.stroke_width(2);
    let mut y = 40;
    let line = |legend: &DrawingArea<DB, plotters::coord::Shift>,
                text: &str,
                style: ShapeStyle,
                y: &mut i32|
     -> Result<(), Box<dyn std::error::Error>> {
        legend.draw(&PathElement::new([(10, *y), (40, *y)], style))?;
        legend.draw(&Text::new(text.to_string(), (48, *y - 8), font.clone()))?;
        *y += 22;
        Ok(())
    };
    line(&legend, "1 ms haptic budget", grey.stroke_width(2), &mut y)?;
    line(&legend, "7 % force JND", red.stroke_width(2), &mut y)?;
    y += 10;
    let present: Vec<usize> = curves.keys().map(|k| method_family(k).1).collect();
    for (k, text) in [
        "linear tets",
        "quadratic tets (T10)",
        "linear tets, edge smoothing (ES)",
    ]
    .iter()
    .enumerate()
    .filter(|(k, _)| present.contains(k))
    {
        let c = (25, y);
        match k {
            0 => legend.draw(&Cross::new(c, 5, black))?,
            1 => legend.draw(&Circle::new(c, 5, BLACK.filled()))?,
            _ => legend.draw(&TriangleMarker::new(c, 6, BLACK.filled()))?,
        }
        legend.draw(&Text::new(text.to_string(), (48, y - 8), font.clone()))?;
        y += 22;
    }
    y += 10;
    for base in &bases {
        line(&legend, base, color_of(base).stroke_width(3), &mut y)?;
    }
    root.present()?;
    Ok(())
}

/// The work-precision plot of every scenario, `docs/precision-<scenario>.png/.svg`.
fn plot_all(rows: &[Row], root: &Path) {
    if register_font() {
        for (scenario, ylabel) in [
            ("lame", "relative L2 displacement error"),
            ("cantilever", "tip deflection error vs Bisshopp-Drucker"),
            ("lv-probe", "probe force error (max over 0.5..3 mm)"),
        ] {
            let base = root.join(format!("docs/precision-{scenario}"));
            match plot_scenario(rows, scenario, ylabel, &base) {
                Ok(()) => println!("plot {}.png/.svg", base.display()),
                Err(e) => eprintln!("plot {scenario}: {e}"),
            }
        }
    } else {
        eprintln!("no DejaVuSans.ttf found (apt-get install fonts-dejavu-core): plots skipped");
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let fresh = args.iter().any(|a| a == "--fresh-reference");
    let only: Option<&str> = args
        .iter()
        .position(|a| a == "--scenario")
        .and_then(|i| args.get(i + 1))
        .map(String::as_str);
    let root: PathBuf = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let commit = git_commit();
    let wall = Instant::now();
    let mut rows = Vec::new();
    let run = |name: &str| only.is_none_or(|o| o == name);
    if run("lame") {
        scenario_lame(quick, &mut rows);
    }
    if run("cantilever") {
        scenario_cantilever(quick, &mut rows);
    }
    let replot = args.iter().any(|a| a == "--replot");
    if replot {
        let rows = Row::read_for_plot(&root.join("docs/bench/precision.json"))
            .expect("reading docs/bench/precision.json");
        plot_all(&rows, &root);
        return;
    }
    if only == Some("lv-h1") {
        let mut rows = Vec::new();
        scenario_lv_h1(fresh, &root.join("target/bench"), &mut rows);
        let out_dir = root.join("docs/bench");
        write_results(&rows, &commit, &out_dir, "precision-lv-h1");
        if register_font() {
            let base = root.join("docs/precision-lv-h1");
            match plot_scenario(
                &rows,
                "lv-probe",
                "probe force error on lv_h1.msh (max over 0.5..3 mm)",
                &base,
            ) {
                Ok(()) => println!("plot {}.png/.svg", base.display()),
                Err(e) => eprintln!("plot lv-h1: {e}"),
            }
        }
        println!(
            "wrote {} rows to {} ({:.1} s)",
            rows.len(),
            out_dir.join("precision-lv-h1.{csv,json}").display(),
            wall.elapsed().as_secs_f64()
        );
        return;
    }
    if only == Some("lv-study") {
        // Static probe curves of linear and quadratic elements on the LV meshes (a study of
        // the discretisation error; prints only).
        // `h1:1` is `lv_h1.msh` (17 924 linear tets) with the built-in lv material and probe.
        let sizes: Vec<(String, bool)> = std::env::var("LV_STUDY")
            .unwrap_or_else(|_| "1000:1,1000:2,2000:2".into())
            .split(',')
            .map(|t| {
                let (n, o) = t.split_once(':').expect("tets:order");
                (n.to_string(), o == "2")
            })
            .collect();
        // LV_STUDY_NU overrides the Poisson ratio (E fixed); LV_STUDY_DEPTHS="0.5,1.5" the depths.
        let nu: Option<f64> = std::env::var("LV_STUDY_NU")
            .ok()
            .map(|v| v.parse().expect("nu"));
        let depths: Vec<f64> = std::env::var("LV_STUDY_DEPTHS").map_or(DEPTHS_MM.to_vec(), |v| {
            v.split(',').map(|d| d.parse().expect("depth mm")).collect()
        });
        for (tets, quad) in sizes {
            let mut scene = if tets == "h1" {
                let mesh = common::lv_h1_scene().expect("lv_h1.msh").mesh;
                common::lv_scene_on(if quad { mesh.to_quadratic() } else { mesh })
            } else {
                lv_scene_order(tets.parse().expect("tets"), quad)
            };
            if let Ok(name) = std::env::var("LV_STUDY_SMOOTHING") {
                scene.strain_smoothing = StrainSmoothing::from_name(&name).expect("smoothing");
            }
            if let Some(nu) = nu {
                let m = &mut scene.material;
                let e = m.youngs_modulus_pa();
                m.lambda_pa = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
                m.mu_pa = e / (2.0 * (1.0 + nu));
            }
            let t = Instant::now();
            let c = probe_static_at(&scene, &depths);
            println!(
                "lv-study {tets} tets order {}: {} nodes, {:.1} s: {:?}",
                if quad { 2 } else { 1 },
                scene.mesh.node_count(),
                t.elapsed().as_secs_f64(),
                c.map(|c| c.forces_n)
            );
        }
        return;
    }
    if only == Some("lv-dyn") {
        // Dynamic probe curves of given meshes and integrators (prints only):
        // LV_DYN="tets:order:integrator:safety,..."
        let spec = std::env::var("LV_DYN").unwrap_or_else(|_| "300:2:semi-implicit:0.5".into());
        for item in spec.split(',') {
            let f: Vec<&str> = item.split(':').collect();
            let mut scene = lv_scene_order(f[0].parse().expect("tets"), f[1] == "2");
            scene.integrator.kind = IntegratorKind::from_name(f[2]).expect("integrator");
            scene.integrator.safety_factor = f.get(3).map_or(0.5, |v| v.parse().expect("sf"));
            scene.integrator.cg_max_iterations = f.get(4).map_or(20, |v| v.parse().expect("cg"));
            scene.integrator.max_substeps = 1000;
            match probe_dynamic(&scene, false) {
                Ok((c, mut ticks, sub)) => {
                    ticks.sort_by(f64::total_cmp);
                    println!(
                        "lv-dyn {item}: {} nodes, {sub} sub-steps, tick p50 {:.0} us: {:?}",
                        scene.mesh.node_count(),
                        ticks[ticks.len() / 2],
                        c.forces_n
                    );
                }
                Err(e) => println!("lv-dyn {item}: {e}"),
            }
        }
        return;
    }
    if run("lv-probe") {
        scenario_lv(quick, fresh, &root.join("target/bench"), &mut rows);
    }
    let out_dir = root.join("docs/bench");
    write_results(&rows, &commit, &out_dir, "precision");
    println!(
        "wrote {} rows to {}",
        rows.len(),
        out_dir.join("precision.{csv,json}").display()
    );
    plot_all(&rows, &root);
    println!("total {:.1} s", wall.elapsed().as_secs_f64());
}
