//! Cores per session (issue 48 section 1): how many threads a session's tick gets, and the
//! daemon's reservation of cores for its running sessions.
//!
//! `[servo] threads = "auto"` gives a session the threads its body asks for
//! (`SoftBody::wants_threads`), limited by the cores no running session has reserved: the
//! machine's (`std::thread::available_parallelism`) or the `[servo] cpus` list's. A session that
//! cannot get its threads gets fewer (at least its servo thread) and never waits; where
//! `SCHED_FIFO` was asked for and refused it gets one (an unprotected worker preempted while it
//! holds a part would stall the servo). `threads = N` gives every session N. Either way the
//! session reserves what it got ([`CoreReservation`]) until its servo loop ends or it is
//! quarantined.
//!
//! An `"auto"` session lends out the tick-pool workers that the cores no other session holds
//! cannot hold beside the threads its body keeps busy beside its tick
//! (`SoftBody::background_threads`: a region cache being built; [`ThreadShare::working`]).
//! They stay parked, and work again once the background work is done or the other sessions
//! have given their cores back (two busy `SCHED_FIFO` threads and a region worker or another
//! session's servo on two cores starve one of them).

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::config::{MAX_SERVO_THREADS, ServoThreads};

/// The cores the daemon shares out and how many its running sessions hold.
#[derive(Debug)]
pub struct CoreBudget {
    capacity: usize,
    reserved: Arc<AtomicUsize>,
}

/// The cores one session holds; given back when dropped. Lock-free: dropping it is one atomic
/// subtraction (the servo loop may drop it after a tick).
#[derive(Debug)]
pub struct CoreReservation {
    reserved: Arc<AtomicUsize>,
    cores: usize,
    first: usize,
    /// The budget's capacity under `threads = "auto"`; `None` under `threads = N`.
    capacity: Option<usize>,
}

/// How many of a session's tick threads work beside its body's background threads and the
/// other sessions' reservations ([`CoreReservation::share`]; module documentation).
#[derive(Debug, Clone)]
pub struct ThreadShare {
    threads: usize,
    /// The budget's capacity and every session's reservations (`"auto"` only).
    budget: Option<(usize, Arc<AtomicUsize>)>,
}

impl ThreadShare {
    /// All `threads` always work (one thread, a fixed count).
    pub fn fixed(threads: usize) -> Self {
        Self {
            threads: threads.max(1),
            budget: None,
        }
    }

    /// Threads of the tick that work while the body keeps `background` threads busy: under
    /// `"auto"` those the budget's cores not reserved by other sessions now hold beside them
    /// (at least the servo thread), under `threads = N` all. Always `1..=threads`; one atomic
    /// read (lock-free).
    pub fn working(&self, background: usize) -> usize {
        match &self.budget {
            Some((capacity, reserved)) => {
                let others = reserved
                    .load(Ordering::Acquire)
                    .saturating_sub(self.threads);
                let free = capacity.saturating_sub(others);
                self.threads.min(free.saturating_sub(background).max(1))
            }
            None => self.threads,
        }
    }
}

impl CoreReservation {
    /// Threads (cores) this reservation holds.
    pub fn cores(&self) -> usize {
        self.cores
    }

    /// Holds `cores` (at least 1) instead, giving the rest back (a tick pool that could not be
    /// created leaves its session on one thread).
    pub fn shrink_to(&mut self, cores: usize) {
        let keep = cores.clamp(1, self.cores);
        self.reserved.fetch_sub(self.cores - keep, Ordering::AcqRel);
        self.cores = keep;
    }

    /// How many of these cores' threads work beside the body's background threads and the
    /// other sessions.
    pub fn share(&self) -> ThreadShare {
        ThreadShare {
            threads: self.cores,
            budget: self.capacity.map(|c| (c, self.reserved.clone())),
        }
    }

    /// Cores other sessions held when this one was made: the session's servo takes the CPU at
    /// this position of the `cpus` list (modulo its length) and its workers the next ones.
    pub fn first(&self) -> usize {
        self.first
    }
}

impl Drop for CoreReservation {
    fn drop(&mut self) {
        self.reserved.fetch_sub(self.cores, Ordering::AcqRel);
    }
}

/// Threads of a session whose body wants `wants`, under `mode`, with `free` cores unreserved;
/// `fifo_refused`: `SCHED_FIFO` was asked for and refused. Always 1..=[`MAX_SERVO_THREADS`].
pub fn decide_threads(mode: ServoThreads, wants: usize, free: usize, fifo_refused: bool) -> usize {
    match mode {
        ServoThreads::Fixed(n) => n.clamp(1, MAX_SERVO_THREADS),
        ServoThreads::Auto if fifo_refused => 1,
        ServoThreads::Auto => wants.clamp(1, MAX_SERVO_THREADS).min(free.max(1)),
    }
}

impl CoreBudget {
    /// A budget of `capacity` cores (at least 1), none reserved.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            reserved: Arc::new(AtomicUsize::new(0)),
        }
    }

    /// The budget of a daemon pinned to `cpus` (their number), or of the whole machine when the
    /// list is empty (`available_parallelism`, 1 when unknown).
    pub fn for_cpus(cpus: &[usize]) -> Self {
        let capacity = if cpus.is_empty() {
            std::thread::available_parallelism().map_or(1, usize::from)
        } else {
            cpus.len()
        };
        Self::new(capacity)
    }

    /// Cores the budget shares out.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Cores the running sessions hold now (may exceed the capacity: fixed `threads = N` and the
    /// one servo thread every session has are never refused).
    pub fn reserved(&self) -> usize {
        self.reserved.load(Ordering::Acquire)
    }

    /// Decides a new session's threads ([`decide_threads`] with the cores free now) and reserves
    /// them, atomically against concurrent starts. Never waits. (A body's background threads
    /// are not reserved: the session lends them its workers, [`ThreadShare`].)
    pub fn reserve(&self, mode: ServoThreads, wants: usize, fifo_refused: bool) -> CoreReservation {
        let mut now = self.reserved.load(Ordering::Acquire);
        loop {
            let free = self.capacity.saturating_sub(now);
            let cores = decide_threads(mode, wants, free, fifo_refused);
            match self.reserved.compare_exchange_weak(
                now,
                now + cores,
                Ordering::AcqRel,
                Ordering::Acquire,
            ) {
                Ok(_) => {
                    return CoreReservation {
                        reserved: self.reserved.clone(),
                        cores,
                        first: now,
                        capacity: matches!(mode, ServoThreads::Auto).then_some(self.capacity),
                    };
                }
                Err(actual) => now = actual,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_takes_what_is_free_and_never_less_than_one() {
        let auto = ServoThreads::Auto;
        assert_eq!(decide_threads(auto, 2, 2, false), 2);
        assert_eq!(decide_threads(auto, 4, 2, false), 2);
        assert_eq!(decide_threads(auto, 2, 1, false), 1);
        assert_eq!(decide_threads(auto, 2, 0, false), 1);
        assert_eq!(decide_threads(auto, 0, 8, false), 1);
        assert_eq!(decide_threads(auto, 2, 2, true), 1, "FIFO refused");
        assert_eq!(decide_threads(ServoThreads::Fixed(3), 1, 0, true), 3);
    }

    #[test]
    fn auto_lends_the_workers_that_other_sessions_and_background_threads_leave_no_core() {
        let working = |cpus: usize, wants: usize, background: usize| {
            let r = CoreBudget::new(cpus).reserve(ServoThreads::Auto, wants, false);
            (r.cores(), r.share().working(background))
        };
        // A body building its region cache keeps a core busy: on two cores its second thread
        // is lent out until the cache is done, on three both work.
        assert_eq!(working(2, 2, 1), (2, 1));
        assert_eq!(working(2, 2, 0), (2, 2));
        assert_eq!(working(3, 2, 1), (2, 2));
        assert_eq!(working(4, 4, 2), (4, 2));
        assert_eq!(working(1, 2, 1), (1, 1));
        assert_eq!(working(2, 2, 5), (2, 1), "never less than the servo thread");
        // Beside another session's core: what the others hold counts, as it changes.
        let budget = CoreBudget::new(3);
        let a = budget.reserve(ServoThreads::Auto, 1, false);
        let b = budget.reserve(ServoThreads::Auto, 2, false);
        assert_eq!((b.cores(), b.share().working(1)), (2, 1));
        drop(a);
        assert_eq!(b.share().working(1), 2, "a gave its core back");
        // Sessions started on a full budget: the one with workers lends them out meanwhile.
        let budget = CoreBudget::new(2);
        let a = budget.reserve(ServoThreads::Auto, 2, false);
        let share = a.share();
        assert_eq!(share.working(0), 2);
        let b = budget.reserve(ServoThreads::Auto, 2, false);
        assert_eq!((b.cores(), b.share().working(0)), (1, 1));
        assert_eq!(share.working(0), 1, "b's servo thread needs a core");
        drop(b);
        assert_eq!(share.working(0), 2);
        drop(a);
        assert_eq!(share.working(0), 2, "the budget's whole capacity");
        // A fixed count always works whole.
        let fixed = CoreBudget::new(2).reserve(ServoThreads::Fixed(2), 2, false);
        assert_eq!(fixed.share().working(1), 2);
        assert_eq!(ThreadShare::fixed(3).working(2), 3);
        let mut shrunk = CoreBudget::new(2).reserve(ServoThreads::Auto, 2, false);
        shrunk.shrink_to(1);
        assert_eq!(shrunk.share().working(0), 1);
    }

    #[test]
    fn reservations_add_up_and_are_given_back_on_drop() {
        let budget = CoreBudget::new(2);
        let a = budget.reserve(ServoThreads::Auto, 2, false);
        assert_eq!((a.cores(), a.first(), budget.reserved()), (2, 0, 2));
        let b = budget.reserve(ServoThreads::Auto, 2, false);
        assert_eq!((b.cores(), b.first(), budget.reserved()), (1, 2, 3));
        drop(a);
        assert_eq!(budget.reserved(), 1);
        let c = budget.reserve(ServoThreads::Auto, 2, false);
        assert_eq!(c.cores(), 1, "one core is free");
        drop((b, c));
        assert_eq!(budget.reserved(), 0);
        assert_eq!(budget.reserve(ServoThreads::Auto, 2, false).cores(), 2);
        assert_eq!(budget.reserved(), 0, "the unnamed reservation was dropped");
    }
}
