//! The built-in left ventricle under the haptic probe: both integrators stay bounded for 10 s of
//! simulated time at a 1 ms tick; the probe force is zero before contact, grows with press
//! depth, opposes the press, and vanishes after release; the surface recovers.

use haptic_model::DVec3;
use haptic_model::contact::ContactModel;
use haptic_model::fem::{FemBody, TickInput};
use haptic_model::integrate::{IntegratorKind, LinearSolver};
use haptic_model::material::MaterialModel;
use haptic_model::scene::{load_builtin, parse_scene_toml};

/// Probe path: start 14 mm from the axis at z = -5 mm (outside the 9.68 mm epicardium radius
/// there), move along -x by `depth` over 1 s, hold, release.
fn device_at(t: f64, depth: f64) -> DVec3 {
    let start = DVec3::new(0.014, 0.0, -0.005);
    let travel = if t < 1.0 {
        depth * t
    } else if t < 2.0 {
        depth
    } else if t < 3.0 {
        depth * (3.0 - t)
    } else {
        0.0
    };
    start - DVec3::X * travel
}

fn run(kind: IntegratorKind) {
    let mut scene = load_builtin("lv").unwrap();
    scene.integrator.kind = kind;
    let mut sim = FemBody::new(&scene).unwrap();
    let plan = sim.plan();
    assert!(
        plan.substeps >= 1 && plan.sub_dt_s <= plan.critical_dt_s,
        "{plan:?}"
    );
    // 14 - 6 = 8 mm from the axis: the 2 mm probe indents the wall (9.68 mm) by 3.7 mm.
    let depth = 0.006;
    let mut forces = Vec::new();
    let mut max_disp: f64 = 0.0;
    let probe_node_rest = DVec3::new(0.00968, 0.0, -0.005);
    let mut inward_at_hold = 0.0;
    for k in 0..10_000 {
        let t = k as f64 * 1e-3;
        let p = device_at(t, depth);
        let v = (device_at(t + 1e-3, depth) - p) / 1e-3;
        let out = sim
            .tick(&TickInput {
                device_position_m: Some(p),
                device_velocity_m_per_s: v,
            })
            .unwrap();
        assert!(out.force_on_device_n.is_finite());
        forces.push((t, out.force_on_device_n, out.in_contact));
        max_disp = max_disp.max(sim.max_displacement_m());
        if k == 1999 {
            // Surface under the probe moved inward (towards the axis, -x).
            let x = &sim.state().x;
            let rest = &sim.fem().rest();
            let nearest = (0..x.len())
                .min_by(|&a, &b| {
                    (rest[a] - probe_node_rest)
                        .length()
                        .total_cmp(&(rest[b] - probe_node_rest).length())
                })
                .unwrap();
            inward_at_hold = rest[nearest].x - x[nearest].x;
        }
    }
    // Bounded: the largest displacement stays of the order of the press depth.
    assert!(max_disp < 0.01, "{kind:?}: max displacement {max_disp} m");
    // Zero force before contact (the first 0.2 s the probe is > 4 mm from the surface).
    assert!(
        forces[..200]
            .iter()
            .all(|(_, f, c)| *f == DVec3::ZERO && !c)
    );
    // Force opposes the press (+x) and grows monotonically while pressing (sampled every 50 ms,
    // allowing 2 % ripple from the dynamics).
    let pressing: Vec<f64> = forces[400..1000]
        .iter()
        .step_by(50)
        .map(|(_, f, _)| f.x)
        .collect();
    // About 0.046 N at 6 mm of device travel on the default quadratic mesh (the static solution
    // there is 0.043 N at 3 mm of indentation).
    assert!(
        pressing.last().unwrap() > &0.03,
        "{kind:?}: force at full depth {pressing:?}"
    );
    for w in pressing.windows(2) {
        assert!(
            w[1] >= w[0] * 0.98 - 1e-6,
            "{kind:?}: not monotone {pressing:?}"
        );
    }
    let f_hold = forces[1999].1;
    // Opposes the press (+x), tilted only by the ellipsoid's surface normal (which is 7 degrees
    // off the x axis at z = -5 mm): within 25 degrees of +x.
    assert!(f_hold.x / f_hold.length() > 0.9, "{f_hold:?}");
    assert!(
        inward_at_hold > 5e-4,
        "{kind:?}: surface moved inward only {inward_at_hold} m"
    );
    // Released: zero force after 3 s, and the body returns to rest.
    assert!(
        forces[3200..]
            .iter()
            .all(|(_, f, c)| *f == DVec3::ZERO && !c)
    );
    assert!(
        sim.max_displacement_m() < 1e-4,
        "{kind:?}: residual displacement {} m",
        sim.max_displacement_m()
    );
}

#[test]
fn semi_implicit_stays_bounded_for_ten_seconds_and_recovers() {
    run(IntegratorKind::SemiImplicit);
}

#[test]
fn symplectic_euler_stays_bounded_for_ten_seconds_and_recovers() {
    run(IntegratorKind::SymplecticEuler);
}

#[test]
fn point_load_moves_the_loaded_region_along_the_force() {
    let scene = load_builtin("lv").unwrap();
    let mut sim = FemBody::new(&scene).unwrap();
    let point = DVec3::new(0.0, 0.00968, -0.005);
    sim.add_point_load(point, DVec3::new(0.0, -0.05, 0.0), 0.5)
        .unwrap();
    for _ in 0..300 {
        sim.tick(&TickInput::default()).unwrap();
    }
    let x = &sim.state().x;
    let rest = &sim.fem().rest();
    let nearest = (0..x.len())
        .min_by(|&a, &b| {
            (rest[a] - point)
                .length()
                .total_cmp(&(rest[b] - point).length())
        })
        .unwrap();
    let d = x[nearest] - rest[nearest];
    assert!(
        d.y < -2e-4 && d.y.abs() > 3.0 * d.x.abs().max(d.z.abs()),
        "{d:?}"
    );
    // Bad loads are rejected and leave the state untouched.
    let before = sim.state().x.clone();
    assert!(
        sim.add_point_load(DVec3::new(f64::NAN, 0.0, 0.0), DVec3::X, 1.0)
            .is_err()
    );
    assert!(sim.add_point_load(point, DVec3::X * 1e6, 1.0).is_err());
    assert!(sim.add_point_load(point, DVec3::X, -1.0).is_err());
    assert!(
        sim.tick(&TickInput {
            device_position_m: Some(DVec3::splat(f64::INFINITY)),
            ..Default::default()
        })
        .is_err()
    );
    assert_eq!(before, sim.state().x);
}

/// A point load acts on the probe's footprint, not on one triangle, so its displacement
/// converges with the mesh: 0.05 N held on the default quadratic `lv` (474 elements) and on the
/// same shell with twice the elements (948) agree within 10 % (measured 7.58 and 7.44 mm).
#[test]
fn point_load_converges_with_the_mesh() {
    let text = include_str!("../../../deploy/scenes/lv.toml");
    let point = DVec3::new(0.0, 0.00968, -0.005);
    let mut displacement = Vec::new();
    for tets in [500, 1000] {
        let scene_text = text.replace("target_tets = 500", &format!("target_tets = {tets}"));
        assert_ne!(
            tets == 1000,
            scene_text == text,
            "lv.toml has target_tets = 500"
        );
        let scene = parse_scene_toml(&scene_text, std::path::Path::new(".")).unwrap();
        let mut sim = FemBody::new(&scene).unwrap();
        sim.add_point_load(point, DVec3::new(0.0, -0.05, 0.0), 10.0)
            .unwrap();
        let rest = sim.fem().rest().to_vec();
        let nearest = (0..rest.len())
            .min_by(|&a, &b| {
                (rest[a] - point)
                    .length()
                    .total_cmp(&(rest[b] - point).length())
            })
            .unwrap();
        let mut last = 0.0;
        for k in 0..1500 {
            sim.tick(&TickInput::default()).unwrap();
            if k % 100 == 99 {
                last = -(sim.state().x[nearest] - rest[nearest]).y;
            }
        }
        displacement.push(last);
    }
    let (coarse, fine) = (displacement[0], displacement[1]);
    println!("point load 0.05 N: {coarse:.4e} m (474 elements), {fine:.4e} m (948)");
    assert!((fine - coarse).abs() < 0.1 * fine, "{coarse} {fine}");
    assert!(fine > 1e-3 && fine < 1e-2, "{fine}");
}

/// The `lv-probe` staircase of the precision benchmark on `scene` (0.5 to 3 mm indentation in
/// 0.5 mm steps, each a 0.1 s smooth ramp and a 0.1 s hold): the force per depth averaged over
/// the second half of the hold (N), and the contact stiffness sent to the device (trace of the
/// 3x3, N/m) a quarter into each step (halfway through its ramp).
fn probe_staircase(scene: &haptic_model::scene::Scene) -> (Vec<f64>, Vec<f64>) {
    let (forces, stiffness, _) = probe_staircase_to(scene, &STAIRCASE_MM);
    (forces, stiffness)
}

/// [`probe_staircase`] to the depths `depths_mm`; also returns, per depth, the largest change
/// of the force's magnitude between neighbouring ticks over the second half of the hold,
/// relative to the mean there.
fn probe_staircase_to(
    scene: &haptic_model::scene::Scene,
    depths_mm: &[f64],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    // Probe centre at first contact: the epicardium at z = -5 mm is 9.682 mm from the axis.
    let device_at = |depth_m: f64| DVec3::new(0.011_682 - depth_m, 0.0, -0.005);
    let smoothstep = |t: f64| {
        let t = t.clamp(0.0, 1.0);
        t * t * (3.0 - 2.0 * t)
    };
    let smoothstep_rate = |t: f64| {
        if (0.0..=1.0).contains(&t) {
            6.0 * t * (1.0 - t)
        } else {
            0.0
        }
    };
    let mut sim = FemBody::new(scene).unwrap();
    let (ramp, hold, tick) = (0.1, 0.1, sim.tick_s());
    let ticks = ((ramp + hold) / tick).round() as usize;
    let mut previous = -0.3e-3;
    let mut forces = Vec::new();
    let mut mid_ramp_stiffness = Vec::new();
    let mut jitter = Vec::new();
    for d in depths_mm.iter().map(|d| d * 1e-3) {
        let (mut sum, mut count) = (0.0, 0);
        let (mut last, mut largest_change) = (None::<f64>, 0.0f64);
        for k in 0..ticks {
            let t = (k + 1) as f64 * tick;
            let depth = previous + (d - previous) * smoothstep(t / ramp);
            let rate = (d - previous) / ramp * smoothstep_rate(t / ramp);
            let out = sim
                .tick(&TickInput {
                    device_position_m: Some(device_at(depth)),
                    device_velocity_m_per_s: DVec3::new(-rate, 0.0, 0.0),
                })
                .unwrap();
            if t > ramp + hold / 2.0 {
                let f = out.force_on_device_n.length();
                sum += f;
                count += 1;
                if let Some(l) = last {
                    largest_change = largest_change.max((f - l).abs());
                }
                last = Some(f);
            }
            if k + 1 == ticks / 4 {
                let k = out.contact_stiffness_n_per_m;
                mid_ramp_stiffness.push(k[0] + k[4] + k[8]);
            }
        }
        forces.push(sum / count as f64);
        jitter.push(largest_change / (sum / count as f64));
        previous = d;
    }
    (forces, mid_ramp_stiffness, jitter)
}

/// The built-in `lv` with St. Venant-Kirchhoff, its material until 2026-11-26 (session 3), for
/// the contact tests whose pins and static solves were computed with it. (With the shipped
/// stable neo-Hookean the rest factor's exact sphere in the stroke below changes by 7.1 %
/// between ticks at worst, against 6.1 % with StVK; the default contact is unaffected.)
fn stvk_lv() -> haptic_model::scene::Scene {
    let mut scene = load_builtin("lv").unwrap();
    scene.material.model = MaterialModel::StVenantKirchhoff;
    scene
}

/// Device depths of [`probe_staircase`], mm.
const STAIRCASE_MM: [f64; 6] = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0];

/// Regression pin of the default scene's probe force: the built-in `lv` (474 quadratic tets,
/// backward Euler on the rest factor since 2026-11-25; `auto` contact, which is the kernel
/// patch with the material's local law of the sphere in series since 2026-11-26; stable
/// neo-Hookean since 2026-11-26, session 3) pressed in the `lv-probe` staircase.
///
/// The pinned values are this press's forces of 2026-11-26, session 3 (St. Venant-Kirchhoff
/// with `"patch-local"` gave 4.19 / 8.96 / 13.79 / 18.63 / 23.39 / 28.05 mN, the Hertz patch
/// before 3.60 / 8.92 / 14.62 / 20.43 / 26.19 / 31.74 mN); a change beyond 1.5 % is a
/// behaviour change to explain, not noise. Against the rigid-sphere reference of the same
/// press (stable neo-Hookean, device convention, `benches/precision/lv_sphere_reference.csv`:
/// five levels of our static solver refined under the probe down to 0.15 mm, least squares
/// after Eca & Hoekstra, 4.595 +- 0.027 mN at 0.5 mm, 10.141 +- 0.068 mN at 1 mm; the
/// independent scikit-fem solve within 1 %) the default reads -0.8 / -1.0 % and must stay
/// within 3 % (well inside the 7 % JND) plus the reference's uncertainty.
/// `tests/lv_probe_reference.rs` checks the feel protocol's holds against the stored file
/// itself.
#[test]
fn default_lv_probe_force_matches_the_benchmark_and_the_converged_reference() {
    const PINNED_N: [f64; 6] = [0.00456, 0.01004, 0.01576, 0.02151, 0.02722, 0.03282];
    const REFERENCE_N: [(f64, f64); 2] = [(0.004595, 0.000027), (0.010141, 0.000068)];
    let (forces, stiffness) = probe_staircase(&load_builtin("lv").unwrap());
    println!("default lv staircase: {forces:.5?} N");
    for ((d, f), pinned) in STAIRCASE_MM.iter().zip(&forces).zip(PINNED_N) {
        assert!(
            (f - pinned).abs() <= 0.015 * pinned,
            "{d} mm: {f:.5} N against the pinned {pinned} N (all: {forces:.5?})"
        );
    }
    for ((d, f), (reference, uncertainty)) in STAIRCASE_MM.iter().zip(&forces).zip(REFERENCE_N) {
        assert!(
            (f - reference).abs() <= 0.03 * reference + uncertainty,
            "{d} mm: {f:.5} N against the converged reference {reference} +- {uncertainty} N"
        );
    }
    // The contact stiffness sent halfway through the ramp from 0.5 to 1 mm is the reference's
    // slope there (the coupling and the tissue in series).
    let slope = (REFERENCE_N[1].0 - REFERENCE_N[0].0) / 0.5e-3;
    println!("mid-ramp contact stiffness {stiffness:.2?} N/m, reference slope {slope:.2} N/m");
    assert!(
        (stiffness[1] - slope).abs() < 0.15 * slope,
        "contact stiffness {:.2} N/m against the reference's slope {slope:.2} N/m",
        stiffness[1]
    );
}

/// The exact sphere contact (`probe.contact = "sphere"`) on the default mesh reaches the
/// mesh's own equilibrium: the staircase's forces equal the static equilibrium of the same mesh
/// pressed by an exact rigid sphere (`haptic_model::indent`: a Newton solve with
/// augmented-Lagrangian contact on sub-triangle contact points, no servo code) to 1 % at
/// 0.5-2 mm (`lv_study sphere --mesh 500:2`: 7.36 / 14.51 / 20.90 / 26.51 mN), and the contact
/// stiffness sent halfway through each ramp is that solve's slope within 15 %. Pinned (1.5 %)
/// to the forces of 2026-11-23. These are 60-90 % above the converged reference: the mesh's
/// facets are coarser than the contact (which is why the default is the Hertz patch).
#[test]
fn sphere_contact_reaches_the_static_sphere_equilibrium_of_its_mesh() {
    const PINNED_N: [f64; 6] = [0.00739, 0.01458, 0.02094, 0.02653, 0.03148, 0.03604];
    const STATIC_SPHERE_N: [f64; 4] = [0.00736, 0.01451, 0.02090, 0.02651];
    let mut scene = stvk_lv();
    scene.probe.contact = ContactModel::Sphere;
    let (forces, mid_ramp_stiffness) = probe_staircase(&scene);
    for ((d, f), pinned) in STAIRCASE_MM.iter().zip(&forces).zip(PINNED_N) {
        assert!(
            (f - pinned).abs() <= 0.015 * pinned,
            "{d} mm: {f:.5} N against the pinned {pinned} N (all: {forces:.5?})"
        );
    }
    println!("mid-ramp contact stiffness {mid_ramp_stiffness:.2?} N/m");
    for (j, pair) in STATIC_SPHERE_N.windows(2).enumerate() {
        let slope = (pair[1] - pair[0]) / 0.5e-3;
        let k = mid_ramp_stiffness[j + 1];
        assert!(
            (k - slope).abs() < 0.15 * slope,
            "{} to {} mm: contact stiffness {k:.2} N/m against the static slope {slope:.2} N/m",
            STAIRCASE_MM[j],
            STAIRCASE_MM[j + 1]
        );
    }
    for ((d, f), reference) in STAIRCASE_MM.iter().zip(&forces).zip(STATIC_SPHERE_N) {
        assert!(
            (f - reference).abs() < 0.01 * reference,
            "{d} mm: {f:.5} N against the static sphere solve's {reference} N"
        );
    }
}

/// The sphere under backward Euler (implicit: the faces in contact are penalty springs in
/// series with the coupling, solved inside the step) reaches the same static equilibrium as
/// the explicit sphere on the default mesh (`haptic_model::indent`, to 1 % at 0.5-2 mm) and
/// holds still there (St. Venant-Kirchhoff: the static solve on this mesh finds no
/// equilibrium at 2.5 mm and beyond, and the dynamics wander there under every contact
/// model that concentrates the load). With the stable materials it holds still to 3.7 mm, where
/// the explicit load distribution under backward Euler swung between 34 and 58 mN from tick to
/// tick (changes between ticks within the 7 % force JND; measured 2.5 % at most, on a
/// capped CG solve), and it agrees with the explicit sphere under symplectic Euler (a
/// different contact code: the exact non-penetrating cast) at every depth within 2.5 %.
#[test]
fn backward_euler_sphere_contact_reaches_the_sphere_equilibrium_and_holds_still() {
    const STATIC_SPHERE_N: [f64; 4] = [0.00736, 0.01451, 0.02090, 0.02651];
    let mut scene = stvk_lv();
    scene.integrator.kind = IntegratorKind::BackwardEuler;
    scene.probe.contact = ContactModel::Sphere;
    let (forces, _, jitter) = probe_staircase_to(&scene, &STAIRCASE_MM[..4]);
    println!(
        "St. Venant-Kirchhoff, backward Euler sphere: {forces:.5?} N, hold jitter {jitter:.4?}"
    );
    for ((d, f), reference) in STAIRCASE_MM.iter().zip(&forces).zip(STATIC_SPHERE_N) {
        assert!(
            (f - reference).abs() < 0.01 * reference,
            "{d} mm: {f:.5} N against the static sphere solve's {reference} N"
        );
    }
    for (d, j) in STAIRCASE_MM.iter().zip(&jitter) {
        assert!(
            *j < 0.01,
            "{d} mm: the force changes by {j:.2e} of itself between ticks"
        );
    }
    let depths = [0.5, 1.0, 2.0, 3.0, 3.7];
    for model in [MaterialModel::StableNeoHookean, MaterialModel::Corotational] {
        let mut implicit = scene.clone();
        implicit.material.model = model;
        let mut explicit = implicit.clone();
        explicit.integrator.kind = IntegratorKind::SymplecticEuler;
        let (be, _, jitter) = probe_staircase_to(&implicit, &depths);
        let (se, _, _) = probe_staircase_to(&explicit, &depths);
        println!(
            "{model:?}: backward Euler sphere {be:.5?} N (hold jitter {jitter:.4?}), symplectic Euler sphere {se:.5?} N"
        );
        for (((d, b), e), j) in depths.iter().zip(&be).zip(&se).zip(&jitter) {
            assert!(
                (b - e).abs() < 0.025 * e,
                "{model:?} {d} mm: {b:.5} N under backward Euler, {e:.5} N under symplectic Euler"
            );
            assert!(
                *j < 0.07,
                "{model:?} {d} mm: the force changes by {j:.2e} of itself between ticks (the JND is 7 %)"
            );
        }
    }
}

/// The stroke of the sliding tests: the default `lv`'s epicardium as the ellipsoid with
/// semi-axes `STROKE_A_M` x `STROKE_A_M` x `STROKE_C_M`, the probe (radius `STROKE_R_M`)
/// pressed `STROKE_DEPTH_M` in at z = -12 mm over 0.2 s, then slid to z = 0 at 20 mm/s.
const STROKE_A_M: f64 = 0.010;
const STROKE_C_M: f64 = 0.020;
const STROKE_R_M: f64 = 0.002;
const STROKE_DEPTH_M: f64 = 0.001;

/// Point and outward normal of the stroke's ellipsoid at height `z` (m) in the x-z plane.
fn stroke_surface_at(z: f64) -> (DVec3, DVec3) {
    let (a, c) = (STROKE_A_M, STROKE_C_M);
    let rho = a * (1.0 - (z / c).powi(2)).sqrt();
    (
        DVec3::new(rho, 0.0, z),
        DVec3::new(rho / (a * a), 0.0, z / (c * c)).normalize(),
    )
}

/// Device position of the stroke at time `t` (s).
fn stroke_device_at(t: f64) -> DVec3 {
    let (press, z) = if t < 0.2 {
        (t / 0.2, -0.012)
    } else {
        (1.0, (-0.012 + 0.02 * (t - 0.2)).min(0.0))
    };
    let (point, normal) = stroke_surface_at(z);
    point + normal * (STROKE_R_M + 0.5e-3 - (STROKE_DEPTH_M + 0.5e-3) * press)
}

/// The probe stroked across the default `lv` at 20 mm/s (issue 14): pressed 1 mm into the
/// epicardium at z = -12 mm over 0.2 s, then slid along the long axis to z = 0 at constant
/// depth along the ellipsoid's normal (semi-axes 10 x 10 x 20 mm). The force follows the
/// surface normal (within the faceting of this coarse mesh, 0.95 in cosine) and changes by
/// less than 7 % of itself between neighbouring ticks (no chatter): the exact sphere under
/// every integrator (backward Euler with CG and on the rest factor, the default's), the default
/// Hertz patch under symplectic Euler and on the rest factor. (On the rest factor the sphere's
/// ticks where a face enters the contact step with the unscaled rest stiffness: with the
/// doubled one the entering face took more of the load at once, 9 % here at the facet edges
/// of this coarse mesh; `docs/decisions.md`, "The whole-body rest factor".)
#[test]
fn the_probe_slides_across_the_lv_without_chatter() {
    let (surface_at, device_at) = (stroke_surface_at, stroke_device_at);
    for (kind, solver, contact) in [
        (
            IntegratorKind::SymplecticEuler,
            LinearSolver::Cg,
            ContactModel::Sphere,
        ),
        (
            IntegratorKind::SemiImplicit,
            LinearSolver::Cg,
            ContactModel::Sphere,
        ),
        (
            IntegratorKind::BackwardEuler,
            LinearSolver::Cg,
            ContactModel::Sphere,
        ),
        (
            IntegratorKind::BackwardEuler,
            LinearSolver::RestCholesky,
            ContactModel::Sphere,
        ),
        (
            IntegratorKind::SymplecticEuler,
            LinearSolver::Cg,
            ContactModel::Auto,
        ),
        (
            IntegratorKind::BackwardEuler,
            LinearSolver::RestCholesky,
            ContactModel::Auto,
        ),
    ] {
        let mut scene = stvk_lv();
        scene.integrator.kind = kind;
        scene.integrator.linear_solver = solver;
        scene.probe.contact = contact;
        let mut sim = FemBody::new(&scene).unwrap();
        let tick = sim.tick_s();
        let (mut worst_cos, mut worst_jump, mut previous) = (1.0f64, 0.0f64, None::<DVec3>);
        for k in 0..800 {
            let t = k as f64 * tick;
            let out = sim
                .tick(&TickInput {
                    device_position_m: Some(device_at(t)),
                    device_velocity_m_per_s: (device_at(t + tick) - device_at(t)) / tick,
                })
                .unwrap();
            let f = out.force_on_device_n;
            if t >= 0.25 {
                let z = -0.012 + 0.02 * (t - 0.2);
                assert!(
                    f.length() > 1e-3,
                    "{kind:?} {solver:?} {contact:?} t = {t:.3}: no contact force {f}"
                );
                worst_cos = worst_cos.min(f.normalize().dot(surface_at(z.min(0.0)).1));
                if let Some(p) = previous {
                    worst_jump = worst_jump.max((f - p).length() / f.length());
                }
            }
            previous = Some(f);
        }
        println!(
            "{kind:?} {solver:?} {contact:?}: worst cosine to the normal {worst_cos:.4}, largest tick-to-tick change {:.2} %",
            100.0 * worst_jump
        );
        assert!(
            worst_cos > 0.95,
            "{kind:?} {solver:?} {contact:?}: force off the normal, cosine {worst_cos}"
        );
        assert!(
            worst_jump < 0.07,
            "{kind:?} {solver:?} {contact:?}: the force jumped by {:.1} % between ticks",
            100.0 * worst_jump
        );
    }
}

/// The same stroke with Coulomb friction (mu = 0.3): the tangential force opposes the stroke
/// and stays inside the friction cone, and the body stays bounded; with the default contact
/// under symplectic Euler and with the implicit sphere under backward Euler.
#[test]
fn friction_drags_against_the_stroke_within_the_cone() {
    for (kind, contact) in [
        (IntegratorKind::SymplecticEuler, ContactModel::Auto),
        (IntegratorKind::BackwardEuler, ContactModel::Sphere),
    ] {
        friction_stroke(kind, contact);
    }
}

fn friction_stroke(kind: IntegratorKind, contact: ContactModel) {
    let mu = 0.3;
    let (surface_at, device_at) = (stroke_surface_at, stroke_device_at);
    let mut scene = load_builtin("lv").unwrap();
    scene.probe.friction_coefficient = mu;
    scene.integrator.kind = kind;
    scene.probe.contact = contact;
    let mut sim = FemBody::new(&scene).unwrap();
    let tick = sim.tick_s();
    let mut largest_ratio: f64 = 0.0;
    for k in 0..700 {
        let t = k as f64 * tick;
        let out = sim
            .tick(&TickInput {
                device_position_m: Some(device_at(t)),
                device_velocity_m_per_s: (device_at(t + tick) - device_at(t)) / tick,
            })
            .unwrap();
        if t >= 0.3 {
            let z = -0.012 + 0.02 * (t - 0.2);
            let along = (device_at(t + tick) - device_at(t)).normalize();
            let f = out.force_on_device_n;
            // The contact normal n from the stiffness k_c n n^T sent with the force (its
            // largest column), about which the cone holds.
            let k = out.contact_stiffness_n_per_m;
            let j = (0..3)
                .max_by(|&a, &b| k[4 * a].total_cmp(&k[4 * b]))
                .unwrap();
            if k[4 * j] <= 0.0 {
                continue;
            }
            let n = DVec3::new(k[j], k[3 + j], k[6 + j]).normalize();
            let n = if n.dot(surface_at(z.min(0.0)).1) < 0.0 {
                -n
            } else {
                n
            };
            let f_n = f.dot(n);
            let f_t = f - n * f_n;
            assert!(
                f_t.dot(along) < 0.0,
                "{kind:?} {contact:?} t = {t:.3}: friction {f_t} does not oppose {along}"
            );
            largest_ratio = largest_ratio.max(f_t.length() / f_n);
        }
    }
    println!("{kind:?} {contact:?}: largest |F_t| / F_n {largest_ratio:.3}");
    // Sliding all along: on the cone's edge (the cone holds for the explicit normal force of
    // the step; the implicit completion moves the final one by a few per cent, up to 6 % with
    // backward Euler's implicit sphere).
    assert!(
        largest_ratio < 1.07 * mu && largest_ratio > 0.9 * mu,
        "{kind:?} {contact:?}: {largest_ratio}"
    );
    assert!(sim.stability().stable);
}
