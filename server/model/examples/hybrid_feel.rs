//! The feel protocols of issue 46 ([`haptic_model::press`]: staircase, the demo's press, the
//! left ventricle's half-turn stroke) on a hybrid scene with the study overrides of
//! `hybrid_press`, printing per hold the force, its steadiness and the hybrid's own counters
//! (active particles, refused activations, regions released for room, refactorings of the
//! implicit core). `--trace` prints every tick (ms, device depth, |F|, active, refactorings).
//!
//! `cargo run --release -p haptic-model --example hybrid_feel -- staircase --depths 0.5,1,2,3,4`

#[path = "common/hybrid_overrides.rs"]
mod hybrid_overrides;
#[path = "common/press_protocol.rs"]
mod press_protocol;

use std::time::Instant;

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::body::{SoftBody, TickInput, TickOutput};
use haptic_model::hybrid::HybridBody;
use haptic_model::press::{self, HoldParams, PressLine};
use haptic_model::scene::load_builtin;
use hybrid_overrides::HybridOverrides;
use press_protocol::Protocol;

#[derive(Parser)]
struct Args {
    /// Built-in hybrid scene.
    #[arg(long, default_value = "lv-hybrid")]
    scene: String,
    #[command(flatten)]
    hybrid: HybridOverrides,
    /// Print every tick.
    #[arg(long)]
    trace: bool,
    /// Line start, mm, along -x (default: the lv-probe line, whose depth zero is the analytic
    /// epicardium); with it the depth zero is the body's rest surface.
    #[arg(long, value_delimiter = ',', allow_negative_numbers = true)]
    from: Option<Vec<f64>>,
    #[command(subcommand)]
    protocol: Protocol,
}

/// A [`HybridBody`] behind the seam that prints its counters every tick when asked.
struct Traced {
    body: HybridBody,
    trace: bool,
    line: PressLine,
    ticks: usize,
}

impl SoftBody for Traced {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, haptic_model::ModelError> {
        let out = self.body.tick(input)?;
        self.ticks += 1;
        if self.trace {
            let d = input
                .device_position_m
                .map_or(f64::NAN, |p| self.line.depth_of(p));
            println!(
                "{} {:.4} {:.4} {} {} {} {}",
                self.ticks,
                d * 1e3,
                out.force_on_device_n.length() * 1e3,
                self.body.active_particles().len(),
                self.body.refused_activations(),
                self.body.released_for_room(),
                self.body.implicit_refactors()
            );
        }
        Ok(out)
    }
    fn add_point_load(
        &mut self,
        p: DVec3,
        f: DVec3,
        d: f64,
    ) -> Result<(), haptic_model::ModelError> {
        self.body.add_point_load(p, f, d)
    }
    fn surface_topology(&self) -> haptic_model::body::SurfaceTopology<'_> {
        self.body.surface_topology()
    }
    fn surface_capacity(&self) -> haptic_model::body::SurfaceCapacity {
        self.body.surface_capacity()
    }
    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        self.body.write_surface_positions(out)
    }
    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        self.body.write_surface_rest_positions(out)
    }
    fn stats(&self) -> haptic_model::body::BodyStats {
        self.body.stats()
    }
    fn info(&self) -> haptic_model::body::BodyInfo {
        self.body.info()
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut scene = load_builtin(&args.scene)?;
    args.hybrid.apply(&mut scene)?;
    let t0 = Instant::now();
    let body = haptic_model::build_hybrid_body(&scene, &mut |_, _| {})?;
    let info = body.info();
    let r = info.probe_radius_m;
    let line = match &args.from {
        None => PressLine::lv_probe(r),
        Some(v) if v.len() == 3 => {
            PressLine::from_rest_surface(&body, DVec3::new(v[0], v[1], v[2]) * 1e-3, -DVec3::X, r)?
        }
        Some(v) => anyhow::bail!("--from takes x,y,z in mm, got {v:?}"),
    };
    println!(
        "{}: set-up {:.2} s, {} sub-steps, core {} tets, {} particles",
        scene.name,
        t0.elapsed().as_secs_f64(),
        info.substeps,
        body.stats().elements,
        body.stats().particles
    );
    let mut b = Traced {
        body,
        trace: args.trace,
        line,
        ticks: 0,
    };
    let tick = info.tick_s;
    let (holds, trace) = match args.protocol {
        Protocol::Staircase {
            depths,
            ramp_s,
            hold_s,
        } => {
            let d: Vec<f64> = depths.iter().map(|d| d * 1e-3).collect();
            let p = HoldParams {
                ramp_s,
                hold_s,
                average_s: (hold_s * 2.0 / 3.0).min(hold_s),
            };
            press::staircase(&mut b, &line, &d, &p, tick)?
        }
        Protocol::Demo {
            depth,
            speed,
            hold_s,
        } => {
            let (h, t) = press::constant_speed_press(
                &mut b,
                &line,
                depth * 1e-3,
                speed * 1e-3,
                hold_s,
                tick,
            )?;
            (vec![h], t)
        }
        Protocol::Stroke { depth, speed } => {
            let (s, t) = press::lv_half_turn(&mut b, r, depth * 1e-3, speed * 1e-3, tick)?;
            println!(
                "stroke: hold {:.4} mN; slide {:.3}..{:.3} mN, largest tick change {:.4} mN ({:.2} % of the hold), contact {}/{}",
                s.hold.force_n * 1e3,
                s.force_min_n * 1e3,
                s.force_max_n * 1e3,
                s.max_tick_change_n * 1e3,
                100.0 * s.max_tick_change_n / s.hold.force_n,
                s.contact_ticks,
                s.slide_ticks
            );
            (vec![s.hold], t)
        }
    };
    println!("device_mm sphere_mm force_mN min..max_mN change_mN change_%");
    for h in &holds {
        println!(
            "{:.3} {:.4} {:.4} {:.3}..{:.3} {:.4} {:.2}",
            h.device_depth_m * 1e3,
            h.sphere_depth_m * 1e3,
            h.force_n * 1e3,
            h.force_min_n * 1e3,
            h.force_max_n * 1e3,
            h.max_tick_change_n * 1e3,
            100.0 * h.steadiness()
        );
    }
    println!(
        "ticks {}: p50 {:.1} us, p99 {:.1} us, max {:.1} us; refused {}, released for room {}, refactorings {}, unconverged proxy solves {}",
        trace.tick_wall_s.len(),
        trace.tick_quantile_s(0.5) * 1e6,
        trace.tick_quantile_s(0.99) * 1e6,
        trace.tick_quantile_s(1.0) * 1e6,
        b.body.refused_activations(),
        b.body.released_for_room(),
        b.body.implicit_refactors(),
        b.body.unconverged_proxy_solves()
    );
    Ok(())
}
