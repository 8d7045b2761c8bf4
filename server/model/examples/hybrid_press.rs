//! Presses the hybrid scene `lv-hybrid` (or any built-in hybrid scene) at the lv-probe point
//! (the epicardium at z = -5 mm, along -x) through a staircase of depths with a chosen ramp
//! and hold, and prints the mean device force over the second half of each hold: a study of
//! how far the mass-scaled dynamics are from the static answer (issue 13).
//!
//! `cargo run --release -p haptic-model --example hybrid_press -- --variant corrected --ramp-s 0.5 --hold-s 6 --mass-scale 1000`
//!
//! The lv-probe benchmark uses `--ramp-s 0.1 --hold-s 0.1`; a hold of several seconds gives the
//! quasi-static force to compare with the converged sphere reference (`docs/accuracy.md`).
//! `--trace-every N` also prints `time_s,depth_mm,force_mn` every N ticks to stderr (the
//! ringing and creep after each ramp).

#[path = "common/hybrid_overrides.rs"]
mod hybrid_overrides;

use clap::Parser;
use haptic_model::DVec3;
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::scene::load_builtin;
use hybrid_overrides::HybridOverrides;

#[derive(Parser)]
struct Args {
    /// Built-in hybrid scene.
    #[arg(long, default_value = "lv-hybrid")]
    scene: String,
    #[command(flatten)]
    hybrid: HybridOverrides,
    /// Ramp to each depth, s (smoothstep).
    #[arg(long, default_value_t = 0.1)]
    ramp_s: f64,
    /// Hold at each depth, s; the force is averaged over its second half.
    #[arg(long, default_value_t = 0.1)]
    hold_s: f64,
    /// Sub-steps per tick override (a study of the step: the body is built from the scene's
    /// preprocessed model and `HybridBody::override_substeps`).
    #[arg(long)]
    substeps: Option<u32>,
    /// Print `time_s,depth_mm,force_mn` to stderr every N ticks (0: only the summary).
    #[arg(long, default_value_t = 0)]
    trace_every: usize,
    /// Depths, mm.
    #[arg(long, default_value = "0.5,1", value_delimiter = ',')]
    depths_mm: Vec<f64>,
}

/// Probe centre x at first contact: the epicardium at z = -5 mm (9.682 mm from the axis) plus
/// the 2 mm probe radius, as in the lv-probe benchmark.
const CONTACT_X_M: f64 = 0.011_682;

fn smoothstep(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut scene = load_builtin(&args.scene)?;
    args.hybrid.apply(&mut scene)?;
    let h = scene.hybrid.as_ref().expect("a hybrid scene");
    let (variant, mass_scale) = (h.params.meshfree.variant, h.params.mass_scale);

    let mut hybrid = haptic_model::build_hybrid_body(&scene, &mut |_, _| {})?;
    if let Some(n) = args.substeps {
        hybrid.override_substeps(n)?;
    }
    let core_mass_scale = hybrid.core_mass_scale();
    let mut body: Box<dyn SoftBody> = Box::new(hybrid);
    let tick = scene.integrator.tick_s;
    println!(
        "{} {} mass_scale {mass_scale}, core_mass_scale {core_mass_scale}, contact stiffness {} N/m per particle, ramp {} s, hold {} s, {} sub-steps per tick",
        args.scene,
        variant.name(),
        scene
            .hybrid
            .as_ref()
            .map_or(0.0, |h| h.params.particle_contact_stiffness_n_per_m()),
        args.ramp_s,
        args.hold_s,
        body.info().substeps
    );
    println!("depth_mm,force_mn,last_force_mn");
    let mut prev = -0.3e-3;
    for d_mm in &args.depths_mm {
        let d = d_mm * 1e-3;
        let n = ((args.ramp_s + args.hold_s) / tick).round() as usize;
        let (mut sum, mut count, mut last) = (0.0, 0usize, 0.0);
        for k in 0..n {
            let t = (k + 1) as f64 * tick;
            let depth = prev + (d - prev) * smoothstep(t / args.ramp_s);
            let out = body.tick(&TickInput {
                device_position_m: Some(DVec3::new(CONTACT_X_M - depth, 0.0, -0.005)),
                device_velocity_m_per_s: DVec3::ZERO,
            })?;
            last = out.force_on_device_n.length();
            if args.trace_every > 0 && k % args.trace_every == 0 {
                eprintln!("{:.4},{:.5},{:.4}", t, depth * 1e3, last * 1e3);
            }
            if t > args.ramp_s + args.hold_s / 2.0 {
                sum += last;
                count += 1;
            }
        }
        println!(
            "{d_mm},{:.4},{:.4}",
            sum / count.max(1) as f64 * 1e3,
            last * 1e3
        );
        prev = d;
    }
    let stats = body.stats();
    println!(
        "core {} tets; particles {} total, {} active at the last depth",
        stats.elements, stats.particles, stats.active_particles
    );
    Ok(())
}
