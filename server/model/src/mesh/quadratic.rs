//! Quadratic (10-node) tetrahedra from a linear mesh: a node at every edge midpoint, surfaces
//! split four ways, so that contact, pressure and display see every node.
//!
//! Neighbours: [`super::TetMesh`]; [`crate::element`] builds the 10-node elements on the result.

use std::collections::HashMap;

use glam::DVec3;

use super::{SurfaceGroup, TET_EDGES, TetMesh, split_triangle};

impl TetMesh {
    /// The quadratic (10-node) version of a linear mesh: one new node at the midpoint of every
    /// edge (straight-sided elements, so the rest geometry is unchanged), the surface groups
    /// split into four triangles per face, node groups kept. A quadratic mesh is returned as it
    /// is.
    pub fn to_quadratic(&self) -> TetMesh {
        if self.is_quadratic() {
            return self.clone();
        }
        let mut nodes = self.nodes.clone();
        let mut edge_node: HashMap<(u32, u32), u32> = HashMap::new();
        let mut mid = |a: u32, b: u32, nodes: &mut Vec<DVec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *edge_node.entry(key).or_insert_with(|| {
                nodes.push((nodes[a as usize] + nodes[b as usize]) * 0.5);
                (nodes.len() - 1) as u32
            })
        };
        let tet_edge_nodes: Vec<[u32; 6]> = self
            .tets
            .iter()
            .map(|t| TET_EDGES.map(|[i, j]| mid(t[i], t[j], &mut nodes)))
            .collect();
        let surfaces = self
            .surfaces
            .iter()
            .map(|s| SurfaceGroup {
                name: s.name.clone(),
                triangles: s
                    .triangles
                    .iter()
                    .flat_map(|&[a, b, c]| {
                        let (ab, bc, ca) = (
                            mid(a, b, &mut nodes),
                            mid(b, c, &mut nodes),
                            mid(c, a, &mut nodes),
                        );
                        split_triangle([a, b, c], ab, bc, ca)
                    })
                    .collect(),
            })
            .collect();
        TetMesh {
            nodes,
            tets: self.tets.clone(),
            tet_edge_nodes,
            surfaces,
            node_groups: self.node_groups.clone(),
        }
    }
}
