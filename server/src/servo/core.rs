//! [`ServoCore`]: the servo's state and its allocation-, lock- and log-free [`ServoCore::tick`].

use std::sync::Arc;
use std::sync::atomic::Ordering;

use haptic_model::body::{SoftBody, TickInput};
use haptic_model::{DVec3, ModelError};
use hdrhistogram::Histogram;

use super::{
    APPLIED_LOAD_CAPACITY, AppliedLoad, Clock, Command, Flow, ForceOut, LatencyBuckets, Pose,
    ServoEnds, SessionShared, Snapshot, StatsSnapshot,
};

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
    /// Overruns, maintained by the loop's [`super::Pacer`].
    pub overruns: u64,
}

/// Default silence limit of a connected device, µs (50 ms: five times the bridge watchdog's
/// fresh window; issue 16).
pub const DEFAULT_DEVICE_SILENCE_US: u64 = 50_000;

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
    /// from [`super::channels`] for this body (the snapshot buffers are sized for its surface).
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
