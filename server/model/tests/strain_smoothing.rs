//! Edge-based strain smoothing (ES-FEM-T4, [`StrainSmoothing::Edge`]): the smoothing domains
//! partition the body, their smoothed gradients reproduce affine fields exactly, mass, volume and
//! inversion count are those of the tetrahedra, and scenes select it with
//! `[mesh] strain_smoothing`. Accuracy is tested against analytic solutions elsewhere (the
//! MacNeal-Harder patch test, finite-difference checks of forces and stiffness, the
//! Bisshopp-Drucker cantilever, the time-step sweep of the stability suite).

use std::collections::HashSet;
use std::path::Path;

use glam::DMat3;
use haptic_model::element::{FemModel, StrainSmoothing};
use haptic_model::fem::FemBody;
use haptic_model::material::MaterialParams;
use haptic_model::mesh::TET_EDGES;
use haptic_model::mesh::generate::box_mesh;
use haptic_model::scene::parse_scene_toml;
use haptic_model::{DVec3, ModelError};

fn models() -> (haptic_model::mesh::TetMesh, FemModel, FemModel) {
    let mesh = box_mesh(DVec3::new(0.02, 0.01, 0.01), [4, 2, 3]);
    let mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
    let fem = FemModel::new(&mesh, mat).unwrap();
    let es = FemModel::with_smoothing(&mesh, mat, StrainSmoothing::Edge).unwrap();
    (mesh, fem, es)
}

#[test]
fn edge_domains_partition_the_body_and_reproduce_affine_fields() {
    let (mesh, fem, es) = models();
    // One cell (one integration point) per mesh edge, counted independently.
    let edges: HashSet<(u32, u32)> = mesh
        .tets
        .iter()
        .flat_map(|t| TET_EDGES.map(|[a, b]| (t[a].min(t[b]), t[a].max(t[b]))))
        .collect();
    assert_eq!(es.cell_count(), edges.len());
    assert_eq!(es.integration_point_count(), edges.len());
    // The domain volumes (V_e / 6 from each tetrahedron around the edge) sum to the body.
    let total: f64 = (0..es.integration_point_count())
        .map(|q| es.ip_weight_m3(q))
        .sum();
    assert!((total / fem.total_volume_m3() - 1.0).abs() < 1e-12);
    // An affine map x = A X + b has F = A in every domain, exactly.
    let a = DMat3::from_cols(
        DVec3::new(1.1, 0.2, -0.1),
        DVec3::new(0.05, 0.9, 0.3),
        DVec3::new(-0.2, 0.1, 1.3),
    );
    let x: Vec<DVec3> = mesh
        .nodes
        .iter()
        .map(|p| a * *p + DVec3::new(1.0, -2.0, 0.5))
        .collect();
    for q in 0..es.integration_point_count() {
        let g = es.ip_gradients(q);
        assert!(g.iter().sum::<DVec3>().length() < 1e-9 * g[0].length());
        let d = es.ip_field_gradient(q, &x) - a;
        let err = d
            .to_cols_array()
            .iter()
            .fold(0.0_f64, |m, v| m.max(v.abs()));
        assert!(err < 1e-12, "domain {q}: F - A = {d}");
        // Its nodes are those of the tetrahedra around one edge: at least the 2 + 2 of one tet.
        assert!(es.ip_nodes(q).len() >= 4);
    }
    // Hence no internal force in a homogeneous rigid motion plus its energy is that of A.
    let mut f = vec![DVec3::ZERO; mesh.node_count()];
    es.add_internal_forces(&x, None, &mut f);
    let mut f_fem = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&x, None, &mut f_fem);
    let scale = f_fem.iter().map(|v| v.length()).fold(0.0, f64::max);
    for (i, (a, b)) in f.iter().zip(&f_fem).enumerate() {
        assert!(
            (*a - *b).length() < 1e-10 * scale,
            "node {i}: ES {a} vs FEM {b}"
        );
    }
    assert!((es.elastic_energy(&x) / fem.elastic_energy(&x) - 1.0).abs() < 1e-12);
}

#[test]
fn mass_volume_and_inversion_count_are_those_of_the_tetrahedra() {
    let (mesh, fem, es) = models();
    assert_eq!(es.lumped_mass_kg(), fem.lumped_mass_kg());
    // A non-affine deformation that flips some elements.
    let x: Vec<DVec3> = mesh
        .nodes
        .iter()
        .map(|p| DVec3::new(p.x, p.y, p.z * (1.0 - 8000.0 * p.x * p.y)))
        .collect();
    assert!(fem.inverted_elements(&x) > 0);
    assert_eq!(es.inverted_elements(&x), fem.inverted_elements(&x));
    assert!((es.deformed_volume_m3(&x) - fem.deformed_volume_m3(&x)).abs() < 1e-18);
    // The smoothed model is softer: its rest stiffness has smaller diagonal blocks on average
    // and a lower highest natural frequency (a larger explicit time step).
    let trace = |m: &FemModel| -> f64 {
        m.rest_diagonal_blocks()
            .iter()
            .map(|b| b.x_axis.x + b.y_axis.y + b.z_axis.z)
            .sum()
    };
    assert!(trace(&es) < trace(&fem));
    assert!(es.max_eigenvalue(0.0, 300) < fem.max_eigenvalue(0.0, 300));
}

fn scene(order: u32, smoothing: &str) -> Result<haptic_model::scene::Scene, ModelError> {
    parse_scene_toml(
        &format!(
            r#"
[mesh]
builtin = "box"
size = [0.01, 0.01, 0.01]
cells = [2, 2, 2]
order = {order}
strain_smoothing = "{smoothing}"
[material]
youngs_modulus_pa = 1e4
poisson_ratio = 0.3
density_kg_per_m3 = 1000.0
[boundary]
clamped = ["ZMIN"]
"#
        ),
        Path::new("."),
    )
}

#[test]
fn scenes_select_the_smoothing_and_reject_bad_values() {
    let s = scene(1, "edge").unwrap();
    assert_eq!(s.strain_smoothing, StrainSmoothing::Edge);
    let sim = FemBody::new(&s).unwrap();
    assert_eq!(sim.fem().strain_smoothing(), StrainSmoothing::Edge);
    assert_eq!(
        scene(1, "none").unwrap().strain_smoothing,
        StrainSmoothing::None
    );
    for (order, name, want) in [
        (1, "node", "unknown strain smoothing"),
        (2, "edge", "order = 1"),
    ] {
        match scene(order, name) {
            Err(e @ ModelError::SceneField { .. }) => {
                let msg = e.to_string();
                assert!(
                    msg.contains("mesh.strain_smoothing") && msg.contains(want),
                    "{msg}"
                );
            }
            other => panic!("order {order} smoothing {name}: {other:?}"),
        }
    }
    // The library refuses it on quadratic elements too.
    let quad = box_mesh(DVec3::splat(0.01), [1, 1, 1]).to_quadratic();
    let mat = MaterialParams::from_youngs(1e4, 0.3, 1000.0);
    assert!(FemModel::with_smoothing(&quad, mat, StrainSmoothing::Edge).is_err());
}
