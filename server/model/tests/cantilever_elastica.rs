//! Large-deflection cantilever (issue 3 section 2; Bisshopp & Drucker 1945, "Large deflection
//! of cantilever beams", Q. Appl. Math. 3:272-275): a beam 10 x 1 x 1 (dimensionless units,
//! E = 1.2e4 so EI = 1000), clamped on its XMIN face, a dead tip load P along -y on the XMAX
//! face nodes (by tributary area), `alpha = P L^2 / (E I)` = 1 and 3. The elastica's tip
//! deflection is v/L = 0.30172 (alpha 1) and 0.60325 (alpha 3).
//!
//! Linear tetrahedra lock in bending (the tip deflects too little: -15 % at alpha 1 on 40x4x4
//! cells); quadratic (10-node) tetrahedra do not, and meet the 3 % on 20x2x2 cells.
//! We use nu = 0 and the load is applied in increments (Newton per increment, 8 per unit of
//! alpha: fewer make the residual-norm line search stall).

use std::time::Instant;

use haptic_model::DVec3;
use haptic_model::element::{FemModel, StrainSmoothing};
use haptic_model::material::{MaterialModel, MaterialParams};
use haptic_model::mesh::generate::box_mesh;
use haptic_model::statics::{StaticParams, solve_static};

const L: f64 = 10.0;
const E: f64 = 1.2e4;
const EI: f64 = E / 12.0;

/// Tip deflections v/L at alpha = 1 and 3 for a `cells` box mesh (6 tets per cell), with
/// linear or quadratic tetrahedra.
fn tip_deflections(
    cells: [usize; 3],
    model: MaterialModel,
    steps: usize,
    quadratic: bool,
    smoothing: StrainSmoothing,
) -> [f64; 2] {
    let mut mesh = box_mesh(DVec3::new(L, 1.0, 1.0), cells);
    if quadratic {
        mesh = mesh.to_quadratic();
    }
    let mut mat = MaterialParams::from_youngs(E, 0.0, 1.0);
    mat.model = model;
    let mut fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
    let names = ["XMIN".to_string()];
    fem.clamp_nodes(&mesh.nodes_of_surfaces(&names, "clamped").unwrap());
    // Tributary areas of the tip face: a third of each triangle per vertex; they sum to 1.
    let n = mesh.node_count();
    let mut weight = vec![0.0; n];
    for t in &mesh.surface("XMAX").unwrap().triangles {
        let [a, b, c] = t.map(|i| mesh.nodes[i as usize]);
        let area = (b - a).cross(c - a).length() / 2.0;
        for &i in t {
            weight[i as usize] += area / 3.0;
        }
    }
    let tip: Vec<usize> = (0..n).filter(|&i| weight[i] > 0.0).collect();
    let mut x = mesh.nodes.clone();
    let mut f_ext = vec![DVec3::ZERO; n];
    let params = StaticParams {
        rel_tol: 1e-8,
        max_iterations: 30,
        ..StaticParams::default()
    };
    let mut out = [0.0; 2];
    let mut alpha_done = 0.0;
    for (k, alpha) in [1.0, 3.0].into_iter().enumerate() {
        let nsteps = ((alpha - alpha_done) * steps as f64).round() as usize;
        for s in 1..=nsteps {
            let a = alpha_done + (alpha - alpha_done) * s as f64 / nsteps as f64;
            let p = a * EI / (L * L);
            for &i in &tip {
                f_ext[i] = DVec3::new(0.0, -p * weight[i], 0.0);
            }
            solve_static(&fem, &f_ext, &mut x, &params)
                .unwrap_or_else(|e| panic!("{cells:?} {model:?} alpha {a}: {e}"));
        }
        alpha_done = alpha;
        let v: f64 = tip
            .iter()
            .map(|&i| (mesh.nodes[i].y - x[i].y) * weight[i])
            .sum();
        out[k] = v / L;
    }
    out
}

const EXACT: [f64; 2] = [0.30172, 0.60325];

/// Relative tip-deflection errors `[alpha 1, alpha 3]` of StVK on a `cells` mesh against the
/// elastica, printed with the run time.
fn relative_errors(cells: [usize; 3], quadratic: bool) -> [f64; 2] {
    relative_errors_with(cells, quadratic, StrainSmoothing::None)
}

fn relative_errors_with(
    cells: [usize; 3],
    quadratic: bool,
    smoothing: StrainSmoothing,
) -> [f64; 2] {
    let t = Instant::now();
    let v = tip_deflections(
        cells,
        MaterialModel::StVenantKirchhoff,
        8,
        quadratic,
        smoothing,
    );
    let err = [v[0] / EXACT[0] - 1.0, v[1] / EXACT[1] - 1.0];
    println!(
        "{} {smoothing:?} {cells:?}: v/L = {:.5} ({:+.2} %) at alpha 1, {:.5} ({:+.2} %) at alpha 3, {:.1} s",
        if quadratic { "quadratic" } else { "linear" },
        v[0],
        err[0] * 100.0,
        v[1],
        err[1] * 100.0,
        t.elapsed().as_secs_f64()
    );
    err
}

/// CI version: the tip deflection at alpha = 1 and 3 approaches the elastica as the mesh is
/// refined (20x2x2 -> 40x4x4 cells). Linear tetrahedra lock in bending: measured errors are
/// printed; the 3 % target needs finer meshes (see the ignored test below).
#[test]
fn tip_deflection_approaches_the_elastica_under_refinement() {
    let errors: Vec<[f64; 2]> = [[20, 2, 2], [40, 4, 4]]
        .into_iter()
        .map(|cells| relative_errors(cells, false))
        .collect();
    for k in 0..2 {
        assert!(
            errors[1][k].abs() < errors[0][k].abs() && errors[1][k].abs() < 0.2,
            "alpha {}: errors {errors:?}",
            [1, 3][k]
        );
    }
}

/// The 3 % target with quadratic tetrahedra, and convergence under refinement:
/// 10x1x1 cells (60 elements) then 20x2x2 (480 elements, the finest mesh this test runs).
#[test]
fn quadratic_tets_reach_the_elastica_within_three_percent() {
    let errors: Vec<[f64; 2]> = [[10, 1, 1], [20, 2, 2]]
        .into_iter()
        .map(|cells| relative_errors(cells, true))
        .collect();
    for k in 0..2 {
        assert!(
            errors[1][k].abs() < 0.03,
            "alpha {}: errors {errors:?}",
            [1, 3][k]
        );
    }
}

/// Edge-based strain smoothing (ES-FEM-T4) takes the bending locking out of linear
/// tetrahedra: on 20x2x2 cells (480 tets) standard linear elements are 41 % / 27 % short of the
/// elastica, the smoothed ones meet the 3 % (measured -0.8 % / -0.3 %; on 40x4x4 cells
/// +1.3 % / +1.2 %, against -14.6 % / -7.6 %).
#[test]
fn edge_smoothed_linear_tets_reach_the_elastica_within_three_percent() {
    let fem = relative_errors_with([20, 2, 2], false, StrainSmoothing::None);
    let es = relative_errors_with([20, 2, 2], false, StrainSmoothing::Edge);
    for k in 0..2 {
        assert!(es[k].abs() < 0.03, "alpha {}: ES {es:?}", [1, 3][k]);
        assert!(
            fem[k].abs() > 0.2,
            "alpha {}: FEM {fem:?} no longer locks?",
            [1, 3][k]
        );
    }
}
