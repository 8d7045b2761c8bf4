//! Result files for people and other tools: a node table (CSV), written in a chosen length unit
//! (the scene's, so a mesh given in mm comes back in mm).
//!
//! Neighbours: the `haptic-solve` command (server crate) writes static solutions with it, and
//! their ParaView `.vtu` with `haptic_cli::vtu` (cell data from
//! [`crate::mesh::TetMesh::volume_ratios`]).

use std::fmt::Write as _;
use std::path::Path;

use glam::DVec3;

use crate::ModelError;

fn io_err(path: &Path, source: std::io::Error) -> ModelError {
    ModelError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Writes `id,x0,y0,z0,x,y,z` per node: rest and current positions divided by `length_unit_m`
/// (1e-3 writes millimetres). `rest` and `x` have one entry per node, in metres.
///
/// # Errors
/// [`ModelError::Io`] when the file cannot be written.
pub fn write_nodes_csv(
    path: &Path,
    rest: &[DVec3],
    x: &[DVec3],
    length_unit_m: f64,
) -> Result<(), ModelError> {
    let s = 1.0 / length_unit_m;
    let mut out = String::with_capacity(rest.len() * 96);
    out.push_str("id,x0,y0,z0,x,y,z\n");
    for (i, (r, p)) in rest.iter().zip(x).enumerate() {
        let _ = writeln!(
            out,
            "{i},{:.12e},{:.12e},{:.12e},{:.12e},{:.12e},{:.12e}",
            r.x * s,
            r.y * s,
            r.z * s,
            p.x * s,
            p.y * s,
            p.z * s
        );
    }
    std::fs::write(path, out).map_err(|e| io_err(path, e))
}
