//! Integration points: one per linear tetrahedron (seed 000 eq. 13-21), four per quadratic
//! (10-node) tetrahedron with the degree-2 Gauss rule, grouped in *cells* so that elements and
//! the smoothing domains of [`super::smoothing`] share every generic path.
//!
//! Neighbours: built by [`super::FemModel::with_smoothing`]; read by the generic element loops,
//! [`super::tangent`] and the vectorised [`super::kernels`].

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::mesh::TetMesh;

/// Integration-point data in flat arrays, grouped in *cells*: a cell is an element (linear or
/// quadratic) or, with strain smoothing, a smoothing domain. Cell `c` has the nodes
/// `nodes[node_start[c]..node_start[c + 1]]` and the integration points
/// `q = point_start[c]..point_start[c + 1]`; point `q` has the rest shape-function gradients
/// `grad[grad_start[q]..grad_start[q + 1]]` (1/m, one per node of its cell, in the cell's node
/// order) and the weight `weight_m3[q]` (m^3; the weights sum to the body's volume).
#[derive(Debug, Clone, Default)]
pub(in crate::element) struct IntegrationPoints {
    pub(in crate::element) node_start: Vec<usize>,
    pub(in crate::element) nodes: Vec<u32>,
    pub(in crate::element) point_start: Vec<usize>,
    /// The cell of each point.
    pub(in crate::element) cell: Vec<u32>,
    pub(in crate::element) grad_start: Vec<usize>,
    pub(in crate::element) grad: Vec<DVec3>,
    pub(in crate::element) weight_m3: Vec<f64>,
}

impl IntegrationPoints {
    /// Bytes of the arrays.
    pub(super) fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        b(&self.node_start)
            + b(&self.nodes)
            + b(&self.point_start)
            + b(&self.cell)
            + b(&self.grad_start)
            + b(&self.grad)
            + b(&self.weight_m3)
    }

    pub(super) fn new() -> Self {
        Self {
            node_start: vec![0],
            point_start: vec![0],
            grad_start: vec![0],
            ..Self::default()
        }
    }

    /// Appends a cell with `nodes` and its points `(gradients in node order, weight)`.
    pub(super) fn push_cell<'a>(
        &mut self,
        nodes: &[u32],
        points: impl IntoIterator<Item = (&'a [DVec3], f64)>,
    ) {
        let c = self.node_start.len() as u32 - 1;
        self.nodes.extend_from_slice(nodes);
        self.node_start.push(self.nodes.len());
        for (g, w) in points {
            debug_assert_eq!(g.len(), nodes.len());
            self.grad.extend_from_slice(g);
            self.grad_start.push(self.grad.len());
            self.weight_m3.push(w);
            self.cell.push(c);
        }
        self.point_start.push(self.weight_m3.len());
    }
}

/// The integration points of linear tetrahedra: one per element (`grad N_0 = -(g1 + g2 + g3)`,
/// weight the volume).
pub(super) fn linear_points(
    tets: &[[u32; 4]],
    dm_inv: &[DMat3],
    volume_m3: &[f64],
) -> IntegrationPoints {
    let mut p = IntegrationPoints::new();
    for ((t, m), &v) in tets.iter().zip(dm_inv).zip(volume_m3) {
        p.push_cell(t, [(linear_gradients(m).as_slice(), v)]);
    }
    p
}

/// The four shape-function gradients of a linear tetrahedron from its `Dm^-1` (rows 1..3).
pub(super) fn linear_gradients(dm_inv: &DMat3) -> [DVec3; 4] {
    let (g1, g2, g3) = (dm_inv.row(0), dm_inv.row(1), dm_inv.row(2));
    [-(g1 + g2 + g3), g1, g2, g3]
}

/// Barycentric coordinates of the points of the 4-point degree-2 Gauss rule on a tetrahedron.
pub(super) const GAUSS4_A: f64 = 0.585_410_196_624_968_5;

pub(super) const GAUSS4_B: f64 = 0.138_196_601_125_010_5;

/// Derivatives of the 10 quadratic shape functions with respect to the reference coordinates
/// `(xi_1, xi_2, xi_3) = (L_1, L_2, L_3)` at barycentric point `l` (node order: corners, then
/// the mid-edge nodes of [`crate::mesh::TET_EDGES`]).
fn quadratic_reference_gradients(l: [f64; 4]) -> [DVec3; 10] {
    let dl = [DVec3::splat(-1.0), DVec3::X, DVec3::Y, DVec3::Z];
    let mut g = [DVec3::ZERO; 10];
    for i in 0..4 {
        g[i] = dl[i] * (4.0 * l[i] - 1.0);
    }
    for (k, [i, j]) in crate::mesh::TET_EDGES.iter().enumerate() {
        g[4 + k] = (dl[*j] * l[*i] + dl[*i] * l[*j]) * 4.0;
    }
    g
}

/// Integration points of the quadratic elements of `mesh` (module docs), with the isoparametric
/// map of the rest positions (so curved elements are handled).
pub(super) fn quadratic_points(mesh: &TetMesh) -> Result<IntegrationPoints, ModelError> {
    let n = mesh.nodes.len();
    let e_count = mesh.tets.len();
    if mesh.tet_edge_nodes.len() != e_count {
        return Err(ModelError::InvalidMesh(format!(
            "{} rows of mid-edge nodes for {e_count} tetrahedra",
            mesh.tet_edge_nodes.len()
        )));
    }
    let mut p = IntegrationPoints::new();
    let mut grads = [[DVec3::ZERO; 10]; 4];
    let mut weights = [0.0; 4];
    for (k, (t, mid)) in mesh.tets.iter().zip(&mesh.tet_edge_nodes).enumerate() {
        let en: Vec<u32> = t.iter().chain(mid).copied().collect();
        if let Some(bad) = en.iter().find(|&&i| i as usize >= n) {
            return Err(ModelError::InvalidMesh(format!(
                "quadratic tetrahedron {k} has an out-of-range node {bad}"
            )));
        }
        for q in 0..4 {
            let mut l = [GAUSS4_B; 4];
            l[q] = GAUSS4_A;
            let dn = quadratic_reference_gradients(l);
            // J = dX/dxi = sum_a X_a (dN_a/dxi)^T
            let jac = en.iter().zip(&dn).fold(DMat3::ZERO, |acc, (&i, g)| {
                let x = mesh.nodes[i as usize];
                acc + DMat3::from_cols(x * g.x, x * g.y, x * g.z)
            });
            let det = jac.determinant();
            if !(det > 0.0) || !det.is_finite() {
                return Err(ModelError::InvalidMesh(format!(
                    "quadratic tetrahedron {k} has a non-positive Jacobian {det:.3e} at \
                     integration point {q}"
                )));
            }
            let jit = jac.inverse().transpose();
            grads[q] = dn.map(|g| jit * g);
            weights[q] = det / 24.0;
        }
        p.push_cell(&en, grads.iter().map(|g| g.as_slice()).zip(weights));
    }
    Ok(p)
}
