//! The handoffs between the servo thread and the async side: the messages (commands, poses,
//! forces, snapshots, statistics), the shared atomics and [`channels`], which sizes them all once.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize};

use haptic_model::DVec3;
use haptic_model::body::{BodyStats, MAX_TOOLS, SoftBody};

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
    /// Device (probe) position of tool slot 0, m; NaN when no device is connected.
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
    /// Every tool slot's probe (the first `tool_count`; slot 0 repeats `probe_m`, `force_n`,
    /// `in_contact`).
    pub tools: [ToolProbeSnapshot; MAX_TOOLS],
    /// Tool slots of the session.
    pub tool_count: usize,
}

/// One tool slot's probe in a [`Snapshot`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ToolProbeSnapshot {
    /// A device drives the slot (and is not silent).
    pub connected: bool,
    /// Device point, m (meaningful when `connected`).
    pub probe_m: DVec3,
    /// Force on the device, N.
    pub force_n: DVec3,
    /// In contact.
    pub in_contact: bool,
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
    /// The servo thread yields to the sessions that keep up (`SCHED_IDLE`; [`super::Yielding`]).
    pub demoted: bool,
    /// Threads the session's tick uses: the servo thread plus its tick-pool workers
    /// ([`crate::cores`]); 0 before the first publication.
    pub threads: u32,
    /// Longest time the servo waited for a part of its tick a pool worker had claimed, µs
    /// (`haptic_model::pool::PoolStats::longest_wait_us`; 0 without workers).
    pub pool_wait_us_max: u64,
    /// The body's size and state at the last publication.
    pub body: BodyStats,
    /// Step compute times, all ticks so far (for the metrics endpoint).
    pub step_buckets: LatencyBuckets,
    /// Pose received to force pushed, all answered samples so far.
    pub pose_to_force_buckets: LatencyBuckets,
    /// Tool slots of the session (`SoftBody::max_tools`, at most [`MAX_TOOLS`]); 0 before the
    /// first publication.
    pub tool_count: u32,
    /// Per tool slot (the first `tool_count`).
    pub tools: [ToolStatsSnapshot; MAX_TOOLS],
}

/// One tool slot's statistics in a [`StatsSnapshot`] (issue 50).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ToolStatsSnapshot {
    /// A device stream drives the slot (its last pose says connected).
    pub connected: bool,
    /// In contact at the last tick.
    pub in_contact: bool,
    /// Force magnitude on the device at the last tick, N.
    pub force_n: f64,
    /// Largest force magnitude so far, N.
    pub peak_force_n: f64,
    /// Pose received to force pushed, this tool's samples, µs.
    pub pose_to_force_p50_us: f64,
    /// 99th percentile of the same, µs.
    pub pose_to_force_p99_us: f64,
    /// Samples consumed.
    pub device_samples: u64,
    /// Ticks in contact so far.
    pub contact_ticks: u64,
    /// The connected device is silent (see [`StatsSnapshot::device_silent`]).
    pub device_silent: bool,
    /// Times it fell silent.
    pub device_silences: u64,
    /// Pose received to force pushed, this tool's samples so far.
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

/// One tool slot's ends on the servo side: its latest pose in, its forces out.
pub struct ToolEnds {
    /// Latest pose in.
    pub pose: triple_buffer::Output<Pose>,
    /// Forces out.
    pub forces: rtrb::Producer<ForceOut>,
}

/// One tool slot's ends on the async side (slots 1.. of [`tool_channels`]; slot 0's are
/// [`ServoHandles::pose`] and [`ServoHandles::forces`]).
pub struct ToolHandles {
    /// Latest pose out to the servo.
    pub pose: triple_buffer::Input<Pose>,
    /// Forces from the servo.
    pub forces: rtrb::Consumer<ForceOut>,
}

/// The handoff ends a [`super::ServoCore`] owns.
pub struct ServoEnds {
    /// Commands in.
    pub commands: rtrb::Consumer<Command>,
    /// Every tool slot's pose in and forces out (at least one, at most [`MAX_TOOLS`]).
    pub tools: Vec<ToolEnds>,
    /// Snapshots out.
    pub snapshot: triple_buffer::Input<Snapshot>,
    /// Statistics out.
    pub stats: triple_buffer::Input<StatsSnapshot>,
}

/// The other ends of a [`super::ServoCore`]'s handoffs, held by the async side.
pub struct ServoHandles {
    /// Commands out to the servo.
    pub commands: rtrb::Producer<Command>,
    /// Latest pose out to the servo (tool slot 0).
    pub pose: triple_buffer::Input<Pose>,
    /// Forces from the servo (tool slot 0).
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
/// side's ends of tool slot 0. A body with several tool slots keeps only slot 0 reachable
/// ([`tool_channels`] gives them all).
pub fn channels(body: &dyn SoftBody) -> (ServoEnds, ServoHandles) {
    let (ends, handles, _more) = tool_channels(body);
    (ends, handles)
}

/// Tool slots of `body`'s sessions: [`SoftBody::max_tools`] within `1..=MAX_TOOLS`.
pub fn tool_slots(body: &dyn SoftBody) -> usize {
    body.max_tools().clamp(1, MAX_TOOLS)
}

/// [`channels`] with every tool slot ([`tool_slots`]): slot 0's async ends in the handles, the
/// others' (slots 1..) in the vector, in slot order.
pub fn tool_channels(body: &dyn SoftBody) -> (ServoEnds, ServoHandles, Vec<ToolHandles>) {
    let (cmd_tx, cmd_rx) = rtrb::RingBuffer::new(COMMAND_CAPACITY);
    let mut tools = Vec::new();
    let mut handles = Vec::new();
    for _ in 0..tool_slots(body) {
        let (force_tx, force_rx) = rtrb::RingBuffer::new(FORCE_CAPACITY);
        let (pose_in, pose_out) = triple_buffer::triple_buffer(&Pose::default());
        tools.push(ToolEnds {
            pose: pose_out,
            forces: force_tx,
        });
        handles.push(ToolHandles {
            pose: pose_in,
            forces: force_rx,
        });
    }
    let first = handles.remove(0);
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
            tools,
            snapshot: snap_in,
            stats: stats_in,
        },
        ServoHandles {
            commands: cmd_tx,
            pose: first.pose,
            forces: first.forces,
            snapshot: snap_out,
            stats: stats_out,
        },
        handles,
    )
}
