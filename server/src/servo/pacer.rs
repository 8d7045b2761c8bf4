//! Pacing of the servo loop: the clock, absolute deadlines ([`Pacer`]) and device pacing
//! ([`DevicePacer`]). Pure and clock-free where it can be: tests drive it with explicit times.

use std::time::Instant;

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
