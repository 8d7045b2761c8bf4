//! Quadratic (10-node) tetrahedra: consistency of forces, energy and tangent (finite
//! differences), the linear and quadratic patch tests against the exact solutions, and the HRZ
//! lumped masses.

use crate::common;

use common::Rng;
use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::element::tangent::cell_tangent_blocks;
use haptic_model::material::{MaterialModel, MaterialParams};
use haptic_model::mesh::generate::box_mesh;
use haptic_model::statics::{StaticParams, solve_static};

const MODELS: [MaterialModel; 3] = [
    MaterialModel::StVenantKirchhoff,
    MaterialModel::Corotational,
    MaterialModel::StableNeoHookean,
];

fn cube_fem(model: MaterialModel, cells: usize) -> FemModel {
    let mesh = box_mesh(DVec3::splat(0.01), [cells; 3]).to_quadratic();
    let mut mat = MaterialParams::from_youngs(1e4, 0.3, 1000.0);
    mat.model = model;
    FemModel::new(&mesh, mat).unwrap()
}

/// A smooth large deformation of the rest positions plus noise.
fn deformed(fem: &FemModel, rng: &mut Rng, noise_m: f64) -> Vec<DVec3> {
    fem.rest()
        .iter()
        .map(|p| {
            DVec3::new(
                p.x + 0.2 * p.y + 30.0 * p.z * p.z,
                0.9 * p.y - 0.1 * p.x,
                1.1 * p.z + 20.0 * p.x * p.y,
            ) + rng.vec() * noise_m
        })
        .collect()
}

#[test]
fn forces_are_minus_the_energy_gradient() {
    let mut rng = Rng(7);
    for model in MODELS {
        let fem = cube_fem(model, 1);
        let x = deformed(&fem, &mut rng, 3e-4);
        let mut f = vec![DVec3::ZERO; fem.node_count()];
        fem.add_internal_forces(&x, None, &mut f);
        let h = 1e-7;
        let mut worst = 0.0f64;
        let scale = f.iter().map(|v| v.length()).fold(0.0, f64::max);
        for i in 0..fem.node_count() {
            for c in 0..3 {
                let mut xp = x.clone();
                xp[i][c] += h;
                let mut xm = x.clone();
                xm[i][c] -= h;
                let g = (fem.elastic_energy(&xp) - fem.elastic_energy(&xm)) / (2.0 * h);
                worst = worst.max((f[i][c] + g).abs() / scale);
            }
        }
        assert!(worst < 1e-6, "{model:?}: force vs -dW/dx {worst:e}");
    }
}

#[test]
fn stiffness_action_and_element_blocks_match_force_differences() {
    let mut rng = Rng(11);
    for model in MODELS {
        let fem = cube_fem(model, 1);
        let n = fem.node_count();
        let x = deformed(&fem, &mut rng, 3e-4);
        let dx: Vec<DVec3> = (0..n).map(|_| rng.vec() * 1e-3).collect();
        let eps = 1e-6;
        let forces = |y: &[DVec3]| {
            let mut f = vec![DVec3::ZERO; n];
            fem.add_internal_forces(y, None, &mut f);
            f
        };
        let xp: Vec<DVec3> = x.iter().zip(&dx).map(|(a, d)| *a + *d * eps).collect();
        let xm: Vec<DVec3> = x.iter().zip(&dx).map(|(a, d)| *a - *d * eps).collect();
        let (fp, fm) = (forces(&xp), forces(&xm));
        let fd: Vec<DVec3> = fp
            .iter()
            .zip(&fm)
            .map(|(a, b)| -(*a - *b) / (2.0 * eps))
            .collect();
        let mut k_dx = vec![DVec3::ZERO; n];
        fem.stiffness_action(&x, &dx, &mut k_dx);
        // The same product from the assembled element blocks.
        let mut k_blocks = vec![DVec3::ZERO; n];
        let mut blocks = Vec::new();
        for e in 0..fem.cell_count() {
            cell_tangent_blocks(&fem, e, &x, &mut blocks);
            let nodes = fem.cell_nodes(e);
            let npe = nodes.len();
            assert_eq!(npe, 10);
            for a in 0..npe {
                for b in 0..npe {
                    k_blocks[nodes[a] as usize] += blocks[a * npe + b] * dx[nodes[b] as usize];
                }
            }
        }
        let scale = fd.iter().map(|v| v.length()).fold(0.0, f64::max);
        let err_action = fd
            .iter()
            .zip(&k_dx)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max)
            / scale;
        let err_blocks = k_dx
            .iter()
            .zip(&k_blocks)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max)
            / scale;
        assert!(err_action < 1e-6, "{model:?}: K dx vs FD {err_action:e}");
        assert!(
            err_blocks < 1e-12,
            "{model:?}: blocks vs action {err_blocks:e}"
        );
    }
}

/// Boundary nodes of the cube `[0, s]^3` (for prescribing the exact solution there).
fn boundary_nodes(fem: &FemModel, s: f64) -> Vec<u32> {
    let tol = 1e-12;
    (0..fem.node_count() as u32)
        .filter(|&i| {
            let p = fem.rest()[i as usize];
            p.to_array().iter().any(|&c| c < tol || c > s - tol)
        })
        .collect()
}

/// Linear patch test, small and 1000 times larger: a homogeneous deformation prescribed on the
/// boundary is reproduced exactly inside by the static solution (StVK).
#[test]
fn homogeneous_deformation_is_reproduced_exactly() {
    for scale in [1e-3, 1.0] {
        let mut fem = cube_fem(MaterialModel::StVenantKirchhoff, 2);
        let s = 0.01;
        let exact = |p: DVec3| {
            p + DVec3::new(
                2.0 * p.x + p.y + p.z,
                p.x + 2.0 * p.y + p.z,
                p.x + p.y + 2.0 * p.z,
            ) * (0.5 * scale)
        };
        let bnd = boundary_nodes(&fem, s);
        fem.clamp_nodes(&bnd);
        let mut x = fem.rest().to_vec();
        for &i in &bnd {
            x[i as usize] = exact(fem.rest()[i as usize]);
        }
        let f_ext = vec![DVec3::ZERO; fem.node_count()];
        let params = StaticParams {
            rel_tol: 0.0,
            abs_tol_n: 1e-12,
            ..StaticParams::default()
        };
        solve_static(&fem, &f_ext, &mut x, &params).unwrap();
        let worst = (0..fem.node_count())
            .map(|i| (x[i] - exact(fem.rest()[i])).length())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-10 * s * scale.max(1e-3) * 1e3,
            "scale {scale}: {worst:e} m"
        );
    }
}

/// Quadratic patch test: linear elasticity's pure-bending field (`sigma_xx = E kappa z`, other
/// stresses zero) is quadratic, so quadratic elements must hold it exactly: the rest stiffness
/// applied to it leaves no residual at the interior nodes (linear tetrahedra leave one: they
/// cannot bend).
#[test]
fn pure_bending_field_is_in_equilibrium() {
    let fem = cube_fem(MaterialModel::StVenantKirchhoff, 2);
    let nu = fem.material().poisson_ratio();
    let kappa = 1.0;
    let u: Vec<DVec3> = fem
        .rest()
        .iter()
        .map(|p| {
            DVec3::new(
                kappa * p.x * p.z,
                -nu * kappa * p.y * p.z,
                -0.5 * kappa * (p.x * p.x + nu * (p.z * p.z - p.y * p.y)),
            )
        })
        .collect();
    let mut r = vec![DVec3::ZERO; fem.node_count()];
    fem.stiffness_action(fem.rest(), &u, &mut r);
    let bnd = boundary_nodes(&fem, 0.01);
    let scale = r.iter().map(|v| v.length()).fold(0.0, f64::max);
    let interior = (0..fem.node_count() as u32)
        .filter(|i| !bnd.contains(i))
        .map(|i| r[i as usize].length())
        .fold(0.0, f64::max);
    assert!(scale > 0.0);
    assert!(
        interior < 1e-12 * scale,
        "interior residual {interior:e} of {scale:e}"
    );
}

#[test]
fn hrz_lumped_masses_sum_to_the_body_mass() {
    let fem = cube_fem(MaterialModel::StVenantKirchhoff, 2);
    let total: f64 = fem.lumped_mass_kg().iter().sum();
    assert!((total - 1000.0 * 1e-6).abs() < 1e-15, "{total}");
    assert!(fem.lumped_mass_kg().iter().all(|&m| m > 0.0));
    assert!((fem.total_volume_m3() - 1e-6).abs() < 1e-18);
    assert!((fem.deformed_volume_m3(fem.rest()) - 1e-6).abs() < 1e-18);
}

/// The vectorised force kernels (StVK and stable Neo-Hookean, elastic + viscous, linear and
/// quadratic elements; the corotational material has none) against the integration-point
/// formula `f_a -= w (P(F) + F S_v(F, Fdot)) grad N_a` of the scalar material functions, on a
/// large non-affine deformation with random velocities.
#[test]
fn vectorised_kernels_match_the_integration_point_formula() {
    use haptic_model::material::{first_piola, viscous_stress};
    let mut rng = Rng(5);
    for model in [
        MaterialModel::StVenantKirchhoff,
        MaterialModel::StableNeoHookean,
    ] {
        for quadratic in [false, true] {
            let mesh = box_mesh(DVec3::splat(0.01), [2, 2, 3]);
            let mesh = if quadratic { mesh.to_quadratic() } else { mesh };
            let mut mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
            mat.model = model;
            mat.phi_pa_s = 0.3;
            mat.psi_pa_s = 0.2;
            let fem = FemModel::new(&mesh, mat).unwrap();
            let x = deformed(&fem, &mut rng, 3e-4);
            let v: Vec<DVec3> = (0..fem.node_count()).map(|_| rng.vec() * 0.1).collect();
            for velocities in [None, Some(v.as_slice())] {
                let mut f = vec![DVec3::ZERO; fem.node_count()];
                fem.add_internal_forces(&x, velocities, &mut f);
                let mut expected = vec![DVec3::ZERO; fem.node_count()];
                for q in 0..fem.integration_point_count() {
                    let fm = fem.ip_field_gradient(q, &x);
                    let mut p = first_piola(&mat, &fm);
                    if let Some(v) = velocities {
                        let fd = fem.ip_field_gradient(q, v);
                        p += fm * viscous_stress(&fm, &fd, mat.phi_pa_s, mat.psi_pa_s);
                    }
                    fem.ip_scatter(q, &(p * -fem.ip_weight_m3(q)), &mut expected);
                }
                let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
                let err = f
                    .iter()
                    .zip(&expected)
                    .map(|(a, b)| (*a - *b).length())
                    .fold(0.0, f64::max);
                assert!(
                    scale > 0.0 && err < 1e-12 * scale,
                    "{model:?} quadratic={quadratic} viscous={}: {err:e} of {scale:e}",
                    velocities.is_some()
                );
            }
        }
    }
}

/// The vectorised backward Euler operator of quadratic StVK elements against the
/// integration-point formula `w (h2 dF S + F S_stvk(sym(F^T dF); lambda', mu')) grad N_a`.
#[test]
fn vectorised_operator_matches_the_integration_point_formula() {
    use haptic_model::material::{green_strain, stvk_stress};
    let mut rng = Rng(9);
    let mesh = box_mesh(DVec3::splat(0.01), [2, 3, 2]).to_quadratic();
    let mat = MaterialParams::from_youngs(1e4, 0.45, 1000.0);
    let fem = FemModel::new(&mesh, mat).unwrap();
    let x = deformed(&fem, &mut rng, 3e-4);
    let p: Vec<DVec3> = (0..fem.node_count()).map(|_| rng.vec()).collect();
    let nq = fem.integration_point_count();
    let ip_f: Vec<_> = (0..nq).map(|q| fem.ip_field_gradient(q, &x)).collect();
    let ip_s: Vec<_> = ip_f
        .iter()
        .map(|f| stvk_stress(&green_strain(f), mat.lambda_pa, mat.mu_pa))
        .collect();
    let c = (1e-6, 3.0e3, 2.0e3);
    let mut out = vec![DVec3::ZERO; fem.node_count()];
    assert!(fem.quadratic_stvk_operator_action(&ip_f, &ip_s, c, &p, &mut out));
    let mut expected = vec![DVec3::ZERO; fem.node_count()];
    for q in 0..nq {
        let (f, s) = (ip_f[q], ip_s[q]);
        let df = fem.ip_field_gradient(q, &p);
        let a = f.transpose() * df;
        let de = (a + a.transpose()) * 0.5;
        let dp = df * (s * c.0) + f * stvk_stress(&de, c.1, c.2);
        fem.ip_scatter(q, &(dp * fem.ip_weight_m3(q)), &mut expected);
    }
    let scale = expected.iter().map(|a| a.length()).fold(0.0, f64::max);
    let err = out
        .iter()
        .zip(&expected)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f64::max);
    assert!(scale > 0.0 && err < 1e-12 * scale, "{err:e} of {scale:e}");
}
