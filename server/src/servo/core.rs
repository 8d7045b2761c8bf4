//! [`ServoCore`]: the servo's state and its allocation-, lock- and log-free [`ServoCore::tick`].
//!
//! The core is split by how its parts change: [`ServoParams`] (set before the loop, read-only in
//! the tick), [`ServoState`] (what a tick reads and writes), [`AppliedLoads`] (the accepted
//! loads a snapshot lists) and [`ServoStats`] (accumulators copied into the statistics).

use std::sync::Arc;
use std::sync::atomic::Ordering;

use haptic_model::body::{MAX_TOOLS, SoftBody, TickInput, TickOutput};
use haptic_model::{DVec3, ModelError};

use super::params::{OverrunLimit, ServoParams};
use super::stats::ServoStats;
use super::{
    APPLIED_LOAD_CAPACITY, AppliedLoad, Clock, Command, Flow, ForceOut, Pose, ServoEnds,
    SessionShared, Snapshot,
};

/// The servo's state and both ends of its handoffs. Everything is sized at construction.
pub struct ServoCore {
    body: Box<dyn SoftBody>,
    ends: ServoEnds,
    shared: Arc<SessionShared>,
    params: ServoParams,
    state: ServoState,
    applied: AppliedLoads,
    stats: ServoStats,
    /// The body's tick pool (for its statistics), how many of the session's tick threads
    /// work beside the body's background threads and the other sessions, and how many work
    /// now.
    pool: Option<Arc<haptic_model::pool::TickPool>>,
    share: crate::cores::ThreadShare,
    threads: u32,
}

/// Default silence limit of a connected device, µs (50 ms: five times the bridge watchdog's
/// fresh window; issue 16).
pub const DEFAULT_DEVICE_SILENCE_US: u64 = 50_000;

/// The overrun judgement's memory.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct OverrunJudge {
    /// Start of the current stretch of slow statistics windows, µs.
    slow_since_us: Option<u64>,
    /// See [`super::StatsSnapshot::overrunning`].
    overrunning: bool,
}

/// What a tick reads and writes besides the body.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct ServoState {
    ticks: u64,
    /// Per tool slot (the first `tool_count`): the last sequence number read.
    last_seq: [Option<u64>; MAX_TOOLS],
    /// Per tool slot: the tick's input (`None` position: no device, or a silent one).
    current: [TickInput; MAX_TOOLS],
    /// Per tool slot: the connected device is silent.
    silent: [bool; MAX_TOOLS],
    /// Tool slots of the body ([`super::tool_slots`]).
    tool_count: usize,
    fault: Option<&'static str>,
    /// Simulated time after the last successful tick, s.
    sim_time_s: f64,
    /// Any connected tool is silent.
    device_silent: bool,
    /// See [`super::StatsSnapshot::demoted`]; set by the loop.
    demoted: bool,
    judge: OverrunJudge,
}

/// Accepted loads not yet reported as ended (the first `len`), for snapshots.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AppliedLoads {
    loads: [AppliedLoad; APPLIED_LOAD_CAPACITY],
    len: usize,
    /// Loads accepted so far.
    total: u64,
}

impl AppliedLoads {
    fn new() -> Self {
        Self {
            loads: [AppliedLoad::default(); APPLIED_LOAD_CAPACITY],
            len: 0,
            total: 0,
        }
    }

    /// Keeps an accepted load for the next snapshot, started at `sim_time_s`. Without watchers
    /// (`watched` false) nothing reports them, so loads that have ended are dropped first; a
    /// table still full (more accepted loads than a body holds, all unreported) loses its
    /// oldest entry, which the index gap shows.
    fn note(
        &mut self,
        point_m: DVec3,
        force_n: DVec3,
        duration_s: f64,
        sim_time_s: f64,
        watched: bool,
    ) {
        self.total += 1;
        if !watched {
            self.prune(sim_time_s);
        }
        if self.len == APPLIED_LOAD_CAPACITY {
            self.loads.copy_within(1.., 0);
            self.len -= 1;
        }
        self.loads[self.len] = AppliedLoad {
            index: self.total,
            point_m,
            force_n,
            start_sim_time_s: sim_time_s,
            duration_s,
        };
        self.len += 1;
    }

    /// Drops the loads that ended at or before `t_s` (order kept; no allocation).
    fn prune(&mut self, t_s: f64) {
        let mut kept = 0;
        for i in 0..self.len {
            let a = self.loads[i];
            if a.start_sim_time_s + a.duration_s > t_s {
                self.loads[kept] = a;
                kept += 1;
            }
        }
        self.len = kept;
    }

    /// Copies the table into a snapshot.
    fn copy_to(&self, snap: &mut Snapshot) {
        snap.applied = self.loads;
        snap.applied_len = self.len;
        snap.applied_total = self.total;
    }
}

/// The latest pose as a tick reads it.
#[derive(Debug, Clone, Copy, Default)]
struct PoseRead {
    pose: Pose,
    /// A sample the servo has not seen before, from a connected device.
    fresh: bool,
}

impl ServoCore {
    /// Judges the session overrunning ([`ServoCore::overrunning`]) once the loop rate of every
    /// statistics window (`stats_every` ticks) has stayed below `min_rate_hz` for `for_us` of
    /// wall time; it stops being so after one window at or above the rate.
    pub fn with_overrun_limit(mut self, min_rate_hz: f64, for_us: u64) -> Self {
        self.params.overrun = Some(OverrunLimit {
            min_rate_hz,
            for_us,
            degrade: false,
        });
        self
    }

    /// As [`Self::with_overrun_limit`], and quarantines the session (zero force, `fault` set,
    /// the body no longer stepped) once it is overrunning: the loop rate of every
    /// statistics window (`stats_every` ticks) has stayed below `min_rate_hz` for `for_us` of
    /// wall time. Without this call the rate is only reported.
    pub fn with_overrun_degrade(mut self, min_rate_hz: f64, for_us: u64) -> Self {
        self.params.overrun = Some(OverrunLimit {
            min_rate_hz,
            for_us,
            degrade: true,
        });
        self
    }

    /// The silence limit of a connected device, µs (default [`DEFAULT_DEVICE_SILENCE_US`]).
    pub fn with_device_silence_us(mut self, us: u64) -> Self {
        self.params.device_silence_us = us.max(1);
        self
    }

    /// Builds the core. `snapshot_every` / `stats_every` are in ticks (>= 1). `ends` must come
    /// from [`super::channels`] for this body (the snapshot buffers are sized for its surface).
    pub fn new(
        body: Box<dyn SoftBody>,
        ends: ServoEnds,
        shared: Arc<SessionShared>,
        snapshot_every: u32,
        stats_every: u32,
    ) -> Self {
        let tool_count = ends.tools.len().clamp(1, MAX_TOOLS);
        Self {
            body,
            ends,
            shared,
            params: ServoParams {
                snapshot_every: snapshot_every.max(1) as u64,
                stats_every: stats_every.max(1) as u64,
                device_silence_us: DEFAULT_DEVICE_SILENCE_US,
                overrun: None,
            },
            state: ServoState {
                tool_count,
                ..ServoState::default()
            },
            applied: AppliedLoads::new(),
            stats: ServoStats::new(),
            pool: None,
            share: crate::cores::ThreadShare::fixed(1),
            threads: 1,
        }
    }

    /// Records the session's tick pool, already handed to the body
    /// (`SoftBody::set_tick_pool`), and the threads its tick has (the servo's plus the pool's
    /// workers, as the session decided): published as `threads` (those working) and
    /// `pool_wait_us_max`. Lends out the workers that have no core now
    /// ([`crate::cores::ThreadShare::working`]); every statistics window checks again.
    pub fn with_tick_pool(
        mut self,
        pool: Option<Arc<haptic_model::pool::TickPool>>,
        share: crate::cores::ThreadShare,
    ) -> Self {
        self.pool = pool;
        self.share = share;
        self.lend_workers();
        self
    }

    /// Activates the pool workers the body's background threads and the other sessions leave
    /// a core and lends out the others (`TickPool::set_active_workers`). Allocation-free and
    /// lock-free.
    fn lend_workers(&mut self) {
        let working = self.share.working(self.body.background_threads());
        let workers = self
            .pool
            .as_ref()
            .map_or(0, |pool| pool.set_active_workers(working - 1));
        self.threads = workers as u32 + 1;
    }

    /// The body (for tests and set-up).
    pub fn body(&self) -> &dyn SoftBody {
        self.body.as_ref()
    }

    /// The fault that quarantined the session, if any.
    pub fn fault(&self) -> Option<&'static str> {
        self.state.fault
    }

    /// True when a device stream (any tool's) published a pose the servo has not read yet
    /// (wait-free).
    pub fn sample_pending(&self) -> bool {
        self.ends.tools.iter().any(|t| t.pose.updated())
    }

    /// True when the session has stayed below its minimum loop rate for the judged time
    /// ([`Self::with_overrun_limit`]).
    pub fn overrunning(&self) -> bool {
        self.state.judge.overrunning
    }

    /// Records whether the loop has demoted this servo thread (published with the statistics).
    pub fn set_demoted(&mut self, demoted: bool) {
        self.state.demoted = demoted;
    }

    /// Records the overruns counted by the loop's pacer (published with the statistics).
    pub fn set_overruns(&mut self, overruns: u64) {
        self.stats.overruns = overruns;
    }

    /// True when the last pose read of any tool slot came from a connected device.
    pub fn device_connected(&self) -> bool {
        self.state.current[..self.state.tool_count]
            .iter()
            .any(|c| c.device_position_m.is_some())
    }

    /// Runs one tick at time `now_us` (clock read again after the step for timing).
    /// Allocation-free, lock-free, no logging.
    pub fn tick(&mut self, now_us: u64, clock: &impl Clock) -> Flow {
        if self.stop_requested() {
            return Flow::Stop;
        }
        if self.stats.window.ticks == 0 && self.state.ticks == 0 {
            self.stats.window.start_us = now_us;
        }
        // 1. Commands.
        self.drain_commands();
        // 2. Latest pose of every tool.
        let reads = self.read_poses(now_us);
        // 3. Step (every tool's contact in the same tick).
        let (out, t1) = self.step_body(clock);
        // 4. Guard and hand out each tool's force.
        let forces = self.hand_out_forces(out.as_ref(), &reads, clock);
        self.state.ticks += 1;
        self.stats.window.ticks += 1;
        // 5. Snapshot for viewers.
        if self.state.ticks.is_multiple_of(self.params.snapshot_every)
            && self.shared.watchers.load(Ordering::Relaxed) > 0
        {
            self.publish_snapshot(&forces);
        }
        // 6. Statistics.
        if self.state.ticks.is_multiple_of(self.params.stats_every) {
            self.publish_stats(t1, &forces);
        }
        Flow::Continue
    }

    /// On a stop request: pushes the final zero force to every tool, marks the servo finished,
    /// true.
    fn stop_requested(&mut self) -> bool {
        if !self.shared.stop.load(Ordering::Acquire) {
            return false;
        }
        for (tool, last) in self.ends.tools.iter_mut().zip(self.state.last_seq) {
            let _ = tool.forces.push(ForceOut {
                seq: last.unwrap_or(0),
                ..ForceOut::default()
            });
        }
        self.shared.finished.store(true, Ordering::Release);
        true
    }

    /// Applies the queued commands (wait-free ring).
    fn drain_commands(&mut self) {
        while let Ok(cmd) = self.ends.commands.pop() {
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
                        let watched = self.shared.watchers.load(Ordering::Relaxed) != 0;
                        self.applied.note(
                            point_m,
                            force_n,
                            duration_s,
                            self.state.sim_time_s,
                            watched,
                        );
                    }
                }
            }
        }
    }

    /// Reads every tool slot's latest pose ([`Self::read_pose`]); any tool silent makes the
    /// session's `device_silent`.
    fn read_poses(&mut self, now_us: u64) -> [PoseRead; MAX_TOOLS] {
        let mut reads = [PoseRead::default(); MAX_TOOLS];
        for (k, read) in reads.iter_mut().enumerate().take(self.state.tool_count) {
            *read = self.read_pose(k, now_us);
        }
        self.state.device_silent = self.state.silent.iter().any(|&s| s);
        reads
    }

    /// Reads tool slot `k`'s latest pose (triple buffer, wait-free) into the tick's input; a
    /// connected device silent for longer than the limit leaves the scene until its next
    /// sample (its contact released; the other tools continue).
    fn read_pose(&mut self, k: usize, now_us: u64) -> PoseRead {
        let ends = &mut self.ends.tools[k];
        ends.pose.update();
        let pose = *ends.pose.output_buffer();
        let fresh = pose.connected && self.state.last_seq[k] != Some(pose.seq);
        // A device that stopped sending (a stalled bridge) must not keep pressing with its
        // last pose: past the silence limit it leaves the scene until its next sample.
        let silent = pose.connected
            && !fresh
            && now_us.saturating_sub(pose.received_us) > self.params.device_silence_us;
        if silent && !self.state.silent[k] {
            self.stats.device_silences += 1;
            self.stats.tools[k].device_silences += 1;
        }
        self.state.silent[k] = silent;
        self.state.current[k] = if pose.connected && !silent {
            TickInput {
                device_position_m: Some(pose.position_m),
                device_velocity_m_per_s: pose.velocity_m_per_s,
            }
        } else {
            TickInput::default()
        };
        if fresh {
            self.state.last_seq[k] = Some(pose.seq);
            self.stats.device_samples += 1;
            self.stats.tools[k].device_samples += 1;
        }
        PoseRead { pose, fresh }
    }

    /// Steps the body unless quarantined (a model error quarantines it) and records the step
    /// time. Returns the output and the clock after the step, µs.
    fn step_body(&mut self, clock: &impl Clock) -> (Option<[TickOutput; MAX_TOOLS]>, u64) {
        let t0 = clock.now_us();
        let n = self.state.tool_count;
        let mut outputs = [TickOutput::default(); MAX_TOOLS];
        let out = if self.state.fault.is_none() {
            match self
                .body
                .tick_tools(&self.state.current[..n], &mut outputs[..n])
            {
                Ok(()) => {
                    self.state.sim_time_s = outputs[0].sim_time_s;
                    Some(outputs)
                }
                Err(e) => {
                    self.state.fault = Some(match e {
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
        self.stats.record_step(t1 - t0);
        (out, t1)
    }

    /// Guards each tool's force ([`Self::hand_out_force`]); the session counts a contact tick
    /// when any tool is in contact, and its peak force is any tool's.
    fn hand_out_forces(
        &mut self,
        out: Option<&[TickOutput; MAX_TOOLS]>,
        reads: &[PoseRead; MAX_TOOLS],
        clock: &impl Clock,
    ) -> [ForceOut; MAX_TOOLS] {
        let mut forces = [ForceOut::default(); MAX_TOOLS];
        for (k, force) in forces.iter_mut().enumerate().take(self.state.tool_count) {
            *force = self.hand_out_force(k, out.map(|o| o[k]), reads[k], clock);
        }
        let any_contact = forces.iter().any(|f| f.in_contact);
        self.stats.contact_ticks += u64::from(any_contact);
        forces
    }

    /// Guards tool slot `k`'s force (a non-finite one, or none, is zero) and pushes it to the
    /// slot's forwarder ring when it answers a fresh sample, recording the pose-to-force
    /// latency.
    fn hand_out_force(
        &mut self,
        k: usize,
        out: Option<TickOutput>,
        read: PoseRead,
        clock: &impl Clock,
    ) -> ForceOut {
        let mut force = ForceOut {
            seq: read.pose.seq,
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
        let magnitude = force.force_n.length();
        self.stats.peak_force_n = self.stats.peak_force_n.max(magnitude);
        let tool = &mut self.stats.tools[k];
        tool.peak_force_n = tool.peak_force_n.max(magnitude);
        tool.contact_ticks += u64::from(force.in_contact);
        if read.fresh {
            // A full ring means the forwarder is stalled; dropping is the safe choice (the
            // bridge's watchdog ramps the force down).
            let _ = self.ends.tools[k].forces.push(force);
            let done = clock.now_us();
            self.stats
                .record_pose_to_force(k, done.saturating_sub(read.pose.received_us));
        }
        force
    }

    /// Writes and publishes a surface snapshot (within the capacity sized by
    /// [`super::channels`]: no allocation), then drops the loads it reported as ended.
    fn publish_snapshot(&mut self, forces: &[ForceOut; MAX_TOOLS]) {
        let snap = self.ends.snapshot.input_buffer_mut();
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
        snap.tick = self.state.ticks;
        snap.sim_time_s = self.state.sim_time_s;
        let d = self.body.write_surface_positions(&mut snap.positions_m);
        snap.max_displacement_m = d;
        snap.probe_m = match self.state.current[0].device_position_m {
            Some(p) => p,
            None => DVec3::NAN,
        };
        snap.force_n = forces[0].force_n;
        snap.in_contact = forces[0].in_contact;
        snap.tool_count = self.state.tool_count;
        for (k, t) in snap.tools.iter_mut().enumerate() {
            let p = self.state.current[k].device_position_m;
            *t = super::ToolProbeSnapshot {
                connected: p.is_some(),
                probe_m: p.unwrap_or(DVec3::NAN),
                force_n: forces[k].force_n,
                in_contact: forces[k].in_contact,
            };
        }
        self.applied.copy_to(snap);
        self.ends.snapshot.publish();
        // Reported once after they ended: drop them.
        self.applied.prune(self.state.sim_time_s);
    }

    /// Closes the statistics window ending at `t1` µs: judges the overrun and publishes the
    /// statistics.
    fn publish_stats(&mut self, t1: u64, forces: &[ForceOut; MAX_TOOLS]) {
        self.lend_workers();
        let body = self.body.stats();
        self.stats.max_displacement_m = self.stats.max_displacement_m.max(body.max_displacement_m);
        let elapsed_us = t1.saturating_sub(self.stats.window.start_us).max(1);
        let rate = self.stats.window.ticks as f64 * 1e6 / elapsed_us as f64;
        self.stats.window.start_us = t1;
        self.stats.window.ticks = 0;
        self.judge_overrun(rate, elapsed_us, t1);
        let s = &self.state;
        let tools = std::array::from_fn(|k| super::ToolStatsSnapshot {
            connected: s.current[k].device_position_m.is_some() || s.silent[k],
            in_contact: forces[k].in_contact,
            force_n: forces[k].force_n.length(),
            device_silent: s.silent[k],
            ..self.stats.tools[k].snapshot()
        });
        *self.ends.stats.input_buffer_mut() = super::StatsSnapshot {
            sim_time_s: s.sim_time_s,
            in_contact: forces.iter().any(|f| f.in_contact),
            tool_count: s.tool_count as u32,
            tools,
            fault: s.fault,
            device_silent: s.device_silent,
            overrunning: s.judge.overrunning,
            demoted: s.demoted,
            threads: self.threads,
            pool_wait_us_max: self.pool.as_ref().map_or(0, |p| p.stats().longest_wait_us),
            ..self.stats.snapshot(s.ticks, rate, body)
        };
        self.ends.stats.publish();
    }

    /// Judges the window of `elapsed_us` ending at `t1` µs, at `rate` Hz (the first window
    /// includes start-up: not judged); quarantines under the `degrade` policy.
    fn judge_overrun(&mut self, rate: f64, elapsed_us: u64, t1: u64) {
        let Some(limit) = self.params.overrun else {
            return;
        };
        if self.state.ticks <= self.params.stats_every {
            return;
        }
        let judge = &mut self.state.judge;
        let window_start = t1.saturating_sub(elapsed_us);
        judge.slow_since_us = if rate < limit.min_rate_hz {
            Some(judge.slow_since_us.unwrap_or(window_start))
        } else {
            None
        };
        let slow_for = judge.slow_since_us.map_or(0, |s| t1.saturating_sub(s));
        judge.overrunning = slow_for >= limit.for_us;
        if judge.overrunning && limit.degrade && self.state.fault.is_none() {
            self.state.fault = Some(
                "the servo cannot keep its rate on this machine (overrun policy \"degrade\"): session quarantined (zero force)",
            );
        }
    }
}
