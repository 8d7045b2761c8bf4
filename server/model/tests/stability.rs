//! Stability stress suite, short versions (issue 3 section 3). Every model / integrator pair
//! reports stable or unstable (`FemBody::stability`, `ModelError::Diverged`,
//! `ModelError::Unstable`) instead of producing NaN:
//! time-step sweep around the computed critical step; Poisson ratio sweep with the volume error;
//! element inversion and a scrambled (flattened) start; a free body spinning at 2 pi rad/s;
//! a 10-fold force impulse at the probe; a sliver mesh under the automatic time-step rule; and
//! NaN / Inf / absurd inputs through every entry point. Measured values are printed
//! (`cargo test -p haptic-model --test model stability:: -- --nocapture`).

use std::path::Path;

use haptic_model::element::StrainSmoothing;
use haptic_model::fem::{FemBody, TickInput};
use haptic_model::integrate::{self, IntegratorKind};
use haptic_model::mesh::generate::{box_mesh, min_dihedral_angle_deg};
use haptic_model::scene::{Scene, load_builtin, parse_scene_toml};
use haptic_model::{DVec3, ModelError};

const ALL: [IntegratorKind; 3] = [
    IntegratorKind::SemiImplicit,
    IntegratorKind::SymplecticEuler,
    IntegratorKind::BackwardEuler,
];

/// A 10 mm cube of 3x3x3 cells (162 tets); `extra` is appended to the TOML (sections after
/// `[material]`'s keys are not allowed there, so it holds whole sections).
fn cube(material: &str, extra: &str) -> Scene {
    let text = format!(
        r#"
[mesh]
builtin = "box"
size = [0.01, 0.01, 0.01]
cells = [3, 3, 3]
[material]
density_kg_per_m3 = 1000.0
{material}
{extra}
"#
    );
    parse_scene_toml(&text, Path::new(".")).unwrap()
}

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) - 0.5
    }
    fn vec(&mut self) -> DVec3 {
        DVec3::new(self.next(), self.next(), self.next())
    }
}

fn kick(sim: &mut FemBody, speed: f64, seed: u64) {
    let mut rng = Rng(seed);
    let clamped: Vec<bool> = sim.fem().constraints().iter().map(|&c| c != 0).collect();
    for (v, c) in sim.state_mut().v.iter_mut().zip(clamped) {
        if !c {
            *v = rng.vec() * speed;
        }
    }
}

fn energy(sim: &FemBody) -> f64 {
    sim.kinetic_energy_j() + sim.fem().elastic_energy(&sim.state().x)
}

#[test]
fn time_step_sweep_around_the_critical_step() {
    // Undamped, so the critical step is that of the bare stiffness.
    let base = cube(
        "youngs_modulus_pa = 10000.0\npoisson_ratio = 0.3",
        "[boundary]\nclamped = [\"ZMIN\"]\n[integrator]\nkind = \"symplectic-euler\"",
    );
    // Both element technologies: the smoothed strain has its own (larger) critical step.
    for smoothing in [StrainSmoothing::None, StrainSmoothing::Edge] {
        let mut base = base.clone();
        base.strain_smoothing = smoothing;
        time_step_sweep(&base, smoothing);
    }
}

fn time_step_sweep(base: &Scene, smoothing: StrainSmoothing) {
    let probe = FemBody::new(base).unwrap();
    let dt_crit = integrate::critical_time_step(probe.fem(), IntegratorKind::SymplecticEuler);
    for factor in [0.25, 0.5, 0.9, 1.1, 2.0] {
        let mut scene = base.clone();
        scene.integrator.tick_s = factor * dt_crit;
        scene.integrator.substeps = Some(1);
        // The configuration check refuses a step above the critical one ...
        let checked = FemBody::new(&scene);
        assert_eq!(
            checked.is_err(),
            factor > 1.0,
            "factor {factor}: {:?}",
            checked.err()
        );
        if let Err(e) = checked {
            assert!(matches!(e, ModelError::Unstable { .. }), "{e}");
        }
        // ... and with the check off, the run-time monitor reports the divergence.
        scene.integrator.check_critical_step = false;
        let mut sim = FemBody::new(&scene).unwrap();
        kick(&mut sim, 1e-3, 7);
        let e0 = energy(&sim);
        let mut max_ratio: f64 = 0.0;
        let mut diverged_at = None;
        for k in 0..4000 {
            match sim.tick(&TickInput::default()) {
                Ok(out) => assert!(out.force_on_device_n.is_finite()),
                Err(ModelError::Diverged { .. }) => {
                    diverged_at = Some(k);
                    break;
                }
                Err(e) => panic!("{e}"),
            }
            if k % 10 == 0 {
                max_ratio = max_ratio.max(energy(&sim) / e0);
            }
        }
        let report = sim.stability();
        println!(
            "symplectic Euler, {smoothing:?}, at {factor} dt_crit ({:.3e} s): max energy ratio {max_ratio:.3}, diverged at tick {diverged_at:?}, stable = {}",
            factor * dt_crit,
            report.stable
        );
        if factor <= 0.9 {
            assert!(diverged_at.is_none() && report.stable);
            assert!(
                max_ratio < 10.0,
                "factor {factor}: energy grew {max_ratio}x"
            );
        } else {
            assert!(diverged_at.is_some(), "factor {factor}: not detected");
            assert!(!report.stable);
            // A diverged simulation refuses to run on.
            assert!(matches!(
                sim.tick(&TickInput::default()),
                Err(ModelError::Diverged { .. })
            ));
        }
    }
}

#[test]
fn backward_euler_stays_bounded_at_one_millisecond() {
    // The LV (semi-implicit needs several sub-steps of ~0.1 ms) and an undamped stiff cube far
    // beyond its explicit limit: one backward Euler step of 1 ms (and 10 ms) stays bounded and
    // dissipates.
    let mut lv = load_builtin("lv").unwrap();
    lv.integrator.kind = IntegratorKind::BackwardEuler;
    let stiff = cube(
        "youngs_modulus_pa = 1000000.0\npoisson_ratio = 0.45",
        "[boundary]\nclamped = [\"ZMIN\"]\n[integrator]\nkind = \"backward-euler\"",
    );
    let mut stiff_10ms = stiff.clone();
    stiff_10ms.integrator.tick_s = 0.01;
    for (name, scene) in [
        ("lv", lv),
        ("stiff cube", stiff),
        ("stiff cube 10 ms", stiff_10ms),
    ] {
        let mut sim = FemBody::new(&scene).unwrap();
        assert_eq!(sim.plan().substeps, 1);
        let explicit = integrate::critical_time_step(sim.fem(), IntegratorKind::SymplecticEuler);
        kick(&mut sim, 0.05, 3);
        let e0 = energy(&sim);
        let mut max_ratio: f64 = 0.0;
        for _ in 0..1000 {
            sim.tick(&TickInput::default()).unwrap();
            max_ratio = max_ratio.max(energy(&sim) / e0);
        }
        let r = sim.stability();
        println!(
            "backward Euler, {name}: tick {:.0e} s = {:.0} x the explicit critical step; max energy ratio {max_ratio:.3}, final {:.3e}, CG {:?}",
            scene.integrator.tick_s,
            scene.integrator.tick_s / explicit,
            energy(&sim) / e0,
            r.cg
        );
        assert!(r.stable && r.inverted_elements == 0);
        // One Newton step with a truncated CG is not exactly dissipative at 287 x the explicit
        // step on a strongly kicked body (measured: 3.4 x transiently); at 1 ms it is.
        let bound = if scene.integrator.tick_s > 2e-3 {
            10.0
        } else {
            1.05
        };
        assert!(max_ratio <= bound, "{name}: energy grew {max_ratio}x");
        assert!(energy(&sim) < 1e-3 * e0, "{name}: did not settle");
    }
}

#[test]
fn poisson_ratio_sweep_reports_the_volume_error() {
    let mut volume = Vec::new();
    for nu in [0.3, 0.45, 0.49, 0.499] {
        for kind in ALL {
            let mut scene = cube(
                &format!(
                    "youngs_modulus_pa = 10000.0\npoisson_ratio = {nu}\nmass_damping_per_s = 50.0\nphi_pa_s = 0.05\npsi_pa_s = 0.05"
                ),
                "[boundary]\nclamped = [\"ZMIN\"]\n[[loads.pressure]]\nsurfaces = [\"ZMAX\"]\npressure_pa = 200.0\n",
            );
            scene.integrator.kind = kind;
            scene.integrator.max_substeps = 2000;
            let mut sim = FemBody::new(&scene).unwrap();
            for _ in 0..500 {
                sim.tick(&TickInput::default()).unwrap();
            }
            let r = sim.stability();
            println!(
                "nu = {nu}, {:<16}: sub-steps {:>4}, volume change {:+.3e}, max displacement {:.3e} m, stable {}",
                kind.name(),
                sim.plan().substeps,
                r.volume_change,
                r.max_displacement_m,
                r.stable
            );
            assert!(r.stable && r.finite && r.inverted_elements == 0);
            assert!(r.volume_change < 0.0, "compression must lose volume");
            if kind == IntegratorKind::BackwardEuler {
                volume.push(r.volume_change.abs());
            }
        }
    }
    // Nearly incompressible material loses far less volume.
    assert!(volume[3] < volume[0] / 5.0, "{volume:?}");
}

/// Runs `ticks` ticks without a device and returns the final stability report.
fn settle(sim: &mut FemBody, ticks: usize) -> haptic_model::fem::StabilityReport {
    for _ in 0..ticks {
        if sim.tick(&TickInput::default()).is_err() {
            break;
        }
    }
    sim.stability()
}

#[test]
fn inversion_and_flattened_start_recover_with_robust_materials() {
    let mut failures = Vec::new();
    for model in ["stvk", "corotational", "stable-neo-hookean"] {
        for kind in [IntegratorKind::SemiImplicit, IntegratorKind::BackwardEuler] {
            for start in ["inverted", "flattened"] {
                let mut scene = cube(
                    &format!(
                        "model = \"{model}\"\nyoungs_modulus_pa = 10000.0\npoisson_ratio = 0.3\nmass_damping_per_s = 30.0\nphi_pa_s = 0.05\npsi_pa_s = 0.05"
                    ),
                    "[boundary]\nclamped = [\"ZMIN\"]",
                );
                scene.integrator.kind = kind;
                scene.integrator.max_substeps = 2000;
                let mut sim = FemBody::new(&scene).unwrap();
                let rest = sim.fem().rest().to_vec();
                for (x, r) in sim.state_mut().x.iter_mut().zip(&rest) {
                    // The clamped base is z = 0: mirror through it, or collapse onto it.
                    x.z = if start == "inverted" { -r.z } else { 0.0 };
                }
                let before = sim.inverted_elements();
                let t0 = std::time::Instant::now();
                let r = settle(&mut sim, 1500);
                let wall = t0.elapsed().as_secs_f64();
                println!(
                    "{model:<18} {:<14} {start:<9}: inverted {before} -> {}, max displacement {:.3e} m, finite {}, stable {} ({wall:.2} s, {} sub-steps)",
                    kind.name(),
                    r.inverted_elements,
                    r.max_displacement_m,
                    r.finite,
                    r.stable,
                    sim.plan().substeps
                );
                // Never NaN: either finite or reported as diverged.
                assert!(r.finite || r.diverged_at_s.is_some());
                assert!(before > 0);
                // Corotational under the explicit semi-implicit scheme from a fully mirrored
                // start is chaotic: whether it recovers depends on round-off (a 1e-12 relative
                // perturbation of the start flips it, with the scalar and the vectorised force
                // alike; measured 2026-11-22), so only "finite or reported" is asserted there.
                let chaotic = model == "corotational"
                    && kind == IntegratorKind::SemiImplicit
                    && start == "inverted";
                if model != "stvk"
                    && !chaotic
                    && !(r.stable && r.max_displacement_m < 1e-4 && r.inverted_elements == 0)
                {
                    failures.push(format!("{model} {} {start}", kind.name()));
                }
            }
        }
    }
    assert!(failures.is_empty(), "did not recover: {failures:?}");
}

fn momenta(sim: &FemBody) -> (DVec3, DVec3) {
    let m = sim.fem().lumped_mass_kg();
    let s = sim.state();
    let p = s.v.iter().zip(m).map(|(v, m)| *v * *m).sum::<DVec3>();
    let l =
        s.x.iter()
            .zip(&s.v)
            .zip(m)
            .map(|((x, v), m)| x.cross(*v) * *m)
            .sum::<DVec3>();
    (p, l)
}

#[test]
fn free_body_spinning_keeps_momentum_and_stays_rigid() {
    let omega = DVec3::new(0.0, 0.0, 2.0 * std::f64::consts::PI);
    for kind in ALL {
        let mut scene = cube("youngs_modulus_pa = 1000000.0\npoisson_ratio = 0.3", "");
        scene.integrator.kind = kind;
        scene.integrator.max_substeps = 1000;
        let mut sim = FemBody::new(&scene).unwrap();
        let centre = DVec3::splat(0.005);
        {
            let s = sim.state_mut();
            for (x, v) in s.x.iter().zip(s.v.iter_mut()) {
                *v = omega.cross(*x - centre) + DVec3::new(0.01, 0.0, 0.0);
            }
        }
        let (p0, l0) = momenta(&sim);
        let ek0 = sim.kinetic_energy_j();
        let mut max_el: f64 = 0.0;
        for _ in 0..1000 {
            sim.tick(&TickInput::default()).unwrap();
            max_el = max_el.max(sim.fem().elastic_energy(&sim.state().x));
        }
        let (p1, l1) = momenta(&sim);
        let dp = (p1 - p0).length() / p0.length();
        let dl = (l1 - l0).length() / l0.length();
        let dk = sim.kinetic_energy_j() / ek0 - 1.0;
        println!(
            "spinning free cube, {:<16}: max elastic / kinetic energy {:.2e}, linear momentum drift {dp:.2e}, angular momentum drift {dl:.2e}, kinetic energy change {dk:+.2e} after 1 s",
            kind.name(),
            max_el / ek0
        );
        assert!(sim.stability().stable);
        match kind {
            IntegratorKind::SymplecticEuler => {
                // Internal forces sum to zero and have zero torque, and `x' = x + h v'` keeps
                // `sum m x' x v'` = `sum m x x v'`: both momenta exact to round-off. The
                // centrifugal stretch of this stiff cube, rho w^2 L^2 / E = 4e-6, keeps the
                // elastic energy at ~1e-6 of the kinetic one.
                assert!(dp < 1e-9 && dl < 1e-9, "{dp} {dl}");
                assert!(max_el / ek0 < 1e-5);
                assert!(dk.abs() < 1e-4);
            }
            IntegratorKind::BackwardEuler => {
                // Linear momentum up to the CG residual. The linearised step sees a finite
                // rotation as a stretch (K annihilates only infinitesimal rotations), so the
                // rotation is damped artificially (measured: most of the spin is lost in 1 s).
                assert!(dp < 1e-3, "{dp}");
                assert!(max_el / ek0 < 1e-2);
            }
            IntegratorKind::SemiImplicit => {
                // The seed's eq. 34 applies `(I + h^2/m K_ii)^-1` to absolute nodal velocities:
                // it damps rigid motion too, so a free body stops (measured: all momentum gone
                // in 1 s). Reported, not a bound: the scheme is meant for anchored bodies.
                assert!(dp <= 1.0 + 1e-9);
            }
        }
    }
}

/// St. Venant-Kirchhoff settles under backward Euler and the semi-implicit scheme. Under
/// symplectic Euler the impulse inverts 6 elements under the probe and StVK, whose stress
/// softens in strong compression and which has inverted equilibria, stays there (measured
/// 2026-11-26: 6.2 mm peak, 2.4 mm left): with the patch's local law in series (the default
/// contact since 2026-11-23, the material's own half-space law since 2026-11-26) the injected
/// load acts until the surface has retreated from the probe by the local indentation plus the
/// coupling's stretch, about 1 mm, instead of 0.13 mm with the bare sphere or patch, so far
/// more of the ten-fold impulse reaches the body. (With the Hertz patch the semi-implicit
/// scheme stayed inverted too; with the material's law it settles: 5.5 mm peak, 0.03 mm
/// left.) Asserted as it is, so that a change either way is seen; the robust materials settle
/// under every integrator (the tests below).
#[test]
fn ten_fold_impulse_settles_without_inversion_stvk() {
    let failures = ten_fold_impulse_failures("stvk");
    assert_eq!(
        failures,
        ["stvk symplectic-euler"],
        "did not settle: {failures:?}"
    );
}

#[test]
fn ten_fold_impulse_settles_without_inversion_corotational() {
    ten_fold_impulse("corotational");
}

#[test]
fn ten_fold_impulse_settles_without_inversion_stable_neo_hookean() {
    ten_fold_impulse("stable-neo-hookean");
}

/// Presses the LV epicardium 6 mm over 0.6 s, adds ten times the probe force at the probe for
/// 5 ms at 0.8 s, releases over 0.9-1.5 s and lets the body settle until 3.5 s (the seed's
/// semi-implicit scheme creeps back slowly: 1.9e-4 m were left at 2.5 s on the default
/// quadratic mesh). Panics unless every integrator settles.
fn ten_fold_impulse(model: &str) {
    let failures = ten_fold_impulse_failures(model);
    assert!(failures.is_empty(), "did not settle: {failures:?}");
}

/// The runs of [`ten_fold_impulse`] that did not settle (`"MODEL INTEGRATOR"`), after asserting
/// what every run must do (the impulse acted; nothing turned NaN unreported).
fn ten_fold_impulse_failures(model: &str) -> Vec<String> {
    let mut failures = Vec::new();
    for kind in ALL {
        let mut scene = load_builtin("lv").unwrap();
        scene.material.model =
            haptic_model::material::MaterialModel::from_scene_name(model).unwrap();
        scene.integrator.kind = kind;
        let mut sim = FemBody::new(&scene).unwrap();
        let device = |k: usize| {
            let t = k as f64 * 1e-3;
            let depth = 0.006 * ((t / 0.6).min(1.0) - ((t - 0.9) / 0.6).clamp(0.0, 1.0));
            DVec3::new(0.014 - depth, 0.0, -0.005)
        };
        let mut hold = DVec3::ZERO;
        let mut max_disp: f64 = 0.0;
        // Largest displacement when the impulse starts, and during it and the 20 ms after.
        let (mut disp_at_hold, mut disp_impulse): (f64, f64) = (0.0, 0.0);
        let mut failed = None;
        for k in 0..3500 {
            let out = sim.tick(&TickInput {
                device_position_m: Some(device(k)),
                device_velocity_m_per_s: (device(k + 1) - device(k)) / 1e-3,
            });
            let out = match out {
                Ok(o) => o,
                Err(e) => {
                    failed = Some(e);
                    break;
                }
            };
            if k == 799 {
                hold = out.force_on_device_n;
                // Ten times the probe force, at the probe (over its contact patch), for 5 ms.
                sim.add_probe_load(-hold * 10.0, 0.005).unwrap();
                disp_at_hold = sim.max_displacement_m();
            }
            if (800..825).contains(&k) {
                disp_impulse = disp_impulse.max(sim.max_displacement_m());
            }
            max_disp = max_disp.max(sim.max_displacement_m());
        }
        let r = sim.stability();
        println!(
            "10-fold impulse ({:.3} N for 5 ms) on lv, {model:<18} {:<16}: displacement {disp_at_hold:.3e} m before, {disp_impulse:.3e} m during, max {max_disp:.3e} m, residual {:.3e} m, inverted {}, error {failed:?}",
            10.0 * hold.length(),
            kind.name(),
            r.max_displacement_m,
            r.inverted_elements
        );
        assert!(hold.length() > 0.03);
        // The impulse acted: the body moved further (measured 8-50 % beyond the held
        // indentation, least under eq. 34, which damps).
        assert!(
            disp_impulse > 1.05 * disp_at_hold,
            "{disp_impulse} vs {disp_at_hold}"
        );
        // Never NaN: finite, or the divergence is reported.
        assert!(r.finite || r.diverged_at_s.is_some());
        // Every material settles under every integrator (measured on the default quadratic
        // mesh: at most 5.7 mm peak displacement, residual 5e-5 m for eq. 34 and 1.2e-7 m
        // or less for the others, no inverted element). When the same load sat on the
        // three nodes of one surface sub-triangle (`add_point_load`), StVK and stable
        // Neo-Hookean exceeded the 100 m/s divergence limit: a point load is singular in
        // the continuum, a probe is not.
        if !(failed.is_none()
            && r.stable
            && max_disp < 0.03
            && r.inverted_elements == 0
            && r.max_displacement_m < 1e-4)
        {
            failures.push(format!("{model} {}", kind.name()));
        }
    }
    failures
}

/// A probe pressed 5 mm past first touch into the default `lv` and slid 6 mm along the long
/// axis at 60 mm/s, and back. The robust materials keep every element upright (measured: none
/// inverted, kinetic energy at most 5.7e-7 J); St. Venant-Kirchhoff, whose stress softens in
/// strong compression, inverts some elements under the probe (measured: 5, kinetic energy
/// spikes to 7e-6 J; all recover when the probe leaves, see the soak example): printed, not
/// asserted.
#[test]
fn deep_sliding_probe_inverts_nothing_with_the_robust_materials() {
    for model in ["stvk", "corotational", "stable-neo-hookean"] {
        let mut scene = load_builtin("lv").unwrap();
        scene.material.model =
            haptic_model::material::MaterialModel::from_scene_name(model).unwrap();
        let mut sim = FemBody::new(&scene).unwrap();
        // Epicardium at x = 9.68 mm on the equator line z = -5 mm; the 2 mm probe touches it
        // with its centre at 11.68 mm.
        let device = |k: usize| {
            let t = k as f64 * 1e-3;
            let depth = 0.005 * (t / 0.3).min(1.0);
            let slide =
                ((t - 0.4).max(0.0) / 0.1).min(1.0) * (1.0 - ((t - 0.6).max(0.0) / 0.1).min(1.0));
            DVec3::new(0.011_68 - depth, 0.0, -0.005 - 0.006 * slide)
        };
        let (mut inverted, mut kinetic, mut force): (usize, f64, f64) = (0, 0.0, 0.0);
        for k in 0..900 {
            let out = sim
                .tick(&TickInput {
                    device_position_m: Some(device(k)),
                    device_velocity_m_per_s: (device(k + 1) - device(k)) / 1e-3,
                })
                .unwrap();
            let r = sim.stability();
            inverted = inverted.max(r.inverted_elements);
            kinetic = kinetic.max(r.kinetic_energy_j);
            force = force.max(out.force_on_device_n.length());
        }
        println!(
            "deep sliding probe on lv, {model:<18}: inverted at most {inverted}, kinetic energy at most {kinetic:.2e} J, force at most {force:.3} N"
        );
        assert!(force > 0.04, "{model}: the probe did not press ({force} N)");
        if model != "stvk" {
            assert_eq!(inverted, 0, "{model}");
            assert!(kinetic < 5e-6, "{model}: {kinetic} J");
        }
    }
}

#[test]
fn sliver_mesh_is_stable_under_the_automatic_time_step() {
    let mut mesh = box_mesh(DVec3::splat(0.01), [3, 3, 3]);
    let good = min_dihedral_angle_deg(&mesh);
    // Push an interior node towards a face of one of its tetrahedra until a sliver appears.
    let centre = DVec3::splat(0.01 / 3.0);
    let node = (0..mesh.nodes.len())
        .min_by(|&a, &b| {
            (mesh.nodes[a] - centre)
                .length()
                .total_cmp(&(mesh.nodes[b] - centre).length())
        })
        .unwrap();
    let original = mesh.nodes[node];
    let mut found = None;
    'search: for dir in [
        DVec3::X,
        DVec3::Y,
        DVec3::Z,
        DVec3::new(1.0, 1.0, 0.0),
        DVec3::new(1.0, 1.0, 1.0),
        DVec3::new(1.0, -1.0, 0.0),
    ] {
        for sign in [1.0, -1.0] {
            for k in 1..400 {
                let p = original + dir.normalize() * sign * (k as f64 * 1e-5);
                mesh.nodes[node] = p;
                let ok = mesh.tets.iter().all(|t| {
                    let [a, b, c, d] = t.map(|i| mesh.nodes[i as usize]);
                    (b - a).cross(c - a).dot(d - a) > 0.0
                });
                if !ok {
                    break;
                }
                let angle = min_dihedral_angle_deg(&mesh);
                if angle < 5.0 && angle > 1.0 {
                    found = Some(angle);
                    break 'search;
                }
            }
        }
    }
    let angle = found.expect("no sliver made");
    for kind in ALL {
        let text = "[mesh]\nbuiltin = \"box\"\nsize = [0.01, 0.01, 0.01]\ncells = [3, 3, 3]\n[material]\ndensity_kg_per_m3 = 1000.0\nyoungs_modulus_pa = 10000.0\npoisson_ratio = 0.3\n[boundary]\nclamped = [\"ZMIN\"]\n";
        let mut scene = parse_scene_toml(text, Path::new(".")).unwrap();
        scene.mesh = mesh.clone();
        scene.integrator.kind = kind;
        scene.integrator.max_substeps = 5000;
        let mut regular = scene.clone();
        regular.mesh = box_mesh(DVec3::splat(0.01), [3, 3, 3]);
        let mut sim = FemBody::new(&scene).unwrap();
        let plain = FemBody::new(&regular).unwrap();
        kick(&mut sim, 1e-2, 11);
        let e0 = energy(&sim);
        let mut max_ratio: f64 = 0.0;
        for _ in 0..1000 {
            sim.tick(&TickInput::default()).unwrap();
            max_ratio = max_ratio.max(energy(&sim) / e0);
        }
        println!(
            "sliver (min dihedral {angle:.2} deg, regular {good:.1}), {:<16}: sub-steps {} (regular mesh {}), critical step {:.3e} s (regular {:.3e}), max energy ratio {max_ratio:.3}",
            kind.name(),
            sim.plan().substeps,
            plain.plan().substeps,
            sim.plan().critical_dt_s,
            plain.plan().critical_dt_s
        );
        assert!(sim.stability().stable);
        assert!(max_ratio < 3.0, "{kind:?}: energy grew {max_ratio}x");
    }
}

#[test]
fn absurd_inputs_are_rejected_without_touching_the_state() {
    for kind in ALL {
        let mut scene = load_builtin("lv").unwrap();
        scene.integrator.kind = kind;
        let mut sim = FemBody::new(&scene).unwrap();
        for _ in 0..20 {
            sim.tick(&TickInput {
                device_position_m: Some(DVec3::new(0.0105, 0.0, -0.005)),
                device_velocity_m_per_s: DVec3::ZERO,
            })
            .unwrap();
        }
        let before = sim.state().clone();
        let loads = sim.active_point_loads();
        let bad_inputs = [
            (Some(DVec3::new(f64::NAN, 0.0, 0.0)), DVec3::ZERO),
            (Some(DVec3::new(0.0, f64::INFINITY, 0.0)), DVec3::ZERO),
            (Some(DVec3::new(1e3, 0.0, 0.0)), DVec3::ZERO),
            (Some(DVec3::ZERO), DVec3::new(0.0, 0.0, f64::NAN)),
            (Some(DVec3::ZERO), DVec3::splat(f64::NEG_INFINITY)),
        ];
        for (p, v) in bad_inputs {
            let r = sim.tick(&TickInput {
                device_position_m: p,
                device_velocity_m_per_s: v,
            });
            assert!(
                matches!(r, Err(ModelError::InvalidDevice(_))),
                "{p:?} {v:?}"
            );
        }
        let bad_loads = [
            (DVec3::new(f64::NAN, 0.0, 0.0), DVec3::X, 0.1),
            (DVec3::ZERO, DVec3::new(0.0, f64::INFINITY, 0.0), 0.1),
            (DVec3::ZERO, DVec3::X * 1e6, 0.1),
            (DVec3::ZERO, DVec3::X, f64::NAN),
            (DVec3::ZERO, DVec3::X, -1.0),
            (DVec3::ZERO, DVec3::X, 1e9),
            (DVec3::splat(1e6), DVec3::X, 0.1),
        ];
        for (p, f, d) in bad_loads {
            assert!(
                matches!(
                    sim.add_point_load(p, f, d),
                    Err(ModelError::InvalidInput(_))
                ),
                "{p:?} {f:?} {d}"
            );
            // The probe load has no point: every bad force or duration is refused too.
            if p == DVec3::ZERO {
                assert!(
                    matches!(sim.add_probe_load(f, d), Err(ModelError::InvalidInput(_))),
                    "{f:?} {d}"
                );
            }
        }
        let after = sim.state();
        assert_eq!(after.x, before.x);
        assert_eq!(after.v, before.v);
        assert_eq!(after.time_s, before.time_s);
        assert_eq!(sim.active_point_loads(), loads);
        assert_eq!(sim.probe_load_remaining_s(), 0.0);
        assert!(sim.stability().stable);
        // The simulation still runs.
        sim.tick(&TickInput::default()).unwrap();
    }
    // Scene values: each error names its field.
    let base = "[mesh]\nbuiltin = \"box\"\nsize = [0.01, 0.01, 0.01]\ncells = [2, 2, 2]\n[material]\ndensity_kg_per_m3 = 1000.0\nyoungs_modulus_pa = 10000.0\npoisson_ratio = 0.3\n";
    let cases = [
        (
            "youngs_modulus_pa = 10000.0",
            "youngs_modulus_pa = nan",
            "material.youngs_modulus_pa",
        ),
        (
            "poisson_ratio = 0.3",
            "poisson_ratio = 0.5",
            "material.poisson_ratio",
        ),
        (
            "density_kg_per_m3 = 1000.0",
            "density_kg_per_m3 = inf",
            "material.density_kg_per_m3",
        ),
        ("", "[integrator]\ntick_s = nan", "integrator.tick_s"),
        (
            "",
            "[integrator]\ncg_tolerance = 2.0",
            "integrator.cg_tolerance",
        ),
        (
            "",
            "[integrator]\ncg_max_iterations = 0",
            "integrator.cg_max_iterations",
        ),
        (
            "",
            "[integrator]\nsafety_factor = -inf",
            "integrator.safety_factor",
        ),
        ("", "[probe]\nradius_m = -1.0", "probe.radius_m"),
        (
            "",
            "[probe]\ncoupling_stiffness_n_per_m = inf",
            "probe.coupling_stiffness_n_per_m",
        ),
        (
            "",
            "[loads]\ngravity_m_per_s2 = [0.0, nan, 0.0]",
            "loads.gravity_m_per_s2",
        ),
        (
            "",
            "[loads]\ngravity_m_per_s2 = [0.0, 0.0, -1e9]",
            "loads.gravity_m_per_s2",
        ),
        (
            "",
            "[[loads.pressure]]\nsurfaces = [\"ZMAX\"]\npressure_pa = inf",
            "loads.pressure[0].pressure_pa",
        ),
        (
            "",
            "[[loads.point]]\npoint_m = [0.0, 0.0, 0.01]\nforce_n = [0.0, 0.0, 1e12]",
            "loads.point[0].force_n",
        ),
        (
            "",
            "[[loads.point]]\npoint_m = [0.0, nan, 0.01]\nforce_n = [0.0, 0.0, 1.0]",
            "loads.point[0].point_m",
        ),
    ];
    for (from, to, field) in cases {
        let text = if from.is_empty() {
            format!("{base}{to}\n")
        } else {
            base.replace(from, to)
        };
        match parse_scene_toml(&text, Path::new(".")) {
            Err(ModelError::SceneField { field: f, .. }) => assert_eq!(f, field, "{to}"),
            other => panic!("{to}: expected an error naming {field}, got {other:?}"),
        }
    }
}

/// The sphere under backward Euler (implicit in the step) against hostile probe motion on the
/// default `lv`: pressed 5 mm past first touch, slid 6 mm at 60 mm/s and back, then the device
/// jumps 10 mm further into the body for one tick (a tracking glitch, 15 m/s) and leaves. Never
/// a panic or a non-finite force; forces within the probe's force limit; the robust materials
/// invert nothing before the jump; corotational comes to rest upright after the release. The
/// jump's coupling force (about 4.5 N) lands on the few faces the sphere touches: St.
/// Venant-Kirchhoff inverts elements and recovers, stable neo-Hookean diverges and is
/// quarantined (`ModelError::Diverged`, the designed end of a session that left the physics),
/// where the Hertz patch, which spreads the same force over 4 mm, survives with every material
/// (measured 2026-11-24; docs/accuracy.md "Sphere contact in the servo").
#[test]
fn the_implicit_sphere_survives_deep_fast_and_jumping_probes() {
    for model in ["stvk", "corotational", "stable-neo-hookean"] {
        let mut scene = load_builtin("lv").unwrap();
        scene.material.model =
            haptic_model::material::MaterialModel::from_scene_name(model).unwrap();
        scene.integrator.kind = haptic_model::integrate::IntegratorKind::BackwardEuler;
        scene.probe.contact = haptic_model::contact::ContactModel::Sphere;
        let max_force = scene.probe.max_force_n;
        let mut sim = FemBody::new(&scene).unwrap();
        let device = |k: usize| -> Option<DVec3> {
            let t = k as f64 * 1e-3;
            if k == 750 {
                return Some(DVec3::new(0.011_68 - 0.015, 0.0, -0.005));
            }
            if t > 0.8 {
                return None;
            }
            let depth = 0.005 * (t / 0.3).min(1.0);
            let slide =
                ((t - 0.4).max(0.0) / 0.1).min(1.0) * (1.0 - ((t - 0.6).max(0.0) / 0.1).min(1.0));
            Some(DVec3::new(0.011_68 - depth, 0.0, -0.005 - 0.006 * slide))
        };
        let (mut inverted, mut force, mut diverged) = (0usize, 0.0f64, None);
        for k in 0..1800 {
            let velocity = match (device(k), device(k + 1)) {
                (Some(a), Some(b)) => (b - a) / 1e-3,
                _ => DVec3::ZERO,
            };
            match sim.tick(&TickInput {
                device_position_m: device(k),
                device_velocity_m_per_s: velocity,
            }) {
                Ok(out) => {
                    let f = out.force_on_device_n.length();
                    assert!(
                        f.is_finite() && f <= max_force * (1.0 + 1e-12),
                        "{model} tick {k}: {f} N"
                    );
                    force = force.max(f);
                }
                Err(e) => {
                    assert!(
                        matches!(e, haptic_model::ModelError::Diverged { .. }),
                        "{model} tick {k}: {e}"
                    );
                    diverged = Some(format!("tick {k}: {e}"));
                    break;
                }
            }
            if k < 750 {
                inverted = inverted.max(sim.stability().inverted_elements);
            }
        }
        let rest = sim.stability();
        println!(
            "implicit sphere, {model:<18}: force at most {force:.3} N, inverted at most {inverted} before the jump, {} after the release, kinetic energy then {:.2e} J, {}",
            rest.inverted_elements,
            rest.kinetic_energy_j,
            diverged.as_deref().unwrap_or("no divergence")
        );
        assert!(force > 0.04, "{model}: the probe did not press ({force} N)");
        if model != "stvk" {
            assert_eq!(inverted, 0, "{model}");
        }
        if model == "corotational" {
            assert!(diverged.is_none(), "{model}: {diverged:?}");
            assert_eq!(rest.inverted_elements, 0, "{model}");
            assert!(
                rest.stable && rest.kinetic_energy_j < 1e-9,
                "{model}: {rest:?}"
            );
        }
    }
}
