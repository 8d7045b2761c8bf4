//! Lumped nodal masses: row sums for linear tetrahedra, the HRZ rule for 10-node tetrahedra.
//!
//! Neighbours: [`super::FemModel`] stores them; [`crate::loads`] uses them for gravity.

use crate::mesh::TetMesh;

/// Lumped nodal masses, kg, one per node of `mesh` (m) with density `density_kg_per_m3`:
/// `m_i = sum_e rho |V_e| / 4` for linear elements; for quadratic ones the HRZ lumping
/// `rho |V_e| / 36` per corner and `4 rho |V_e| / 27` per mid-edge node (module docs).
/// [`super::FemModel::new`] stores the same values in `lumped_mass_kg`.
pub fn lumped_masses(mesh: &TetMesh, density_kg_per_m3: f64) -> Vec<f64> {
    let mut m = vec![0.0; mesh.nodes.len()];
    let (corner, edge) = if mesh.is_quadratic() {
        (1.0 / 36.0, 4.0 / 27.0)
    } else {
        (0.25, 0.0)
    };
    for (e, t) in mesh.tets.iter().enumerate() {
        let [a, b, c, d] = t.map(|i| mesh.nodes[i as usize]);
        let mass = density_kg_per_m3 * crate::mesh::tet_signed_volume(a, b, c, d).abs();
        for &i in t {
            m[i as usize] += mass * corner;
        }
        if let Some(mid) = mesh.tet_edge_nodes.get(e) {
            for &i in mid {
                m[i as usize] += mass * edge;
            }
        }
    }
    m
}
