//! `lame`: thick sphere a = 7 mm, b = 10 mm, E = 10 kPa, nu = 0.3, p = 0.1 kPa on the inner
//! surface (dead load from `loads::add_pressure_load`, consistent on quadratic faces), rollers on three inner axis nodes;
//! dynamic run to steady state (load ramped in over 20 ms, at most 3 s simulated, mass damping
//! 300 /s) with each integrator, and the static Newton solve as the method `static`; error of
//! the final displacement field against the analytic Lamé solution.

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::loads::add_pressure_load;
use haptic_model::material::{MaterialModel, MaterialParams};
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::{sphere_shell, sphere_shell_quadratic};
use haptic_model::statics::{StaticParams, solve_static};

use crate::common::{MATERIALS, run_loaded_with};
use crate::method::{material_label, methods, steady_text};
use crate::report::{Row, Scenario};

/// Inner radius a, outer radius b (m), Young's modulus (Pa), Poisson ratio, inner pressure (Pa).
const LAME: (f64, f64, f64, f64, f64) = (7e-3, 10e-3, 10e3, 0.3, 100.0);

/// The analytic radial displacement at radius `r`, m.
fn lame_u_r(r: f64) -> f64 {
    let (a, b, e, nu, p) = LAME;
    p * a.powi(3) / (e * (b.powi(3) - a.powi(3)))
        * ((1.0 - 2.0 * nu) * r + (1.0 + nu) * b.powi(3) / (2.0 * r * r))
}

/// Relative L2 and max nodal error of positions `x` against the analytic field, and the mean
/// inner radial displacement.
fn lame_errors(mesh: &TetMesh, x: &[DVec3]) -> (f64, f64, f64) {
    let (mut num2, mut den2, mut max_e) = (0.0, 0.0, 0.0f64);
    for (p, q) in mesh.nodes.iter().zip(x) {
        let exact = p.normalize() * lame_u_r(p.length());
        let e = (*q - *p - exact).length();
        num2 += e * e;
        den2 += exact.length_squared();
        max_e = max_e.max(e);
    }
    let inner: Vec<u32> = {
        let mut v: Vec<u32> = mesh
            .surface("INNER")
            .expect("INNER")
            .triangles
            .iter()
            .flatten()
            .copied()
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    };
    let mean_ur = inner
        .iter()
        .map(|&i| (x[i as usize] - mesh.nodes[i as usize]).dot(mesh.nodes[i as usize].normalize()))
        .sum::<f64>()
        / inner.len() as f64;
    ((num2 / den2).sqrt(), max_e, mean_ur)
}

/// Runs the scenario: the static solve and every dynamic method per mesh and material.
pub fn run(quick: bool, rows: &mut Vec<Row>) {
    let (a, b, e, nu, p) = LAME;
    // (target tets, quadratic elements)
    let targets: &[(usize, bool)] = if quick {
        &[(1000, false), (3000, false), (1000, true)]
    } else {
        &[
            (1000, false),
            (2000, false),
            (5000, false),
            (10000, false),
            (1000, true),
            (2000, true),
        ]
    };
    let safeties: &[f64] = if quick { &[0.5] } else { &[0.5, 0.25] };
    let all_methods = methods(safeties);
    let exact_inner = lame_u_r(a);
    let reference = format!("analytic u_r(a) = {:.4} mm", exact_inner * 1e3);
    for &(target, quadratic) in targets {
        let mesh = if quadratic {
            sphere_shell_quadratic(a, b, target)
        } else {
            sphere_shell(a, b, target)
        };
        for &model in MATERIALS {
            let mut mat = MaterialParams::from_youngs(e, nu, 1000.0);
            mat.mass_damping_per_s = 300.0;
            mat.model = model;
            let mut fem = FemModel::new(&mesh, mat).expect("sphere FEM");
            let node = |name: &str| mesh.node_group(name).expect("node group").nodes[0] as usize;
            fem.set_constraint(node("INNER_PZ"), 0b011);
            fem.set_constraint(node("INNER_NZ"), 0b011);
            fem.set_constraint(node("INNER_PX"), 0b110);
            let mut f_ext = vec![DVec3::ZERO; mesh.node_count()];
            // Consistent loads on the curved faces of quadratic elements.
            add_pressure_load(
                &mesh.surface("INNER").expect("INNER").triangles,
                quadratic,
                &mesh.nodes,
                p,
                &mut f_ext,
            );
            // Static: the discretisation error alone.
            let (row, x_static) = static_row(model, &mesh, &fem, &f_ext, &reference);
            row.print();
            rows.push(row);
            // The corotational force costs a polar decomposition per element (about 30 times
            // the StVK force): the other materials run dynamically on the two coarse meshes.
            let dynamic =
                model == MaterialModel::StVenantKirchhoff || (target <= 2000 && !quadratic);
            for m in all_methods
                .iter()
                .filter(|m| dynamic && m.material == model)
            {
                let mut row =
                    Row::new(Scenario::Lame, m.label(), m.kind.name(), &mesh).material(model);
                row.reference = reference.clone();
                match run_loaded_with(&fem, &mesh, &m.params(), &f_ext, 0.02, 3.0) {
                    Err(e) => row.settings = format!("refused: {e}"),
                    Ok(run) => {
                        row.settings = format!(
                            "tick 1 ms, {}, alpha 300/s, {}",
                            m.step_text(run.substeps),
                            steady_text(run.time_s, 3.0)
                        );
                        row.set_times(&run.ticks, 1e-3);
                        row.stable = run.stable && run.x.iter().all(|v| v.is_finite());
                        if row.stable {
                            let (l2, max_e, mean) = lame_errors(&mesh, &run.x);
                            row.rel_l2_error = l2;
                            row.max_nodal_error_m = max_e;
                            row.observable_error = (mean - exact_inner).abs() / exact_inner;
                            let settle = rel_diff(&mesh.nodes, &run.x, &x_static);
                            row.observable = format!(
                                "mean u_r(a) = {:.4} mm; vs same-mesh static {:.2e}",
                                mean * 1e3,
                                settle
                            );
                        }
                    }
                }
                row.print();
                rows.push(row);
            }
        }
    }
}

/// The static row of `mesh` under `f_ext` (Newton + sparse Cholesky, timed as a whole) and
/// the static solution.
fn static_row(
    model: MaterialModel,
    mesh: &TetMesh,
    fem: &FemModel,
    f_ext: &[DVec3],
    reference: &str,
) -> (Row, Vec<DVec3>) {
    let exact_inner = lame_u_r(LAME.0);
    let mut x = mesh.nodes.clone();
    let t = Instant::now();
    let rep = solve_static(fem, f_ext, &mut x, &StaticParams::default());
    let solve_us = t.elapsed().as_secs_f64() * 1e6;
    let mut row = Row::new(
        Scenario::Lame,
        material_label("static".into(), model),
        "static",
        mesh,
    )
    .material(model);
    row.settings = "Newton + sparse Cholesky; time = whole solve".into();
    row.set_solve_time(solve_us);
    row.reference = reference.to_string();
    let x_static = x.clone();
    if let Ok(rep) = rep {
        let (l2, max_e, mean) = lame_errors(mesh, &x);
        row.rel_l2_error = l2;
        row.max_nodal_error_m = max_e;
        row.observable_error = (mean - exact_inner).abs() / exact_inner;
        row.observable = format!(
            "mean u_r(a) = {:.4} mm ({} Newton it.)",
            mean * 1e3,
            rep.iterations
        );
        row.stable = true;
    }
    (row, x_static)
}

/// `|x - y| / |y - rest|` over all nodes.
fn rel_diff(rest: &[DVec3], x: &[DVec3], y: &[DVec3]) -> f64 {
    let (mut n, mut d) = (0.0, 0.0);
    for ((r, x), y) in rest.iter().zip(x).zip(y) {
        n += (*x - *y).length_squared();
        d += (*y - *r).length_squared();
    }
    (n / d).sqrt()
}
