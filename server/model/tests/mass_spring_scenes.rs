//! Mass-spring scenes: the built-ins (`hemisphere-springs`, `lv-surface-springs`) load with
//! valid calibration tables identical to their `deploy/scenes/` copies and build through
//! `build_body`; every bad value is refused naming its field; a missing, malformed or stale
//! table is detected and refused with the command that computes it.

use std::path::{Path, PathBuf};

use haptic_model::mass_spring::calibration::ContactShape;
use haptic_model::scene::{
    ModelFamily, TableState, builtin_calibration, load_builtin, load_scene_file, parse_scene_toml,
};
use haptic_model::{ModelError, build_body};

const NAMES: [&str; 2] = ["hemisphere-springs", "lv-surface-springs"];

fn deploy_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes")
}

#[test]
fn the_builtin_spring_scenes_load_with_valid_tables_and_build() {
    for name in NAMES {
        let scene = load_builtin(name).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(scene.family, ModelFamily::MassSpring);
        let ms = scene.mass_spring.as_ref().expect("mass-spring part");
        assert!(
            matches!(ms.table, TableState::Ready(_)),
            "{name}: {:?}",
            ms.table().err()
        );
        assert_eq!(ms.contact, ContactShape::Probe(scene.probe));
        let body = build_body(&scene).unwrap_or_else(|e| panic!("{name}: {e}"));
        let info = body.info();
        assert_eq!(info.family, "mass-spring");
        let stats = body.stats();
        assert_eq!(stats.nodes, ms.surface.node_count());
        assert_eq!(stats.surface_vertices, ms.surface.node_count());
        assert_eq!(
            body.surface_topology().triangles.len(),
            ms.surface.triangle_count()
        );
        // The deploy copy of the table is the compiled-in one, and the deploy scene reads it.
        let file = &ms.calibration_file;
        let copy = std::fs::read_to_string(deploy_dir().join(file)).expect("deploy table");
        assert_eq!(
            copy,
            builtin_calibration(file).expect("built-in table"),
            "{file}"
        );
        // And so are the organ reference and table, when the scene has them.
        if let Some(organ) = &ms.organ {
            let reference = format!("{name}.reference.csv");
            for file in [reference.as_str(), organ.file.as_str()] {
                let copy = std::fs::read_to_string(deploy_dir().join(file)).expect("deploy copy");
                assert_eq!(copy, builtin_calibration(file).expect("built-in"), "{file}");
            }
            assert!(organ.table.is_ok(), "{:?}", organ.table().err());
        }
        let from_file = load_scene_file(&deploy_dir().join(format!("{name}.toml"))).expect("file");
        let msf = from_file.mass_spring.expect("mass-spring part");
        assert!(
            matches!(msf.table, TableState::Ready(_)),
            "{:?}",
            msf.table().err()
        );
        assert_eq!(msf.organ.is_some(), ms.organ.is_some(), "{name}");
        if let Some(o) = &msf.organ {
            assert!(o.table.is_ok(), "{name}: {:?}", o.table().err());
        }
    }
    let hemi = load_builtin("hemisphere-springs").unwrap();
    let ms = hemi.mass_spring.unwrap();
    // 50 mm radius, about 8 mm edges, the rim clamped.
    let rim = (0..ms.surface.node_count() as u32)
        .filter(|&i| ms.surface.is_fixed(i))
        .count();
    assert!(rim > 20 && ms.surface.node_count() > 200);
    for i in 0..ms.surface.node_count() {
        let p = ms.surface.rest()[i];
        assert!((p.length() - 0.05).abs() < 1e-12 && p.z >= 0.0);
        assert!(
            ms.surface.rest_normal(i as u32).dot(p) > 0.0,
            "outward normals"
        );
    }
}

fn field_error(text: &str) -> (String, String) {
    match parse_scene_toml(text, Path::new(".")) {
        Err(ModelError::SceneField { field, message }) => (field, message),
        Err(e) => panic!("expected a field error, got {e}"),
        Ok(_) => panic!("expected an error for:\n{text}"),
    }
}

const BASE: &str = r#"
[model]
family = "mass-spring"
[mesh]
builtin = "hemisphere"
length_unit = "mm"
outer_radius = 50.0
edge_length = 10.0
[boundary]
clamped = ["RIM"]
[mass_spring]
mesh_spring_n_per_m = 60.0
home_spring_n_per_m = 60.0
node_mass_kg = 0.001
springs = "unchanged"
"#;

#[test]
fn bad_values_are_refused_naming_the_field() {
    let scene = parse_scene_toml(BASE, Path::new(".")).expect("base scene");
    assert!(matches!(
        scene.mass_spring.as_ref().unwrap().table,
        TableState::NotNeeded
    ));
    build_body(&scene).expect("unchanged springs need no table");
    // The Hertz and local-law patches need a material's law, which a spring surface does not
    // have.
    for contact in ["patch-hertz", "patch-local"] {
        let scene = parse_scene_toml(
            &format!("{BASE}\n[probe]\ncontact = \"{contact}\"\n"),
            Path::new("."),
        )
        .expect("parses");
        match build_body(&scene) {
            Err(ModelError::SceneField { field, .. }) => assert_eq!(field, "probe.contact"),
            Err(e) => panic!("expected a field error, got {e}"),
            Ok(_) => panic!("a mass-spring surface accepted {contact}"),
        }
    }
    let cases = [
        (
            "node_mass_kg = 0.001",
            "node_mass_kg = -1.0",
            "mass_spring.node_mass_kg",
        ),
        (
            "mesh_spring_n_per_m = 60.0",
            "mesh_spring_n_per_m = nan",
            "mass_spring.mesh_spring_n_per_m",
        ),
        (
            "home_spring_n_per_m = 60.0",
            "",
            "mass_spring.home_spring_n_per_m",
        ),
        (
            "springs = \"unchanged\"",
            "springs = \"double\"",
            "mass_spring.springs",
        ),
        (
            "springs = \"unchanged\"",
            "springs = \"unchanged\"\nrings = 99",
            "mass_spring.rings",
        ),
        (
            "springs = \"unchanged\"",
            "springs = \"unchanged\"\nvertex_rule = \"sqrt3\"",
            "mass_spring.vertex_rule",
        ),
        (
            "springs = \"unchanged\"",
            "springs = \"unchanged\"\ndamping_n_s_per_m = -0.1",
            "mass_spring.damping_n_s_per_m",
        ),
        (
            "springs = \"unchanged\"",
            "springs = \"unchanged\"\ncoarsen_delay_s = -1.0",
            "mass_spring.coarsen_delay_s",
        ),
        (
            "springs = \"unchanged\"",
            "springs = \"unchanged\"\nkm_over_kh_after = 0.0",
            "mass_spring.km_over_kh_after",
        ),
        (
            "edge_length = 10.0",
            "edge_length = 80.0",
            "mesh.edge_length",
        ),
        ("edge_length = 10.0", "", "mesh.edge_length"),
        (
            "family = \"mass-spring\"",
            "family = \"fem\"",
            "mesh.builtin",
        ),
    ];
    for (from, to, field) in cases {
        let text = BASE.replace(from, to);
        assert_ne!(text, BASE);
        let (f, m) = field_error(&text);
        assert_eq!(f, field, "{to}: {m}");
    }
    let extra = [
        (
            "[material]\nyoungs_modulus_pa = 1.0\npoisson_ratio = 0.3\ndensity_kg_per_m3 = 1.0\n",
            "material",
        ),
        ("[loads]\ngravity_m_per_s2 = [0.0, 0.0, -9.81]\n", "loads"),
        (
            "[integrator]\nkind = \"backward-euler\"\n",
            "integrator.kind",
        ),
    ];
    for (section, field) in extra {
        let (f, m) = field_error(&format!("{BASE}\n{section}"));
        assert_eq!(f, field, "{m}");
    }
    let (f, _) = field_error(&BASE.replace("springs = \"unchanged\"", "").replace(
        "[mass_spring]\nmesh_spring_n_per_m = 60.0\nhome_spring_n_per_m = 60.0\nnode_mass_kg = 0.001\n",
        "",
    ));
    assert_eq!(f, "mass_spring");
    // A [mass_spring] section in a FEM scene.
    let fem = haptic_model::scene::builtin_scene_toml("lv").unwrap();
    let (f, _) = field_error(&format!("{fem}\n[mass_spring]\nnode_mass_kg = 1.0\n"));
    assert_eq!(f, "mass_spring");
}

#[test]
fn missing_malformed_and_stale_tables_are_refused_with_the_command() {
    let dir = std::env::temp_dir().join(format!("haptic-ms-scenes-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // The subdivision table alone: the scene without its organ keys (their files would have
    // to be copied too; the organ table's refusals are the organ tests').
    let hemi: String = haptic_model::scene::builtin_scene_toml("hemisphere-springs")
        .unwrap()
        .lines()
        .filter(|l| {
            !["reference_file", "reference_axis", "organ_file"]
                .iter()
                .any(|k| l.starts_with(k))
        })
        .map(|l| format!("{l}\n"))
        .collect();
    let table = builtin_calibration("hemisphere-springs.calibration.csv").unwrap();
    let scene_path = dir.join("h.toml");
    std::fs::write(&scene_path, &hemi).unwrap();
    let table_path = dir.join("hemisphere-springs.calibration.csv");
    let refused = |why: &str| {
        let scene = load_scene_file(&scene_path).expect("the scene itself is valid");
        let ms = scene.mass_spring.as_ref().unwrap();
        assert!(matches!(ms.table, TableState::Unusable(_)), "{why}");
        let err = build_body(&scene).err().expect("refused").to_string();
        assert!(
            err.contains("haptic-calibrate") && err.contains("calibration"),
            "{why}: {err}"
        );
        err
    };
    // Missing.
    let _ = std::fs::remove_file(&table_path);
    let err = refused("missing");
    assert!(err.contains("cannot be read"), "{err}");
    // Malformed.
    std::fs::write(&table_path, table.replacen("# key", "# key zz", 1)).unwrap();
    refused("malformed");
    // Stale: the scene's springs changed after the table was computed.
    std::fs::write(&table_path, table).unwrap();
    assert!(matches!(
        load_scene_file(&scene_path)
            .unwrap()
            .mass_spring
            .unwrap()
            .table,
        TableState::Ready(_)
    ));
    std::fs::write(
        &scene_path,
        hemi.replace("home_spring_n_per_m = 60.0", "home_spring_n_per_m = 61.0"),
    )
    .unwrap();
    let err = refused("stale");
    assert!(err.contains("stale"), "{err}");
    // The probe radius is part of what the table was computed for.
    std::fs::write(
        &scene_path,
        hemi.replace("radius_m = 0.004", "radius_m = 0.005"),
    )
    .unwrap();
    refused("probe radius");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn client_point_loads_push_the_surface() {
    // `hapticctl force` / `ApplyForce`: a force at the apex of the hemisphere, spread as the
    // probe would spread it, over the coarse nodes there.
    let scene = load_builtin("hemisphere-springs").unwrap();
    let mut body = build_body(&scene).unwrap();
    let apex = scene.mass_spring.as_ref().unwrap().surface.rest()[0];
    body.add_point_load(apex, haptic_model::DVec3::new(0.0, 0.0, -0.2), 0.5)
        .expect("point load");
    assert_eq!(body.stats().active_point_loads, 1);
    let idle = haptic_model::body::TickInput::default();
    for _ in 0..400 {
        body.tick(&idle).unwrap();
    }
    let n = body.surface_topology().vertex_count;
    let mut x = vec![0f32; 3 * n];
    let mut rest = vec![0f32; 3 * n];
    let moved = body.write_surface_positions(&mut x);
    body.write_surface_rest_positions(&mut rest);
    // The apex (vertex 0) moved down, by less than F / K_h for one home spring (3.3 mm): the
    // load is spread over the probe's patch, about 19 nodes on the 4 mm mesh since session 13
    // (the apex's weight about 0.19: measured 0.93 mm; on the 8 mm mesh one to three nodes
    // and more than 1 mm, the bound until then).
    let dz = f64::from(x[2] - rest[2]);
    assert!(dz < -0.5e-3 && dz > -4e-3, "apex moved {dz} m");
    assert!((moved - dz.abs()).abs() < 1e-3);
    assert!(
        body.add_point_load(apex, haptic_model::DVec3::new(f64::NAN, 0.0, 0.0), 1.0)
            .is_err()
    );
}
