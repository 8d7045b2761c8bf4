//! Hertz contact: a rigid sphere of radius R pressed into a large elastic block (a half-space
//! to within the block's size) gives `F = 4/3 E/(1 - nu^2) R^(1/2) d^(3/2)` and the contact
//! radius `a = (R d)^(1/2)` (K. L. Johnson, *Contact Mechanics*, 1985, eq. 4.22-4.23) at small
//! strain. The static indentation ([`haptic_model::indent`]) must follow both for d/R from 0.02
//! to 0.1 (checked at 0.02, 0.06 and 0.1): force within 10 %, contact radius within 15 %.
//!
//! The block is a quarter (symmetry planes x = 0 and y = 0 on rollers, base clamped) of
//! 7 R x 7 R x 7 R, at least 20 times the largest contact radius (0.32 R), on a tensor grid
//! refined to R / 30 under the sphere and growing by 1.3 per cell away from it; StVK with
//! nu = 0.3 (small strains: the largest is about 0.2 a / R = 6 %). The depths 0.02 and 0.06
//! are one continuation (the second starts from the first's solution); 0.1 is solved from rest
//! on a second thread, so that the two solves share the test machine's two cores (the whole
//! file took 18 s in debug with the exact node contact of 2026-11-26; about 90 s before).
//!
//! A second test checks that the contact tangent Newton uses (with or without the sphere's
//! curvature term) changes the iteration and not the converged force, on the built-in LV.

use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::indent::{IndentParams, Indentation, Indenter, indent};
use haptic_model::material::MaterialParams;
use haptic_model::mesh::generate::{box_mesh_graded, graded_coordinates};

const R: f64 = 2e-3;
const E: f64 = 10e3;
const NU: f64 = 0.3;

#[test]
fn sphere_on_half_space_follows_hertz() {
    let size = 7.0 * R;
    let fine = R / 30.0;
    let lateral = graded_coordinates(fine, 0.36 * R, 1.3, size);
    let depth: Vec<f64> = graded_coordinates(fine, 0.15 * R, 1.3, size)
        .iter()
        .rev()
        .map(|z| -z)
        .collect();
    let mesh = box_mesh_graded(&lateral, &lateral, &depth);
    let mut fem = FemModel::new(&mesh, MaterialParams::from_youngs(E, NU, 1000.0)).unwrap();
    for (i, p) in mesh.nodes.iter().enumerate() {
        let mut mask = 0u8;
        if p.x == 0.0 {
            mask |= 1;
        }
        if p.y == 0.0 {
            mask |= 2;
        }
        if p.z == -size {
            mask = 7;
        }
        if mask != 0 {
            fem.set_constraint(i, mask);
        }
    }
    let top = mesh.surface("ZMAX").unwrap().triangles.clone();
    eprintln!(
        "Hertz block: {} nodes, {} tets, {} top triangles",
        mesh.nodes.len(),
        mesh.tets.len(),
        top.len()
    );
    let ratios = [0.02, 0.06, 0.1];
    let depths: Vec<f64> = ratios.iter().map(|r| r * R).collect();
    let indenter = Indenter {
        radius_m: R,
        from_m: DVec3::new(0.0, 0.0, 1.5 * R),
        direction: DVec3::new(0.0, 0.0, -1.0),
    };
    let t = std::time::Instant::now();
    let solve = |depths: &[f64]| {
        indent(
            &fem,
            &top,
            &indenter,
            depths,
            &IndentParams::default(),
            &mut |p| {
                eprintln!(
                    "d/R {:.3}: F {:.5e} N, a {:.4e} m, {} nodes and {} points in contact, {} updates, {} Newton",
                    p.depth_m / R,
                    4.0 * p.force_on_sphere_n.z,
                    2.0 * p.contact_radius_m,
                    p.nodes_in_contact,
                    p.points_in_contact,
                    p.augmentations,
                    p.newton_iterations
                )
            },
        )
        .unwrap()
    };
    // Two independent solves on two threads (see the file's doc): 0.02 then 0.06, and 0.1.
    let points: Vec<_> = std::thread::scope(|s| {
        let deepest = s.spawn(|| solve(&depths[2..]));
        let mut points = solve(&depths[..2]);
        points.extend(
            deepest
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
        );
        points
    });
    assert_eq!(points.len(), ratios.len());
    eprintln!("solved in {:.1} s", t.elapsed().as_secs_f64());
    let e_star = E / (1.0 - NU * NU);
    let mut worst = (0.0f64, 0.0f64);
    for p in &points {
        let d = p.depth_m;
        // Four quarters; the body pushes the sphere up (+z).
        let f = 4.0 * p.force_on_sphere_n.z;
        let f_hertz = 4.0 / 3.0 * e_star * R.sqrt() * d.powf(1.5);
        let a_hertz = (R * d).sqrt();
        // The quarter's contact area is a quarter of the circle's: a = sqrt(4 A / pi).
        let a = (4.0 * p.contact_area_m2 / std::f64::consts::PI).sqrt();
        let (ef, ea) = (f / f_hertz - 1.0, a / a_hertz - 1.0);
        eprintln!(
            "d/R {:.2}: F {f:.4e} N vs Hertz {f_hertz:.4e} N ({:+.1} %), a {a:.4e} m vs {a_hertz:.4e} m ({:+.1} %), penetration {:.1e} m",
            d / R,
            100.0 * ef,
            100.0 * ea,
            p.max_penetration_m
        );
        assert!(p.max_penetration_m <= 1e-4 * d + 1e-12, "gap tolerance");
        worst = (worst.0.max(ef.abs()), worst.1.max(ea.abs()));
    }
    assert!(
        worst.0 < 0.10,
        "force off Hertz by {:.1} %",
        100.0 * worst.0
    );
    assert!(
        worst.1 < 0.15,
        "contact radius off Hertz by {:.1} %",
        100.0 * worst.1
    );
}

/// The built-in `lv`, its force model and the scene's sphere on the `lv-probe` line (along -x
/// at y = 0, z = -5 mm, from x = 12.7 mm).
fn lv_probe() -> (haptic_model::scene::Scene, FemModel, Indenter) {
    let scene = haptic_model::scene::load_builtin("lv").unwrap();
    let fem = scene.fem_model().unwrap();
    let indenter = Indenter {
        radius_m: scene.probe.radius_m,
        from_m: DVec3::new(0.0127, 0.0, -0.005),
        direction: DVec3::new(-1.0, 0.0, 0.0),
    };
    (scene, fem, indenter)
}

/// Newton's tangent with or without the sphere's curvature term
/// (`IndentParams::curvature_stiffness`, on by default): that changes the iteration, not the
/// equilibrium. On
/// the built-in `lv` (474 curved quadratic elements) pressed along the `lv-probe` line, the
/// forces with and without the term agree within the gap tolerance's share of the force.
#[test]
fn the_contact_tangent_changes_the_path_not_the_answer() {
    let (scene, fem, indenter) = lv_probe();
    let depths = [0.5e-3, 1.0e-3];
    let run = |curvature_stiffness: bool| {
        let params = IndentParams {
            curvature_stiffness,
            ..IndentParams::default()
        };
        indent(
            &fem,
            &scene.touchable,
            &indenter,
            &depths,
            &params,
            &mut |_| {},
        )
        .unwrap()
    };
    let (with_term, without_term) = (run(true), run(false));
    for (a, b) in with_term.iter().zip(&without_term) {
        let (fa, fb) = (a.force_on_sphere_n, b.force_on_sphere_n);
        eprintln!(
            "depth {:.2} mm: {:.6e} N ({} Newton iterations) with the curvature term, {:.6e} N ({}) without",
            a.depth_m * 1e3,
            fa.length(),
            a.newton_iterations,
            fb.length(),
            b.newton_iterations
        );
        assert!(fa.length() > 1e-3, "the sphere must press: {fa}");
        assert!((fa - fb).length() < 5e-4 * fa.length(), "{fa} against {fb}");
    }
}

/// A reference solve can stop after any depth and continue in another process: an
/// indentation resumed from a checkpoint taken at 0.5 mm reaches the same 1 mm equilibrium as
/// the uninterrupted run (to well within the Newton tolerance: the resumed run refactors its
/// preconditioner), and a checkpoint of another size is refused without touching the run.
#[test]
fn a_resumed_indentation_continues_like_an_uninterrupted_one() {
    let (scene, fem, indenter) = lv_probe();
    let params = IndentParams::default();
    let new_run = || Indentation::new(&fem, &scene.touchable, &indenter, &params).unwrap();
    let mut straight = new_run();
    straight.solve(0.5e-3).unwrap();
    let checkpoint = straight.checkpoint();
    let expected = straight.solve(1.0e-3).unwrap().force_on_sphere_n;

    let mut resumed = new_run();
    let mut foreign = checkpoint.clone();
    foreign.positions_m.pop();
    let err = resumed.resume(foreign).unwrap_err().to_string();
    assert!(err.contains("positions"), "{err}");
    assert_eq!(
        resumed.checkpoint().reached_m,
        0.0,
        "a refused checkpoint changed the run"
    );
    resumed.resume(checkpoint.clone()).unwrap();
    assert_eq!(resumed.checkpoint(), checkpoint);
    let got = resumed.solve(1.0e-3).unwrap().force_on_sphere_n;
    eprintln!("1 mm: {expected} N uninterrupted, {got} N resumed at 0.5 mm");
    assert!(
        expected.length() > 1e-3,
        "the sphere must press: {expected}"
    );
    assert!(
        (got - expected).length() < 1e-7 * expected.length(),
        "{got} against {expected}"
    );
}
