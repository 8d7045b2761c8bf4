//! The spring-constant lookup table of haptic subdivision (Zhang, Payandeh & Dill section
//! 3.2.4 and 3.3, step 1): for a contact node C, the home spring constant `K'_h = a K_h` of a
//! subdivided area, with `K'_m = rho K'_h` at a fixed ratio `rho = K'_m / K'_h`, such that the
//! same contact force presses the contact to the same depth before and after subdivision
//! (eq. 4, `F'(K'_h, K'_m, x) = F(K_h, K_m, x)`), tabulated over the normalized displacement
//! `x / L` and interpolated at run time.
//!
//! The experiment behind it (section 3.2.2), for any mesh and each node C: a local patch of the
//! coarse surface (the subdivided rings plus a margin of [`PATCH_EXTRA_RINGS`] rings and the
//! probe's reach, its outer ring held at rest; the response decays within a few rings, the
//! convergence check is in `docs/accuracy.md`) is pressed statically at C along C's rest normal
//! to `L / 1000` (the small-displacement limit) and `k D / 15`, k = 1..15 ([`SAMPLES`],
//! `D = 1.5 L`), giving the coarse force F; the
//! patch is then subdivided around C exactly as at run time and `a` is found (secant
//! iterations on `log a`, to 1e-5 of F) such that the subdivided patch needs the same force
//! at the same depth. The table stores, per sample, `a` against the displacement of C in the
//! subdivided patch over L: what the body observes at run time and interpolates in.
//!
//! The contact is the paper's point contact at C ([`ContactShape::Point`]: the depth is C's
//! displacement) or, for the bodies the servo drives, the haptic probe itself
//! ([`ContactShape::Probe`]: the depth is the travel of the probe's centre, and the force is
//! the probe's at static equilibrium, its patch, weights and normal following the deformed
//! surface). The probe spreads its force over every node within `2 r`, and a subdivided
//! surface has more nodes there: a table made for a point contact would not keep the probe's
//! force (measured: `docs/accuracy.md`).
//!
//! The table is computed for every free node ([`calibrate`], minutes for hundreds of nodes,
//! on all cores, with progress), cached as a text file beside the scene
//! ([`CalibrationTable::to_text`], [`CalibrationTable::parse`]) under a key
//! ([`calibration_key`]) that hashes everything it depends on, so that a stale file is
//! detected.
//!
//! Neighbours: uses [`super::surface`], [`super::refine`], [`super::loop_rules`],
//! [`super::network`]; read by the body and by the scene loader.

use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use glam::DVec3;

use super::contact_rest::{ContactRest, contact_rest_positions};
use super::loop_rules::{apply, edge_stencil, vertex_stencil};
use super::network::{ContactLoad, Network, Spring, press};
use super::refine::{NO_OWNER, Refinement};
use super::surface::{NONE, SpringSurface};
use super::{MassSpringParams, VertexRule};
use crate::ModelError;
use crate::contact::{Probe, ProbeParams};

mod patch;

pub use patch::{LocalPatch, default_margin, surface_contact_rest};

/// Samples per node: the small-depth limit ([`FIRST_SAMPLE_OVER_L`]), then depths
/// `k D / (SAMPLES - 1)`, k = 1..SAMPLES, up to `D =` [`DEPTH_RANGE_OVER_L`]` L`.
pub const SAMPLES: usize = 16;

/// Depth of the first sample over L: the small-displacement limit (the springs' geometric
/// stiffness is negligible there: for a point contact `a -> 1`).
pub const FIRST_SAMPLE_OVER_L: f64 = 1e-3;

/// Depth of sample `k` (0-based) over the element size L.
pub fn sample_depth_over_l(k: usize) -> f64 {
    if k == 0 {
        FIRST_SAMPLE_OVER_L
    } else {
        DEPTH_RANGE_OVER_L * k as f64 / (SAMPLES - 1) as f64
    }
}

/// The deepest calibrated depth over the element size L. The paper assumes displacements up
/// to L (section 3.2.2); probes press somewhat deeper on fine meshes (the LV: 3 mm on 2.2 mm
/// elements), and beyond the table the last factor holds.
pub const DEPTH_RANGE_OVER_L: f64 = 1.5;

/// Rings of the local calibration patch beyond the subdivided ones (the outermost held at rest).
pub const PATCH_EXTRA_RINGS: u32 = 3;

/// The factors `a = K'_h / K_h` a sample may take; a match outside is treated as unmatched
/// (an isolated deep sample whose probe patch lost nodes needed 45 on the hemisphere) and
/// takes its neighbour's factor.
pub const SCALE_RANGE: (f64, f64) = (0.01, 10.0);

/// The largest step of [`LocalPatch::match_force`] in `ln s` before the match is bracketed
/// (a factor of e^1.5, about 4.5). Without it the secant's extrapolation left the search window
/// at once when the start was far from the match: on `lv-surface-springs` 23 nodes near the
/// apex kept their first sample's factor (0.010-0.016) at every depth (docs/accuracy.md,
/// "The organ table, session 4").
pub const MAX_UNBRACKETED_STEP: f64 = 1.5;

/// Version of the table's definition; part of the key (3: the probe meets the contact
/// positions of [`super::contact_rest`]).
pub const CALIBRATION_VERSION: u32 = 3;

/// How the contact presses the surface in the calibration experiment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ContactShape {
    /// A force on the contact node alone (the paper's experiment).
    Point,
    /// The haptic probe itself ([`crate::contact::Probe`]: a sphere whose proxy plane and
    /// reaction spread over the nodes within `2 r` with kernel weights, joined to the device by
    /// the virtual coupling), its centre travelling along the contact node's normal.
    Probe(ProbeParams),
}

/// The calibration of one contact node: per sample, the displacement of the contact node in
/// the subdivided surface over L, the home spring factor `a = K'_h / K_h`, and the force.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeCalibration {
    /// Element size L at the node, m.
    pub element_size_m: f64,
    /// Displacement of the contact node after subdivision over L, increasing.
    pub x_over_l: [f64; SAMPLES],
    /// `K'_h / K_h` at each sample.
    pub kh_scale: [f64; SAMPLES],
    /// Contact force of the coarse surface at each sample (= the subdivided one's), N.
    pub force_n: [f64; SAMPLES],
}

impl NodeCalibration {
    /// `K'_h / K_h` at normalized displacement `x_over_l`: linear interpolation between the
    /// samples, constant beyond the first and the last.
    pub fn scale(&self, x_over_l: f64) -> f64 {
        let xs = &self.x_over_l;
        if !(x_over_l > xs[0]) {
            return self.kh_scale[0];
        }
        for k in 1..SAMPLES {
            if x_over_l <= xs[k] {
                let t = (x_over_l - xs[k - 1]) / (xs[k] - xs[k - 1]);
                return self.kh_scale[k - 1] + t * (self.kh_scale[k] - self.kh_scale[k - 1]);
            }
        }
        self.kh_scale[SAMPLES - 1]
    }
}

/// The lookup table of a surface: one [`NodeCalibration`] per free node (module
/// documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationTable {
    key: u64,
    rows: Vec<Option<NodeCalibration>>,
}

impl CalibrationTable {
    /// The table's key ([`calibration_key`] of what it was computed for).
    pub fn key(&self) -> u64 {
        self.key
    }

    /// Number of nodes it covers (calibrated or not).
    pub fn node_count(&self) -> usize {
        self.rows.len()
    }

    /// The calibration of node `i` (`None` for a fixed node).
    pub fn node(&self, i: u32) -> Option<&NodeCalibration> {
        self.rows.get(i as usize).and_then(|r| r.as_ref())
    }

    /// `K'_h / K_h` for contact node `i` at normalized displacement `x_over_l` (1 for a node
    /// without calibration). Allocation-free.
    pub fn scale(&self, i: u32, x_over_l: f64) -> f64 {
        self.node(i).map_or(1.0, |c| c.scale(x_over_l))
    }

    /// The largest `K'_h / K_h` in the table (at least 1), for the stability bound.
    pub fn max_scale(&self) -> f64 {
        self.rows
            .iter()
            .flatten()
            .flat_map(|r| r.kh_scale)
            .fold(1.0, f64::max)
    }

    /// A table of the given rows (one per node, `None` for a node without calibration) under
    /// `key`: tests and tools that calibrate a few nodes ([`calibrate_node`]).
    pub fn from_rows(key: u64, rows: Vec<Option<NodeCalibration>>) -> Self {
        Self { key, rows }
    }

    /// A table giving every node the calibration `row` (benchmarks on generated meshes whose
    /// calibration would take hours; not a calibrated table).
    pub fn uniform(node_count: usize, row: NodeCalibration, key: u64) -> Self {
        Self {
            key,
            rows: vec![Some(row); node_count],
        }
    }

    /// The cache file's text: a commented header with the key, then one CSV row per node and
    /// sample: `node,element_size_m,sample,x_over_l,kh_scale,force_n`.
    pub fn to_text(&self, description: &str) -> String {
        let mut s = table_header(
            "haptic-model mass-spring calibration table (Zhang, Payandeh & Dill section 3.2.4)",
            description,
            self.key,
        );
        let _ = writeln!(s, "# nodes {}", self.rows.len());
        let _ = writeln!(s, "node,element_size_m,sample,x_over_l,kh_scale,force_n");
        for (i, row) in self.rows.iter().enumerate() {
            if let Some(r) = row {
                for k in 0..SAMPLES {
                    let _ = writeln!(
                        s,
                        "{i},{:e},{},{:e},{:e},{:e}",
                        r.element_size_m,
                        k + 1,
                        r.x_over_l[k],
                        r.kh_scale[k],
                        r.force_n[k]
                    );
                }
            }
        }
        s
    }

    /// Parses a cache file's text (`path` names it in errors). Messages say what was expected
    /// on which line, never the text found there: a client's scene can name the file (issue 47).
    ///
    /// # Errors
    /// [`ModelError::Calibration`] naming the file and line for a missing key or node count,
    /// a malformed or non-finite number, a node out of range, samples missing or out of order,
    /// or displacements that do not increase.
    pub fn parse(text: &str, path: &str) -> Result<Self, ModelError> {
        let err = |line: usize, m: String| table_error(path, line, m);
        let mut key = None;
        let mut nodes = None;
        let mut rows: Vec<Option<NodeCalibration>> = Vec::new();
        let mut header_seen = false;
        for (k, line) in text.lines().enumerate() {
            let ln = k + 1;
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            if let Some(c) = line.strip_prefix('#') {
                let c = c.trim();
                if let Some(v) = c.strip_prefix("key ") {
                    key = Some(
                        u64::from_str_radix(v.trim(), 16)
                            .map_err(|_| err(ln, "expected `# key` and 16 hex digits".into()))?,
                    );
                } else if let Some(v) = c.strip_prefix("nodes ") {
                    let n: usize = v
                        .trim()
                        .parse()
                        .map_err(|_| err(ln, "expected `# nodes` and a whole number".into()))?;
                    if n > 10_000_000 {
                        return Err(err(ln, "expected at most 10 000 000 nodes".into()));
                    }
                    nodes = Some(n);
                    rows = vec![None; n];
                }
                continue;
            }
            if !header_seen {
                if line != "node,element_size_m,sample,x_over_l,kh_scale,force_n" {
                    return Err(err(
                        ln,
                        "expected the column header `node,element_size_m,sample,x_over_l,kh_scale,force_n`"
                            .into(),
                    ));
                }
                header_seen = true;
                continue;
            }
            if nodes.is_none() {
                return Err(err(ln, "a row before the `# nodes` line".into()));
            }
            parse_row(line, ln, &mut rows, path)?;
        }
        let key = key.ok_or_else(|| err(0, "no `# key` line".into()))?;
        if nodes.is_none() {
            return Err(err(0, "no `# nodes` line".into()));
        }
        for (i, r) in rows.iter().enumerate() {
            if let Some(r) = r
                && r.x_over_l[SAMPLES - 1].is_nan()
            {
                return Err(err(0, format!("node {i} has fewer than {SAMPLES} samples")));
            }
        }
        Ok(Self { key, rows })
    }
}

/// A calibration-table error in file `path` at `line` (0: the whole file).
pub(crate) fn table_error(path: &str, line: usize, m: String) -> ModelError {
    ModelError::Calibration {
        path: path.to_string(),
        message: if line > 0 {
            format!("line {line}: {m}")
        } else {
            m
        },
    }
}

/// One data row `line` (line number `ln`) of a calibration table of `rows.len()` nodes: checks
/// its fields and stores its sample in `rows`.
fn parse_row(
    line: &str,
    ln: usize,
    rows: &mut [Option<NodeCalibration>],
    path: &str,
) -> Result<(), ModelError> {
    let err = |line: usize, m: String| table_error(path, line, m);
    let n = rows.len();
    let f: Vec<&str> = line.split(',').collect();
    if f.len() != 6 {
        return Err(err(ln, "expected 6 comma-separated fields".into()));
    }
    let int = |s: &str| -> Result<usize, ModelError> {
        s.trim()
            .parse()
            .map_err(|_| err(ln, "expected a whole number of 0 or more".into()))
    };
    let num = |s: &str| -> Result<f64, ModelError> {
        let v: f64 = s
            .trim()
            .parse()
            .map_err(|_| err(ln, "expected a number".into()))?;
        if !v.is_finite() {
            return Err(err(ln, "expected a finite number".into()));
        }
        Ok(v)
    };
    let (node, sample) = (int(f[0])?, int(f[2])?);
    if node >= n {
        return Err(err(ln, format!("node {node} is beyond the {n} nodes")));
    }
    if !(1..=SAMPLES).contains(&sample) {
        return Err(err(ln, format!("sample {sample} is not in 1..={SAMPLES}")));
    }
    let row = rows[node].get_or_insert(NodeCalibration {
        element_size_m: num(f[1])?,
        x_over_l: [f64::NAN; SAMPLES],
        kh_scale: [f64::NAN; SAMPLES],
        force_n: [f64::NAN; SAMPLES],
    });
    let s = sample - 1;
    if s > 0 && row.x_over_l[s - 1].is_nan() {
        return Err(err(
            ln,
            format!("node {node}: sample {sample} out of order"),
        ));
    }
    row.x_over_l[s] = num(f[3])?;
    row.kh_scale[s] = num(f[4])?;
    row.force_n[s] = num(f[5])?;
    if !(row.kh_scale[s] > 0.0) {
        return Err(err(ln, format!("node {node}: kh_scale must be > 0")));
    }
    if s > 0 && !(row.x_over_l[s] > row.x_over_l[s - 1]) {
        return Err(err(
            ln,
            format!("node {node}: x_over_l must increase with the sample"),
        ));
    }
    Ok(())
}

/// The first lines of a table file: `# title`, the description's lines commented, `# key`
/// in 16 hexadecimal digits.
pub(crate) fn table_header(title: &str, description: &str, key: u64) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# {title}");
    for line in description.lines() {
        let _ = writeln!(s, "# {line}");
    }
    let _ = writeln!(s, "# key {key:016x}");
    s
}

/// FNV-1a, 64 bits: a stable hash for the cache key (no dependency, same on every platform).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Fnv(pub(crate) u64);

impl Fnv {
    pub(crate) fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    pub(crate) fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 ^= u64::from(x);
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    pub(crate) fn f64(&mut self, v: f64) {
        self.bytes(&v.to_bits().to_le_bytes());
    }
    pub(crate) fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    /// Every rest position, triangle and fixed flag of `surface`, in that order (the part of
    /// the calibration and organ tables' keys that names the surface).
    pub(crate) fn surface(&mut self, surface: &SpringSurface) {
        for p in surface.rest() {
            self.f64(p.x);
            self.f64(p.y);
            self.f64(p.z);
        }
        for t in surface.triangles() {
            for &i in t {
                self.u64(u64::from(i));
            }
        }
        for i in 0..surface.node_count() as u32 {
            self.bytes(&[u8::from(surface.is_fixed(i))]);
        }
    }
}

/// The key of the table for `surface` with `params` and contact `shape`: a hash of the
/// definition version, the sample count and patch size, every rest position, triangle and
/// fixed flag, `K_h`, `K_m`, `K'_m / K'_h`, the rings, the vertex rule and the contact shape.
/// Any change of these makes a cached table stale. (Mass, damping and the coarsening delay do
/// not enter a static calibration.)
pub fn calibration_key(
    surface: &SpringSurface,
    params: &MassSpringParams,
    shape: ContactShape,
) -> u64 {
    let mut h = Fnv::new();
    h.u64(u64::from(CALIBRATION_VERSION));
    h.u64(SAMPLES as u64);
    h.u64(u64::from(PATCH_EXTRA_RINGS));
    h.f64(DEPTH_RANGE_OVER_L);
    h.f64(SCALE_RANGE.0);
    h.f64(SCALE_RANGE.1);
    h.u64(surface.node_count() as u64);
    h.surface(surface);
    let s = &params.subdivision;
    h.f64(params.home_spring_n_per_m);
    h.f64(params.mesh_spring_n_per_m);
    h.f64(s.km_over_kh_after);
    h.u64(u64::from(s.rings));
    h.bytes(s.vertex_rule.name().as_bytes());
    match shape {
        ContactShape::Point => h.bytes(b"point"),
        ContactShape::Probe(p) => {
            h.bytes(b"probe");
            h.f64(p.radius_m);
            h.f64(p.coupling_stiffness_n_per_m);
        }
    }
    h.0
}

/// Calibrates contact node `node` of `surface` (module documentation): the table row for
/// `params` and `shape`. Samples at which the subdivided surface cannot give the coarse force
/// (the probe does not touch it yet: its nodes sit a little lower on a convex surface), whose
/// static solve does not settle, or whose factor is outside [`SCALE_RANGE`], take the factor
/// of the nearest matched sample before them (after them for the first).
///
/// # Errors
/// As [`LocalPatch::new`] and [`LocalPatch::match_force`]; [`ModelError::NoConvergence`]
/// when no sample can be matched.
pub fn calibrate_node(
    surface: &SpringSurface,
    params: &MassSpringParams,
    shape: ContactShape,
    node: u32,
) -> Result<NodeCalibration, ModelError> {
    let contact = surface_contact_rest(surface, shape);
    calibrate_node_with(surface, params, shape, node, contact.as_ref())
}

/// [`calibrate_node`] with the surface's contact positions at rest computed beforehand
/// ([`surface_contact_rest`]).
///
/// # Errors
/// As [`calibrate_node`].
pub fn calibrate_node_with(
    surface: &SpringSurface,
    params: &MassSpringParams,
    shape: ContactShape,
    node: u32,
    contact: Option<&ContactRest>,
) -> Result<NodeCalibration, ModelError> {
    let s = &params.subdivision;
    let (kh, km) = (params.home_spring_n_per_m, params.mesh_spring_n_per_m);
    let mut patch = LocalPatch::with_contact(
        surface,
        node,
        s.rings,
        default_margin(surface, node, shape),
        s.vertex_rule,
        shape,
        (kh, km),
        contact,
    )?;
    let l = patch.element_size_m();
    let mut xc = patch.coarse_rest();
    let mut xf = patch.fine_rest();
    let mut out = NodeCalibration {
        element_size_m: l,
        x_over_l: [0.0; SAMPLES],
        kh_scale: [f64::NAN; SAMPLES],
        force_n: [0.0; SAMPLES],
    };
    let ratio = s.km_over_kh_after;
    let mut a = 1.0;
    for k in 0..SAMPLES {
        let depth = sample_depth_over_l(k) * l;
        // A sample whose static solve does not settle (the probe's patch cycling between
        // configurations, seen beyond L) is skipped like one that cannot be matched.
        let backup_c = xc.clone();
        let f = match patch.coarse_press(depth, &mut xc) {
            Ok(f) => f,
            Err(ModelError::NoConvergence(_)) => {
                xc = backup_c;
                f64::NAN
            }
            Err(e) => return Err(e),
        };
        out.force_n[k] = f;
        if !(f > 0.0) {
            out.force_n[k] = f.max(0.0);
            continue;
        }
        let backup = xf.clone();
        let constants = |a: f64| (a * kh, ratio * a * kh);
        let mut matched = patch.match_force(f, depth, constants, a, &mut xf);
        let retry = match &matched {
            Ok(Some((a_k, _))) => !(SCALE_RANGE.0..=SCALE_RANGE.1).contains(a_k),
            Ok(None) | Err(ModelError::NoConvergence(_)) => true,
            Err(_) => false,
        };
        if a != 1.0 && retry {
            // Started from the previous sample's factor, which can be far off (the first,
            // tiny-depth sample's is about a twelfth of the next one's): once more from 1.
            xf.clone_from(&backup);
            matched = patch.match_force(f, depth, constants, 1.0, &mut xf);
        }
        match matched {
            Ok(Some((a_k, u))) if (SCALE_RANGE.0..=SCALE_RANGE.1).contains(&a_k) => {
                a = a_k;
                out.x_over_l[k] = u / l;
                out.kh_scale[k] = a;
            }
            Ok(Some(_)) => xf = backup,
            Ok(None) | Err(ModelError::NoConvergence(_)) => xf = backup,
            Err(e) => return Err(e),
        }
    }
    fill_unmatched(&mut out, node)?;
    Ok(out)
}

/// Gives the samples [`calibrate_node_with`] could not match their neighbour's factor (the
/// first matched one before it, the last one after) and keeps the displacements increasing,
/// so that the table is a function of the displacement.
///
/// # Errors
/// [`ModelError::NoConvergence`] when no sample matched.
fn fill_unmatched(out: &mut NodeCalibration, node: u32) -> Result<(), ModelError> {
    let Some(first) = out.kh_scale.iter().position(|v| v.is_finite()) else {
        return Err(ModelError::NoConvergence(format!(
            "node {node}: no depth up to L at which the subdivided force can match"
        )));
    };
    for k in 0..SAMPLES {
        if !out.kh_scale[k].is_finite() {
            // Not matched (not touched yet, or out of range): the neighbouring factor.
            let j = if k < first {
                first
            } else {
                (0..k)
                    .rev()
                    .find(|&j| out.kh_scale[j].is_finite())
                    .unwrap_or(first)
            };
            out.kh_scale[k] = out.kh_scale[j];
            out.x_over_l[k] = 0.0;
        }
    }
    for k in 1..SAMPLES {
        if !(out.x_over_l[k] > out.x_over_l[k - 1]) {
            // A displacement that does not grow with the depth would make the lookup
            // ambiguous: keep the table a function of the displacement.
            out.x_over_l[k] = out.x_over_l[k - 1] + 1e-9;
        }
    }
    Ok(())
}

/// Calibrates every free node of `surface` for `params` and `shape` on `threads` threads
/// (at least 1), calling `progress(done, total)` after each node. Minutes for thousands of
/// nodes.
///
/// # Errors
/// The first error of [`calibrate_node`], naming the node.
pub fn calibrate(
    surface: &SpringSurface,
    params: &MassSpringParams,
    shape: ContactShape,
    threads: usize,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<CalibrationTable, ModelError> {
    let nodes: Vec<u32> = (0..surface.node_count() as u32)
        .filter(|&i| !surface.is_fixed(i))
        .collect();
    let total = nodes.len();
    let contact = surface_contact_rest(surface, shape);
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let rows: Mutex<Vec<Option<NodeCalibration>>> = Mutex::new(vec![None; surface.node_count()]);
    let failure: Mutex<Option<ModelError>> = Mutex::new(None);
    std::thread::scope(|scope| {
        for _ in 0..threads.max(1) {
            scope.spawn(|| {
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    if k >= total || failure.lock().map(|f| f.is_some()).unwrap_or(true) {
                        break;
                    }
                    let node = nodes[k];
                    match calibrate_node_with(surface, params, shape, node, contact.as_ref()) {
                        Ok(row) => {
                            if let Ok(mut r) = rows.lock() {
                                r[node as usize] = Some(row);
                            }
                            progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
                        }
                        Err(e) => {
                            if let Ok(mut f) = failure.lock() {
                                f.get_or_insert(ModelError::Calibration {
                                    path: String::new(),
                                    message: format!("node {node}: {e}"),
                                });
                            }
                            break;
                        }
                    }
                }
            });
        }
    });
    if let Some(e) = failure.into_inner().ok().flatten() {
        return Err(e);
    }
    Ok(CalibrationTable {
        key: calibration_key(surface, params, shape),
        rows: rows.into_inner().unwrap_or_default(),
    })
}
