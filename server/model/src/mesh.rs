//! Linear tetrahedral meshes with named boundary surfaces and node groups.
//!
//! Neighbours: [`crate::gmsh`] and [`crate::mesher`] produce a [`TetMesh`]; [`crate::fem`]
//! precomputes element data from it; [`crate::scene`] picks clamped and touchable surfaces by name.

use glam::DVec3;

use crate::ModelError;

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

/// A linear tetrahedral mesh in SI units (metres).
#[derive(Debug, Clone, PartialEq)]
pub struct TetMesh {
    /// Rest positions of the nodes, m. Length N.
    pub nodes: Vec<DVec3>,
    /// Tetrahedra as node indices, positively oriented: `(x1-x0) . ((x2-x0) x (x3-x0)) > 0`.
    pub tets: Vec<[u32; 4]>,
    /// Named boundary surfaces.
    pub surfaces: Vec<SurfaceGroup>,
    /// Named node sets.
    pub node_groups: Vec<NodeGroup>,
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

    /// All boundary faces of the tetrahedral mesh (faces used by exactly one tetrahedron),
    /// oriented with outward normals. Requires positively oriented tetrahedra.
    pub fn boundary_triangles(&self) -> Vec<[u32; 3]> {
        use std::collections::HashMap;
        // Faces of a positive tet (a,b,c,d) with outward normals.
        const FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];
        let mut count: HashMap<[u32; 3], ([u32; 3], u32)> = HashMap::new();
        for t in &self.tets {
            for f in FACES {
                let tri = [t[f[0]], t[f[1]], t[f[2]]];
                let mut key = tri;
                key.sort_unstable();
                count
                    .entry(key)
                    .and_modify(|e| e.1 += 1)
                    .or_insert((tri, 1));
            }
        }
        let mut out: Vec<[u32; 3]> = count
            .into_values()
            .filter(|&(_, c)| c == 1)
            .map(|(t, _)| t)
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
