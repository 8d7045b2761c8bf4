//! Strain smoothing of linear tetrahedra: the edge-based smoothed FEM (ES-FEM-T4), one
//! integration point per mesh edge with the volume-averaged gradients of the tetrahedra around
//! it.
//!
//! Neighbours: produces the cells of `super::quadrature::IntegrationPoints` used by
//! [`super::FemModel`].

use glam::{DMat3, DVec3};

use super::quadrature::{IntegrationPoints, linear_gradients};

/// Strain smoothing of linear tetrahedra (element technology), chosen per scene with
/// `[mesh] strain_smoothing`.
///
/// - [`StrainSmoothing::None`]: standard FEM, one deformation gradient per tetrahedron.
/// - [`StrainSmoothing::Edge`]: the edge-based smoothed FEM, ES-FEM-T4 (G. R. Liu and
///   T. Nguyen-Thoi, *Smoothed Finite Element Methods*, CRC Press 2010; Zeng & Liu,
///   Arch. Comput. Methods Eng. 25 (2018) 397). Each mesh edge `k` owns the smoothing domain
///   made of one sixth of every tetrahedron around it, of volume `V_k = sum_e V_e / 6`, and
///   carries the volume-averaged deformation gradient
///   `F_k = (1 / V_k) sum_e (V_e / 6) F_e = sum_j x_j (G_kj)^T`,
///   `G_kj = (1 / V_k) sum_{e ∋ k, j} (V_e / 6) grad N_j^e`. The energy is
///   `sum_k V_k Psi(F_k)`; forces, stiffness and viscous stress follow from `F_k` exactly as from
///   an integration point with weight `V_k` and gradients `G_kj` (its nodes: those of the
///   tetrahedra around the edge). Linear tetrahedra are overly stiff in bending and shear; the
///   smoothed strain softens them while keeping the linear patch test exact (a linear field has
///   the same `F` in every element, so its average too), and unlike the node-based variant it
///   has no spurious low-energy modes (measured effect on the LV: `docs/accuracy.md`, "Strain
///   smoothing"). Linear meshes only; masses stay lumped per element.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StrainSmoothing {
    /// Standard FEM.
    #[default]
    None,
    /// Edge-based smoothed FEM (ES-FEM-T4).
    Edge,
}

impl StrainSmoothing {
    /// Parses the scene name: `"none"` or `"edge"`.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "none" => Some(Self::None),
            "edge" => Some(Self::Edge),
            _ => None,
        }
    }

    /// The scene name.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Edge => "edge",
        }
    }
}

/// The smoothing domains of the edge-based smoothed FEM ([`StrainSmoothing::Edge`]) of linear
/// tetrahedra: one cell with one point per mesh edge.
pub(super) fn edge_smoothed_points(
    tets: &[[u32; 4]],
    dm_inv: &[DMat3],
    volume_m3: &[f64],
) -> IntegrationPoints {
    // Edge id of every (tet, local edge), in order of first appearance.
    let mut ids = std::collections::HashMap::with_capacity(tets.len() * 2);
    let mut edge_of = Vec::with_capacity(6 * tets.len());
    for t in tets {
        for [a, b] in crate::mesh::TET_EDGES {
            let key = (t[a].min(t[b]), t[a].max(t[b]));
            let next = ids.len();
            edge_of.push(*ids.entry(key).or_insert(next));
        }
    }
    let edges = ids.len();
    // Tetrahedra around each edge (CSR).
    let mut start = vec![0usize; edges + 1];
    for &k in &edge_of {
        start[k + 1] += 1;
    }
    for k in 0..edges {
        start[k + 1] += start[k];
    }
    let mut fill = start.clone();
    let mut around = vec![0u32; edge_of.len()];
    for (i, &k) in edge_of.iter().enumerate() {
        around[fill[k]] = (i / 6) as u32;
        fill[k] += 1;
    }
    let mut p = IntegrationPoints::new();
    let (mut nodes, mut grads) = (Vec::<u32>::new(), Vec::<DVec3>::new());
    for k in 0..edges {
        nodes.clear();
        grads.clear();
        let ring = &around[start[k]..start[k + 1]];
        let vk: f64 = ring.iter().map(|&e| volume_m3[e as usize] / 6.0).sum();
        for &e in ring {
            let e = e as usize;
            let w = volume_m3[e] / 6.0 / vk;
            for (&i, g) in tets[e].iter().zip(linear_gradients(&dm_inv[e])) {
                match nodes.iter().position(|&j| j == i) {
                    Some(a) => grads[a] += g * w,
                    None => {
                        nodes.push(i);
                        grads.push(g * w);
                    }
                }
            }
        }
        p.push_cell(&nodes, [(grads.as_slice(), vk)]);
    }
    p
}
