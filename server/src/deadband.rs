//! What the forwarder of a session ([`crate::session`]) sends to a DeviceLink stream: the
//! perceptual force deadband (which commands pass) and the command itself, clamped to the
//! attached device's limits.

use haptics_proto::v1::{ForceCommand, Vec3};

use crate::frame::unix_time_us;
use crate::servo::ForceOut;

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

/// The command for `f`, its force and contact stiffness clamped to the attached device's
/// `(force N, stiffness N/m)` limits ([`crate::device::DeviceShared::limits`]).
pub(crate) fn force_command(
    f: &ForceOut,
    (max_force_n, max_stiffness_n_per_m): (f64, f64),
) -> ForceCommand {
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
