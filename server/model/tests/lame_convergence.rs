//! Lamé thick sphere convergence (issue 3 section 2): inner radius a = 7 mm, outer b = 10 mm,
//! E = 10 kPa, nu = 0.3, internal pressure p; relative L2 nodal error of the radial
//! displacement over all nodes against `u_r(r) = p a^3 / (E (b^3 - a^3)) [(1 - 2 nu) r +
//! (1 + nu) b^3 / (2 r^2)]` on three meshes, observed order >= 1.8 between the two finest,
//! with `h ~ tets^(-1/3)`.
//!
//! The analytic solution is linear elasticity; StVK differs from it at the order of the strain
//! (1 % at p = 0.1 kPa), which would hide the discretisation error of the finest meshes. The
//! error is relative and the linear part scales with p, so we load with p = 0.1 Pa (strain 1e-5)
//! and compare relative errors. The meshed surfaces are polyhedral with nodes on the spheres;
//! the pressure is applied on the flat faces (consistent nodal loads), and the solution is
//! compared at the node positions.

use crate::common;
use common::lame_u_r;

use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::loads::add_pressure_forces;
use haptic_model::material::MaterialParams;
use haptic_model::mesh::generate::sphere_shell;
use haptic_model::statics::{StaticParams, solve_static};

/// (tets, relative L2 error of u_r over all nodes).
fn solve(target_tets: usize) -> (usize, f64) {
    let (a, b, e, nu, p) = (7e-3, 10e-3, 10e3, 0.3, 0.1);
    let mesh = sphere_shell(a, b, target_tets);
    let mut fem = FemModel::new(&mesh, MaterialParams::from_youngs(e, nu, 1000.0)).unwrap();
    let node = |name: &str| mesh.node_group(name).unwrap().nodes[0] as usize;
    fem.set_constraint(node("INNER_PZ"), 0b011);
    fem.set_constraint(node("INNER_NZ"), 0b011);
    fem.set_constraint(node("INNER_PX"), 0b110);
    let inner = &mesh.surface("INNER").unwrap().triangles;
    let mut f_ext = vec![DVec3::ZERO; mesh.node_count()];
    add_pressure_forces(inner, &mesh.nodes, p, &mut f_ext);
    let mut x = mesh.nodes.clone();
    solve_static(&fem, &f_ext, &mut x, &StaticParams::default()).unwrap();
    let (mut num, mut den) = (0.0, 0.0);
    for (x, x0) in x.iter().zip(&mesh.nodes) {
        let r = x0.length();
        let exact = lame_u_r(r, a, b, e, nu, p);
        let u_r = (*x - *x0).dot(*x0 / r);
        num += (u_r - exact).powi(2);
        den += exact * exact;
    }
    (mesh.tet_count(), (num / den).sqrt())
}

#[test]
fn radial_displacement_converges_at_second_order() {
    let results: Vec<(usize, f64)> = [1500, 5000, 16000].into_iter().map(solve).collect();
    let h = |t: usize| (t as f64).powf(-1.0 / 3.0);
    for (i, (t, e)) in results.iter().enumerate() {
        let order = if i > 0 {
            let (t0, e0) = results[i - 1];
            format!("{:.2}", (e0 / e).ln() / (h(t0) / h(*t)).ln())
        } else {
            "-".into()
        };
        println!("tets {t:>6}: relative L2 error of u_r {e:.3e}, order {order}");
    }
    let (t1, e1) = results[results.len() - 2];
    let (t2, e2) = results[results.len() - 1];
    let order = (e1 / e2).ln() / (h(t1) / h(t2)).ln();
    assert!(e2 < e1 && order >= 1.8, "order {order:.2} ({results:?})");
}
