//! The bridge loop: a device thread at the device rate and a network task holding one
//! `DeviceLink.Connect` stream (devices.md section 3.1).
//!
//! ```text
//! [device thread, std::thread, absolute deadlines, no catch-up]      [tokio network task]
//!   read pose ----- try_send (bounded mpsc, never blocks) ----------> DeviceSample stream
//!   latest ForceCommand <-- force slot (std Mutex, held for a copy) <-- ForceCommand stream
//!   guard: age by seq, watchdog, latch/re-arm, local contact model,     seq -> pose time, x0;
//!     passivity, clamp, slew -> write_force                             drop unknown/old seq
//!   (optional) append TickRecord to a pre-reserved Vec                  reconnect + backoff
//! ```
//!
//! Choices:
//! - **Force slot = `std::sync::Mutex<ForceSlot>`.** Both sides hold it only to copy ~80 bytes;
//!   the network task never awaits or allocates while holding it, so the device thread waits at
//!   most a few hundred nanoseconds (no priority inversion worth a wait-free structure in a
//!   separate process whose only other thread is the network task). The server's servo loop
//!   uses wait-free slots instead (DESIGN.md section 3).
//! - **Samples go out through a bounded tokio mpsc with `try_send`.** A full queue drops the
//!   sample and counts it; the device thread never blocks on the network.
//! - **The round trip** is measured pose-to-force: from the device read (`device_time_us`) to
//!   the arrival of the `ForceCommand` echoing that `seq`, on the same injected clock, recorded
//!   in an hdrhistogram by the network task (microseconds).
//! - **Every command is aged from the pose it answers.** The network task keeps `seq -> (read
//!   time, position)` of the samples it sent; a command whose `seq` is unknown (not sent, or
//!   too old for the ring) or not newer than the last accepted one is dropped and counted, the
//!   others reach the guard with the read time and position of their pose.
//! - **Limits at connect time.** The server's response headers carry the scene's force and
//!   force-rate limits (`haptics-max-force-n`, `haptics-max-force-rate-n-per-s`, see the proto)
//!   and its instance id (`haptics-server-instance`); the guard applies the lower of the
//!   scene's and the device's limits.
//! - **Link loss** (no server, stream error, server closed the stream) marks the link down; the
//!   held command keeps ageing, so the force ramps to zero by 60 ms and is disabled at 100 ms
//!   (re-armed as the guard says). The task reconnects with exponential backoff (default 50 ms
//!   doubling to 1 s) until the script finishes or shutdown. A server that answers NOT_FOUND
//!   for the session (it restarted without restoring it) ends the run with a clear message; a
//!   new server instance that restored the session is reported and re-attached to.
//! - **Fault injection** ([`FaultInjection`], for tests and demos only): drops a fraction of the
//!   messages both ways and delays force commands by a random 5-50 ms (in order, as TCP would).
//!
//! Neighbours: [`crate::device`] (the device), [`crate::guard`] (per-tick safety),
//! [`crate::record`] (per-tick rows), `haptics_proto::v1` (the wire contract).

use std::collections::VecDeque;
use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::{DeviceCapabilities, DeviceSample, ForceCommand};
use hdrhistogram::Histogram;
use serde::Serialize;
use thiserror::Error;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Endpoint;
use tracing::{debug, info, warn};

use crate::clock::Clock;
use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, vec3};
use crate::guard::{ForceGuard, GuardCommand, GuardParams, GuardState, GuardStats, Limits};
use crate::record::TickRecord;

/// Number of sent `seq -> send time` entries kept for round-trip matching (4 s at 1 kHz).
const RTT_RING: usize = 4096;
/// Rows reserved up front when recording: 120 s at the device rate.
const RECORD_RESERVE_S: f64 = 120.0;
/// Consecutive failed device reads tolerated before the device is declared faulty, in us
/// (devices.md S2: zero at once, fault after 20 ms).
const DEVICE_FAULT_US: u64 = 20_000;
/// How long to wait for the server to close its side after we close ours.
const CLOSE_GRACE: Duration = Duration::from_millis(200);

/// Response header with the scene's force limit, N (decimal text).
pub const HEADER_MAX_FORCE: &str = "haptics-max-force-n";
/// Response header with the scene's force-rate limit, N/s (decimal text).
pub const HEADER_MAX_FORCE_RATE: &str = "haptics-max-force-rate-n-per-s";
/// Request header asking the server for a force-stream deadband (fraction, decimal text).
pub const HEADER_FORCE_DEADBAND: &str = "haptics-force-deadband";
/// Response header with the server's instance id (changes when the daemon restarts).
pub const HEADER_SERVER_INSTANCE: &str = "haptics-server-instance";

/// The operator's re-arm button: a counter of presses shared with the device thread (the
/// binary presses it for every line read on standard input).
#[derive(Debug, Clone, Default)]
pub struct RearmButton(Arc<AtomicU64>);

impl RearmButton {
    /// A button never pressed.
    pub fn new() -> Self {
        Self::default()
    }

    /// Presses the button once.
    pub fn press(&self) {
        self.0.fetch_add(1, Ordering::AcqRel);
    }

    /// Presses so far.
    pub fn presses(&self) -> u64 {
        self.0.load(Ordering::Acquire)
    }
}

impl PartialEq for RearmButton {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// Who re-arms the forces after the guard disabled them (devices.md S9).
#[derive(Debug, Clone, PartialEq)]
pub enum RearmMode {
    /// Re-arm as soon as the link has been healthy for 500 ms (the operator consented up front
    /// with `--rearm auto`).
    Auto,
    /// Re-arm when the operator presses the button after the link has been healthy for 500 ms.
    Operator(RearmButton),
}

/// Injected network faults (tests and demos only; never in a lab session).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaultInjection {
    /// Fraction of messages dropped, each way (0..=1).
    pub drop_fraction: f64,
    /// Smallest added delay of a force command, us.
    pub delay_min_us: u64,
    /// Largest added delay of a force command, us (uniformly drawn; commands stay in order).
    pub delay_max_us: u64,
    /// Seed of the generator (the same seed drops the same messages).
    pub seed: u64,
}

/// Checked run-time configuration of the bridge.
#[derive(Debug, Clone, PartialEq)]
pub struct BridgeConfig {
    /// Server URL, `http://host:port` (or `https://` with a CA in `credentials`).
    pub server_url: String,
    /// Token and TLS files (a `device` token is enough; [`haptic_cli::credentials`]).
    pub credentials: haptic_cli::credentials::ClientCredentials,
    /// Session id sent on the first sample of every stream.
    pub session_id: String,
    /// Device loop rate, in Hz.
    pub rate_hz: f64,
    /// Guard limits.
    pub guard: GuardParams,
    /// First reconnect delay (doubles after each failure).
    pub backoff_initial: Duration,
    /// Largest reconnect delay.
    pub backoff_max: Duration,
    /// TCP connect timeout per attempt.
    pub connect_timeout: Duration,
    /// Hard stop after this long, if set.
    pub max_duration: Option<Duration>,
    /// Keep one [`TickRecord`] per device tick.
    pub record: bool,
    /// Capacity of the device -> network sample queue (and of the outbound stream queue).
    pub sample_queue: usize,
    /// Who re-arms after the guard disabled the forces.
    pub rearm: RearmMode,
    /// Injected network faults (`None` in normal use).
    pub fault: Option<FaultInjection>,
    /// Pose deadband (fraction of the predicted force, e.g. 0.07; `None`: every sample is sent).
    pub deadband: Option<f64>,
    /// What the first sample of every stream tells the daemon about the device
    /// ([`capabilities_of`] its spec; `None`: nothing, as bridges before issue 50 did).
    pub capabilities: Option<DeviceCapabilities>,
}

impl BridgeConfig {
    /// Defaults for `spec`: its rate and guard limits, 50 ms -> 1 s backoff, 500 ms connect
    /// timeout, no hard stop, no recording, 256-sample queues, automatic re-arm, no fault
    /// injection, no deadband.
    pub fn new(
        server_url: impl Into<String>,
        session_id: impl Into<String>,
        spec: &DeviceSpec,
    ) -> Self {
        Self {
            server_url: server_url.into(),
            credentials: Default::default(),
            session_id: session_id.into(),
            rate_hz: spec.rate_hz,
            guard: GuardParams::from_spec(spec),
            backoff_initial: Duration::from_millis(50),
            backoff_max: Duration::from_secs(1),
            connect_timeout: Duration::from_millis(500),
            max_duration: None,
            record: false,
            sample_queue: 256,
            rearm: RearmMode::Auto,
            fault: None,
            deadband: None,
            capabilities: Some(capabilities_of(spec)),
        }
    }

    /// Checks the fields.
    ///
    /// # Errors
    /// [`BridgeError::Config`] naming the field.
    pub fn validate(&self) -> Result<(), BridgeError> {
        let bad = |m: String| Err(BridgeError::Config(m));
        if !(self.server_url.starts_with("http://") || self.server_url.starts_with("https://")) {
            return bad(format!(
                "server URL must start with http:// or https://, got `{}`",
                self.server_url
            ));
        }
        if self.session_id.is_empty() {
            return bad("session id must not be empty".to_owned());
        }
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 100_000.0) {
            return bad(format!(
                "rate_hz must be in (0, 100000], got {}",
                self.rate_hz
            ));
        }
        let g = &self.guard;
        if !(g.max_force_n.is_finite() && g.max_force_n >= 0.0) {
            return bad(format!(
                "max_force_n must be finite and >= 0, got {}",
                g.max_force_n
            ));
        }
        if g.max_rate_n_per_s.is_nan() || g.max_rate_n_per_s <= 0.0 {
            return bad(format!(
                "max_rate_n_per_s must be > 0, got {}",
                g.max_rate_n_per_s
            ));
        }
        if g.zero_us <= g.fresh_us {
            return bad(format!(
                "watchdog: zero_us ({}) must exceed fresh_us ({})",
                g.zero_us, g.fresh_us
            ));
        }
        if self.backoff_initial.is_zero() || self.backoff_max < self.backoff_initial {
            return bad("backoff: need 0 < initial <= max".to_owned());
        }
        if self.sample_queue == 0 {
            return bad("sample_queue must be >= 1".to_owned());
        }
        if !(g.fresh_us < g.zero_us && g.zero_us < g.latch_us) {
            return bad(format!(
                "watchdog: need fresh_us < zero_us < latch_us, got {} / {} / {}",
                g.fresh_us, g.zero_us, g.latch_us
            ));
        }
        if let Some(f) = &self.fault
            && !((0.0..=1.0).contains(&f.drop_fraction) && f.delay_min_us <= f.delay_max_us)
        {
            return bad(format!(
                "fault injection: need 0 <= drop <= 1 and min <= max delay, got {f:?}"
            ));
        }
        if let Some(k) = self.deadband
            && !(k.is_finite() && k > 0.0 && k < 1.0)
        {
            return bad(format!("deadband must be in (0, 1), got {k}"));
        }
        Ok(())
    }
}

/// What can stop the bridge from running at all (link trouble is not an error: it is retried and
/// reported in [`BridgeSummary`]).
#[derive(Debug, Error)]
pub enum BridgeError {
    /// A configuration field is out of range.
    #[error("invalid bridge configuration: {0}")]
    Config(String),
    /// The server URL does not parse.
    #[error("invalid server URL `{url}`: {message}")]
    InvalidUrl {
        /// The URL as given.
        url: String,
        /// Why it was rejected.
        message: String,
    },
    /// The device or its spec is unusable.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The device thread could not start or panicked.
    #[error("device thread: {0}")]
    Thread(String),
}

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

/// The result of [`run`]: the summary and, when recording, one row per device tick.
#[derive(Debug, Clone, Default)]
pub struct BridgeReport {
    /// Totals of the run.
    pub summary: BridgeSummary,
    /// Per-tick rows (empty unless [`BridgeConfig::record`]).
    pub ticks: Vec<TickRecord>,
}

/// The latest force command, as handed from the network task to the device thread.
#[derive(Debug, Clone, Copy)]
struct ReceivedForce {
    generation: u64,
    seq: u64,
    force_n: [f64; 3],
    stiffness_n_per_m: [f64; 9],
    in_contact: bool,
    /// Read time and position of the pose this answers (from the sent ring).
    sample_time_us: u64,
    sample_position_m: [f64; 3],
    rtt_us: Option<u64>,
}

/// The latest-value slot between the network task (writer) and the device thread (reader).
#[derive(Debug, Default)]
struct ForceSlot {
    /// A stream is open (health needs it; the guard ages the held command either way).
    link_up: bool,
    latest: Option<ReceivedForce>,
    /// The scene's limits sent by the server at connect time.
    limits: Option<Limits>,
}

#[derive(Debug, Default)]
struct Shared {
    slot: Mutex<ForceSlot>,
    /// Set by the network side to stop the device thread (shutdown).
    stop: AtomicBool,
    /// The guard's state code ([`GuardState::code`]), for the log monitor.
    guard_state: AtomicU8,
}

impl Shared {
    fn slot(&self) -> std::sync::MutexGuard<'_, ForceSlot> {
        // A panic elsewhere must not stop the device loop from commanding zero.
        self.slot.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn set_link(&self, up: bool, limits: Option<Limits>) {
        let mut s = self.slot();
        s.link_up = up;
        if up {
            s.limits = limits;
        }
    }
}

/// One device sample on its way to the network task.
#[derive(Debug, Clone, Copy)]
struct OutSample {
    seq: u64,
    state: DeviceState,
}

#[derive(Debug, Default)]
struct DeviceLoopStats {
    ticks: u64,
    overruns: u64,
    samples_dropped: u64,
    samples_suppressed: u64,
    peak_force_n: f64,
    max_depth_m: f64,
    final_force_n: [f64; 3],
    guard: GuardStats,
    limits: Option<Limits>,
    device_errors: u64,
    device_fault: Option<String>,
    duration_s: f64,
    records: Vec<TickRecord>,
}

/// The pose deadband (Hinterseer and Steinbach's perceptual deadband, devices.md \[S38\], applied
/// to the force the local contact model predicts): a sample goes out when the predicted force
/// changed by more than `k` times its value at the last sent sample (and by more than
/// [`DEADBAND_FLOOR_N`]), when the probe moved more than [`DEADBAND_MOVE_M`] (so contact onset
/// is seen), or at the latest [`DEADBAND_HEARTBEAT_US`] after the last one (so the command ages
/// stay below the 10 ms watchdog and silence still means a fault).
#[derive(Debug, Clone, Copy)]
struct Deadband {
    k: f64,
    last_sent_us: Option<u64>,
    sent_position_m: [f64; 3],
    sent_force_n: [f64; 3],
}

/// Smallest force change that triggers a sample under the deadband, N.
pub const DEADBAND_FLOOR_N: f64 = 1e-3;
/// Movement that triggers a sample under the deadband, m.
pub const DEADBAND_MOVE_M: f64 = 2e-4;
/// Longest gap between two samples under the deadband, us.
pub const DEADBAND_HEARTBEAT_US: u64 = 5_000;

impl Deadband {
    fn should_send(&self, now_us: u64, position_m: [f64; 3], predicted_n: [f64; 3]) -> bool {
        let Some(last) = self.last_sent_us else {
            return true;
        };
        let df = vec3::norm(vec3::sub(predicted_n, self.sent_force_n));
        now_us.saturating_sub(last) >= DEADBAND_HEARTBEAT_US
            || vec3::norm(vec3::sub(position_m, self.sent_position_m)) > DEADBAND_MOVE_M
            || (df > self.k * vec3::norm(self.sent_force_n) && df > DEADBAND_FLOOR_N)
    }
}

/// The device thread: one tick per period at absolute deadlines until the device finishes, the
/// hard stop passes, or `shared.stop` is set. Writes zero and calls `safe_stop` on the way out.
/// Nothing in the tick allocates (except growing a full recording buffer), logs or awaits.
fn device_loop(
    mut device: Box<dyn HapticDevice>,
    clock: Arc<dyn Clock>,
    shared: Arc<Shared>,
    samples: mpsc::Sender<OutSample>,
    config: &BridgeConfig,
) -> DeviceLoopStats {
    let spec = device.spec().clone();
    let period_us = ((1e6 / config.rate_hz).round() as u64).max(1);
    let mut guard = ForceGuard::new(config.guard);
    let axis = device.press_axis();
    let mut st = DeviceLoopStats::default();
    if config.record {
        st.records
            .reserve((RECORD_RESERVE_S * config.rate_hz) as usize);
    }
    let start_us = clock.now_us();
    let stop_at_us = config
        .max_duration
        .map(|d| start_us.saturating_add(u64::try_from(d.as_micros()).unwrap_or(u64::MAX)));
    let mut deadline_us = start_us;
    let mut seq = 0_u64;
    let mut failing_since_us: Option<u64> = None;
    let mut presses_seen = match &config.rearm {
        RearmMode::Operator(b) => b.presses(),
        RearmMode::Auto => 0,
    };
    let mut output_disabled = false;
    let mut deadband = config.deadband.map(|k| Deadband {
        k,
        last_sent_us: None,
        sent_position_m: [0.0; 3],
        sent_force_n: [0.0; 3],
    });
    loop {
        let now = clock.now_us();
        if shared.stop.load(Ordering::Acquire)
            || device.finished(now)
            || stop_at_us.is_some_and(|t| now >= t)
        {
            break;
        }
        st.ticks += 1;
        match device.read(now) {
            Ok(state) => {
                failing_since_us = None;
                let (link_up, latest, limits) = {
                    let s = shared.slot();
                    (s.link_up, s.latest, s.limits)
                };
                let predicted = latest.map_or([0.0; 3], |r| {
                    crate::guard::extrapolate(
                        r.force_n,
                        &r.stiffness_n_per_m,
                        r.sample_position_m,
                        state.position_m,
                        config.guard.max_extrapolation_m,
                    )
                });
                let send = deadband
                    .as_ref()
                    .is_none_or(|d| d.should_send(now, state.position_m, predicted));
                if send {
                    seq += 1;
                    if let Some(d) = deadband.as_mut() {
                        d.last_sent_us = Some(now);
                        d.sent_position_m = state.position_m;
                        d.sent_force_n = predicted;
                    }
                    if let Err(mpsc::error::TrySendError::Full(_)) =
                        samples.try_send(OutSample { seq, state })
                    {
                        st.samples_dropped += 1;
                    }
                } else {
                    st.samples_suppressed += 1;
                }
                guard.set_app_limits(limits);
                match &config.rearm {
                    RearmMode::Auto => {
                        if guard.state() == GuardState::ReadyToRearm {
                            guard.request_rearm();
                        }
                    }
                    RearmMode::Operator(b) => {
                        let p = b.presses();
                        if p != presses_seen {
                            presses_seen = p;
                            guard.request_rearm();
                        }
                    }
                }
                let cmd = latest.map(|r| GuardCommand {
                    generation: r.generation,
                    seq: r.seq,
                    force_n: r.force_n,
                    stiffness_n_per_m: r.stiffness_n_per_m,
                    position_m: r.sample_position_m,
                    sample_time_us: r.sample_time_us,
                });
                let f = guard.filter(now, link_up, cmd.as_ref(), &state, &spec);
                let disabled = guard.state().is_disabled();
                if disabled != output_disabled {
                    // devices.md S5: disabled in hardware too, while latched.
                    output_disabled = disabled;
                    if device.set_output_enabled(!disabled).is_err() {
                        st.device_errors += 1;
                    }
                }
                shared
                    .guard_state
                    .store(guard.state().code(), Ordering::Release);
                if device.write_force(f).is_err() {
                    st.device_errors += 1;
                }
                st.final_force_n = f;
                st.peak_force_n = st.peak_force_n.max(vec3::norm(f));
                if let Some(a) = axis {
                    let d = vec3::dot(vec3::sub(state.position_m, a.start_m), a.direction);
                    st.max_depth_m = st.max_depth_m.max(d);
                }
                if config.record {
                    let in_use = matches!(
                        guard.state(),
                        GuardState::Fresh | GuardState::Rising | GuardState::Ramp
                    );
                    let used = latest.filter(|_| in_use);
                    st.records.push(TickRecord {
                        t_s: now.saturating_sub(start_us) as f64 * 1e-6,
                        position_m: state.position_m,
                        force_n: f,
                        in_contact: used.is_some_and(|r| r.in_contact),
                        rtt_us: used.and_then(|r| r.rtt_us),
                        age_us: guard.held_age_us(),
                        state: guard.state().name(),
                        command_n: guard.command_n(),
                    });
                }
            }
            Err(e) => {
                // devices.md S2: never trust a stale pose; zero now, give up after 20 ms.
                st.device_errors += 1;
                guard.reset();
                let _ = device.write_force([0.0; 3]);
                st.final_force_n = [0.0; 3];
                let since = *failing_since_us.get_or_insert(now);
                if now.saturating_sub(since) >= DEVICE_FAULT_US {
                    st.device_fault = Some(e.to_string());
                    break;
                }
            }
        }
        deadline_us += period_us;
        let after = clock.now_us();
        if after > deadline_us {
            // Overrun: skip the missed deadlines instead of bursting to catch up.
            st.overruns += 1;
            deadline_us += ((after - deadline_us) / period_us + 1) * period_us;
        }
        clock.sleep_until_us(deadline_us);
    }
    if device.write_force([0.0; 3]).is_err() {
        st.device_errors += 1;
    }
    device.safe_stop();
    st.final_force_n = [0.0; 3];
    st.guard = guard.stats();
    st.limits = Some(guard.limits());
    st.duration_s = clock.now_us().saturating_sub(start_us) as f64 * 1e-6;
    st
}

/// A small xorshift generator for fault injection (deterministic per seed, no dependency).
#[derive(Debug, Clone, Copy)]
struct XorShift(u64);

impl XorShift {
    fn next_f64(&mut self) -> f64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        (x >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Network-side state and counters.
struct NetCtx {
    clock: Arc<dyn Clock>,
    /// Puts the bridge's token on the device stream.
    token: haptic_cli::credentials::BearerToken,
    shared: Arc<Shared>,
    /// `seq -> (read time us, position m)` of recently sent samples, indexed by
    /// `seq % RTT_RING`.
    sent: Vec<(u64, u64, [f64; 3])>,
    rtt_us: Histogram<u64>,
    generation: u64,
    last_accepted_seq: Option<u64>,
    samples_sent: u64,
    samples_dropped: u64,
    forces_received: u64,
    unmatched_forces: u64,
    stale_forces: u64,
    contact_samples: u64,
    streams_opened: u64,
    reconnects: u64,
    link_failures: u64,
    attempts: u64,
    last_link_error: Option<String>,
    server_instance: Option<String>,
    server_restarts: u64,
    session_lost: Option<String>,
    access_refused: Option<String>,
    fault: Option<FaultInjection>,
    rng: XorShift,
    injected_drops: u64,
    /// Force commands held back by injected delay: (release time us, command).
    delayed: VecDeque<(u64, ForceCommand)>,
}

/// The capabilities message of a device spec (scene frame when the spec is a
/// [`crate::transform::Transformed`] device's): name, degrees of freedom, workspace box, peak and
/// continuous force, stiffness limit and rate.
pub fn capabilities_of(spec: &DeviceSpec) -> DeviceCapabilities {
    DeviceCapabilities {
        name: spec.name.clone(),
        sensed_degrees_of_freedom: spec.sensed_degrees_of_freedom,
        actuated_degrees_of_freedom: spec.actuated_degrees_of_freedom,
        workspace_min_m: Some(spec.workspace_min_m.into()),
        workspace_max_m: Some(spec.workspace_max_m.into()),
        max_force_n: spec.max_force_n,
        max_continuous_force_n: spec.max_continuous_force_n,
        max_stiffness_n_per_m: spec.max_stiffness_n_per_m,
        native_rate_hz: spec.rate_hz,
    }
}

fn to_proto(s: &OutSample) -> DeviceSample {
    DeviceSample {
        session_id: String::new(),
        seq: s.seq,
        device_time_us: s.state.time_us,
        position_m: Some(s.state.position_m.into()),
        velocity_m_per_s: Some(s.state.velocity_m_per_s.into()),
        capabilities: None,
    }
}

impl NetCtx {
    fn injected_drop(&mut self) -> bool {
        let Some(f) = self.fault else { return false };
        let drop = f.drop_fraction > 0.0 && self.rng.next_f64() < f.drop_fraction;
        self.injected_drops += u64::from(drop);
        drop
    }

    fn forward(&mut self, out: &mpsc::Sender<DeviceSample>, msg: DeviceSample) {
        let p = msg.position_m.as_ref().map_or([0.0; 3], |v| v.to_array());
        self.sent[(msg.seq % RTT_RING as u64) as usize] = (msg.seq, msg.device_time_us, p);
        if self.injected_drop() {
            return;
        }
        match out.try_send(msg) {
            Ok(()) => self.samples_sent += 1,
            Err(_) => self.samples_dropped += 1,
        }
    }

    /// A command from the stream: through fault injection, then [`NetCtx::on_force`].
    fn receive(&mut self, cmd: ForceCommand) {
        if self.injected_drop() {
            return;
        }
        match self.fault {
            Some(f) if f.delay_max_us > 0 => {
                let span = (f.delay_max_us - f.delay_min_us) as f64;
                let delay = f.delay_min_us + (self.rng.next_f64() * span) as u64;
                let now = self.clock.now_us();
                let after_previous = self.delayed.back().map_or(0, |(t, _)| *t);
                self.delayed
                    .push_back(((now + delay).max(after_previous), cmd));
            }
            _ => self.on_force(&cmd),
        }
    }

    /// Delivers the delayed commands that are due.
    fn release_delayed(&mut self) {
        let now = self.clock.now_us();
        while self.delayed.front().is_some_and(|(t, _)| *t <= now) {
            if let Some((_, cmd)) = self.delayed.pop_front() {
                self.on_force(&cmd);
            }
        }
    }

    fn next_release(&self) -> Option<Duration> {
        let (t, _) = self.delayed.front()?;
        Some(Duration::from_micros(t.saturating_sub(self.clock.now_us())))
    }

    fn on_force(&mut self, cmd: &ForceCommand) {
        let now = self.clock.now_us();
        self.forces_received += 1;
        let (seq, sample_time_us, sample_position_m) =
            self.sent[(cmd.seq % RTT_RING as u64) as usize];
        if seq != cmd.seq {
            self.unmatched_forces += 1;
            return;
        }
        if self.last_accepted_seq.is_some_and(|s| cmd.seq <= s) {
            self.stale_forces += 1;
            return;
        }
        self.last_accepted_seq = Some(cmd.seq);
        let rtt = now.saturating_sub(sample_time_us);
        self.rtt_us.saturating_record(rtt.max(1));
        self.contact_samples += u64::from(cmd.in_contact);
        self.generation += 1;
        // proto3: an absent vector is the zero vector; a stiffness that is not 3x3 is unknown
        // (no extrapolation). Non-finite values pass on to the guard, which rejects and counts
        // them.
        let force_n = cmd.force_n.as_ref().map_or([0.0; 3], |v| v.to_array());
        let mut stiffness_n_per_m = [0.0; 9];
        if cmd.stiffness_n_per_m.len() == 9 {
            stiffness_n_per_m.copy_from_slice(&cmd.stiffness_n_per_m);
        }
        let mut s = self.shared.slot();
        s.latest = Some(ReceivedForce {
            generation: self.generation,
            seq: cmd.seq,
            force_n,
            stiffness_n_per_m,
            in_contact: cmd.in_contact,
            sample_time_us,
            sample_position_m,
            rtt_us: Some(rtt),
        });
    }
}

/// How one stream ended.
enum StreamEnd {
    /// The device finished (its sample queue closed).
    Finished,
    /// The shutdown signal fired.
    Shutdown,
    /// Connecting or streaming failed; retry.
    Failed(String),
    /// The server does not know the session (NOT_FOUND): retrying cannot help.
    SessionGone(String),
    /// The server refused the credentials (UNAUTHENTICATED, PERMISSION_DENIED): retrying
    /// cannot help either.
    Refused(String),
}

/// `error: cause: cause ...`, since tonic's transport errors hide the useful part in sources.
fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

/// Resolves once `true` is sent on `shutdown`; never if the sender is gone without sending it.
async fn wait_shutdown(shutdown: &mut watch::Receiver<bool>) {
    loop {
        if *shutdown.borrow_and_update() {
            return;
        }
        if shutdown.changed().await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

/// Sleeps for `d`, or forever when `None`.
async fn sleep_or_pending(d: Option<Duration>) {
    match d {
        Some(d) => tokio::time::sleep(d).await,
        None => std::future::pending::<()>().await,
    }
}

/// The scene's limits from the response headers (`None` when absent or malformed).
fn header_limits(md: &tonic::metadata::MetadataMap) -> Option<Limits> {
    let num = |k: &str| -> Option<f64> { md.get(k)?.to_str().ok()?.trim().parse().ok() };
    let l = Limits {
        max_force_n: num(HEADER_MAX_FORCE)?,
        max_rate_n_per_s: num(HEADER_MAX_FORCE_RATE)?,
    };
    l.is_valid().then_some(l)
}

async fn run_stream(
    endpoint: &Endpoint,
    config: &BridgeConfig,
    first: OutSample,
    samples: &mut mpsc::Receiver<OutSample>,
    shutdown: &mut watch::Receiver<bool>,
    ctx: &mut NetCtx,
) -> StreamEnd {
    ctx.attempts += 1;
    let channel = tokio::select! {
        biased;
        _ = wait_shutdown(shutdown) => return StreamEnd::Shutdown,
        c = endpoint.connect() => match c {
            Ok(c) => c,
            Err(e) => {
                return StreamEnd::Failed(format!("connect to {}: {}", config.server_url, chain(&e)));
            }
        },
    };
    let mut client = DeviceLinkClient::with_interceptor(channel, ctx.token.clone());
    let (out_tx, out_rx) = mpsc::channel::<DeviceSample>(config.sample_queue);
    let mut first_msg = to_proto(&first);
    first_msg.session_id.clone_from(&config.session_id);
    first_msg.capabilities.clone_from(&config.capabilities);
    // The first sample carries the session id: never drop it by injection.
    let fault = ctx.fault.take();
    ctx.forward(&out_tx, first_msg);
    ctx.fault = fault;
    let mut request = tonic::Request::new(ReceiverStream::new(out_rx));
    if let Some(k) = config.deadband
        && let Ok(v) = k.to_string().parse()
    {
        // The same deadband on the force stream, applied by the server.
        request.metadata_mut().insert(HEADER_FORCE_DEADBAND, v);
    }
    let call = client.connect(request);
    tokio::pin!(call);
    // Keep feeding samples while waiting for response headers: a server may wait for the first
    // message (it carries the session id) before answering.
    let response = loop {
        tokio::select! {
            biased;
            _ = wait_shutdown(shutdown) => return StreamEnd::Shutdown,
            r = &mut call => match r {
                Ok(resp) => break resp,
                Err(status) if status.code() == tonic::Code::NotFound => {
                    return StreamEnd::SessionGone(status.message().to_owned());
                }
                Err(status) if matches!(
                    status.code(),
                    tonic::Code::Unauthenticated | tonic::Code::PermissionDenied
                ) => {
                    return StreamEnd::Refused(format!("{:?}: {}", status.code(), status.message()));
                }
                Err(status) => return StreamEnd::Failed(format!("Connect rejected: {status}")),
            },
            s = samples.recv() => match s {
                Some(s) => ctx.forward(&out_tx, to_proto(&s)),
                None => return StreamEnd::Finished,
            },
        }
    };
    let limits = header_limits(response.metadata());
    let instance = response
        .metadata()
        .get(HEADER_SERVER_INSTANCE)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned);
    let mut inbound = response.into_inner();
    ctx.streams_opened += 1;
    if ctx.attempts > 1 {
        ctx.reconnects += 1;
    }
    if let (Some(old), Some(new)) = (&ctx.server_instance, &instance)
        && old != new
    {
        ctx.server_restarts += 1;
        warn!(
            session = %config.session_id,
            "hapticd restarted (instance {old} -> {new}) and restored session {}: re-attached; \
             forces stay off until the link is healthy and they are re-armed",
            config.session_id
        );
    }
    if instance.is_some() {
        ctx.server_instance = instance;
    }
    ctx.shared.set_link(true, limits);
    match limits {
        Some(l) => info!(
            url = %config.server_url, session = %config.session_id,
            scene_max_force_n = l.max_force_n, scene_max_rate_n_per_s = l.max_rate_n_per_s,
            "DeviceLink stream open"
        ),
        None => info!(url = %config.server_url, session = %config.session_id,
            "DeviceLink stream open (the server sent no scene limits: device limits only)"),
    }
    let end = loop {
        // Deliver what is due first: a timer is only checked when the runtime turns, and a
        // stream of samples every millisecond would keep a zero-length sleep from firing.
        ctx.release_delayed();
        let release = ctx.next_release();
        tokio::select! {
            biased;
            _ = wait_shutdown(shutdown) => break StreamEnd::Shutdown,
            _ = sleep_or_pending(release) => ctx.release_delayed(),
            m = inbound.message() => match m {
                Ok(Some(cmd)) => ctx.receive(cmd),
                Ok(None) => break StreamEnd::Failed("server closed the stream".to_owned()),
                Err(status) => break StreamEnd::Failed(format!("stream error: {status}")),
            },
            s = samples.recv() => match s {
                Some(s) => ctx.forward(&out_tx, to_proto(&s)),
                None => break StreamEnd::Finished,
            },
        }
    };
    ctx.shared.set_link(false, None);
    ctx.delayed.clear();
    if matches!(end, StreamEnd::Finished | StreamEnd::Shutdown) {
        // Close our half and collect the answers still in flight, briefly.
        drop(out_tx);
        let _ = tokio::time::timeout(CLOSE_GRACE, async {
            while let Ok(Some(cmd)) = inbound.message().await {
                ctx.on_force(&cmd);
            }
        })
        .await;
    }
    end
}

/// Logs the guard's transitions (the device thread cannot: it must not allocate or block).
async fn monitor(shared: Arc<Shared>, rearm: RearmMode) {
    let mut last = GuardState::NoCommand;
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    while !shared.stop.load(Ordering::Acquire) {
        tick.tick().await;
        let now = GuardState::from_code(shared.guard_state.load(Ordering::Acquire));
        if now == last {
            continue;
        }
        match now {
            GuardState::Disabled if !last.is_disabled() => warn!(
                "forces DISABLED: no fresh force command for 100 ms; they stay off until the \
                 link has been healthy for 0.5 s and they are re-armed"
            ),
            GuardState::ReadyToRearm => match rearm {
                RearmMode::Operator(_) => warn!(
                    "link healthy for 0.5 s: press Enter to re-arm the forces (they ramp up over 0.2 s)"
                ),
                RearmMode::Auto => info!("link healthy for 0.5 s: re-arming (--rearm auto)"),
            },
            GuardState::Rising if last.is_disabled() => {
                info!("forces re-armed: ramping up over 0.2 s")
            }
            GuardState::Ramp => debug!("force commands older than 10 ms: ramping down"),
            _ => {}
        }
        last = now;
    }
}

async fn network_loop(
    endpoint: Endpoint,
    config: &BridgeConfig,
    mut samples: mpsc::Receiver<OutSample>,
    mut shutdown: watch::Receiver<bool>,
    ctx: &mut NetCtx,
) {
    let mut backoff = config.backoff_initial;
    loop {
        // Every stream starts with a fresh sample, which carries the session id.
        let first = tokio::select! {
            biased;
            _ = wait_shutdown(&mut shutdown) => return,
            s = samples.recv() => match s {
                Some(s) => s,
                None => return,
            },
        };
        let opened_before = ctx.streams_opened;
        match run_stream(&endpoint, config, first, &mut samples, &mut shutdown, ctx).await {
            StreamEnd::Finished | StreamEnd::Shutdown => return,
            StreamEnd::SessionGone(msg) => {
                let why = if ctx.streams_opened > 0 {
                    format!(
                        "hapticd at {} no longer has session {} ({msg}): it restarted without \
                         restoring it (run hapticd with --state-dir to restore sessions); giving up",
                        config.server_url, config.session_id
                    )
                } else {
                    format!(
                        "hapticd at {} has no session {} ({msg}): check --session",
                        config.server_url, config.session_id
                    )
                };
                warn!("{why}");
                ctx.session_lost = Some(why);
                return;
            }
            StreamEnd::Refused(msg) => {
                let why = format!(
                    "hapticd at {} refused the device link ({msg}): give a `device` (or \
                     `admin`) token with --token-file or HAPTICD_TOKEN_FILE (docs/security.md); \
                     not retrying",
                    config.server_url
                );
                warn!("{why}");
                ctx.last_link_error = Some(msg);
                ctx.access_refused = Some(why);
                return;
            }
            StreamEnd::Failed(msg) => {
                ctx.link_failures += 1;
                if ctx.streams_opened > opened_before {
                    backoff = config.backoff_initial;
                }
                warn!(error = %msg, retry_in_ms = backoff.as_millis() as u64, "DeviceLink down; zero force");
                ctx.last_link_error = Some(msg);
            }
        }
        // Back off, discarding samples (force is zero meanwhile) but noticing the end.
        let sleep = tokio::time::sleep(backoff);
        tokio::pin!(sleep);
        loop {
            tokio::select! {
                biased;
                _ = wait_shutdown(&mut shutdown) => return,
                _ = &mut sleep => break,
                s = samples.recv() => if s.is_none() { return },
            }
        }
        backoff = (backoff * 2).min(config.backoff_max);
    }
}

/// Runs the bridge until the device finishes, `config.max_duration` passes, or `true` is sent
/// on `shutdown`: streams the device's samples to `DeviceLink.Connect` at `config.server_url`,
/// renders the guarded forces it answers, reconnects with backoff when the link fails, and ends
/// with zero force and `safe_stop`.
///
/// `clock` times the device loop, the guard and the round trips; pass a
/// [`crate::clock::MonotonicClock`] for real runs. Never connecting is not an error: check
/// [`BridgeSummary::connected`].
///
/// # Errors
/// [`BridgeError::Config`] / [`BridgeError::InvalidUrl`] / [`BridgeError::Device`] before
/// anything starts; [`BridgeError::Thread`] if the device thread cannot start or panics.
pub async fn run(
    device: Box<dyn HapticDevice>,
    clock: Arc<dyn Clock>,
    config: BridgeConfig,
    shutdown: watch::Receiver<bool>,
) -> Result<BridgeReport, BridgeError> {
    config.validate()?;
    device.spec().validate()?;
    let token = config
        .credentials
        .interceptor()
        .map_err(|e| BridgeError::Config(e.to_string()))?;
    let endpoint = config
        .credentials
        .endpoint(&config.server_url)
        .map_err(|e| BridgeError::InvalidUrl {
            url: config.server_url.clone(),
            message: e.to_string(),
        })?
        .tcp_nodelay(true)
        .connect_timeout(config.connect_timeout);
    let config = Arc::new(config);
    let shared = Arc::new(Shared::default());
    let (sample_tx, sample_rx) = mpsc::channel(config.sample_queue);
    let handle = {
        let (clock, shared, config) = (clock.clone(), shared.clone(), config.clone());
        std::thread::Builder::new()
            .name("bridge-device".to_owned())
            .spawn(move || device_loop(device, clock, shared, sample_tx, &config))
            .map_err(|e| BridgeError::Thread(format!("cannot start: {e}")))?
    };
    let monitor_task = tokio::spawn(monitor(shared.clone(), config.rearm.clone()));
    let mut ctx = NetCtx {
        clock,
        shared: shared.clone(),
        sent: vec![(u64::MAX, 0, [0.0; 3]); RTT_RING],
        rtt_us: Histogram::new_with_bounds(1, 60_000_000, 3)
            .map_err(|e| BridgeError::Config(format!("histogram: {e}")))?,
        generation: 0,
        samples_sent: 0,
        samples_dropped: 0,
        forces_received: 0,
        unmatched_forces: 0,
        contact_samples: 0,
        streams_opened: 0,
        reconnects: 0,
        link_failures: 0,
        attempts: 0,
        last_link_error: None,
        last_accepted_seq: None,
        stale_forces: 0,
        server_instance: None,
        server_restarts: 0,
        session_lost: None,
        access_refused: None,
        fault: config.fault,
        token,
        rng: XorShift(config.fault.map_or(1, |f| f.seed.max(1))),
        injected_drops: 0,
        delayed: VecDeque::new(),
    };
    network_loop(endpoint, &config, sample_rx, shutdown, &mut ctx).await;
    shared.stop.store(true, Ordering::Release);
    shared.set_link(false, None);
    let _ = monitor_task.await;
    let dev = tokio::task::spawn_blocking(move || handle.join())
        .await
        .map_err(|e| BridgeError::Thread(e.to_string()))?
        .map_err(|_| BridgeError::Thread("device thread panicked".to_owned()))?;
    let h = &ctx.rtt_us;
    let rtt = |q: f64| (!h.is_empty()).then(|| h.value_at_quantile(q));
    let summary = BridgeSummary {
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
    };
    info!(
        ticks = summary.ticks,
        forces = summary.forces_received,
        "bridge finished"
    );
    Ok(BridgeReport {
        summary,
        ticks: dev.records,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sent_at(us: u64, position_m: [f64; 3], force_n: [f64; 3], k: f64) -> Deadband {
        Deadband {
            k,
            last_sent_us: Some(us),
            sent_position_m: position_m,
            sent_force_n: force_n,
        }
    }

    #[test]
    fn the_pose_deadband_sends_at_its_exact_thresholds() {
        let zero = [0.0; 3];
        // Nothing sent yet: send.
        let first = Deadband {
            last_sent_us: None,
            ..sent_at(0, zero, zero, 0.1)
        };
        assert!(first.should_send(0, zero, zero));
        // Heartbeat: 5 ms after the last sample, however still.
        let d = sent_at(1_000, zero, [0.05, 0.0, 0.0], 0.1);
        assert!(!d.should_send(1_000 + DEADBAND_HEARTBEAT_US - 1, zero, [0.05, 0.0, 0.0]));
        assert!(d.should_send(1_000 + DEADBAND_HEARTBEAT_US, zero, [0.05, 0.0, 0.0]));
        // Movement: more than 0.2 mm from the last sent position (exactly 0.2 mm is not).
        let still_force = [0.05, 0.0, 0.0];
        assert!(!d.should_send(2_000, [0.0, DEADBAND_MOVE_M, 0.0], still_force));
        assert!(d.should_send(2_000, [0.0, DEADBAND_MOVE_M * 1.01, 0.0], still_force));
        // Force: a change above k = 10 % of the sent 0.05 N (5 mN), in any direction.
        assert!(!d.should_send(2_000, zero, [0.0549, 0.0, 0.0]));
        assert!(d.should_send(2_000, zero, [0.0551, 0.0, 0.0]));
        assert!(d.should_send(2_000, zero, [0.0449, 0.0, 0.0]));
        assert!(d.should_send(2_000, zero, [0.05, 0.0051, 0.0]));
        // The 1 mN floor: 10 % of 1 mN would be 0.1 mN, the floor wins.
        let small = sent_at(1_000, zero, [0.001, 0.0, 0.0], 0.1);
        assert!(!small.should_send(2_000, zero, [0.0019, 0.0, 0.0]));
        assert!(small.should_send(2_000, zero, [0.00205, 0.0, 0.0]));
        // Contact onset from zero force: any change above the floor.
        let free = sent_at(1_000, zero, zero, 0.1);
        assert!(!free.should_send(2_000, zero, [0.0009, 0.0, 0.0]));
        assert!(free.should_send(2_000, zero, [0.0011, 0.0, 0.0]));
    }
}
