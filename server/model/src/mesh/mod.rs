//! Tetrahedral meshes (linear 4-node, or quadratic 10-node with mid-edge nodes) with named
//! boundary surfaces and node groups.
//!
//! Owns: mesh data and everything that reads or writes meshes: [`gmsh`] (Gmsh `.msh` 2.2 /
//! 4.1 ASCII reader), [`generate`] (structured shells and boxes built in code),
//! [`quadratic`](TetMesh::to_quadratic) (10-node elements from a linear mesh), [`export`] (CSV
//! node tables, ParaView `.vtu`).
//! May use: nothing of the crate but [`crate::ModelError`]. Used by [`crate::element`]
//! (precomputes element data) and [`crate::scene`] (picks clamped and touchable surfaces by
//! name).

use glam::DVec3;

use crate::ModelError;

pub mod export;
pub mod generate;
pub mod gmsh;
mod quadratic;

/// A named set of boundary triangles (a Gmsh 2-D physical group or a mesher-made surface).
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceGroup {
    /// Name (e.g. `EPI`, `ENDO`, `BASE`).
    pub name: String,
    /// Triangles as node indices, ordered counter-clockwise seen from outside the body
    /// (so `(b - a) x (c - a)` is the outward normal).
    pub triangles: Vec<[u32; 3]>,
}

/// A named set of nodes (a Gmsh 0-D or 1-D physical group, or a mesher-made set).
#[derive(Debug, Clone, PartialEq)]
pub struct NodeGroup {
    /// Name (e.g. `EPIPT`).
    pub name: String,
    /// Node indices.
    pub nodes: Vec<u32>,
}

/// A tetrahedral mesh in SI units (metres): linear (4-node) tetrahedra, or quadratic (10-node)
/// ones when [`TetMesh::tet_edge_nodes`] is not empty.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TetMesh {
    /// Rest positions of the nodes, m. Length N.
    pub nodes: Vec<DVec3>,
    /// Tetrahedra as node indices (the corners), positively oriented:
    /// `(x1-x0) . ((x2-x0) x (x3-x0)) > 0`.
    pub tets: Vec<[u32; 4]>,
    /// Mid-edge nodes of quadratic (10-node) tetrahedra, one row per entry of `tets`, in the VTK
    /// order of edges `(0,1), (1,2), (2,0), (0,3), (1,3), (2,3)` of the corners. Empty for a
    /// linear mesh. The surface groups of a quadratic mesh are split into four triangles per
    /// face (corners and mid-edge nodes), so contact, pressure and display see every node.
    pub tet_edge_nodes: Vec<[u32; 6]>,
    /// Named boundary surfaces.
    pub surfaces: Vec<SurfaceGroup>,
    /// Named node sets.
    pub node_groups: Vec<NodeGroup>,
}

/// Corner pairs of the six edges of a tetrahedron, in the VTK order of the mid-edge nodes of
/// [`TetMesh::tet_edge_nodes`].
pub const TET_EDGES: [[usize; 2]; 6] = [[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]];

/// The four triangles of triangle `(a, b, c)` split at its mid-edge nodes `m_ab, m_bc, m_ca`,
/// with the orientation of `(a, b, c)`.
pub fn split_triangle(t: [u32; 3], m_ab: u32, m_bc: u32, m_ca: u32) -> [[u32; 3]; 4] {
    let [a, b, c] = t;
    [
        [a, m_ab, m_ca],
        [m_ab, b, m_bc],
        [m_ca, m_bc, c],
        [m_ab, m_bc, m_ca],
    ]
}

/// Signed volume of the tetrahedron `(a, b, c, d)`, m^3 (seed 000 eq. 17). Positive when
/// `(b-a) . ((c-a) x (d-a)) > 0`.
#[inline]
pub fn tet_signed_volume(a: DVec3, b: DVec3, c: DVec3, d: DVec3) -> f64 {
    (b - a).dot((c - a).cross(d - a)) / 6.0
}

impl TetMesh {
    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Number of tetrahedra.
    pub fn tet_count(&self) -> usize {
        self.tets.len()
    }

    /// Whether the tetrahedra are quadratic (10-node).
    pub fn is_quadratic(&self) -> bool {
        !self.tet_edge_nodes.is_empty()
    }

    /// Current over rest volume of each tetrahedron (of the corner tetrahedron for quadratic
    /// elements), one per entry of `tets`: 1 undeformed, negative for an inverted element.
    /// `x` holds the current positions, one per node, m.
    pub fn volume_ratios(&self, x: &[DVec3]) -> Vec<f64> {
        self.tets
            .iter()
            .map(|t| {
                let [a, b, c, d] = t.map(|i| i as usize);
                let cur = tet_signed_volume(x[a], x[b], x[c], x[d]);
                let rest =
                    tet_signed_volume(self.nodes[a], self.nodes[b], self.nodes[c], self.nodes[d]);
                cur / rest
            })
            .collect()
    }

    /// The surface group called `name`, if any.
    pub fn surface(&self, name: &str) -> Option<&SurfaceGroup> {
        self.surfaces.iter().find(|s| s.name == name)
    }

    /// The node group called `name`, if any.
    pub fn node_group(&self, name: &str) -> Option<&NodeGroup> {
        self.node_groups.iter().find(|g| g.name == name)
    }

    /// Total rest volume, m^3.
    pub fn volume(&self) -> f64 {
        self.tets
            .iter()
            .map(|t| {
                let [a, b, c, d] = t.map(|i| self.nodes[i as usize]);
                tet_signed_volume(a, b, c, d)
            })
            .sum()
    }

    /// Scales every coordinate by `factor` (e.g. 1e-3 for a mesh in mm).
    pub fn scale(&mut self, factor: f64) {
        for p in &mut self.nodes {
            *p *= factor;
        }
    }

    /// Reorders the nodes of negatively oriented tetrahedra so that all are positive.
    ///
    /// # Errors
    /// [`ModelError::InvalidMesh`] if a tetrahedron is degenerate (|volume| below 1e-12 of the
    /// bounding-box volume) or an index is out of range.
    pub fn orient_and_check(&mut self) -> Result<(), ModelError> {
        if self.tets.is_empty() {
            return Err(ModelError::InvalidMesh("the mesh has no tetrahedra".into()));
        }
        let n = self.nodes.len() as u32;
        let (lo, hi) = self.bounding_box();
        let scale = (hi - lo).max_element().powi(3).max(f64::MIN_POSITIVE);
        for (k, t) in self.tets.iter_mut().enumerate() {
            if let Some(bad) = t.iter().find(|&&i| i >= n) {
                return Err(ModelError::InvalidMesh(format!(
                    "tetrahedron {k} references node {bad} but the mesh has {n} nodes"
                )));
            }
            let [a, b, c, d] = t.map(|i| self.nodes[i as usize]);
            let v = tet_signed_volume(a, b, c, d);
            if !(v.abs() > 1e-12 * scale) {
                return Err(ModelError::InvalidMesh(format!(
                    "tetrahedron {k} {t:?} is degenerate (volume {v:.3e} m^3)"
                )));
            }
            if v < 0.0 {
                t.swap(2, 3);
                // Swapping corners 2 and 3 maps the edges (1,2) <-> (1,3) and (2,0) <-> (0,3).
                if let Some(e) = self.tet_edge_nodes.get_mut(k) {
                    e.swap(1, 4);
                    e.swap(2, 3);
                }
            }
        }
        if !self.tet_edge_nodes.is_empty() {
            if self.tet_edge_nodes.len() != self.tets.len() {
                return Err(ModelError::InvalidMesh(format!(
                    "{} rows of mid-edge nodes for {} tetrahedra",
                    self.tet_edge_nodes.len(),
                    self.tets.len()
                )));
            }
            if let Some(bad) = self.tet_edge_nodes.iter().flatten().find(|&&i| i >= n) {
                return Err(ModelError::InvalidMesh(format!(
                    "a mid-edge node {bad} is out of range (the mesh has {n} nodes)"
                )));
            }
        }
        Ok(())
    }

    /// Axis-aligned bounding box `(min, max)` of the nodes, m.
    pub fn bounding_box(&self) -> (DVec3, DVec3) {
        self.nodes.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        )
    }

    /// The longest corner-to-corner edge of any tetrahedron, m (0 without tetrahedra).
    pub fn longest_edge_m(&self) -> f64 {
        self.tets
            .iter()
            .flat_map(|t| {
                TET_EDGES
                    .iter()
                    .map(|&[a, b]| self.nodes[t[a] as usize].distance(self.nodes[t[b] as usize]))
            })
            .fold(0.0, f64::max)
    }

    /// All boundary faces of the tetrahedral mesh (faces used by exactly one tetrahedron),
    /// oriented with outward normals. Requires positively oriented tetrahedra. For a quadratic
    /// mesh each face is split into four triangles at its mid-edge nodes.
    pub fn boundary_triangles(&self) -> Vec<[u32; 3]> {
        use std::collections::HashMap;
        // Faces of a positive tet (a,b,c,d) with outward normals.
        const FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];
        // Index of the mid-edge node of corners (i, j) in `TET_EDGES`.
        let edge_slot = |i: usize, j: usize| {
            TET_EDGES
                .iter()
                .position(|&[a, b]| (a, b) == (i, j) || (a, b) == (j, i))
                .expect("tet edge")
        };
        // Sorted face -> (oriented face, element, local corners, use count).
        type FaceUse = ([u32; 3], usize, [usize; 3], u32);
        let mut count: HashMap<[u32; 3], FaceUse> = HashMap::new();
        for (e, t) in self.tets.iter().enumerate() {
            for f in FACES {
                let tri = [t[f[0]], t[f[1]], t[f[2]]];
                let mut key = tri;
                key.sort_unstable();
                count
                    .entry(key)
                    .and_modify(|c| c.3 += 1)
                    .or_insert((tri, e, f, 1));
            }
        }
        let mut out: Vec<[u32; 3]> = count
            .into_values()
            .filter(|c| c.3 == 1)
            .flat_map(|(tri, e, f, _)| {
                if self.tet_edge_nodes.is_empty() {
                    vec![tri]
                } else {
                    let m = &self.tet_edge_nodes[e];
                    let mid = |i: usize, j: usize| m[edge_slot(f[i], f[j])];
                    split_triangle(tri, mid(0, 1), mid(1, 2), mid(2, 0)).to_vec()
                }
            })
            .collect();
        out.sort_unstable();
        out
    }

    /// Re-orients each triangle of every surface group to agree with the outward orientation of
    /// the boundary faces of the tetrahedra (Gmsh surface elements may be oriented either way).
    /// Triangles that are not boundary faces are left as they are.
    pub fn orient_surfaces_outward(&mut self) {
        use std::collections::HashMap;
        let outward: HashMap<[u32; 3], [u32; 3]> = self
            .boundary_triangles()
            .into_iter()
            .map(|t| {
                let mut k = t;
                k.sort_unstable();
                (k, t)
            })
            .collect();
        for s in &mut self.surfaces {
            for tri in &mut s.triangles {
                let mut k = *tri;
                k.sort_unstable();
                if let Some(o) = outward.get(&k) {
                    *tri = *o;
                }
            }
        }
    }

    /// The distinct nodes of the named surfaces, sorted.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] naming `field` if a surface name is unknown.
    pub fn nodes_of_surfaces(&self, names: &[String], field: &str) -> Result<Vec<u32>, ModelError> {
        let mut nodes = Vec::new();
        for name in names {
            if let Some(s) = self.surface(name) {
                nodes.extend(s.triangles.iter().flatten().copied());
            } else if let Some(g) = self.node_group(name) {
                nodes.extend(g.nodes.iter().copied());
            } else {
                return Err(ModelError::field(
                    field,
                    format!(
                        "no surface or node group named `{name}` (mesh has: {})",
                        self.group_names()
                    ),
                ));
            }
        }
        nodes.sort_unstable();
        nodes.dedup();
        Ok(nodes)
    }

    /// Comma-separated names of all surface and node groups, for error messages.
    pub fn group_names(&self) -> String {
        self.surfaces
            .iter()
            .map(|s| s.name.as_str())
            .chain(self.node_groups.iter().map(|g| g.name.as_str()))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform scaling by s multiplies every volume by s^3; a reflection inverts every element.
    #[test]
    fn volume_ratios_of_a_scaled_and_a_mirrored_box() {
        let mesh = generate::box_mesh(DVec3::new(1.0, 2.0, 3.0), [2, 1, 1]);
        let scaled: Vec<DVec3> = mesh.nodes.iter().map(|p| *p * 1.5).collect();
        let ratios = mesh.volume_ratios(&scaled);
        assert_eq!(ratios.len(), mesh.tets.len());
        assert!(
            ratios.iter().all(|r| (r - 3.375).abs() < 1e-12),
            "{ratios:?}"
        );
        let mirrored: Vec<DVec3> = mesh
            .nodes
            .iter()
            .map(|p| p * DVec3::new(-1.0, 1.0, 1.0))
            .collect();
        let ratios = mesh.volume_ratios(&mirrored);
        assert!(ratios.iter().all(|r| (r + 1.0).abs() < 1e-12), "{ratios:?}");
    }
}
