//! `cantilever`: beam 100 x 10 x 10 mm (E = 100 kPa, nu = 0.3, rho = 1000 kg/m^3), clamped
//! at x = 0, dead tip load with alpha = P L^2 / (E I) = 1 spread over the tip face by area;
//! observable: tip deflection v / L against Bisshopp-Drucker's 0.30172. Static solve in 10
//! load steps and every dynamic method (mass damping 60 /s, at most 3 s simulated, 1 s with
//! `--quick`).

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::material::{MaterialModel, MaterialParams};
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::box_mesh;
use haptic_model::statics::{StaticParams, solve_static};

use crate::common::{MATERIALS, run_loaded_with};
use crate::method::{Method, material_label, methods, steady_text};
use crate::report::{Row, Scenario};

/// Bisshopp-Drucker's tip deflection v / L at alpha = P L^2 / (E I) = 1.
const BD_ALPHA1: f64 = 0.30172;

/// Runs the scenario: the static solve and every dynamic method per mesh and material.
pub fn run(quick: bool, rows: &mut Vec<Row>) {
    let (len, h, e, nu): (f64, f64, f64, f64) = (0.1, 0.01, 1e5, 0.3);
    let inertia = h.powi(4) / 12.0;
    let load = e * inertia / (len * len); // alpha = 1
    // (cells across, quadratic elements)
    let ns: &[(usize, bool)] = if quick {
        &[(2, false), (1, true)]
    } else {
        &[(2, false), (3, false), (4, false), (1, true), (2, true)]
    };
    let reference = format!("Bisshopp-Drucker v/L = {BD_ALPHA1}");
    let all_methods = methods(&[0.5]);
    for &(n, quadratic) in ns {
        for &model in MATERIALS {
            let mut mesh = box_mesh(DVec3::new(len, h, h), [10 * n, n, n]);
            if quadratic {
                mesh = mesh.to_quadratic();
            }
            let mut mat = MaterialParams::from_youngs(e, nu, 1000.0);
            mat.mass_damping_per_s = 60.0;
            mat.model = model;
            let mut fem = FemModel::new(&mesh, mat).expect("beam FEM");
            let clamped = mesh
                .nodes_of_surfaces(&["XMIN".to_string()], "clamped")
                .expect("XMIN");
            fem.clamp_nodes(&clamped);
            let tip = &mesh.surface("XMAX").expect("XMAX").triangles;
            let area: f64 = tip.iter().map(|t| tri_area(&mesh.nodes, t)).sum();
            let mut f_ext = vec![DVec3::ZERO; mesh.node_count()];
            for t in tip {
                let share = load * tri_area(&mesh.nodes, t) / area / 3.0;
                for &i in t {
                    f_ext[i as usize].z -= share;
                }
            }
            let tip_nodes = mesh
                .nodes_of_surfaces(&["XMAX".to_string()], "tip")
                .expect("XMAX");
            let deflection = |x: &[DVec3]| {
                -tip_nodes
                    .iter()
                    .map(|&i| x[i as usize].z - mesh.nodes[i as usize].z)
                    .sum::<f64>()
                    / tip_nodes.len() as f64
                    / len
            };
            let (x, ok, solve_us) = static_solve(&fem, &f_ext, mesh.nodes.clone());
            let mut row = Row::new(
                Scenario::Cantilever,
                material_label("static".into(), model),
                "static",
                &mesh,
            )
            .material(model);
            row.settings = format!(
                "{}x{n}x{n} cells, 10 load steps, Newton; time = whole solve",
                10 * n
            );
            row.set_solve_time(solve_us);
            row.reference = reference.clone();
            let static_v = deflection(&x);
            if ok {
                row.stable = true;
                row.observable_error = (static_v - BD_ALPHA1).abs() / BD_ALPHA1;
                row.observable = format!("v/L = {static_v:.5}");
            }
            row.print();
            rows.push(row);
            let cap = if quick { 1.0 } else { 3.0 };
            // The other materials (corotational: a polar decomposition per element) run
            // dynamically on the two coarser meshes only.
            let dynamic = model == MaterialModel::StVenantKirchhoff || n <= 3;
            let beam = Beam {
                n,
                model,
                mesh: &mesh,
                fem: &fem,
                f_ext: &f_ext,
                reference: &reference,
            };
            dynamic_rows(
                &beam,
                all_methods
                    .iter()
                    .filter(|m| dynamic && m.material == model),
                cap,
                &deflection,
                static_v,
                rows,
            );
        }
    }
}

/// Static with 10 load increments from `x0`: the positions, whether every increment
/// converged, the wall time of the whole solve (us).
fn static_solve(fem: &FemModel, f_ext: &[DVec3], x0: Vec<DVec3>) -> (Vec<DVec3>, bool, f64) {
    let mut x = x0;
    let t = Instant::now();
    let mut ok = true;
    for k in 1..=10 {
        let fk: Vec<DVec3> = f_ext.iter().map(|f| *f * (k as f64 / 10.0)).collect();
        if solve_static(
            fem,
            &fk,
            &mut x,
            &StaticParams {
                rel_tol: 1e-9,
                ..StaticParams::default()
            },
        )
        .is_err()
        {
            ok = false;
            break;
        }
    }
    let solve_us = t.elapsed().as_secs_f64() * 1e6;
    (x, ok, solve_us)
}

/// One beam of the scenario: `n` cells across, its material, mesh, model, tip load and
/// reference text.
struct Beam<'a> {
    n: usize,
    model: MaterialModel,
    mesh: &'a TetMesh,
    fem: &'a FemModel,
    f_ext: &'a [DVec3],
    reference: &'a str,
}

/// The dynamic rows of `beam`, one per method (at most `cap` s simulated); `deflection` gives
/// v / L of positions, `static_v` the static solution's on this mesh.
fn dynamic_rows<'m>(
    beam: &Beam<'_>,
    methods: impl Iterator<Item = &'m Method>,
    cap: f64,
    deflection: &dyn Fn(&[DVec3]) -> f64,
    static_v: f64,
    rows: &mut Vec<Row>,
) {
    let Beam {
        n,
        model,
        mesh,
        fem,
        f_ext,
        reference,
    } = *beam;
    for m in methods {
        let mut row =
            Row::new(Scenario::Cantilever, m.label(), m.kind.name(), &mesh).material(model);
        row.reference = reference.to_string();
        match run_loaded_with(&fem, &mesh, &m.params(), &f_ext, 0.3, cap) {
            Err(e) => row.settings = format!("refused: {e}"),
            Ok(run) => {
                row.settings = format!(
                    "{}x{n}x{n} cells, {}, alpha 60/s, {}",
                    10 * n,
                    m.step_text(run.substeps),
                    steady_text(run.time_s, cap)
                );
                row.set_times(&run.ticks, 1e-3);
                row.stable = run.stable && run.x.iter().all(|v| v.is_finite());
                if row.stable {
                    let v = deflection(&run.x);
                    row.observable_error = (v - BD_ALPHA1).abs() / BD_ALPHA1;
                    row.observable = format!("v/L = {v:.5} (static on this mesh {static_v:.5})");
                }
            }
        }
        row.print();
        rows.push(row);
    }
}

fn tri_area(x: &[DVec3], t: &[u32; 3]) -> f64 {
    let [a, b, c] = t.map(|i| x[i as usize]);
    0.5 * (b - a).cross(c - a).length()
}
