//! Numerical contracts of the FEM core (issue 2, section 9): patch test, rigid-motion
//! invariance, force = -grad(energy) by finite differences, tangent by finite differences of the
//! force, lumped masses, viscous stress of a rigid rotation, critical-step sharpness.

use crate::common;
use common::Rng;

use glam::{DMat3, DQuat};
use haptic_model::DVec3;
use haptic_model::element::{CLAMPED, FemModel};
use haptic_model::integrate::{self, IntegratorKind, explicit};
use haptic_model::material::MaterialParams;
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::box_mesh;
use haptic_model::statics::{StaticParams, solve_static};

fn material() -> MaterialParams {
    MaterialParams::from_youngs(10e3, 0.3, 1000.0)
}

fn cube() -> TetMesh {
    box_mesh(DVec3::splat(0.01), [3, 3, 3])
}

fn boundary_nodes(mesh: &TetMesh) -> Vec<u32> {
    let mut b: Vec<u32> = mesh.boundary_triangles().into_iter().flatten().collect();
    b.sort_unstable();
    b.dedup();
    b
}

#[test]
fn patch_test_reproduces_affine_field_inside() {
    let mesh = cube();
    let boundary = boundary_nodes(&mesh);
    assert!(
        boundary.len() < mesh.node_count(),
        "the patch needs interior nodes"
    );
    let mut fem = FemModel::new(&mesh, material()).unwrap();
    fem.clamp_nodes(&boundary);
    // An affine field with stretch, shear and rotation-like parts (moderate: 2 %).
    let a = DMat3::from_cols(
        DVec3::new(0.02, 0.005, -0.01),
        DVec3::new(0.01, -0.015, 0.004),
        DVec3::new(-0.003, 0.008, 0.012),
    );
    let b = DVec3::new(1e-4, -2e-4, 3e-4);
    let exact: Vec<DVec3> = mesh.nodes.iter().map(|p| *p + a * *p + b).collect();
    let mut x = mesh.nodes.clone();
    for &i in &boundary {
        x[i as usize] = exact[i as usize];
    }
    let f_ext = vec![DVec3::ZERO; mesh.node_count()];
    let report = solve_static(&fem, &f_ext, &mut x, &StaticParams::default()).unwrap();
    assert!(report.iterations >= 1);
    let umax = exact
        .iter()
        .zip(&mesh.nodes)
        .map(|(e, r)| (*e - *r).length())
        .fold(0.0, f64::max);
    let err = x
        .iter()
        .zip(&exact)
        .map(|(x, e)| (*x - *e).length())
        .fold(0.0, f64::max);
    assert!(
        err / umax < 1e-10,
        "patch test relative error {:.3e}",
        err / umax
    );
    // And the internal forces vanish at the interior nodes of the exact field.
    let mut f = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&exact, None, &mut f);
    let scale = fem.material().youngs_modulus_pa() * 0.01 * 0.01 * 0.02;
    for (i, fi) in f.iter().enumerate() {
        if fem.constraints()[i] != CLAMPED {
            assert!(fi.length() < 1e-10 * scale, "node {i}: {fi:?}");
        }
    }
}

#[test]
fn rigid_rotation_and_translation_give_zero_elastic_force() {
    let mesh = cube();
    let fem = FemModel::new(&mesh, material()).unwrap();
    let q = DQuat::from_axis_angle(DVec3::new(1.0, -2.0, 0.5).normalize(), 1.1);
    let t = DVec3::new(0.3, -0.1, 0.02);
    let x: Vec<DVec3> = mesh.nodes.iter().map(|p| q * *p + t).collect();
    let mut f = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&x, None, &mut f);
    // Compare with the force of a 1 % stretch, which is O(E h^2 0.01).
    let stretched: Vec<DVec3> = mesh.nodes.iter().map(|p| *p * 1.01).collect();
    let mut f_ref = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&stretched, None, &mut f_ref);
    let fmax = f.iter().map(|v| v.length()).fold(0.0, f64::max);
    let fref = f_ref.iter().map(|v| v.length()).fold(0.0, f64::max);
    assert!(fref > 0.0);
    assert!(
        fmax < 1e-12 * fref * 100.0,
        "rigid motion force {fmax:.3e} vs stretch force {fref:.3e}"
    );
    assert!(fem.elastic_energy(&x).abs() < 1e-15 * fem.elastic_energy(&stretched) * 1e3);
}

#[test]
fn rigid_rotation_velocity_gives_zero_viscous_force() {
    let mesh = cube();
    let mut mat = material();
    mat.phi_pa_s = 3.0;
    mat.psi_pa_s = 2.0;
    let fem = FemModel::new(&mesh, mat).unwrap();
    let omega = DVec3::new(0.3, -1.0, 2.0);
    let v: Vec<DVec3> = mesh.nodes.iter().map(|p| omega.cross(*p)).collect();
    let mut f = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&mesh.nodes, Some(&v), &mut f);
    let fmax = f.iter().map(|v| v.length()).fold(0.0, f64::max);
    // A stretching velocity field of the same magnitude produces a clearly non-zero force.
    let v2: Vec<DVec3> = mesh.nodes.iter().map(|p| *p * omega.length()).collect();
    let mut f2 = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&mesh.nodes, Some(&v2), &mut f2);
    let f2max = f2.iter().map(|v| v.length()).fold(0.0, f64::max);
    assert!(f2max > 0.0);
    assert!(
        fmax < 1e-12 * f2max,
        "viscous force of a rigid rotation {fmax:.3e} vs {f2max:.3e}"
    );
}

#[test]
fn internal_force_is_minus_energy_gradient() {
    let mesh = cube();
    let fem = FemModel::new(&mesh, material()).unwrap();
    let mut rng = Rng(7);
    // A large, non-affine deformation: 15 % of the cell size random plus a shear.
    let h = 0.01 / 3.0;
    let x: Vec<DVec3> = mesh
        .nodes
        .iter()
        .map(|p| *p + DVec3::new(0.2 * p.y, 0.0, -0.1 * p.x) + rng.vec() * (0.15 * h))
        .collect();
    let mut f = vec![DVec3::ZERO; mesh.node_count()];
    fem.add_internal_forces(&x, None, &mut f);
    let eps = 1e-7 * h;
    let fscale = f.iter().map(|v| v.length()).fold(0.0, f64::max);
    let mut worst: f64 = 0.0;
    let mut xp = x.clone();
    for i in (0..mesh.node_count()).step_by(3) {
        for c in 0..3 {
            xp[i][c] = x[i][c] + eps;
            let ep = fem.elastic_energy(&xp);
            xp[i][c] = x[i][c] - eps;
            let em = fem.elastic_energy(&xp);
            xp[i][c] = x[i][c];
            let fd = -(ep - em) / (2.0 * eps);
            worst = worst.max((fd - f[i][c]).abs() / fscale);
        }
    }
    assert!(worst < 1e-6, "force vs -dW/dx relative error {worst:.3e}");
}

#[test]
fn tangent_stiffness_matches_force_differences() {
    let mesh = cube();
    let fem = FemModel::new(&mesh, material()).unwrap();
    let mut rng = Rng(11);
    let h = 0.01 / 3.0;
    let x: Vec<DVec3> = mesh
        .nodes
        .iter()
        .map(|p| *p * 1.05 + rng.vec() * (0.1 * h))
        .collect();
    let dx: Vec<DVec3> = (0..mesh.node_count()).map(|_| rng.vec() * h).collect();
    let mut kdx = vec![DVec3::ZERO; mesh.node_count()];
    fem.stiffness_action(&x, &dx, &mut kdx);
    let eps = 1e-6;
    let shifted = |s: f64| -> Vec<DVec3> {
        let xs: Vec<DVec3> = x.iter().zip(&dx).map(|(a, d)| *a + *d * s).collect();
        let mut f = vec![DVec3::ZERO; mesh.node_count()];
        fem.add_internal_forces(&xs, None, &mut f);
        f
    };
    let (fp, fm) = (shifted(eps), shifted(-eps));
    let scale = kdx.iter().map(|v| v.length()).fold(0.0, f64::max);
    let worst = (0..mesh.node_count())
        .map(|i| ((fm[i] - fp[i]) / (2.0 * eps) - kdx[i]).length())
        .fold(0.0, f64::max);
    assert!(
        worst < 1e-6 * scale,
        "K dx vs -df relative error {:.3e}",
        worst / scale
    );
    // The assembled element tangent of the static solver agrees with the matrix-free action.
    let mut kdx2 = vec![DVec3::ZERO; mesh.node_count()];
    for (e, t) in fem.tets().iter().enumerate() {
        let k = haptic_model::element::tangent::element_tangent(&fem, e, &x);
        for a in 0..4 {
            for b in 0..4 {
                kdx2[t[a] as usize] += k[a][b] * dx[t[b] as usize];
            }
        }
    }
    let worst2 = (0..mesh.node_count())
        .map(|i| (kdx2[i] - kdx[i]).length())
        .fold(0.0, f64::max);
    assert!(
        worst2 < 1e-10 * scale,
        "element tangent vs action {:.3e}",
        worst2 / scale
    );
}

#[test]
fn lumped_masses_sum_to_density_times_volume() {
    let mesh = box_mesh(DVec3::new(0.02, 0.01, 0.005), [4, 3, 2]);
    let fem = FemModel::new(&mesh, material()).unwrap();
    let total: f64 = fem.lumped_mass_kg().iter().sum();
    let expected = 1000.0 * 0.02 * 0.01 * 0.005;
    assert!(
        (total - expected).abs() < 1e-12 * expected,
        "{total} vs {expected}"
    );
    assert!((fem.total_volume_m3() - 0.02 * 0.01 * 0.005).abs() < 1e-15);
    assert!(fem.lumped_mass_kg().iter().all(|&m| m > 0.0));
}

/// Runs symplectic Euler with no damping from a random initial velocity for `steps` steps of
/// `dt` and returns the final kinetic-plus-strain energy over the initial one.
fn energy_growth(fem: &FemModel, dt: f64, steps: usize) -> f64 {
    let n = fem.node_count();
    let mut rng = Rng(3);
    let mut x = fem.rest().to_vec();
    let mut v: Vec<DVec3> = (0..n)
        .map(|i| {
            if fem.constraints()[i] == CLAMPED {
                DVec3::ZERO
            } else {
                rng.vec() * 1e-3
            }
        })
        .collect();
    let energy = |x: &[DVec3], v: &[DVec3]| {
        fem.elastic_energy(x)
            + v.iter()
                .zip(fem.lumped_mass_kg())
                .map(|(v, m)| 0.5 * m * v.length_squared())
                .sum::<f64>()
    };
    let e0 = energy(&x, &v);
    let mut f = vec![DVec3::ZERO; n];
    for _ in 0..steps {
        f.iter_mut().for_each(|a| *a = DVec3::ZERO);
        fem.add_internal_forces(&x, None, &mut f);
        let vmax2 = explicit::integrate_nodes(
            IntegratorKind::SymplecticEuler,
            fem,
            &[],
            dt,
            &f,
            &mut x,
            &mut v,
        );
        if vmax2.is_nan() || vmax2 >= 1e6 {
            return f64::INFINITY;
        }
    }
    energy(&x, &v) / e0
}

#[test]
fn computed_critical_step_separates_stable_from_unstable() {
    let mesh = box_mesh(DVec3::new(0.01, 0.01, 0.01), [3, 3, 3]);
    let mut fem = FemModel::new(&mesh, material()).unwrap();
    let zmin: Vec<u32> = mesh
        .surface("ZMIN")
        .unwrap()
        .triangles
        .iter()
        .flatten()
        .copied()
        .collect();
    fem.clamp_nodes(&zmin);
    let dt = integrate::critical_time_step(&fem, IntegratorKind::SymplecticEuler);
    assert!(dt.is_finite() && dt > 0.0);
    // Sanity against the classic element Courant estimate h_min / c (same order of magnitude).
    let c = fem.material().dilatational_wave_speed_m_per_s();
    let courant = (0.01 / 3.0) / c;
    assert!(
        dt < courant && dt > 0.05 * courant,
        "dt_crit {dt:.3e} vs h/c {courant:.3e}"
    );
    let stable = energy_growth(&fem, 0.9 * dt, 4000);
    let unstable = energy_growth(&fem, 1.1 * dt, 4000);
    assert!(stable < 2.0, "0.9 dt_crit: energy ratio {stable}");
    assert!(unstable > 1e3, "1.1 dt_crit: energy ratio {unstable}");
}
