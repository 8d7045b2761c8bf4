//! Surface meshes in (`haptic-mesh`): a closed organ surface from segmentation software (STL,
//! OBJ or PLY; optionally a second closed surface for a cavity) becomes a tetrahedral Gmsh mesh
//! with named physical groups and a scene file the daemon accepts.
//!
//! Steps: read the surface with a well-kept reader (`stl_io`, `tobj`, `ply-rs`), merge
//! coincident vertices, check it is closed and manifold (every edge shared by exactly two
//! triangles; the error names the count and the first bad edge's position), split it into the
//! clamped part (`BASE`: triangles whose three vertices satisfy the clamp rule) and the
//! touchable rest (`OUTER`), then let **Gmsh** (the program, Debian's `gmsh`) fill the volume:
//! the surface triangulation is kept as given and the interior is meshed by Delaunay up to the
//! requested size. Gmsh's own diagnostics (self-intersections, overlapping facets) are passed on
//! as the error. Physical groups: `OUTER`, `BASE`, `INNER` (the cavity, when given) and the
//! volume `TISSUE`. Coordinates stay in the surface's unit; the scene says which
//! (`length_unit`).
//!
//! Neighbours: the `haptic-mesh` binary; the result is read back by
//! [`haptic_model::mesh::gmsh`] (through [`haptic_model::scene::load_scene_file`]) before
//! success is reported.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// A triangulated surface: vertices (surface unit) and triangles (indices into them).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SurfaceMesh {
    /// Vertex positions.
    pub vertices: Vec<[f64; 3]>,
    /// Triangles, three vertex indices each.
    pub triangles: Vec<[u32; 3]>,
}

/// What went wrong turning a surface into a volume mesh.
#[derive(Debug, thiserror::Error)]
pub enum MeshInError {
    /// The file could not be read or parsed.
    #[error("{path}: {message}")]
    Read {
        /// File.
        path: String,
        /// What failed.
        message: String,
    },
    /// The surface has holes or non-manifold edges.
    #[error("{path}: the surface is not closed: {message}")]
    NotClosed {
        /// File.
        path: String,
        /// Counts and the first bad edge.
        message: String,
    },
    /// An option is unusable with this surface.
    #[error("{0}")]
    Options(String),
    /// Gmsh is missing or failed; its error lines are quoted.
    #[error("gmsh: {0}")]
    Gmsh(String),
    /// Writing the outputs failed.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: String,
        /// OS error.
        source: std::io::Error,
    },
}

fn read_err(path: &Path, message: impl std::fmt::Display) -> MeshInError {
    MeshInError::Read {
        path: path.display().to_string(),
        message: message.to_string(),
    }
}

/// Removes a directory tree when dropped (a work folder, on success and on every error path).
struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Reads an STL (ASCII or binary), OBJ or PLY surface by extension and merges coincident
/// vertices (to 1e-9 of the bounding box diagonal).
///
/// # Errors
/// [`MeshInError::Read`] for an unknown extension, an unreadable or malformed file, an index
/// out of range, a non-finite coordinate or no triangles.
pub fn read_surface(path: &Path) -> Result<SurfaceMesh, MeshInError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let open = || std::fs::File::open(path).map_err(|e| read_err(path, e));
    let (vertices, triangles): (Vec<[f64; 3]>, Vec<[u32; 3]>) = match ext.as_str() {
        "stl" => {
            // stl_io's messages quote the line it stopped at: say what the format expects.
            let mesh = stl_io::read_stl(&mut std::io::BufReader::new(open()?)).map_err(|e| {
                read_err(
                    path,
                    if e.kind() == std::io::ErrorKind::InvalidData {
                        "not a readable STL file: expected binary STL, or ASCII `solid`, then \
                         per facet `facet normal`, `outer loop`, three `vertex x y z` lines, \
                         `endloop`, `endfacet`"
                            .to_string()
                    } else {
                        format!("not a readable STL file ({})", e.kind())
                    },
                )
            })?;
            let v = mesh
                .vertices
                .iter()
                .map(|p| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])])
                .collect();
            let t = mesh
                .faces
                .iter()
                .map(|f| f.vertices.map(|i| i as u32))
                .collect();
            (v, t)
        }
        "obj" => {
            let options = tobj::LoadOptions {
                triangulate: true,
                single_index: true,
                ..Default::default()
            };
            let (models, _) =
                tobj::load_obj_buf(&mut std::io::BufReader::new(open()?), &options, |_| {
                    Err(tobj::LoadError::OpenFileFailed)
                })
                .map_err(|e| read_err(path, format!("not a readable OBJ file: {e}")))?;
            let mut v = Vec::new();
            let mut t = Vec::new();
            for m in models {
                let base = v.len() as u32;
                v.extend(
                    m.mesh
                        .positions
                        .chunks_exact(3)
                        .map(|p| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]),
                );
                t.extend(
                    m.mesh
                        .indices
                        .chunks_exact(3)
                        .map(|i| [base + i[0], base + i[1], base + i[2]]),
                );
            }
            (v, t)
        }
        "ply" => {
            let m = read_ply(path, &mut std::io::BufReader::new(open()?))?;
            (m.vertices, m.triangles)
        }
        _ => {
            return Err(read_err(
                path,
                "unknown surface format: expected .stl, .obj or .ply",
            ));
        }
    };
    let n = vertices.len() as u32;
    if triangles.is_empty() {
        return Err(read_err(path, "no triangles"));
    }
    if let Some(t) = triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
        return Err(read_err(
            path,
            format!("triangle {t:?} indexes past {n} vertices"),
        ));
    }
    if vertices.iter().flatten().any(|c| !c.is_finite()) {
        return Err(read_err(path, "a coordinate is not finite"));
    }
    Ok(merge_coincident(SurfaceMesh {
        vertices,
        triangles,
    }))
}

fn read_ply(path: &Path, r: &mut impl std::io::BufRead) -> Result<SurfaceMesh, MeshInError> {
    use ply_rs::ply::Property;
    let parser = ply_rs::parser::Parser::<ply_rs::ply::DefaultElement>::new();
    // ply-rs's messages quote the line: keep only its line number (issue 47).
    let ply = parser.read_ply(r).map_err(|e| {
        let text = e.to_string();
        let line = text
            .strip_prefix("Line ")
            .and_then(|t| t.split(':').next())
            .and_then(|n| n.trim().parse::<usize>().ok());
        read_err(
            path,
            format!(
                "not a readable PLY file{}: expected a `ply` header, `format ascii 1.0` or \
                 binary, `element`/`property` lines, `end_header`, then the data",
                line.map_or(String::new(), |l| format!(" (line {l})"))
            ),
        )
    })?;
    let scalar = |p: Option<&Property>| -> Option<f64> {
        Some(match p? {
            Property::Float(x) => f64::from(*x),
            Property::Double(x) => *x,
            Property::Int(x) => f64::from(*x),
            Property::UInt(x) => f64::from(*x),
            Property::Short(x) => f64::from(*x),
            Property::UShort(x) => f64::from(*x),
            Property::Char(x) => f64::from(*x),
            Property::UChar(x) => f64::from(*x),
            _ => return None,
        })
    };
    let mut v = Vec::new();
    for (i, e) in ply.payload.get("vertex").into_iter().flatten().enumerate() {
        let c = ["x", "y", "z"].map(|k| scalar(e.get(k)));
        match c {
            [Some(x), Some(y), Some(z)] => v.push([x, y, z]),
            _ => return Err(read_err(path, format!("vertex {i} lacks numeric x, y, z"))),
        }
    }
    let mut t = Vec::new();
    for (i, e) in ply.payload.get("face").into_iter().flatten().enumerate() {
        let list: Vec<i64> = match e.get("vertex_indices").or_else(|| e.get("vertex_index")) {
            Some(Property::ListInt(l)) => l.iter().map(|&x| i64::from(x)).collect(),
            Some(Property::ListUInt(l)) => l.iter().map(|&x| i64::from(x)).collect(),
            Some(Property::ListUChar(l)) => l.iter().map(|&x| i64::from(x)).collect(),
            Some(Property::ListShort(l)) => l.iter().map(|&x| i64::from(x)).collect(),
            Some(Property::ListUShort(l)) => l.iter().map(|&x| i64::from(x)).collect(),
            Some(Property::ListChar(l)) => l.iter().map(|&x| i64::from(x)).collect(),
            _ => {
                return Err(read_err(
                    path,
                    format!("face {i} has no vertex_indices list"),
                ));
            }
        };
        if list.len() < 3 || list.iter().any(|&x| x < 0 || x > i64::from(u32::MAX)) {
            return Err(read_err(path, format!("face {i} has a bad index list")));
        }
        // A polygon becomes a fan.
        for k in 1..list.len() - 1 {
            t.push([list[0] as u32, list[k] as u32, list[k + 1] as u32]);
        }
    }
    Ok(SurfaceMesh {
        vertices: v,
        triangles: t,
    })
}

/// Merges vertices closer than 1e-9 of the bounding-box diagonal (STL and OBJ files often
/// repeat them per face) and drops triangles that become degenerate.
pub fn merge_coincident(mesh: SurfaceMesh) -> SurfaceMesh {
    let (lo, hi) = bounds(&mesh.vertices);
    let diag = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
    let q = (diag * 1e-9).max(f64::MIN_POSITIVE);
    let mut index: HashMap<[i64; 3], u32> = HashMap::new();
    let mut vertices = Vec::new();
    let remap: Vec<u32> = mesh
        .vertices
        .iter()
        .map(|p| {
            let key = p.map(|c| (c / q).round() as i64);
            *index.entry(key).or_insert_with(|| {
                vertices.push(*p);
                vertices.len() as u32 - 1
            })
        })
        .collect();
    let triangles = mesh
        .triangles
        .iter()
        .map(|t| t.map(|i| remap[i as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .collect();
    SurfaceMesh {
        vertices,
        triangles,
    }
}

fn bounds(v: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in v {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

/// Checks that every edge is shared by exactly two triangles (closed, manifold).
///
/// # Errors
/// [`MeshInError::NotClosed`] with the number of boundary (one triangle) and non-manifold
/// (three or more) edges and the midpoint of the first one.
pub fn check_closed(mesh: &SurfaceMesh, path: &Path) -> Result<(), MeshInError> {
    let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *edges.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    let mut open: Vec<(u32, u32)> = edges
        .iter()
        .filter(|(_, n)| **n == 1)
        .map(|(e, _)| *e)
        .collect();
    let mut over: Vec<(u32, u32)> = edges
        .iter()
        .filter(|(_, n)| **n > 2)
        .map(|(e, _)| *e)
        .collect();
    if open.is_empty() && over.is_empty() {
        return Ok(());
    }
    open.sort_unstable();
    over.sort_unstable();
    let first = open.first().or(over.first()).copied().unwrap_or_default();
    let (a, b) = (
        mesh.vertices[first.0 as usize],
        mesh.vertices[first.1 as usize],
    );
    let mid = [0, 1, 2].map(|k| 0.5 * (a[k] + b[k]));
    Err(MeshInError::NotClosed {
        path: path.display().to_string(),
        message: format!(
            "{} boundary edge(s) (used by one triangle) and {} non-manifold edge(s) (three or \
             more); the first at ({:.6}, {:.6}, {:.6}). Close the holes in the segmentation \
             software (or with a mesh repair tool) and export again",
            open.len(),
            over.len(),
            mid[0],
            mid[1],
            mid[2]
        ),
    })
}

/// Which outer-surface triangles are clamped (physical group `BASE`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClampRule {
    /// Triangles whose vertices all have `z <= value` (surface unit).
    BelowZ(f64),
    /// Triangles whose vertices all have `z >= value`.
    AboveZ(f64),
}

impl ClampRule {
    fn holds(self, p: [f64; 3]) -> bool {
        match self {
            ClampRule::BelowZ(z) => p[2] <= z,
            ClampRule::AboveZ(z) => p[2] >= z,
        }
    }
}

/// Options of [`mesh_volume`].
#[derive(Debug, Clone, PartialEq)]
pub struct VolumeOptions {
    /// Clamped part of the outer surface.
    pub clamp: ClampRule,
    /// Largest tetrahedron edge inside, surface unit (`None`: Gmsh's default from the surface).
    pub max_size: Option<f64>,
    /// Gmsh executable.
    pub gmsh: PathBuf,
}

/// What [`mesh_volume`] produced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VolumeSummary {
    /// Outer-surface triangles touchable (`OUTER`) and clamped (`BASE`).
    pub outer_triangles: usize,
    /// Clamped triangles.
    pub base_triangles: usize,
    /// Cavity triangles (`INNER`).
    pub inner_triangles: usize,
}

/// Writes the surfaces as a Gmsh 2.2 surface mesh (elementary and physical tags 1 = `OUTER`,
/// 2 = `BASE`, 3 = `INNER`), runs Gmsh on a script that bounds a volume by them, and leaves the
/// tetrahedral mesh at `out_msh` (Gmsh 2.2 ASCII). `progress` gets Gmsh's `Info` lines.
///
/// # Errors
/// [`MeshInError::Options`] when the clamp rule selects no triangle or all of them,
/// [`MeshInError::Gmsh`] when Gmsh is missing or fails (its error lines quoted),
/// [`MeshInError::Io`] for the temporary files.
pub fn mesh_volume(
    outer: &SurfaceMesh,
    inner: Option<&SurfaceMesh>,
    options: &VolumeOptions,
    out_msh: &Path,
    progress: impl FnMut(&str),
) -> Result<VolumeSummary, MeshInError> {
    let is_base = clamped_triangles(outer, options)?;
    let base_triangles = is_base.iter().filter(|&&b| b).count();
    let work = out_msh.with_extension("gmsh-work");
    std::fs::create_dir_all(&work).map_err(|source| MeshInError::Io {
        path: work.display().to_string(),
        source,
    })?;
    // The work folder goes whatever happens next (issue 47: a failed run left it behind).
    let _work_guard = RemoveOnDrop(work.clone());
    write_text(
        &work.join("surface.msh"),
        surface_msh_text(outer, inner, &is_base),
    )?;
    let out_abs = std::path::absolute(out_msh).map_err(|source| MeshInError::Io {
        path: out_msh.display().to_string(),
        source,
    })?;
    write_text(
        &work.join("volume.geo"),
        volume_geo_text(inner.is_some(), options.max_size),
    )?;
    run_gmsh(&options.gmsh, &work, &out_abs, progress)?;
    Ok(VolumeSummary {
        outer_triangles: outer.triangles.len(),
        base_triangles,
        inner_triangles: inner.map_or(0, |m| m.triangles.len()),
    })
}

/// Per outer triangle, whether the clamp rule holds at its three vertices.
///
/// # Errors
/// [`MeshInError::Options`] when the rule selects no triangle or all of them.
fn clamped_triangles(
    outer: &SurfaceMesh,
    options: &VolumeOptions,
) -> Result<Vec<bool>, MeshInError> {
    let is_base: Vec<bool> = outer
        .triangles
        .iter()
        .map(|t| {
            t.iter()
                .all(|&i| options.clamp.holds(outer.vertices[i as usize]))
        })
        .collect();
    let base_triangles = is_base.iter().filter(|&&b| b).count();
    if base_triangles == 0 {
        return Err(MeshInError::Options(format!(
            "the clamp rule {:?} selects no outer triangle: nothing would hold the body",
            options.clamp
        )));
    }
    if base_triangles == outer.triangles.len() {
        return Err(MeshInError::Options(format!(
            "the clamp rule {:?} selects every outer triangle: nothing would be touchable",
            options.clamp
        )));
    }
    Ok(is_base)
}

/// Writes `text` to `path`, the error naming the path.
fn write_text(path: &Path, text: String) -> Result<(), MeshInError> {
    std::fs::write(path, text).map_err(|source| MeshInError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// The surfaces as a Gmsh 2.2 surface mesh: elementary and physical tags 1 = `OUTER`, 2 =
/// `BASE` (where `is_base`), 3 = `INNER`.
fn surface_msh_text(outer: &SurfaceMesh, inner: Option<&SurfaceMesh>, is_base: &[bool]) -> String {
    let mut text = String::from("$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n");
    let inner_offset = outer.vertices.len();
    let all_vertices: Vec<&[f64; 3]> = outer
        .vertices
        .iter()
        .chain(inner.map_or(&[][..], |m| &m.vertices[..]))
        .collect();
    let _ = writeln!(text, "{}", all_vertices.len());
    for (i, p) in all_vertices.iter().enumerate() {
        let _ = writeln!(text, "{} {:e} {:e} {:e}", i + 1, p[0], p[1], p[2]);
    }
    let inner_count = inner.map_or(0, |m| m.triangles.len());
    let _ = writeln!(
        text,
        "$EndNodes\n$Elements\n{}",
        outer.triangles.len() + inner_count
    );
    let mut id = 0;
    for (t, &base) in outer.triangles.iter().zip(is_base) {
        id += 1;
        let tag = if base { 2 } else { 1 };
        let _ = writeln!(
            text,
            "{id} 2 2 {tag} {tag} {} {} {}",
            t[0] + 1,
            t[1] + 1,
            t[2] + 1
        );
    }
    for t in inner.map_or(&[][..], |m| &m.triangles[..]) {
        id += 1;
        let [a, b, c] = t.map(|i| i as usize + inner_offset + 1);
        let _ = writeln!(text, "{id} 2 2 3 3 {a} {b} {c}");
    }
    text.push_str("$EndElements\n");
    text
}

/// The Gmsh script that bounds a volume by `surface.msh`'s surfaces (a cavity when
/// `with_inner`) and names the physical groups.
fn volume_geo_text(with_inner: bool, max_size: Option<f64>) -> String {
    let mut geo = String::from("Merge \"surface.msh\";\nSurface Loop(1) = {1, 2};\n");
    if with_inner {
        geo.push_str("Surface Loop(2) = {3};\nVolume(1) = {1, 2};\n");
        geo.push_str("Physical Surface(\"INNER\") = {3};\n");
    } else {
        geo.push_str("Volume(1) = {1};\n");
    }
    geo.push_str(
        "Physical Surface(\"OUTER\") = {1};\nPhysical Surface(\"BASE\") = {2};\n\
         Physical Volume(\"TISSUE\") = {1};\nMesh.Optimize = 1;\nMesh.MshFileVersion = 2.2;\n",
    );
    if let Some(h) = max_size {
        let _ = writeln!(geo, "Mesh.MeshSizeMax = {h:e};");
    }
    geo
}

/// Runs Gmsh on `work/volume.geo`, writing `out_abs`; `progress` gets its `Info` lines.
///
/// # Errors
/// [`MeshInError::Gmsh`] when Gmsh is missing, fails, or logs an error (quoted).
fn run_gmsh(
    gmsh: &Path,
    work: &Path,
    out_abs: &Path,
    mut progress: impl FnMut(&str),
) -> Result<(), MeshInError> {
    let output = Command::new(gmsh)
        .current_dir(work)
        .args(["volume.geo", "-3", "-format", "msh22", "-o"])
        .arg(out_abs)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| {
            MeshInError::Gmsh(format!(
                "cannot run {}: {e} (install Debian's gmsh: tests/install-gmsh.sh)",
                gmsh.display()
            ))
        })?;
    let log = String::from_utf8_lossy(&output.stdout).into_owned()
        + &String::from_utf8_lossy(&output.stderr);
    for line in log.lines().filter(|l| l.starts_with("Info")) {
        progress(line);
    }
    let errors: Vec<&str> = log
        .lines()
        .filter(|l| {
            l.starts_with("Error")
                && !["----", "summary", "warnings", "errors", "full log"]
                    .iter()
                    .any(|s| l.contains(s))
        })
        .collect();
    if output.status.success() && errors.is_empty() {
        return Ok(());
    }
    let quoted: String = errors
        .iter()
        .take(6)
        .copied()
        .collect::<Vec<_>>()
        .join("; ");
    let hint = if log.contains("intersect") || log.contains("overlapping") {
        " (the surface intersects itself: repair it before meshing)"
    } else {
        ""
    };
    Err(MeshInError::Gmsh(format!(
        "volume meshing failed{hint}: {}",
        if quoted.is_empty() {
            format!("exit status {}", output.status)
        } else {
            quoted
        }
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit cube as 12 triangles, outward.
    fn cube() -> SurfaceMesh {
        let v = (0..8)
            .map(|i| {
                [
                    f64::from(i & 1),
                    f64::from((i >> 1) & 1),
                    f64::from((i >> 2) & 1),
                ]
            })
            .collect();
        let q = [
            [0, 2, 3, 1],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 4, 6, 2],
            [1, 3, 7, 5],
        ];
        let triangles = q
            .iter()
            .flat_map(|f: &[u32; 4]| [[f[0], f[1], f[2]], [f[0], f[2], f[3]]])
            .collect();
        SurfaceMesh {
            vertices: v,
            triangles,
        }
    }

    #[test]
    fn closed_surfaces_pass_and_holes_are_named() {
        let p = Path::new("cube.stl");
        check_closed(&cube(), p).unwrap();
        let mut open = cube();
        open.triangles.pop();
        let e = check_closed(&open, p).unwrap_err().to_string();
        assert!(
            e.contains("3 boundary edge(s)") && e.contains("0 non-manifold"),
            "{e}"
        );
    }

    #[test]
    fn repeated_vertices_merge_into_one_closed_surface() {
        // Per-face vertices, as STL stores them: 36 vertices for 12 triangles.
        let c = cube();
        let soup = SurfaceMesh {
            vertices: c
                .triangles
                .iter()
                .flat_map(|t| t.map(|i| c.vertices[i as usize]))
                .collect(),
            triangles: (0..12).map(|k| [3 * k, 3 * k + 1, 3 * k + 2]).collect(),
        };
        assert!(check_closed(&soup, Path::new("x")).is_err());
        let merged = merge_coincident(soup);
        assert_eq!(merged.vertices.len(), 8);
        check_closed(&merged, Path::new("x")).unwrap();
    }

    #[test]
    fn obj_and_ply_cubes_read_as_closed_surfaces_with_quads_split() {
        let dir = std::env::temp_dir().join(format!("surface-mesh-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let v: Vec<String> = (0..8)
            .map(|i| format!("{} {} {}", i & 1, (i >> 1) & 1, (i >> 2) & 1))
            .collect();
        let quads = [
            [0, 2, 3, 1],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 6, 7, 3],
            [0, 4, 6, 2],
            [1, 3, 7, 5],
        ];
        let mut obj = String::new();
        for p in &v {
            obj.push_str(&format!("v {p}\n"));
        }
        for q in &quads {
            obj.push_str(&format!(
                "f {} {} {} {}\n",
                q[0] + 1,
                q[1] + 1,
                q[2] + 1,
                q[3] + 1
            ));
        }
        let mut ply = format!(
            "ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n\
             property float z\nelement face 6\nproperty list uchar int vertex_indices\n\
             end_header\n{}\n",
            v.join("\n")
        );
        for q in &quads {
            ply.push_str(&format!("4 {} {} {} {}\n", q[0], q[1], q[2], q[3]));
        }
        for (name, text) in [("cube.obj", obj), ("cube.ply", ply)] {
            let path = dir.join(name);
            std::fs::write(&path, text).unwrap();
            let m = read_surface(&path).unwrap();
            assert_eq!((m.vertices.len(), m.triangles.len()), (8, 12), "{name}");
            check_closed(&m, &path).unwrap();
        }
        let e = read_surface(&dir.join("cube.off")).unwrap_err().to_string();
        assert!(e.contains("unknown surface format"), "{e}");
        // Malformed files: what the format expects, never the text found (issue 47).
        let mark = "S3cr3tMark";
        for (name, text, expect) in [
            (
                "bad.stl",
                format!("solid x\n{mark} 1 2 3\n"),
                "expected binary STL",
            ),
            (
                "bad.ply",
                format!("ply\nformat ascii 1.0\n{mark} vertex 8\nend_header\n"),
                "not a readable PLY file (line 3)",
            ),
            ("bad.obj", format!("v 0 0 0\nv {mark} 1 1\n"), "OBJ"),
        ] {
            let path = dir.join(name);
            std::fs::write(&path, text).unwrap();
            let e = read_surface(&path).unwrap_err().to_string();
            assert!(e.contains(expect) && !e.contains(mark), "{name}: {e}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn clamp_rules_that_select_nothing_or_everything_are_refused() {
        let opts = |clamp| VolumeOptions {
            clamp,
            max_size: None,
            gmsh: PathBuf::from("gmsh"),
        };
        let out = std::env::temp_dir().join("never-written.msh");
        let e = mesh_volume(&cube(), None, &opts(ClampRule::BelowZ(-1.0)), &out, |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("selects no outer triangle"), "{e}");
        let e = mesh_volume(&cube(), None, &opts(ClampRule::AboveZ(-1.0)), &out, |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("selects every outer triangle"), "{e}");
    }
}
