//! How the hybrid scenes feel through the servo's interface (issue 46 section 3), pressed with
//! [`haptic_model::press`] as the daemon's servo ticks them: `lv-hybrid` (stable neo-Hookean,
//! the lv scene's organ) holds every depth to 4 mm steadily (no tick-to-tick change above the
//! 7 % force JND of the hold's force), also after the demo's 10 mm/s press and while it slides
//! half way round the ventricle, and its held force follows the sphere reference within the JND
//! from 0.5 to 4 mm. `ellipsoids-hybrid` holds its depths steadily and its force grows with the
//! depth.
//!
//! The reference is `benches/precision/lv_sphere_reference.csv` (the rigid 2 mm sphere on the
//! idealized LV, curved quadratic meshes refined under the probe to 0.21 mm, Richardson over
//! four nested levels; our own solver, so a self-convergence check, cross-checked by the
//! independent scikit-fem solve under `research/`), read here, in the device convention: the
//! device's travel past the sphere touching the analytic epicardium, the depth the press
//! commands.

use crate::common;

use glam::DVec3;
use haptic_model::body::SoftBody;
use haptic_model::press::{self, HoldParams, HoldReport, PressLine};
use haptic_model::scene::load_builtin;

/// One row of the sphere reference: depth (mm), force (N) and its uncertainty (N).
#[derive(Debug, Clone, Copy, PartialEq)]
struct ReferenceRow {
    depth_mm: f64,
    force_n: f64,
    uncertainty_n: f64,
}

/// The rows of the reference CSV text `csv` for `material` in `convention` (columns
/// `material,depth_convention,depth_mm,force_n,uncertainty_n,...`; `#` lines and the header
/// skipped).
fn reference_rows(csv: &str, material: &str, convention: &str) -> Vec<ReferenceRow> {
    csv.lines()
        .filter(|l| !l.starts_with('#') && !l.starts_with("material,"))
        .filter_map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            (c.len() >= 5 && c[0] == material && c[1] == convention).then(|| {
                let num = |i: usize| -> f64 {
                    c[i].parse()
                        .unwrap_or_else(|_| panic!("reference row {l}: column {i}"))
                };
                ReferenceRow {
                    depth_mm: num(2),
                    force_n: num(3),
                    uncertainty_n: num(4),
                }
            })
        })
        .collect()
}

/// The stable neo-Hookean reference in the device convention.
fn neo_hookean_device_reference() -> Vec<ReferenceRow> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/benches/precision/lv_sphere_reference.csv"
    );
    let csv = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let rows = reference_rows(&csv, "stable-neo-hookean", "device");
    assert!(
        rows.len() >= 5,
        "{path}: {} stable neo-Hookean rows",
        rows.len()
    );
    rows
}

/// Ramps of 0.3 s and holds of 0.6 s, the force averaged over the last 0.3 s.
const HOLDS: HoldParams = HoldParams {
    ramp_s: 0.3,
    hold_s: 0.6,
    average_s: 0.3,
};

fn lv_hybrid() -> Box<dyn SoftBody> {
    let scene = load_builtin("lv-hybrid").expect("lv-hybrid");
    haptic_model::build_body(&scene).expect("body")
}

/// Every hold steady within the JND and in contact throughout.
fn assert_steady(label: &str, holds: &[HoldReport]) {
    for h in holds {
        eprintln!(
            "{label}: device {:.2} mm, sphere {:.3} mm: {:.3} mN, largest tick change {:.2} %",
            h.device_depth_m * 1e3,
            h.sphere_depth_m * 1e3,
            h.force_n * 1e3,
            100.0 * h.steadiness()
        );
        assert_eq!(h.contact_ticks, h.hold_ticks, "{label}: contact lost");
        assert!(
            h.steadiness() <= common::FORCE_JND,
            "{label}: {:.2} % from one tick to the next at {:.2} mm",
            100.0 * h.steadiness(),
            h.device_depth_m * 1e3
        );
    }
}

/// Each hold within the JND of the reference row at its device depth.
fn assert_follows(label: &str, holds: &[HoldReport], reference: &[ReferenceRow]) {
    for h in holds {
        let depth_mm = h.device_depth_m * 1e3;
        let row = reference
            .iter()
            .find(|r| (r.depth_mm - depth_mm).abs() < 1e-9)
            .unwrap_or_else(|| panic!("no reference row at {depth_mm} mm"));
        let error = h.force_n / row.force_n - 1.0;
        eprintln!(
            "{label}: device {depth_mm:.2} mm: {:.3} mN against {:.3} +- {:.3} mN, {:+.1} %",
            h.force_n * 1e3,
            row.force_n * 1e3,
            row.uncertainty_n * 1e3,
            100.0 * error
        );
        assert!(
            error.abs() <= common::FORCE_JND,
            "{label}: {:+.1} % at {depth_mm:.2} mm",
            100.0 * error
        );
    }
}

#[test]
fn lv_hybrid_follows_the_neo_hookean_reference_and_holds_steady_to_4_mm() {
    // Before 2026-11-26 (St. Venant-Kirchhoff, a penalty probe): chatter from 0 to 107 /
    // 218 mN at 3 / 4 mm.
    let reference = neo_hookean_device_reference();
    let mut body = lv_hybrid();
    let line = PressLine::lv_probe(body.info().probe_radius_m);
    let depths = [0.5, 1.0, 2.0, 3.0, 4.0].map(|d| d * 1e-3);
    let (holds, _) = press::staircase(body.as_mut(), &line, &depths, &HOLDS, 1e-3).expect("press");
    assert_steady("lv-hybrid", &holds);
    assert_follows("lv-hybrid", &holds, &reference);
}

#[test]
fn lv_hybrid_holds_steady_after_the_demo_press() {
    // The demo's press: 10 mm/s to 3.7 mm, then a hold (before 2026-11-26: 0 to 186 mN from
    // one tick to the next).
    let mut body = lv_hybrid();
    let line = PressLine::lv_probe(body.info().probe_radius_m);
    let (hold, trace) =
        press::constant_speed_press(body.as_mut(), &line, 3.7e-3, 10e-3, 0.5, 1e-3).expect("press");
    assert_steady("lv-hybrid demo", &[hold]);
    // The force grows with the depth all the way in (to within the JND of a tick's change).
    let press = &trace.force_n[..trace.force_n.len() - hold.hold_ticks];
    let mut peak: f64 = 0.0;
    for f in press {
        peak = peak.max(f.length());
        assert!(
            f.length() >= peak * (1.0 - common::FORCE_JND),
            "{f} after {peak}"
        );
    }
}

#[test]
fn lv_hybrid_slides_half_way_round_without_a_jump() {
    // Pressed 2 mm, then slid at 20 mm/s half way round the ventricle at the probe's height
    // (before 2026-11-26: 10 to 42 mN, a 26 mN jump within a tick).
    let mut body = lv_hybrid();
    let r = body.info().probe_radius_m;
    let (stroke, _) = press::lv_half_turn(body.as_mut(), r, 2e-3, 20e-3, 1e-3).expect("stroke");
    eprintln!(
        "stroke: hold {:.3} mN, slide {:.3}..{:.3} mN, largest tick change {:.3} mN",
        stroke.hold.force_n * 1e3,
        stroke.force_min_n * 1e3,
        stroke.force_max_n * 1e3,
        stroke.max_tick_change_n * 1e3
    );
    assert_eq!(stroke.contact_ticks, stroke.slide_ticks, "contact lost");
    assert!(
        stroke.max_tick_change_n <= common::FORCE_JND * stroke.hold.force_n,
        "{:.2} % of the hold's force within a tick",
        100.0 * stroke.max_tick_change_n / stroke.hold.force_n
    );
}

#[test]
fn ellipsoids_hybrid_holds_steady_and_presses_harder_deeper() {
    let scene = load_builtin("ellipsoids-hybrid").expect("scene");
    let mut body = haptic_model::build_body(&scene).expect("body");
    let r = body.info().probe_radius_m;
    let line =
        PressLine::from_rest_surface(body.as_ref(), DVec3::new(15e-3, 0.0, 0.0), -DVec3::X, r)
            .expect("line");
    let depths = [0.5, 1.0, 2.0, 3.0, 4.0].map(|d| d * 1e-3);
    let (holds, _) = press::staircase(body.as_mut(), &line, &depths, &HOLDS, 1e-3).expect("press");
    assert_steady("ellipsoids-hybrid", &holds);
    for w in holds.windows(2) {
        assert!(
            w[1].force_n > w[0].force_n,
            "{:.3} mN at {:.1} mm after {:.3} mN",
            w[1].force_n * 1e3,
            w[1].device_depth_m * 1e3,
            w[0].force_n * 1e3
        );
    }
}

/// `lv-hybrid` with its lattice spacing (m) and its core's wanted tetrahedra changed.
fn lv_hybrid_refined(spacing_m: f64, core_target_tets: usize) -> Box<dyn SoftBody> {
    let mut scene = load_builtin("lv-hybrid").expect("lv-hybrid");
    let h = scene.hybrid.as_mut().expect("a hybrid scene");
    h.params.meshfree.spacing_m = spacing_m;
    h.core_target_tets = core_target_tets;
    haptic_model::build_body(&scene).expect("body")
}

#[test]
fn refining_the_lattice_or_the_core_moves_lv_hybrid_towards_the_reference() {
    // Issue 46 section 3: "refining the core or the particle spacing moves the force towards
    // the reference, not away". The scene's penalty is given per area
    // (`contact_stiffness_pa_per_m`): with 16 N/m per particle at every spacing the 0.5 mm
    // press moved away (+1.4 / +2.2 / +2.3 / +2.7 % at 0.3 / 0.26 / 0.23 / 0.2 mm,
    // docs/accuracy.md). The scene's lattice is 0.35 mm (since 2026-11-27, session 11).
    let reference = neo_hookean_device_reference();
    let depths = [0.5e-3, 1e-3];
    let press = |label: &str, mut body: Box<dyn SoftBody>| -> Vec<f64> {
        let line = PressLine::lv_probe(body.info().probe_radius_m);
        let (holds, _) =
            press::staircase(body.as_mut(), &line, &depths, &HOLDS, 1e-3).expect("press");
        assert_steady(label, &holds);
        holds
            .iter()
            .map(|h| {
                let depth_mm = h.device_depth_m * 1e3;
                let row = reference
                    .iter()
                    .find(|r| (r.depth_mm - depth_mm).abs() < 1e-9)
                    .expect("a reference row");
                h.force_n / row.force_n - 1.0
            })
            .collect()
    };
    let scene = press(
        "lv-hybrid (0.35 mm, 702 tets)",
        lv_hybrid_refined(0.35e-3, 700),
    );
    let finer_lattice = press("finer lattice (0.3 mm)", lv_hybrid_refined(0.3e-3, 700));
    let finer_core = press(
        "finer core (about 2 000 tets)",
        lv_hybrid_refined(0.35e-3, 2000),
    );
    for (k, depth) in depths.iter().enumerate() {
        eprintln!(
            "{:.1} mm: scene {:+.2} %, finer lattice {:+.2} %, finer core {:+.2} %",
            depth * 1e3,
            100.0 * scene[k],
            100.0 * finer_lattice[k],
            100.0 * finer_core[k]
        );
        for (label, refined) in [("lattice", finer_lattice[k]), ("core", finer_core[k])] {
            assert!(
                refined.abs() < scene[k].abs(),
                "a finer {label} moved the {:.1} mm press away from the reference: {:+.2} % after {:+.2} %",
                depth * 1e3,
                100.0 * refined,
                100.0 * scene[k]
            );
        }
    }
}

#[test]
fn reference_rows_are_read_by_material_and_convention() {
    let csv = "# a comment, with commas\n\
        material,depth_convention,depth_mm,force_n,uncertainty_n,observed_order\n\
        stable-neo-hookean,device,0.5,4.5e-3,1e-4,0.8\n\
        stable-neo-hookean,sphere,0.5,4.7e-3,9e-5,0.9\n\
        stvk,device,0.5,4.2e-3,3e-5,\n\
        stable-neo-hookean,device,1,1.0e-2,2e-4,\n";
    let rows = reference_rows(csv, "stable-neo-hookean", "device");
    assert_eq!(
        rows,
        [
            ReferenceRow {
                depth_mm: 0.5,
                force_n: 4.5e-3,
                uncertainty_n: 1e-4
            },
            ReferenceRow {
                depth_mm: 1.0,
                force_n: 1.0e-2,
                uncertainty_n: 2e-4
            }
        ]
    );
    // The shipped file has every depth the press test checks.
    let shipped = neo_hookean_device_reference();
    for d in [0.5, 1.0, 2.0, 3.0, 4.0] {
        assert!(
            shipped.iter().any(|r| r.depth_mm == d && r.force_n > 0.0),
            "{d} mm"
        );
    }
}
