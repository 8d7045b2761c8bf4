//! The device thread: one tick per period at absolute deadlines (read, deadband, guard,
//! write); nothing on the per-tick path allocates, locks for longer than a copy, or logs.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use tokio::sync::mpsc;

use crate::clock::Clock;
use crate::device::{DeviceError, DeviceSpec, DeviceState, HapticDevice, PressAxis, vec3};
use crate::guard::{ForceGuard, GuardCommand, GuardState, GuardStats, Limits};
use crate::record::TickRecord;

use super::shared::{OutSample, ReceivedForce, Shared};
use super::{BridgeConfig, RearmMode};

/// Rows reserved up front when recording: 120 s at the device rate.
const RECORD_RESERVE_S: f64 = 120.0;
/// Consecutive failed device reads tolerated before the device is declared faulty, in us
/// (devices.md S2: zero at once, fault after 20 ms).
const DEVICE_FAULT_US: u64 = 20_000;

#[derive(Debug, Default)]
pub(super) struct DeviceLoopStats {
    pub(super) ticks: u64,
    pub(super) overruns: u64,
    pub(super) samples_dropped: u64,
    pub(super) samples_suppressed: u64,
    pub(super) peak_force_n: f64,
    pub(super) max_depth_m: f64,
    pub(super) final_force_n: [f64; 3],
    pub(super) guard: GuardStats,
    pub(super) limits: Option<Limits>,
    pub(super) device_errors: u64,
    pub(super) device_fault: Option<String>,
    pub(super) duration_s: f64,
    pub(super) records: Vec<TickRecord>,
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

/// The device thread's state between ticks: what [`device_loop`] set up before the first tick
/// and carries from one tick to the next. Built once per run; a tick only copies into it.
struct DeviceThread<'a> {
    device: Box<dyn HapticDevice>,
    clock: Arc<dyn Clock>,
    shared: Arc<Shared>,
    samples: mpsc::Sender<OutSample>,
    config: &'a BridgeConfig,
    spec: DeviceSpec,
    period_us: u64,
    guard: ForceGuard,
    axis: Option<PressAxis>,
    st: DeviceLoopStats,
    start_us: u64,
    stop_at_us: Option<u64>,
    deadline_us: u64,
    /// Sequence number of the last sample sent.
    seq: u64,
    /// First failed read of the current run of failures.
    failing_since_us: Option<u64>,
    /// Re-arm button presses already acted on.
    presses_seen: u64,
    /// The device's output is disabled in hardware (devices.md S5).
    output_disabled: bool,
    deadband: Option<Deadband>,
}

impl<'a> DeviceThread<'a> {
    /// Everything the loop needs before its first tick (the recording buffer reserved here).
    fn new(
        device: Box<dyn HapticDevice>,
        clock: Arc<dyn Clock>,
        shared: Arc<Shared>,
        samples: mpsc::Sender<OutSample>,
        config: &'a BridgeConfig,
    ) -> Self {
        let spec = device.spec().clone();
        let period_us = ((1e6 / config.rate_hz).round() as u64).max(1);
        let guard = ForceGuard::new(config.guard);
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
        let presses_seen = match &config.rearm {
            RearmMode::Operator(b) => b.presses(),
            RearmMode::Auto => 0,
        };
        let deadband = config.deadband.map(|k| Deadband {
            k,
            last_sent_us: None,
            sent_position_m: [0.0; 3],
            sent_force_n: [0.0; 3],
        });
        Self {
            device,
            clock,
            shared,
            samples,
            config,
            spec,
            period_us,
            guard,
            axis,
            st,
            start_us,
            stop_at_us,
            deadline_us: start_us,
            seq: 0,
            failing_since_us: None,
            presses_seen,
            output_disabled: false,
            deadband,
        }
    }

    /// The device finished, the hard stop passed, or the network side asked to stop.
    fn stop_requested(&self, now: u64) -> bool {
        self.shared.stop.load(Ordering::Acquire)
            || self.device.finished(now)
            || self.stop_at_us.is_some_and(|t| now >= t)
    }

    /// One tick with a good pose: read the slot, send the sample (unless the deadband keeps it
    /// back), re-arm if due, render the guarded force, count it and record the row.
    fn tick(&mut self, now: u64, state: DeviceState) {
        self.failing_since_us = None;
        let (link_up, latest, limits) = {
            let s = self.shared.slot();
            (s.link_up, s.latest, s.limits)
        };
        self.send_sample(now, state, latest);
        self.guard.set_app_limits(limits);
        self.rearm();
        let f = self.render(now, link_up, latest, &state);
        let st = &mut self.st;
        st.final_force_n = f;
        st.peak_force_n = st.peak_force_n.max(vec3::norm(f));
        if let Some(a) = self.axis {
            let d = vec3::dot(vec3::sub(state.position_m, a.start_m), a.direction);
            st.max_depth_m = st.max_depth_m.max(d);
        }
        if self.config.record {
            self.record(now, &state, f, latest);
        }
    }

    /// Hands the sample to the network task (never blocking: a full queue drops and counts
    /// it), or counts it as kept back by the deadband.
    fn send_sample(&mut self, now: u64, state: DeviceState, latest: Option<ReceivedForce>) {
        let predicted = latest.map_or([0.0; 3], |r| {
            crate::guard::extrapolate(
                r.force_n,
                &r.stiffness_n_per_m,
                r.sample_position_m,
                state.position_m,
                self.config.guard.max_extrapolation_m,
            )
        });
        let send = self
            .deadband
            .as_ref()
            .is_none_or(|d| d.should_send(now, state.position_m, predicted));
        if send {
            self.seq += 1;
            if let Some(d) = self.deadband.as_mut() {
                d.last_sent_us = Some(now);
                d.sent_position_m = state.position_m;
                d.sent_force_n = predicted;
            }
            if let Err(mpsc::error::TrySendError::Full(_)) = self.samples.try_send(OutSample {
                seq: self.seq,
                state,
            }) {
                self.st.samples_dropped += 1;
            }
        } else {
            self.st.samples_suppressed += 1;
        }
    }

    /// Asks the guard to re-arm: at once when it is ready (`--rearm auto`), or on a new press
    /// of the operator's button.
    fn rearm(&mut self) {
        match &self.config.rearm {
            RearmMode::Auto => {
                if self.guard.state() == GuardState::ReadyToRearm {
                    self.guard.request_rearm();
                }
            }
            RearmMode::Operator(b) => {
                let p = b.presses();
                if p != self.presses_seen {
                    self.presses_seen = p;
                    self.guard.request_rearm();
                }
            }
        }
    }

    /// The guard's force for the latest command, written to the device (with the hardware
    /// output switched off while the guard is latched); returns the force written, N.
    fn render(
        &mut self,
        now: u64,
        link_up: bool,
        latest: Option<ReceivedForce>,
        state: &DeviceState,
    ) -> [f64; 3] {
        let cmd = latest.map(|r| GuardCommand {
            generation: r.generation,
            seq: r.seq,
            force_n: r.force_n,
            stiffness_n_per_m: r.stiffness_n_per_m,
            position_m: r.sample_position_m,
            sample_time_us: r.sample_time_us,
        });
        let f = self
            .guard
            .filter(now, link_up, cmd.as_ref(), state, &self.spec);
        let disabled = self.guard.state().is_disabled();
        if disabled != self.output_disabled {
            // devices.md S5: disabled in hardware too, while latched.
            self.output_disabled = disabled;
            if self.device.set_output_enabled(!disabled).is_err() {
                self.st.device_errors += 1;
            }
        }
        self.shared
            .guard_state
            .store(self.guard.state().code(), Ordering::Release);
        if self.device.write_force(f).is_err() {
            self.st.device_errors += 1;
        }
        f
    }

    /// Appends this tick's row to the pre-reserved recording.
    fn record(
        &mut self,
        now: u64,
        state: &DeviceState,
        f: [f64; 3],
        latest: Option<ReceivedForce>,
    ) {
        let guard = &self.guard;
        let in_use = matches!(
            guard.state(),
            GuardState::Fresh | GuardState::Rising | GuardState::Ramp
        );
        let used = latest.filter(|_| in_use);
        self.st.records.push(TickRecord {
            t_s: now.saturating_sub(self.start_us) as f64 * 1e-6,
            position_m: state.position_m,
            force_n: f,
            in_contact: used.is_some_and(|r| r.in_contact),
            rtt_us: used.and_then(|r| r.rtt_us),
            age_us: guard.held_age_us(),
            state: guard.state().name(),
            command_n: guard.command_n(),
        });
    }

    /// A failed read (devices.md S2: never trust a stale pose): zero now; true when the reads
    /// have failed for [`DEVICE_FAULT_US`] and the loop must give up.
    fn read_failed(&mut self, now: u64, e: DeviceError) -> bool {
        self.st.device_errors += 1;
        self.guard.reset();
        let _ = self.device.write_force([0.0; 3]);
        self.st.final_force_n = [0.0; 3];
        let since = *self.failing_since_us.get_or_insert(now);
        if now.saturating_sub(since) >= DEVICE_FAULT_US {
            self.st.device_fault = Some(e.to_string());
            return true;
        }
        false
    }

    /// Sleeps until the next deadline; an overrun skips the missed deadlines instead of
    /// bursting to catch up.
    fn wait_next_deadline(&mut self) {
        self.deadline_us += self.period_us;
        let after = self.clock.now_us();
        if after > self.deadline_us {
            self.st.overruns += 1;
            self.deadline_us += ((after - self.deadline_us) / self.period_us + 1) * self.period_us;
        }
        self.clock.sleep_until_us(self.deadline_us);
    }

    /// Zero force, `safe_stop`, and the run's totals.
    fn finish(mut self) -> DeviceLoopStats {
        if self.device.write_force([0.0; 3]).is_err() {
            self.st.device_errors += 1;
        }
        self.device.safe_stop();
        let mut st = self.st;
        st.final_force_n = [0.0; 3];
        st.guard = self.guard.stats();
        st.limits = Some(self.guard.limits());
        st.duration_s = self.clock.now_us().saturating_sub(self.start_us) as f64 * 1e-6;
        st
    }
}

/// The device thread: one tick per period at absolute deadlines until the device finishes, the
/// hard stop passes, or `shared.stop` is set. Writes zero and calls `safe_stop` on the way out.
/// Nothing in the tick allocates (except growing a full recording buffer), logs or awaits.
pub(super) fn device_loop(
    device: Box<dyn HapticDevice>,
    clock: Arc<dyn Clock>,
    shared: Arc<Shared>,
    samples: mpsc::Sender<OutSample>,
    config: &BridgeConfig,
) -> DeviceLoopStats {
    let mut t = DeviceThread::new(device, clock, shared, samples, config);
    loop {
        let now = t.clock.now_us();
        if t.stop_requested(now) {
            break;
        }
        t.st.ticks += 1;
        match t.device.read(now) {
            Ok(state) => t.tick(now, state),
            Err(e) => {
                if t.read_failed(now, e) {
                    break;
                }
            }
        }
        t.wait_next_deadline();
    }
    t.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::ManualClock;
    use crate::counting_alloc::counted;
    use crate::sim::{Script, SimProbe};

    /// The device loop's per-tick path (slot copy, sample hand-off, deadband, guard with its
    /// passivity controller and re-arm, force write, statistics, a pre-reserved recording)
    /// allocates nothing once the sample queue has made its blocks: 3 000 ticks of a scripted
    /// press answered by a spring-like server, with a link loss in the middle (watchdog, latch,
    /// automatic re-arm), counted by the allocator.
    #[test]
    fn the_device_tick_allocates_nothing() {
        let spec = DeviceSpec::sim_default();
        let script = Script::Press {
            start_m: [0.0, 0.0, 0.0],
            direction: [0.0, 0.0, -1.0],
            depth_m: 0.01,
            speed_m_per_s: 0.01,
            hold_s: 1.0,
        };
        let probe = SimProbe::new(script, spec.clone()).unwrap();
        let clock = ManualClock::new(0);
        let shared = Arc::new(Shared::default());
        let (tx, mut rx) = mpsc::channel(4_096);
        let mut config = BridgeConfig::new("http://127.0.0.1:1", "s", &spec);
        config.record = true;
        config.deadband = Some(0.07);
        let mut t = DeviceThread::new(
            Box::new(probe),
            Arc::new(clock.clone()),
            shared.clone(),
            tx,
            &config,
        );
        // A server answering each new sample (sequence number) with a 200 N/m wall below
        // z = -2 mm; the slot's generation moves with every answer, as the network task's does.
        let answer = |now: u64, position_m: [f64; 3], seq: u64, link_up: bool| {
            let depth_m = (-0.002 - position_m[2]).max(0.0);
            let mut slot = shared.slot();
            slot.link_up = link_up;
            let answered = slot.latest.map_or(0, |r| r.seq);
            if link_up && seq > answered {
                slot.latest = Some(ReceivedForce {
                    generation: seq,
                    seq,
                    force_n: [0.0, 0.0, 200.0 * depth_m],
                    stiffness_n_per_m: [0.0; 9],
                    in_contact: depth_m > 0.0,
                    sample_time_us: now,
                    sample_position_m: position_m,
                    rtt_us: Some(300),
                });
            }
        };
        let mut ticks = |t: &mut DeviceThread<'_>, n: u64, link_up: bool| {
            for _ in 0..n {
                let now = t.clock.now_us();
                let state = t.device.read(now).expect("the simulated probe reads");
                t.tick(now, state);
                answer(now, state.position_m, t.seq, link_up);
                t.wait_next_deadline();
                while rx.try_recv().is_ok() {}
            }
        };
        // Warm-up outside the count: tokio's bounded channel allocates its blocks of 32 slots as
        // the first samples go through and recycles them from then on (measured: one allocation
        // in the first 500 ticks after a 10-tick warm-up, at about the 40th sample, none after).
        ticks(&mut t, 500, true);
        let (_, allocations) = counted(|| {
            ticks(&mut t, 1_500, true);
            ticks(&mut t, 300, false);
            ticks(&mut t, 1_200, true);
        });
        let st = t.finish();
        assert_eq!(allocations, 0, "the device tick allocated");
        // The run exercised what it claims: contact force, a watchdog latch and a re-arm.
        assert!(
            st.peak_force_n > 0.5,
            "peak {} N {:?}",
            st.peak_force_n,
            st.guard
        );
        assert!(
            st.guard.watchdog_expired >= 1 && st.guard.rearms >= 1,
            "{:?}",
            st.guard
        );
        assert_eq!(st.records.len(), 3_500);
    }

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
