//! Material models of issue 3 section 1 (StVK, corotational, stable Neo-Hookean) and the
//! finite-difference checks of section 2: stress against energy, stress differential against
//! stress, nodal forces against the energy and the stiffness action against the forces, for
//! every material, at large deformations including a compressed and (for the robust materials)
//! an inverted element; the polar decomposition; the common linearisation at rest; the scene
//! field `material.model`.

use crate::common;
use common::Rng;

use std::path::Path;

use glam::{DMat3, DQuat};
use haptic_model::DVec3;
use haptic_model::ModelError;
use haptic_model::element::{FemModel, StrainSmoothing};
use haptic_model::material::{
    self, MaterialModel, MaterialParams, energy_density, first_piola, first_piola_differential,
    polar_decomposition,
};
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::box_mesh;
use haptic_model::scene::parse_scene_toml;

const MODELS: [MaterialModel; 3] = [
    MaterialModel::StVenantKirchhoff,
    MaterialModel::Corotational,
    MaterialModel::StableNeoHookean,
];

fn params(model: MaterialModel) -> MaterialParams {
    let mut m = MaterialParams::from_youngs(10e3, 0.3, 1000.0);
    m.model = model;
    m
}

fn norm(m: &DMat3) -> f64 {
    (m.x_axis.length_squared() + m.y_axis.length_squared() + m.z_axis.length_squared()).sqrt()
}

fn rotation(axis: DVec3, angle: f64) -> DMat3 {
    DMat3::from_quat(DQuat::from_axis_angle(axis.normalize(), angle))
}

/// Deformation gradients at large deformation: (name, F, inverted).
fn test_gradients() -> Vec<(&'static str, DMat3, bool)> {
    let mut rng = Rng(7);
    let q = rotation(DVec3::new(1.0, 2.0, -0.5), 0.9);
    vec![
        ("general", DMat3::IDENTITY + rng.mat() * 0.4, false),
        (
            "stretched+rotated",
            q * DMat3::from_diagonal(DVec3::new(1.8, 0.9, 1.3)) * rotation(DVec3::Z, 0.4),
            false,
        ),
        (
            "compressed",
            q * DMat3::from_diagonal(DVec3::new(0.35, 0.6, 0.5))
                + DMat3::from_cols(DVec3::new(0.0, 0.05, 0.0), DVec3::ZERO, DVec3::ZERO),
            false,
        ),
        (
            "inverted",
            q * DMat3::from_diagonal(DVec3::new(0.9, 0.7, -0.3)) * rotation(DVec3::X, 0.3),
            true,
        ),
    ]
}

#[test]
fn polar_decomposition_is_a_proper_rotation_times_a_symmetric_matrix() {
    let mut rng = Rng(3);
    let mut cases: Vec<DMat3> = test_gradients().into_iter().map(|c| c.1).collect();
    cases.push(DMat3::IDENTITY);
    cases.push(DMat3::from_diagonal(DVec3::new(1.0, 1.0, 0.0)));
    cases.push(DMat3::from_diagonal(DVec3::new(-1.0, -1.0, -1.0)));
    cases.push(rotation(DVec3::Y, 2.0) * DMat3::from_diagonal(DVec3::new(2.0, 1e-9, 1e-9)));
    for _ in 0..200 {
        cases.push(rng.mat() * 2.0);
    }
    for f in cases {
        let (r, s) = polar_decomposition(&f);
        let ortho = norm(&(r.transpose() * r - DMat3::IDENTITY));
        assert!(ortho < 1e-12, "R^T R - I = {ortho:e} for {f}");
        assert!((r.determinant() - 1.0).abs() < 1e-12, "det R for {f}");
        assert!(
            norm(&(s - s.transpose())) < 1e-12 * (1.0 + norm(&s)),
            "S symmetric"
        );
        assert!(
            norm(&(r * s - f)) < 1e-12 * (1.0 + norm(&f)),
            "R S != F for {f}: {}",
            norm(&(r * s - f))
        );
    }
    // A pure rotation is recovered exactly, also far from the identity.
    let q = rotation(DVec3::new(0.3, -1.0, 0.2), 2.9);
    let (r, s) = polar_decomposition(&q);
    assert!(norm(&(r - q)) < 1e-13 && norm(&(s - DMat3::IDENTITY)) < 1e-13);
}

/// P = dPsi/dF and dP = (dP/dF):dF by central differences, at large deformations.
#[test]
fn stress_is_the_energy_gradient_and_its_differential_is_exact() {
    let mut rng = Rng(11);
    for model in MODELS {
        let mat = params(model);
        for (name, f, inverted) in test_gradients() {
            if inverted && model == MaterialModel::StVenantKirchhoff {
                // StVK is defined there too, but it is not one of the robust materials; still
                // check it: the formulas are polynomial and exact.
            }
            let p = first_piola(&mat, &f);
            let h = 1e-6;
            let mut p_fd = DMat3::ZERO;
            for c in 0..3 {
                for r in 0..3 {
                    let mut d = DMat3::ZERO;
                    d.col_mut(c)[r] = h;
                    let w = (energy_density(&mat, &(f + d)) - energy_density(&mat, &(f - d)))
                        / (2.0 * h);
                    p_fd.col_mut(c)[r] = w;
                }
            }
            let err = norm(&(p - p_fd)) / norm(&p).max(mat.mu_pa * 1e-3);
            assert!(err < 1e-6, "{model:?} {name}: |P - dPsi/dF| rel {err:e}");
            for _ in 0..3 {
                let df = rng.mat();
                let dp = first_piola_differential(&mat, &f, &df);
                let fd = (first_piola(&mat, &(f + df * h)) - first_piola(&mat, &(f - df * h)))
                    * (0.5 / h);
                let err = norm(&(dp - fd)) / norm(&fd).max(mat.mu_pa * 1e-3);
                assert!(err < 1e-6, "{model:?} {name}: |dP - FD| rel {err:e}");
            }
        }
    }
}

/// All three materials linearise at rest to the same linear elasticity
/// `dP = lambda tr(dF) I + mu (dF + dF^T)`, vanish at rest, and are rotation invariant.
#[test]
fn every_material_linearises_to_the_same_linear_elasticity() {
    let mut rng = Rng(5);
    for model in MODELS {
        let mat = params(model);
        assert!(norm(&first_piola(&mat, &DMat3::IDENTITY)) < 1e-9 * mat.mu_pa);
        assert!(energy_density(&mat, &DMat3::IDENTITY).abs() < 1e-9 * mat.mu_pa);
        for _ in 0..5 {
            let df = rng.mat();
            let tr = df.x_axis.x + df.y_axis.y + df.z_axis.z;
            let lin = DMat3::from_diagonal(DVec3::splat(mat.lambda_pa * tr))
                + (df + df.transpose()) * mat.mu_pa;
            let dp = first_piola_differential(&mat, &DMat3::IDENTITY, &df);
            assert!(
                norm(&(dp - lin)) < 1e-10 * norm(&lin),
                "{model:?}: {dp} vs {lin}"
            );
        }
        // Frame indifference: Psi(Q F) = Psi(F), P(Q F) = Q P(F).
        let q = rotation(DVec3::new(1.0, -1.0, 3.0), 1.3);
        for (name, f, _) in test_gradients() {
            let (w, wq) = (energy_density(&mat, &f), energy_density(&mat, &(q * f)));
            assert!(
                (w - wq).abs() < 1e-10 * w.abs().max(1.0),
                "{model:?} {name}"
            );
            let (p, pq) = (first_piola(&mat, &f), first_piola(&mat, &(q * f)));
            assert!(norm(&(pq - q * p)) < 1e-10 * norm(&p), "{model:?} {name}");
        }
    }
}

/// The robust materials push an inverted element back: the energy decreases along
/// `-P` and, for a flat element, P is finite.
#[test]
fn robust_materials_resist_inversion() {
    for model in [MaterialModel::Corotational, MaterialModel::StableNeoHookean] {
        let mat = params(model);
        let mut cases = vec![
            DMat3::from_diagonal(DVec3::new(1.0, 1.0, -0.5)),
            DMat3::from_diagonal(DVec3::new(1.0, 1.0, 0.0)),
            DMat3::from_diagonal(DVec3::new(0.1, 0.1, 0.0)),
        ];
        if model == MaterialModel::Corotational {
            // F = 0 is a stationary point of the stable Neo-Hookean energy (P = mu F +
            // lambda_s (J - alpha) cof F vanishes there), but not of the corotational one.
            cases.push(DMat3::ZERO);
        }
        for f in cases {
            let p = first_piola(&mat, &f);
            assert!(p.is_finite(), "{model:?}: P({f}) = {p}");
            // The normal stress along the inverted axis is compressive (pushes z back up).
            assert!(p.z_axis.z < 0.0, "{model:?}: P_zz = {} at {f}", p.z_axis.z);
        }
    }
}

fn deformed_mesh(seed: u64, invert_one: bool) -> (TetMesh, Vec<DVec3>) {
    let mesh = box_mesh(DVec3::splat(0.01), [2, 2, 2]);
    let mut rng = Rng(seed);
    // A large rotation, a 40 % stretch and random noise of 10 % of an edge.
    let q = rotation(DVec3::new(0.2, 1.0, 0.4), 0.8);
    let a = q * DMat3::from_diagonal(DVec3::new(1.4, 0.7, 0.9));
    let mut x: Vec<DVec3> = mesh
        .nodes
        .iter()
        .map(|p| a * *p + rng.vec() * 5e-4)
        .collect();
    if invert_one {
        // Push the centre node through a face of one of its tetrahedra.
        let c = mesh
            .nodes
            .iter()
            .position(|p| (*p - DVec3::splat(0.005)).length() < 1e-9)
            .unwrap();
        x[c] += a * DVec3::new(0.008, 0.0, 0.0);
    }
    (mesh, x)
}

fn count_inverted(fem: &FemModel, x: &[DVec3]) -> usize {
    (0..fem.tets().len())
        .filter(|&e| fem.deformation_gradient(e, x).determinant() < 0.0)
        .count()
}

/// Nodal forces are minus the gradient of the elastic energy, and the stiffness action is
/// minus the derivative of the forces, for every material on a large, non-homogeneous
/// deformation (and one with inverted elements for the robust materials).
#[test]
fn forces_and_stiffness_action_match_finite_differences_for_every_material() {
    for (model, smoothing) in MODELS
        .into_iter()
        .flat_map(|m| [(m, StrainSmoothing::None), (m, StrainSmoothing::Edge)])
    {
        for invert in [false, true] {
            if invert && model == MaterialModel::StVenantKirchhoff {
                continue;
            }
            let (mesh, x) = deformed_mesh(21, invert);
            let fem = FemModel::with_smoothing(&mesh, params(model), smoothing).unwrap();
            if invert {
                assert!(
                    count_inverted(&fem, &x) > 0,
                    "the test needs an inverted tet"
                );
            }
            let n = mesh.node_count();
            let mut f = vec![DVec3::ZERO; n];
            fem.add_internal_forces(&x, None, &mut f);
            let fscale = f.iter().map(|v| v.length()).fold(0.0, f64::max);
            let h = 1e-8;
            let mut worst: f64 = 0.0;
            for i in (0..n).step_by(3) {
                for c in 0..3 {
                    let mut xp = x.clone();
                    let mut xm = x.clone();
                    xp[i][c] += h;
                    xm[i][c] -= h;
                    let g = (fem.elastic_energy(&xp) - fem.elastic_energy(&xm)) / (2.0 * h);
                    worst = worst.max((f[i][c] + g).abs() / fscale);
                }
            }
            assert!(
                worst < 1e-6,
                "{model:?} {smoothing:?} inverted={invert}: force vs energy {worst:e}"
            );
            // Stiffness action against a central difference of the forces.
            let mut rng = Rng(99);
            let dx: Vec<DVec3> = (0..n).map(|_| rng.vec() * 1e-3).collect();
            let mut k_dx = vec![DVec3::ZERO; n];
            fem.stiffness_action(&x, &dx, &mut k_dx);
            let eps = 1e-5;
            let shifted = |s: f64| {
                let xs: Vec<DVec3> = x.iter().zip(&dx).map(|(a, d)| *a + *d * s).collect();
                let mut fs = vec![DVec3::ZERO; n];
                fem.add_internal_forces(&xs, None, &mut fs);
                fs
            };
            let (fp, fm) = (shifted(eps), shifted(-eps));
            let kscale = k_dx.iter().map(|v| v.length()).fold(0.0, f64::max);
            let err = (0..n)
                .map(|i| (k_dx[i] + (fp[i] - fm[i]) / (2.0 * eps)).length())
                .fold(0.0, f64::max)
                / kscale;
            assert!(
                err < 1e-6,
                "{model:?} {smoothing:?} inverted={invert}: K dx vs FD {err:e}"
            );
            // And the assembled cell tangents of the static solver agree with the action (and
            // for plain elements the 4x4 element tangent too).
            let mut k_cells = vec![DVec3::ZERO; n];
            let mut blocks = Vec::new();
            for c in 0..fem.cell_count() {
                haptic_model::element::tangent::cell_tangent_blocks(&fem, c, &x, &mut blocks);
                let t = fem.cell_nodes(c);
                for a in 0..t.len() {
                    for b in 0..t.len() {
                        k_cells[t[a] as usize] += blocks[a * t.len() + b] * dx[t[b] as usize];
                    }
                }
            }
            let err = (0..n)
                .map(|i| (k_cells[i] - k_dx[i]).length())
                .fold(0.0, f64::max)
                / kscale;
            assert!(
                err < 1e-10,
                "{model:?} {smoothing:?}: cell tangents vs action {err:e}"
            );
            if smoothing == StrainSmoothing::None {
                let mut k_el = vec![DVec3::ZERO; n];
                for (e, t) in fem.tets().iter().enumerate() {
                    let k = haptic_model::element::tangent::element_tangent(&fem, e, &x);
                    for a in 0..4 {
                        for b in 0..4 {
                            k_el[t[a] as usize] += k[a][b] * dx[t[b] as usize];
                        }
                    }
                }
                let err = (0..n)
                    .map(|i| (k_el[i] - k_dx[i]).length())
                    .fold(0.0, f64::max)
                    / kscale;
                assert!(err < 1e-10, "{model:?}: element_tangent vs action {err:e}");
            }
        }
    }
}

/// The viscous stress is added as `P_v = F S_v` for every material: a rigid rotation rate
/// gives no viscous force, a stretching rate does.
#[test]
fn viscous_stress_applies_to_every_material() {
    for (model, smoothing) in MODELS
        .into_iter()
        .flat_map(|m| [(m, StrainSmoothing::None), (m, StrainSmoothing::Edge)])
    {
        let mut mat = params(model);
        mat.phi_pa_s = 0.5;
        mat.psi_pa_s = 0.5;
        let mesh = box_mesh(DVec3::splat(0.01), [2, 1, 1]);
        let fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
        let n = mesh.node_count();
        let x = mesh.nodes.clone();
        let w = DVec3::new(0.3, -1.0, 2.0);
        let v_rot: Vec<DVec3> = x.iter().map(|p| w.cross(*p)).collect();
        let mut f = vec![DVec3::ZERO; n];
        fem.add_internal_forces(&x, Some(&v_rot), &mut f);
        assert!(
            f.iter().all(|v| v.length() < 1e-12),
            "{model:?} {smoothing:?}: {f:?}"
        );
        let v_str: Vec<DVec3> = x.iter().map(|p| DVec3::new(p.x, 0.0, 0.0)).collect();
        fem.add_internal_forces(&x, Some(&v_str), &mut f);
        assert!(f.iter().any(|v| v.length() > 1e-8), "{model:?}");
        assert!(material::energy_density(&mat, &DMat3::IDENTITY).abs() < 1e-9);
    }
}

const SCENE: &str = r#"
[mesh]
builtin = "box"
size = [10.0, 10.0, 20.0]
cells = [2, 2, 4]
length_unit = "mm"

[material]
MODEL
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
density_kg_per_m3 = 1060.0

[boundary]
clamped = ["ZMIN"]
"#;

#[test]
fn scene_parses_material_model() {
    let parse = |line: &str| parse_scene_toml(&SCENE.replace("MODEL", line), Path::new("."));
    assert_eq!(
        parse("").unwrap().material.model,
        MaterialModel::StVenantKirchhoff
    );
    for m in MODELS {
        let s = parse(&format!("model = \"{}\"", m.scene_name())).unwrap();
        assert_eq!(s.material.model, m);
    }
    match parse("model = \"mooney-rivlin\"") {
        Err(ModelError::SceneField { field, message }) => {
            assert_eq!(field, "material.model");
            assert!(message.contains("mooney-rivlin"), "{message}");
        }
        other => panic!("expected a material.model error, got {other:?}"),
    }
}
