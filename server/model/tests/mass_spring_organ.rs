//! The mass-spring surface calibrated to its organ (issue 46 section 4): the built-in
//! `lv-surface-springs` pressed as a user feels it ([`press::staircase`], ramps of 0.5 s and
//! holds of 1.5 s through `SoftBody::tick`) at every point of its stored FEM reference
//! (`scene/calibrations/lv-surface-springs.reference.csv`: the lv-probe point's deep
//! stable neo-Hookean reference and our two-level solves at p1-p5, corrected to it), with its
//! run-time subdivision and without: the force of the never-subdivided surface within 10 % of
//! the reference at the measured sphere depth from 0.25 to 4 mm at every
//! point and on a node, an edge's midpoint and a triangle's centroid near the lv-probe point
//! (subdivided too since session 12), each
//! hold steady (the largest tick-to-tick change at most 7 % of the held force), a stroke
//! continuous, and the tick with the organ table allocation-free.

use crate::counting_alloc;

use counting_alloc::counted;
use haptic_model::DVec3;
use haptic_model::body::TickInput;
use haptic_model::mass_spring::organ::ReferencePoint;
use haptic_model::mass_spring::{MassSpringBody, OrganReference};
use haptic_model::press::{self, HoldParams, PressLine, lv_epicardium_point};
use haptic_model::scene::{Scene, load_builtin};

/// Device depths pressed at the scene's first three points, m.
const DEPTHS_M: [f64; 6] = [0.25e-3, 0.5e-3, 1e-3, 2e-3, 3e-3, 4e-3];
/// Device depths pressed at p3-p5, m (four: the test's cost).
const P345_DEPTHS_M: [f64; 4] = [0.25e-3, 1e-3, 2e-3, 4e-3];
/// The acceptance tolerance against the reference (issue 46 section 4), met by the coarse
/// surface at every reference point and depth since session 13 (the table read at the sphere's
/// depth below the organ on the coarse surface too: -1.7 to +6.7 %, lv-probe +6.7 % at
/// 0.25 mm; until then the kernel plane's travel, which ran 0.02 mm ahead of the sphere there:
/// +10.2 %, held to 11 %). Subdivided, the 10 % since
/// session 12 (two-ring areas kept while the probe stays in them, the depth read below the
/// organ's arcs: -1.9 to +9.7 % at the six points; session 5: -13.3 to +14.4 %, p5 -45.2 % at
/// 0.25 mm; docs/accuracy.md, "The spring surfaces, session 12" and "session 13").
const TOLERANCE: f64 = 0.10;
const SUBDIVIDED_TOLERANCE: f64 = 0.10;
/// Device depths of the node / edge / centroid presses, m.
const SITE_DEPTHS_M: [f64; 4] = [0.5e-3, 1e-3, 2e-3, 4e-3];
/// Their tolerance, never subdivided (the issue's; measured in session 13: -3.0 to +4.7 %;
/// session 5: -6.6 to +1.4 %) and subdivided (the since session 12: measured -0.6 to +2.7 %; session 5
/// -7.7 to +14.1 %).
const SITE_TOLERANCE: f64 = 0.10;
const SITE_SUBDIVIDED_TOLERANCE: f64 = 0.10;
/// The force JND: the largest tick-to-tick change allowed in a hold.
const JND: f64 = 0.07;

fn scene() -> Scene {
    load_builtin("lv-surface-springs").expect("built-in scene")
}

/// The scene's body with its organ table, subdivided as the scene says or never (`rings = 0`).
fn body(scene: &Scene, subdivided: bool) -> MassSpringBody {
    let ms = scene.mass_spring.as_ref().expect("a mass-spring scene");
    let mut params = ms.params;
    if !subdivided {
        params.subdivision.rings = 0;
    }
    let table = if subdivided {
        ms.table().expect("subdivision table")
    } else {
        None
    };
    let organ = ms.organ.as_ref().expect("the scene has a reference_file");
    MassSpringBody::new(
        ms.surface.clone(),
        &params,
        table,
        scene.probe,
        &scene.integrator,
        &scene.name,
    )
    .expect("body")
    .with_organ_table(organ.table().expect("organ table"))
    .expect("organ table fits")
}

fn reference(scene: &Scene) -> OrganReference {
    let ms = scene.mass_spring.as_ref().expect("a mass-spring scene");
    ms.organ.as_ref().expect("organ").reference.clone()
}

#[test]
fn lv_surface_springs_follows_its_reference_subdivided_and_not() {
    let scene = scene();
    let reference = reference(&scene);
    let names: Vec<&str> = reference.points().iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["lv-probe", "p1", "p2", "p3", "p4", "p5"]);
    assert_eq!(
        include_str!("../examples/springs_reference/lv_points.reference.csv"),
        include_str!("../src/scene/calibrations/lv-surface-springs.reference.csv"),
        "the scene's reference is springs_reference/lv_points.reference.csv"
    );
    let mut failures = Vec::new();
    for subdivided in [true, false] {
        for p in reference.points() {
            let tolerance = |_device_depth_m: f64| {
                if subdivided {
                    SUBDIVIDED_TOLERANCE
                } else {
                    TOLERANCE
                }
            };
            let depths: &[f64] = if ["p3", "p4", "p5"].contains(&p.name.as_str()) {
                &P345_DEPTHS_M
            } else {
                &DEPTHS_M
            };
            failures.extend(press_point(&scene, p, subdivided, depths, tolerance));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// Presses `p` (its press line; the lv-probe line for `lv-probe`) through the staircase of
/// `depths_m` (device depths, m), subdivided or not, printing each hold against the point's
/// reference at the measured sphere depth; returns the holds outside `tolerance(device depth)`,
/// unsteady (largest tick-to-tick change above the JND) or not in contact throughout.
fn press_point(
    scene: &Scene,
    p: &ReferencePoint,
    subdivided: bool,
    depths_m: &[f64],
    tolerance: impl Fn(f64) -> f64,
) -> Vec<String> {
    let mut body = body(scene, subdivided);
    let r = body.probe().params.radius_m;
    let line = if p.name == "lv-probe" {
        PressLine::lv_probe(r)
    } else {
        PressLine::at_surface_point(p.position_m, p.direction, r)
    };
    let tick = scene.integrator.tick_s;
    let (holds, _) =
        press::staircase(&mut body, &line, depths_m, &HoldParams::default(), tick).expect("press");
    let mut failures = Vec::new();
    for h in &holds {
        let want = p.force_at(h.sphere_depth_m);
        let e = h.force_n / want - 1.0;
        let line = format!(
            "{} {}: device {:.2} mm sphere {:.3} mm: {:.3} mN, reference {:.3} mN \
             ({:+.1} %), steadiness {:.2} %",
            p.name,
            if subdivided { "subdivided" } else { "coarse" },
            h.device_depth_m * 1e3,
            h.sphere_depth_m * 1e3,
            h.force_n * 1e3,
            want * 1e3,
            100.0 * e,
            100.0 * h.steadiness()
        );
        eprintln!("{line}");
        if e.abs() > tolerance(h.device_depth_m)
            || h.steadiness() > JND
            || h.contact_ticks != h.hold_ticks
        {
            failures.push(line);
        }
    }
    failures
}

/// Linear interpolation of a target curve (N at `xs`, m) at `x`, through the origin below the
/// first depth (as [`haptic_model::mass_spring::organ::ReferencePoint::force_at`]).
fn curve_at(xs: &[f64], ys: &[f64], x: f64) -> f64 {
    let n = xs.len();
    if x <= xs[0] {
        return ys[0] * (x / xs[0]).max(0.0);
    }
    let k = xs.partition_point(|&v| v < x).clamp(1, n - 1);
    let t = (x - xs[k - 1]) / (xs[k] - xs[k - 1]);
    ys[k - 1] + t * (ys[k] - ys[k - 1])
}

/// Wherever the probe lands: near the lv-probe point, on the coarse node closest to it, on the
/// midpoint of one of its edges and on the centroid of one of its triangles (the centroid is
/// no site of the table: its factor is interpolated), each pressed along the analytic
/// epicardium's inward normal under the site (the line's depth zero where the sphere touches
/// the analytic surface), subdivided and not, within the tolerance of the reference
/// interpolated to the site.
#[test]
fn lv_surface_springs_answers_alike_on_nodes_edges_and_centroids() {
    let scene = scene();
    let reference = reference(&scene);
    let ms = scene.mass_spring.as_ref().expect("a mass-spring scene");
    let axis = ms.organ.as_ref().expect("organ").axis;
    let (s, rest) = (&ms.surface, ms.surface.rest());
    let probe = DVec3::new(9.682e-3, 0.0, -5e-3);
    let dist = |i: u32| (rest[i as usize] - probe).length();
    let n = (0..s.node_count() as u32)
        .min_by(|&a, &b| dist(a).total_cmp(&dist(b)))
        .expect("nodes");
    let tri = s.triangles()[s.triangles_at(n)[0] as usize];
    let other = *tri
        .iter()
        .find(|&&j| j != n)
        .expect("a triangle has three nodes");
    let p = |i: u32| rest[i as usize];
    let sites = [
        ("node", p(n)),
        ("edge midpoint", 0.5 * (p(n) + p(other))),
        ("centroid", (p(tri[0]) + p(tri[1]) + p(tri[2])) / 3.0),
    ];
    let mut failures = Vec::new();
    for subdivided in [true, false] {
        for (name, q) in sites {
            let (point, inward) = lv_epicardium_point(q.z, q.y.atan2(q.x));
            let target = reference.target_at(axis, point);
            let mut body = body(&scene, subdivided);
            let line = PressLine::at_surface_point(point, inward, body.probe().params.radius_m);
            let (holds, _) = press::staircase(
                &mut body,
                &line,
                &SITE_DEPTHS_M,
                &HoldParams::default(),
                scene.integrator.tick_s,
            )
            .expect("press");
            for h in &holds {
                let want = curve_at(reference.depths_m(), &target, h.sphere_depth_m);
                let e = h.force_n / want - 1.0;
                let line = format!(
                    "{name} {}: device {:.2} mm sphere {:.3} mm: {:.3} mN, reference {:.3} mN \
                     ({:+.1} %), steadiness {:.2} %",
                    if subdivided { "subdivided" } else { "coarse" },
                    h.device_depth_m * 1e3,
                    h.sphere_depth_m * 1e3,
                    h.force_n * 1e3,
                    want * 1e3,
                    100.0 * e,
                    100.0 * h.steadiness()
                );
                eprintln!("{line}");
                let tolerance = if subdivided {
                    SITE_SUBDIVIDED_TOLERANCE
                } else {
                    SITE_TOLERANCE
                };
                if e.abs() > tolerance || h.steadiness() > JND {
                    failures.push(line);
                }
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// A stroke reads the organ table continuously: pressed 2 mm at lv-probe and slid half way
/// round the ventricle at 20 mm/s (issue 46's stroke, [`press::lv_half_turn`]), the probe in
/// contact throughout and no tick-to-tick change above 7 % of the hold's force, never
/// subdivided (the table is read at the probe's foot on the rest surface, which slides with
/// it; measured 0.41 %) and subdivided as shipped: the subdivision events along the stroke (a
/// new two-ring area each time the probe leaves the last one) render the force blended over
/// `EVENT_BLEND_TICKS` (measured 2.5 %; 73.8 % before the blend, when this bound was 75 %).
#[test]
fn a_stroke_reads_the_organ_table_continuously() {
    let scene = scene();
    for subdivided in [false, true] {
        let mut body = body(&scene, subdivided);
        let r = body.probe().params.radius_m;
        let (report, _) = press::lv_half_turn(&mut body, r, 2e-3, 20e-3, scene.integrator.tick_s)
            .expect("stroke");
        let hold = report.hold.force_n;
        let change = report.max_tick_change_n / hold;
        eprintln!(
            "stroke {}: hold {:.3} mN, slide {:.3}..{:.3} mN, largest tick change {:.3} mN \
             ({:.2} % of the hold)",
            if subdivided { "subdivided" } else { "coarse" },
            hold * 1e3,
            report.force_min_n * 1e3,
            report.force_max_n * 1e3,
            report.max_tick_change_n * 1e3,
            100.0 * change
        );
        assert!(change <= JND, "{:.2} %", 100.0 * change);
        assert_eq!(report.contact_ticks, report.slide_ticks);
    }
}

#[test]
fn a_tick_with_the_organ_table_does_not_allocate() {
    let scene = scene();
    let mut body = body(&scene, true);
    let r = body.probe().params.radius_m;
    let line = PressLine::lv_probe(r);
    let across = DVec3::new(0.0, 1.0, 0.0);
    body.tick(&TickInput::default()).expect("tick");
    let mut allocations = 0;
    for t in 0..1500 {
        // Press to 3 mm, slide 8 mm sideways (subdivision events: since session 15 an area
        // is kept while the probe's rest foot stays in it, which a 4 mm slide on the LV's
        // two-ring area did), lift off.
        let p = match t {
            0..=499 => line.device_at(3e-3 * t as f64 / 500.0),
            500..=999 => line.device_at(3e-3) + across * (8e-3 * (t - 500) as f64 / 500.0),
            _ => line.device_at(-2e-3),
        };
        let input = TickInput {
            device_position_m: Some(p),
            device_velocity_m_per_s: DVec3::ZERO,
        };
        allocations += counted(|| body.tick(&input).expect("tick")).1;
    }
    assert!(body.contact_factor() != 1.0, "the organ table was used");
    assert!(
        body.event_stats().subdivisions >= 2,
        "{:?}",
        body.event_stats()
    );
    assert_eq!(allocations, 0);
}
