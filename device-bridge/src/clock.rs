//! Time sources for the bridge: the [`Clock`] trait, a real [`MonotonicClock`] and a
//! [`ManualClock`] that tests advance by hand.
//!
//! Neighbours: the device loop in [`crate::link`] reads the clock every tick and sleeps to absolute
//! deadlines through it; the pure [`crate::guard`] functions take `now_us` values read from it, so
//! the watchdog is tested at exact thresholds without sleeping (devices.md section 5.1: never
//! assert wall-clock timing on the shared 2-core machines).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// A monotonic microsecond clock shared by the device thread and the network task.
pub trait Clock: Send + Sync {
    /// Microseconds since the clock's origin (monotonic, never decreases).
    fn now_us(&self) -> u64;

    /// Blocks the calling (device) thread until `now_us() >= deadline_us`.
    ///
    /// Returns at once when the deadline has passed. A manual clock jumps to the deadline
    /// instead of sleeping.
    fn sleep_until_us(&self, deadline_us: u64);
}

/// Real time: microseconds since construction, measured with [`Instant`]; sleeps with
/// `spin_sleep` (native sleep, then a short spin) for sub-millisecond accuracy.
#[derive(Debug, Clone, Copy)]
pub struct MonotonicClock {
    origin: Instant,
}

impl MonotonicClock {
    /// A clock whose zero is now.
    pub fn new() -> Self {
        Self {
            origin: Instant::now(),
        }
    }
}

impl Default for MonotonicClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for MonotonicClock {
    fn now_us(&self) -> u64 {
        u64::try_from(self.origin.elapsed().as_micros()).unwrap_or(u64::MAX)
    }

    fn sleep_until_us(&self, deadline_us: u64) {
        spin_sleep::sleep_until(self.origin + Duration::from_micros(deadline_us));
    }
}

/// A clock that only moves when told to. Clones share the same time, so a test keeps one clone
/// and hands another to the code under test.
#[derive(Debug, Clone, Default)]
pub struct ManualClock {
    now_us: Arc<AtomicU64>,
}

impl ManualClock {
    /// A manual clock reading `start_us` microseconds.
    pub fn new(start_us: u64) -> Self {
        Self {
            now_us: Arc::new(AtomicU64::new(start_us)),
        }
    }

    /// Sets the time to `now_us` microseconds (may move backwards; tests only).
    pub fn set_us(&self, now_us: u64) {
        self.now_us.store(now_us, Ordering::SeqCst);
    }

    /// Advances the time by `dt_us` microseconds.
    pub fn advance_us(&self, dt_us: u64) {
        self.now_us.fetch_add(dt_us, Ordering::SeqCst);
    }
}

impl Clock for ManualClock {
    fn now_us(&self) -> u64 {
        self.now_us.load(Ordering::SeqCst)
    }

    fn sleep_until_us(&self, deadline_us: u64) {
        self.now_us.fetch_max(deadline_us, Ordering::SeqCst);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_clock_advances_and_jumps_to_deadlines() {
        let c = ManualClock::new(5);
        let shared = c.clone();
        c.advance_us(10);
        assert_eq!(shared.now_us(), 15);
        shared.sleep_until_us(1_000);
        assert_eq!(c.now_us(), 1_000);
        // A past deadline does not move time backwards.
        c.sleep_until_us(10);
        assert_eq!(c.now_us(), 1_000);
    }

    #[test]
    fn monotonic_clock_never_decreases() {
        let c = MonotonicClock::new();
        let a = c.now_us();
        c.sleep_until_us(a + 200);
        assert!(c.now_us() >= a + 200);
    }
}
