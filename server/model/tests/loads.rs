//! Scene loads (issue 3 section 1): gravity, dead and follower pressure on tagged surfaces and
//! point forces, parsed from `[loads]`, summed correctly by `Scene::external_forces`, applied by
//! every integrator in the tick (a damped dynamic run settles on the static solution), and
//! rejected with the offending field named.

use std::path::Path;

use haptic_model::fem::{FemBody, TickInput};
use haptic_model::integrate::IntegratorKind;
use haptic_model::scene::{Scene, parse_scene_toml};
use haptic_model::statics::{StaticParams, solve_static};
use haptic_model::{DVec3, ModelError};

/// A 20 x 10 x 10 mm beam (4 x 2 x 2 cells), clamped at x = 0, with the given `[loads]` text.
fn beam(loads: &str) -> Result<Scene, ModelError> {
    let text = format!(
        r#"
[mesh]
builtin = "box"
size = [0.02, 0.01, 0.01]
cells = [4, 2, 2]
[material]
youngs_modulus_pa = 20000.0
poisson_ratio = 0.3
density_kg_per_m3 = 1000.0
mass_damping_per_s = 60.0
phi_pa_s = 0.2
psi_pa_s = 0.2
[boundary]
clamped = ["XMIN"]
{loads}
"#
    );
    parse_scene_toml(&text, Path::new("."))
}

#[test]
fn external_forces_sum_to_the_applied_loads() {
    let scene = beam(
        "[loads]\ngravity_m_per_s2 = [0.0, 0.0, -9.81]\n\
         [[loads.pressure]]\nsurfaces = [\"ZMAX\"]\npressure_pa = 50.0\n\
         [[loads.pressure]]\nsurfaces = [\"YMAX\"]\npressure_pa = 20.0\nfollower = true\n\
         [[loads.point]]\npoint_m = [0.02, 0.005, 0.005]\nforce_n = [0.0, 0.001, 0.0]\n",
    )
    .unwrap();
    assert_eq!(scene.loads.pressure.len(), 2);
    assert!(scene.loads.pressure[1].follower && !scene.loads.pressure[0].follower);
    let p = scene.loads.point[0];
    assert!((p.bary.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    let rest = scene.mesh.nodes.clone();
    let f = scene.external_forces(&rest);
    let total: DVec3 = f.iter().copied().sum();
    let mass = 1000.0 * 0.02 * 0.01 * 0.01;
    // gravity + 50 Pa on the 2e-4 m^2 top face (pushing down) + 20 Pa on the 2e-4 m^2 side
    // face at y = 0.01 (pushing -y) + the point force.
    let expected = DVec3::new(0.0, -20.0 * 2e-4 + 0.001, -9.81 * mass - 50.0 * 2e-4);
    assert!((total - expected).length() < 1e-12, "{total} vs {expected}");

    // Rotate the body rigidly by 90 degrees about x: the follower pressure turns with it (its
    // total goes from -y to -z), the dead loads do not.
    let rot = |v: DVec3| DVec3::new(v.x, -v.z, v.y);
    let turned: Vec<DVec3> = rest.iter().map(|x| rot(*x)).collect();
    let g = scene.external_forces(&turned);
    let total_turned: DVec3 = g.iter().copied().sum();
    let follower = DVec3::new(0.0, -20.0 * 2e-4, 0.0);
    let expected_turned = expected - follower + rot(follower);
    assert!(
        (total_turned - expected_turned).length() < 1e-12,
        "{total_turned} vs {expected_turned}"
    );
}

#[test]
fn damped_dynamics_settle_on_the_static_solution_for_every_integrator() {
    let loads = "[loads]\ngravity_m_per_s2 = [0.0, 0.0, -9.81]\n\
                 [[loads.pressure]]\nsurfaces = [\"XMAX\"]\npressure_pa = 30.0\nfollower = true\n\
                 [[loads.point]]\npoint_m = [0.02, 0.005, 0.01]\nforce_n = [0.0, 0.0, -0.002]\n";
    let scene = beam(loads).unwrap();
    // Static reference: Newton on the dead part, fixed point on the follower part.
    let sim = FemBody::new(&scene).unwrap();
    let fem = sim.fem().clone();
    let mut x = fem.rest().to_vec();
    for _ in 0..30 {
        let f = scene.external_forces(&x);
        solve_static(&fem, &f, &mut x, &StaticParams::default()).unwrap();
    }
    let tip = |x: &[DVec3]| {
        (0..x.len())
            .filter(|&i| fem.rest()[i].x > 0.0199)
            .map(|i| x[i] - fem.rest()[i])
            .sum::<DVec3>()
            / (0..x.len()).filter(|&i| fem.rest()[i].x > 0.0199).count() as f64
    };
    let reference = tip(&x);
    assert!(reference.z < -1e-4, "{reference}");
    for kind in [
        IntegratorKind::SemiImplicit,
        IntegratorKind::SymplecticEuler,
        IntegratorKind::BackwardEuler,
    ] {
        let mut s = scene.clone();
        s.integrator.kind = kind;
        let mut sim = FemBody::new(&s).unwrap();
        for _ in 0..4000 {
            sim.tick(&TickInput::default()).unwrap();
        }
        let got = tip(&sim.state().x);
        let err = (got - reference).length() / reference.length();
        println!(
            "{:<16}: tip displacement {got} m vs static {reference} m, relative error {err:.2e}",
            kind.name()
        );
        assert!(err < 1e-4, "{kind:?}: {err}");
    }
}

#[test]
fn load_errors_name_their_field() {
    let cases = [
        (
            "[[loads.pressure]]\nsurfaces = [\"NOPE\"]\npressure_pa = 1.0",
            "loads.pressure[0].surfaces",
        ),
        (
            "[[loads.pressure]]\nsurfaces = [\"ZMAX\"]",
            "loads.pressure[0].pressure_pa",
        ),
        (
            "[[loads.pressure]]\nsurfaces = [\"ZMAX\"]\npressure_pa = 1.0\n[[loads.pressure]]\nsurfaces = []\npressure_pa = 1.0",
            "loads.pressure[1].surfaces",
        ),
        (
            "[[loads.point]]\nforce_n = [0.0, 0.0, 1.0]",
            "loads.point[0].point_m",
        ),
        (
            "[[loads.point]]\npoint_m = [5.0, 0.0, 0.0]\nforce_n = [0.0, 0.0, 1.0]",
            "loads.point[0].point_m",
        ),
        (
            "[[loads.point]]\npoint_m = [0.0, 0.0, 0.0]\nforce_n = [0.0, inf, 1.0]",
            "loads.point[0].force_n",
        ),
        (
            "[loads]\ngravity_m_per_s2 = [0.0, 0.0, inf]",
            "loads.gravity_m_per_s2",
        ),
    ];
    for (text, field) in cases {
        match beam(text) {
            Err(ModelError::SceneField { field: f, message }) => {
                assert_eq!(f, field, "{text}: {message}")
            }
            other => panic!("{text}: expected an error naming {field}, got {other:?}"),
        }
    }
    // Unknown keys name their field.
    assert!(matches!(
        beam("[loads]\ngravity = [0.0, 0.0, -9.81]"),
        Err(ModelError::SceneField { field, .. }) if field == "loads.gravity"
    ));
    // No section: no load.
    assert!(beam("").unwrap().loads.is_empty());
}
