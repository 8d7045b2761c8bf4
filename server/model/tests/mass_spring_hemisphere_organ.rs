//! `hemisphere-springs` calibrated to the FEM of its own solid (issue 46 section 4): the
//! built-in scene pressed as a user feels it ([`press::staircase`], ramps of 0.5 s and holds of
//! 1.5 s through `SoftBody::tick`) along the inward normal at each point of its stored
//! reference (`scene/calibrations/hemisphere-springs.reference.csv`: the solid half ball of
//! radius 50 mm, base clamped, stable neo-Hookean E = 14.5 kPa, nu = 0.45, pressed by the
//! scene's exact 4 mm sphere; our `haptic-solve --indent` on two mesh levels, hmin 1.2 and
//! 0.85 mm: a self-convergence check; it does not depend on the spring mesh, 4 mm edges since
//! session 13), never subdivided and with the scene's one-ring subdivision: the
//! force against the reference at the measured sphere depth within the tolerances below (the
//! issue's 10 % where the surface meets it, the measured bound elsewhere: docs/accuracy.md,
//! "hemisphere-springs calibrated to its solid"), every hold steady (the largest tick-to-tick
//! change at most 7 % of the held force) and in contact throughout.

use haptic_model::mass_spring::organ::ReferencePoint;
use haptic_model::mass_spring::{MassSpringBody, OrganReference};
use haptic_model::press::{self, HoldParams, PressLine};
use haptic_model::scene::{Scene, load_builtin};

/// Device depths pressed, m (four of the staircase 0.25-4 mm: the test's cost).
const DEPTHS_M: [f64; 4] = [0.25e-3, 1e-3, 2e-3, 4e-3];
/// The force JND: the largest tick-to-tick change allowed in a hold.
const JND: f64 = 0.07;

/// The tolerance against the reference at point `name`, device depth `device_depth_m` (m),
/// never subdivided or subdivided: the 10 % wherever the surface meets it, tighter
/// where it meets it with a margin. Measured, h0-h5, at 0.25 / 1 / 2 / 4 mm: never subdivided
/// -9.6..-2.4 / -4.3..-0.9 / -3.2..0.0 / -0.9..+1.7 % (unchanged since session 14); subdivided
/// -5.3..+8.0 / -1.9..+1.0 / -1.4..+1.2 / -1.7..+0.7 % (session 16: the organ table's sites at
/// the corner Loop children's centroids, read at the probe's foot in a subdivided area;
/// session 15: -6.2..+10.2 / -3.6..-0.7 / -3.4..+0.4 / -3.3..+2.6 %, h4 at 0.25 mm reading a
/// linear interpolation over its Loop child between a node and two edge midpoints whose presses
/// are 12-20 % softer; docs/accuracy.md, "The spring surfaces, session 16"). Subdivided at
/// 0.25 mm tightened from 12 % (session 15) to 9 % (h3 and h4 +8.0 %).
fn tolerance(name: &str, subdivided: bool, device_depth_m: f64) -> f64 {
    match (subdivided, device_depth_m) {
        _ if name == "h0" => 0.10,
        (true, d) if d < 0.5e-3 => 0.09,
        _ => 0.10,
    }
}

fn scene() -> Scene {
    load_builtin("hemisphere-springs").expect("built-in scene")
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

/// Presses `p` along its line through the staircase, subdivided or not, printing each hold
/// against the reference at the measured sphere depth; returns the holds outside the
/// tolerance, unsteady or not in contact throughout.
fn press_point(scene: &Scene, p: &ReferencePoint, subdivided: bool) -> Vec<String> {
    let mut body = body(scene, subdivided);
    let line = PressLine::at_surface_point(p.position_m, p.direction, body.probe().params.radius_m);
    let (holds, _) = press::staircase(
        &mut body,
        &line,
        &DEPTHS_M,
        &HoldParams::default(),
        scene.integrator.tick_s,
    )
    .expect("press");
    let mut failures = Vec::new();
    for h in &holds {
        let want = p.force_at(h.sphere_depth_m);
        let e = h.force_n / want - 1.0;
        let line = format!(
            "{} {}: device {:.2} mm sphere {:.3} mm: {:.3} mN, reference {:.3} mN ({:+.1} %), \
             steadiness {:.2} %",
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
        if e.abs() > tolerance(&p.name, subdivided, h.device_depth_m)
            || h.steadiness() > JND
            || h.contact_ticks != h.hold_ticks
        {
            failures.push(line);
        }
    }
    failures
}

#[test]
fn hemisphere_springs_follows_its_solid_at_six_points() {
    let scene = scene();
    let reference = reference(&scene);
    let names: Vec<&str> = reference.points().iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["h0", "h1", "h2", "h3", "h4", "h5"]);
    let mut failures = Vec::new();
    for subdivided in [false, true] {
        for p in reference.points() {
            failures.extend(press_point(&scene, p, subdivided));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The stored reference against an independent one, Hertz's sphere on a sphere (radii 4 and
/// 50 mm: `F = 4/3 E* R^(1/2) d^(3/2)`, `1/R = 1/4 + 1/50 mm^-1`, `E* = E / (1 - nu^2)`),
/// valid while the contact is small against both radii: within 3 % at every point from 0.25 to
/// 1 mm (measured -1.4 to +2.4 %; the FEM's finest level moved by at most 1.4 % from 0.25 mm
/// when refined once more at h0 and h3). Past 1 mm the half ball is softer than Hertz's
/// half-space pair (-9 % at 4 mm), as finite strain and the contact's size make it.
#[test]
fn the_reference_follows_hertz_in_the_first_millimetre() {
    let (e_pa, nu) = (14.5e3, 0.45);
    let e_star = e_pa / (1.0 - nu * nu);
    let radius_m: f64 = 1.0 / (1.0 / 4e-3 + 1.0 / 50e-3);
    let hertz = |d: f64| 4.0 / 3.0 * e_star * radius_m.sqrt() * d.powf(1.5);
    let reference = reference(&scene());
    for p in reference.points() {
        for (d, f) in p.depth_m.iter().zip(&p.force_n) {
            if (0.24e-3..=1.01e-3).contains(d) {
                let e = f / hertz(*d) - 1.0;
                assert!(
                    e.abs() < 0.03,
                    "{} at {} mm: {:+.1} %",
                    p.name,
                    d * 1e3,
                    100.0 * e
                );
            }
        }
    }
}

/// The calibration is a fixed point of the run time at its own site (session 14): node 28
/// (next to h1) calibrated never subdivided, every site of a table given its row, and the body
/// pressed at the node along its normal with the scene's coupling reads the reference within
/// 2 % at every depth of the table from 0.25 mm (the calibration presses with its springs
/// scaled by the factor it measures, so its coupling's stretch, its device and the kernel
/// patch taken around it are the run time's; pressed with constant springs, session 13's
/// calibration, node 28's factor at 4 mm was 0.2055 against 0.1542: +33 % there).
#[test]
fn a_site_calibrated_reads_its_reference_at_run_time() {
    use haptic_model::mass_spring::organ::{
        OrganTable, calibrate_organ_node, press_sphere_depths, site_press,
    };
    let scene = scene();
    let ms = scene.mass_spring.as_ref().expect("a mass-spring scene");
    let organ = ms.organ.as_ref().expect("organ");
    let surface = &ms.surface;
    let mut params = ms.params;
    params.subdivision.rings = 0;
    let fresh = || {
        MassSpringBody::new(
            surface.clone(),
            &params,
            None,
            scene.probe,
            &scene.integrator,
            "t",
        )
        .expect("body")
    };
    let site = 28;
    let row = calibrate_organ_node(surface, (fresh(), None), &organ.reference, organ.axis, site)
        .expect("calibrated");
    // Every site takes the row's factors: the table's own text with the factor columns replaced.
    let shipped = organ.table.clone().expect("organ table");
    let text: String = shipped
        .to_text("test")
        .lines()
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            match (
                f.len(),
                f.first().and_then(|s| s.parse::<u32>().ok()),
                f.get(1).and_then(|s| s.parse::<usize>().ok()),
            ) {
                (8, Some(_), Some(k)) => format!(
                    "{},{},{},{:e},{:e},{}",
                    f[0],
                    f[1],
                    f[2],
                    row.factor[k - 1],
                    row.factor[k - 1],
                    f[5..].join(",")
                ),
                _ => l.to_string(),
            }
        })
        .map(|l| l + "\n")
        .collect();
    let table = OrganTable::parse(&text, "test").expect("table");
    let mut body = fresh().with_organ_table(table).expect("fits");
    let (point, inward) = site_press(surface, site);
    let depths: Vec<f64> = organ
        .reference
        .depths_m()
        .iter()
        .copied()
        .filter(|&d| d >= 0.24e-3)
        .collect();
    let forces = press_sphere_depths(&mut body, point, inward, &depths, None).expect("pressed");
    let k = organ.reference.depths_m().len() - depths.len();
    for (j, (d, f)) in depths.iter().zip(&forces).enumerate() {
        let e = f / row.target_force_n[k + j] - 1.0;
        eprintln!(
            "node {site} at {:.2} mm: {:.2} mN against {:.2} mN ({:+.2} %)",
            d * 1e3,
            f * 1e3,
            row.target_force_n[k + j] * 1e3,
            100.0 * e
        );
        assert!(e.abs() < 0.02, "at {:.2} mm: {:+.2} %", d * 1e3, 100.0 * e);
    }
    assert_eq!(
        body.probe().params.coupling_stiffness_n_per_m,
        scene.probe.coupling_stiffness_n_per_m
    );
}

/// A long edge's subdivided press is made in its nearer end's area (session 14): the midpoint
/// of edge 28-51, next to h1, lies 2.58 mm from node 29 and 3.05 mm from its ends, where the
/// run time's nearest-node rule made two areas (about nodes 29 and 50) that no press beside the
/// midpoint makes; an edge of the pole's ring (nodes nearer than any third node) keeps the
/// run time's rule.
#[test]
fn a_long_edge_is_pressed_in_its_nearer_ends_area() {
    use haptic_model::mass_spring::organ::edge_area_end;
    let scene = scene();
    let surface = &scene
        .mass_spring
        .as_ref()
        .expect("a mass-spring scene")
        .surface;
    let nc = surface.node_count() as u32;
    let site = |a: u32, b: u32| nc + surface.edge_between(a, b).expect("an edge");
    assert_eq!(edge_area_end(surface, site(28, 51)), Some(28));
    let apex = glam::DVec3::new(0.0, 0.0, 50e-3);
    let pole = (0..nc)
        .min_by(|&i, &j| {
            let d = |k: u32| (surface.rest()[k as usize] - apex).length();
            d(i).total_cmp(&d(j))
        })
        .expect("nodes");
    for &n in surface.neighbours(pole) {
        assert_eq!(
            edge_area_end(surface, site(pole, n)),
            None,
            "edge {pole}-{n}"
        );
    }
    assert_eq!(edge_area_end(surface, 0), None);
    assert_eq!(
        edge_area_end(surface, nc + surface.edge_count() as u32),
        None
    );
}

/// A press keeps the area it made while its rest foot stays in it (session 15): at h2, 4 mm
/// deep, the triangle the dent's deepest point touches leaves node 136's one-ring area past
/// 3 mm while the foot stays in it; the nearest-node rule then added node 99's area, 20 %
/// stiffer than the one-area press the table is calibrated with (docs/accuracy.md, "The spring
/// surfaces, session 15").
#[test]
fn a_deep_press_keeps_the_area_it_made() {
    let scene = scene();
    let p = reference(&scene).point("h2").expect("h2").clone();
    for depth_m in [0.25e-3, 4e-3] {
        let mut body = body(&scene, true);
        let r = body.probe().params.radius_m;
        let line = PressLine::at_surface_point(p.position_m, p.direction, r);
        press::staircase(
            &mut body,
            &line,
            &[depth_m],
            &HoldParams::default(),
            scene.integrator.tick_s,
        )
        .expect("press");
        let centres: Vec<u32> = body.area_home_constants().map(|c| c.0).collect();
        assert_eq!(centres, [136], "at {} mm", depth_m * 1e3);
    }
}

/// A corner child's site reads its own row at run time (session 16): the centroid of node 408's
/// Loop child of triangle 407-472-408 (next to h4), pressed subdivided along its normal by the
/// scene's body with the shipped table, has its probe's foot at the site, where the factor is
/// the site's row alone, and gives the reference within 2 % at every depth of the table from
/// 0.25 mm (the calibration pressed it so, in node 408's area at the run time's factor; read
/// at the patch's centroid, which lies nearer the node, it would not be the site's row).
#[test]
fn a_child_site_reads_its_row_at_run_time() {
    use haptic_model::mass_spring::organ::{press_sphere_depths, site_press};
    let scene = scene();
    let ms = scene.mass_spring.as_ref().expect("a mass-spring scene");
    let surface = &ms.surface;
    let organ = ms.organ.as_ref().expect("organ");
    let table = organ.table().expect("organ table");
    let t = (0..surface.triangle_count() as u32)
        .find(|&t| {
            let mut tri = surface.triangles()[t as usize];
            tri.sort_unstable();
            tri == [407, 408, 472]
        })
        .expect("triangle 407-472-408");
    let corner = surface.triangles()[t as usize]
        .iter()
        .position(|&n| n == 408)
        .expect("node 408");
    let site = table.child_site(t, corner).expect("a child site");
    let row = table.row(site).expect("its row").clone();
    assert!(row.subdivided_force_n.iter().all(|&f| f > 0.0), "pressed");
    let mut body = body(&scene, true);
    let (point, inward) = site_press(surface, site);
    let depths = organ.reference.depths_m();
    let k = depths.iter().position(|&d| d >= 0.24e-3).expect("0.25 mm");
    let forces =
        press_sphere_depths(&mut body, point, inward, &depths[k..], None).expect("pressed");
    for (j, f) in forces.iter().enumerate() {
        let e = f / row.target_force_n[k + j] - 1.0;
        eprintln!(
            "site {site} at {:.2} mm: {:.2} mN against {:.2} mN ({:+.2} %)",
            depths[k + j] * 1e3,
            f * 1e3,
            row.target_force_n[k + j] * 1e3,
            100.0 * e
        );
        assert!(
            e.abs() < 0.02,
            "at {:.2} mm: {:+.2} %",
            depths[k + j] * 1e3,
            100.0 * e
        );
    }
}
