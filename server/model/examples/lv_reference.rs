//! The rigid-sphere reference of the `lv-probe` press (docs/accuracy.md, "The sphere reference
//! on four refined levels"), in two steps that
//! `server/model/examples/lv_reference.sh` runs:
//!
//! - `solve`: one mesh level. The idealized LV of `../shared/data/lv/README.md` meshed by Gmsh
//!   as a half model (`lv_probe_half.geo`: y >= 0, groups ENDO, EPI, BASE, SYM; mm), made
//!   quadratic with its mid-edge nodes on the analytic ellipsoids
//!   ([`haptic_model::mesh::generate::curve_lv_surfaces`]), BASE clamped, SYM on rollers (no
//!   y motion: the plane y = 0 is a plane of mirror symmetry of geometry, load and clamp), EPI
//!   touchable; a rigid frictionless sphere of 2 mm radius moving along -x at y = 0, z = -5 mm
//!   ([`haptic_model::indent::Indentation`], converged at every depth or an error). Two depth
//!   conventions: `sphere`, the sphere's travel from the centre x = 9.682458 + 2 mm (where it
//!   touches the analytic epicardium at (9.682458, 0, -5) mm), and `device`, the device's
//!   travel `D = s + F_x / k` with the scenes' virtual coupling `k` = 300 N/m (solved for the
//!   sphere travel `s` by secant steps to 1e-10 m). Forces are the full body's (twice the
//!   half's x and z components). Appends one CSV row per depth and convention as each
//!   converges.
//! - `combine`: the rows of three or more levels into the reference: per material,
//!   convention and depth, with four or more levels the least-squares estimate of Eca &
//!   Hoekstra (2014) over all of them (`eca_hoekstra`: the limit of a fitted `f0 + a h^p`
//!   and a band that covers the fit's scatter), with three Richardson's extrapolation through
//!   them and Roache's grid convergence index (1.25 times the extrapolated value's distance
//!   from the finest level's). Both are written, with the observed order of each of the last
//!   two consecutive triples of levels to show whether the three-level orders are regular.
//!   Writes the CSV the benchmark and the tests read (format:
//!   `server/model/benches/precision/lv_sphere_reference.csv`'s header comment).
//!
//! The reference comes from our own solver: it is a self-convergence check, cross-checked at
//! one depth per material by an independent code (scikit-fem, `research/`).

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::{Parser, Subcommand};
use haptic_model::DVec3;
use haptic_model::element::FemModel;
use haptic_model::indent::{IndentParams, Indentation, Indenter};
use haptic_model::material::{MaterialModel, MaterialParams};
use haptic_model::statics::StaticParams;

/// The epicardium's x at y = 0, z = -5 mm: 10 sqrt(1 - (5/20)^2) mm.
const SURFACE_X_MM: f64 = 9.682_458_365_518_542;
/// Sphere radius, mm.
const RADIUS_MM: f64 = 2.0;
/// The press line's z, mm.
const PROBE_Z_MM: f64 = -5.0;
/// Virtual coupling stiffness of the LV scenes, N/m.
const COUPLING_N_PER_M: f64 = 300.0;
/// The scenes' material.
const YOUNGS_PA: f64 = 14_500.0;
const POISSON: f64 = 0.45;
const DENSITY: f64 = 1060.0;

#[derive(Debug, Parser)]
#[command(name = "lv_reference")]
struct Args {
    #[command(subcommand)]
    step: Step,
}

#[derive(Debug, Subcommand)]
enum Step {
    /// Solve one mesh level (appends to --out).
    Solve {
        /// The half LV mesh (Gmsh, mm, groups ENDO, EPI, BASE, SYM).
        #[arg(long)]
        msh: PathBuf,
        /// The level's size parameter (the element size under the probe), mm.
        #[arg(long)]
        h: f64,
        /// Material by scene name (stvk, stable-neo-hookean, corotational).
        #[arg(long)]
        material: String,
        /// Depths, mm, increasing.
        #[arg(long, value_delimiter = ',')]
        depths: Vec<f64>,
        /// Output CSV (rows appended; header written when new).
        #[arg(long)]
        out: PathBuf,
        /// Checkpoint file: written after each depth (both conventions), and when it exists
        /// at the start the solve continues after its last depth (the CSV is cut back to the
        /// rows of the depths it holds). Refused when it belongs to another mesh, material or
        /// depth list.
        #[arg(long)]
        checkpoint: Option<PathBuf>,
        /// Contact points inside the touchable triangles longer than this fraction of the
        /// sphere radius (`IndentParams::point_spacing`; default 0.25, which none of the
        /// refined levels' triangles under the probe exceed, so their nodes alone carry the
        /// contact).
        #[arg(long, default_value_t = 0.25)]
        point_spacing: f64,
        /// Threads of each Newton system's factorisation (0: every core). The Cholesky
        /// factor is the same whatever the count; the `L D L^T` of an indefinite tangent
        /// agrees to round-off.
        #[arg(long, default_value_t = 0)]
        threads: usize,
    },
    /// Combine four or more levels into the reference CSV.
    Combine {
        /// Level CSVs written by `solve` (any order; rows are grouped by their h).
        #[arg(long, value_delimiter = ',', required_unless_present = "levels_from")]
        csv: Vec<PathBuf>,
        /// A reference CSV written by an earlier `combine` (its `f_h<h>_n` columns, 7
        /// significant digits) whose levels join those of `--csv`: a level solved again in
        /// `--csv` replaces the column's value, and a column's h (written to 4 decimals) takes
        /// the `--csv` level's h it rounds from. So one new level can join the stored
        /// reference without the older levels' files.
        #[arg(long)]
        levels_from: Option<PathBuf>,
        /// The reference CSV to write.
        #[arg(long)]
        out: PathBuf,
        /// Also print the Markdown tables of docs/accuracy.md.
        #[arg(long)]
        markdown: bool,
        /// Mesh ensembles: sizes within this fraction of each other (for example 0.04) are
        /// samples of one level, meshed at slightly different size parameters. The level's
        /// force is their mean (at their mean size); the finest level's single-mesh noise (its
        /// samples' deviation about a line in h, or with fewer than four samples the nearest
        /// coarser level's) is written, and the three finest levels' order is also given over
        /// their means moved by one standard error either way.
        #[arg(long)]
        ensemble: Option<f64>,
    },
}

const LEVEL_HEADER: &str = "material,depth_convention,depth_mm,h_mm,nodes,tets,sphere_travel_mm,force_n,fx_n,fz_n,contact_radius_mm,nodes_in_contact,newton_iterations,seconds";

fn main() -> anyhow::Result<()> {
    match Args::parse().step {
        Step::Solve {
            msh,
            h,
            material,
            depths,
            out,
            checkpoint,
            point_spacing,
            threads,
        } => solve_level(
            &msh,
            (h, point_spacing, threads),
            &material,
            &depths,
            &out,
            checkpoint.as_deref(),
        ),
        Step::Combine {
            csv,
            levels_from,
            out,
            markdown,
            ensemble,
        } => combine(&csv, levels_from.as_deref(), &out, (markdown, ensemble)),
    }
}

/// The half LV of `msh` with curved quadratic elements, clamps and rollers, and its
/// touchable triangles.
fn half_lv(msh: &Path, model: MaterialModel) -> anyhow::Result<(FemModel, Vec<[u32; 3]>, usize)> {
    let mut mesh = haptic_model::mesh::gmsh::load_msh(msh)?;
    mesh.scale(1e-3);
    let vertices_tets = mesh.tets.len();
    let mut mesh = mesh.to_quadratic();
    let straight = haptic_model::mesh::generate::curve_lv_surfaces(&mut mesh);
    if straight > 0 {
        eprintln!(
            "{}: {straight} mid-edge node(s) left straight (curving would invert their elements)",
            msh.display()
        );
    }
    let mut material = MaterialParams::from_youngs(YOUNGS_PA, POISSON, DENSITY);
    material.model = model;
    let mut fem = FemModel::new(&mesh, material)?;
    let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    let base = mesh.nodes_of_surfaces(&names(&["BASE"]), "BASE")?;
    let sym = mesh.nodes_of_surfaces(&names(&["SYM"]), "SYM")?;
    for &i in &sym {
        fem.set_constraint(i as usize, 0b010);
    }
    fem.clamp_nodes(&base);
    let epi = mesh
        .surface("EPI")
        .ok_or_else(|| anyhow::anyhow!("{}: no EPI group", msh.display()))?;
    let touchable = epi
        .triangles
        .iter()
        .filter(|t| !t.iter().all(|i| base.binary_search(i).is_ok()))
        .copied()
        .collect();
    Ok((fem, touchable, vertices_tets))
}

/// One converged state: sphere travel (m) and the full body's force on the sphere (N).
struct Solved {
    travel_m: f64,
    force: DVec3,
    contact_radius_m: f64,
    nodes_in_contact: usize,
    newton: usize,
}

fn solve_at(run: &mut Indentation<'_>, travel_m: f64) -> anyhow::Result<Solved> {
    let p = run.solve(travel_m)?;
    let f = p.force_on_sphere_n;
    Ok(Solved {
        travel_m,
        // The half model: twice its x and z components; y is the symmetry plane's.
        force: DVec3::new(2.0 * f.x, 0.0, 2.0 * f.z),
        // Half the contact is on the half model: the full contact's area is twice it.
        contact_radius_m: (2.0 * p.contact_area_m2 / std::f64::consts::PI).sqrt(),
        nodes_in_contact: p.nodes_in_contact,
        newton: p.newton_iterations,
    })
}

/// The rigid sphere (2 mm, from x = 15 mm along -x at the probe's z) and the indentation's
/// parameters: contact points at `point_spacing`, the Newton systems factorised on `threads`
/// threads (0: every core).
fn sphere_press(point_spacing: f64, threads: usize) -> (Indenter, IndentParams) {
    let mm = 1e-3;
    let from_x = 15.0;
    let indenter = Indenter {
        radius_m: RADIUS_MM * mm,
        from_m: DVec3::new(from_x, 0.0, PROBE_Z_MM) * mm,
        direction: DVec3::new(-1.0, 0.0, 0.0),
    };
    let threads = match threads {
        0 => std::thread::available_parallelism().map_or(1, usize::from),
        n => n,
    };
    let defaults = IndentParams::default();
    let params = IndentParams {
        zero_distance_m: Some((from_x - SURFACE_X_MM - RADIUS_MM) * mm),
        point_spacing,
        newton: StaticParams {
            threads,
            ..defaults.newton
        },
        ..defaults
    };
    (indenter, params)
}

fn solve_level(
    msh: &Path,
    (h, point_spacing, threads): (f64, f64, usize),
    material: &str,
    depths: &[f64],
    out: &Path,
    checkpoint: Option<&Path>,
) -> anyhow::Result<()> {
    let model = MaterialModel::from_scene_name(material)
        .ok_or_else(|| anyhow::anyhow!("unknown material {material:?}"))?;
    let (fem, touchable, tets) = half_lv(msh, model)?;
    eprintln!(
        "{} (h {h} mm): {} nodes, {tets} tets, {} touchable triangles, material {material}",
        msh.display(),
        fem.node_count(),
        touchable.len()
    );
    let mm = 1e-3;
    let (indenter, params) = sphere_press(point_spacing, threads);
    let mut run = Indentation::new(&fem, &touchable, &indenter, &params)?;
    // The default spacing keeps the key of the checkpoints written before the option existed.
    let points = match point_spacing == IndentParams::default().point_spacing {
        true => String::new(),
        false => format!(" point spacing {point_spacing}"),
    };
    let key = format!(
        "{} h {h} {material} nodes {} depths {depths:?}{points}",
        msh.file_name().unwrap_or_default().to_string_lossy(),
        fem.node_count()
    );
    let done = match checkpoint.filter(|p| p.exists()) {
        Some(path) => resume_level(&mut run, path, &key, out)?,
        None => 0,
    };
    let new_file = !out.exists();
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(out)?;
    if new_file {
        writeln!(file, "{LEVEL_HEADER}")?;
    }
    let t0 = Instant::now();
    let row = |conv: &str, depth_mm: f64, s: &Solved, file: &mut std::fs::File| {
        let line = format!(
            "{material},{conv},{depth_mm},{h},{},{tets},{:.9},{:.9e},{:.9e},{:.9e},{:.6},{},{},{:.1}",
            fem.node_count(),
            s.travel_m / mm,
            s.force.length(),
            s.force.x,
            s.force.z,
            s.contact_radius_m / mm,
            s.nodes_in_contact,
            s.newton,
            t0.elapsed().as_secs_f64()
        );
        eprintln!("  {line}");
        writeln!(file, "{line}").and_then(|()| file.flush())
    };
    for (i, &d) in depths.iter().enumerate().skip(done) {
        let sphere = solve_at(&mut run, d * mm)?;
        row("sphere", d, &sphere, &mut file)?;
        // Device travel D = s + F_x / k: secant steps on s from s = D and s = D - F_x(D) / k.
        let target = d * mm;
        let g = |s: &Solved| s.travel_m + s.force.x / COUPLING_N_PER_M - target;
        let mut a = sphere;
        let mut b = solve_at(&mut run, target - a.force.x / COUPLING_N_PER_M)?;
        let mut steps = 0;
        while g(&b).abs() > 1e-10 {
            steps += 1;
            if steps > 20 {
                anyhow::bail!("device depth {d} mm: the secant steps did not converge");
            }
            let next = b.travel_m - g(&b) * (b.travel_m - a.travel_m) / (g(&b) - g(&a));
            a = b;
            b = solve_at(&mut run, next)?;
        }
        row("device", d, &b, &mut file)?;
        if let Some(path) = checkpoint {
            // The device's secant left the run at the device depth: the next depth starts
            // from there, resumed or not.
            checkpoint_file::write(path, &key, i + 1, &run.checkpoint())?;
        }
    }
    Ok(())
}

/// Resumes `run` from the checkpoint at `path` (which must carry `key`), cuts the CSV `out`
/// back to the header and the rows of the depths the checkpoint holds (a depth interrupted
/// between its two rows is solved again), and returns how many depths are done.
fn resume_level(
    run: &mut Indentation<'_>,
    path: &Path,
    key: &str,
    out: &Path,
) -> anyhow::Result<usize> {
    let (done, c) = checkpoint_file::read(path, key)?;
    let reached_mm = c.reached_m * 1e3;
    run.resume(c)?;
    let text = std::fs::read_to_string(out)
        .map_err(|e| anyhow::anyhow!("{}: {e} (the checkpoint's CSV)", out.display()))?;
    let kept: Vec<&str> = text.lines().take(1 + 2 * done).collect();
    anyhow::ensure!(
        kept.len() == 1 + 2 * done,
        "{} has {} rows but the checkpoint holds {done} depths (two rows each)",
        out.display(),
        kept.len().saturating_sub(1)
    );
    std::fs::write(out, kept.join("\n") + "\n")?;
    eprintln!(
        "resumed from {}: {done} depths done, sphere travel {reached_mm:.6} mm",
        path.display()
    );
    Ok(done)
}

/// The checkpoint file of `solve --checkpoint`: magic, key (mesh, h, material, nodes,
/// depths), depths done, then the [`haptic_model::indent::IndentCheckpoint`]'s numbers, all
/// little-endian; written to a temporary file and renamed, so a kill leaves the last one.
mod checkpoint_file {
    use std::path::Path;

    use haptic_model::DVec3;
    use haptic_model::indent::IndentCheckpoint;

    const MAGIC: &[u8; 8] = b"LVREFCP1";

    fn put_f64s(out: &mut Vec<u8>, v: impl ExactSizeIterator<Item = f64>) {
        out.extend_from_slice(&(v.len() as u64).to_le_bytes());
        v.for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
    }

    fn put_points(out: &mut Vec<u8>, p: &[DVec3]) {
        put_f64s(
            out,
            p.iter()
                .flat_map(|p| p.to_array())
                .collect::<Vec<_>>()
                .into_iter(),
        );
    }

    /// Writes `c` with `key` and `done` to `path` (through `path.tmp`).
    pub fn write(path: &Path, key: &str, done: usize, c: &IndentCheckpoint) -> anyhow::Result<()> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&(key.len() as u64).to_le_bytes());
        out.extend_from_slice(key.as_bytes());
        out.extend_from_slice(&(done as u64).to_le_bytes());
        out.extend_from_slice(&c.reached_m.to_le_bytes());
        put_points(&mut out, &c.positions_m);
        out.push(u8::from(c.previous.is_some()));
        if let Some((d, x)) = &c.previous {
            out.extend_from_slice(&d.to_le_bytes());
            put_points(&mut out, x);
        }
        put_f64s(&mut out, c.active.iter().map(|&a| f64::from(u8::from(a))));
        put_f64s(&mut out, c.lambda.iter().copied());
        put_f64s(&mut out, c.multiplier_n.iter().copied());
        put_f64s(&mut out, c.penalty_n_per_m.iter().copied());
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, &out)?;
        std::fs::rename(&tmp, path)?;
        Ok(())
    }

    /// A reader over the file's bytes that fails on a short file.
    struct Bytes<'a>(&'a [u8]);

    impl Bytes<'_> {
        fn take(&mut self, n: usize) -> anyhow::Result<&[u8]> {
            anyhow::ensure!(self.0.len() >= n, "the checkpoint file is truncated");
            let (a, b) = self.0.split_at(n);
            self.0 = b;
            Ok(a)
        }
        fn u64(&mut self) -> anyhow::Result<u64> {
            Ok(u64::from_le_bytes(self.take(8)?.try_into()?))
        }
        fn f64(&mut self) -> anyhow::Result<f64> {
            Ok(f64::from_le_bytes(self.take(8)?.try_into()?))
        }
        fn f64s(&mut self) -> anyhow::Result<Vec<f64>> {
            let n = usize::try_from(self.u64()?)?;
            anyhow::ensure!(n <= self.0.len() / 8, "the checkpoint file is truncated");
            (0..n).map(|_| self.f64()).collect()
        }
        fn points(&mut self) -> anyhow::Result<Vec<DVec3>> {
            let v = self.f64s()?;
            anyhow::ensure!(
                v.len() % 3 == 0,
                "the checkpoint's positions are not triples"
            );
            Ok(v.chunks_exact(3).map(DVec3::from_slice).collect())
        }
    }

    /// Reads the checkpoint at `path`; refused when its key is not `key`.
    pub fn read(path: &Path, key: &str) -> anyhow::Result<(usize, IndentCheckpoint)> {
        let data = std::fs::read(path)?;
        let mut b = Bytes(&data);
        anyhow::ensure!(
            b.take(8)? == MAGIC,
            "{} is not a checkpoint",
            path.display()
        );
        let n = usize::try_from(b.u64()?)?;
        let theirs = String::from_utf8_lossy(b.take(n)?).into_owned();
        anyhow::ensure!(
            theirs == key,
            "{} is the checkpoint of [{theirs}], not of this solve [{key}]",
            path.display()
        );
        let done = usize::try_from(b.u64()?)?;
        let reached_m = b.f64()?;
        let positions_m = b.points()?;
        let previous = match b.take(1)?[0] {
            0 => None,
            _ => Some((b.f64()?, b.points()?)),
        };
        let active = b.f64s()?.into_iter().map(|a| a != 0.0).collect();
        let c = IndentCheckpoint {
            reached_m,
            positions_m,
            previous,
            active,
            lambda: b.f64s()?,
            multiplier_n: b.f64s()?,
            penalty_n_per_m: b.f64s()?,
        };
        anyhow::ensure!(b.0.is_empty(), "{} has trailing bytes", path.display());
        Ok((done, c))
    }
}

/// A level row of the combine step.
#[derive(Debug, Clone)]
struct LevelRow {
    material: String,
    convention: String,
    depth_mm: f64,
    h_mm: f64,
    nodes: usize,
    force_n: f64,
}

fn read_levels(paths: &[PathBuf]) -> anyhow::Result<Vec<LevelRow>> {
    let mut rows = Vec::new();
    for p in paths {
        let text = std::fs::read_to_string(p)?;
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
        let col = |name: &str| {
            header
                .iter()
                .position(|h| *h == name)
                .ok_or_else(|| anyhow::anyhow!("{}: no column {name}", p.display()))
        };
        let (cm, cc, cd, ch, cn, cf) = (
            col("material")?,
            col("depth_convention")?,
            col("depth_mm")?,
            col("h_mm")?,
            col("nodes")?,
            col("force_n")?,
        );
        for l in lines.filter(|l| !l.trim().is_empty()) {
            let v: Vec<&str> = l.split(',').collect();
            rows.push(LevelRow {
                material: v[cm].into(),
                convention: v[cc].into(),
                depth_mm: v[cd].parse()?,
                h_mm: v[ch].parse()?,
                nodes: v[cn].parse()?,
                force_n: v[cf].parse()?,
            });
        }
    }
    Ok(rows)
}

/// The level rows held in a reference CSV written by [`combine`] (`text`): one row per
/// non-empty `f_h<h>_n` cell, `nodes` 0 (not stored there).
fn reference_levels(text: &str) -> anyhow::Result<Vec<LevelRow>> {
    let mut lines = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty());
    let header: Vec<&str> = lines
        .next()
        .ok_or_else(|| anyhow::anyhow!("no header"))?
        .split(',')
        .collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .ok_or_else(|| anyhow::anyhow!("no column {name}"))
    };
    let (cm, cc, cd) = (col("material")?, col("depth_convention")?, col("depth_mm")?);
    let levels: Vec<(usize, f64)> = header
        .iter()
        .enumerate()
        .filter_map(|(i, h)| {
            let size = h.strip_prefix("f_h")?.strip_suffix("_n")?;
            Some(size.parse::<f64>().map(|s| (i, s)))
        })
        .collect::<Result<_, _>>()?;
    anyhow::ensure!(!levels.is_empty(), "no f_h<h>_n column");
    let mut rows = Vec::new();
    for (n, l) in lines.enumerate() {
        let v: Vec<&str> = l.split(',').collect();
        anyhow::ensure!(v.len() == header.len(), "row {}: {} fields", n + 1, v.len());
        for &(i, h_mm) in &levels {
            if v[i].is_empty() {
                continue;
            }
            rows.push(LevelRow {
                material: v[cm].into(),
                convention: v[cc].into(),
                depth_mm: v[cd].parse()?,
                h_mm,
                nodes: 0,
                force_n: v[i].parse()?,
            });
        }
    }
    Ok(rows)
}

/// `solved` (the levels' own rows) joined by `stored` (from a reference CSV): a stored h
/// within the 4-decimal rounding (5e-5 mm) of a solved level's takes that level's h, and a
/// stored row whose (material, convention, depth, h) was solved is dropped.
fn merge_levels(mut solved: Vec<LevelRow>, stored: Vec<LevelRow>) -> Vec<LevelRow> {
    let hs: Vec<f64> = solved.iter().map(|r| r.h_mm).collect();
    for mut r in stored {
        if let Some(h) = hs.iter().find(|h| (**h - r.h_mm).abs() <= 5e-5) {
            r.h_mm = *h;
        }
        let same = |s: &LevelRow| {
            s.material == r.material
                && s.convention == r.convention
                && s.depth_mm == r.depth_mm
                && s.h_mm == r.h_mm
        };
        if !solved.iter().any(same) {
            solved.push(r);
        }
    }
    solved
}

/// Richardson's extrapolation through three levels (sizes `h` coarse to fine, values `f`):
/// the observed order `p` from `(f3 - f2) / (f2 - f1) = (h3^p - h2^p) / (h2^p - h1^p)`
/// (bisection on [0.2, 10]), the extrapolated value and Roache's grid convergence index
/// `1.25 |f* - f3|`; `None` when the changes are not monotone and shrinking.
fn richardson(h: [f64; 3], f: [f64; 3]) -> Option<(f64, f64, f64)> {
    let (e21, e32) = (f[1] - f[0], f[2] - f[1]);
    if e21 == 0.0 || e32 / e21 <= 0.0 || e32.abs() >= e21.abs() {
        return None;
    }
    let target = e32 / e21;
    let g = |p: f64| (h[2].powf(p) - h[1].powf(p)) / (h[1].powf(p) - h[0].powf(p)) - target;
    let (mut lo, mut hi) = (0.2, 10.0);
    if g(lo).signum() == g(hi).signum() {
        return None;
    }
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if g(mid).signum() == g(lo).signum() {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let p = 0.5 * (lo + hi);
    let value = f[2] - e32 / (h[2].powf(p) - h[1].powf(p)) * h[2].powf(p);
    Some((value, 1.25 * (value - f[2]).abs(), p))
}

/// A least-squares fit over every level of `f(h) = f0 + sum_k a_k h^(e_k)` (h in mm): the
/// limit `f0`, the standard deviation `sigma` of the residuals (over `n - 1 - terms` degrees of
/// freedom) and the fitted value at the finest level.
#[derive(Debug, Clone, Copy)]
struct LsFit {
    f0: f64,
    sigma: f64,
    at_finest: f64,
}

/// [`LsFit`] for the exponents `exps` (one or two terms), by the normal equations; `None` when
/// they are singular or there are no degrees of freedom left.
fn ls_fit(levels: &[(f64, f64)], exps: &[f64]) -> Option<LsFit> {
    let m = 1 + exps.len();
    if levels.len() <= m {
        return None;
    }
    let basis = |h: f64| -> Vec<f64> {
        std::iter::once(1.0)
            .chain(exps.iter().map(|e| h.powf(*e)))
            .collect()
    };
    // [A^T A | A^T f], Gaussian elimination with partial pivoting.
    let mut a = vec![vec![0.0; m + 1]; m];
    for &(h, f) in levels {
        let b = basis(h);
        for (row, bi) in a.iter_mut().zip(&b) {
            for (x, bj) in row.iter_mut().zip(b.iter().chain(std::iter::once(&f))) {
                *x += bi * bj;
            }
        }
    }
    for c in 0..m {
        let piv = (c..m).max_by(|&x, &y| a[x][c].abs().total_cmp(&a[y][c].abs()))?;
        if a[piv][c].abs() < 1e-300 {
            return None;
        }
        a.swap(c, piv);
        let pivot_row = a[c].clone();
        for (r, row) in a.iter_mut().enumerate() {
            if r != c {
                let k = row[c] / pivot_row[c];
                for (x, p) in row.iter_mut().zip(&pivot_row).skip(c) {
                    *x -= k * p;
                }
            }
        }
    }
    let coef: Vec<f64> = (0..m).map(|i| a[i][m] / a[i][i]).collect();
    let eval = |h: f64| basis(h).iter().zip(&coef).map(|(b, c)| b * c).sum::<f64>();
    let ssr: f64 = levels.iter().map(|&(h, f)| (f - eval(h)).powi(2)).sum();
    let h_fine = levels.last()?.0;
    Some(LsFit {
        f0: coef[0],
        sigma: (ssr / (levels.len() - m) as f64).sqrt(),
        at_finest: eval(h_fine),
    })
}

/// The least-squares uncertainty estimate of Eca & Hoekstra (J. Comput. Phys. 262, 2014,
/// 104-130) over four or more levels (`(h, f)` coarse to fine), for refinement studies whose
/// three-level orders scatter:
/// - fit `f0 + a h^p` with `p` free (searched on [0.2, 4]); if `0.5 <= p < 2.1`, the value is
///   `f0` and the uncertainty `1.25 |f0 - f_1| + sigma + |f_1 - fit(h_1)|` (`f_1` the finest
///   level);
/// - otherwise the fixed-order fits `f0 + a h`, `f0 + a h^2` and `f0 + a h + b h^2`, the one with
///   the smallest `sigma`, with the safety factor 3: `3 |f0 - f_1| + sigma + |f_1 - fit(h_1)|`,
///   and when `p >= 2.1` at least `1.25` times the data range per level
///   `(max f - min f) / (n - 1)`.
///
/// Returns (value, uncertainty, the free fit's order); `None` below four levels.
fn eca_hoekstra(levels: &[(f64, f64)]) -> Option<(f64, f64, f64)> {
    if levels.len() < 4 {
        return None;
    }
    let f1 = levels.last()?.1;
    let (p, free) = (200..=4000)
        .filter_map(|i| {
            let p = f64::from(i) * 1e-3;
            ls_fit(levels, &[p]).map(|fit| (p, fit))
        })
        .min_by(|a, b| a.1.sigma.total_cmp(&b.1.sigma))?;
    let band =
        |fit: &LsFit, fs: f64| fs * (fit.f0 - f1).abs() + fit.sigma + (f1 - fit.at_finest).abs();
    if (0.5..2.1).contains(&p) {
        return Some((free.f0, band(&free, 1.25), p));
    }
    let fixed = [&[1.0][..], &[2.0][..], &[1.0, 2.0][..]]
        .iter()
        .filter_map(|e| ls_fit(levels, e))
        .min_by(|a, b| a.sigma.total_cmp(&b.sigma))?;
    let mut u = band(&fixed, 3.0);
    if p >= 2.1 {
        let (lo, hi) = levels
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), l| {
                (lo.min(l.1), hi.max(l.1))
            });
        u = u.max(1.25 * (hi - lo) / (levels.len() - 1) as f64);
    }
    Some((fixed.f0, u, p))
}

fn combine(
    paths: &[PathBuf],
    levels_from: Option<&Path>,
    out: &Path,
    (markdown, ensemble): (bool, Option<f64>),
) -> anyhow::Result<()> {
    let mut rows = read_levels(paths)?;
    if let Some(reference) = levels_from {
        let text = std::fs::read_to_string(reference)
            .map_err(|e| anyhow::anyhow!("{}: {e}", reference.display()))?;
        let stored =
            reference_levels(&text).map_err(|e| anyhow::anyhow!("{}: {e}", reference.display()))?;
        rows = merge_levels(rows, stored);
    }
    let mut sizes: Vec<f64> = rows.iter().map(|r| r.h_mm).collect();
    sizes.sort_by(|a, b| b.total_cmp(a));
    sizes.dedup();
    let groups = size_groups(&sizes, ensemble);
    if groups.len() < 3 {
        anyhow::bail!("{} level(s): Richardson needs three or more", groups.len());
    }
    let hs: Vec<f64> = groups
        .iter()
        .map(|g| g.iter().sum::<f64>() / g.len() as f64)
        .collect();
    let mut keys: Vec<(String, String, f64)> = rows
        .iter()
        .map(|r| (r.material.clone(), r.convention.clone(), r.depth_mm))
        .collect();
    keys.sort_by(|a, b| (&a.0, &a.1).cmp(&(&b.0, &b.1)).then(a.2.total_cmp(&b.2)));
    keys.dedup();
    let mut csv = csv_header(&hs)?;
    let mut md = String::new();
    for key in &keys {
        let (material, conv, depth) = key;
        let stats: Vec<Option<LevelStat>> = groups
            .iter()
            .map(|g| {
                LevelStat::of(rows.iter().filter(|r| {
                    &r.material == material
                        && &r.convention == conv
                        && r.depth_mm == *depth
                        && g.contains(&r.h_mm)
                }))
            })
            .collect();
        let present: Vec<(f64, LevelStat)> = hs
            .iter()
            .zip(&stats)
            .filter_map(|(&h, s)| s.map(|s| (h, s)))
            .collect();
        if present.len() < 3 {
            continue;
        }
        let levels: Vec<(f64, f64)> = present.iter().map(|(h, s)| (*h, s.force_n)).collect();
        let sd = level_sd(present.iter().map(|p| p.1));
        let se: Vec<f64> = present
            .iter()
            .zip(&sd)
            .map(|((_, s), sd)| sd.map_or(0.0, |sd| sd / (s.samples as f64).sqrt()))
            .collect();
        let e = Estimate::of(&levels, &se, *sd.last().unwrap_or(&None));
        csv_row(
            &mut csv,
            key,
            &e,
            stats.iter().map(|s| s.map(|s| s.force_n)),
        )?;
        md_row(&mut md, key, &e, &present)?;
    }
    std::fs::write(out, csv)?;
    println!("levels: {}", describe_levels(&groups, &hs, &rows));
    println!("wrote {}", out.display());
    if markdown {
        println!(
            "| material | convention | depth, mm | levels, mN (coarse to fine; samples) | reference, mN | order (3 finest) | order (3 before) | order (least squares) | Richardson (3 finest), GCI | single-mesh noise, mN | order (3 finest), +- 1 standard error |"
        );
        println!("|---|---|---|---|---|---|---|---|---|---|---|");
        print!("{md}");
    }
    Ok(())
}

/// The levels of `combine` for its log: each size (mm), its largest node count and, for an
/// ensemble, its samples' sizes.
fn describe_levels(groups: &[Vec<f64>], hs: &[f64], rows: &[LevelRow]) -> String {
    let described: Vec<String> = groups
        .iter()
        .zip(hs)
        .map(|(g, &h)| {
            let nodes = rows
                .iter()
                .filter(|r| g.contains(&r.h_mm))
                .map(|r| r.nodes)
                .max()
                .filter(|n| *n > 0)
                .map_or(String::new(), |n| format!(": {n} nodes"));
            if g.len() > 1 {
                let list: Vec<String> = g.iter().map(|s| s.to_string()).collect();
                format!("{h:.5} mm{nodes} (samples {})", list.join(" / "))
            } else {
                format!("{h} mm{nodes}")
            }
        })
        .collect();
    described.join(", ")
}

/// The sizes `hs` (mm, coarse to fine) in groups, coarse to fine: with `rel`, a size joins
/// the group before it when within `rel` (relative) of that group's first (largest) size;
/// without, one size per group.
fn size_groups(hs: &[f64], rel: Option<f64>) -> Vec<Vec<f64>> {
    let mut groups: Vec<Vec<f64>> = Vec::new();
    for &h in hs {
        match groups.last_mut() {
            Some(g) if rel.is_some_and(|r| g[0] - h <= r * g[0]) => g.push(h),
            _ => groups.push(vec![h]),
        }
    }
    groups
}

/// The samples of one level (one material, convention and depth): the mean force (N), their
/// count and the variance of their residuals about a straight line in h (N^2; 0 below three
/// samples), so the level's own trend over its sizes is not counted as noise.
#[derive(Debug, Clone, Copy)]
struct LevelStat {
    force_n: f64,
    samples: usize,
    variance: f64,
}

impl LevelStat {
    fn of<'a>(rows: impl Iterator<Item = &'a LevelRow>) -> Option<Self> {
        let hf: Vec<(f64, f64)> = rows.map(|r| (r.h_mm, r.force_n)).collect();
        let n = hf.len();
        if n == 0 {
            return None;
        }
        let mean = |v: &dyn Fn(&(f64, f64)) -> f64| hf.iter().map(v).sum::<f64>() / n as f64;
        let (hm, fm) = (mean(&|x| x.0), mean(&|x| x.1));
        let shh: f64 = hf.iter().map(|x| (x.0 - hm).powi(2)).sum();
        let shf: f64 = hf.iter().map(|x| (x.0 - hm) * (x.1 - fm)).sum();
        let slope = if shh > 0.0 { shf / shh } else { 0.0 };
        let variance = if n > 2 {
            hf.iter()
                .map(|x| (x.1 - fm - slope * (x.0 - hm)).powi(2))
                .sum::<f64>()
                / (n - 2) as f64
        } else {
            0.0
        };
        Some(Self {
            force_n: fm,
            samples: n,
            variance,
        })
    }
}

/// Each level's single-mesh noise (N), coarse to fine: the deviation of its own samples
/// ([`LevelStat`]) when they leave two or more degrees of freedom (four or more samples), else
/// the nearest coarser level's (the noise shrinks with the size, so that errs wide), else
/// `None`.
fn level_sd(stats: impl Iterator<Item = LevelStat>) -> Vec<Option<f64>> {
    let mut last = None;
    stats
        .map(|s| {
            if s.samples > 3 {
                last = Some(s.variance.sqrt());
            }
            last
        })
        .collect()
}

/// The reference file's comment lines and column names for the levels `hs` (mm).
fn csv_header(hs: &[f64]) -> anyhow::Result<String> {
    let mut csv = String::from(
        "# The rigid-sphere reference of the lv-probe press (server/model/examples/lv_reference.rs,\n\
         # written by server/model/examples/lv_reference.sh). A self-convergence check of our own\n\
         # solver over the levels below (cross-checked by research/, scikit-fem: docs/accuracy.md).\n\
         # Columns: material, depth convention (sphere: the sphere's travel from the analytic\n\
         # epicardium, centre x = 11.682458 mm; device: D = s + F_x / (300 N/m)), depth (mm), the\n\
         # reference force magnitude (N) and its uncertainty (N): with four or more levels the\n\
         # least-squares estimate of Eca & Hoekstra (J. Comput. Phys. 262, 2014) over all of\n\
         # them, with three Richardson's extrapolation and Roache's GCI; then the observed\n\
         # Richardson order of the three finest levels (empty: changes not monotone and\n\
         # shrinking, or an order outside 0.2-10) and of the three before, the least-squares\n\
         # fit's order, Richardson's value through the three finest levels and its GCI (N; no\n\
         # order: the finest level and the spread of the three finest); with mesh ensembles\n\
         # (`combine --ensemble`: each level the mean of meshes at slightly different sizes) the\n\
         # finest level's single-mesh noise (standard deviation, N) and the three finest levels' order\n\
         # range over their means moved by one standard error (empty: none, or some moves not\n\
         # monotone); then each level's force (N; the samples' mean) in columns\n\
         # f_h<size under the probe, mm>_n, coarse to fine (empty: not solved).\n",
    );
    write!(
        csv,
        "material,depth_convention,depth_mm,force_n,uncertainty_n,observed_order,previous_order,ls_order,richardson_force_n,gci_n,noise_sd_n,order_min,order_max"
    )?;
    for h in hs {
        write!(csv, ",f_h{h:.4}_n")?;
    }
    csv.push('\n');
    Ok(csv)
}

/// The reference value of one (material, convention, depth) from its levels `(h mm, force N)`
/// (three or more, coarse to fine).
struct Estimate {
    value: f64,
    unc: f64,
    richardson_value: f64,
    gci: f64,
    order: Option<f64>,
    previous: Option<f64>,
    ls: Option<(f64, f64, f64)>,
    /// The finest level's single-mesh noise (N), with ensembles.
    noise: Option<f64>,
    /// The three finest levels' order over their values moved by `se` either way (all eight
    /// moves monotone and shrinking), with ensembles.
    order_range: Option<(f64, f64)>,
}

impl Estimate {
    /// `se[i]`: the standard error of level i's force (N; 0 without ensembles); `noise`: the
    /// single mesh's noise, when known.
    fn of(levels: &[(f64, f64)], se: &[f64], noise: Option<f64>) -> Self {
        let k = levels.len();
        let tri = |i: usize| {
            richardson(
                [levels[i].0, levels[i + 1].0, levels[i + 2].0],
                [levels[i].1, levels[i + 1].1, levels[i + 2].1],
            )
        };
        let finest = levels[k - 1].1;
        let (richardson_value, gci, order) = match tri(k - 3) {
            Some((v, u, p)) => (v, u, Some(p)),
            None => {
                let spread = levels[k - 3..]
                    .iter()
                    .map(|l| (l.1 - finest).abs())
                    .fold(0.0, f64::max);
                (finest, spread, None)
            }
        };
        // Four or more levels: the least-squares estimate over all of them is the reference;
        // three: Richardson through them with Roache's GCI.
        let ls = eca_hoekstra(levels);
        let (value, unc) = ls.map_or((richardson_value, gci), |(v, u, _)| (v, u));
        let previous = if k >= 4 {
            tri(k - 4).map(|t| t.2)
        } else {
            None
        };
        let order_range = noise.and_then(|_| {
            let (h, f) = (
                [levels[k - 3].0, levels[k - 2].0, levels[k - 1].0],
                [levels[k - 3].1, levels[k - 2].1, levels[k - 1].1],
            );
            let moved = (0..8).map(|signs: usize| {
                let g: [f64; 3] = std::array::from_fn(|i| {
                    let sign = if signs >> i & 1 == 1 { 1.0 } else { -1.0 };
                    f[i] + sign * se[k - 3 + i]
                });
                richardson(h, g).map(|t| t.2)
            });
            moved.collect::<Option<Vec<f64>>>().map(|p| {
                p.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| {
                    (lo.min(x), hi.max(x))
                })
            })
        });
        Self {
            value,
            unc,
            richardson_value,
            gci,
            order,
            previous,
            ls,
            noise,
            order_range,
        }
    }
}

/// One line of the reference file: the estimate, then each level's force.
fn csv_row(
    csv: &mut String,
    (material, conv, depth): &(String, String, f64),
    e: &Estimate,
    at_levels: impl Iterator<Item = Option<f64>>,
) -> anyhow::Result<()> {
    let Estimate {
        value,
        unc,
        richardson_value,
        gci,
        ..
    } = *e;
    let fmt_order = |p: Option<f64>| p.map_or(String::new(), |p| format!("{p:.3}"));
    write!(
        csv,
        "{material},{conv},{depth},{value:.6e},{unc:.3e},{},{},{},{richardson_value:.6e},{gci:.3e}",
        fmt_order(e.order),
        fmt_order(e.previous),
        fmt_order(e.ls.map(|l| l.2)),
    )?;
    let noise = e.noise.map_or(String::new(), |n| format!("{n:.3e}"));
    write!(
        csv,
        ",{noise},{},{}",
        fmt_order(e.order_range.map(|r| r.0)),
        fmt_order(e.order_range.map(|r| r.1))
    )?;
    for f in at_levels {
        match f {
            Some(f) => write!(csv, ",{f:.6e}")?,
            None => csv.push(','),
        }
    }
    csv.push('\n');
    Ok(())
}

/// One row of the Markdown table.
fn md_row(
    md: &mut String,
    (material, conv, depth): &(String, String, f64),
    e: &Estimate,
    levels: &[(f64, LevelStat)],
) -> anyhow::Result<()> {
    writeln!(
        md,
        "| {material} | {conv} | {depth} | {} | **{:.4} +- {:.4} ({:.1} %)** | {} | {} | {} | {:.4} +- {:.4} ({:.1} %) | {} | {} |",
        levels
            .iter()
            .map(|(_, s)| if s.samples > 1 {
                format!("{:.4} ({})", s.force_n * 1e3, s.samples)
            } else {
                format!("{:.4}", s.force_n * 1e3)
            })
            .collect::<Vec<_>>()
            .join(" / "),
        e.value * 1e3,
        e.unc * 1e3,
        100.0 * e.unc / e.value,
        e.order.map_or("none".into(), |p| format!("{p:.2}")),
        e.previous.map_or("none".into(), |p| format!("{p:.2}")),
        e.ls.map_or("-".into(), |l| format!("{:.2}", l.2)),
        e.richardson_value * 1e3,
        e.gci * 1e3,
        100.0 * e.gci / e.richardson_value,
        e.noise.map_or("-".into(), |n| format!("{:.4}", n * 1e3)),
        e.order_range
            .map_or("-".into(), |(lo, hi)| format!("{lo:.2} to {hi:.2}")),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const H: [f64; 5] = [0.6, 0.42, 0.3, 0.2121, 0.15];

    #[test]
    fn a_clean_power_law_is_extrapolated_exactly() {
        // f = 4.6 + 0.3 h^1.3: the free fit finds p = 1.3 and the limit, with no scatter.
        let levels: Vec<(f64, f64)> = H.iter().map(|&h| (h, 4.6 + 0.3 * h.powf(1.3))).collect();
        let (value, u, p) = eca_hoekstra(&levels).expect("five levels");
        assert!((p - 1.3).abs() < 2e-3, "{p}");
        assert!((value - 4.6).abs() < 1e-4, "{value}");
        // 1.25 times the finest level's distance from the limit, nothing for scatter.
        let eps = 0.3 * 0.15f64.powf(1.3);
        assert!(
            (u - 1.25 * eps).abs() < 1e-3 * eps + 1e-6,
            "{u} against {}",
            1.25 * eps
        );
        // Richardson through the three finest levels agrees.
        let (rv, gci, rp) = richardson([H[2], H[3], H[4]], [levels[2].1, levels[3].1, levels[4].1])
            .expect("monotone");
        assert!(
            (rp - 1.3).abs() < 1e-6 && (rv - 4.6).abs() < 1e-9,
            "{rv} {rp}"
        );
        assert!((gci - 1.25 * eps).abs() < 1e-9);
    }

    #[test]
    fn scatter_widens_the_band_and_irregular_orders_take_the_safety_factor_3() {
        // A first-order trend with an alternating scatter of 0.3 % of the trend's last change:
        // the three finest levels alone give a wild order, the fit does not.
        let trend = |h: f64| 10.0 + 0.5 * h;
        let noise = [0.0, 0.004, -0.004, 0.004, -0.004];
        let levels: Vec<(f64, f64)> = H
            .iter()
            .zip(noise)
            .map(|(&h, e)| (h, trend(h) + e))
            .collect();
        let (value, u, p) = eca_hoekstra(&levels).expect("five levels");
        let f1 = levels[4].1;
        assert!((value - 10.0).abs() < u, "{value} +- {u}");
        assert!(u >= 1.25 * (value - f1).abs(), "{u}");
        // The band holds the true limit and the scatter.
        assert!(u > 0.004, "{u}");
        assert!(
            (0.5..2.1).contains(&p) || u >= 3.0 * (value - f1).abs(),
            "{p} {u}"
        );
        // Four levels are needed.
        assert!(eca_hoekstra(&levels[..3]).is_none());
    }

    #[test]
    fn ensembles_group_by_size_average_out_their_noise_and_bracket_the_true_order() {
        // f = 4 + 0.5 h^1.5 on five levels, four meshes each at 1.02 / 1.0067 / 0.9933 / 0.98
        // times the level's size, with a mesh noise of +d / -d / +d / -d (d = 2 % of the finest
        // level's distance from the limit): the groups are the five levels, each level's
        // deviation is the noise, and the three finest means' order range holds the true 1.5.
        let law = |h: f64| 4.0 + 0.5 * h.powf(1.5);
        let levels = [0.2121, 0.15, 0.10607, 0.075, 0.053];
        let d = 0.02 * 0.5 * 0.053f64.powf(1.5);
        let mut rows = Vec::new();
        for &h in &levels {
            let third = 0.02 / 3.0;
            for (scale, noise) in [(1.02, d), (1.0 + third, -d), (1.0 - third, d), (0.98, -d)] {
                rows.push(LevelRow {
                    material: "stvk".into(),
                    convention: "sphere".into(),
                    depth_mm: 0.5,
                    h_mm: h * scale,
                    nodes: 0,
                    force_n: law(h * scale) + noise,
                });
            }
        }
        let mut sizes: Vec<f64> = rows.iter().map(|r| r.h_mm).collect();
        sizes.sort_by(|a, b| b.total_cmp(a));
        let groups = size_groups(&sizes, Some(0.05));
        assert_eq!(groups.len(), 5, "{groups:?}");
        assert!(groups.iter().all(|g| g.len() == 4));
        assert_eq!(size_groups(&sizes, None).len(), 20);
        let stats: Vec<LevelStat> = groups
            .iter()
            .map(|g| LevelStat::of(rows.iter().filter(|r| g.contains(&r.h_mm))).expect("rows"))
            .collect();
        let sds = level_sd(stats.iter().copied());
        let sd = sds[4].expect("ensembles");
        // About a line in h, the noise (+d, -d, +d, -d) at evenly spaced sizes leaves the
        // residuals (0.4, -1.2, 1.2, -0.4) d: a deviation of sqrt(1.6) d over two degrees of
        // freedom per level (the law's curvature over +-2 % adds a little).
        let expected = 1.6f64.sqrt() * d;
        assert!((sd / expected - 1.0).abs() < 0.1, "{sd} against {expected}");
        let hs: Vec<f64> = groups.iter().map(|g| g.iter().sum::<f64>() / 4.0).collect();
        let means: Vec<(f64, f64)> = hs
            .iter()
            .zip(&stats)
            .map(|(h, s)| (*h, s.force_n))
            .collect();
        assert!(sds.iter().all(Option::is_some));
        // Three meshes leave one degree of freedom: such a level takes the coarser one's.
        let mut three = stats.clone();
        three[4].samples = 3;
        three[4].variance = 0.0;
        assert_eq!(level_sd(three.into_iter())[4], sds[3]);
        let se = vec![sd / 2.0; 5];
        let e = Estimate::of(&means, &se, Some(sd));
        let (lo, hi) = e.order_range.expect("monotone within one standard error");
        assert!(lo < 1.5 && 1.5 < hi && hi - lo < 0.5, "{lo} to {hi}");
        assert!((e.value - 4.0).abs() < e.unc, "{} +- {}", e.value, e.unc);
        // Without ensembles no range is claimed.
        assert!(Estimate::of(&means, &[0.0; 5], None).order_range.is_none());
    }

    #[test]
    fn the_fits_match_a_direct_least_squares_solution() {
        // f0 + a h + b h^2 through four points with known residuals: the normal equations'
        // limit against the exact coefficients of a quadratic through noise-free data.
        let levels: Vec<(f64, f64)> = H[..4]
            .iter()
            .map(|&h| (h, 2.0 - 0.7 * h + 1.1 * h * h))
            .collect();
        let fit = ls_fit(&levels, &[1.0, 2.0]).expect("fit");
        assert!((fit.f0 - 2.0).abs() < 1e-12, "{fit:?}");
        assert!(fit.sigma < 1e-12 && (fit.at_finest - levels[3].1).abs() < 1e-12);
        assert!(
            ls_fit(&levels[..3], &[1.0, 2.0]).is_none(),
            "no degree of freedom"
        );
    }

    #[test]
    fn a_stored_reference_gives_back_its_levels_and_a_solved_level_replaces_them() {
        let text = "# comment\n\
            material,depth_convention,depth_mm,force_n,uncertainty_n,f_h0.6000_n,f_h0.1061_n\n\
            stvk,device,0.5,4.1e-3,5e-5,4.3055e-3,4.2225e-3\n\
            stable-neo-hookean,device,0.5,4.6e-3,3e-5,4.7366e-3,\n";
        let stored = reference_levels(text).expect("parses");
        let got: Vec<(&str, f64, f64)> = stored
            .iter()
            .map(|r| (r.material.as_str(), r.h_mm, r.force_n))
            .collect();
        assert_eq!(
            got,
            [
                ("stvk", 0.6, 4.3055e-3),
                ("stvk", 0.1061, 4.2225e-3),
                ("stable-neo-hookean", 0.6, 4.7366e-3)
            ]
        );
        // A sixth level solved for the neo-Hookean material at h = 0.10607 mm: the stored
        // StVK column (0.1061) joins it as the same level, the solved row stays.
        let solved = vec![LevelRow {
            material: "stable-neo-hookean".into(),
            convention: "device".into(),
            depth_mm: 0.5,
            h_mm: 0.10607,
            nodes: 219_211,
            force_n: 4.61e-3,
        }];
        let merged = merge_levels(solved, stored);
        let mut hs: Vec<f64> = merged.iter().map(|r| r.h_mm).collect();
        hs.sort_by(f64::total_cmp);
        hs.dedup();
        assert_eq!(hs, [0.10607, 0.6]);
        assert_eq!(merged.len(), 4);
        // The same cell solved again replaces the stored value.
        let again = vec![LevelRow {
            material: "stvk".into(),
            convention: "device".into(),
            depth_mm: 0.5,
            h_mm: 0.6,
            nodes: 4_711,
            force_n: 4.3e-3,
        }];
        let merged = merge_levels(again, reference_levels(text).expect("parses"));
        let at = merged
            .iter()
            .filter(|r| r.material == "stvk" && r.h_mm == 0.6)
            .map(|r| r.force_n)
            .collect::<Vec<_>>();
        assert_eq!(at, [4.3e-3]);
        assert!(reference_levels("material,depth_convention,depth_mm\nstvk,device,0.5\n").is_err());
        assert!(
            reference_levels("material,depth_convention,depth_mm,f_h0.6_n\nstvk,device\n").is_err()
        );
    }
}
