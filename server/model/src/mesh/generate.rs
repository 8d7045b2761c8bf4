//! Structured tetrahedral meshes built in code, in metres: the idealized left ventricle
//! ([`lv_shell`]), closed ellipsoidal shells ([`ellipsoid_shell`]), the thick-walled sphere of
//! the Lamé problem ([`sphere_shell`]) and boxes ([`box_mesh`]).
//!
//! Shells of revolution are built in three steps:
//!
//! 1. a triangulated *reference surface* made of rings of constant meridian arc-length fraction
//!    `sigma` in `[0, 1]` (a ring is a closed loop of `n_i` vertices at polar angles
//!    `2 pi (j + o_i) / n_i`; poles are single vertices). `n_i` follows the ring circumference so
//!    that triangles are close to equilateral everywhere: there is no polar-angle singularity,
//!    the pole vertex has about six neighbours like any other vertex. Consecutive rings are
//!    joined by a "zipper" that always advances along the ring whose next vertex has the smaller
//!    angle;
//! 2. the surface is extruded through `L` transmural layers: layer `k` lies on the ellipsoid
//!    whose semi-axes interpolate linearly between the inner (`t = 0`) and outer (`t = 1`)
//!    ones, `t = k / L`, each vertex at the same arc-length fraction of its layer's meridian, so
//!    inner and outer nodes are exactly on the analytic surfaces;
//! 3. every prism is split into three tetrahedra with the rule that each quadrilateral face is
//!    cut by the diagonal starting at its lowest global node index. Neighbouring prisms then
//!    agree on every shared face (the mesh is conforming) and no prism is left unsplittable
//!    (Dompierre, Labbé, Vallet, Camarero, *How to subdivide pyramids, prisms and hexahedra into
//!    tetrahedra*, 8th International Meshing Roundtable, 1999).
//!
//! Boundary faces are then classified into named, outward-oriented surfaces.
//!
//! Neighbours: produces [`TetMesh`] (see [`crate::mesh`]); used by [`crate::scene`] for the
//! built-in scenes and by tests as analytic references.

use std::f64::consts::{PI, TAU};

use glam::DVec3;

use crate::mesh::{NodeGroup, SurfaceGroup, TetMesh, tet_signed_volume};

/// Idealized left ventricle of the Land et al. 2015 cardiac mechanics benchmark (Proc. R. Soc.
/// A 471:20150641), in metres: a truncated ellipsoidal shell with endocardium semi-axes
/// (7, 7, 17) mm and epicardium (10, 10, 20) mm, apex on -z, cut by the base plane z = 5 mm.
/// Transmural layers interpolate the semi-axes linearly (`a(t) = 7 + 3t`, `c(t) = 17 + 3t` mm),
/// each cut at z = 5 mm, so base nodes have z = 0.005 m exactly.
///
/// Surfaces (outward oriented): `ENDO`, `EPI`, `BASE`. Node groups: `ENDOPT`, `EPIPT` (the
/// endocardial and epicardial apex nodes, (0, 0, -0.017) and (0, 0, -0.020) m).
///
/// `target_tets`: wanted number of tetrahedra; the result is within about 30 % of it for
/// 1000..=30000 (smaller targets give the coarsest mesh the construction allows, about 100 tets).
/// The exact myocardial volume is 3234.73 mm^3; the mesh volume converges to it.
pub fn lv_shell(target_tets: usize) -> TetMesh {
    let mm = 1e-3;
    let profile = Profile {
        inner: DVec3::new(7.0, 7.0, 17.0) * mm,
        outer: DVec3::new(10.0, 10.0, 20.0) * mm,
        z_cut: Some(5.0 * mm),
    };
    let shell = revolution_shell(&profile, target_tets);
    let mut mesh = shell.classify("ENDO", "EPI", Some("BASE"));
    mesh.node_groups = vec![
        NodeGroup {
            name: "ENDOPT".into(),
            nodes: vec![shell.node(0, 0, 0)],
        },
        NodeGroup {
            name: "EPIPT".into(),
            nodes: vec![shell.node(shell.layers, 0, 0)],
        },
    ];
    mesh
}

/// [`lv_shell`] with quadratic (10-node) elements whose mid-edge nodes on `ENDO` and `EPI` lie on
/// the analytic ellipsoids (curved, isoparametric boundary; the rim edges of the base stay in
/// the plane z = 5 mm). Geometric error O(h^3) instead of the O(h^2) sag of flat facets, which
/// on the coarse meshes is a sizeable part of a shallow probe depth (0.1 to 0.2 mm).
pub fn lv_shell_quadratic(target_tets: usize) -> TetMesh {
    let mm = 1e-3;
    let mut mesh = lv_shell(target_tets).to_quadratic();
    curve_shell_edges(
        &mut mesh,
        &[
            ("ENDO", DVec3::new(7.0, 7.0, 17.0) * mm),
            ("EPI", DVec3::new(10.0, 10.0, 20.0) * mm),
        ],
        Some(5.0 * mm),
    );
    mesh
}

/// Moves the mid-edge nodes of the surfaces `ENDO` and `EPI` of a quadratic mesh of the
/// idealized LV in metres (any mesher's: for example a Gmsh file of
/// `../shared/data/lv/README.md`'s geometry read and made quadratic by
/// [`TetMesh::to_quadratic`]) onto the analytic ellipsoids, semi-axes 7, 7, 17 mm and 10, 10,
/// 20 mm, as [`lv_shell_quadratic`] does (edges on the base plane z = 5 mm stay in it; an edge
/// in a plane through the long axis, such as a symmetry plane y = 0, stays in it). Corner
/// nodes are left where they are (a mesher puts them on the surfaces). An element that the
/// move would invert (an edge long against the surface's curvature, as near the
/// endocardium's apex, where the radius of curvature is 2.9 mm, on coarse meshes) keeps
/// straight edges. Returns the number of mid-edge nodes left straight.
pub fn curve_lv_surfaces(mesh: &mut TetMesh) -> usize {
    let mm = 1e-3;
    let straight = mesh.nodes.clone();
    curve_shell_edges(
        mesh,
        &[
            ("ENDO", DVec3::new(7.0, 7.0, 17.0) * mm),
            ("EPI", DVec3::new(10.0, 10.0, 20.0) * mm),
        ],
        Some(5.0 * mm),
    );
    let mut reverted = 0;
    loop {
        let bad: Vec<usize> = (0..mesh.tets.len())
            .filter(|&t| !quadratic_tet_is_valid(mesh, t))
            .collect();
        if bad.is_empty() {
            return reverted;
        }
        let before = reverted;
        for t in bad {
            for &m in &mesh.tet_edge_nodes[t] {
                let m = m as usize;
                if mesh.nodes[m] != straight[m] {
                    mesh.nodes[m] = straight[m];
                    reverted += 1;
                }
            }
        }
        if reverted == before {
            // Invalid with straight edges too: the caller's element check reports it.
            return reverted;
        }
    }
}

/// Whether the isoparametric map of quadratic tetrahedron `t` has a positive Jacobian at its
/// corners, its centroid and the points of the 4-point Gauss rule.
fn quadratic_tet_is_valid(mesh: &TetMesh, t: usize) -> bool {
    let (a, b) = (0.585_410_196_624_968_5, 0.138_196_601_125_010_5);
    let mut samples = vec![[0.25; 4]];
    for k in 0..4 {
        let mut corner = [0.0; 4];
        corner[k] = 1.0;
        let mut gauss = [b; 4];
        gauss[k] = a;
        samples.push(corner);
        samples.push(gauss);
    }
    let dl = [DVec3::splat(-1.0), DVec3::X, DVec3::Y, DVec3::Z];
    let nodes: Vec<DVec3> = mesh.tets[t]
        .iter()
        .chain(&mesh.tet_edge_nodes[t])
        .map(|&i| mesh.nodes[i as usize])
        .collect();
    samples.iter().all(|l| {
        let mut jac = glam::DMat3::ZERO;
        let mut add = |x: DVec3, g: DVec3| {
            jac += glam::DMat3::from_cols(x * g.x, x * g.y, x * g.z);
        };
        for i in 0..4 {
            add(nodes[i], dl[i] * (4.0 * l[i] - 1.0));
        }
        for (k, [i, j]) in crate::mesh::TET_EDGES.iter().enumerate() {
            add(nodes[4 + k], (dl[*j] * l[*i] + dl[*i] * l[*j]) * 4.0);
        }
        jac.determinant() > 0.0
    })
}

/// [`ellipsoid_shell`] with curved quadratic elements (see [`lv_shell_quadratic`]).
///
/// # Panics
/// As [`ellipsoid_shell`].
pub fn ellipsoid_shell_quadratic(inner: DVec3, outer: DVec3, target_tets: usize) -> TetMesh {
    let mut mesh = ellipsoid_shell(inner, outer, target_tets).to_quadratic();
    curve_shell_edges(&mut mesh, &[("INNER", inner), ("OUTER", outer)], None);
    mesh
}

/// [`sphere_shell`] with curved quadratic elements (see [`lv_shell_quadratic`]).
///
/// # Panics
/// As [`sphere_shell`].
pub fn sphere_shell_quadratic(
    inner_radius_m: f64,
    outer_radius_m: f64,
    target_tets: usize,
) -> TetMesh {
    let mut mesh = sphere_shell(inner_radius_m, outer_radius_m, target_tets).to_quadratic();
    curve_shell_edges(
        &mut mesh,
        &[
            ("INNER", DVec3::splat(inner_radius_m)),
            ("OUTER", DVec3::splat(outer_radius_m)),
        ],
        None,
    );
    mesh
}

/// A triangulated hemisphere of radius `radius_m` (m) centred at the origin, dome towards +z,
/// rim in the plane z = 0, with edges of about `edge_m` (m): a surface without tetrahedra for
/// the mass-spring family (Zhang, Payandeh & Dill Figure 12). Rings of nodes at constant polar
/// angle as for the shells above (near-equilateral triangles, about six neighbours at the
/// apex). Surface `SURFACE` (outward oriented), node groups `RIM` (the nodes at z = 0) and
/// `APEX` (the node at (0, 0, radius)).
///
/// # Panics
/// If `radius_m` or `edge_m` is not positive, or `edge_m > radius_m`.
pub fn hemisphere_surface(radius_m: f64, edge_m: f64) -> TetMesh {
    assert!(
        radius_m > 0.0 && edge_m > 0.0 && edge_m <= radius_m,
        "hemisphere radius {radius_m} m, edge {edge_m} m"
    );
    let profile = Profile {
        inner: DVec3::splat(radius_m),
        outer: DVec3::splat(radius_m),
        z_cut: Some(0.0),
    };
    let rings = design_rings(&profile, edge_m);
    let mut start = Vec::with_capacity(rings.len());
    let mut nv = 0;
    for r in &rings {
        start.push(nv);
        nv += r.n;
    }
    let last = rings.len() - 1;
    let meridian = Meridian::new(radius_m, radius_m, PI / 2.0);
    let mut nodes = Vec::with_capacity(nv);
    for (i, ring) in rings.iter().enumerate() {
        // The helpers run from the apex at -z; the dome is mirrored to +z.
        let phi = if i == last {
            PI / 2.0
        } else {
            meridian.phi(ring.sigma)
        };
        let (sin_phi, z) = if i == 0 {
            (0.0, radius_m)
        } else if i == last {
            (1.0, 0.0)
        } else {
            (phi.sin(), radius_m * phi.cos())
        };
        for j in 0..ring.n {
            let theta = TAU * (j as f64 + ring.offset) / ring.n as f64;
            let (s, c) = theta.sin_cos();
            nodes.push(DVec3::new(
                radius_m * sin_phi * c,
                radius_m * sin_phi * s,
                z,
            ));
        }
    }
    // Outward orientation: the normal points away from the centre (the zipper's triangles are
    // not consistently oriented at the pole; the shells take theirs from the tetrahedra).
    let triangles: Vec<[u32; 3]> = zipper(&rings, &start)
        .into_iter()
        .map(|[a, b, c]| {
            let [pa, pb, pc] = [a, b, c].map(|i| nodes[i]);
            let outward = (pb - pa).cross(pc - pa).dot(pa + pb + pc) > 0.0;
            if outward {
                [a as u32, b as u32, c as u32]
            } else {
                [a as u32, c as u32, b as u32]
            }
        })
        .collect();
    let rim = (start[last]..nv).map(|i| i as u32).collect();
    TetMesh {
        nodes,
        tets: Vec::new(),
        tet_edge_nodes: Vec::new(),
        surfaces: vec![SurfaceGroup {
            name: "SURFACE".into(),
            triangles,
        }],
        node_groups: vec![
            NodeGroup {
                name: "RIM".into(),
                nodes: rim,
            },
            NodeGroup {
                name: "APEX".into(),
                nodes: vec![0],
            },
        ],
    }
}

/// Moves the mid-edge nodes of the named surfaces of a quadratic shell (centred at the origin)
/// onto their ellipsoids `x^2 / a^2 + y^2 / b^2 + z^2 / c^2 = 1` (semi-axes `(a, b, c)`), by
/// scaling from the origin; an edge on the cut plane `z = z_cut` is scaled in that plane.
fn curve_shell_edges(mesh: &mut TetMesh, surfaces: &[(&str, DVec3)], z_cut: Option<f64>) {
    use std::collections::HashMap;
    let mut ends: HashMap<u32, [u32; 2]> = HashMap::new();
    for (t, mid) in mesh.tets.iter().zip(&mesh.tet_edge_nodes) {
        for (k, [i, j]) in crate::mesh::TET_EDGES.iter().enumerate() {
            ends.insert(mid[k], [t[*i], t[*j]]);
        }
    }
    for &(name, axes) in surfaces {
        let Some(group) = mesh.surface(name) else {
            continue;
        };
        let mut mids: Vec<u32> = group
            .triangles
            .iter()
            .flatten()
            .copied()
            .filter(|i| ends.contains_key(i))
            .collect();
        mids.sort_unstable();
        mids.dedup();
        for m in mids {
            let [a, b] = ends[&m];
            let (pa, pb) = (mesh.nodes[a as usize], mesh.nodes[b as usize]);
            let p = mesh.nodes[m as usize];
            let on_cut =
                z_cut.is_some_and(|z| (pa.z - z).abs() < 1e-12 && (pb.z - z).abs() < 1e-12);
            let (ax, ay, az) = (axes.x, axes.y, axes.z);
            // Rotationally symmetric shells (a = b) keep the expressions they were built with
            // before ellipsoids with a != b (the same nodes to the last bit).
            mesh.nodes[m as usize] = if on_cut && ax == ay {
                // In the plane: the ring of radius a sqrt(1 - z^2 / c^2).
                let rho = ax * (1.0 - p.z * p.z / (az * az)).max(0.0).sqrt();
                let r = (p.x * p.x + p.y * p.y).sqrt();
                DVec3::new(p.x * rho / r, p.y * rho / r, p.z)
            } else if on_cut {
                // In the plane: the ellipse x^2 / a^2 + y^2 / b^2 = 1 - z^2 / c^2.
                let rim = (1.0 - p.z * p.z / (az * az)).max(0.0);
                let q = (p.x * p.x / (ax * ax) + p.y * p.y / (ay * ay)) / rim;
                DVec3::new(p.x / q.sqrt(), p.y / q.sqrt(), p.z)
            } else if ax == ay {
                let q = (p.x * p.x + p.y * p.y) / (ax * ax) + p.z * p.z / (az * az);
                p / q.sqrt()
            } else {
                let q = p.x * p.x / (ax * ax) + p.y * p.y / (ay * ay) + p.z * p.z / (az * az);
                p / q.sqrt()
            };
        }
    }
}

/// Closed concentric ellipsoidal shell (no cut), centred at the origin, in metres.
///
/// `inner`, `outer`: semi-axes (x, y, z) of the inner and outer ellipsoids, m; intermediate
/// layers interpolate them linearly. `target_tets`: wanted number of tetrahedra (the coarsest
/// construction has about 120; about 188 gives the seed's coarse "Ellipsoids Model").
///
/// Surfaces (outward oriented): `INNER`, `OUTER`, and `POLE`, the subset of `OUTER` triangles
/// around the bottom pole (centroid below `-0.8 outer.z`, or touching the pole node), meant to be
/// clamped so that the body cannot drift. Node groups: `INNER_NZ`, `INNER_PZ`, `OUTER_NZ`,
/// `OUTER_PZ` (pole nodes on the z axis).
///
/// # Panics
/// If a semi-axis is not finite and positive or `inner` is not smaller than `outer` in every
/// component.
pub fn ellipsoid_shell(inner: DVec3, outer: DVec3, target_tets: usize) -> TetMesh {
    assert!(
        inner.is_finite() && inner.min_element() > 0.0 && inner.cmplt(outer).all(),
        "ellipsoid_shell: need 0 < inner < outer, got {inner} and {outer}"
    );
    let profile = Profile {
        inner,
        outer,
        z_cut: None,
    };
    let shell = revolution_shell(&profile, target_tets);
    let mut mesh = shell.classify("INNER", "OUTER", None);
    let pole = shell.node(shell.layers, 0, 0);
    let cap = -0.8 * outer.z;
    let pole_tris: Vec<[u32; 3]> = mesh
        .surface("OUTER")
        .map(|s| {
            s.triangles
                .iter()
                .filter(|t| {
                    let z = t.iter().map(|&i| mesh.nodes[i as usize].z).sum::<f64>() / 3.0;
                    z < cap || t.contains(&pole)
                })
                .copied()
                .collect()
        })
        .unwrap_or_default();
    mesh.surfaces.push(SurfaceGroup {
        name: "POLE".into(),
        triangles: pole_tris,
    });
    mesh.node_groups = shell.pole_groups();
    mesh
}

/// A shell of revolution between the ellipsoids of semi-axes `inner` and `outer` (x, y, z, m),
/// kept below the plane `z = z_cut` when given (the construction of [`lv_shell`] with free
/// axes): the hybrid model's FEM core and outer surface are built with it.
///
/// Surfaces (outward oriented): `INNER`, `OUTER`, and `BASE` when truncated.
///
/// # Panics
/// If a semi-axis is not finite and positive or `inner` is not smaller than `outer` in every
/// component.
pub fn truncated_ellipsoid_shell(
    inner: DVec3,
    outer: DVec3,
    z_cut: Option<f64>,
    target_tets: usize,
) -> TetMesh {
    assert!(
        inner.is_finite() && inner.min_element() > 0.0 && inner.cmplt(outer).all(),
        "truncated_ellipsoid_shell: need 0 < inner < outer, got {inner} and {outer}"
    );
    let profile = Profile {
        inner,
        outer,
        z_cut,
    };
    let shell = revolution_shell(&profile, target_tets);
    shell.classify("INNER", "OUTER", z_cut.map(|_| "BASE"))
}

/// [`truncated_ellipsoid_shell`] with curved quadratic (10-node) elements: the mid-edge nodes
/// on `INNER` and `OUTER` lie on the ellipsoids (see [`lv_shell_quadratic`]); the hybrid
/// model's FEM with `hybrid.inactive_layer = "elements"` and `mesh.order = 2`.
///
/// # Panics
/// As [`truncated_ellipsoid_shell`].
pub fn truncated_ellipsoid_shell_quadratic(
    inner: DVec3,
    outer: DVec3,
    z_cut: Option<f64>,
    target_tets: usize,
) -> TetMesh {
    let mut mesh = truncated_ellipsoid_shell(inner, outer, z_cut, target_tets).to_quadratic();
    curve_shell_edges(&mut mesh, &[("INNER", inner), ("OUTER", outer)], z_cut);
    mesh
}

/// Thick-walled hollow sphere centred at the origin (the Lamé problem), in metres.
///
/// `inner_radius_m` < `outer_radius_m`, m. `target_tets`: wanted number of tetrahedra (within
/// about 30 % for 1000..=50000).
///
/// Surfaces (outward oriented): `INNER` (normals toward the centre), `OUTER`. Node groups, each a
/// single node exactly on a coordinate axis: `INNER_PZ` (0, 0, r), `INNER_NZ` (0, 0, -r),
/// `INNER_PX` (r, 0, 0) with r the inner radius, and `OUTER_PZ`, `OUTER_NZ`, `OUTER_PX` likewise
/// on the outer surface. Fixing x and y at the z-axis nodes and y at the x-axis node removes the
/// six rigid modes without restraining the radial expansion.
///
/// # Panics
/// If the radii are not finite with `0 < inner_radius_m < outer_radius_m`.
pub fn sphere_shell(inner_radius_m: f64, outer_radius_m: f64, target_tets: usize) -> TetMesh {
    assert!(
        inner_radius_m.is_finite()
            && inner_radius_m > 0.0
            && outer_radius_m.is_finite()
            && inner_radius_m < outer_radius_m,
        "sphere_shell: need 0 < inner < outer, got {inner_radius_m} and {outer_radius_m}"
    );
    let profile = Profile {
        inner: DVec3::splat(inner_radius_m),
        outer: DVec3::splat(outer_radius_m),
        z_cut: None,
    };
    let shell = revolution_shell(&profile, target_tets);
    let mut mesh = shell.classify("INNER", "OUTER", None);
    let mut groups = shell.pole_groups();
    let eq = shell.rings.len() / 2;
    debug_assert!(shell.rings[eq].offset == 0.0 && 2 * eq + 1 == shell.rings.len());
    groups.push(NodeGroup {
        name: "INNER_PX".into(),
        nodes: vec![shell.node(0, eq, 0)],
    });
    groups.push(NodeGroup {
        name: "OUTER_PX".into(),
        nodes: vec![shell.node(shell.layers, eq, 0)],
    });
    mesh.node_groups = groups;
    mesh
}

/// Axis-aligned box `[0, size.x] x [0, size.y] x [0, size.z]` (m) of `cells[0] x cells[1] x
/// cells[2]` hexahedra, each split into 6 tetrahedra along its main diagonal (Kuhn / Freudenthal
/// subdivision, conforming on the grid): `6 * nx * ny * nz` tets, `(nx+1)(ny+1)(nz+1)` nodes,
/// node `(i, j, k)` at index `i + (nx+1) (j + (ny+1) k)`.
///
/// Surfaces (outward oriented): `XMIN`, `XMAX`, `YMIN`, `YMAX`, `ZMIN`, `ZMAX`.
///
/// # Panics
/// If a size is not finite and positive or a cell count is zero.
pub fn box_mesh(size_m: DVec3, cells: [usize; 3]) -> TetMesh {
    assert!(
        size_m.is_finite() && size_m.min_element() > 0.0 && cells.iter().all(|&c| c > 0),
        "box_mesh: need positive sizes and cell counts, got {size_m} and {cells:?}"
    );
    let axis = |n: usize, s: f64| -> Vec<f64> {
        (0..=n)
            .map(|i| if i == n { s } else { s * (i as f64 / n as f64) })
            .collect()
    };
    box_mesh_graded(
        &axis(cells[0], size_m.x),
        &axis(cells[1], size_m.y),
        &axis(cells[2], size_m.z),
    )
}

/// Grid coordinates from 0 to `length_m`: cells of `fine_m` up to `fine_extent_m`, then cells
/// growing geometrically by `ratio` (a last cell shorter than its predecessor is merged into
/// it). For locally refined boxes ([`box_mesh_graded`]): a contact zone resolved finely, a far
/// field coarse.
///
/// # Panics
/// If the lengths are not finite and positive with `fine_m <= length_m`, or `ratio < 1`.
pub fn graded_coordinates(fine_m: f64, fine_extent_m: f64, ratio: f64, length_m: f64) -> Vec<f64> {
    assert!(
        fine_m > 0.0 && fine_m <= length_m && length_m.is_finite() && ratio >= 1.0,
        "graded_coordinates: need 0 < fine <= length and ratio >= 1"
    );
    let mut xs = vec![0.0];
    let mut h = fine_m;
    let mut x = 0.0;
    loop {
        if x + h >= length_m - 1e-9 * length_m {
            break;
        }
        x += h;
        xs.push(x);
        if x >= fine_extent_m {
            h *= ratio;
        }
    }
    if xs.len() > 1 && length_m - x < 0.5 * h / ratio {
        xs.pop();
    }
    xs.push(length_m);
    xs
}

/// The box of [`box_mesh`] on a tensor grid with the given node coordinates per axis
/// (ascending, at least two each, m): the box spans `[xs[0], xs.last()]` and so on, and the
/// surfaces are named as in [`box_mesh`].
///
/// # Panics
/// If an axis has fewer than two coordinates or is not strictly increasing and finite.
pub fn box_mesh_graded(xs: &[f64], ys: &[f64], zs: &[f64]) -> TetMesh {
    for a in [xs, ys, zs] {
        assert!(
            a.len() >= 2 && a.windows(2).all(|w| w[1] > w[0]) && a.iter().all(|v| v.is_finite()),
            "box_mesh_graded: each axis needs two or more increasing finite coordinates"
        );
    }
    let [nx, ny, nz] = [xs.len() - 1, ys.len() - 1, zs.len() - 1];
    let id = |i: usize, j: usize, k: usize| (i + (nx + 1) * (j + (ny + 1) * k)) as u32;
    let mut nodes = Vec::with_capacity((nx + 1) * (ny + 1) * (nz + 1));
    for &z in zs {
        for &y in ys {
            for &x in xs {
                nodes.push(DVec3::new(x, y, z));
            }
        }
    }
    const PERMS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut tets = Vec::with_capacity(6 * nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                for p in PERMS {
                    let mut c = [i, j, k];
                    let mut t = [id(c[0], c[1], c[2]), 0, 0, 0];
                    for (s, &axis) in p.iter().enumerate() {
                        c[axis] += 1;
                        t[s + 1] = id(c[0], c[1], c[2]);
                    }
                    tets.push(t);
                }
            }
        }
    }
    let mut mesh = TetMesh {
        nodes,
        tets,
        tet_edge_nodes: Vec::new(),
        surfaces: Vec::new(),
        node_groups: Vec::new(),
    };
    orient(&mut mesh);
    let boundary = mesh.boundary_triangles();
    let names = ["XMIN", "XMAX", "YMIN", "YMAX", "ZMIN", "ZMAX"];
    let mut surfaces: Vec<SurfaceGroup> = names
        .iter()
        .map(|n| SurfaceGroup {
            name: (*n).into(),
            triangles: Vec::new(),
        })
        .collect();
    let lo = DVec3::new(xs[0], ys[0], zs[0]);
    let hi = DVec3::new(xs[nx], ys[ny], zs[nz]);
    for t in boundary {
        let p = t.map(|i| mesh.nodes[i as usize]);
        for axis in 0..3 {
            if p.iter().all(|q| q[axis] == lo[axis]) {
                surfaces[2 * axis].triangles.push(t);
            } else if p.iter().all(|q| q[axis] == hi[axis]) {
                surfaces[2 * axis + 1].triangles.push(t);
            }
        }
    }
    mesh.surfaces = surfaces;
    mesh
}

/// Smallest dihedral angle over all tetrahedra of `mesh`, degrees (a quality measure: slivers
/// have angles near 0; the regular tetrahedron has 70.5). Returns 180 for an empty mesh.
pub fn min_dihedral_angle_deg(mesh: &TetMesh) -> f64 {
    let mut min = PI;
    for t in &mesh.tets {
        let x = t.map(|i| mesh.nodes[i as usize]);
        // Outward unit normal of the face opposite each vertex.
        let normals: [DVec3; 4] = std::array::from_fn(|k| {
            let f: Vec<DVec3> = (0..4).filter(|&i| i != k).map(|i| x[i]).collect();
            let n = (f[1] - f[0]).cross(f[2] - f[0]).normalize_or_zero();
            if n.dot(x[k] - f[0]) > 0.0 { -n } else { n }
        });
        for a in 0..4 {
            for b in a + 1..4 {
                let angle = PI - normals[a].dot(normals[b]).clamp(-1.0, 1.0).acos();
                min = min.min(angle);
            }
        }
    }
    min.to_degrees()
}

/// A shell of revolution between two concentric ellipsoids (semi-axes x, y, z), optionally
/// truncated by the plane `z = z_cut` (keeping `z <= z_cut`).
struct Profile {
    inner: DVec3,
    outer: DVec3,
    z_cut: Option<f64>,
}

impl Profile {
    /// Semi-axes of the layer at transmural coordinate `t` in [0, 1].
    fn axes(&self, t: f64) -> DVec3 {
        if t == 0.0 {
            self.inner
        } else if t == 1.0 {
            self.outer
        } else {
            self.inner + (self.outer - self.inner) * t
        }
    }

    /// Eccentric-anomaly angle (from the -z apex) where the meridian ends.
    fn phi_end(&self, c: f64) -> f64 {
        match self.z_cut {
            Some(z) => (-z / c).acos(),
            None => PI,
        }
    }

    /// Mean wall thickness, m.
    fn thickness(&self) -> f64 {
        let d = self.outer - self.inner;
        (d.x + d.y + d.z) / 3.0
    }
}

/// Cumulative arc length of a meridian ellipse `(a sin phi, -c cos phi)` on a uniform phi grid.
struct Meridian {
    phi_end: f64,
    s: Vec<f64>,
}

impl Meridian {
    const SAMPLES: usize = 4096;

    fn new(a: f64, c: f64, phi_end: f64) -> Self {
        let m = Self::SAMPLES;
        let speed = |phi: f64| (a * a * phi.cos().powi(2) + c * c * phi.sin().powi(2)).sqrt();
        let dphi = phi_end / m as f64;
        let mut s = Vec::with_capacity(m + 1);
        s.push(0.0);
        for k in 0..m {
            let p0 = k as f64 * dphi;
            // Simpson on each interval.
            let ds = dphi / 6.0 * (speed(p0) + 4.0 * speed(p0 + 0.5 * dphi) + speed(p0 + dphi));
            s.push(s[k] + ds);
        }
        Self { phi_end, s }
    }

    fn length(&self) -> f64 {
        self.s[Self::SAMPLES]
    }

    /// The angle phi at arc-length fraction `sigma` in [0, 1].
    fn phi(&self, sigma: f64) -> f64 {
        if sigma <= 0.0 {
            return 0.0;
        }
        if sigma >= 1.0 {
            return self.phi_end;
        }
        let target = sigma * self.length();
        let k = self
            .s
            .partition_point(|&v| v <= target)
            .clamp(1, Self::SAMPLES)
            - 1;
        let f = (target - self.s[k]) / (self.s[k + 1] - self.s[k]);
        (k as f64 + f) * self.phi_end / Self::SAMPLES as f64
    }
}

/// One ring of the reference surface.
#[derive(Debug, Clone, Copy)]
struct Ring {
    /// Meridian arc-length fraction.
    sigma: f64,
    /// Number of vertices (1 for a pole).
    n: usize,
    /// Angular offset of vertex 0 as a fraction of the vertex spacing.
    offset: f64,
}

/// A built shell before its boundary is classified.
struct Shell {
    mesh: TetMesh,
    rings: Vec<Ring>,
    /// First surface-vertex index of each ring.
    ring_start: Vec<usize>,
    /// Vertices per layer.
    nv: usize,
    /// Number of layers of prisms (L); node layers are 0..=L.
    layers: usize,
    truncated: bool,
}

impl Shell {
    /// Global node index of vertex `j` of ring `i` in node layer `k`.
    fn node(&self, k: usize, i: usize, j: usize) -> u32 {
        (k * self.nv + self.ring_start[i] + j) as u32
    }

    /// Splits the boundary into inner, outer and (truncated shells) base surfaces.
    fn classify(&self, inner: &str, outer: &str, base: Option<&str>) -> TetMesh {
        let mut mesh = self.mesh.clone();
        let last_ring_start = self.ring_start[self.rings.len() - 1];
        let mut groups = [inner, outer, base.unwrap_or("BASE")].map(|n| SurfaceGroup {
            name: n.to_string(),
            triangles: Vec::new(),
        });
        for t in mesh.boundary_triangles() {
            let layer = t.map(|i| i as usize / self.nv);
            let vertex = t.map(|i| i as usize % self.nv);
            if layer.iter().all(|&k| k == 0) {
                groups[0].triangles.push(t);
            } else if layer.iter().all(|&k| k == self.layers) {
                groups[1].triangles.push(t);
            } else if self.truncated && vertex.iter().all(|&v| v >= last_ring_start) {
                groups[2].triangles.push(t);
            } else {
                unreachable!("boundary face {t:?} is on no named surface");
            }
        }
        let [g0, g1, g2] = groups;
        mesh.surfaces = if base.is_some() {
            vec![g0, g1, g2]
        } else {
            vec![g0, g1]
        };
        mesh
    }

    /// `INNER_NZ`, `INNER_PZ`, `OUTER_NZ`, `OUTER_PZ` for a closed shell.
    fn pole_groups(&self) -> Vec<NodeGroup> {
        let top = self.rings.len() - 1;
        let g = |name: &str, node: u32| NodeGroup {
            name: name.into(),
            nodes: vec![node],
        };
        vec![
            g("INNER_NZ", self.node(0, 0, 0)),
            g("INNER_PZ", self.node(0, top, 0)),
            g("OUTER_NZ", self.node(self.layers, 0, 0)),
            g("OUTER_PZ", self.node(self.layers, top, 0)),
        ]
    }
}

/// Ring layout for a target edge length `h` on the mid-wall layer.
fn design_rings(p: &Profile, h: f64) -> Vec<Ring> {
    let mid = p.axes(0.5);
    let a = 0.5 * (mid.x + mid.y);
    let meridian = Meridian::new(a, mid.z, p.phi_end(mid.z));
    let closed = p.z_cut.is_none();
    let mut r = ((meridian.length() / h).round() as usize).max(2);
    if closed && r & 1 == 1 {
        r += 1;
    }
    let half = r / 2;
    // Mean radius of the ring's ellipse (x, y semi-axes).
    let radius = ((mid.x * mid.x + mid.y * mid.y) / 2.0).sqrt();
    (0..=r)
        .map(|i| {
            let sigma = i as f64 / r as f64;
            let pole = i == 0 || (closed && i == r);
            let n = if pole {
                1
            } else {
                let phi = if closed && 2 * i == r {
                    PI / 2.0
                } else {
                    meridian.phi(sigma)
                };
                ((TAU * radius * phi.sin() / h).round() as usize).max(3)
            };
            // Alternate half-spacing offsets; the equator ring of a closed shell has offset 0 so
            // that it holds nodes on the +x axis.
            let offset = if (i + half) & 1 == 0 { 0.0 } else { 0.5 };
            Ring { sigma, n, offset }
        })
        .collect()
}

/// Triangles of the reference surface joining consecutive rings (surface-vertex indices).
fn zipper(rings: &[Ring], start: &[usize]) -> Vec<[usize; 3]> {
    let mut tris = Vec::new();
    for i in 0..rings.len() - 1 {
        let (lo, up) = (rings[i], rings[i + 1]);
        let l = |p: usize| start[i] + p % lo.n;
        let u = |q: usize| start[i + 1] + q % up.n;
        if lo.n == 1 {
            tris.extend((0..up.n).map(|q| [l(0), u(q), u(q + 1)]));
        } else if up.n == 1 {
            tris.extend((0..lo.n).map(|p| [l(p), l(p + 1), u(0)]));
        } else {
            let alpha = |p: usize| (p as f64 + lo.offset) / lo.n as f64;
            let beta = |q: usize| (q as f64 + up.offset) / up.n as f64;
            let (mut p, mut q) = (0, 0);
            while p < lo.n || q < up.n {
                if q == up.n || (p < lo.n && alpha(p + 1) < beta(q + 1)) {
                    tris.push([l(p), l(p + 1), u(q)]);
                    p += 1;
                } else {
                    tris.push([l(p), u(q + 1), u(q)]);
                    q += 1;
                }
            }
        }
    }
    tris
}

/// Number of surface triangles of a ring layout.
fn triangle_count(rings: &[Ring]) -> usize {
    rings
        .windows(2)
        .map(|w| match (w[0].n, w[1].n) {
            (1, m) => m,
            (n, 1) => n,
            (n, m) => n + m,
        })
        .sum()
}

/// Number of prism layers for an edge length `h`.
fn layer_count(p: &Profile, h: f64) -> usize {
    ((p.thickness() / h).round() as usize).max(1)
}

/// Builds the tetrahedral shell closest to `target_tets`.
fn revolution_shell(p: &Profile, target_tets: usize) -> Shell {
    // Tets = 3 L T; pick h by scanning around the estimate from the volume.
    let mid = p.axes(0.5);
    let area_estimate = 4.0 * PI * (mid.x * mid.y + mid.y * mid.z + mid.z * mid.x) / 3.0;
    let volume_estimate = area_estimate * p.thickness();
    let target = target_tets.max(1) as f64;
    // Prism volume ~ (sqrt 3 / 4) h^3 when its height is h.
    let h0 = (volume_estimate * 3.0 / (target * 3f64.sqrt() / 4.0)).cbrt();
    // Score: distance to the target count (log scale) plus a small penalty on the prism aspect
    // (layer height over edge length) departing from 1.
    let mut best: Option<(f64, f64, usize)> = None;
    for s in -60..=60 {
        let h = h0 * 1.015f64.powi(s);
        let tris = triangle_count(&design_rings(p, h));
        let l0 = layer_count(p, h);
        for layers in l0.saturating_sub(1).max(1)..=l0 + 1 {
            let aspect = p.thickness() / layers as f64 / h;
            if !(0.6..=1.7).contains(&aspect) && layers != l0 {
                continue;
            }
            let count = 3 * layers * tris;
            let score = (count as f64 / target).ln().abs() + 0.1 * aspect.ln().abs();
            if best.is_none_or(|(e, _, _)| score < e) {
                best = Some((score, h, layers));
            }
        }
    }
    let (_, h, layers) = best.unwrap_or((0.0, h0, layer_count(p, h0)));
    build_shell(p, design_rings(p, h), layers)
}

/// Extrudes the ring surface through `layers` layers and splits the prisms into tetrahedra.
fn build_shell(p: &Profile, rings: Vec<Ring>, layers: usize) -> Shell {
    let mut start = Vec::with_capacity(rings.len());
    let mut nv = 0;
    for r in &rings {
        start.push(nv);
        nv += r.n;
    }
    let closed = p.z_cut.is_none();
    let last = rings.len() - 1;
    let mut nodes = Vec::with_capacity(nv * (layers + 1));
    for k in 0..=layers {
        let t = k as f64 / layers as f64;
        let ax = p.axes(t);
        let c = ax.z;
        let meridian = Meridian::new(0.5 * (ax.x + ax.y), c, p.phi_end(c));
        for (i, ring) in rings.iter().enumerate() {
            // (sin phi, z) of the ring on this layer, with exact values at special rings.
            let (sin_phi, z) = if i == 0 {
                (0.0, -c)
            } else if i == last && closed {
                (0.0, c)
            } else if i == last {
                let z = p.z_cut.unwrap_or(c);
                ((1.0 - (z / c) * (z / c)).sqrt(), z)
            } else if closed && 2 * i == last {
                (1.0, 0.0)
            } else {
                let phi = meridian.phi(ring.sigma);
                (phi.sin(), -c * phi.cos())
            };
            for j in 0..ring.n {
                let theta = TAU * (j as f64 + ring.offset) / ring.n as f64;
                let (s, co) = if theta == 0.0 {
                    (0.0, 1.0)
                } else {
                    theta.sin_cos()
                };
                nodes.push(DVec3::new(ax.x * sin_phi * co, ax.y * sin_phi * s, z));
            }
        }
    }
    let surface = zipper(&rings, &start);
    let mut tets = Vec::with_capacity(3 * layers * surface.len());
    for k in 0..layers {
        for tri in &surface {
            let b = tri.map(|v| (k * nv + v) as u32);
            let prism = [
                b[0],
                b[1],
                b[2],
                b[0] + nv as u32,
                b[1] + nv as u32,
                b[2] + nv as u32,
            ];
            tets.extend(split_prism(prism));
        }
    }
    let mut mesh = TetMesh {
        nodes,
        tets,
        tet_edge_nodes: Vec::new(),
        surfaces: Vec::new(),
        node_groups: Vec::new(),
    };
    orient(&mut mesh);
    Shell {
        mesh,
        rings,
        ring_start: start,
        nv,
        layers,
        truncated: !closed,
    }
}

/// Splits the prism `[a, b, c, a', b', c']` (bottom triangle, then the top vertices above
/// them) into 3 tetrahedra so that each quadrilateral face is cut by the diagonal from its
/// lowest index (Dompierre et al. 1999, table 3). Orientation is fixed later.
fn split_prism(v: [u32; 6]) -> [[u32; 4]; 3] {
    // Vertex permutations that bring each vertex to position 0 while preserving the prism.
    const ROT: [[usize; 6]; 6] = [
        [0, 1, 2, 3, 4, 5],
        [1, 2, 0, 4, 5, 3],
        [2, 0, 1, 5, 3, 4],
        [3, 5, 4, 0, 2, 1],
        [4, 3, 5, 1, 0, 2],
        [5, 4, 3, 2, 1, 0],
    ];
    let imin = (0..6).min_by_key(|&i| v[i]).unwrap_or(0);
    let w = ROT[imin].map(|i| v[i]);
    if w[1].min(w[5]) < w[2].min(w[4]) {
        [
            [w[0], w[1], w[2], w[5]],
            [w[0], w[1], w[5], w[4]],
            [w[0], w[4], w[5], w[3]],
        ]
    } else {
        [
            [w[0], w[1], w[2], w[4]],
            [w[0], w[4], w[2], w[5]],
            [w[0], w[4], w[5], w[3]],
        ]
    }
}

/// Makes every tetrahedron positively oriented.
fn orient(mesh: &mut TetMesh) {
    for t in &mut mesh.tets {
        let [a, b, c, d] = t.map(|i| mesh.nodes[i as usize]);
        if tet_signed_volume(a, b, c, d) < 0.0 {
            t.swap(2, 3);
        }
    }
}
