//! What a run reports: [`BridgeSummary`] (totals) and [`BridgeReport`] (with the per-tick rows).

use std::fmt;

use serde::Serialize;

use crate::record::TickRecord;

use super::BridgeConfig;
use super::device_loop::DeviceLoopStats;
use super::net::NetCtx;

/// What happened during a run. Counts are totals over the run; times in microseconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct BridgeSummary {
    /// Samples handed to the gRPC stream.
    pub samples_sent: u64,
    /// Samples dropped because a queue was full (device -> network, or the outbound stream).
    pub samples_dropped: u64,
    /// `ForceCommand`s received.
    pub forces_received: u64,
    /// Forces whose `seq` matched no recently sent sample (dropped).
    pub unmatched_forces: u64,
    /// Forces whose `seq` was not newer than the last accepted one (dropped).
    pub stale_forces: u64,
    /// Samples the pose deadband kept back.
    pub samples_suppressed: u64,
    /// Messages dropped by fault injection (both ways).
    pub injected_drops: u64,
    /// Median pose-to-force round trip, in us (`None` without matched forces).
    pub rtt_p50_us: Option<u64>,
    /// 99th percentile round trip, in us.
    pub rtt_p99_us: Option<u64>,
    /// Largest round trip, in us.
    pub rtt_max_us: Option<u64>,
    /// Largest force magnitude written to the device, in N.
    pub peak_force_n: f64,
    /// Largest distance travelled from the start along the press direction, in m (scripted
    /// drivers; 0 otherwise).
    pub max_depth_m: f64,
    /// Received forces flagged `in_contact`.
    pub contact_samples: u64,
    /// Commands clamped to the peak force (S6).
    pub clamped: u64,
    /// Ticks on which the slew limit acted (S7).
    pub rate_limited: u64,
    /// Non-finite commands rejected (S11).
    pub rejected_nan: u64,
    /// Entries into the stale-command ramp (S4).
    pub watchdog_ramps: u64,
    /// Entries into the expired state (command older than the ramp).
    pub watchdog_expired: u64,
    /// Ticks zeroed because the position was outside the workspace (S11).
    pub workspace_violations: u64,
    /// Times the output was disabled after 100 ms without a fresh command (S5).
    pub latches: u64,
    /// Re-arms (S9).
    pub rearms: u64,
    /// Re-arm requests refused because the link was not healthy for long enough yet.
    pub rearm_refused: u64,
    /// Energy the passivity observer saw absorbed by the environment at the end, J.
    pub passivity_energy_j: f64,
    /// Energy the passivity controller dissipated, J.
    pub passivity_dissipated_j: f64,
    /// Ticks on which the passivity controller acted.
    pub passivity_active_ticks: u64,
    /// Force limit in force at the end (the lower of the device's and the scene's), N.
    pub max_force_n: f64,
    /// Force-rate limit in force at the end, N/s.
    pub max_force_rate_n_per_s: f64,
    /// Daemon restarts seen (a new server instance on reconnect).
    pub server_restarts: u64,
    /// Why the session cannot be reached any more (the daemon answered NOT_FOUND), if so.
    pub session_lost: Option<String>,
    /// Why the daemon refused this bridge (UNAUTHENTICATED or PERMISSION_DENIED: no token, a
    /// wrong one, or a role without the device link), if it did: the bridge stops at once
    /// rather than retry, since retrying cannot help (issue 47).
    pub access_refused: Option<String>,
    /// Streams that reached the server (response headers received).
    pub streams_opened: u64,
    /// Streams opened after an earlier attempt failed or a stream was lost.
    pub reconnects: u64,
    /// Connection attempts or streams that failed.
    pub link_failures: u64,
    /// The last link failure, if any.
    pub last_link_error: Option<String>,
    /// Device ticks run.
    pub ticks: u64,
    /// Ticks whose work overran the next deadline (missed deadlines are skipped, not caught up).
    pub overruns: u64,
    /// Failed device reads or writes.
    pub device_errors: u64,
    /// Why the device loop gave up, if it did.
    pub device_fault: Option<String>,
    /// Last force written to the device, in N (zero after a clean stop).
    pub final_force_n: [f64; 3],
    /// Wall time of the device loop, in s.
    pub duration_s: f64,
}

impl BridgeSummary {
    /// The totals of a run: the network side's counters and round trips (`ctx`), the device
    /// thread's (`dev`), and the limits in force at the end (`config`'s when the scene sent none).
    pub(super) fn of_run(ctx: &NetCtx, dev: &DeviceLoopStats, config: &BridgeConfig) -> Self {
        let h = &ctx.rtt_us;
        let rtt = |q: f64| (!h.is_empty()).then(|| h.value_at_quantile(q));
        Self {
            samples_sent: ctx.samples_sent,
            samples_dropped: ctx.samples_dropped + dev.samples_dropped,
            forces_received: ctx.forces_received,
            unmatched_forces: ctx.unmatched_forces,
            stale_forces: ctx.stale_forces + dev.guard.stale_dropped,
            samples_suppressed: dev.samples_suppressed,
            injected_drops: ctx.injected_drops,
            rtt_p50_us: rtt(0.5),
            rtt_p99_us: rtt(0.99),
            rtt_max_us: (!h.is_empty()).then(|| h.max()),
            peak_force_n: dev.peak_force_n,
            max_depth_m: dev.max_depth_m,
            contact_samples: ctx.contact_samples,
            clamped: dev.guard.clamped,
            rate_limited: dev.guard.rate_limited,
            rejected_nan: dev.guard.rejected_nan,
            watchdog_ramps: dev.guard.watchdog_ramps,
            watchdog_expired: dev.guard.watchdog_expired,
            workspace_violations: dev.guard.workspace_violations,
            latches: dev.guard.latches,
            rearms: dev.guard.rearms,
            rearm_refused: dev.guard.rearm_refused,
            passivity_energy_j: dev.guard.passivity.energy_j,
            passivity_dissipated_j: dev.guard.passivity.dissipated_j,
            passivity_active_ticks: dev.guard.passivity.active_ticks,
            max_force_n: dev
                .limits
                .map_or(config.guard.max_force_n, |l| l.max_force_n),
            max_force_rate_n_per_s: dev
                .limits
                .map_or(config.guard.max_rate_n_per_s, |l| l.max_rate_n_per_s),
            server_restarts: ctx.server_restarts,
            session_lost: ctx.session_lost.clone(),
            access_refused: ctx.access_refused.clone(),
            streams_opened: ctx.streams_opened,
            reconnects: ctx.reconnects,
            link_failures: ctx.link_failures,
            last_link_error: ctx.last_link_error.clone(),
            ticks: dev.ticks,
            overruns: dev.overruns,
            device_errors: dev.device_errors,
            device_fault: dev.device_fault.clone(),
            final_force_n: dev.final_force_n,
            duration_s: dev.duration_s,
        }
    }

    /// True when at least one stream reached the server.
    pub fn connected(&self) -> bool {
        self.streams_opened > 0
    }
}

fn opt_us(v: Option<u64>) -> String {
    v.map_or_else(|| "-".to_owned(), |v| v.to_string())
}

impl fmt::Display for BridgeSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "samples sent: {} (dropped {})",
            self.samples_sent, self.samples_dropped
        )?;
        writeln!(
            f,
            "forces received: {} (dropped: unknown seq {}, old seq {})",
            self.forces_received, self.unmatched_forces, self.stale_forces
        )?;
        writeln!(
            f,
            "round trip p50/p99: {}/{} us",
            opt_us(self.rtt_p50_us),
            opt_us(self.rtt_p99_us)
        )?;
        writeln!(f, "round trip max: {} us", opt_us(self.rtt_max_us))?;
        writeln!(f, "peak force: {:.3} N", self.peak_force_n)?;
        writeln!(f, "max depth: {:.3} mm", self.max_depth_m * 1e3)?;
        writeln!(f, "contact samples: {}", self.contact_samples)?;
        writeln!(
            f,
            "guard: clamped {}, rate limited {}, rejected NaN {}, watchdog ramps {}, expired {}, outside workspace {}",
            self.clamped,
            self.rate_limited,
            self.rejected_nan,
            self.watchdog_ramps,
            self.watchdog_expired,
            self.workspace_violations
        )?;
        writeln!(
            f,
            "safety: limits {:.3} N, {:.1} N/s; disabled {}, re-armed {} (refused {}); passivity dissipated {:.3e} J in {} ticks",
            self.max_force_n,
            self.max_force_rate_n_per_s,
            self.latches,
            self.rearms,
            self.rearm_refused,
            self.passivity_dissipated_j,
            self.passivity_active_ticks
        )?;
        writeln!(
            f,
            "link: streams opened {}, reconnects {}, failures {}, daemon restarts {}{}",
            self.streams_opened,
            self.reconnects,
            self.link_failures,
            self.server_restarts,
            self.last_link_error
                .as_ref()
                .map_or_else(String::new, |e| format!(" (last: {e})"))
        )?;
        writeln!(
            f,
            "device: ticks {}, overruns {}, errors {}, {:.3} s{}",
            self.ticks,
            self.overruns,
            self.device_errors,
            self.duration_s,
            self.device_fault
                .as_ref()
                .map_or_else(String::new, |e| format!(", fault: {e}"))
        )?;
        let [x, y, z] = self.final_force_n;
        write!(f, "final force: [{x:.3}, {y:.3}, {z:.3}] N")
    }
}

/// The result of [`super::run`]: the summary and, when recording, one row per device tick.
#[derive(Debug, Clone, Default)]
pub struct BridgeReport {
    /// Totals of the run.
    pub summary: BridgeSummary,
    /// Per-tick rows (empty unless [`super::BridgeConfig::record`]).
    pub ticks: Vec<TickRecord>,
}
