//! Reader for Gmsh `.msh` meshes, ASCII formats 2.2 and 4.1.
//!
//! Sections read: `$MeshFormat`, `$PhysicalNames`, `$Entities` (4.1: entity tag -> physical
//! tags), `$Nodes`, `$Elements`; any other section is skipped. Kept elements:
//!
//! - linear tetrahedra (type 4): all of them, or only those in 3-D physical groups when the file
//!   has any;
//! - triangles (type 2), grouped into [`SurfaceGroup`]s by the name of their 2-D physical group
//!   (from `$PhysicalNames`, else `surface_<tag>`);
//! - points (type 15), grouped into [`NodeGroup`]s by the name of their 0-D physical group (else
//!   `point_<tag>`).
//!
//! Nodes are renumbered `0..N-1` in increasing Gmsh tag order, keeping only the nodes used by
//! the tetrahedra; surface triangles or points that reference other nodes are dropped.
//! Coordinates stay in the file's unit: the scene scales them (see [`crate::scene`]).
//!
//! Neighbours: produces a [`TetMesh`] (see [`crate::mesh`]); used by [`crate::scene`].

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use glam::DVec3;

use crate::ModelError;
use crate::mesh::{NodeGroup, SurfaceGroup, TetMesh};

/// Gmsh element type numbers we use.
const TYPE_TRIANGLE: u32 = 2;
const TYPE_TET: u32 = 4;
const TYPE_POINT: u32 = 15;

/// Reads a Gmsh mesh file (ASCII 2.2 or 4.1) into a [`TetMesh`] in the file's length unit.
///
/// # Errors
/// [`ModelError::Io`] if the file cannot be read; [`ModelError::MeshFormat`] if it is binary,
/// not UTF-8, of an unsupported version or malformed (with the 1-based line when known);
/// [`ModelError::InvalidMesh`] if the tetrahedra are degenerate.
pub fn load_msh(path: &Path) -> Result<TetMesh, ModelError> {
    load_msh_named(path, &path.display().to_string())
}

/// [`load_msh`] with errors naming the file `shown` (the path as a scene or a client wrote
/// it, rather than where it resolved). No message quotes the file's text (see
/// [`read_msh`]).
///
/// # Errors
/// As [`load_msh`].
pub fn load_msh_named(path: &Path, shown: &str) -> Result<TetMesh, ModelError> {
    let shown = shown.to_string();
    let bytes = std::fs::read(path).map_err(|source| ModelError::Io {
        path: shown.clone(),
        source,
    })?;
    match String::from_utf8(bytes) {
        Ok(text) => read_msh(&text, &shown),
        Err(e) => {
            // A binary file still starts with an ASCII `$MeshFormat` header: report that.
            let bytes = e.into_bytes();
            let head = String::from_utf8_lossy(&bytes[..bytes.len().min(200)]).into_owned();
            let mut lines = head.lines();
            if lines.next().map(str::trim) == Some("$MeshFormat")
                && let Some(l) = lines.next()
            {
                check_format_line(l, 2, &shown)?;
            }
            Err(fmt_err(
                &shown,
                None,
                "the file is not UTF-8 text (binary .msh files are not supported; re-export as ASCII)",
            ))
        }
    }
}

/// Parses the text of a Gmsh mesh (ASCII 2.2 or 4.1) into a [`TetMesh`] in the file's length
/// unit. `path_for_errors` names the source in error messages.
///
/// The tetrahedra are positively oriented ([`TetMesh::orient_and_check`]) and the surface
/// triangles outward oriented ([`TetMesh::orient_surfaces_outward`]).
///
/// Error messages give the file, the line and what was expected there, never what was found:
/// a daemon reads files a client names, and must not send back a line of a file that is not
/// a mesh (issue 47).
///
/// # Errors
/// [`ModelError::MeshFormat`] for binary files, unsupported versions, missing sections, bad
/// numbers or truncated sections (with the 1-based line number); [`ModelError::InvalidMesh`] if
/// there are no tetrahedra or some are degenerate.
pub fn read_msh(text: &str, path_for_errors: &str) -> Result<TetMesh, ModelError> {
    let mut cur = Cursor::new(text, path_for_errors);
    let mut version: Option<Version> = None;
    let mut names: HashMap<(u32, i64), String> = HashMap::new();
    let mut entities: HashMap<(u32, i64), Vec<i64>> = HashMap::new();
    let mut nodes: Option<BTreeMap<u64, DVec3>> = None;
    let mut elements: Option<Vec<Element>> = None;

    while let Some((line_no, line)) = cur.next_line() {
        let line = line.trim();
        let Some(section) = line.strip_prefix('$') else {
            return Err(cur.err(
                line_no,
                "expected a `$Section` header (a line starting with `$`)",
            ));
        };
        if section.starts_with("End") {
            return Err(cur.err(line_no, "a `$End...` line outside its section"));
        }
        if section != "MeshFormat" && version.is_none() {
            return Err(cur.err(line_no, "the file must start with a $MeshFormat section"));
        }
        match section {
            "MeshFormat" => {
                let (n, l) = cur.expect_line("$MeshFormat")?;
                version = Some(check_format_line(l, n, path_for_errors)?);
            }
            "PhysicalNames" => read_physical_names(&mut cur, &mut names)?,
            "Entities" if version == Some(Version::V41) => read_entities(&mut cur, &mut entities)?,
            "Nodes" => {
                nodes = Some(match version {
                    Some(Version::V22) => read_nodes_22(&mut cur)?,
                    _ => read_nodes_41(&mut cur)?,
                })
            }
            "Elements" => {
                elements = Some(match version {
                    Some(Version::V22) => read_elements_22(&mut cur)?,
                    _ => read_elements_41(&mut cur, &entities)?,
                })
            }
            _ => {
                cur.skip_section(section)?;
                continue;
            }
        }
        cur.expect_end(section)?;
    }
    let last = cur.line_count();
    if version.is_none() {
        return Err(fmt_err(
            path_for_errors,
            Some(last.max(1)),
            "no $MeshFormat section (is this a Gmsh .msh file?)",
        ));
    }
    let Some(nodes) = nodes else {
        return Err(fmt_err(
            path_for_errors,
            Some(last),
            "reached the end of the file without a $Nodes section",
        ));
    };
    let Some(mut elements) = elements else {
        return Err(fmt_err(
            path_for_errors,
            Some(last),
            "reached the end of the file without an $Elements section",
        ));
    };
    elements.sort_by_key(|e| e.tag);
    assemble(nodes, &elements, &names, path_for_errors)
}

/// Supported format versions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Version {
    V22,
    V41,
}

/// One element of interest: Gmsh element tag, type, physical tags, node tags.
struct Element {
    tag: u64,
    line: usize,
    kind: u32,
    physical: Vec<i64>,
    nodes: Vec<u64>,
}

fn fmt_err(path: &str, line: Option<usize>, message: impl Into<String>) -> ModelError {
    ModelError::MeshFormat {
        path: path.to_string(),
        line,
        message: message.into(),
    }
}

/// Checks the `version file-type data-size` line of `$MeshFormat`.
fn check_format_line(line: &str, line_no: usize, path: &str) -> Result<Version, ModelError> {
    let mut it = line.split_whitespace();
    let ver = it.next().unwrap_or("");
    let file_type = it.next().unwrap_or("");
    if file_type != "0" {
        if file_type == "1" {
            return Err(fmt_err(
                path,
                Some(line_no),
                "binary Gmsh files are not supported (file-type 1); re-export as ASCII",
            ));
        }
        return Err(fmt_err(
            path,
            Some(line_no),
            "malformed $MeshFormat line: expected `version file-type data-size`, e.g. `4.1 0 8`",
        ));
    }
    match ver {
        "2.2" | "2.1" | "2" | "2.0" => Ok(Version::V22),
        "4.1" => Ok(Version::V41),
        _ => Err(fmt_err(
            path,
            Some(line_no),
            "unsupported Gmsh format version: expected ASCII 2.2 or 4.1",
        )),
    }
}

/// A line cursor over the text that skips blank lines and remembers line numbers (1-based).
struct Cursor<'a> {
    lines: Vec<&'a str>,
    pos: usize,
    path: &'a str,
}

impl<'a> Cursor<'a> {
    fn new(text: &'a str, path: &'a str) -> Self {
        Self {
            lines: text.lines().collect(),
            pos: 0,
            path,
        }
    }

    fn line_count(&self) -> usize {
        self.lines.len()
    }

    fn err(&self, line: usize, message: impl Into<String>) -> ModelError {
        fmt_err(self.path, Some(line), message)
    }

    /// The next non-blank line and its 1-based number.
    fn next_line(&mut self) -> Option<(usize, &'a str)> {
        while self.pos < self.lines.len() {
            let l = self.lines[self.pos];
            self.pos += 1;
            if !l.trim().is_empty() {
                return Some((self.pos, l));
            }
        }
        None
    }

    /// The next non-blank line, or an "unexpected end of file" error naming `section`.
    fn expect_line(&mut self, section: &str) -> Result<(usize, &'a str), ModelError> {
        let n = self.lines.len();
        self.next_line().ok_or_else(|| {
            fmt_err(
                self.path,
                Some(n.max(1)),
                format!("unexpected end of file in {section} (truncated?)"),
            )
        })
    }

    /// The next line, split into whitespace-separated numbers of type `T`.
    fn numbers<T: std::str::FromStr>(
        &mut self,
        section: &str,
    ) -> Result<(usize, Vec<T>), ModelError> {
        let (n, l) = self.expect_line(section)?;
        if l.trim_start().starts_with('$') {
            return Err(self.err(
                n,
                format!("{section} ended too early: expected more lines (counts do not match)"),
            ));
        }
        let v = l
            .split_whitespace()
            .enumerate()
            .map(|(i, w)| {
                w.parse::<T>().map_err(|_| {
                    self.err(
                        n,
                        format!("{section}: expected a number as field {}", i + 1),
                    )
                })
            })
            .collect::<Result<Vec<T>, _>>()?;
        Ok((n, v))
    }

    /// Like [`Cursor::numbers`] but requires at least `min` numbers.
    fn numbers_min<T: std::str::FromStr>(
        &mut self,
        section: &str,
        min: usize,
        what: &str,
    ) -> Result<(usize, Vec<T>), ModelError> {
        let (n, v) = self.numbers::<T>(section)?;
        if v.len() < min {
            return Err(self.err(
                n,
                format!("{section}: expected {what} ({min} numbers) on this line"),
            ));
        }
        Ok((n, v))
    }

    /// Consumes the `$End<section>` line.
    fn expect_end(&mut self, section: &str) -> Result<(), ModelError> {
        let (n, l) = self.expect_line(&format!("${section}"))?;
        let want = format!("$End{section}");
        if l.trim() != want {
            return Err(self.err(n, format!("expected `{want}` (counts do not match?)")));
        }
        Ok(())
    }

    /// Skips an unknown section up to its `$End<section>` line.
    fn skip_section(&mut self, section: &str) -> Result<(), ModelError> {
        let want = format!("$End{section}");
        while let Some((_, l)) = self.next_line() {
            if l.trim() == want {
                return Ok(());
            }
        }
        Err(fmt_err(
            self.path,
            Some(self.lines.len().max(1)),
            "unexpected end of file: an unknown section has no `$End...` line",
        ))
    }
}

/// Converts a count read from the file.
fn count(cur: &Cursor<'_>, line: usize, v: i64, what: &str) -> Result<usize, ModelError> {
    usize::try_from(v).map_err(|_| cur.err(line, format!("expected a {what} of 0 or more")))
}

fn read_physical_names(
    cur: &mut Cursor<'_>,
    names: &mut HashMap<(u32, i64), String>,
) -> Result<(), ModelError> {
    const S: &str = "$PhysicalNames";
    let (n0, v) = cur.numbers_min::<i64>(S, 1, "the number of names")?;
    let total = count(cur, n0, v[0], "count")?;
    for _ in 0..total {
        let (n, l) = cur.expect_line(S)?;
        let mut it = l.split_whitespace();
        let dim = it.next().and_then(|w| w.parse::<u32>().ok());
        let tag = it.next().and_then(|w| w.parse::<i64>().ok());
        let (Some(dim), Some(tag)) = (dim, tag) else {
            return Err(cur.err(n, "$PhysicalNames: expected `dim tag \"name\"`"));
        };
        let rest = l.trim();
        let name = match (rest.find('"'), rest.rfind('"')) {
            (Some(a), Some(b)) if b > a => rest[a + 1..b].to_string(),
            _ => {
                return Err(cur.err(
                    n,
                    "$PhysicalNames: expected a quoted name (`dim tag \"name\"`)",
                ));
            }
        };
        names.insert((dim, tag), name);
    }
    Ok(())
}

fn read_entities(
    cur: &mut Cursor<'_>,
    entities: &mut HashMap<(u32, i64), Vec<i64>>,
) -> Result<(), ModelError> {
    const S: &str = "$Entities";
    let (n0, v) = cur.numbers_min::<i64>(S, 4, "numPoints numCurves numSurfaces numVolumes")?;
    for dim in 0..4u32 {
        let k = count(cur, n0, v[dim as usize], "entity count")?;
        for _ in 0..k {
            let (n, e) = cur.numbers::<f64>(S)?;
            // Points: tag x y z nphys phys...; others: tag 6 bbox numbers nphys phys... nbound ...
            let at = if dim == 0 { 4 } else { 7 };
            let nphys = e.get(at).copied().unwrap_or(-1.0);
            if e.len() <= at
                || nphys < 0.0
                || nphys.fract() != 0.0
                || e.len() < at + 1 + nphys as usize
            {
                return Err(cur.err(n, format!("$Entities: malformed {}-D entity line", dim)));
            }
            let phys = e[at + 1..at + 1 + nphys as usize]
                .iter()
                .map(|&p| p as i64)
                .collect();
            entities.insert((dim, e[0] as i64), phys);
        }
    }
    Ok(())
}

fn check_xyz(cur: &Cursor<'_>, line: usize, v: &[f64]) -> Result<DVec3, ModelError> {
    let p = DVec3::new(v[0], v[1], v[2]);
    if !p.is_finite() {
        return Err(cur.err(line, "non-finite node coordinate"));
    }
    Ok(p)
}

fn insert_node(
    cur: &Cursor<'_>,
    nodes: &mut BTreeMap<u64, DVec3>,
    line: usize,
    tag: i64,
    p: DVec3,
) -> Result<(), ModelError> {
    let t = u64::try_from(tag).map_err(|_| cur.err(line, "expected a node tag of 0 or more"))?;
    if nodes.insert(t, p).is_some() {
        return Err(cur.err(line, "expected a new node tag: this one appears twice"));
    }
    Ok(())
}

fn read_nodes_22(cur: &mut Cursor<'_>) -> Result<BTreeMap<u64, DVec3>, ModelError> {
    const S: &str = "$Nodes";
    let (n0, v) = cur.numbers_min::<i64>(S, 1, "the number of nodes")?;
    let total = count(cur, n0, v[0], "node count")?;
    let mut nodes = BTreeMap::new();
    for _ in 0..total {
        let (n, l) = cur.expect_line(S)?;
        let w: Vec<&str> = l.split_whitespace().collect();
        if l.trim_start().starts_with('$') || w.len() < 4 {
            return Err(cur.err(n, "$Nodes: expected `tag x y z` (truncated section?)"));
        }
        let tag: i64 = w[0]
            .parse()
            .map_err(|_| cur.err(n, "$Nodes: expected an integer node tag as field 1"))?;
        let mut xyz = [0.0; 3];
        for k in 0..3 {
            xyz[k] = w[k + 1]
                .parse()
                .map_err(|_| cur.err(n, format!("$Nodes: expected a number as field {}", k + 2)))?;
        }
        let p = check_xyz(cur, n, &xyz)?;
        insert_node(cur, &mut nodes, n, tag, p)?;
    }
    Ok(nodes)
}

fn read_nodes_41(cur: &mut Cursor<'_>) -> Result<BTreeMap<u64, DVec3>, ModelError> {
    const S: &str = "$Nodes";
    let (n0, v) = cur.numbers_min::<i64>(S, 4, "numEntityBlocks numNodes minNodeTag maxNodeTag")?;
    let blocks = count(cur, n0, v[0], "block count")?;
    let total = count(cur, n0, v[1], "node count")?;
    let mut nodes = BTreeMap::new();
    for _ in 0..blocks {
        let (nb, b) =
            cur.numbers_min::<i64>(S, 4, "entityDim entityTag parametric numNodesInBlock")?;
        let k = count(cur, nb, b[3], "node count")?;
        let mut tags = Vec::with_capacity(k);
        for _ in 0..k {
            let (n, t) = cur.numbers_min::<i64>(S, 1, "a node tag")?;
            if t.len() != 1 {
                return Err(cur.err(n, "$Nodes: expected one node tag per line"));
            }
            tags.push(t[0]);
        }
        for &tag in &tags {
            let (n, xyz) = cur.numbers_min::<f64>(S, 3, "x y z")?;
            let p = check_xyz(cur, n, &xyz)?;
            insert_node(cur, &mut nodes, n, tag, p)?;
        }
    }
    if nodes.len() != total {
        return Err(cur.err(
            n0,
            format!(
                "$Nodes announces {total} nodes but its blocks hold {}",
                nodes.len()
            ),
        ));
    }
    Ok(nodes)
}

/// Number of nodes of the element types we keep.
fn nodes_of_type(kind: u32) -> Option<usize> {
    match kind {
        TYPE_TRIANGLE => Some(3),
        TYPE_TET => Some(4),
        TYPE_POINT => Some(1),
        _ => None,
    }
}

fn node_tags(cur: &Cursor<'_>, line: usize, v: &[i64]) -> Result<Vec<u64>, ModelError> {
    v.iter()
        .map(|&t| u64::try_from(t).map_err(|_| cur.err(line, "expected node tags of 0 or more")))
        .collect()
}

fn read_elements_22(cur: &mut Cursor<'_>) -> Result<Vec<Element>, ModelError> {
    const S: &str = "$Elements";
    let (n0, v) = cur.numbers_min::<i64>(S, 1, "the number of elements")?;
    let total = count(cur, n0, v[0], "element count")?;
    let mut out = Vec::new();
    for _ in 0..total {
        let (n, e) = cur.numbers_min::<i64>(S, 3, "`tag type ntags tags... nodes...`")?;
        let (tag, kind, ntags) = (e[0], e[1], count(cur, n, e[2], "tag count")?);
        let Some(nn) = u32::try_from(kind).ok().and_then(nodes_of_type) else {
            continue;
        };
        if e.len() != 3 + ntags + nn {
            return Err(cur.err(
                n,
                format!(
                    "$Elements: expected {} numbers for an element of type {kind} with {ntags} tags",
                    3 + ntags + nn
                ),
            ));
        }
        let physical = if ntags >= 1 && e[3] != 0 {
            vec![e[3]]
        } else {
            Vec::new()
        };
        let nodes = node_tags(cur, n, &e[3 + ntags..])?;
        out.push(Element {
            tag: tag.max(0) as u64,
            line: n,
            kind: kind as u32,
            physical,
            nodes,
        });
    }
    Ok(out)
}

fn read_elements_41(
    cur: &mut Cursor<'_>,
    entities: &HashMap<(u32, i64), Vec<i64>>,
) -> Result<Vec<Element>, ModelError> {
    const S: &str = "$Elements";
    let (n0, v) = cur.numbers_min::<i64>(
        S,
        4,
        "numEntityBlocks numElements minElementTag maxElementTag",
    )?;
    let blocks = count(cur, n0, v[0], "block count")?;
    let total = count(cur, n0, v[1], "element count")?;
    let mut seen = 0usize;
    let mut out = Vec::new();
    for _ in 0..blocks {
        let (nb, b) =
            cur.numbers_min::<i64>(S, 4, "entityDim entityTag elementType numElementsInBlock")?;
        let dim = u32::try_from(b[0])
            .map_err(|_| cur.err(nb, format!("bad entity dimension {}", b[0])))?;
        let kind = b[2];
        let k = count(cur, nb, b[3], "element count")?;
        seen += k;
        let nn = u32::try_from(kind).ok().and_then(nodes_of_type);
        let physical = entities.get(&(dim, b[1])).cloned().unwrap_or_default();
        for _ in 0..k {
            let (n, e) = cur.numbers_min::<i64>(S, 2, "`tag nodes...`")?;
            let Some(nn) = nn else { continue };
            if e.len() != 1 + nn {
                return Err(cur.err(
                    n,
                    format!(
                        "$Elements: expected {} numbers for an element of type {kind}",
                        1 + nn
                    ),
                ));
            }
            let nodes = node_tags(cur, n, &e[1..])?;
            out.push(Element {
                tag: e[0].max(0) as u64,
                line: n,
                kind: kind as u32,
                physical: physical.clone(),
                nodes,
            });
        }
    }
    if seen != total {
        return Err(cur.err(
            n0,
            format!("$Elements announces {total} elements but its blocks hold {seen}"),
        ));
    }
    Ok(out)
}

/// The named surfaces (triangles) and node groups (points) of `elements` in the compact
/// numbering `index` (elements with a node outside it are left out); unnamed groups are called
/// `surface_TAG` and `point_TAG`.
fn physical_groups(
    elements: &[Element],
    index: &HashMap<u64, u32>,
    names: &HashMap<(u32, i64), String>,
) -> (Vec<SurfaceGroup>, Vec<NodeGroup>) {
    let map = |e: &Element| -> Option<Vec<u32>> {
        e.nodes.iter().map(|t| index.get(t).copied()).collect()
    };
    let mut surfaces: BTreeMap<i64, Vec<[u32; 3]>> = BTreeMap::new();
    let mut points: BTreeMap<i64, Vec<u32>> = BTreeMap::new();
    for e in elements {
        match e.kind {
            TYPE_TRIANGLE => {
                if let Some(v) = map(e) {
                    for &p in &e.physical {
                        surfaces.entry(p).or_default().push([v[0], v[1], v[2]]);
                    }
                }
            }
            TYPE_POINT => {
                if let Some(v) = map(e) {
                    for &p in &e.physical {
                        points.entry(p).or_default().push(v[0]);
                    }
                }
            }
            _ => {}
        }
    }
    let surfaces = surfaces
        .into_iter()
        .map(|(tag, triangles)| SurfaceGroup {
            name: names
                .get(&(2, tag))
                .cloned()
                .unwrap_or_else(|| format!("surface_{tag}")),
            triangles,
        })
        .collect();
    let node_groups = points
        .into_iter()
        .map(|(tag, mut nodes)| {
            nodes.sort_unstable();
            nodes.dedup();
            NodeGroup {
                name: names
                    .get(&(0, tag))
                    .cloned()
                    .unwrap_or_else(|| format!("point_{tag}")),
                nodes,
            }
        })
        .collect();
    (surfaces, node_groups)
}

/// Builds the compacted [`TetMesh`] from the parsed nodes and elements.
fn assemble(
    nodes: BTreeMap<u64, DVec3>,
    elements: &[Element],
    names: &HashMap<(u32, i64), String>,
    path: &str,
) -> Result<TetMesh, ModelError> {
    for e in elements {
        if e.nodes.iter().any(|t| !nodes.contains_key(t)) {
            return Err(fmt_err(
                path,
                Some(e.line),
                "expected nodes defined in $Nodes: this element names another",
            ));
        }
    }
    let has_3d_groups = names.keys().any(|&(d, _)| d == 3)
        || elements
            .iter()
            .any(|e| e.kind == TYPE_TET && !e.physical.is_empty());
    let tets: Vec<&Element> = elements
        .iter()
        .filter(|e| e.kind == TYPE_TET && (!has_3d_groups || !e.physical.is_empty()))
        .collect();
    if tets.is_empty() {
        return Err(fmt_err(
            path,
            None,
            "no linear tetrahedra (element type 4) in the mesh (only first-order tetrahedral meshes are supported)",
        ));
    }
    // Compact numbering in increasing Gmsh tag order.
    let mut used: Vec<u64> = tets.iter().flat_map(|e| e.nodes.iter().copied()).collect();
    used.sort_unstable();
    used.dedup();
    let index: HashMap<u64, u32> = used
        .iter()
        .enumerate()
        .map(|(i, &t)| (t, i as u32))
        .collect();
    let mut mesh = TetMesh {
        nodes: used.iter().map(|t| nodes[t]).collect(),
        tets: tets
            .iter()
            .map(|e| [0, 1, 2, 3].map(|k| index[&e.nodes[k]]))
            .collect(),
        tet_edge_nodes: Vec::new(),
        surfaces: Vec::new(),
        node_groups: Vec::new(),
    };
    (mesh.surfaces, mesh.node_groups) = physical_groups(elements, &index, names);
    mesh.orient_and_check()?;
    mesh.orient_surfaces_outward();
    Ok(mesh)
}
