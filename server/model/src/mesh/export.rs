//! Result files for people and other tools: a node table (CSV) and a ParaView unstructured grid
//! (`.vtu`, VTK XML, ASCII). Both are written in a chosen length unit (the scene's, so a mesh
//! given in mm comes back in mm).
//!
//! Neighbours: the `haptic-solve` command (server crate) writes static solutions with these.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;

use glam::DVec3;

use crate::ModelError;
use crate::mesh::TetMesh;

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

/// Writes a VTK XML unstructured grid (`.vtu`, ASCII) of the tetrahedra at the current positions
/// `x`, with point data `displacement` (x - rest) and cell data `volume_ratio` (of the corner tetrahedron for quadratic elements: current over
/// rest volume, negative for inverted elements). Coordinates are divided by `length_unit_m`.
///
/// # Errors
/// [`ModelError::Io`] when the file cannot be written.
pub fn write_vtu(
    path: &Path,
    mesh: &TetMesh,
    x: &[DVec3],
    length_unit_m: f64,
) -> Result<(), ModelError> {
    let s = 1.0 / length_unit_m;
    let (n, e) = (mesh.nodes.len(), mesh.tets.len());
    let mut v = String::with_capacity(n * 80 + e * 60);
    let _ = writeln!(v, r#"<?xml version="1.0"?>"#);
    let _ = writeln!(
        v,
        r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian">"#
    );
    let _ = writeln!(
        v,
        "<UnstructuredGrid>\n<Piece NumberOfPoints=\"{n}\" NumberOfCells=\"{e}\">"
    );
    let _ = writeln!(v, "<PointData Vectors=\"displacement\">");
    let _ = writeln!(
        v,
        r#"<DataArray type="Float64" Name="displacement" NumberOfComponents="3" format="ascii">"#
    );
    for (p, r) in x.iter().zip(&mesh.nodes) {
        let d = (*p - *r) * s;
        let _ = writeln!(v, "{:.12e} {:.12e} {:.12e}", d.x, d.y, d.z);
    }
    let _ = writeln!(
        v,
        "</DataArray>\n</PointData>\n<CellData Scalars=\"volume_ratio\">"
    );
    let _ = writeln!(
        v,
        r#"<DataArray type="Float64" Name="volume_ratio" format="ascii">"#
    );
    for t in &mesh.tets {
        let [a, b, c, d] = t.map(|i| i as usize);
        let cur = crate::mesh::tet_signed_volume(x[a], x[b], x[c], x[d]);
        let rest = crate::mesh::tet_signed_volume(
            mesh.nodes[a],
            mesh.nodes[b],
            mesh.nodes[c],
            mesh.nodes[d],
        );
        let _ = writeln!(v, "{:.12e}", cur / rest);
    }
    let _ = writeln!(v, "</DataArray>\n</CellData>\n<Points>");
    let _ = writeln!(
        v,
        r#"<DataArray type="Float64" NumberOfComponents="3" format="ascii">"#
    );
    for p in x {
        let _ = writeln!(v, "{:.12e} {:.12e} {:.12e}", p.x * s, p.y * s, p.z * s);
    }
    let _ = writeln!(v, "</DataArray>\n</Points>\n<Cells>");
    let _ = writeln!(
        v,
        r#"<DataArray type="Int64" Name="connectivity" format="ascii">"#
    );
    // Quadratic elements: VTK_QUADRATIC_TETRA (24), whose mid-edge node order is ours.
    let npe = if mesh.is_quadratic() { 10 } else { 4 };
    for (k, t) in mesh.tets.iter().enumerate() {
        let _ = write!(v, "{} {} {} {}", t[0], t[1], t[2], t[3]);
        if let Some(m) = mesh.tet_edge_nodes.get(k) {
            for i in m {
                let _ = write!(v, " {i}");
            }
        }
        v.push('\n');
    }
    let _ = writeln!(
        v,
        "</DataArray>\n<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">"
    );
    for k in 1..=e {
        let _ = writeln!(v, "{}", npe * k);
    }
    // VTK_TETRA = 10, VTK_QUADRATIC_TETRA = 24
    let _ = writeln!(
        v,
        "</DataArray>\n<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">"
    );
    let cell_type = if mesh.is_quadratic() { "24\n" } else { "10\n" };
    for _ in 0..e {
        v.push_str(cell_type);
    }
    let _ = writeln!(
        v,
        "</DataArray>\n</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>"
    );
    let mut f = std::fs::File::create(path).map_err(|e| io_err(path, e))?;
    f.write_all(v.as_bytes()).map_err(|e| io_err(path, e))
}
