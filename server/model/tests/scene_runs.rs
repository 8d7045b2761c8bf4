//! Every Gmsh file of `../shared/data/lv/` loads through its scene file and runs under the probe;
//! an explicit configuration that cannot be stable is refused with a clear error.

use std::path::Path;

use haptic_model::fem::{FemBody, TickInput};
use haptic_model::integrate::IntegratorKind;
use haptic_model::scene::{load_builtin, load_scene_file};
use haptic_model::{DVec3, ModelError};

#[test]
fn every_lv_mesh_file_loads_and_runs() {
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes");
    for name in ["lv_h3", "lv_h3_v41", "lv_h2", "lv_h1"] {
        let scene = load_scene_file(&scenes.join(format!("{name}.toml"))).unwrap();
        // mm converted to m: the epicardium's equatorial radius is 10 mm.
        let (lo, hi) = scene.mesh.bounding_box();
        assert!(
            (hi.x - 0.010).abs() < 1e-4 && (lo.z + 0.020).abs() < 1e-4,
            "{name}: {lo} {hi}"
        );
        let mut sim = FemBody::new(&scene).unwrap();
        let mut peak: f64 = 0.0;
        for k in 0..300 {
            // Reach the surface quickly, then press 1 mm in.
            let x = 0.0125 - 0.002 * (k as f64 / 300.0);
            let out = sim
                .tick(&TickInput {
                    device_position_m: Some(DVec3::new(x, 0.0, -0.005)),
                    ..Default::default()
                })
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            peak = peak.max(out.force_on_device_n.length());
        }
        assert!(peak > 1e-3, "{name}: the probe never pushed ({peak} N)");
        assert!(
            sim.max_displacement_m() < 0.003,
            "{name}: {} m",
            sim.max_displacement_m()
        );
    }
}

#[test]
fn an_explicit_configuration_that_cannot_be_stable_is_refused() {
    let mut scene = load_builtin("lv").unwrap();
    scene.integrator.kind = IntegratorKind::SymplecticEuler;
    // One sub-step of 1 ms is far above the ~0.1 ms critical step.
    scene.integrator.substeps = Some(1);
    let err = FemBody::new(&scene).unwrap_err();
    assert!(matches!(err, ModelError::Unstable { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("symplectic-euler") && msg.contains("needs dt <="),
        "{msg}"
    );
    // Automatic sub-stepping with too few allowed sub-steps is refused the same way.
    scene.integrator.substeps = None;
    scene.integrator.max_substeps = 2;
    assert!(matches!(
        FemBody::new(&scene),
        Err(ModelError::Unstable { .. })
    ));
    // And the automatic plan is stable by construction.
    scene.integrator.max_substeps = 64;
    let sim = FemBody::new(&scene).unwrap();
    let sf = scene.integrator.safety_factor;
    assert!(sf <= 0.9);
    assert!(sim.plan().sub_dt_s <= sf * sim.plan().critical_dt_s + 1e-15);
}
