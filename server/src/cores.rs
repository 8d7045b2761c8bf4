//! Cores per session (issue 48 section 1): how many threads a session's tick gets, and the
//! daemon's reservation of cores for its running sessions.
//!
//! `[servo] threads = "auto"` gives a session the threads its body asks for
//! (`SoftBody::wants_threads`, at most the budget's cores): the machine's
//! (`std::thread::available_parallelism`) or the `[servo] cpus` list's. It reserves ("holds")
//! those of them that cores no running session holds can take, at least its servo thread, and
//! never waits; where `SCHED_FIFO` was asked for and refused it gets one thread (an unprotected
//! worker preempted while it holds a part would stall the servo). `threads = N` gives every
//! session N and holds them. Either way the session holds its cores ([`CoreReservation`])
//! until its servo loop ends or it is quarantined.
//!
//! An `"auto"` session takes the cores it wants but does not hold as other sessions give them
//! back (at a statistics window, first come first served), and lends out tick-pool workers
//! ([`ThreadShare::working`]): while the sessions hold more cores than the budget has (every
//! session holds its servo thread's), as many workers as that excess, shared among the
//! sessions with workers; and those that the cores left by the other sessions' working threads
//! cannot hold beside the threads its body keeps busy beside its tick
//! (`SoftBody::background_threads`: a region cache being built). Lent workers stay parked,
//! and work again once the excess or the background work is gone (two busy `SCHED_FIFO`
//! threads and a region worker or another session's servo on two cores starve one of them).
//! Workers keep the CPUs of the `cpus` list chosen at the session's start.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::config::{MAX_SERVO_THREADS, ServoThreads};

/// The cores the daemon shares out and how many its running sessions hold.
#[derive(Debug)]
pub struct CoreBudget {
    capacity: usize,
    reserved: Arc<AtomicUsize>,
    /// Workers the `"auto"` sessions lend out because the sessions hold more cores than there
    /// are (at most that excess; [`ThreadShare::working`]).
    lent: Arc<AtomicUsize>,
}

/// The cores one session holds; given back when dropped. Lock-free: dropping it is four atomic
/// operations (the servo loop may drop it after a tick).
#[derive(Debug)]
pub struct CoreReservation {
    reserved: Arc<AtomicUsize>,
    lent: Arc<AtomicUsize>,
    /// This session's part of `lent`; [`RELEASED`] once given back.
    my_lent: Arc<AtomicUsize>,
    /// Threads of the session's tick (its servo thread and pool workers).
    threads: usize,
    /// Cores held now, `1..=threads` (grows under `"auto"`, [`ThreadShare::working`]);
    /// [`RELEASED`] once given back.
    held: Arc<AtomicUsize>,
    first: usize,
    /// The budget's capacity under `threads = "auto"`; `None` under `threads = N`.
    capacity: Option<usize>,
}

/// `CoreReservation::held` and `my_lent` once the reservation is dropped: nothing more may be
/// taken or lent.
const RELEASED: usize = usize::MAX;

/// How many of a session's tick threads work beside its body's background threads and the
/// other sessions' reservations ([`CoreReservation::share`]; module documentation).
#[derive(Debug, Clone)]
pub struct ThreadShare {
    threads: usize,
    /// `"auto"` only.
    budget: Option<AutoShare>,
}

/// What an `"auto"` session's [`ThreadShare`] reads: the budget's capacity and counts, and
/// its own.
#[derive(Debug, Clone)]
struct AutoShare {
    capacity: usize,
    reserved: Arc<AtomicUsize>,
    lent: Arc<AtomicUsize>,
    held: Arc<AtomicUsize>,
    my_lent: Arc<AtomicUsize>,
}

impl ThreadShare {
    /// All `threads` always work (one thread, a fixed count).
    pub fn fixed(threads: usize) -> Self {
        Self {
            threads: threads.max(1),
            budget: None,
        }
    }

    /// Threads of the tick that work while the body keeps `background` threads busy. Under
    /// `"auto"` the session first holds as many of the cores it does not hold yet as are free;
    /// while the sessions hold more cores than the budget has, it lends out workers until as
    /// many are lent as that excess (not a worker from every session, only enough);
    /// of the rest, those work that the cores other sessions' working threads leave hold
    /// beside `background` (at least the servo thread). Under `threads = N` all work. Always
    /// `1..=threads`; lock-free (atomic reads, and compare-exchanges when counts change).
    pub fn working(&self, background: usize) -> usize {
        let Some(a) = &self.budget else {
            return self.threads;
        };
        let mine = take_free_cores(a, self.threads);
        let my_lent = lend_for_the_excess(a, mine);
        if a.held.load(Ordering::Acquire) == RELEASED {
            return 1;
        }
        let others_held = a.reserved.load(Ordering::Acquire).saturating_sub(mine);
        let others_lent = a.lent.load(Ordering::Acquire).saturating_sub(my_lent);
        let free = a
            .capacity
            .saturating_sub(others_held.saturating_sub(others_lent));
        (mine - my_lent).min(free.saturating_sub(background).max(1))
    }
}

/// Moves the budget's lent workers towards the excess of cores held over its capacity, one
/// of this session's workers at a time (it holds `mine` cores and always keeps its servo
/// thread): lends while fewer are lent, takes back while more are. Returns its workers lent.
fn lend_for_the_excess(a: &AutoShare, mine: usize) -> usize {
    loop {
        let my = a.my_lent.load(Ordering::Acquire);
        if my == RELEASED {
            return 0;
        }
        let excess = a
            .reserved
            .load(Ordering::Acquire)
            .saturating_sub(a.capacity);
        let lent = a.lent.load(Ordering::Acquire);
        if lent > excess && my > 0 {
            let back = a
                .my_lent
                .compare_exchange(my, my - 1, Ordering::AcqRel, Ordering::Acquire);
            if back.is_ok() {
                a.lent.fetch_sub(1, Ordering::AcqRel);
            }
        } else if lent < excess && my + 1 < mine {
            let claimed =
                a.lent
                    .compare_exchange(lent, lent + 1, Ordering::AcqRel, Ordering::Acquire);
            if claimed.is_ok()
                && a.my_lent
                    .compare_exchange(my, my + 1, Ordering::AcqRel, Ordering::Acquire)
                    .is_err()
            {
                // Released meanwhile: the claim is not this session's to keep.
                a.lent.fetch_sub(1, Ordering::AcqRel);
                return 0;
            }
        } else {
            return my;
        }
    }
}

/// Holds up to `threads` cores in all for the session of `a`, taking them from those of the
/// budget that no session holds; returns the cores held after (1 once released).
fn take_free_cores(a: &AutoShare, threads: usize) -> usize {
    let AutoShare {
        capacity,
        reserved,
        held,
        ..
    } = a;
    let capacity = *capacity;
    let mine = held.load(Ordering::Acquire);
    if mine == RELEASED {
        return 1;
    }
    if mine >= threads {
        return mine;
    }
    let mut now = reserved.load(Ordering::Acquire);
    let take = loop {
        let take = (threads - mine).min(capacity.saturating_sub(now));
        if take == 0 {
            return mine;
        }
        match reserved.compare_exchange_weak(now, now + take, Ordering::AcqRel, Ordering::Acquire) {
            Ok(_) => break take,
            Err(actual) => now = actual,
        }
    };
    if held
        .compare_exchange(mine, mine + take, Ordering::AcqRel, Ordering::Acquire)
        .is_ok()
    {
        return mine + take;
    }
    // Released meanwhile (or changed by a clone): give the cores back.
    reserved.fetch_sub(take, Ordering::AcqRel);
    match held.load(Ordering::Acquire) {
        RELEASED => 1,
        h => h.clamp(1, threads),
    }
}

impl CoreReservation {
    /// Threads of the session's tick: its servo thread and its pool's workers, those whose
    /// cores it does not hold yet included.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Cores this reservation holds now (`1..=threads`).
    pub fn cores(&self) -> usize {
        self.held.load(Ordering::Acquire).min(self.threads)
    }

    /// One thread instead (a tick pool that could not be created), giving the other cores
    /// held back.
    pub fn shrink_to_one(&mut self) {
        let held = self.held.swap(1, Ordering::AcqRel);
        self.reserved
            .fetch_sub(held.saturating_sub(1), Ordering::AcqRel);
        self.threads = 1;
    }

    /// How many of these threads work beside the body's background threads and the other
    /// sessions ([`ThreadShare::working`], which also takes the cores wanted as they come free).
    pub fn share(&self) -> ThreadShare {
        ThreadShare {
            threads: self.threads,
            budget: self.capacity.map(|capacity| AutoShare {
                capacity,
                reserved: self.reserved.clone(),
                lent: self.lent.clone(),
                held: self.held.clone(),
                my_lent: self.my_lent.clone(),
            }),
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
        let held = self.held.swap(RELEASED, Ordering::AcqRel);
        self.reserved.fetch_sub(held, Ordering::AcqRel);
        let lent = self.my_lent.swap(RELEASED, Ordering::AcqRel);
        self.lent.fetch_sub(lent, Ordering::AcqRel);
    }
}

/// Cores a session whose body wants `wants` threads holds under `mode` with `free` cores
/// unreserved (with `free` the budget's capacity: its threads); `fifo_refused`: `SCHED_FIFO` was
/// asked for and refused. Always 1..=[`MAX_SERVO_THREADS`].
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
            lent: Arc::new(AtomicUsize::new(0)),
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

    /// Decides a new session's threads ([`decide_threads`] with the budget's capacity) and the
    /// cores it holds ([`decide_threads`] with the cores free now), and reserves those,
    /// atomically against concurrent starts. Never waits. (A body's background threads are not
    /// reserved: the session lends them its workers, [`ThreadShare`].)
    pub fn reserve(&self, mode: ServoThreads, wants: usize, fifo_refused: bool) -> CoreReservation {
        let threads = decide_threads(mode, wants, self.capacity, fifo_refused);
        let mut now = self.reserved.load(Ordering::Acquire);
        loop {
            let free = self.capacity.saturating_sub(now);
            let cores = decide_threads(mode, wants, free, fifo_refused).min(threads);
            match self.reserved.compare_exchange_weak(
                now,
                now + cores,
                Ordering::AcqRel,
                Ordering::Acquire,
            ) {
                Ok(_) => {
                    return CoreReservation {
                        reserved: self.reserved.clone(),
                        lent: self.lent.clone(),
                        my_lent: Arc::new(AtomicUsize::new(0)),
                        threads,
                        held: Arc::new(AtomicUsize::new(cores)),
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
        assert_eq!(share.working(0), 1, "released: the servo thread only");
        // A fixed count always works whole.
        let fixed = CoreBudget::new(2).reserve(ServoThreads::Fixed(2), 2, false);
        assert_eq!(fixed.share().working(1), 2);
        assert_eq!(ThreadShare::fixed(3).working(2), 3);
        let budget = CoreBudget::new(2);
        let mut shrunk = budget.reserve(ServoThreads::Auto, 2, false);
        shrunk.shrink_to_one();
        assert_eq!((shrunk.threads(), shrunk.share().working(0)), (1, 1));
        assert_eq!(budget.reserved(), 1);
    }

    /// A session started while other sessions hold the cores it wants holds them once they
    /// are given back, first come first served, and a dropped reservation takes nothing more.
    #[test]
    fn auto_takes_the_cores_it_wants_as_other_sessions_give_them_back() {
        let auto = ServoThreads::Auto;
        let budget = CoreBudget::new(2);
        let a = budget.reserve(auto, 2, false);
        let b = budget.reserve(auto, 2, false);
        assert_eq!((b.threads(), b.cores(), budget.reserved()), (2, 1, 3));
        let share = b.share();
        assert_eq!((share.working(0), budget.reserved()), (1, 3), "none free");
        drop(a);
        assert_eq!(budget.reserved(), 1);
        assert_eq!(share.working(0), 2, "a's cores came back");
        assert_eq!((b.cores(), budget.reserved()), (2, 2));
        // A session started now holds its servo thread's core: b lends its worker meanwhile
        // and keeps both cores, so it has them again when c stops.
        let c = budget.reserve(auto, 2, false);
        let c_share = c.share();
        assert_eq!((c.cores(), c_share.working(0), share.working(0)), (1, 1, 1));
        assert_eq!(budget.reserved(), 3);
        drop(c);
        assert_eq!((share.working(0), b.cores(), budget.reserved()), (2, 2, 2));
        assert_eq!(c_share.working(0), 1, "a dropped reservation's share");
        assert_eq!(budget.reserved(), 2, "and it took nothing");
        drop(b);
        assert_eq!((share.working(0), budget.reserved()), (1, 0));
        // Never more than the body wants or the budget has.
        let d = budget.reserve(auto, 1, false);
        assert_eq!(
            (d.threads(), d.share().working(0), budget.reserved()),
            (1, 1, 1)
        );
        let e = CoreBudget::new(2).reserve(auto, 4, false);
        assert_eq!((e.threads(), e.cores()), (2, 2));
        let fifo_refused = CoreBudget::new(2).reserve(auto, 2, true);
        assert_eq!(
            (fifo_refused.threads(), fifo_refused.share().working(0)),
            (1, 1)
        );
    }

    /// Sessions holding more cores than the budget has lend out only as many workers as that
    /// excess, not one each, and take them back as the excess goes.
    #[test]
    fn only_as_many_workers_as_the_excess_are_lent_out() {
        let auto = ServoThreads::Auto;
        let budget = CoreBudget::new(16);
        let mut sessions: Vec<_> = (0..9).map(|_| budget.reserve(auto, 2, false)).collect();
        let mut shares: Vec<_> = sessions.iter().map(CoreReservation::share).collect();
        assert_eq!(
            budget.reserved(),
            17,
            "the ninth holds its servo thread's core"
        );
        let working = |shares: &[ThreadShare]| {
            // Two statistics windows each: the counts settle in the first.
            shares.iter().for_each(|s| {
                s.working(0);
            });
            shares.iter().map(|s| s.working(0)).collect::<Vec<_>>()
        };
        let w = working(&shares);
        assert_eq!(w.iter().sum::<usize>(), 16, "{w:?}");
        assert_eq!(w.iter().filter(|&&n| n == 1).count(), 2, "{w:?}");
        assert_eq!(w[8], 1, "the ninth waits for a core");
        // A session that was not lending stops: the ninth takes its core, nobody lends.
        let lender = w[..8].iter().position(|&n| n == 1).expect("one lends");
        let stopped = (lender + 1) % 8;
        sessions.remove(stopped);
        shares.remove(stopped);
        let w = working(&shares);
        assert_eq!(w, vec![2; 8], "{w:?}");
        assert_eq!(budget.reserved(), 16);
        // Two more on a full budget: two workers lent; a lender stops and the count holds.
        sessions.extend((0..2).map(|_| budget.reserve(auto, 2, false)));
        shares.extend(sessions[8..].iter().map(CoreReservation::share));
        let w = working(&shares);
        assert_eq!(w.iter().sum::<usize>(), 16, "{w:?}");
        let lenders: Vec<_> = (0..8).filter(|&i| w[i] == 1).collect();
        assert_eq!(lenders.len(), 2, "{w:?}");
        sessions.remove(lenders[0]);
        shares.remove(lenders[0]);
        let w = working(&shares);
        assert_eq!(w.iter().sum::<usize>(), 16, "{w:?}");
        drop(sessions);
        assert_eq!(budget.reserved(), 0);
        assert_eq!(
            budget.lent.load(Ordering::Acquire),
            0,
            "lent workers given back"
        );
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
