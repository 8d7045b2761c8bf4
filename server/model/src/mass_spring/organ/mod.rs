//! The organ calibration: the surface's probe force follows the organ's force-indentation
//! reference (issue 46 section 4), by the paper's own device, spring constants that vary with the
//! contact's displacement from a table computed offline (Zhang, Payandeh & Dill section 3.2.4,
//! there for the subdivided area, eq. 4).
//!
//! A surface on home springs pressed by the probe's kernel patch stiffens as the probe sinks:
//! the patch takes in nodes the sphere has not displaced, which hold it up (on the left
//! ventricle's surface the force over depth grows from 7 to 22 N/m between 0.25 and 4 mm, with
//! the mesh springs at a hundredth of the home springs still from 7 to 17 N/m), where the organ's
//! wall responds almost linearly (10-11 N/m). No constant spring can follow that, so every
//! spring constant of the body (home and mesh, coarse and subdivided) is multiplied by a
//! *contact factor* `beta`: per node `i` and probe sphere depth `s` (since version 4 the
//! sphere's depth below the organ at the probe's foot, [`foot`]: below the flat rest triangle
//! along the contact normal plus the organ's height over it; the kernel plane's travel below
//! its rest position without a foot) the table holds
//!
//! `beta_i(s) = F_ref(i, s) / F_1(i, s)`,
//!
//! `F_1` the static probe force of the surface with its constant springs pressed at node `i`
//! along its rest normal to sphere depth `s` (through the body's own tick, held until it
//! settles), `F_ref` the organ's reference at that node. Scaling every spring by the same factor
//! scales the static force at a given shape by that factor, so the body pressed at node `i` to
//! depth `s` gives `F_ref` exactly, provided the probe's patch is the run time's: the patch is
//! gathered and weighted around the device, which sits the coupling's stretch below the
//! sphere, so the calibration presses with the springs already scaled by the `beta` it
//! measures (found with the depth in the same holds; session 14: with the constant springs
//! the 4 mm hemisphere's table read +20-25 % at 4 mm, [`press_sphere_depths`]).
//!
//! A spring surface pressed *between* nodes answers otherwise than on a node (on the left
//! ventricle's surface, with the node's factor, up to +13 % at an edge's midpoint never
//! subdivided and +29 % subdivided: docs/accuracy.md), so the table has a row per *site*: every
//! coarse node and every coarse edge's midpoint, each pressed there (along the mean of its
//! ends' normals for an edge), never subdivided (`factor`) and with the run-time subdivision
//! the scene configures around the contact (`factor_subdivided`: the eq. 4 table keeps the
//! force at a node, not between nodes; a long edge's press in its nearer end's area,
//! [`edge_area_end`]). Since version 5 the subdivided column also has a row at the centroid of
//! each coarse triangle's three corner Loop children (pressed in the corner's area): between a
//! node and its edges' midpoints a subdivided surface's needed factor stays near the node's
//! and rises only close to the midpoints (a press there bears on one type-2 node), which a
//! linear interpolation over the child cannot follow (session 16: +10 % at the point h4 of
//! `hemisphere-springs` at 0.25 mm; docs/accuracy.md). At run time `beta` is interpolated in
//! `s` and at the probe's *foot* on the coarse rest surface ([`foot`]: where the line through
//! the sphere's centre along the contact normal meets the rest triangles, which for a press
//! along a site's normal is the site itself, so a user's press there reads what the
//! calibration measured) over its coarse triangle's four Loop children (corners: coarse nodes
//! and edge midpoints, exactly the sites): linearly over the middle child, over the three
//! triangles a corner child's centroid makes with its sides in a corner child (with the
//! coarse column, whose centroid rows are their corners' mean, that is the same linear
//! interpolation). So it is continuous while the probe slides and constant during a
//! hold; the centroid of a triangle takes the mean of its edges' factors (measured:
//! docs/accuracy.md).
//!
//! The reference ([`OrganReference`], a CSV beside the scene) gives force against sphere depth
//! at a few points of the organ's surface, from an FEM solve of the organ pressed by the exact
//! sphere (`server/model/examples/springs_reference/`). Between them the target is interpolated
//! along an axis of symmetry of the organ (scene key `reference_axis`: the left ventricle and the
//! hemisphere are bodies of revolution about z, so the reference depends on the height only):
//! linearly between the two points that bracket the node's coordinate on the axis, the nearest
//! point's curve beyond them.
//!
//! Owns: the reference, the table and its calibration. Uses: [`super::calibration`] (the local
//! patch and its static probe press), [`super::surface`].

use std::fmt::Write as _;

use glam::DVec3;

use super::MassSpringParams;
use super::calibration::{Fnv, table_error, table_header};
use super::surface::SpringSurface;
use crate::ModelError;
use crate::contact::ProbeParams;

mod calibrate;
pub mod foot;

pub use calibrate::{
    DEPTH_ATTEMPTS, DEPTH_FALLBACK_TOLERANCE, DEPTH_TOLERANCE, FACTOR_TOLERANCE, MAX_HOLD_TICKS,
    OrganSetup, RAMP_TICKS, SETTLE_TOLERANCE, SETTLE_WINDOW_TICKS, SUBDIVIDED_FACTOR_SPREAD,
    calibrate_child_site, calibrate_organ, calibrate_organ_node, child_of_site, edge_area_end,
    press_sphere_depths, site_press,
};

/// Version of the organ table's definition; part of its key. 3 (session 5): in a subdivided
/// area (the `factor_subdivided` column) the depth is the sphere's depth below the flat rest
/// triangle at the probe's foot ([`foot`]), at calibration and at run time alike (was the
/// kernel plane's travel, which the coarse column keeps).
/// 4 (session 13): on the coarse surface too (wherever the probe has a foot), the depth is the
/// sphere's depth below the organ at the foot: the flat triangle's plus the organ's height
/// over it (the arcs over its edges), as in a subdivided area since session 12.
/// 5 (session 16): the sites at the corner Loop children's centroids ([`OrganTable::child_site`]).
pub const ORGAN_VERSION: u32 = 5;

/// The column header of a reference file (further columns may follow, e.g. each mesh level's
/// force; they are not read).
pub const REFERENCE_COLUMNS: &str =
    "point,x_mm,y_mm,z_mm,dx,dy,dz,depth_mm,force_n,uncertainty_n,device_depth_mm";

/// The column header of an organ table file.
pub const TABLE_COLUMNS: &str =
    "site,sample,depth_m,factor,factor_subdivided,target_force_n,spring_force_n,subdivided_force_n";

/// The factors a node may take; a calibrated factor outside is an error (a reference or a
/// surface far from each other: fix the scene's constants).
pub const FACTOR_RANGE: (f64, f64) = (1e-3, 1e3);

/// One point of the organ's reference: where and along which direction the sphere presses, and
/// the force against its depth.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferencePoint {
    /// Name (the reference file's `point` column).
    pub name: String,
    /// The point on the organ's surface, m.
    pub position_m: DVec3,
    /// The press direction (unit).
    pub direction: DVec3,
    /// Sphere depths below the organ's surface, m, increasing (the same for every point).
    pub depth_m: Vec<f64>,
    /// Force magnitude at each depth, N.
    pub force_n: Vec<f64>,
    /// The reference's uncertainty at each depth, N.
    pub uncertainty_n: Vec<f64>,
    /// The device's depth at each depth (the sphere's plus the scenes' coupling stretch), m.
    pub device_depth_m: Vec<f64>,
}

impl ReferencePoint {
    /// The force at sphere depth `depth_m` (m), N: linear between the reference's depths,
    /// proportional to the depth below the first (the force vanishes at zero depth), the last
    /// slope beyond the last.
    pub fn force_at(&self, depth_m: f64) -> f64 {
        interpolate(&self.depth_m, &self.force_n, depth_m)
    }
}

/// Linear interpolation through `(xs, ys)` (xs increasing, at least one), through the origin
/// below the first point and along the last segment beyond the last.
fn interpolate(xs: &[f64], ys: &[f64], x: f64) -> f64 {
    let n = xs.len();
    if n == 1 || x <= xs[0] {
        return ys[0] * (x / xs[0]).max(0.0);
    }
    let k = xs.partition_point(|&v| v < x).clamp(1, n - 1);
    let t = (x - xs[k - 1]) / (xs[k] - xs[k - 1]);
    ys[k - 1] + t * (ys[k] - ys[k - 1])
}

/// The organ's force-indentation reference at points of its surface (module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct OrganReference {
    points: Vec<ReferencePoint>,
    /// FNV-1a hash of the file's text: part of the table's key.
    text_hash: u64,
}

impl OrganReference {
    /// The points.
    pub fn points(&self) -> &[ReferencePoint] {
        &self.points
    }

    /// The point named `name`.
    pub fn point(&self, name: &str) -> Option<&ReferencePoint> {
        self.points.iter().find(|p| p.name == name)
    }

    /// Parses a reference file's text (`path` names it in errors): `#` comments, the header
    /// [`REFERENCE_COLUMNS`] (further columns allowed), then rows grouped by point, depths
    /// increasing; every point with the same depths.
    ///
    /// # Errors
    /// [`ModelError::Calibration`] naming the file and line for a missing header, a malformed,
    /// non-finite or negative number, a zero direction, depths that do not increase, points
    /// with different depths, or no point.
    pub fn parse(text: &str, path: &str) -> Result<Self, ModelError> {
        let err = |line: usize, m: String| table_error(path, line, m);
        let mut points: Vec<ReferencePoint> = Vec::new();
        let mut header = false;
        for (k, line) in text.lines().enumerate() {
            let ln = k + 1;
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            if !header {
                if !line.starts_with(REFERENCE_COLUMNS) {
                    return Err(err(
                        ln,
                        format!("expected the header `{REFERENCE_COLUMNS}`, got `{line}`"),
                    ));
                }
                header = true;
                continue;
            }
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            if f.len() < 11 {
                return Err(err(
                    ln,
                    format!("expected 11 fields or more, got {}", f.len()),
                ));
            }
            let num = |s: &str| -> Result<f64, ModelError> {
                let v: f64 = s
                    .parse()
                    .map_err(|e| err(ln, format!("bad number `{s}`: {e}")))?;
                if v.is_finite() {
                    Ok(v)
                } else {
                    Err(err(ln, format!("`{s}` is not finite")))
                }
            };
            let v: Vec<f64> = f[1..11].iter().map(|s| num(s)).collect::<Result<_, _>>()?;
            let position = DVec3::new(v[0], v[1], v[2]) * 1e-3;
            let direction = DVec3::new(v[3], v[4], v[5]).normalize_or_zero();
            if direction == DVec3::ZERO {
                return Err(err(ln, "the direction is zero".into()));
            }
            let (depth, force, unc, device) = (v[6] * 1e-3, v[7], v[8], v[9] * 1e-3);
            if !(depth > 0.0 && force >= 0.0 && unc >= 0.0) {
                return Err(err(
                    ln,
                    "depth must be > 0, force and uncertainty >= 0".into(),
                ));
            }
            let new_point = points.last().is_none_or(|p| p.name != f[0]);
            if new_point {
                if points.iter().any(|p| p.name == f[0]) {
                    return Err(err(ln, format!("point `{}` appears twice", f[0])));
                }
                points.push(ReferencePoint {
                    name: f[0].to_string(),
                    position_m: position,
                    direction,
                    depth_m: Vec::new(),
                    force_n: Vec::new(),
                    uncertainty_n: Vec::new(),
                    device_depth_m: Vec::new(),
                });
            }
            let p = points.last_mut().expect("pushed above");
            if p.depth_m.last().is_some_and(|&d| depth <= d) {
                return Err(err(ln, format!("point `{}`: depths must increase", p.name)));
            }
            p.depth_m.push(depth);
            p.force_n.push(force);
            p.uncertainty_n.push(unc);
            p.device_depth_m.push(device);
        }
        let Some(first) = points.first() else {
            return Err(err(0, "no reference point".into()));
        };
        if let Some(p) = points.iter().find(|p| p.depth_m != first.depth_m) {
            return Err(err(
                0,
                format!(
                    "point `{}` has other depths than `{}`: every point needs the same",
                    p.name, first.name
                ),
            ));
        }
        let mut h = Fnv::new();
        h.bytes(text.as_bytes());
        Ok(Self {
            points,
            text_hash: h.0,
        })
    }

    /// The common sphere depths of the points, m.
    pub fn depths_m(&self) -> &[f64] {
        &self.points[0].depth_m
    }

    /// The target force curve (N, at [`OrganReference::depths_m`]) at a surface point
    /// `position_m` (m): the points' curves interpolated along `axis` (unit) by the
    /// coordinate `position . axis` (module documentation).
    pub fn target_at(&self, axis: DVec3, position_m: DVec3) -> Vec<f64> {
        let a = position_m.dot(axis);
        let mut order: Vec<(f64, usize)> = self
            .points
            .iter()
            .enumerate()
            .map(|(k, p)| (p.position_m.dot(axis), k))
            .collect();
        order.sort_by(|x, y| x.0.total_cmp(&y.0));
        let curve = |k: usize| self.points[k].force_n.clone();
        let n = order.len();
        if a <= order[0].0 {
            return curve(order[0].1);
        }
        if a >= order[n - 1].0 {
            return curve(order[n - 1].1);
        }
        let j = order.partition_point(|o| o.0 < a).clamp(1, n - 1);
        let ((a0, k0), (a1, k1)) = (order[j - 1], order[j]);
        let t = if a1 > a0 { (a - a0) / (a1 - a0) } else { 0.5 };
        let (f0, f1) = (&self.points[k0].force_n, &self.points[k1].force_n);
        f0.iter().zip(f1).map(|(x, y)| x + t * (y - x)).collect()
    }
}

/// One site's row of the organ table (a coarse node, a coarse edge's midpoint, or a corner
/// Loop child's centroid).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OrganRow {
    /// The contact factor `beta` of the coarse surface at each of the table's depths.
    pub factor: Vec<f64>,
    /// The contact factor with the node's area subdivided (the scene's rings and area
    /// constants; equal to `factor` when the eq. 4 table keeps the coarse force, or without
    /// subdivision).
    pub factor_subdivided: Vec<f64>,
    /// The reference's force at the site at each depth, N.
    pub target_force_n: Vec<f64>,
    /// The coarse surface's force with constant springs at each depth, N (0 for a fixed node,
    /// whose factors are its free neighbours' mean).
    pub spring_force_n: Vec<f64>,
    /// The subdivided surface's force at each depth, N (as `spring_force_n`; 0 where the
    /// subdivided factor is the coarse one).
    pub subdivided_force_n: Vec<f64>,
}

/// The organ table of a surface (module documentation): per *site* the contact factor over
/// sphere depth. The sites are the coarse nodes `0..N`, then one per coarse edge `e` (its
/// midpoint, site `N + e`: the number Loop subdivision gives the edge's new node), then three
/// per coarse triangle `t` (the centroids of its corner Loop children, site `N + E + 3 t + i`
/// for corner `i`: [`OrganTable::child_site`]; version 5).
#[derive(Debug, Clone, PartialEq)]
pub struct OrganTable {
    key: u64,
    depths_m: Vec<f64>,
    nodes: usize,
    /// Sites at the corner children's centroids (three per coarse triangle), the last rows.
    children: usize,
    rows: Vec<OrganRow>,
}

impl OrganTable {
    /// The table's key ([`organ_key`]).
    pub fn key(&self) -> u64 {
        self.key
    }

    /// Number of coarse nodes.
    pub fn node_count(&self) -> usize {
        self.nodes
    }

    /// Number of coarse edges (sites after the nodes).
    pub fn edge_count(&self) -> usize {
        self.rows.len() - self.nodes - self.children
    }

    /// Number of corner children's sites (three per coarse triangle, after the edges).
    pub fn child_count(&self) -> usize {
        self.children
    }

    /// Number of sites (nodes, edges and corner children).
    pub fn site_count(&self) -> usize {
        self.rows.len()
    }

    /// The site of the centroid of coarse triangle `t`'s Loop child at its corner `i` (0..3),
    /// `None` when the table has no such site.
    pub fn child_site(&self, t: u32, i: usize) -> Option<u32> {
        let k = 3 * t as usize + i;
        (i < 3 && k < self.children).then(|| (self.rows.len() - self.children + k) as u32)
    }

    /// Why the table does not fit `surface` (another node, edge or triangle count), or `None`.
    pub fn mismatch(&self, surface: &SpringSurface) -> Option<String> {
        let (n, e, t) = (
            surface.node_count(),
            surface.edge_count(),
            surface.triangle_count(),
        );
        ((self.nodes, self.edge_count(), self.children) != (n, e, 3 * t)).then(|| {
            format!(
                "covers {} nodes, {} edges and {} child sites, the surface has {n}, {e} and {}",
                self.nodes,
                self.edge_count(),
                self.children,
                3 * t
            )
        })
    }

    /// The sphere depths of the samples, m.
    pub fn depths_m(&self) -> &[f64] {
        &self.depths_m
    }

    /// Site `i`'s row (a node below [`OrganTable::node_count`], then the edges' midpoints, then
    /// the corner children's centroids, [`OrganTable::child_site`]).
    pub fn row(&self, i: u32) -> Option<&OrganRow> {
        self.rows.get(i as usize)
    }

    /// The contact factor of site `i` at sphere depth `depth_m` (m), of the coarse surface or
    /// (`subdivided`) with the site's area subdivided: linear between the samples, constant
    /// beyond the first and the last; 1 for a site out of range. Allocation-free.
    pub fn factor(&self, i: u32, depth_m: f64, subdivided: bool) -> f64 {
        let Some(r) = self.rows.get(i as usize) else {
            return 1.0;
        };
        let f = if subdivided {
            &r.factor_subdivided
        } else {
            &r.factor
        };
        let d = &self.depths_m;
        if !(depth_m > d[0]) {
            return f[0];
        }
        let n = d.len();
        if depth_m >= d[n - 1] {
            return f[n - 1];
        }
        let k = d.partition_point(|&v| v < depth_m).clamp(1, n - 1);
        let t = (depth_m - d[k - 1]) / (d[k] - d[k - 1]);
        f[k - 1] + t * (f[k] - f[k - 1])
    }

    /// The largest factor in the table (for the stability bound).
    pub fn max_factor(&self) -> f64 {
        self.rows
            .iter()
            .flat_map(|r| r.factor.iter().chain(&r.factor_subdivided).copied())
            .fold(0.0, f64::max)
    }

    /// The file's text: commented header with the key, the node, edge and depth counts, then
    /// [`TABLE_COLUMNS`] rows, one per site and depth.
    pub fn to_text(&self, description: &str) -> String {
        let mut s = table_header(
            "haptic-model mass-spring organ table (contact factor over sphere depth)",
            description,
            self.key,
        );
        let _ = writeln!(s, "# nodes {}", self.nodes);
        let _ = writeln!(s, "# edges {}", self.edge_count());
        let _ = writeln!(s, "# children {}", self.children);
        let _ = writeln!(s, "# samples {}", self.depths_m.len());
        let _ = writeln!(s, "{TABLE_COLUMNS}");
        for (i, r) in self.rows.iter().enumerate() {
            for (k, d) in self.depths_m.iter().enumerate() {
                let _ = writeln!(
                    s,
                    "{i},{},{d:e},{:e},{:e},{:e},{:e},{:e}",
                    k + 1,
                    r.factor[k],
                    r.factor_subdivided[k],
                    r.target_force_n[k],
                    r.spring_force_n[k],
                    r.subdivided_force_n[k]
                );
            }
        }
        s
    }

    /// Parses a table file's text (`path` names it in errors).
    ///
    /// # Errors
    /// [`ModelError::Calibration`] naming the file and line for a missing key, node, edge or
    /// sample count or header, a malformed or non-finite number, a site or sample out of range
    /// or out of order, depths that differ between sites or do not increase, a factor outside
    /// [`FACTOR_RANGE`], or a site without rows.
    pub fn parse(text: &str, path: &str) -> Result<Self, ModelError> {
        let err = |line: usize, m: String| table_error(path, line, m);
        let mut counts = Counts::default();
        let mut reader = RowReader::default();
        let mut header = false;
        for (k, line) in text.lines().enumerate() {
            let ln = k + 1;
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            if let Some(c) = line.strip_prefix('#') {
                counts.read(c.trim(), ln, &err)?;
                continue;
            }
            if !header {
                if line != TABLE_COLUMNS {
                    return Err(err(ln, format!("expected the header `{TABLE_COLUMNS}`")));
                }
                header = true;
                continue;
            }
            let (Some(nn), Some(ne), Some(m)) = (counts.nodes, counts.edges, counts.samples) else {
                return Err(err(
                    ln,
                    "a row before the `# nodes`, `# edges` and `# samples` lines".into(),
                ));
            };
            let n = nn + ne + counts.children.unwrap_or(0);
            reader.read(line, n, m, &|message| err(ln, message))?;
        }
        let key = counts.key.ok_or_else(|| err(0, "no `# key` line".into()))?;
        let nn = counts
            .nodes
            .ok_or_else(|| err(0, "no `# nodes` line".into()))?;
        let ne = counts
            .edges
            .ok_or_else(|| err(0, "no `# edges` line".into()))?;
        let n = nn + ne + counts.children.unwrap_or(0);
        let RowReader { depths, rows, next } = reader;
        if rows.len() != n || next.1 != 0 {
            return Err(err(
                0,
                format!("{} complete sites of the {n} announced", next.0),
            ));
        }
        Ok(Self {
            key,
            depths_m: depths,
            nodes: nn,
            children: counts.children.unwrap_or(0),
            rows,
        })
    }
}

/// The data rows of a table file read so far: the depths (site 0's), the sites' rows, and the
/// site and sample expected next (`(site, last sample read)`).
#[derive(Default)]
struct RowReader {
    depths: Vec<f64>,
    rows: Vec<OrganRow>,
    next: (usize, usize),
}

impl RowReader {
    /// Reads one data row of a table of `n` sites with `m` samples each; `err` makes this line's
    /// error (see [`OrganTable::parse`]).
    fn read(
        &mut self,
        line: &str,
        n: usize,
        m: usize,
        err: &dyn Fn(String) -> ModelError,
    ) -> Result<(), ModelError> {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() != 8 {
            return Err(err(format!("expected 8 fields, got {}", f.len())));
        }
        let int = |s: &str| -> Result<usize, ModelError> {
            s.parse()
                .map_err(|e| err(format!("bad integer `{s}`: {e}")))
        };
        let num = |s: &str| -> Result<f64, ModelError> {
            let v: f64 = s
                .parse()
                .map_err(|e| err(format!("bad number `{s}`: {e}")))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(err(format!("`{s}` is not finite")))
            }
        };
        let (node, sample) = (int(f[0])?, int(f[1])?);
        if (node, sample) != (self.next.0, self.next.1 + 1) {
            return Err(err(format!(
                "expected site {} sample {}, got site {node} sample {sample}",
                self.next.0,
                self.next.1 + 1
            )));
        }
        if node >= n {
            return Err(err(format!("site {node} is beyond the {n} sites")));
        }
        let (depth, factor, factor_sub) = (num(f[2])?, num(f[3])?, num(f[4])?);
        for v in [factor, factor_sub] {
            if !(FACTOR_RANGE.0..=FACTOR_RANGE.1).contains(&v) {
                return Err(err(format!("factor {v} is outside {FACTOR_RANGE:?}")));
            }
        }
        let s = sample - 1;
        if node == 0 {
            if s > 0 && !(depth > self.depths[s - 1]) {
                return Err(err("depths must increase".into()));
            }
            if !(depth > 0.0) {
                return Err(err("depths must be > 0".into()));
            }
            self.depths.push(depth);
        } else if depth != self.depths[s] {
            return Err(err(format!("site {node}: depths differ from site 0's")));
        }
        if s == 0 {
            self.rows.push(OrganRow {
                factor: Vec::with_capacity(m),
                factor_subdivided: Vec::with_capacity(m),
                target_force_n: Vec::with_capacity(m),
                spring_force_n: Vec::with_capacity(m),
                subdivided_force_n: Vec::with_capacity(m),
            });
        }
        let r = self.rows.last_mut().expect("pushed at sample 1");
        r.factor.push(factor);
        r.factor_subdivided.push(factor_sub);
        r.target_force_n.push(num(f[5])?);
        r.spring_force_n.push(num(f[6])?);
        r.subdivided_force_n.push(num(f[7])?);
        self.next = if sample == m {
            (node + 1, 0)
        } else {
            (node, sample)
        };
        Ok(())
    }
}

/// The `# key`, `# nodes`, `# edges`, `# children` (none before version 5) and `# samples`
/// lines of a table file.
#[derive(Default)]
struct Counts {
    key: Option<u64>,
    nodes: Option<usize>,
    edges: Option<usize>,
    children: Option<usize>,
    samples: Option<usize>,
}

impl Counts {
    /// Reads one comment line `c` (without its `#`, trimmed) of line `ln`; other comments are
    /// ignored. `err` makes the error naming the file and line.
    fn read(
        &mut self,
        c: &str,
        ln: usize,
        err: &impl Fn(usize, String) -> ModelError,
    ) -> Result<(), ModelError> {
        let count = |v: &str, what: &str| -> Result<usize, ModelError> {
            let n: usize = v
                .trim()
                .parse()
                .map_err(|e| err(ln, format!("bad {what} count `{v}`: {e}")))?;
            if n == 0 || n > 10_000_000 {
                return Err(err(ln, format!("{n} {what} is out of range")));
            }
            Ok(n)
        };
        if let Some(v) = c.strip_prefix("key ") {
            self.key = Some(
                u64::from_str_radix(v.trim(), 16)
                    .map_err(|e| err(ln, format!("bad key `{v}`: {e}")))?,
            );
        } else if let Some(v) = c.strip_prefix("nodes ") {
            self.nodes = Some(count(v, "nodes")?);
        } else if let Some(v) = c.strip_prefix("edges ") {
            self.edges = Some(count(v, "edges")?);
        } else if let Some(v) = c.strip_prefix("children ") {
            // Zero allowed: a table without the corner children's sites.
            self.children = Some(if v.trim() == "0" {
                0
            } else {
                count(v, "children")?
            });
        } else if let Some(v) = c.strip_prefix("samples ") {
            let n = count(v, "samples")?;
            if n > 1000 {
                return Err(err(ln, format!("{n} samples is out of range")));
            }
            self.samples = Some(n);
        }
        Ok(())
    }
}

/// The organ table's key: a hash of [`ORGAN_VERSION`], the surface (rest positions,
/// triangles, fixed flags), `K_h`, `K_m`, the subdivision (rings, spring rule, vertex rule),
/// the probe's radius and contact model, the reference's text and the axis. Any change makes a
/// stored table stale.
pub fn organ_key(
    surface: &SpringSurface,
    params: &MassSpringParams,
    probe: &ProbeParams,
    reference: &OrganReference,
    axis: DVec3,
) -> u64 {
    let mut h = Fnv::new();
    h.u64(u64::from(ORGAN_VERSION));
    h.surface(surface);
    h.f64(params.home_spring_n_per_m);
    h.f64(params.mesh_spring_n_per_m);
    let sub = &params.subdivision;
    h.u64(u64::from(sub.rings));
    h.bytes(sub.springs.name().as_bytes());
    h.bytes(sub.vertex_rule.name().as_bytes());
    h.f64(probe.radius_m);
    h.bytes(probe.contact.name().as_bytes());
    h.u64(reference.text_hash);
    h.f64(axis.x);
    h.f64(axis.y);
    h.f64(axis.z);
    h.0
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "# test\n\
        point,x_mm,y_mm,z_mm,dx,dy,dz,depth_mm,force_n,uncertainty_n,device_depth_mm,level_1\n\
        a,0,0,1,0,0,-1,0.5,0.002,0.0001,0.51,9\n\
        a,0,0,1,0,0,-1,1,0.005,0.0001,1.02,9\n\
        b,0,0,3,0,0,-1,0.5,0.004,0.0001,0.51,9\n\
        b,0,0,3,0,0,-1,1,0.009,0.0001,1.03,9\n";

    #[test]
    fn the_target_is_interpolated_along_the_axis() {
        let r = OrganReference::parse(TEXT, "t.csv").expect("parses");
        assert_eq!(r.points().len(), 2);
        let z = DVec3::Z;
        let mid = r.target_at(z, DVec3::new(5.0, 0.0, 2e-3));
        assert!((mid[0] - 0.003).abs() < 1e-15 && (mid[1] - 0.007).abs() < 1e-15);
        assert_eq!(
            r.target_at(z, DVec3::new(0.0, 0.0, -1.0)),
            vec![0.002, 0.005]
        );
        assert_eq!(
            r.target_at(z, DVec3::new(0.0, 0.0, 1.0)),
            vec![0.004, 0.009]
        );
        let a = r.point("a").expect("a");
        // Through the origin below the first depth, linear between, the last slope beyond.
        assert!((a.force_at(0.25e-3) - 0.001).abs() < 1e-15);
        assert!((a.force_at(0.75e-3) - 0.0035).abs() < 1e-15);
        assert!((a.force_at(1.5e-3) - 0.008).abs() < 1e-15);
    }

    #[test]
    fn malformed_references_are_refused_with_the_line() {
        let bad = [
            (
                TEXT.replace("a,0,0,1,0,0,-1,1,", "a,0,0,1,0,0,-1,0.4,"),
                "line 4",
            ),
            (
                TEXT.replace("b,0,0,3,0,0,-1,1,", "b,0,0,3,0,0,-1,2,"),
                "other depths",
            ),
            (
                TEXT.replace("0,0,-1,0.5,0.002", "0,0,0,0.5,0.002"),
                "direction",
            ),
            (TEXT.replace("0.005", "NaN"), "not finite"),
            ("point,x\n".to_string(), "header"),
            ("# nothing\n".to_string(), "no reference point"),
        ];
        for (text, want) in bad {
            let e = OrganReference::parse(&text, "t.csv")
                .expect_err(want)
                .to_string();
            assert!(
                e.contains(want) && e.contains("t.csv"),
                "{e} (wanted {want})"
            );
        }
    }

    #[test]
    fn the_table_text_round_trips_and_interpolates() {
        let t = OrganTable {
            key: 0xabc,
            depths_m: vec![1e-4, 1e-3],
            nodes: 1,
            children: 0,
            rows: vec![
                OrganRow {
                    factor: vec![2.0, 1.0],
                    factor_subdivided: vec![3.0, 1.5],
                    target_force_n: vec![1e-3, 1e-2],
                    spring_force_n: vec![5e-4, 1e-2],
                    subdivided_force_n: vec![1e-3 / 3.0, 1e-2 / 1.5],
                },
                OrganRow {
                    factor: vec![0.5, 0.25],
                    factor_subdivided: vec![0.5, 0.25],
                    target_force_n: vec![1e-3, 1e-2],
                    spring_force_n: vec![2e-3, 4e-2],
                    subdivided_force_n: vec![0.0, 0.0],
                },
            ],
        };
        let back = OrganTable::parse(&t.to_text("x\ny"), "t").expect("parses");
        assert_eq!(back, t);
        assert_eq!((back.node_count(), back.edge_count()), (1, 1));
        assert_eq!((back.child_count(), back.child_site(0, 0)), (0, None));
        // With the corner children's sites (version 5): the last rows, three per triangle.
        let mut with_children = t.clone();
        let child = with_children.rows[1].clone();
        with_children
            .rows
            .extend([child.clone(), child.clone(), child]);
        with_children.children = 3;
        let text = with_children.to_text("");
        let back = OrganTable::parse(&text, "t").expect("parses");
        assert_eq!(back, with_children);
        assert_eq!(
            (back.edge_count(), back.child_count(), back.site_count()),
            (1, 3, 5)
        );
        assert_eq!(
            (back.child_site(0, 0), back.child_site(0, 2)),
            (Some(2), Some(4))
        );
        assert_eq!((back.child_site(1, 0), back.child_site(0, 3)), (None, None));
        let short = text.replace("# children 3", "# children 4");
        let e = OrganTable::parse(&short, "t").expect_err("a site short");
        assert!(e.to_string().contains("5 complete sites of the 6"), "{e}");
        assert_eq!(t.factor(0, 0.0, false), 2.0);
        assert!((t.factor(0, 5.5e-4, false) - 1.5).abs() < 1e-12);
        assert!((t.factor(0, 5.5e-4, true) - 2.25).abs() < 1e-12);
        assert_eq!(t.factor(1, 1.0, true), 0.25);
        assert_eq!(t.factor(7, 1e-3, false), 1.0);
        assert_eq!(t.max_factor(), 3.0);
        let text = t.to_text("");
        for (bad, want) in [
            (
                text.replace("1,2,1e-3", "1,3,1e-3"),
                "expected site 1 sample 2",
            ),
            (
                text.replace("# samples 2", "# samples 3"),
                "expected site 0 sample 3",
            ),
            (text.replace("0,1,1e-4,2e0", "0,1,1e-4,2e9"), "outside"),
            (text.replace("# key 0000000000000abc\n", ""), "no `# key`"),
            (text.replace("# edges 1\n", ""), "`# edges`"),
        ] {
            let e = OrganTable::parse(&bad, "t").expect_err(want).to_string();
            assert!(e.contains(want), "{e} (wanted {want})");
        }
    }
}
