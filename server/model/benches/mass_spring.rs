//! The mass-spring family's costs (issue 18, section 4), on one thread:
//!
//! - **subdivision events**: the wall time of a one-ring and a two-ring subdivision event
//!   around a random node and of the coarsening back ([`MassSpringBody::subdivide_around`],
//!   [`MassSpringBody::coarsen`]: the same code the tick runs), median / p99 / max over many;
//! - **ticks with events**: a probe pressing, sliding and leaving, so that the ticks that run
//!   an event are among those timed: the slowest tick and the overruns of the 1 ms budget;
//! - **step time**: servo ticks while the probe holds the apex pressed (one-ring subdivided),
//!   median / p99 / max, on the built-in scenes and on generated hemispheres of about 1k, 10k
//!   and 50k surface nodes (the hemisphere scene's springs, mass and probe, with its table
//!   applied to every node: the costs do not depend on the factors).
//!
//! Run: `cargo bench -p haptic-model --bench mass_spring` (`-- --quick`: fewer repetitions;
//! `-- --only timing --mesh 50k`: the timings of the meshes whose label contains `50k`).
//! Writes `target/bench/mass_spring.csv` (or `--out DIR`) and prints a table. Medians and
//! percentiles of one run on a shared 2-core machine: compare within the table.

mod common;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use clap::Parser;
use common::TickTimes;
use haptic_model::DVec3;
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::mass_spring::calibration::CalibrationTable;
use haptic_model::mass_spring::{MassSpringBody, SpringSurface};
use haptic_model::mesh::generate;
use haptic_model::scene::{Scene, load_builtin};
use serde::Serialize;

/// Mass-spring costs: subdivision events and servo ticks by surface size.
#[derive(Debug, Parser)]
#[command(name = "mass_spring")]
struct Args {
    /// Fewer repetitions (about a minute).
    #[arg(long)]
    quick: bool,
    /// Run only the force steps of the vertex rules (`slide`), only the timings (`timing`) or
    /// only the timings of the events (`events`).
    #[arg(long, value_enum, default_value_t = Only::All)]
    only: Only,
    /// Subdivision events per mesh and ring count [default: 400, 50 with `--quick`, at most 4
    /// per node].
    #[arg(long)]
    reps: Option<usize>,
    /// Time only the meshes whose label contains this (e.g. `10k`, `lv`) [default: all].
    #[arg(long)]
    mesh: Option<String>,
    /// Folder of mass_spring.csv [default: target/bench of the workspace].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Passed by `cargo bench` to every harness-less benchmark; ignored.
    #[arg(long, hide = true)]
    bench: bool,
}

/// Which parts to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Only {
    All,
    Timing,
    Events,
    Slide,
}

/// One row of `mass_spring.csv`.
#[derive(Debug, Serialize)]
struct Row {
    mesh: String,
    nodes: usize,
    triangles: usize,
    /// "event 1-ring", "event 2-ring", "coarsen 1-ring", ..., "tick (pressed)", "tick (events)".
    what: String,
    substeps: u32,
    count: u64,
    p50_us: f64,
    p99_us: f64,
    max_us: f64,
    /// Ticks over 1 ms (tick rows).
    overruns: u64,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let out = args.out.clone().unwrap_or_else(common::default_out_dir);
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let path = out.join("mass_spring.csv");
    let mut csv = csv::Writer::from_path(&path)?;
    let hemi = load_builtin("hemisphere-springs")?;
    if args.only == Only::All || args.only == Only::Slide {
        slide(&hemi, &out)?;
    }
    if args.only == Only::Slide {
        return Ok(());
    }
    let meshes = meshes(&args, &hemi)?;
    println!(
        "{:<20} {:>6} {:>6} {:<16} {:>4} {:>7} {:>9} {:>9} {:>9} {:>8}",
        "mesh", "nodes", "tris", "what", "sub", "count", "p50 us", "p99 us", "max us", "overruns"
    );
    for (label, scene) in &meshes {
        let ms = scene.mass_spring.as_ref().context("mass-spring scene")?;
        let n = ms.surface.node_count();
        let reps = args
            .reps
            .unwrap_or(if args.quick { 50 } else { 400 })
            .min(4 * n);
        let mut emit = Emit {
            csv: &mut csv,
            mesh: label,
            nodes: n,
            triangles: ms.surface.triangle_count(),
        };
        event_rows(scene, &ms.surface, reps, &mut emit)?;
        if args.only == Only::Events {
            continue;
        }
        events_tick_row(scene, &ms.surface, args.quick, &mut emit)?;
        pressed_tick_row(label, scene, &ms.surface, args.quick, &mut emit)?;
    }
    csv.flush()?;
    println!("wrote {}", path.display());
    Ok(())
}

/// The meshes to time: the two built-ins and the generated hemispheres, those matching
/// `--mesh`.
fn meshes(args: &Args, hemi: &Scene) -> anyhow::Result<Vec<(String, Scene)>> {
    let lv = load_builtin("lv-surface-springs")?;
    let mut meshes: Vec<(String, Scene)> = vec![
        ("hemisphere-springs".into(), hemi.clone()),
        ("lv-surface-springs".into(), lv),
    ];
    for (label, edge_mm) in [
        ("hemisphere 1k", 4.3),
        ("hemisphere 10k", 1.36),
        ("hemisphere 50k", 0.61),
    ] {
        if args.mesh.as_deref().is_none_or(|m| label.contains(m)) {
            meshes.push((label.into(), generated(hemi, edge_mm * 1e-3)?));
        }
    }
    if let Some(m) = &args.mesh {
        meshes.retain(|(label, _)| label.contains(m.as_str()));
    }
    Ok(meshes)
}

/// Prints and writes the rows of one mesh.
struct Emit<'a> {
    csv: &'a mut csv::Writer<std::fs::File>,
    mesh: &'a str,
    nodes: usize,
    triangles: usize,
}

impl Emit<'_> {
    fn emit(
        &mut self,
        what: &str,
        substeps: u32,
        t: &TickTimes,
        overruns: u64,
    ) -> anyhow::Result<()> {
        let p = t.percentiles();
        let row = Row {
            mesh: self.mesh.to_string(),
            nodes: self.nodes,
            triangles: self.triangles,
            what: what.into(),
            substeps,
            count: t.len(),
            p50_us: p.p50_us,
            p99_us: p.p99_us,
            max_us: p.max_us,
            overruns,
        };
        println!(
            "{:<20} {:>6} {:>6} {:<16} {:>4} {:>7} {:>9.1} {:>9.1} {:>9.1} {:>8}",
            row.mesh,
            row.nodes,
            row.triangles,
            row.what,
            row.substeps,
            row.count,
            row.p50_us,
            row.p99_us,
            row.max_us,
            row.overruns
        );
        self.csv.serialize(&row)?;
        Ok(())
    }
}

/// Events: subdivide around a random free node, then coarsen, `reps` times, with 1 and 2 rings.
fn event_rows(
    scene: &Scene,
    surface: &SpringSurface,
    reps: usize,
    emit: &mut Emit<'_>,
) -> anyhow::Result<()> {
    let n = surface.node_count();
    for rings in [1u32, 2] {
        let mut body = body_with_rings(scene, rings)?;
        let free: Vec<u32> = (0..n as u32).filter(|&i| !surface.is_fixed(i)).collect();
        let (mut sub, mut coarse) = (TickTimes::new(), TickTimes::new());
        let mut rng = common_rng(rings as u64);
        for _ in 0..reps {
            let c = free[(rng() * free.len() as f64) as usize % free.len()];
            let t = Instant::now();
            body.subdivide_around(&[c]);
            sub.record(t.elapsed());
            let t = Instant::now();
            body.coarsen();
            coarse.record(t.elapsed());
        }
        emit.emit(
            &format!("event {rings}-ring"),
            body.plan().substeps,
            &sub,
            0,
        )?;
        emit.emit(
            &format!("coarsen {rings}-ring"),
            body.plan().substeps,
            &coarse,
            0,
        )?;
    }
    Ok(())
}

/// Ticks with events: press the apex, slide to a rim-ward node, leave, press again.
fn events_tick_row(
    scene: &Scene,
    surface: &SpringSurface,
    quick: bool,
    emit: &mut Emit<'_>,
) -> anyhow::Result<()> {
    let mut body = body_with_rings(scene, 1)?;
    let path = probe_path(surface, scene.probe.radius_m);
    let ticks = if quick { 1500 } else { 3000 };
    let mut times = TickTimes::new();
    for k in 0..ticks {
        let input = TickInput {
            device_position_m: Some(path(k as f64 / ticks as f64)),
            device_velocity_m_per_s: DVec3::ZERO,
        };
        let t = Instant::now();
        body.tick(&input)?;
        times.record(t.elapsed());
    }
    let events = body.event_stats().events;
    emit.emit(
        &format!("tick ({events} events)"),
        body.plan().substeps,
        &times,
        times.count_at_least_us(1000),
    )?;
    Ok(())
}

/// Step time while pressed (subdivided).
fn pressed_tick_row(
    label: &str,
    scene: &Scene,
    surface: &SpringSurface,
    quick: bool,
    emit: &mut Emit<'_>,
) -> anyhow::Result<()> {
    let n = surface.node_count();
    let mut body = body_with_rings(scene, 1)?;
    let apex = surface.rest()[0] + surface.rest_normal(0) * scene.probe.radius_m;
    let press = |d: f64| TickInput {
        device_position_m: Some(apex - surface.rest_normal(0) * d),
        device_velocity_m_per_s: DVec3::ZERO,
    };
    let depth = 0.5 * surface.element_size_m(0);
    for k in 0..300 {
        body.tick(&press(depth * (k as f64 / 200.0).min(1.0)))?;
    }
    let mut times = TickTimes::new();
    let count = if quick {
        500
    } else {
        if n > 20_000 { 1000 } else { 3000 }
    };
    for _ in 0..count {
        let t = Instant::now();
        body.tick(&press(depth))?;
        times.record(t.elapsed());
    }
    assert!(
        body.stats().nodes > n,
        "{label}: the pressed surface is subdivided"
    );
    emit.emit(
        "tick (pressed)",
        body.plan().substeps,
        &times,
        times.count_at_least_us(1000),
    )?;
    Ok(())
}

/// The force steps of subdivision events under load, for each vertex rule: the probe slides
/// at half an element deep from the hemisphere's apex over two elements in 1 s, so that the
/// contact node changes and areas are subdivided under the probe. The table rows of the nodes
/// on the path are calibrated for each rule. Prints the largest force change over one tick at
/// the ticks that ran an event against the changes of the other ticks; writes
/// `mass_spring_slide.csv`.
fn slide(scene: &Scene, out: &std::path::Path) -> anyhow::Result<()> {
    use haptic_model::mass_spring::VertexRule;
    use haptic_model::mass_spring::calibration::calibrate_node;
    let ms = scene.mass_spring.as_ref().context("mass-spring")?;
    let s = &ms.surface;
    let l = s.element_size_m(0);
    let r = scene.probe.radius_m;
    let n0 = s.rest_normal(0);
    let top = s.rest()[0] + n0 * (r - 0.5 * l);
    let path = |t: f64| {
        // Along the sphere: rotate the pressed point about y.
        let angle = (2.0 * l / 0.05) * t.clamp(0.0, 1.0);
        let (sn, cs) = angle.sin_cos();
        DVec3::new(top.z * sn, 0.0, top.z * cs)
    };
    let near: Vec<u32> = (0..s.node_count() as u32)
        .filter(|&i| {
            !s.is_fixed(i)
                && (0..=20)
                    .any(|k| (s.rest()[i as usize] - path(k as f64 / 20.0)).length() < 1.6 * l)
        })
        .collect();
    let mut w = csv::Writer::from_path(out.join("mass_spring_slide.csv"))?;
    w.write_record(["vertex_rule", "tick", "force_n", "event"])?;
    println!("slide: {} nodes calibrated per vertex rule", near.len());
    for rule in [VertexRule::Keep, VertexRule::Loop] {
        let mut p = ms.params;
        p.subdivision.vertex_rule = rule;
        let mut rows = vec![None; s.node_count()];
        for &i in &near {
            rows[i as usize] = Some(calibrate_node(s, &p, ms.contact, i)?);
        }
        let table = CalibrationTable::from_rows(0, rows);
        let mut body = MassSpringBody::new(
            s.clone(),
            &p,
            Some(table),
            scene.probe,
            &scene.integrator,
            "slide",
        )?;
        // Press at the apex, hold, slide, hold.
        let mut forces = Vec::new();
        let mut event_ticks = Vec::new();
        for k in 0..1700 {
            let pos = if k < 300 {
                s.rest()[0] + n0 * (r - 0.5 * l * (k as f64 / 200.0).min(1.0))
            } else {
                path((k - 300) as f64 / 1000.0)
            };
            let before = body.event_stats().events;
            let o = body.tick(&TickInput {
                device_position_m: Some(pos),
                device_velocity_m_per_s: DVec3::ZERO,
            })?;
            let event = body.event_stats().events > before;
            forces.push(o.force_on_device_n.length());
            if event {
                event_ticks.push(k);
            }
            w.write_record([
                rule.name().to_string(),
                k.to_string(),
                forces[k].to_string(),
                event.to_string(),
            ])?;
        }
        let steps: Vec<(usize, f64)> = (301..forces.len())
            .map(|k| (k, (forces[k] - forces[k - 1]).abs()))
            .collect();
        let at_events = steps
            .iter()
            .filter(|(k, _)| event_ticks.contains(k) || event_ticks.contains(&(k - 1)))
            .map(|s| s.1)
            .fold(0.0, f64::max);
        let mut others: Vec<f64> = steps
            .iter()
            .filter(|(k, _)| !event_ticks.contains(k) && !event_ticks.contains(&(k - 1)))
            .map(|s| s.1)
            .collect();
        others.sort_by(f64::total_cmp);
        let p99 = others[(others.len() * 99) / 100];
        let mean_f = forces[300..].iter().sum::<f64>() / (forces.len() - 300) as f64;
        println!(
            "slide, vertex rule {:<5}: {} events; largest force step at an event tick {:.4} N ({:.1} % of the mean force {:.3} N); other ticks p99 {:.4} N, max {:.4} N",
            rule.name(),
            event_ticks.len(),
            at_events,
            at_events / mean_f * 100.0,
            mean_f,
            p99,
            others.last().copied().unwrap_or(0.0)
        );
    }
    w.flush()?;
    Ok(())
}

/// A generated hemisphere with the scene's parameters and probe (radius half the edge), its
/// table the built-in hemisphere's apex row for every node.
fn generated(base: &Scene, edge_m: f64) -> anyhow::Result<Scene> {
    let mesh = generate::hemisphere_surface(0.05, edge_m);
    let rim = mesh.node_group("RIM").context("RIM")?.nodes.clone();
    let tris = mesh
        .surface("SURFACE")
        .context("SURFACE")?
        .triangles
        .clone();
    let surface = SpringSurface::from_mesh(&mesh.nodes, &tris, &rim)?;
    let mut scene = base.clone();
    let ms = scene.mass_spring.as_mut().context("mass-spring")?;
    let row = *ms.table()?.context("table")?.node(0).context("apex row")?;
    ms.table = haptic_model::scene::TableState::Ready(CalibrationTable::uniform(
        surface.node_count(),
        row,
        0,
    ));
    ms.surface = surface;
    scene.probe.radius_m = 0.5 * edge_m;
    Ok(scene)
}

fn body_with_rings(scene: &Scene, rings: u32) -> anyhow::Result<MassSpringBody> {
    let ms = scene.mass_spring.as_ref().context("mass-spring")?;
    let mut p = ms.params;
    p.subdivision.rings = rings;
    Ok(MassSpringBody::new(
        ms.surface.clone(),
        &p,
        ms.table()?,
        scene.probe,
        &scene.integrator,
        &scene.name,
    )?)
}

/// The device along a press-slide-leave-press path, `s` in [0, 1]: 4 mm... half an element
/// into the apex, a slide over two elements, lift off for a while, press again.
fn probe_path(surface: &SpringSurface, r: f64) -> impl Fn(f64) -> DVec3 + '_ {
    let l = surface.element_size_m(0);
    let apex = surface.rest()[0];
    let n = surface.rest_normal(0);
    let side = DVec3::X;
    move |s: f64| {
        let depth = 0.5 * l;
        let top = apex + n * (r - depth);
        match s {
            s if s < 0.2 => apex + n * (r - depth * s / 0.2),
            s if s < 0.4 => top + side * (2.0 * l * (s - 0.2) / 0.2),
            s if s < 0.8 => top + side * 2.0 * l + n * 0.02,
            _ => top,
        }
    }
}

/// A deterministic source of numbers in [0, 1) (SplitMix64).
fn common_rng(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
}
