//! `lv-h1` (`--scenario lv-h1`, not part of the full run; own output
//! `precision-lv-h1.{csv,json,png,svg}`): the `lv-probe` press on `lv_h1.msh` (17 924 linear
//! tets) with standard and edge-smoothed elements and with backward Euler on a contact-local
//! active region, the rest condensed, against the same converged references (force and
//! surface displacement) as `lv-probe`.

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::element::StrainSmoothing;
use haptic_model::fem::FemBody;
use haptic_model::integrate::condensed::{ActiveRegion, DEFAULT_STIFFNESS_MARGIN, TileMode};
use haptic_model::integrate::{IntegratorKind, LinearSolver};
use haptic_model::material::MaterialModel;
use haptic_model::scene::Scene;

use crate::common::lv_press::probe_dynamic;
use crate::common::{CONTACT_X_M, PROBE_Z_M, lv_h1_scene, lv_scene_on};
use crate::lv_probe::fill_lv_errors;
use crate::method::Method;
use crate::report::{Row, Scenario};
use crate::{Config, LvH1Rows};

/// Condensed rows of [`run`]: (strain smoothing, radius of the active region in mm).
const CONDENSED_RUNS: &[(StrainSmoothing, f64)] = &[
    (StrainSmoothing::Edge, 5.0),
    (StrainSmoothing::Edge, 6.0),
    (StrainSmoothing::Edge, 7.0),
    (StrainSmoothing::Edge, 8.0),
    (StrainSmoothing::None, 7.0),
];

/// The rows of `lv-probe` on `lv_h1.msh`: backward Euler on a contact-local active region with
/// the rest condensed ([`CONDENSED_RUNS`], `haptic_model::integrate::condensed`), then (unless
/// `--lv-h1-rows condensed`) the shipped scenes ([`scene_rows`]) and standard and edge-smoothed
/// (ES-FEM-T4) elements, each with semi-implicit at 0.5 and symplectic Euler at 0.9 of the
/// critical step and backward Euler with CG capped at 5; all but the scene rows St.
/// Venant-Kirchhoff. `--lv-h1-rows scenes`: the scene rows alone. No rows when `lv_h1.msh` is absent. Static curves on this mesh take minutes
/// each (the `lv_study` example).
pub fn run(cfg: &Config) -> Vec<Row> {
    let mut rows = Vec::new();
    let Some(h1) = lv_h1_scene() else {
        eprintln!("lv_h1.msh not found: scenario lv-h1 skipped");
        return rows;
    };
    if cfg.lv_h1_rows == LvH1Rows::Scenes {
        scene_rows(&mut rows);
        return rows;
    }
    let model = MaterialModel::StVenantKirchhoff;
    let ref_text = crate::lv_probe::sphere_reference_text(model);
    let mut base = lv_scene_on(h1.mesh);
    // The built-in lv scene's material is stable neo-Hookean since 2026-11-26: these rows are
    // labelled and referenced as St. Venant-Kirchhoff, so they must run it.
    base.material.model = model;
    // Semi-implicit at 0.5: at 0.9 it diverges on this mesh with standard elements (StVK
    // stiffens under the probe; ARCHITECTURE.md, "Safety factor 0.5").
    let runs = [
        (IntegratorKind::SemiImplicit, 0.5, 20),
        (IntegratorKind::SymplecticEuler, 0.9, 20),
        (IntegratorKind::BackwardEuler, 1.0, 5),
    ];
    for &(smoothing, radius_mm) in CONDENSED_RUNS {
        let row = condensed_row(&base, smoothing, radius_mm, &ref_text);
        row.print();
        rows.push(row);
    }
    if cfg.lv_h1_rows == LvH1Rows::Condensed {
        return rows;
    }
    scene_rows(&mut rows);
    for smoothing in [StrainSmoothing::None, StrainSmoothing::Edge] {
        for (kind, sf, cg) in runs {
            let m = Method {
                kind,
                sf,
                cg,
                solver: LinearSolver::Cg,
                material: model,
            };
            let mut sc = base.clone();
            sc.strain_smoothing = smoothing;
            sc.integrator.kind = kind;
            sc.integrator.safety_factor = sf;
            sc.integrator.cg_max_iterations = cg;
            sc.integrator.linear_solver = m.solver;
            sc.integrator.max_substeps = 1000;
            let mut row =
                Row::new(Scenario::LvProbe, m.label(), kind.name(), &sc.mesh).smoothed(smoothing);
            row.reference = ref_text.clone();
            match probe_dynamic(&sc, false) {
                Ok((c, ticks, sub)) => {
                    row.settings = format!(
                        "lv_h1.msh, strain smoothing {}; tick 1 ms, {}; staircase 0.5..3 mm",
                        smoothing.name(),
                        m.step_text(sub)
                    );
                    row.set_times(&ticks, sc.integrator.tick_s);
                    fill_lv_errors(&mut row, model, &c);
                }
                Err(e) => row.settings = format!("{}: {e}", row.method),
            }
            row.print();
            rows.push(row);
        }
    }
    rows
}

/// One row of [`CONDENSED_RUNS`]: backward Euler on the active region of `radius_mm` around
/// the contact point, the rest of `base` condensed, with `smoothing`.
fn condensed_row(base: &Scene, smoothing: StrainSmoothing, radius_mm: f64, ref_text: &str) -> Row {
    // St. Venant-Kirchhoff, as [`run`] sets it.
    let model = base.material.model;
    let mut sc = base.clone();
    sc.strain_smoothing = smoothing;
    sc.integrator.kind = IntegratorKind::BackwardEuler;
    sc.integrator.substeps = Some(1);
    // The contact point of the press: the probe centre at first contact minus its radius.
    sc.active_region = Some(ActiveRegion {
        centre_m: DVec3::new(CONTACT_X_M - sc.probe.radius_m, 0.0, PROBE_Z_M),
        radius_m: radius_mm * 1e-3,
        stiffness_margin: DEFAULT_STIFFNESS_MARGIN,
        follow: false,
        tiles: TileMode::Off,
    });
    // One label for every radius, so the radii form one work-precision curve.
    let method = "condensed backward-euler".to_string();
    let mut row = Row::new(
        Scenario::LvProbe,
        method.clone(),
        "backward-euler",
        &sc.mesh,
    )
    .smoothed(smoothing);
    row.reference = ref_text.to_string();
    let t0 = Instant::now();
    let sizes = match FemBody::new(&sc) {
        Ok(sim) => sim.condensed().map(|c| c.sizes()).unwrap_or_default(),
        Err(e) => {
            row.settings = format!("{method}: {e}");
            return row;
        }
    };
    let setup_s = t0.elapsed().as_secs_f64();
    match probe_dynamic(&sc, false) {
        Ok((c, ticks, _)) => {
            row.settings = format!(
                "lv_h1.msh, strain smoothing {}; tick 1 ms, active region r = {radius_mm} mm: one backward Euler step on the {} tets within it ({} equations, {} interface nodes, {} factor entries), the other {} condensed; set-up {setup_s:.1} s",
                smoothing.name(),
                sizes.active_tets,
                sizes.equations,
                sizes.interface_nodes,
                sizes.factor_entries,
                sc.mesh.tets.len() - sizes.active_tets,
            );
            row.set_times(&ticks, sc.integrator.tick_s);
            fill_lv_errors(&mut row, model, &c);
        }
        Err(e) => row.settings = format!("{method}: {e}"),
    }
    row
}

/// The shipped scenes on `lv_h1.msh` (`deploy/scenes/`), each pressed exactly as its file
/// configures it (material, strain smoothing, integrator, active region; stable neo-Hookean
/// today), against the sphere reference of its own material. Label "`<file stem>` (scene)",
/// which `readme::SHIPPED` matches. A scene that does not load is a row saying why.
pub fn scene_rows(rows: &mut Vec<Row>) {
    for stem in ["lv_h1", "lv_h1_es", "lv_h1_condensed"] {
        let path = crate::common::workspace_root().join(format!("deploy/scenes/{stem}.toml"));
        let method = format!("{stem} (scene)");
        let sc = match haptic_model::scene::load_scene_file(&path) {
            Ok(sc) => sc,
            Err(e) => {
                let mut row = Row::blank(Scenario::LvProbe, method.clone(), "-");
                row.settings = format!("{}: {e}", path.display());
                row.print();
                rows.push(row);
                continue;
            }
        };
        let model = sc.material.model;
        let mut row = Row::new(
            Scenario::LvProbe,
            method,
            sc.integrator.kind.name(),
            &sc.mesh,
        )
        .smoothed(sc.strain_smoothing)
        .material(model);
        row.reference = crate::lv_probe::sphere_reference_text(model);
        match probe_dynamic(&sc, false) {
            Ok((c, ticks, sub)) => {
                row.settings = format!(
                    "deploy/scenes/{stem}.toml as shipped: strain smoothing {}, {} ({}), {sub} sub-step(s) per 1 ms tick{}; staircase 0.5..3 mm",
                    sc.strain_smoothing.name(),
                    sc.integrator.kind.name(),
                    sc.integrator.linear_solver.name(),
                    if sc.active_region.is_some() {
                        ", contact-local active region, the rest condensed"
                    } else {
                        ""
                    },
                );
                row.set_times(&ticks, sc.integrator.tick_s);
                fill_lv_errors(&mut row, model, &c);
            }
            Err(e) => row.settings = format!("{}: {e}", row.method),
        }
        row.print();
        rows.push(row);
    }
}
