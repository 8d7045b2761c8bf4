//! Scenes: a mesh, a material, boundary conditions, an integrator and a probe.
//! Placeholder: the parser and built-ins come with the mesh change.

use crate::contact::ProbeParams;
use crate::integrator::IntegratorParams;
use crate::material::MaterialParams;
use crate::mesh::TetMesh;

/// A validated scene, ready to build a [`crate::sim::Simulation`]. SI units.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Scene name (built-in name or the file's `name`).
    pub name: String,
    /// One-line description, with the source of the parameters.
    pub description: String,
    /// The mesh in metres.
    pub mesh: TetMesh,
    /// Material.
    pub material: MaterialParams,
    /// Integrator settings.
    pub integrator: IntegratorParams,
    /// Haptic probe settings.
    pub probe: ProbeParams,
    /// Nodes fixed at their rest position (clamped), sorted, distinct.
    pub clamped_nodes: Vec<u32>,
    /// Triangles the probe can touch, outward oriented.
    pub touchable: Vec<[u32; 3]>,
    /// The scene file's length unit in metres (1e-3 for "mm"); outputs for users use it.
    pub length_unit_m: f64,
}
