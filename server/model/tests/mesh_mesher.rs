//! Built-in meshers: orientation, conformity, counts, volumes, analytic surfaces, node groups.

use std::collections::{BTreeSet, HashMap};

use haptic_model::DVec3;
use haptic_model::mesh::generate::{
    box_mesh, ellipsoid_shell, lv_shell, min_dihedral_angle_deg, sphere_shell,
};
use haptic_model::mesh::{TetMesh, tet_signed_volume};

/// Exact volume of the part `z <= z0` of the solid ellipsoid with semi-axes (a, b, c).
fn ellipsoid_cap_volume(a: f64, b: f64, c: f64, z0: f64) -> f64 {
    std::f64::consts::PI * a * b * ((z0 + c) - (z0.powi(3) + c.powi(3)) / (3.0 * c * c))
}

fn lv_exact_volume() -> f64 {
    let mm = 1e-3;
    ellipsoid_cap_volume(10.0 * mm, 10.0 * mm, 20.0 * mm, 5.0 * mm)
        - ellipsoid_cap_volume(7.0 * mm, 7.0 * mm, 17.0 * mm, 5.0 * mm)
}

/// Every tet positive; every face shared by at most two tets; every interior face by exactly
/// two; the boundary equals the union of the named surfaces (as oriented triangles, no
/// duplicates); every node used.
fn check_mesh(m: &TetMesh, surfaces: &[&str]) {
    let scale = {
        let (lo, hi) = m.bounding_box();
        (hi - lo).max_element().powi(3)
    };
    let mut faces: HashMap<[u32; 3], u32> = HashMap::new();
    let mut used = vec![false; m.node_count()];
    for t in &m.tets {
        let [a, b, c, d] = t.map(|i| m.nodes[i as usize]);
        assert!(
            tet_signed_volume(a, b, c, d) > 1e-9 * scale,
            "tet {t:?} not positive"
        );
        for f in [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]] {
            let mut k = [t[f[0]], t[f[1]], t[f[2]]];
            k.sort_unstable();
            *faces.entry(k).or_default() += 1;
        }
        for &i in t {
            used[i as usize] = true;
        }
    }
    assert!(used.iter().all(|&u| u), "unused nodes");
    assert!(
        faces.values().all(|&c| c <= 2),
        "a face is shared by more than two tets"
    );
    let boundary: BTreeSet<[u32; 3]> = m.boundary_triangles().into_iter().collect();
    assert_eq!(boundary.len(), faces.values().filter(|&&c| c == 1).count());
    let mut named = BTreeSet::new();
    let mut total = 0;
    for s in surfaces {
        let g = m.surface(s).unwrap_or_else(|| panic!("no surface {s}"));
        assert!(!g.triangles.is_empty(), "{s} empty");
        total += g.triangles.len();
        named.extend(g.triangles.iter().copied());
    }
    assert_eq!(total, named.len(), "named surfaces overlap");
    assert_eq!(boundary, named, "boundary != union of named surfaces");
    // A closed, conforming boundary: every boundary edge is used by exactly two boundary faces,
    // in opposite directions.
    let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
    for t in &boundary {
        for e in 0..3 {
            let (a, b) = (t[e], t[(e + 1) % 3]);
            *edges.entry((a.min(b), a.max(b))).or_default() += if a < b { 1 } else { -1 };
        }
    }
    assert!(
        edges.values().all(|&v| v == 0),
        "boundary is not a closed oriented surface"
    );
}

fn on_ellipsoid(p: DVec3, ax: DVec3) -> f64 {
    ((p / ax).length_squared() - 1.0).abs()
}

fn surface_nodes(m: &TetMesh, name: &str) -> Vec<DVec3> {
    let mut ids: Vec<u32> = m
        .surface(name)
        .unwrap()
        .triangles
        .iter()
        .flatten()
        .copied()
        .collect();
    ids.sort_unstable();
    ids.dedup();
    ids.iter().map(|&i| m.nodes[i as usize]).collect()
}

fn stats(label: &str, m: &TetMesh, exact: f64) -> (f64, f64) {
    let angle = min_dihedral_angle_deg(m);
    let err = (m.volume() - exact) / exact;
    println!(
        "{label}: tets {} nodes {} min dihedral {angle:.1} deg volume error {:+.3} %",
        m.tet_count(),
        m.node_count(),
        100.0 * err
    );
    (angle, err)
}

#[test]
fn lv_shell_is_valid_conforming_and_converges() {
    let exact = lv_exact_volume();
    assert!((exact - 3234.73e-9).abs() < 0.01e-9, "{exact}");
    for target in [1000, 2000, 5000, 10000, 20000, 30000] {
        let m = lv_shell(target);
        check_mesh(&m, &["ENDO", "EPI", "BASE"]);
        let ratio = m.tet_count() as f64 / target as f64;
        assert!(
            (0.8..=1.2).contains(&ratio),
            "target {target}: {} tets",
            m.tet_count()
        );
        let (angle, err) = stats(&format!("lv_shell({target})"), &m, exact);
        assert!(angle > 10.0, "target {target}: min dihedral {angle}");
        if target >= 2000 {
            assert!(err.abs() < 0.03, "target {target}: volume error {err}");
        }
        if target >= 20000 {
            assert!(err.abs() < 0.01, "target {target}: volume error {err}");
        }
    }
}

#[test]
fn lv_shell_nodes_lie_on_the_analytic_surfaces() {
    let mm = 1e-3;
    let m = lv_shell(2000);
    let endo = DVec3::new(7.0, 7.0, 17.0) * mm;
    let epi = DVec3::new(10.0, 10.0, 20.0) * mm;
    for p in surface_nodes(&m, "ENDO") {
        assert!(on_ellipsoid(p, endo) < 1e-12, "{p}");
        assert!(p.z <= 5.0 * mm);
    }
    for p in surface_nodes(&m, "EPI") {
        assert!(on_ellipsoid(p, epi) < 1e-12, "{p}");
    }
    for p in surface_nodes(&m, "BASE") {
        assert_eq!(p.z, 0.005);
    }
    let (lo, hi) = m.bounding_box();
    assert_eq!(hi.z, 0.005);
    assert!((lo.z + 0.020).abs() < 1e-15);
    let endopt = &m.node_group("ENDOPT").unwrap().nodes;
    let epipt = &m.node_group("EPIPT").unwrap().nodes;
    assert_eq!(endopt.len(), 1);
    assert_eq!(epipt.len(), 1);
    assert_eq!(m.nodes[endopt[0] as usize], DVec3::new(0.0, 0.0, -0.017));
    assert_eq!(m.nodes[epipt[0] as usize], DVec3::new(0.0, 0.0, -0.020));
}

#[test]
fn lv_shell_surfaces_face_outward() {
    let m = lv_shell(3000);
    let radial = |g: &str| -> f64 {
        let tris = &m.surface(g).unwrap().triangles;
        tris.iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.nodes[i as usize]);
                let centre = (a + b + c) / 3.0;
                (b - a)
                    .cross(c - a)
                    .normalize()
                    .dot(DVec3::new(centre.x, centre.y, 0.0).normalize_or_zero())
            })
            .sum::<f64>()
            / tris.len() as f64
    };
    assert!(radial("EPI") > 0.5);
    assert!(radial("ENDO") < -0.5);
    for t in &m.surface("BASE").unwrap().triangles {
        let [a, b, c] = t.map(|i| m.nodes[i as usize]);
        assert!((b - a).cross(c - a).normalize().z > 0.999_999);
    }
}

#[test]
fn ellipsoid_shell_coarse_seed_model() {
    let mm = 1e-3;
    let (inner, outer) = (
        DVec3::new(6.0, 6.0, 12.0) * mm,
        DVec3::new(10.0, 10.0, 16.0) * mm,
    );
    let m = ellipsoid_shell(inner, outer, 188);
    check_mesh(&m, &["INNER", "OUTER"]);
    assert!((130..=250).contains(&m.tet_count()), "{}", m.tet_count());
    let exact = 4.0 / 3.0
        * std::f64::consts::PI
        * (outer.x * outer.y * outer.z - inner.x * inner.y * inner.z);
    stats("ellipsoid_shell(188)", &m, exact);
    for p in surface_nodes(&m, "INNER") {
        assert!(on_ellipsoid(p, inner) < 1e-12);
    }
    for p in surface_nodes(&m, "OUTER") {
        assert!(on_ellipsoid(p, outer) < 1e-12);
    }
    // POLE is a non-empty subset of OUTER at the bottom.
    let outer_set: BTreeSet<[u32; 3]> = m
        .surface("OUTER")
        .unwrap()
        .triangles
        .iter()
        .copied()
        .collect();
    let pole = &m.surface("POLE").unwrap().triangles;
    assert!(pole.len() >= 3);
    assert!(pole.iter().all(|t| outer_set.contains(t)));
    assert!(
        pole.iter()
            .flatten()
            .all(|&i| m.nodes[i as usize].z < -0.5 * outer.z)
    );
    assert_eq!(
        m.nodes[m.node_group("OUTER_NZ").unwrap().nodes[0] as usize],
        DVec3::new(0.0, 0.0, -outer.z)
    );

    // Finer meshes converge to the exact volume.
    let fine = ellipsoid_shell(inner, outer, 20000);
    check_mesh(&fine, &["INNER", "OUTER"]);
    let (angle, err) = stats("ellipsoid_shell(20000)", &fine, exact);
    assert!(err.abs() < 0.01 && angle > 10.0);
}

#[test]
fn sphere_shell_has_axis_nodes_and_converges() {
    let (ri, ro) = (0.01, 0.02);
    let exact = 4.0 / 3.0 * std::f64::consts::PI * (ro * ro * ro - ri * ri * ri);
    let mut last_err = f64::INFINITY;
    for target in [1000, 5000, 10000, 20000, 40000] {
        let m = sphere_shell(ri, ro, target);
        check_mesh(&m, &["INNER", "OUTER"]);
        let ratio = m.tet_count() as f64 / target as f64;
        assert!(
            (0.8..=1.2).contains(&ratio),
            "target {target}: {} tets",
            m.tet_count()
        );
        let (angle, err) = stats(&format!("sphere_shell({target})"), &m, exact);
        assert!(angle > 10.0, "{angle}");
        assert!(
            err < 0.0 && err.abs() < last_err,
            "volume must converge from below: {err}"
        );
        last_err = err.abs();
        for p in surface_nodes(&m, "INNER") {
            assert!((p.length() / ri - 1.0).abs() < 1e-12);
        }
        for p in surface_nodes(&m, "OUTER") {
            assert!((p.length() / ro - 1.0).abs() < 1e-12);
        }
        let node = |g: &str| {
            let n = &m.node_group(g).unwrap_or_else(|| panic!("{g}")).nodes;
            assert_eq!(n.len(), 1, "{g}");
            m.nodes[n[0] as usize]
        };
        assert_eq!(node("INNER_PZ"), DVec3::new(0.0, 0.0, ri));
        assert_eq!(node("INNER_NZ"), DVec3::new(0.0, 0.0, -ri));
        assert_eq!(node("INNER_PX"), DVec3::new(ri, 0.0, 0.0));
        assert_eq!(node("OUTER_PX"), DVec3::new(ro, 0.0, 0.0));
        // The INNER normals point toward the centre.
        for t in &m.surface("INNER").unwrap().triangles {
            let [a, b, c] = t.map(|i| m.nodes[i as usize]);
            assert!((b - a).cross(c - a).dot(a + b + c) < 0.0);
        }
    }
    assert!(last_err < 0.01);
}

#[test]
fn box_mesh_is_exact() {
    let size = DVec3::new(0.03, 0.02, 0.01);
    let m = box_mesh(size, [3, 2, 4]);
    check_mesh(&m, &["XMIN", "XMAX", "YMIN", "YMAX", "ZMIN", "ZMAX"]);
    assert_eq!(m.tet_count(), 6 * 3 * 2 * 4);
    assert_eq!(m.node_count(), 4 * 3 * 5);
    assert!((m.volume() - size.x * size.y * size.z).abs() < 1e-18);
    let (lo, hi) = m.bounding_box();
    assert_eq!(lo, DVec3::ZERO);
    assert_eq!(hi, size);
    let area = |g: &str| -> f64 {
        m.surface(g)
            .unwrap()
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.nodes[i as usize]);
                0.5 * (b - a).cross(c - a).length()
            })
            .sum()
    };
    assert!((area("XMAX") - size.y * size.z).abs() < 1e-15);
    assert!((area("ZMIN") - size.x * size.y).abs() < 1e-15);
    for t in &m.surface("ZMIN").unwrap().triangles {
        let [a, b, c] = t.map(|i| m.nodes[i as usize]);
        assert!((b - a).cross(c - a).z < 0.0);
    }
    assert!((min_dihedral_angle_deg(&m) - 0.0).abs() > 10.0);
}

#[test]
fn meshes_are_deterministic() {
    assert_eq!(lv_shell(2000), lv_shell(2000));
    assert_eq!(sphere_shell(1.0, 2.0, 5000), sphere_shell(1.0, 2.0, 5000));
}

/// Curved quadratic LV: every node of `ENDO` / `EPI` (corners and mid-edge nodes) on its
/// ellipsoid, base nodes in the base plane, and the volume (integrated with the isoparametric
/// map) much closer to the exact one than the flat-faceted linear mesh of the same size.
#[test]
fn curved_quadratic_lv_is_on_the_surfaces_and_more_accurate_in_volume() {
    use haptic_model::element::FemModel;
    use haptic_model::material::MaterialParams;
    use haptic_model::mesh::generate::lv_shell_quadratic;
    let mm = 1e-3;
    let exact = lv_exact_volume();
    let lin = lv_shell(1000);
    let quad = lv_shell_quadratic(1000);
    assert!(quad.is_quadratic());
    for (name, ax) in [
        ("ENDO", DVec3::new(7.0, 7.0, 17.0) * mm),
        ("EPI", DVec3::new(10.0, 10.0, 20.0) * mm),
    ] {
        let worst = surface_nodes(&quad, name)
            .iter()
            .map(|&p| on_ellipsoid(p, ax))
            .fold(0.0, f64::max);
        assert!(worst < 1e-12, "{name}: {worst:e}");
    }
    assert!(
        surface_nodes(&quad, "BASE")
            .iter()
            .all(|p| (p.z - 5.0 * mm).abs() < 1e-15)
    );
    let fem = FemModel::new(&quad, MaterialParams::from_youngs(1e4, 0.3, 1000.0)).unwrap();
    let err_quad = (fem.deformed_volume_m3(&quad.nodes) - exact).abs() / exact;
    let err_lin = (lin.volume() - exact).abs() / exact;
    println!("volume error: linear {err_lin:.2e}, curved quadratic {err_quad:.2e}");
    assert!(err_quad < 0.2 * err_lin, "{err_quad} vs {err_lin}");
}
