//! MacNeal-Harder 3-D patch test (issue 3 section 2; MacNeal & Harder 1985, "A proposed
//! standard set of problems to test finite element accuracy", Finite Elem. Anal. Des. 1:3-20):
//! the unit cube with its 8 corners and 8 irregular interior nodes, E = 1e6, nu = 0.25, the
//! corners displaced by `u = 1e-3 (2x + y + z)/2`, `v = 1e-3 (x + 2y + z)/2`,
//! `w = 1e-3 (x + y + 2z)/2`. The interior nodes must follow the same affine field to 1e-10
//! relative, and the stress is `sigma_xx = sigma_yy = sigma_zz = 2000`, shear 400.
//!
//! The classic patch is 7 hexahedra (an inner hexahedron on the 8 interior nodes and one per
//! cube face); we split each into the 6 tetrahedra around one of its 4 main diagonals (Kuhn),
//! choosing the diagonals by exhaustive search (4^7 combinations) so that neighbouring
//! hexahedra split their shared faces the same way. No extra points are added.

use glam::DMat3;
use haptic_model::DVec3;
use haptic_model::element::{CLAMPED, FemModel, StrainSmoothing};
use haptic_model::material::{self, MaterialModel, MaterialParams};
use haptic_model::mesh::{TetMesh, tet_signed_volume};
use haptic_model::statics::{StaticParams, solve_static};

const INTERIOR: [[f64; 3]; 8] = [
    [0.249, 0.342, 0.192],
    [0.826, 0.288, 0.288],
    [0.850, 0.649, 0.263],
    [0.273, 0.750, 0.230],
    [0.320, 0.186, 0.643],
    [0.677, 0.305, 0.683],
    [0.788, 0.693, 0.644],
    [0.165, 0.745, 0.702],
];

/// Node index of the cube corner (a, b, c) in {0,1}^3 (nodes 0..8) and of the interior node
/// nearest to it (nodes 8..16).
fn corner(a: usize, b: usize, c: usize) -> u32 {
    (a + 2 * b + 4 * c) as u32
}
fn inner(a: usize, b: usize, c: usize) -> u32 {
    // INTERIOR is listed counter-clockwise per layer: (0,0),(1,0),(1,1),(0,1).
    let k = match (a, b) {
        (0, 0) => 0,
        (1, 0) => 1,
        (1, 1) => 2,
        _ => 3,
    };
    (8 + k + 4 * c) as u32
}

/// The 7 hexahedra, each as 8 node indices in local order `i + 2 j + 4 k`.
fn hexahedra() -> Vec<[u32; 8]> {
    let mut hexes = Vec::new();
    let local = |f: &dyn Fn(usize, usize, usize) -> u32| {
        let mut h = [0; 8];
        for (l, v) in h.iter_mut().enumerate() {
            *v = f(l & 1, (l >> 1) & 1, (l >> 2) & 1);
        }
        h
    };
    hexes.push(local(&|a, b, c| inner(a, b, c)));
    for axis in 0..3 {
        for side in 0..2 {
            // Local coordinate along `axis`: 0 = the cube face, 1 = the inner hexahedron.
            hexes.push(local(&|i, j, k| {
                let mut p = [0; 3];
                let (o1, o2) = ((axis + 1) % 3, (axis + 2) % 3);
                p[axis] = side;
                p[o1] = j;
                p[o2] = k;
                if i == 0 {
                    corner(p[0], p[1], p[2])
                } else {
                    inner(p[0], p[1], p[2])
                }
            }));
        }
    }
    hexes
}

/// The 6 Kuhn tetrahedra of hexahedron `h` around the main diagonal from local vertex `s` to
/// `7 - s` (`s` in 0..4).
fn kuhn(h: &[u32; 8], s: usize) -> Vec<[u32; 4]> {
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    perms
        .iter()
        .map(|p| {
            let mut v = 0usize;
            let mut t = [h[s], 0, 0, 0];
            for (q, &axis) in p.iter().enumerate() {
                v |= 1 << axis;
                t[q + 1] = h[v ^ s];
            }
            t
        })
        .collect()
}

/// The 16 nodes and a conforming tetrahedralisation of the 7-hexahedron patch.
fn patch_mesh() -> TetMesh {
    let mut nodes: Vec<DVec3> = (0..8)
        .map(|l| DVec3::new((l & 1) as f64, ((l >> 1) & 1) as f64, ((l >> 2) & 1) as f64))
        .collect();
    nodes.extend(INTERIOR.iter().map(|p| DVec3::from_array(*p)));
    let hexes = hexahedra();
    let on_cube_face = |t: &[u32; 3]| {
        (0..3).any(|ax| {
            let c = t.map(|i| nodes[i as usize][ax]);
            c.iter().all(|&x| x == 0.0) || c.iter().all(|&x| x == 1.0)
        })
    };
    for combo in 0..4usize.pow(7) {
        let mut tets = Vec::new();
        for (h, hex) in hexes.iter().enumerate() {
            tets.extend(kuhn(hex, (combo >> (2 * h)) & 3));
        }
        // Orient, and require a proper tiling: positive volumes summing to 1, each face
        // shared by two tets or lying on the cube surface.
        let mut vol = 0.0;
        let mut ok = true;
        for t in &mut tets {
            let v = tet_signed_volume(
                nodes[t[0] as usize],
                nodes[t[1] as usize],
                nodes[t[2] as usize],
                nodes[t[3] as usize],
            );
            if v.abs() < 1e-6 {
                ok = false;
            }
            if v < 0.0 {
                t.swap(2, 3);
            }
            vol += v.abs();
        }
        if !ok || (vol - 1.0).abs() > 1e-12 {
            continue;
        }
        let mut faces: Vec<[u32; 3]> = tets
            .iter()
            .flat_map(|t| {
                [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]].map(|f| {
                    let mut tri = f.map(|i| t[i]);
                    tri.sort_unstable();
                    tri
                })
            })
            .collect();
        faces.sort_unstable();
        let mut conforming = true;
        let mut i = 0;
        while i < faces.len() {
            let mut j = i;
            while j < faces.len() && faces[j] == faces[i] {
                j += 1;
            }
            let count = j - i;
            if count > 2 || (count == 1 && !on_cube_face(&faces[i])) {
                conforming = false;
                break;
            }
            i = j;
        }
        if conforming {
            return TetMesh {
                nodes,
                tets,
                tet_edge_nodes: Vec::new(),
                surfaces: Vec::new(),
                node_groups: Vec::new(),
            };
        }
    }
    panic!("no conforming Kuhn split of the 7-hexahedron patch");
}

/// Displacement gradient of the prescribed field times `scale`.
fn grad_u(scale: f64) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(1.0, 0.5, 0.5),
        DVec3::new(0.5, 1.0, 0.5),
        DVec3::new(0.5, 0.5, 1.0),
    ) * (1e-3 * scale)
}

/// Both element technologies: standard FEM and the edge-based smoothed FEM (the average of a
/// constant deformation gradient is that gradient, so it must pass the patch test as well).
const SMOOTHINGS: [StrainSmoothing; 2] = [StrainSmoothing::None, StrainSmoothing::Edge];

/// Solves the patch with the corners on the affine field, in `steps` load increments; returns
/// the positions and the largest interior nodal error relative to the largest displacement.
fn solve_patch(
    model: MaterialModel,
    smoothing: StrainSmoothing,
    scale: f64,
    steps: usize,
) -> (FemModel, Vec<DVec3>, f64) {
    let mesh = patch_mesh();
    assert_eq!(mesh.node_count(), 16);
    let mut mat = MaterialParams::from_youngs(1e6, 0.25, 1.0);
    mat.model = model;
    let mut fem = FemModel::with_smoothing(&mesh, mat, smoothing).unwrap();
    fem.clamp_nodes(&(0..8).collect::<Vec<u32>>());
    let g = grad_u(scale);
    let mut x = mesh.nodes.clone();
    let params = StaticParams {
        abs_tol_n: 1e-12 * 1e6 * scale.max(1.0),
        max_iterations: 100,
        ..StaticParams::default()
    };
    let f_ext = vec![DVec3::ZERO; 16];
    for s in 1..=steps {
        let gs = g * (s as f64 / steps as f64);
        for (xi, p) in x.iter_mut().zip(&mesh.nodes).take(8) {
            *xi = *p + gs * *p;
        }
        solve_static(&fem, &f_ext, &mut x, &params)
            .unwrap_or_else(|e| panic!("{model:?} scale {scale} step {s}: {e}"));
    }
    let umax = mesh
        .nodes
        .iter()
        .map(|p| (g * *p).length())
        .fold(0.0, f64::max);
    let err = (8..16)
        .map(|i| (x[i] - (mesh.nodes[i] + g * mesh.nodes[i])).length())
        .fold(0.0, f64::max)
        / umax;
    assert!(fem.constraints()[..8].iter().all(|&c| c == CLAMPED));
    (fem, x, err)
}

#[test]
fn patch_mesh_is_a_valid_tetrahedralisation_of_the_16_points() {
    let mesh = patch_mesh();
    assert_eq!(mesh.node_count(), 16);
    assert_eq!(mesh.tet_count(), 42);
    assert!((mesh.volume() - 1.0).abs() < 1e-12);
    // Every node is used.
    let mut used = [false; 16];
    mesh.tets
        .iter()
        .flatten()
        .for_each(|&i| used[i as usize] = true);
    assert!(used.iter().all(|&u| u));
}

#[test]
fn small_displacement_reproduces_the_affine_field_and_the_stress_for_every_material() {
    for model in [
        MaterialModel::StVenantKirchhoff,
        MaterialModel::Corotational,
        MaterialModel::StableNeoHookean,
    ] {
        for smoothing in SMOOTHINGS {
            let (_, _, err) = solve_patch(model, smoothing, 1.0, 1);
            println!("{model:?} {smoothing:?}: interior displacement error {err:.2e} (relative)");
            assert!(
                err < 1e-10,
                "{model:?} {smoothing:?}: interior nodal error {err:e}"
            );
        }
        let (fem, x, _) = solve_patch(model, StrainSmoothing::None, 1.0, 1);
        let mat = fem.material();
        let mut worst_lin: f64 = 0.0;
        for e in 0..fem.tets().len() {
            let f = fem.deformation_gradient(e, &x);
            // Linear (small-strain) stress from the element F.
            let h = f - DMat3::IDENTITY;
            let eps = (h + h.transpose()) * 0.5;
            let tr = eps.x_axis.x + eps.y_axis.y + eps.z_axis.z;
            let sigma =
                eps * (2.0 * mat.mu_pa) + DMat3::from_diagonal(DVec3::splat(mat.lambda_pa * tr));
            let want = DMat3::from_cols(
                DVec3::new(2000.0, 400.0, 400.0),
                DVec3::new(400.0, 2000.0, 400.0),
                DVec3::new(400.0, 400.0, 2000.0),
            );
            let d = sigma - want;
            worst_lin = worst_lin.max(
                d.to_cols_array()
                    .iter()
                    .fold(0.0_f64, |m, v| m.max(v.abs()))
                    / 2000.0,
            );
            // The material's own Cauchy stress J^-1 P F^T differs only at second order (1e-3).
            let cauchy = material::first_piola(mat, &f) * f.transpose() / f.determinant();
            let dc = (cauchy - want)
                .to_cols_array()
                .iter()
                .fold(0.0, |m: f64, v| m.max(v.abs()));
            assert!(dc / 2000.0 < 5e-3, "{model:?} element {e}: Cauchy {cauchy}");
            if e == 0 && model == MaterialModel::StVenantKirchhoff {
                let s =
                    material::stvk_stress(&material::green_strain(&f), mat.lambda_pa, mat.mu_pa);
                println!("StVK second Piola-Kirchhoff stress S = {s}; Cauchy {cauchy}");
            }
        }
        println!("{model:?}: linear stress error {worst_lin:.2e} (relative to 2000)");
        assert!(worst_lin < 1e-8, "{model:?}: stress error {worst_lin:e}");
    }
}

/// At 1000 times the displacement (strains of order 1) the homogeneous deformation is still an
/// exact equilibrium of the nonlinear problem: StVK (and the other materials) reproduce it.
#[test]
fn large_displacement_still_reproduces_the_homogeneous_deformation() {
    for model in [
        MaterialModel::StVenantKirchhoff,
        MaterialModel::Corotational,
        MaterialModel::StableNeoHookean,
    ] {
        for smoothing in SMOOTHINGS {
            let (_, _, err) = solve_patch(model, smoothing, 1000.0, 10);
            println!(
                "{model:?} {smoothing:?} at 1000x: interior displacement error {err:.2e} (relative)"
            );
            assert!(
                err < 1e-10,
                "{model:?} {smoothing:?}: interior nodal error {err:e} at 1000x"
            );
        }
    }
}
