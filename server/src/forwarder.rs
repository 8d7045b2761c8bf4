//! The forwarder of a session (one thread, [`crate::session`]): drains each tool slot's force
//! ring into that slot's DeviceLink stream, through the perceptual force deadband and the
//! attached device's limits. Woken by the servo with `Thread::unpark` (wait-free).

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use haptics_proto::v1::{ForceCommand, Vec3};

use crate::error::ServerError;
use crate::frame::unix_time_us;
use crate::servo::{ForceOut, SessionShared};
use crate::session::ToolSlot;

/// Longest gap between two force commands under the force deadband, µs (keeps the bridge's
/// command ages well under its 10 ms watchdog threshold).
pub const DEADBAND_HEARTBEAT_US: u64 = 5_000;
/// Smallest force change the deadband passes, N.
pub const DEADBAND_FLOOR_N: f64 = 1e-3;

/// The perceptual deadband on the force stream (Hinterseer and Steinbach, devices.md \[S38\]): a
/// force command is sent when the force changed by more than `k` times the last sent one (and
/// by more than [`DEADBAND_FLOOR_N`]), when the contact flag or the contact stiffness changed
/// by more than `k`, or [`DEADBAND_HEARTBEAT_US`] after the last one sent. `k <= 0` sends all.
pub fn force_deadband_passes(
    k: f64,
    last: Option<&ForceOut>,
    since_last_us: u64,
    f: &ForceOut,
) -> bool {
    let Some(l) = last else { return true };
    if k <= 0.0 || since_last_us >= DEADBAND_HEARTBEAT_US || l.in_contact != f.in_contact {
        return true;
    }
    let d = (f.force_n - l.force_n).length();
    if d > k * l.force_n.length() && d > DEADBAND_FLOOR_N {
        return true;
    }
    let norm = |m: &[f64; 9]| m.iter().map(|v| v * v).sum::<f64>().sqrt();
    let dk: f64 = f
        .stiffness_n_per_m
        .iter()
        .zip(&l.stiffness_n_per_m)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    dk > k * norm(&l.stiffness_n_per_m)
}

/// The force deadband of the attached device stream and what it held back.
#[derive(Debug, Default)]
pub struct DeadbandShared {
    /// Deadband fraction as `f64` bits (0: off), set when a device attaches.
    pub fraction_bits: std::sync::atomic::AtomicU64,
    /// Force commands held back so far.
    pub suppressed: std::sync::atomic::AtomicU64,
    /// Force commands sent so far.
    pub sent: std::sync::atomic::AtomicU64,
}

/// Spawns the forwarder thread of session `id`: drains each tool slot's force ring (`rings[k]`
/// for `tools[k]`) into that slot's DeviceLink stream through its deadband and its device's
/// limits, until the servo has finished and the rings are empty.
pub(crate) fn spawn_forwarder(
    id: &str,
    mut rings: Vec<rtrb::Consumer<ForceOut>>,
    fwd_shared: Arc<SessionShared>,
    tools: Vec<Arc<ToolSlot>>,
) -> Result<std::thread::JoinHandle<()>, ServerError> {
    std::thread::Builder::new()
        .name(format!("fwd-{id}"))
        .spawn(move || {
            let mut last: Vec<Option<(ForceOut, Instant)>> = vec![None; tools.len()];
            loop {
                std::thread::park_timeout(Duration::from_millis(5));
                for ((ring, tool), last) in rings.iter_mut().zip(&tools).zip(&mut last) {
                    forward_tool(ring, tool, last, &fwd_shared);
                }
                if fwd_shared.finished.load(Ordering::Acquire) && rings.iter().all(|r| r.is_empty())
                {
                    break;
                }
            }
        })
        .map_err(|e| ServerError::Internal(format!("spawning the forwarder: {e}")))
}

/// Drains one tool's force ring into its stream (the forwarder's work for one slot): `last` is
/// the last command sent and when, for the deadband.
fn forward_tool(
    ring: &mut rtrb::Consumer<ForceOut>,
    tool: &ToolSlot,
    last: &mut Option<(ForceOut, Instant)>,
    shared: &SessionShared,
) {
    while let Ok(f) = ring.pop() {
        let k = f64::from_bits(tool.deadband.fraction_bits.load(Ordering::Relaxed));
        let finishing = shared.stop.load(Ordering::Acquire);
        let since = last.map_or(u64::MAX, |(_, t)| t.elapsed().as_micros() as u64);
        if !finishing && !force_deadband_passes(k, last.as_ref().map(|(l, _)| l), since, &f) {
            tool.deadband.suppressed.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        if let Some(tx) = tool.sender() {
            let limits = tool.device.limits();
            if tx.try_send(Ok(force_command(&f, limits))).is_ok() {
                tool.deadband.sent.fetch_add(1, Ordering::Relaxed);
            }
            *last = Some((f, Instant::now()));
        } else {
            *last = None;
        }
    }
}

/// The command for `f`, its force and contact stiffness clamped to the attached device's
/// `(force N, stiffness N/m)` limits ([`crate::device::DeviceShared::limits`]).
fn force_command(f: &ForceOut, (max_force_n, max_stiffness_n_per_m): (f64, f64)) -> ForceCommand {
    let force = crate::device::clamp_force(f.force_n, max_force_n);
    let stiffness = crate::device::clamp_stiffness(f.stiffness_n_per_m, max_stiffness_n_per_m);
    ForceCommand {
        seq: f.seq,
        force_n: Some(Vec3::from(force.to_array())),
        server_time_us: unix_time_us(),
        in_contact: f.in_contact,
        stiffness_n_per_m: stiffness.to_vec(),
        proxy_position_m: Some(Vec3::from(f.proxy_m.to_array())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use haptic_model::DVec3;

    fn out(fx: f64, in_contact: bool) -> ForceOut {
        ForceOut {
            force_n: DVec3::new(fx, 0.0, 0.0),
            in_contact,
            ..ForceOut::default()
        }
    }

    #[test]
    fn the_force_deadband_passes_changes_above_seven_percent_and_a_heartbeat() {
        let last = out(0.1, true);
        // (k, force, since last us, sent?)
        let table = [
            (0.0, out(0.1, true), 0, true),         // off
            (0.07, out(0.106, true), 1_000, false), // 6 % change
            (0.07, out(0.108, true), 1_000, true),  // 8 % change
            (0.07, out(0.1, true), 4_999, false),
            (0.07, out(0.1, true), 5_000, true),  // heartbeat
            (0.07, out(0.1, false), 1_000, true), // contact flag changed
        ];
        for (k, f, since, want) in table {
            assert_eq!(
                force_deadband_passes(k, Some(&last), since, &f),
                want,
                "{k} {f:?} {since}"
            );
        }
        assert!(force_deadband_passes(0.07, None, 0, &last));
        // Below the 1 mN floor nothing passes early, whatever the relative change.
        let tiny = out(0.0002, true);
        assert!(!force_deadband_passes(
            0.07,
            Some(&tiny),
            1_000,
            &out(0.0009, true)
        ));
    }
}
