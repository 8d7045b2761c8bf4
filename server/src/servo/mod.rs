//! The servo loop: one OS thread per session running the model at the servo rate (1 kHz).
//!
//! A tick has a fixed shape (STYLE.md habit 6): wait for the absolute deadline, drain commands
//! (SPSC ring, wait-free), read the latest device pose (triple buffer, wait-free), step the
//! model, guard the force, push it to the force ring and wake the forwarder, publish a surface
//! snapshot every k-th tick while someone watches, publish statistics every m-th tick, record
//! timing in preallocated histograms. Nothing in [`ServoCore::tick`] allocates, locks, blocks or
//! logs; `tests/servo_no_alloc.rs` proves it with a counting allocator.
//!
//! Late ticks are counted as overruns and the schedule is re-based on the current time: the loop
//! never "catches up" with a burst of back-to-back ticks ([`Pacer`]).
//!
//! Neighbours: [`crate::session`] creates the rings/buffers and threads; the gRPC services in
//! [`crate::service`] sit on the other side of every handoff.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Instant;

use haptic_model::body::{BodyStats, SoftBody, TickInput};
use haptic_model::{DVec3, ModelError};
use hdrhistogram::Histogram;

/// A command from the gRPC side to the servo thread.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Command {
    /// Apply a validated point load.
    ApplyForce {
        /// Surface point, m.
        point_m: DVec3,
        /// Force, N.
        force_n: DVec3,
        /// Duration, s.
        duration_s: f64,
    },
}

/// The latest device pose, written by the DeviceLink stream task, read by the servo.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pose {
    /// Sequence number of the DeviceSample.
    pub seq: u64,
    /// Haptic interaction point, m.
    pub position_m: DVec3,
    /// Device velocity, m/s.
    pub velocity_m_per_s: DVec3,
    /// When the stream task received it, µs on the session clock.
    pub received_us: u64,
    /// False once the device disconnected (the probe leaves the scene).
    pub connected: bool,
}

/// A force for the device, from the servo to the forwarder thread.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ForceOut {
    /// Seq of the pose this answers.
    pub seq: u64,
    /// Force to render, N.
    pub force_n: DVec3,
    /// Probe in contact.
    pub in_contact: bool,
    /// Contact stiffness, 3x3 row-major, N/m.
    pub stiffness_n_per_m: [f64; 9],
    /// Proxy position, m.
    pub proxy_m: DVec3,
}

/// A load injected by `ApplyForce` as the servo applied it, for viewers and recordings.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct AppliedLoad {
    /// 1-based count of the session's accepted loads: gaps show loads a snapshot missed.
    pub index: u64,
    /// Point the load was aimed at, m.
    pub point_m: DVec3,
    /// Total force, N.
    pub force_n: DVec3,
    /// Simulated time of the tick that applied it, s.
    pub start_sim_time_s: f64,
    /// How long it acts, simulated s.
    pub duration_s: f64,
}

/// Loads a snapshot can list: the most a body holds at once
/// ([`haptic_model::loads::MAX_POINT_LOADS`]).
pub const APPLIED_LOAD_CAPACITY: usize = haptic_model::loads::MAX_POINT_LOADS;

/// A surface snapshot for viewers (preallocated for the body's largest surface; overwritten in
/// place, so taking one never allocates).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Snapshot {
    /// Tick counter when taken.
    pub tick: u64,
    /// Simulated time, s.
    pub sim_time_s: f64,
    /// Surface topology version of `triangles` and `rest_positions_m`
    /// ([`haptic_model::body::SurfaceTopology::version`]); `u64::MAX` before the first snapshot.
    pub topology_version: u64,
    /// Surface triangles, three vertex indices each (rewritten only when the version changes).
    pub triangles: Vec<u32>,
    /// Rest positions of the surface vertices, xyz interleaved, m (rewritten with `triangles`).
    pub rest_positions_m: Vec<f32>,
    /// Surface vertex positions, xyz interleaved, m.
    pub positions_m: Vec<f32>,
    /// Device (probe) position, m; NaN when no device is connected.
    pub probe_m: DVec3,
    /// Contact force on the device, N.
    pub force_n: DVec3,
    /// In contact.
    pub in_contact: bool,
    /// Largest surface displacement from rest, m.
    pub max_displacement_m: f64,
    /// Injected loads acting now or ended since the previous snapshot (the first
    /// `applied_len`), so every accepted load appears in at least one snapshot.
    pub applied: [AppliedLoad; APPLIED_LOAD_CAPACITY],
    /// Entries of `applied` in use.
    pub applied_len: usize,
    /// Loads accepted by the session so far.
    pub applied_total: u64,
}

/// Upper bounds of the latency buckets, µs (the last bucket is everything above). Chosen around
/// the 1 ms tick: the step budget, the device period and the watchdog's 10 ms.
pub const LATENCY_BUCKET_BOUNDS_US: [u64; 11] = [
    50, 100, 200, 300, 500, 750, 1_000, 1_500, 2_000, 5_000, 10_000,
];

/// Counts of durations per [`LATENCY_BUCKET_BOUNDS_US`] bucket (not cumulative; the last slot
/// counts those above the largest bound) and their sum: a Prometheus histogram's data, kept by
/// the servo at the cost of a short scan per record, copied out with the statistics.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LatencyBuckets {
    /// Per-bucket counts; `counts[i]` for `bounds[i-1] < d <= bounds[i]`.
    pub counts: [u64; LATENCY_BUCKET_BOUNDS_US.len() + 1],
    /// Sum of all recorded durations, µs.
    pub sum_us: u64,
}

impl LatencyBuckets {
    /// Records one duration, µs. No allocation, no lock.
    pub fn record(&mut self, us: u64) {
        let i = LATENCY_BUCKET_BOUNDS_US
            .iter()
            .position(|&b| us <= b)
            .unwrap_or(LATENCY_BUCKET_BOUNDS_US.len());
        self.counts[i] += 1;
        self.sum_us = self.sum_us.saturating_add(us);
    }

    /// Number of recorded durations.
    pub fn count(&self) -> u64 {
        self.counts.iter().sum()
    }
}

/// Statistics published by the servo for `GetStats`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StatsSnapshot {
    /// Ticks run.
    pub steps: u64,
    /// Late ticks.
    pub overruns: u64,
    /// Ticks per second of wall time over the last publication window.
    pub loop_rate_hz: f64,
    /// Step compute time percentiles and maximum, µs.
    pub step_p50_us: f64,
    /// 99th percentile step time, µs.
    pub step_p99_us: f64,
    /// Largest step time, µs.
    pub step_max_us: f64,
    /// Pose received to force pushed, µs.
    pub pose_to_force_p50_us: f64,
    /// 99th percentile pose-to-force, µs.
    pub pose_to_force_p99_us: f64,
    /// Simulated time, s.
    pub sim_time_s: f64,
    /// In contact at the last tick.
    pub in_contact: bool,
    /// Ticks whose force was a contact's, so far.
    pub contact_ticks: u64,
    /// Largest device force magnitude so far, N.
    pub peak_force_n: f64,
    /// Largest nodal displacement from rest so far, m.
    pub max_displacement_m: f64,
    /// Device samples consumed.
    pub device_samples: u64,
    /// The fault that quarantined the session, if any.
    pub fault: Option<&'static str>,
    /// A connected device has sent nothing for longer than the silence limit: treated as gone
    /// (no probe in the scene, zero force) until its next sample.
    pub device_silent: bool,
    /// Times a connected device fell silent.
    pub device_silences: u64,
    /// The loop rate has stayed below the minimum (`servo.min_rate_fraction` of the nominal
    /// rate) for a second: the session cannot keep its rate on this machine.
    pub overrunning: bool,
    /// The servo thread yields to the sessions that keep up (`SCHED_IDLE`; [`Yielding`]).
    pub demoted: bool,
    /// The body's size and state at the last publication.
    pub body: BodyStats,
    /// Step compute times, all ticks so far (for the metrics endpoint).
    pub step_buckets: LatencyBuckets,
    /// Pose received to force pushed, all answered samples so far.
    pub pose_to_force_buckets: LatencyBuckets,
}

/// Atomics shared between the servo thread and the async side.
#[derive(Debug, Default)]
pub struct SessionShared {
    /// Set to stop the servo loop (it sends a zero force and exits).
    pub stop: AtomicBool,
    /// Number of viewers watching; snapshots are only taken while it is positive.
    pub watchers: AtomicUsize,
    /// Device samples rejected by the stream task (NaN, absurd values).
    pub rejected_samples: AtomicU64,
    /// Device samples dropped because their `seq` was not newer than the last one accepted.
    pub out_of_order_samples: AtomicU64,
    /// Device samples dropped because they lay outside the workspace the device declared.
    pub out_of_workspace_samples: AtomicU64,
    /// Set by the servo when it has sent its final zero force and exited.
    pub finished: AtomicBool,
}

/// A monotonic microsecond clock. Tests use a manual one.
pub trait Clock {
    /// Microseconds since the clock's epoch.
    fn now_us(&self) -> u64;
}

/// The real clock: microseconds since a session epoch.
#[derive(Debug, Clone, Copy)]
pub struct MonotonicClock {
    epoch: Instant,
}

impl MonotonicClock {
    /// A clock whose zero is `epoch`.
    pub fn new(epoch: Instant) -> Self {
        Self { epoch }
    }

    /// The epoch.
    pub fn epoch(&self) -> Instant {
        self.epoch
    }
}

impl Clock for MonotonicClock {
    fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }
}

/// Absolute-deadline pacing with overrun counting and no catch-up bursts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pacer {
    period_us: u64,
    deadline_us: u64,
    /// Late ticks so far.
    pub overruns: u64,
}

impl Pacer {
    /// First deadline at `start_us + period_us`.
    pub fn new(start_us: u64, period_us: u64) -> Self {
        Self {
            period_us,
            deadline_us: start_us + period_us,
            overruns: 0,
        }
    }

    /// The absolute time the next tick must start, µs.
    pub fn deadline_us(&self) -> u64 {
        self.deadline_us
    }

    /// Call after a tick that started at `started_us` finished at `now_us`: advances the
    /// deadline by one period. If the tick started a full period late or finished after the next
    /// deadline, it is an overrun and the schedule is re-based on `now_us` (the next tick runs
    /// at once, then the rhythm resumes: never a burst of ticks to catch up).
    pub fn finish(&mut self, started_us: u64, now_us: u64) {
        let next = self.deadline_us + self.period_us;
        let late_start = started_us >= self.deadline_us + self.period_us;
        if late_start || now_us > next {
            self.overruns += 1;
            self.deadline_us = now_us;
        } else {
            self.deadline_us = next;
        }
    }
}

/// What the device-paced loop should do now ([`DevicePacer::decide`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wake {
    /// Run a tick now.
    Tick,
    /// Sleep until this time (µs), or until a new device sample wakes the thread earlier.
    SleepUntil(u64),
}

/// Device-paced scheduling (issue 15, section 2): the servo runs one tick as soon as a device
/// sample arrives, so the force answering a sample comes from a tick that has seen it (the
/// pose-to-force latency is the wake-up plus one step, not the wait for the next 1 ms slot
/// plus one step). A 1 ms schedule of slots keeps simulated time on wall-clock time:
///
/// - a pending sample starts a tick at once unless the simulation is already more than
///   `lead_us` (one period) ahead of its slot (a burst of samples after a network stall
///   collapses into the latest one, it never runs the model faster than real time);
/// - without a sample, a tick runs anyway `grace_us` after its slot: at once when no device is
///   connected (the plain 1 ms fallback), half a period late while one is (a late sample still
///   gets its own tick; a lost one does not stop the body);
/// - a tick that ends after the next slot is an overrun and the schedule is re-based on the
///   current time: never a burst of back-to-back ticks to catch up (a stopped daemon resumes
///   with one tick, then the rhythm).
///
/// Pure and clock-free: tests drive it with explicit times.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DevicePacer {
    period_us: u64,
    /// Slot of the next tick, µs.
    due_us: u64,
    lead_us: u64,
    grace_us: u64,
    /// Late ticks so far.
    pub overruns: u64,
}

impl DevicePacer {
    /// First slot at `start_us`; lead one period, grace half a period while a device is
    /// connected.
    pub fn new(start_us: u64, period_us: u64) -> Self {
        Self {
            period_us,
            due_us: start_us,
            lead_us: period_us,
            grace_us: period_us / 2,
            overruns: 0,
        }
    }

    /// The slot of the next tick, µs.
    pub fn due_us(&self) -> u64 {
        self.due_us
    }

    /// What to do at `now_us`, given whether a new device sample is waiting and whether a
    /// device is connected.
    pub fn decide(&self, now_us: u64, sample_pending: bool, device_connected: bool) -> Wake {
        let fallback = self.due_us + if device_connected { self.grace_us } else { 0 };
        let earliest = self.due_us.saturating_sub(self.lead_us);
        if (sample_pending && now_us >= earliest) || now_us >= fallback {
            Wake::Tick
        } else if sample_pending {
            Wake::SleepUntil(earliest)
        } else {
            Wake::SleepUntil(fallback)
        }
    }

    /// Call after a tick that ended at `now_us`: the next slot is one period later; a tick
    /// that ended after it is an overrun and re-bases the schedule on `now_us`.
    pub fn finish(&mut self, now_us: u64) {
        self.due_us += self.period_us;
        if now_us > self.due_us {
            self.overruns += 1;
            self.due_us = now_us;
        }
    }
}

/// What the loop should do after a tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Flow {
    /// Keep ticking.
    Continue,
    /// Stop requested: the final zero force has been pushed.
    Stop,
}

/// The servo's state and both ends of its handoffs. Everything is sized at construction.
pub struct ServoCore {
    body: Box<dyn SoftBody>,
    commands: rtrb::Consumer<Command>,
    pose: triple_buffer::Output<Pose>,
    forces: rtrb::Producer<ForceOut>,
    snapshot: triple_buffer::Input<Snapshot>,
    stats: triple_buffer::Input<StatsSnapshot>,
    shared: Arc<SessionShared>,
    snapshot_every: u64,
    stats_every: u64,
    step_hist: Histogram<u64>,
    p2f_hist: Histogram<u64>,
    step_buckets: LatencyBuckets,
    p2f_buckets: LatencyBuckets,
    ticks: u64,
    last_seq: Option<u64>,
    /// A connected device silent for longer than this is treated as gone, µs.
    device_silence_us: u64,
    /// The session is overrunning when the loop rate stays below `min_rate_hz` for this
    /// long, µs of wall time (`None`: never judged).
    overrun_limit: Option<(f64, u64)>,
    /// Quarantine an overrunning session (overrun policy `degrade`).
    degrade_on_overrun: bool,
    /// See [`StatsSnapshot::overrunning`].
    overrunning: bool,
    /// See [`StatsSnapshot::demoted`]; set by the loop.
    demoted: bool,
    /// Start of the current stretch of slow statistics windows, µs.
    slow_since_us: Option<u64>,
    device_silent: bool,
    device_silences: u64,
    current: TickInput,
    fault: Option<&'static str>,
    peak_force_n: f64,
    contact_ticks: u64,
    max_displacement_m: f64,
    device_samples: u64,
    window_start_us: u64,
    window_ticks: u64,
    last_force: ForceOut,
    /// Simulated time after the last successful tick, s.
    sim_time_s: f64,
    /// Accepted loads not yet reported as ended (first `applied_len`), for snapshots.
    applied: [AppliedLoad; APPLIED_LOAD_CAPACITY],
    applied_len: usize,
    applied_total: u64,
    /// Overruns, maintained by the loop's [`Pacer`].
    pub overruns: u64,
}

/// Default silence limit of a connected device, µs (50 ms: five times the bridge watchdog's
/// fresh window; issue 16).
pub const DEFAULT_DEVICE_SILENCE_US: u64 = 50_000;

/// The handoff ends a [`ServoCore`] owns.
pub struct ServoEnds {
    /// Commands in.
    pub commands: rtrb::Consumer<Command>,
    /// Latest pose in.
    pub pose: triple_buffer::Output<Pose>,
    /// Forces out.
    pub forces: rtrb::Producer<ForceOut>,
    /// Snapshots out.
    pub snapshot: triple_buffer::Input<Snapshot>,
    /// Statistics out.
    pub stats: triple_buffer::Input<StatsSnapshot>,
}

/// The other ends of a [`ServoCore`]'s handoffs, held by the async side.
pub struct ServoHandles {
    /// Commands out to the servo.
    pub commands: rtrb::Producer<Command>,
    /// Latest pose out to the servo.
    pub pose: triple_buffer::Input<Pose>,
    /// Forces from the servo.
    pub forces: rtrb::Consumer<ForceOut>,
    /// Snapshots from the servo.
    pub snapshot: triple_buffer::Output<Snapshot>,
    /// Statistics from the servo.
    pub stats: triple_buffer::Output<StatsSnapshot>,
}

/// Capacity of the command ring (ApplyForce requests queued between two ticks).
pub const COMMAND_CAPACITY: usize = 64;
/// Capacity of the force ring (forces queued for the forwarder).
pub const FORCE_CAPACITY: usize = 256;

/// Creates every handoff of a servo for `body`, sized once (the snapshot buffers hold the
/// body's largest surface, [`SoftBody::surface_capacity`]): the servo's ends and the async
/// side's ends.
pub fn channels(body: &dyn SoftBody) -> (ServoEnds, ServoHandles) {
    let (cmd_tx, cmd_rx) = rtrb::RingBuffer::new(COMMAND_CAPACITY);
    let (force_tx, force_rx) = rtrb::RingBuffer::new(FORCE_CAPACITY);
    let (pose_in, pose_out) = triple_buffer::triple_buffer(&Pose::default());
    // Full-length buffers: a clone (the triple buffer makes three) keeps only the length as
    // capacity, and the servo later shrinks and regrows them within it.
    let cap = body.surface_capacity();
    let snap0 = Snapshot {
        topology_version: u64::MAX,
        triangles: vec![0; 3 * cap.triangles],
        rest_positions_m: vec![0.0; 3 * cap.vertices],
        positions_m: vec![0.0; 3 * cap.vertices],
        ..Snapshot::default()
    };
    let (snap_in, snap_out) = triple_buffer::triple_buffer(&snap0);
    let (stats_in, stats_out) = triple_buffer::triple_buffer(&StatsSnapshot::default());
    (
        ServoEnds {
            commands: cmd_rx,
            pose: pose_out,
            forces: force_tx,
            snapshot: snap_in,
            stats: stats_in,
        },
        ServoHandles {
            commands: cmd_tx,
            pose: pose_in,
            forces: force_rx,
            snapshot: snap_out,
            stats: stats_out,
        },
    )
}

fn histogram() -> Histogram<u64> {
    // 1 µs .. 60 s at 3 significant digits; fixed size, so recording never allocates.
    Histogram::new_with_bounds(1, 60_000_000, 3).expect("static histogram bounds")
}

impl ServoCore {
    /// Judges the session overrunning ([`ServoCore::overrunning`]) once the loop rate of every
    /// statistics window (`stats_every` ticks) has stayed below `min_rate_hz` for `for_us` of
    /// wall time; it stops being so after one window at or above the rate.
    pub fn with_overrun_limit(mut self, min_rate_hz: f64, for_us: u64) -> Self {
        self.overrun_limit = Some((min_rate_hz, for_us));
        self
    }

    /// As [`Self::with_overrun_limit`], and quarantines the session (zero force, `fault` set,
    /// the body no longer stepped) once it is overrunning: the loop rate of every
    /// statistics window (`stats_every` ticks) has stayed below `min_rate_hz` for `for_us` of
    /// wall time. Without this call the rate is only reported.
    pub fn with_overrun_degrade(mut self, min_rate_hz: f64, for_us: u64) -> Self {
        self.overrun_limit = Some((min_rate_hz, for_us));
        self.degrade_on_overrun = true;
        self
    }

    /// The silence limit of a connected device, µs (default [`DEFAULT_DEVICE_SILENCE_US`]).
    pub fn with_device_silence_us(mut self, us: u64) -> Self {
        self.device_silence_us = us.max(1);
        self
    }

    /// Builds the core. `snapshot_every` / `stats_every` are in ticks (>= 1). `ends` must come
    /// from [`channels`] for this body (the snapshot buffers are sized for its surface).
    pub fn new(
        body: Box<dyn SoftBody>,
        ends: ServoEnds,
        shared: Arc<SessionShared>,
        snapshot_every: u32,
        stats_every: u32,
    ) -> Self {
        Self {
            body,
            commands: ends.commands,
            pose: ends.pose,
            forces: ends.forces,
            snapshot: ends.snapshot,
            stats: ends.stats,
            shared,
            snapshot_every: snapshot_every.max(1) as u64,
            stats_every: stats_every.max(1) as u64,
            step_hist: histogram(),
            p2f_hist: histogram(),
            step_buckets: LatencyBuckets::default(),
            p2f_buckets: LatencyBuckets::default(),
            ticks: 0,
            last_seq: None,
            device_silence_us: DEFAULT_DEVICE_SILENCE_US,
            overrun_limit: None,
            degrade_on_overrun: false,
            overrunning: false,
            demoted: false,
            slow_since_us: None,
            device_silent: false,
            device_silences: 0,
            current: TickInput::default(),
            fault: None,
            peak_force_n: 0.0,
            contact_ticks: 0,
            max_displacement_m: 0.0,
            device_samples: 0,
            window_start_us: 0,
            window_ticks: 0,
            last_force: ForceOut::default(),
            sim_time_s: 0.0,
            applied: [AppliedLoad::default(); APPLIED_LOAD_CAPACITY],
            applied_len: 0,
            applied_total: 0,
            overruns: 0,
        }
    }

    /// Keeps an accepted load for the next snapshot. Without watchers nothing reports them, so
    /// loads that have ended are dropped first; a table still full (more accepted loads than a
    /// body holds, all unreported) loses its oldest entry, which the index gap shows.
    fn note_applied(&mut self, point_m: DVec3, force_n: DVec3, duration_s: f64) {
        self.applied_total += 1;
        if self.shared.watchers.load(Ordering::Relaxed) == 0 {
            self.prune_applied(self.sim_time_s);
        }
        if self.applied_len == APPLIED_LOAD_CAPACITY {
            self.applied.copy_within(1.., 0);
            self.applied_len -= 1;
        }
        self.applied[self.applied_len] = AppliedLoad {
            index: self.applied_total,
            point_m,
            force_n,
            start_sim_time_s: self.sim_time_s,
            duration_s,
        };
        self.applied_len += 1;
    }

    /// Drops the loads that ended at or before `t_s` (order kept; no allocation).
    fn prune_applied(&mut self, t_s: f64) {
        let mut kept = 0;
        for i in 0..self.applied_len {
            let a = self.applied[i];
            if a.start_sim_time_s + a.duration_s > t_s {
                self.applied[kept] = a;
                kept += 1;
            }
        }
        self.applied_len = kept;
    }

    /// The body (for tests and set-up).
    pub fn body(&self) -> &dyn SoftBody {
        self.body.as_ref()
    }

    /// The fault that quarantined the session, if any.
    pub fn fault(&self) -> Option<&'static str> {
        self.fault
    }

    /// True when the device stream published a pose the servo has not read yet (wait-free).
    pub fn sample_pending(&self) -> bool {
        self.pose.updated()
    }

    /// True when the session has stayed below its minimum loop rate for the judged time
    /// ([`Self::with_overrun_limit`]).
    pub fn overrunning(&self) -> bool {
        self.overrunning
    }

    /// Records whether the loop has demoted this servo thread (published with the statistics).
    pub fn set_demoted(&mut self, demoted: bool) {
        self.demoted = demoted;
    }

    /// True when the last pose read came from a connected device.
    pub fn device_connected(&self) -> bool {
        self.current.device_position_m.is_some()
    }

    /// Runs one tick at time `now_us` (clock read again after the step for timing).
    /// Allocation-free, lock-free, no logging.
    pub fn tick(&mut self, now_us: u64, clock: &impl Clock) -> Flow {
        if self.shared.stop.load(Ordering::Acquire) {
            let seq = self.last_seq.unwrap_or(0);
            let _ = self.forces.push(ForceOut {
                seq,
                ..ForceOut::default()
            });
            self.shared.finished.store(true, Ordering::Release);
            return Flow::Stop;
        }
        if self.window_ticks == 0 && self.ticks == 0 {
            self.window_start_us = now_us;
        }
        // 1. Commands.
        while let Ok(cmd) = self.commands.pop() {
            match cmd {
                Command::ApplyForce {
                    point_m,
                    force_n,
                    duration_s,
                } => {
                    // Validated by the handler; a full load table drops the command.
                    if self
                        .body
                        .add_point_load(point_m, force_n, duration_s)
                        .is_ok()
                    {
                        self.note_applied(point_m, force_n, duration_s);
                    }
                }
            }
        }
        // 2. Latest pose.
        self.pose.update();
        let pose = *self.pose.output_buffer();
        let fresh = pose.connected && self.last_seq != Some(pose.seq);
        // A device that stopped sending (a stalled bridge) must not keep pressing with its
        // last pose: past the silence limit it leaves the scene until its next sample.
        let silent = pose.connected
            && !fresh
            && now_us.saturating_sub(pose.received_us) > self.device_silence_us;
        if silent && !self.device_silent {
            self.device_silences += 1;
        }
        self.device_silent = silent;
        if pose.connected && !silent {
            self.current = TickInput {
                device_position_m: Some(pose.position_m),
                device_velocity_m_per_s: pose.velocity_m_per_s,
            };
        } else {
            self.current = TickInput::default();
        }
        if fresh {
            self.last_seq = Some(pose.seq);
            self.device_samples += 1;
        }
        // 3. Step.
        let t0 = clock.now_us();
        let out = if self.fault.is_none() {
            match self.body.tick(&self.current) {
                Ok(o) => {
                    self.sim_time_s = o.sim_time_s;
                    Some(o)
                }
                Err(e) => {
                    self.fault = Some(match e {
                        ModelError::Diverged { .. } => {
                            "the simulation diverged; session quarantined (zero force)"
                        }
                        ModelError::InvalidDevice(m) => m,
                        _ => "the model failed; session quarantined (zero force)",
                    });
                    None
                }
            }
        } else {
            None
        };
        let t1 = clock.now_us();
        self.step_hist.saturating_record((t1 - t0).max(1));
        self.step_buckets.record(t1 - t0);
        // 4. Guard and hand out the force.
        let mut force = ForceOut {
            seq: pose.seq,
            ..ForceOut::default()
        };
        if let Some(o) = out
            && o.force_on_device_n.is_finite()
        {
            force.force_n = o.force_on_device_n;
            force.in_contact = o.in_contact;
            force.stiffness_n_per_m = o.contact_stiffness_n_per_m;
            force.proxy_m = o.proxy_position_m;
        }
        self.peak_force_n = self.peak_force_n.max(force.force_n.length());
        self.contact_ticks += u64::from(force.in_contact);
        self.last_force = force;
        if fresh {
            // A full ring means the forwarder is stalled; dropping is the safe choice (the
            // bridge's watchdog ramps the force down).
            let _ = self.forces.push(force);
            let done = clock.now_us();
            let p2f_us = done.saturating_sub(pose.received_us);
            self.p2f_hist.saturating_record(p2f_us.max(1));
            self.p2f_buckets.record(p2f_us);
        }
        self.ticks += 1;
        self.window_ticks += 1;
        // 5. Snapshot for viewers.
        if self.ticks.is_multiple_of(self.snapshot_every)
            && self.shared.watchers.load(Ordering::Relaxed) > 0
        {
            let snap = self.snapshot.input_buffer_mut();
            let topology = self.body.surface_topology();
            let n = 3 * topology.vertex_count;
            // Within the capacity sized by `channels`: no allocation.
            if snap.topology_version != topology.version {
                snap.triangles.clear();
                snap.triangles
                    .extend(topology.triangles.iter().flatten().copied());
                snap.rest_positions_m.resize(n, 0.0);
                self.body
                    .write_surface_rest_positions(&mut snap.rest_positions_m);
                snap.topology_version = topology.version;
            }
            snap.positions_m.resize(n, 0.0);
            snap.tick = self.ticks;
            snap.sim_time_s = self.sim_time_s;
            let d = self.body.write_surface_positions(&mut snap.positions_m);
            snap.max_displacement_m = d;
            snap.probe_m = match self.current.device_position_m {
                Some(p) => p,
                None => DVec3::NAN,
            };
            snap.force_n = force.force_n;
            snap.in_contact = force.in_contact;
            snap.applied = self.applied;
            snap.applied_len = self.applied_len;
            snap.applied_total = self.applied_total;
            self.snapshot.publish();
            // Reported once after they ended: drop them.
            self.prune_applied(self.sim_time_s);
        }
        // 6. Statistics.
        if self.ticks.is_multiple_of(self.stats_every) {
            let body = self.body.stats();
            self.max_displacement_m = self.max_displacement_m.max(body.max_displacement_m);
            let elapsed_us = t1.saturating_sub(self.window_start_us).max(1);
            let rate = self.window_ticks as f64 * 1e6 / elapsed_us as f64;
            self.window_start_us = t1;
            self.window_ticks = 0;
            // The first window includes start-up: not judged.
            if let Some((min_rate_hz, for_us)) = self.overrun_limit
                && self.ticks > self.stats_every
            {
                let window_start = t1.saturating_sub(elapsed_us);
                self.slow_since_us = if rate < min_rate_hz {
                    Some(self.slow_since_us.unwrap_or(window_start))
                } else {
                    None
                };
                let slow_for = self.slow_since_us.map_or(0, |s| t1.saturating_sub(s));
                self.overrunning = slow_for >= for_us;
                if self.overrunning && self.degrade_on_overrun && self.fault.is_none() {
                    self.fault = Some(
                        "the servo cannot keep its rate on this machine (overrun policy \"degrade\"): session quarantined (zero force)",
                    );
                }
            }
            let s = self.stats.input_buffer_mut();
            *s = StatsSnapshot {
                steps: self.ticks,
                overruns: self.overruns,
                loop_rate_hz: rate,
                step_p50_us: self.step_hist.value_at_quantile(0.5) as f64,
                step_p99_us: self.step_hist.value_at_quantile(0.99) as f64,
                step_max_us: self.step_hist.max() as f64,
                pose_to_force_p50_us: if self.p2f_hist.is_empty() {
                    0.0
                } else {
                    self.p2f_hist.value_at_quantile(0.5) as f64
                },
                pose_to_force_p99_us: if self.p2f_hist.is_empty() {
                    0.0
                } else {
                    self.p2f_hist.value_at_quantile(0.99) as f64
                },
                sim_time_s: self.sim_time_s,
                in_contact: force.in_contact,
                contact_ticks: self.contact_ticks,
                peak_force_n: self.peak_force_n,
                max_displacement_m: self.max_displacement_m,
                device_samples: self.device_samples,
                fault: self.fault,
                device_silent: self.device_silent,
                device_silences: self.device_silences,
                overrunning: self.overrunning,
                demoted: self.demoted,
                body,
                step_buckets: self.step_buckets,
                pose_to_force_buckets: self.p2f_buckets,
            };
            self.stats.publish();
        }
        Flow::Continue
    }
}

/// Real-time set-up outcome messages (logged by the caller, never from the tick).
pub fn setup_realtime(cfg: &crate::config::ServoConfig) -> Vec<String> {
    let mut warnings = Vec::new();
    if let Some(cpu) = cfg.cpu {
        let ok = core_affinity::get_core_ids()
            .and_then(|ids| ids.into_iter().find(|c| c.id == cpu))
            .map(core_affinity::set_for_current)
            .unwrap_or(false);
        if !ok {
            warnings.push(format!(
                "could not pin the servo thread to CPU {cpu}; running unpinned"
            ));
        }
    }
    if cfg.realtime {
        use thread_priority::*;
        let prio = ThreadPriority::Crossplatform(
            ThreadPriorityValue::try_from(cfg.priority.min(99)).unwrap_or(ThreadPriorityValue::MAX),
        );
        let policy = ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo);
        if let Err(e) = set_thread_priority_and_policy(thread_native_id(), prio, policy) {
            warnings.push(format!(
                "SCHED_FIFO priority {} refused ({e:?}); running with normal scheduling",
                cfg.priority
            ));
        }
    }
    if cfg.mlockall {
        // SAFETY: mlockall has no memory-safety preconditions; it only changes paging.
        let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
        if rc != 0 {
            warnings.push(format!(
                "mlockall failed ({}); memory may be paged",
                std::io::Error::last_os_error()
            ));
        }
    }
    warnings
}

/// Lets an overrunning session's servo thread yield to the sessions that keep up (issue 16,
/// section 2). While the session is overrunning ([`ServoCore::overrunning`]) and another
/// session runs, its thread is moved to `SCHED_IDLE`: it then gets only the CPU time the
/// others leave, so a model too heavy for the machine cannot slow a session that fits. When
/// it keeps its rate again, or is alone, the thread's original policy (normal or
/// `SCHED_FIFO`) comes back. Linux lets a thread leave `SCHED_IDLE` only with
/// `CAP_SYS_NICE` (the systemd unit grants it); without it a demoted thread stays demoted,
/// which `GetStats` shows (`demoted`).
///
/// Called from the loop after each tick, never inside it: a demotion is one system call.
#[derive(Debug)]
pub struct Yielding {
    enabled: bool,
    running_sessions: Arc<std::sync::atomic::AtomicUsize>,
    /// The thread's policy and priority when the loop started.
    original: (libc::c_int, libc::c_int),
    demoted: bool,
    /// A policy change was refused: stop trying.
    stuck: bool,
}

impl Yielding {
    /// Reads the calling (servo) thread's policy, after [`setup_realtime`]. `running_sessions`
    /// counts the daemon's sessions; `enabled: false` never demotes.
    pub fn new(enabled: bool, running_sessions: Arc<std::sync::atomic::AtomicUsize>) -> Self {
        // SAFETY: both calls only read the calling thread's scheduling attributes into a
        // local, properly sized struct.
        let original = unsafe {
            let mut param = libc::sched_param { sched_priority: 0 };
            let policy = libc::sched_getscheduler(0);
            libc::sched_getparam(0, &mut param);
            (policy.max(0), param.sched_priority)
        };
        Self {
            enabled,
            running_sessions,
            original,
            demoted: false,
            stuck: false,
        }
    }

    /// Demotes or restores the thread as the session's state asks (see the type).
    pub fn after_tick(&mut self, core: &mut ServoCore) {
        if !self.enabled || self.stuck {
            return;
        }
        let want = core.overrunning() && self.running_sessions.load(Ordering::Relaxed) > 1;
        if want == self.demoted {
            return;
        }
        let (policy, priority) = if want {
            (libc::SCHED_IDLE, 0)
        } else {
            self.original
        };
        let param = libc::sched_param {
            sched_priority: priority,
        };
        // SAFETY: changes the calling thread's own policy; `param` outlives the call.
        if unsafe { libc::sched_setscheduler(0, policy, &param) } == 0 {
            self.demoted = want;
            core.set_demoted(want);
        } else {
            self.stuck = true;
        }
    }
}

/// Runs the servo loop until stopped, device-paced ([`DevicePacer`]): a tick as soon as a
/// device sample arrives (the stream task unparks this thread after publishing it), a tick per
/// `period_us` slot otherwise. Wakes `forwarder` after each tick.
pub fn run_loop_device_paced(
    mut core: ServoCore,
    clock: MonotonicClock,
    period_us: u64,
    forwarder: std::thread::Thread,
    mut yielding: Yielding,
) {
    let mut pacer = DevicePacer::new(clock.now_us(), period_us);
    loop {
        let now = clock.now_us();
        let wake = pacer.decide(now, core.sample_pending(), core.device_connected());
        if let Wake::SleepUntil(t) = wake {
            // A sample's arrival unparks us early; spurious wake-ups just decide again.
            std::thread::park_timeout(std::time::Duration::from_micros(t.saturating_sub(now)));
            continue;
        }
        let started = clock.now_us();
        let flow = core.tick(started, &clock);
        forwarder.unpark();
        if flow == Flow::Stop {
            break;
        }
        pacer.finish(clock.now_us());
        core.overruns = pacer.overruns;
        yielding.after_tick(&mut core);
    }
}

/// Runs the servo loop until stopped: paces ticks at `period_us` with absolute deadlines and
/// wakes `forwarder` after each tick that produced a force.
pub fn run_loop(
    mut core: ServoCore,
    clock: MonotonicClock,
    period_us: u64,
    forwarder: std::thread::Thread,
    mut yielding: Yielding,
) {
    let sleeper = spin_sleep::SpinSleeper::default();
    let mut pacer = Pacer::new(clock.now_us(), period_us);
    loop {
        let deadline = clock.epoch() + std::time::Duration::from_micros(pacer.deadline_us());
        sleeper.sleep_until(deadline);
        let started = clock.now_us();
        let flow = core.tick(started, &clock);
        forwarder.unpark();
        if flow == Flow::Stop {
            break;
        }
        pacer.finish(started, clock.now_us());
        core.overruns = pacer.overruns;
        yielding.after_tick(&mut core);
    }
}

#[cfg(test)]
mod device_pacer_tests {
    use super::*;

    #[test]
    fn a_sample_starts_a_tick_at_once_and_a_missing_one_falls_back() {
        let mut p = DevicePacer::new(0, 1_000);
        // No device: the plain 1 ms schedule.
        assert_eq!(p.decide(0, false, false), Wake::Tick);
        p.finish(400);
        assert_eq!(p.decide(400, false, false), Wake::SleepUntil(1_000));
        assert_eq!(p.decide(1_000, false, false), Wake::Tick);
        p.finish(1_400);
        // A device connects; its sample at 1 300 us (before the 2 000 us slot) ticks at once.
        assert_eq!(p.decide(1_300, true, true), Wake::Tick);
        p.finish(1_800);
        // Connected, no sample yet: wait until half a period past the 3 000 us slot.
        assert_eq!(p.decide(1_800, false, true), Wake::SleepUntil(3_500));
        assert_eq!(p.decide(2_300, true, true), Wake::Tick);
        p.finish(2_800);
        // The next sample is lost: the body still ticks at 4 500 us.
        assert_eq!(p.decide(4_499, false, true), Wake::SleepUntil(4_500));
        assert_eq!(p.decide(4_500, false, true), Wake::Tick);
        p.finish(5_000);
        assert_eq!(p.overruns, 0);
    }

    #[test]
    fn a_burst_of_samples_never_runs_the_model_faster_than_real_time() {
        let mut p = DevicePacer::new(0, 1_000);
        let mut ticks = 0;
        let mut now = 0;
        // Samples pending all the time for 100 ms, ticks taking 100 us each.
        while now < 100_000 {
            match p.decide(now, true, true) {
                Wake::Tick => {
                    ticks += 1;
                    now += 100;
                    p.finish(now);
                }
                Wake::SleepUntil(t) => now = t,
            }
        }
        // At most one tick ahead of the 1 ms schedule.
        assert!((100..=102).contains(&ticks), "{ticks}");
    }

    #[test]
    fn a_stall_is_an_overrun_and_the_schedule_rebases_without_a_burst() {
        let mut p = DevicePacer::new(0, 1_000);
        assert_eq!(p.decide(0, true, true), Wake::Tick);
        // The process was stopped for 500 ms during the tick.
        p.finish(500_000);
        assert_eq!(p.overruns, 1);
        assert_eq!(p.due_us(), 500_000);
        // One tick now (a sample is pending), then the rhythm: no back-to-back catch-up.
        assert_eq!(p.decide(500_010, true, true), Wake::Tick);
        p.finish(500_500);
        assert_eq!(p.decide(500_510, false, true), Wake::SleepUntil(501_500));
        assert_eq!(p.decide(500_510, true, true), Wake::Tick);
        p.finish(500_600);
        assert_eq!(p.decide(500_610, true, true), Wake::SleepUntil(501_000));
    }
}
