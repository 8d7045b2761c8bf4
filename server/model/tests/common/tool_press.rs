//! Shared helpers of the several-tools tests (`tools.rs`, `tools_mass_spring.rs`): a smooth
//! ramp to a depth then a hold, two-slot runs and their holds' statistics. Each file declares
//! `#[path = "common/tool_press.rs"] mod tool_press;`.
#![allow(dead_code)]

use glam::DVec3;
use haptic_model::body::{SoftBody, TickInput, TickOutput};
use haptic_model::press::PressLine;

/// Ramp time of [`ramp_input`], s.
pub const RAMP_S: f64 = 0.2;

/// The device input on `line` at time `t` (s) of a smoothstep ramp over [`RAMP_S`] to
/// `depth_m` (m past first contact), then a hold; the ramp starts 0.2 mm before first contact,
/// so contact begins gently. The velocity is the ramp's derivative.
pub fn ramp_input(line: &PressLine, depth_m: f64, t: f64) -> TickInput {
    let u = (t / RAMP_S).clamp(0.0, 1.0);
    let s = u * u * (3.0 - 2.0 * u);
    let ds = if t < RAMP_S {
        6.0 * u * (1.0 - u) / RAMP_S
    } else {
        0.0
    };
    let d0 = -0.2e-3;
    TickInput {
        device_position_m: Some(line.device_at(d0 + (depth_m - d0) * s)),
        device_velocity_m_per_s: line.direction * (depth_m - d0) * ds,
    }
}

/// Runs `ticks` two-slot ticks of `body` with `input(tick)`, returning every tick's outputs.
pub fn run(
    body: &mut dyn SoftBody,
    ticks: usize,
    mut input: impl FnMut(usize) -> [TickInput; 2],
) -> Vec<[TickOutput; 2]> {
    let mut trace = Vec::with_capacity(ticks);
    for k in 0..ticks {
        let mut out = [TickOutput::default(); 2];
        body.tick_tools(&input(k), &mut out).expect("tick");
        trace.push(out);
    }
    trace
}

/// Mean force (N) over `range` of tool `slot`, and the largest tick-to-tick change (N).
pub fn hold_stats(
    trace: &[[TickOutput; 2]],
    slot: usize,
    range: std::ops::Range<usize>,
) -> (DVec3, f64) {
    let forces: Vec<DVec3> = trace[range]
        .iter()
        .map(|o| o[slot].force_on_device_n)
        .collect();
    let mean = forces.iter().copied().sum::<DVec3>() / forces.len() as f64;
    let change = forces
        .windows(2)
        .map(|w| (w[1] - w[0]).length())
        .fold(0.0, f64::max);
    (mean, change)
}
