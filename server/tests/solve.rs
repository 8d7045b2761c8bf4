//! `haptic-solve`'s library: static solutions of scene files and their output files.

use std::path::Path;

use haptic_model::element::FemModel;
use haptic_model::scene::parse_scene_toml;
use haptic_model::statics::free_residual_norm;
use haptic_server::solve::{SolveParams, solve_scene, write_solution};

const SCENE: &str = r#"
name = "lv-inflation-test"
[mesh]
builtin = "lv"
target_tets = 1000
length_unit = "mm"
[material]
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
density_kg_per_m3 = 1060.0
[boundary]
clamped = ["BASE"]
[[loads.pressure]]
surfaces = ["ENDO"]
pressure_pa = 500.0
follower = true
"#;

#[test]
fn cavity_pressure_inflates_the_ventricle_and_files_are_written() {
    let scene = parse_scene_toml(SCENE, Path::new(".")).unwrap();
    let params = SolveParams {
        load_steps: 2,
        ..SolveParams::default()
    };
    let (x, report) = solve_scene(&scene, &params).unwrap();
    assert!(report.residual_n < 1e-8, "{report:?}");
    // The reported residual is the true one: the follower load re-evaluated at the final shape,
    // computed here independently of the solver's bookkeeping.
    let mut fem = FemModel::new(&scene.mesh, scene.material).unwrap();
    fem.clamp_nodes(&scene.clamped_nodes);
    let truth = free_residual_norm(&fem, &scene.external_forces(&x), &x);
    assert!(
        (truth - report.residual_n).abs() <= 1e-12 + 1e-6 * truth,
        "reported {:e}, true {truth:e}",
        report.residual_n
    );
    assert!(
        report.load_passes > 2,
        "a follower load needs passes: {report:?}"
    );
    assert!(
        report.max_displacement_m > 1e-5 && report.max_displacement_m < 2e-3,
        "{report:?}"
    );
    // Endocardial nodes near the equator (z = -5 mm) move away from the long axis.
    let endo = scene.mesh.surface("ENDO").unwrap();
    let mut outward = 0;
    let mut checked = 0;
    for &i in endo.triangles.iter().flatten() {
        let r = scene.mesh.nodes[i as usize];
        if (r.z + 0.005).abs() < 0.002 {
            checked += 1;
            let radial = (x[i as usize] - r).truncate().dot(r.truncate().normalize());
            if radial > 0.0 {
                outward += 1;
            }
        }
    }
    assert!(
        checked > 10 && outward == checked,
        "{outward}/{checked} equatorial endocardial nodes moved outward"
    );

    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("solve-test");
    write_solution(&dir, &scene, &x).unwrap();
    let csv = std::fs::read_to_string(dir.join("nodes.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("id,x0,y0,z0,x,y,z"));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), scene.mesh.node_count());
    // In the scene's unit (mm): the epicardial apex is at z = -20 mm.
    let min_z0 = rows.iter().map(|r| r[3]).fold(f64::INFINITY, f64::min);
    assert!((min_z0 + 20.0).abs() < 1e-6, "{min_z0}");
    let k = 7;
    assert!((rows[k][4] - x[k].x * 1e3).abs() < 1e-9);
    let vtu = std::fs::read_to_string(dir.join("solution.vtu")).unwrap();
    assert!(vtu.contains(&format!(
        "NumberOfPoints=\"{}\" NumberOfCells=\"{}\"",
        scene.mesh.node_count(),
        scene.mesh.tet_count()
    )));
    assert_eq!(
        vtu.matches("<DataArray").count(),
        vtu.matches("</DataArray>").count()
    );
}

#[test]
fn a_scene_without_loads_is_refused() {
    let text = SCENE.split("[[loads.pressure]]").next().unwrap();
    let scene = parse_scene_toml(text, Path::new(".")).unwrap();
    let err = solve_scene(&scene, &SolveParams::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("no [loads]"), "{err}");
}

/// A follower load that has not settled is a failure with the true residual, never a
/// "converged" with the residual of the last frozen-load solve.
#[test]
fn an_unsettled_follower_load_fails_loudly() {
    let scene = parse_scene_toml(SCENE, Path::new(".")).unwrap();
    let params = SolveParams {
        load_steps: 1,
        max_follower_passes: 2,
        ..SolveParams::default()
    };
    let err = solve_scene(&scene, &params).unwrap_err().to_string();
    assert!(
        err.contains("load increment 1/1")
            && err.contains("did not settle in 2 passes")
            && err.contains("more load steps"),
        "{err}"
    );
}
