//! The one writer of VTK XML unstructured grids (`.vtu`, ASCII) and their time series (`.pvd`),
//! for ParaView: `hapticctl export-vtu` writes recorded surfaces (triangles, `Float32`),
//! `haptic-solve` writes static solutions (tetrahedra, `Float64`).
//!
//! A [`Grid`] names its arrays, their number type (which fixes how a value is printed: `{}` for
//! integers and `Float32`, `{:.12e}` for `Float64`) and their line [`Layout`]; [`write_vtu`]
//! checks the shapes and writes the file. The format is VTK's "XML File Formats"
//! (<https://docs.vtk.org/en/latest/design_documents/VTKFileFormats.html>).
//!
//! Neighbours: `haptic_client::record` (recordings) and `haptic_server::solve` (solutions)
//! build the grids; the model computes the values (`TetMesh::volume_ratios`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// VTK cell type of a linear triangle.
pub const VTK_TRIANGLE: u8 = 5;
/// VTK cell type of a linear (4-node) tetrahedron.
pub const VTK_TETRA: u8 = 10;
/// VTK cell type of a quadratic (10-node) tetrahedron.
pub const VTK_QUADRATIC_TETRA: u8 = 24;

/// Why a grid was not written.
#[derive(Debug, thiserror::Error)]
pub enum VtuError {
    /// The arrays do not describe a grid (lengths, offsets or number types do not agree).
    #[error("not a valid grid: {0}")]
    Shape(String),
    /// The file could not be written.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
}

/// The values of one `<DataArray>`, by VTK number type.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Values<'a> {
    /// `Float32`, printed with `{}` (shortest text that reads back the same `f32`).
    F32(&'a [f32]),
    /// `Float64`, printed with `{:.12e}` (13 significant digits).
    F64(&'a [f64]),
    /// `UInt8`.
    U8(&'a [u8]),
    /// `UInt32`.
    U32(&'a [u32]),
    /// `Int64`.
    I64(&'a [i64]),
}

impl Values<'_> {
    /// Number of values.
    pub fn len(&self) -> usize {
        match self {
            Values::F32(v) => v.len(),
            Values::F64(v) => v.len(),
            Values::U8(v) => v.len(),
            Values::U32(v) => v.len(),
            Values::I64(v) => v.len(),
        }
    }

    /// True when there are no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn type_name(&self) -> &'static str {
        match self {
            Values::F32(_) => "Float32",
            Values::F64(_) => "Float64",
            Values::U8(_) => "UInt8",
            Values::U32(_) => "UInt32",
            Values::I64(_) => "Int64",
        }
    }

    /// Value `i` as an index (integer types only; `None` for floats and negative values).
    fn index(&self, i: usize) -> Option<usize> {
        match self {
            Values::U8(v) => Some(usize::from(v[i])),
            Values::U32(v) => usize::try_from(v[i]).ok(),
            Values::I64(v) => usize::try_from(v[i]).ok(),
            Values::F32(_) | Values::F64(_) => None,
        }
    }

    fn write_value(&self, s: &mut String, i: usize) {
        let _ = match self {
            Values::F32(v) => write!(s, "{}", v[i]),
            Values::F64(v) => write!(s, "{:.12e}", v[i]),
            Values::U8(v) => write!(s, "{}", v[i]),
            Values::U32(v) => write!(s, "{}", v[i]),
            Values::I64(v) => write!(s, "{}", v[i]),
        };
    }
}

/// How an array's values are laid out in the ASCII text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// One tuple per line (its components, or one cell's point indices), separated by spaces.
    Rows,
    /// Every value followed by a space, all on one line.
    Line,
}

/// One named `<DataArray>`: `components` values per point or cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DataArray<'a> {
    /// `Name` attribute (none for the points' coordinates).
    pub name: Option<&'a str>,
    /// `NumberOfComponents` (written when above 1): 1 for scalars, 3 for vectors.
    pub components: usize,
    /// The values, tuple after tuple.
    pub values: Values<'a>,
    /// Line layout.
    pub layout: Layout,
}

/// The cells of a grid: VTK's `connectivity`, `offsets` and `types` arrays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cells<'a> {
    /// Point indices of every cell, concatenated (an integer type; one cell per line).
    pub connectivity: Values<'a>,
    /// End of each cell in `connectivity` (an integer type, non-decreasing, last = its length).
    pub offsets: Values<'a>,
    /// VTK cell type of each cell (`UInt8`: [`VTK_TRIANGLE`], [`VTK_TETRA`], ...).
    pub types: Values<'a>,
    /// Line layout of `offsets` and `types`.
    pub layout: Layout,
}

/// VTK XML file-format version written in the `VTKFile` element (the ASCII content is the same).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Version {
    /// `0.1`.
    V0_1,
    /// `1.0`.
    V1_0,
}

/// An unstructured grid (one piece) to write with [`write_vtu`].
#[derive(Debug, Clone, PartialEq)]
pub struct Grid<'a> {
    /// The `VTKFile` version attribute.
    pub version: Version,
    /// Point coordinates (3 components per point; their number type and unit as the caller's).
    pub points: DataArray<'a>,
    /// The cells.
    pub cells: Cells<'a>,
    /// Point data; the first array is the active one (`Scalars` or `Vectors` by its components).
    pub point_data: Vec<DataArray<'a>>,
    /// Cell data; the first array is the active one.
    pub cell_data: Vec<DataArray<'a>>,
    /// Point and cell data before the points and cells (VTK's own writers' order) or after.
    pub data_first: bool,
}

/// Writes `grid` to `path` as a VTK XML unstructured grid (ASCII).
///
/// # Errors
/// [`VtuError::Shape`] when the arrays do not agree (nothing is written);
/// [`VtuError::Io`] when the file cannot be written.
pub fn write_vtu(path: &Path, grid: &Grid) -> Result<(), VtuError> {
    let text = vtu_text(grid)?;
    std::fs::write(path, text).map_err(|source| VtuError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// The text of [`write_vtu`].
///
/// # Errors
/// [`VtuError::Shape`] when the arrays do not agree.
pub fn vtu_text(grid: &Grid) -> Result<String, VtuError> {
    let cell_ends = check(grid)?;
    let (n, m) = (grid.points.values.len() / 3, cell_ends.len());
    let mut s = String::with_capacity(64 * (n + m) + 512);
    let version = match grid.version {
        Version::V0_1 => "0.1",
        Version::V1_0 => "1.0",
    };
    let _ = write!(
        s,
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"{version}\" \
         byte_order=\"LittleEndian\">\n<UnstructuredGrid>\n<Piece NumberOfPoints=\"{n}\" \
         NumberOfCells=\"{m}\">\n"
    );
    if grid.data_first {
        write_data(&mut s, "PointData", &grid.point_data);
        write_data(&mut s, "CellData", &grid.cell_data);
    }
    s.push_str("<Points>\n");
    write_array(&mut s, &grid.points, None);
    s.push_str("</Points>\n<Cells>\n");
    let c = &grid.cells;
    for (name, values, layout, rows) in [
        (
            "connectivity",
            c.connectivity,
            Layout::Rows,
            Some(&cell_ends),
        ),
        ("offsets", c.offsets, c.layout, None),
        ("types", c.types, c.layout, None),
    ] {
        let array = DataArray {
            name: Some(name),
            components: 1,
            values,
            layout,
        };
        write_array(&mut s, &array, rows.map(Vec::as_slice));
    }
    s.push_str("</Cells>\n");
    if !grid.data_first {
        write_data(&mut s, "PointData", &grid.point_data);
        write_data(&mut s, "CellData", &grid.cell_data);
    }
    s.push_str("</Piece>\n</UnstructuredGrid>\n</VTKFile>\n");
    Ok(s)
}

/// Checks the shapes; returns the end of each cell in the connectivity.
fn check(grid: &Grid) -> Result<Vec<usize>, VtuError> {
    let bad = |m: String| Err(VtuError::Shape(m));
    let p = &grid.points;
    if p.components != 3 || !p.values.len().is_multiple_of(3) {
        return bad(format!(
            "points need 3 components, got {} values in {}",
            p.values.len(),
            p.components
        ));
    }
    let c = &grid.cells;
    let (n, m) = (p.values.len() / 3, c.offsets.len());
    if c.types.len() != m || !matches!(c.types, Values::U8(_)) {
        return bad(format!("{m} offsets need {m} UInt8 cell types"));
    }
    let mut ends = Vec::with_capacity(m);
    for i in 0..m {
        let end = c
            .offsets
            .index(i)
            .ok_or_else(|| VtuError::Shape(format!("offset {i} is not a non-negative integer")))?;
        if end < ends.last().copied().unwrap_or(0) {
            return bad(format!("offset {i} ({end}) decreases"));
        }
        ends.push(end);
    }
    let len = c.connectivity.len();
    if ends.last().copied().unwrap_or(0) != len {
        return bad(format!(
            "the last offset is not the connectivity's length {len}"
        ));
    }
    if (0..len).any(|i| c.connectivity.index(i).is_none_or(|k| k >= n)) {
        return bad(format!("connectivity names a point outside 0..{n}"));
    }
    for (data, count) in [(&grid.point_data, n), (&grid.cell_data, m)] {
        for a in data {
            if a.components == 0 || a.values.len() != a.components * count {
                return bad(format!(
                    "array {:?}: {} values for {count} tuples of {}",
                    a.name.unwrap_or(""),
                    a.values.len(),
                    a.components
                ));
            }
        }
    }
    Ok(ends)
}

/// `<PointData>` or `<CellData>` with its arrays (nothing when there are none).
fn write_data(s: &mut String, element: &str, arrays: &[DataArray]) {
    let Some(active) = arrays.first() else {
        return;
    };
    let kind = if active.components == 1 {
        "Scalars"
    } else {
        "Vectors"
    };
    let _ = writeln!(
        s,
        "<{element} {kind}=\"{}\">",
        active.name.unwrap_or_default()
    );
    for a in arrays {
        write_array(s, a, None);
    }
    let _ = writeln!(s, "</{element}>");
}

/// One `<DataArray>`; `rows` gives the end of each row when rows are not tuples (cells).
fn write_array(s: &mut String, a: &DataArray, rows: Option<&[usize]>) {
    let _ = write!(s, "<DataArray type=\"{}\"", a.values.type_name());
    if let Some(name) = a.name {
        let _ = write!(s, " Name=\"{name}\"");
    }
    if a.components > 1 {
        let _ = write!(s, " NumberOfComponents=\"{}\"", a.components);
    }
    s.push_str(" format=\"ascii\">\n");
    let len = a.values.len();
    match a.layout {
        Layout::Line => {
            for i in 0..len {
                a.values.write_value(s, i);
                s.push(' ');
            }
            s.push('\n');
        }
        Layout::Rows => {
            let tuples: Vec<usize>;
            let ends = match rows {
                Some(ends) => ends,
                None => {
                    let k = a.components.max(1);
                    tuples = (1..=len / k).map(|t| t * k).collect();
                    &tuples
                }
            };
            let mut start = 0;
            for &end in ends {
                for i in start..end {
                    if i > start {
                        s.push(' ');
                    }
                    a.values.write_value(s, i);
                }
                s.push('\n');
                start = end;
            }
        }
    }
    s.push_str("</DataArray>\n");
}

/// Writes a ParaView collection (`.pvd`) listing `datasets` as `(timestep, file)` pairs, files
/// relative to the collection's folder, in the given order.
///
/// # Errors
/// [`VtuError::Io`] when the file cannot be written.
pub fn write_pvd(path: &Path, datasets: &[(f64, String)]) -> Result<(), VtuError> {
    let mut s = String::from(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n  <Collection>\n",
    );
    for (timestep, file) in datasets {
        let _ = writeln!(
            s,
            "    <DataSet timestep=\"{timestep}\" part=\"0\" file=\"{file}\"/>"
        );
    }
    s.push_str("  </Collection>\n</VTKFile>\n");
    std::fs::write(path, s).map_err(|source| VtuError::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One triangle at `points` (3 points), surface style: points and cells first, one-line
    /// offsets and types.
    fn triangle(points: &[f32]) -> Grid<'_> {
        Grid {
            version: Version::V0_1,
            points: DataArray {
                name: None,
                components: 3,
                values: Values::F32(points),
                layout: Layout::Rows,
            },
            cells: Cells {
                connectivity: Values::U32(&[0, 1, 2]),
                offsets: Values::U32(&[3]),
                types: Values::U8(&[VTK_TRIANGLE]),
                layout: Layout::Line,
            },
            point_data: vec![],
            cell_data: vec![],
            data_first: false,
        }
    }

    #[test]
    fn a_triangle_in_the_recordings_layout() {
        let points = [0.0f32, 0.0, 0.0, 1.5, 0.0, 0.0, 0.0, 2.0, -0.25];
        let displacement = [0.0f32, 0.5, 1e-3];
        let mut grid = triangle(&points);
        grid.point_data.push(DataArray {
            name: Some("displacement_m"),
            components: 1,
            values: Values::F32(&displacement),
            layout: Layout::Line,
        });
        let expected = "<?xml version=\"1.0\"?>
<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">
<UnstructuredGrid>
<Piece NumberOfPoints=\"3\" NumberOfCells=\"1\">
<Points>
<DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"ascii\">
0 0 0
1.5 0 0
0 2 -0.25
</DataArray>
</Points>
<Cells>
<DataArray type=\"UInt32\" Name=\"connectivity\" format=\"ascii\">
0 1 2
</DataArray>
<DataArray type=\"UInt32\" Name=\"offsets\" format=\"ascii\">
3 
</DataArray>
<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">
5 
</DataArray>
</Cells>
<PointData Scalars=\"displacement_m\">
<DataArray type=\"Float32\" Name=\"displacement_m\" format=\"ascii\">
0 0.5 0.001 
</DataArray>
</PointData>
</Piece>
</UnstructuredGrid>
</VTKFile>
";
        assert_eq!(vtu_text(&grid).unwrap(), expected);
    }

    /// One tetrahedron, solution style (data first, `Float64` in `{:.12e}`, one value a line).
    #[test]
    fn a_tetrahedron_in_the_solutions_layout() {
        let points = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let displacement = [
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -0.125,
        ];
        let grid = Grid {
            version: Version::V1_0,
            points: DataArray {
                name: None,
                components: 3,
                values: Values::F64(&points),
                layout: Layout::Rows,
            },
            cells: Cells {
                connectivity: Values::I64(&[0, 1, 2, 3]),
                offsets: Values::I64(&[4]),
                types: Values::U8(&[VTK_TETRA]),
                layout: Layout::Rows,
            },
            point_data: vec![DataArray {
                name: Some("displacement"),
                components: 3,
                values: Values::F64(&displacement),
                layout: Layout::Rows,
            }],
            cell_data: vec![DataArray {
                name: Some("volume_ratio"),
                components: 1,
                values: Values::F64(&[0.875]),
                layout: Layout::Rows,
            }],
            data_first: true,
        };
        let z = "0.000000000000e0";
        let text = vtu_text(&grid).unwrap();
        let expected = format!(
            "<?xml version=\"1.0\"?>
<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\">
<UnstructuredGrid>
<Piece NumberOfPoints=\"4\" NumberOfCells=\"1\">
<PointData Vectors=\"displacement\">
<DataArray type=\"Float64\" Name=\"displacement\" NumberOfComponents=\"3\" format=\"ascii\">
{z} {z} {z}
{z} {z} {z}
{z} {z} {z}
{z} {z} -1.250000000000e-1
</DataArray>
</PointData>
<CellData Scalars=\"volume_ratio\">
<DataArray type=\"Float64\" Name=\"volume_ratio\" format=\"ascii\">
8.750000000000e-1
</DataArray>
</CellData>
<Points>
<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">
{z} {z} {z}
1.000000000000e0 {z} {z}
{z} 1.000000000000e0 {z}
{z} {z} 1.000000000000e0
</DataArray>
</Points>
<Cells>
<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">
0 1 2 3
</DataArray>
<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">
4
</DataArray>
<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">
10
</DataArray>
</Cells>
</Piece>
</UnstructuredGrid>
</VTKFile>
"
        );
        assert_eq!(text, expected);
    }

    #[test]
    fn inconsistent_grids_are_refused() {
        let points = [0.0f32; 9];
        let ok = triangle(&points);
        assert!(vtu_text(&ok).is_ok());
        let refused = |g: Grid| match vtu_text(&g) {
            Err(VtuError::Shape(m)) => m,
            other => panic!("accepted: {other:?}"),
        };
        let mut g = ok.clone();
        g.cells.connectivity = Values::U32(&[0, 1, 3]);
        assert!(refused(g).contains("outside 0..3"));
        let mut g = ok.clone();
        g.cells.offsets = Values::U32(&[2]);
        assert!(refused(g).contains("last offset"));
        let mut g = ok.clone();
        g.cells.offsets = Values::F32(&[3.0]);
        assert!(refused(g).contains("not a non-negative integer"));
        let mut g = ok.clone();
        g.cells.types = Values::U8(&[]);
        assert!(refused(g).contains("cell types"));
        let mut g = ok.clone();
        g.points.values = Values::F32(&points[..8]);
        assert!(refused(g).contains("3 components"));
        let mut g = ok.clone();
        g.point_data.push(DataArray {
            name: Some("u"),
            components: 1,
            values: Values::F32(&[1.0, 2.0]),
            layout: Layout::Line,
        });
        assert!(refused(g).contains("\"u\""));
    }

    #[test]
    fn a_series_lists_its_files_in_order() {
        let dir = std::env::temp_dir().join(format!("haptic-cli-vtu-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("s.pvd");
        write_pvd(&path, &[(0.0, "a.vtu".into()), (0.125, "b.vtu".into())]).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(
            text,
            "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n  \
             <Collection>\n    <DataSet timestep=\"0\" part=\"0\" file=\"a.vtu\"/>\n    \
             <DataSet timestep=\"0.125\" part=\"0\" file=\"b.vtu\"/>\n  </Collection>\n\
             </VTKFile>\n"
        );
    }
}
