//! The `[boundary]` section: the clamped nodes and the touchable triangles.

use super::*;

/// `(clamped nodes, touchable triangles)` of `mesh`: the named surfaces' nodes and triangles;
/// without `boundary.touchable`, every surface triangle of a surface mesh, or else the boundary
/// triangles not wholly clamped. An unknown surface, or no touchable triangle, is an error.
pub(super) fn build_boundary(
    boundary: &RawBoundary,
    mesh: &TetMesh,
) -> Result<(Vec<u32>, Vec<[u32; 3]>), ModelError> {
    let clamped_nodes = match &boundary.clamped {
        Some(names) => mesh.nodes_of_surfaces(names, "boundary.clamped")?,
        None => Vec::new(),
    };
    let touchable = match &boundary.touchable {
        Some(names) => {
            let mut tris = Vec::new();
            for name in names {
                let Some(s) = mesh.surface(name) else {
                    let known: Vec<&str> = mesh.surfaces.iter().map(|s| s.name.as_str()).collect();
                    return Err(ModelError::field(
                        "boundary.touchable",
                        format!(
                            "no surface named `{name}` (mesh surfaces: {})",
                            known.join(", ")
                        ),
                    ));
                };
                tris.extend(s.triangles.iter().copied());
            }
            unique_triangles(tris)
        }
        None if mesh.tets.is_empty() => unique_triangles(
            mesh.surfaces
                .iter()
                .flat_map(|s| s.triangles.iter().copied())
                .collect(),
        ),
        None => mesh
            .boundary_triangles()
            .into_iter()
            .filter(|t| !t.iter().all(|i| clamped_nodes.binary_search(i).is_ok()))
            .collect(),
    };
    if touchable.is_empty() {
        return Err(ModelError::field(
            "boundary.touchable",
            "no touchable triangle is left",
        ));
    }
    Ok((clamped_nodes, touchable))
}

/// `tris` without repeats (the same three nodes in any order), first occurrence kept.
fn unique_triangles(mut tris: Vec<[u32; 3]>) -> Vec<[u32; 3]> {
    let mut seen = std::collections::HashSet::new();
    tris.retain(|t| {
        let mut k = *t;
        k.sort_unstable();
        seen.insert(k)
    });
    tris
}
