//! A real-time worker pool for one body's tick (issue 48 section 1).
//!
//! A session may give its body a few threads beside the servo thread; the body cuts parts of its
//! tick (element-force batches, the coarse companion beside the condensed region, particle
//! groups) into jobs for them. The contract every implementation keeps:
//!
//! - **No allocation, no lock, no logging** in [`TickPool::for_each_mut`] and [`TickPool::join`]
//!   (they run inside the servo tick): workers wait by spinning, then parking; the caller never
//!   parks.
//! - **Results never depend on who ran a part.** A job is cut into [`TickPool::threads`] parts by
//!   the caller, so the arithmetic is fixed by the thread count, not by scheduling; one thread is
//!   the one-core code path, bit for bit.
//! - **A starved worker degrades to one core**: parts no worker has claimed run on the caller.
//! - **Workers can be lent out** ([`TickPool::set_active_workers`]): the inactive ones stay
//!   parked and claim nothing, so the cores they would take are free for other work (a region
//!   cache being built beside the tick); the job's parts, and so its arithmetic, stay the same.
//!
//! **How it works.** [`TickPool::new`] starts `workers` std threads. A parts job
//! ([`TickPool::for_each_mut`]) is published as one word `(epoch << 36) | (parts << 20) | next`:
//! every thread, the caller included, claims part `next` by `fetch_add(1)` on that word, so a
//! claim is always a part of the job current at the claim (a late worker cannot run a part of a
//! finished job: that job's word was replaced before its caller returned). The caller then spins
//! (never parks) only for parts a worker claimed and has not finished. [`TickPool::join`]
//! offers its second closure in a task slot (`offered -> claimed -> done`), runs the first, and
//! takes the second back to run it itself when no worker claimed it. One parts job and one task
//! may be in flight together (the region's parts while a worker ticks the companion); a second
//! caller that finds a slot busy (a cloned body on another thread) runs its job serially on
//! itself. Workers spin [`SPIN_US`] after their last work, then `park()`; the caller `unpark`s
//! the parked ones when it publishes (a `SeqCst` flag on both sides, so no wake-up is lost).
//! While a body holds [`TickPool::hot`] (its whole tick) the workers do not park at all: they
//! are woken at the tick's start, while the caller runs its serial prologue, and spin between
//! the tick's jobs, so no job waits for a parked worker's wake-up (a syscall on the caller and
//! tens of microseconds of scheduling in a VM: issue 48 s1, docs/benchmarks.md "Workers kept
//! awake through a tick"). Between ticks they park as before.
//! Jobs erase their closure's type into a data pointer and a monomorphic call function valid
//! until the job is done: this module's `unsafe`.
//!
//! **Panics.** A part or task that panics on a worker is caught there (the worker lives on);
//! the caller panics once the job is done (a task's payload is re-raised, a part's becomes "a
//! part of a tick-pool job panicked on a worker"). A panic on the caller first withdraws the
//! unclaimed parts and waits for the claimed ones (they borrow its stack), then unwinds. Either
//! way the pool stays usable and nothing deadlocks; a body that panics mid-tick is poisoned
//! anyway (the session quarantines it).

use std::cell::UnsafeCell;
use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};
use std::sync::Arc;
use std::sync::atomic::Ordering::{AcqRel, Acquire, Relaxed, Release, SeqCst};
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU32, AtomicU64, AtomicUsize};
use std::thread::{JoinHandle, Thread};
use std::time::{Duration, Instant};

use crate::ModelError;

/// Called on each worker thread as it starts, with its index `0..workers`: the server pins the
/// worker to a CPU and gives it the servo's scheduling policy there.
pub type StartHook = Arc<dyn Fn(usize) + Send + Sync>;

/// Most worker threads a pool takes (a body's tick is cut into at most `MAX_WORKERS + 1` parts).
pub const MAX_WORKERS: usize = 15;

/// Where two threads cut an ascending list of `n` entries whose `i`-th has key `key(i)` (a
/// particle, a grid cell): the middle index `h` and its key, when every entry before `h` has a
/// lower key, so the halves own disjoint sides of the arrays the keys index; `None` for fewer
/// than two entries or a key repeated across the cut (then one thread does it all).
pub(crate) fn cut_at_middle(n: usize, key: impl Fn(usize) -> u32) -> Option<(usize, usize)> {
    let h = n / 2;
    (h > 0 && key(h - 1) < key(h)).then(|| (h, key(h) as usize))
}

/// How long a worker spins after its last part or task before it parks, microseconds.
pub const SPIN_US: u64 = 50;

/// Most parts a threaded [`TickPool::for_each_mut`] job takes (the word's 16-bit part count);
/// a longer slice runs serially on the caller.
pub const MAX_THREADED_PARTS: usize = PARTS_MASK as usize;

/// What the pool has done so far, for `GetStats`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PoolStats {
    /// Jobs run ([`TickPool::for_each_mut`] and [`TickPool::join`] calls).
    pub jobs: u64,
    /// Parts run on the calling thread.
    pub parts_on_caller: u64,
    /// Parts run by a worker.
    pub parts_on_workers: u64,
    /// Longest time the caller waited for a part a worker had claimed, microseconds.
    pub longest_wait_us: u64,
}

/// The parts word: `next` in bits 0..20, the part count in 20..36, the epoch above.
const NEXT_BITS: u32 = 20;
const NEXT_MASK: u64 = (1 << NEXT_BITS) - 1;
const PARTS_MASK: u64 = (1 << 16) - 1;
const EPOCH_SHIFT: u32 = 36;

/// The states of the task slot ([`TickPool::join`]).
const TASK_EMPTY: u8 = 0;
const TASK_OFFERED: u8 = 1;
const TASK_CLAIMED: u8 = 2;
const TASK_DONE: u8 = 3;

/// The part a claim `w` (the parts word before the `fetch_add`) hands out, if any.
fn claimed_part(w: u64) -> Option<usize> {
    let next = w & NEXT_MASK;
    let parts = (w >> NEXT_BITS) & PARTS_MASK;
    (next < parts).then_some(next as usize)
}

/// A job with its closure's type erased: `call(data, part)`; `data` is valid while the job is.
#[derive(Clone, Copy)]
struct Erased {
    data: *const (),
    call: unsafe fn(*const (), usize),
}

/// The call of an empty slot (never made: a slot is read only after a claim).
unsafe fn no_call(_: *const (), _: usize) {}

impl Erased {
    const NONE: Self = Self {
        data: std::ptr::null(),
        call: no_call,
    };
}

/// What the caller and the workers share.
struct Shared {
    /// `(epoch << 36) | (parts << 20) | next` of the current parts job.
    parts_word: AtomicU64,
    /// The current parts job; written by its caller before the word is published.
    parts_job: UnsafeCell<Erased>,
    /// Parts of the current job that workers finished.
    parts_done: AtomicU32,
    /// A worker's part panicked in the current job.
    parts_panicked: AtomicBool,
    /// A caller owns the parts slot.
    parts_busy: AtomicBool,
    /// `TASK_EMPTY`, `TASK_OFFERED`, `TASK_CLAIMED` or `TASK_DONE`.
    task_state: AtomicU8,
    /// The offered task; written by its caller before it is offered.
    task_job: UnsafeCell<Erased>,
    /// A caller owns the task slot.
    task_busy: AtomicBool,
    /// Worker `k` is parked or about to park (the caller unparks it when it publishes).
    sleeping: [AtomicBool; MAX_WORKERS],
    /// Live [`Hot`] guards: while above zero the workers spin instead of parking.
    hot: AtomicU32,
    /// Workers `0..active` claim work; the others stay parked ([`TickPool::set_active_workers`]).
    active: AtomicUsize,
    /// The pool is being dropped: workers return.
    stop: AtomicBool,
    jobs: AtomicU64,
    parts_on_caller: AtomicU64,
    parts_on_workers: AtomicU64,
    longest_wait_ns: AtomicU64,
}

// SAFETY: the `UnsafeCell`s are written only by the caller owning the slot (its busy flag) while
// no worker can read them (no claimable part, task not offered), and read by a worker only
// after a claim that synchronises with the publishing store (Release/Acquire); the raw pointers
// they hold are only dereferenced under that claim (see `call_part`, `call_task`).
unsafe impl Send for Shared {}
// SAFETY: as for `Send` above.
unsafe impl Sync for Shared {}

impl Shared {
    fn new(workers: usize) -> Self {
        Self {
            parts_word: AtomicU64::new(0),
            parts_job: UnsafeCell::new(Erased::NONE),
            parts_done: AtomicU32::new(0),
            parts_panicked: AtomicBool::new(false),
            parts_busy: AtomicBool::new(false),
            task_state: AtomicU8::new(TASK_EMPTY),
            task_job: UnsafeCell::new(Erased::NONE),
            task_busy: AtomicBool::new(false),
            sleeping: std::array::from_fn(|_| AtomicBool::new(false)),
            hot: AtomicU32::new(0),
            active: AtomicUsize::new(workers),
            stop: AtomicBool::new(false),
            jobs: AtomicU64::new(0),
            parts_on_caller: AtomicU64::new(0),
            parts_on_workers: AtomicU64::new(0),
            longest_wait_ns: AtomicU64::new(0),
        }
    }

    /// Work a worker could claim now (`SeqCst`: the other half of the caller's wake-up check).
    fn has_work(&self) -> bool {
        self.task_state.load(SeqCst) == TASK_OFFERED
            || claimed_part(self.parts_word.load(SeqCst)).is_some()
    }

    /// Claims and runs the offered task, if any (on a worker). Whether it ran one.
    fn run_task(&self) -> bool {
        if self.task_state.load(Relaxed) != TASK_OFFERED
            || self
                .task_state
                .compare_exchange(TASK_OFFERED, TASK_CLAIMED, Acquire, Relaxed)
                .is_err()
        {
            return false;
        }
        // SAFETY: the claim synchronises with the caller's offer, which followed its write of
        // `task_job`; the caller neither rewrites it nor returns until `TASK_DONE`.
        let job = unsafe { *self.task_job.get() };
        // SAFETY: `job` is the claimed task's (`call_task` with its own data), run once.
        unsafe { (job.call)(job.data, 0) };
        self.parts_on_workers.fetch_add(1, Relaxed);
        self.task_state.store(TASK_DONE, Release);
        true
    }

    /// Claims and runs parts of the current job while there are any (on a worker). Whether it
    /// ran one.
    fn run_parts(&self) -> bool {
        let mut ran = false;
        while claimed_part(self.parts_word.load(Acquire)).is_some() {
            let Some(p) = claimed_part(self.parts_word.fetch_add(1, AcqRel)) else {
                break;
            };
            // SAFETY: the claim of part `p` synchronises with the store that published this
            // job, after its caller wrote `parts_job`; the caller does not return (nor rewrite
            // the slot) before this part is counted in `parts_done`.
            let job = unsafe { *self.parts_job.get() };
            // SAFETY: `job` is the current job's (`call_part`), `p` is below its part count and
            // was handed out once.
            let out = catch_unwind(AssertUnwindSafe(|| unsafe { (job.call)(job.data, p) }));
            if out.is_err() {
                self.parts_panicked.store(true, Relaxed);
            }
            self.parts_on_workers.fetch_add(1, Relaxed);
            self.parts_done.fetch_add(1, Release);
            ran = true;
        }
        ran
    }

    /// Records a wait of the caller for workers.
    fn note_wait(&self, since: Instant) {
        let ns = u64::try_from(since.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.longest_wait_ns.fetch_max(ns, Relaxed);
    }
}

/// A slot owned while this guard lives.
struct Busy<'a>(&'a AtomicBool);

impl<'a> Busy<'a> {
    fn try_take(flag: &'a AtomicBool) -> Option<Self> {
        flag.compare_exchange(false, true, Acquire, Relaxed)
            .ok()
            .map(|_| Self(flag))
    }
}

impl Drop for Busy<'_> {
    fn drop(&mut self) {
        self.0.store(false, Release);
    }
}

/// The workers kept awake while this lives ([`TickPool::hot`]).
#[must_use = "the workers stay awake only while the guard lives"]
pub struct Hot<'a>(&'a AtomicU32);

impl Drop for Hot<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Release);
    }
}

/// The erased data of a parts job: the items and the closure.
struct PartsJob<'a, T> {
    items: *mut T,
    f: &'a (dyn Fn(usize, &mut T) + Sync),
}

/// Runs part `p` of the [`PartsJob<T>`] at `data`.
///
/// # Safety
/// `data` points to a live `PartsJob<T>` whose `items` holds more than `p` elements, and part
/// `p` is run once (its `&mut` is unique).
unsafe fn call_part<T>(data: *const (), p: usize) {
    // SAFETY: the caller's contract.
    let job = unsafe { &*data.cast::<PartsJob<'_, T>>() };
    // SAFETY: `p` is in bounds and handed out once, so this `&mut` aliases nothing.
    let item = unsafe { &mut *job.items.add(p) };
    (job.f)(p, item);
}

/// The erased data of a task: the closure until it runs, then its result.
struct Task<B, R> {
    f: Option<B>,
    out: Option<std::thread::Result<R>>,
}

/// Runs the [`Task<B, R>`] at `data` and stores its result (a panic is caught into it).
///
/// # Safety
/// `data` points to a live `Task<B, R>` no other thread touches until the call returns.
unsafe fn call_task<B: FnOnce() -> R, R>(data: *const (), _: usize) {
    // SAFETY: the caller's contract (the pointer came from a `&mut Task<B, R>`).
    let task = unsafe { &mut *data.cast_mut().cast::<Task<B, R>>() };
    if let Some(f) = task.f.take() {
        task.out = Some(catch_unwind(AssertUnwindSafe(f)));
    }
}

/// The worker pool of one body (module documentation). Shared by the body and its workers.
pub struct TickPool {
    workers: usize,
    shared: Arc<Shared>,
    threads: Vec<Thread>,
    handles: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for TickPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TickPool")
            .field("threads", &self.threads())
            .finish()
    }
}

/// A worker's life: the start hook, then claim work, spin (while the pool is [`TickPool::hot`]
/// or for [`SPIN_US`] after its last work), park, until `stop`. An inactive worker
/// ([`TickPool::set_active_workers`]) claims nothing and parks at once.
fn worker(shared: Arc<Shared>, k: usize, on_start: StartHook) {
    on_start(k);
    let spin = Duration::from_micros(SPIN_US);
    let mut idle_since = Instant::now();
    while !shared.stop.load(Acquire) {
        let active = k < shared.active.load(Relaxed);
        if active && (shared.run_task() | shared.run_parts()) {
            idle_since = Instant::now();
        } else if active && (shared.hot.load(Relaxed) > 0 || idle_since.elapsed() < spin) {
            std::hint::spin_loop();
        } else {
            shared.sleeping[k].store(true, SeqCst);
            // `hot` and `active` read after `sleeping` is set (all `SeqCst`, as in
            // `TickPool::hot` and `set_active_workers`): a guard taken or an activation made
            // now either sees this worker sleeping and unparks it, or is seen here.
            let active = k < shared.active.load(SeqCst);
            let wanted = active && (shared.has_work() || shared.hot.load(SeqCst) > 0);
            if !wanted && !shared.stop.load(SeqCst) {
                std::thread::park();
            }
            shared.sleeping[k].store(false, SeqCst);
            idle_since = Instant::now();
        }
    }
}

impl TickPool {
    /// The pool without workers: every call runs on the caller, in order (one core).
    pub fn serial() -> Arc<Self> {
        Arc::new(Self {
            workers: 0,
            shared: Arc::new(Shared::new(0)),
            threads: Vec::new(),
            handles: Vec::new(),
        })
    }

    /// A pool of `workers` threads beside the caller; `on_start(k)` runs first on worker `k`
    /// (dropping the pool waits for the hooks to return). Allocates: set-up, not a tick.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when `workers > MAX_WORKERS` or a thread cannot be started
    /// (the ones already started are stopped).
    pub fn new(workers: usize, on_start: StartHook) -> Result<Arc<Self>, ModelError> {
        if workers > MAX_WORKERS {
            return Err(ModelError::InvalidInput(format!(
                "a tick pool takes at most {MAX_WORKERS} workers, not {workers}"
            )));
        }
        let mut pool = Self {
            workers: 0,
            shared: Arc::new(Shared::new(workers)),
            threads: Vec::with_capacity(workers),
            handles: Vec::with_capacity(workers),
        };
        for k in 0..workers {
            let shared = Arc::clone(&pool.shared);
            let hook = Arc::clone(&on_start);
            let handle = std::thread::Builder::new()
                .name(format!("tick-pool-{k}"))
                .spawn(move || worker(shared, k, hook))
                .map_err(|e| {
                    ModelError::InvalidInput(format!("starting tick-pool worker {k}: {e}"))
                })?;
            pool.threads.push(handle.thread().clone());
            pool.handles.push(handle);
            pool.workers = k + 1;
        }
        Ok(Arc::new(pool))
    }

    /// Threads that run a job: the workers plus the caller. Also the number of parts a body
    /// cuts a job into, so its arithmetic does not depend on scheduling.
    pub fn threads(&self) -> usize {
        self.workers + 1
    }

    /// Keeps the workers awake until the guard drops: wakes the parked ones now, and while any
    /// guard lives they spin between jobs instead of parking. A body takes it for its whole
    /// tick, so the tick's jobs find the workers spinning. Allocation-free and lock-free; guards
    /// nest (a companion's tick inside its region's).
    pub fn hot(&self) -> Hot<'_> {
        self.shared.hot.fetch_add(1, SeqCst);
        self.wake();
        Hot(&self.shared.hot)
    }

    /// Workers that claim work (module documentation): `0..=workers`, all of them unless
    /// [`Self::set_active_workers`] lent some out.
    pub fn active_workers(&self) -> usize {
        self.shared.active.load(Relaxed).min(self.workers)
    }

    /// Lets only the first `n` workers (at most all) claim work from now on: the others park
    /// and stay parked, leaving their cores to other threads, until a later call activates them
    /// again. Jobs are still cut into [`Self::threads`] parts, so results do not change; parts
    /// no active worker takes run on the caller (with none active, every job is serial there).
    /// Allocation-free and lock-free; call it between jobs (a worker that already claimed a
    /// part finishes it). Unparks only on a change, so it may be called every window.
    /// Returns the workers active now.
    pub fn set_active_workers(&self, n: usize) -> usize {
        let n = n.min(self.workers);
        if self.shared.active.swap(n, SeqCst) != n {
            self.wake();
        }
        n
    }

    /// Unparks the active workers that are parked or about to park (after a publish).
    fn wake(&self) {
        let active = self.active_workers();
        for (k, t) in self.threads.iter().enumerate().take(active) {
            if self.shared.sleeping[k].load(SeqCst) {
                t.unpark();
            }
        }
    }

    /// Runs `f(p, &mut items[p])` once for every `p`, each on one thread, and returns when all
    /// are done. Allocation-free and lock-free. Serial on the caller without active workers, for
    /// fewer than two or more than [`MAX_THREADED_PARTS`] items, and when another caller's
    /// parts job is in flight.
    ///
    /// # Panics
    /// When `f` panics (on the caller: the same panic; on a worker: "a part of a tick-pool job
    /// panicked on a worker"), after every claimed part has finished (module documentation).
    pub fn for_each_mut<T: Send>(&self, items: &mut [T], f: &(dyn Fn(usize, &mut T) + Sync)) {
        let sh = &*self.shared;
        sh.jobs.fetch_add(1, Relaxed);
        let n = items.len();
        let slot = if self.active_workers() > 0 && (2..=MAX_THREADED_PARTS).contains(&n) {
            Busy::try_take(&sh.parts_busy)
        } else {
            None
        };
        let Some(_slot) = slot else {
            for (p, item) in items.iter_mut().enumerate() {
                f(p, item);
            }
            sh.parts_on_caller.fetch_add(n as u64, Relaxed);
            return;
        };
        let job = PartsJob {
            items: items.as_mut_ptr(),
            f,
        };
        let data = (&raw const job).cast::<()>();
        // SAFETY: this caller owns the parts slot and the previous job's word is exhausted, so
        // no worker reads `parts_job` until the store below publishes this job.
        unsafe {
            *sh.parts_job.get() = Erased {
                data,
                call: call_part::<T>,
            };
        }
        sh.parts_done.store(0, Relaxed);
        let epoch = (sh.parts_word.load(Relaxed) >> EPOCH_SHIFT).wrapping_add(1);
        let head = (epoch << EPOCH_SHIFT) | ((n as u64) << NEXT_BITS);
        sh.parts_word.store(head, SeqCst);
        self.wake();
        let mut mine = 0_u32;
        let ran = catch_unwind(AssertUnwindSafe(|| {
            while let Some(p) = claimed_part(sh.parts_word.fetch_add(1, AcqRel)) {
                mine += 1;
                // SAFETY: `job` lives on this frame until every claimed part is done, `p` is
                // below `n` and handed out once.
                unsafe { call_part::<T>(data, p) };
            }
        }));
        // Withdraw what is unclaimed (parts remain only after a panic), then wait for the parts
        // workers claimed: they borrow `items` and `f`.
        let old = sh.parts_word.swap(head | n as u64, AcqRel);
        let claimed = ((old & NEXT_MASK) as usize).min(n) as u32;
        let by_workers = claimed - mine;
        if sh.parts_done.load(Acquire) < by_workers {
            let since = Instant::now();
            while sh.parts_done.load(Acquire) < by_workers {
                std::hint::spin_loop();
            }
            sh.note_wait(since);
        }
        sh.parts_on_caller.fetch_add(u64::from(mine), Relaxed);
        if let Err(payload) = ran {
            sh.parts_panicked.store(false, Relaxed);
            resume_unwind(payload);
        }
        if sh.parts_panicked.swap(false, Relaxed) {
            panic!("a part of a tick-pool job panicked on a worker");
        }
    }

    /// Runs `a` on the caller and `b` on a worker if one claims it (else on the caller after
    /// `a`); returns both results. Allocation-free and lock-free; serial without active workers or
    /// when another caller's task is in flight.
    ///
    /// # Panics
    /// When `a` or `b` panics, with its payload, after `b` is finished or withdrawn (`b` is
    /// not run when `a` panicked before a worker claimed it).
    pub fn join<RA: Send, RB: Send>(
        &self,
        a: impl FnOnce() -> RA + Send,
        b: impl FnOnce() -> RB + Send,
    ) -> (RA, RB) {
        let sh = &*self.shared;
        sh.jobs.fetch_add(1, Relaxed);
        let slot = if self.active_workers() > 0 {
            Busy::try_take(&sh.task_busy)
        } else {
            None
        };
        let Some(slot) = slot else {
            let ra = a();
            let rb = b();
            sh.parts_on_caller.fetch_add(2, Relaxed);
            return (ra, rb);
        };
        let (ra, on_caller, mut task) = self.offer(a, b);
        drop(slot);
        sh.parts_on_caller
            .fetch_add(if on_caller { 2 } else { 1 }, Relaxed);
        let ra = ra.unwrap_or_else(|payload| resume_unwind(payload));
        let rb = match (on_caller, task.f.take(), task.out.take()) {
            (true, Some(b), _) => b(),
            (false, _, Some(Ok(rb))) => rb,
            (false, _, Some(Err(payload))) => resume_unwind(payload),
            _ => unreachable!("a tick-pool task is run once, by the caller or a worker"),
        };
        (ra, rb)
    }

    /// [`Self::join`] with the task slot owned: offers `b`, runs `a`, then takes `b` back
    /// (`true`: the caller must run it) or waits until the worker that claimed it is done.
    #[allow(clippy::type_complexity)]
    fn offer<RA, RB, A: FnOnce() -> RA, B: FnOnce() -> RB>(
        &self,
        a: A,
        b: B,
    ) -> (std::thread::Result<RA>, bool, Task<B, RB>) {
        let sh = &*self.shared;
        let mut task = Task {
            f: Some(b),
            out: None,
        };
        // SAFETY: this caller owns the task slot and it is empty, so no worker reads `task_job`
        // until the offer below.
        unsafe {
            *sh.task_job.get() = Erased {
                data: (&raw mut task).cast_const().cast::<()>(),
                call: call_task::<B, RB>,
            };
        }
        sh.task_state.store(TASK_OFFERED, SeqCst);
        self.wake();
        let ra = catch_unwind(AssertUnwindSafe(a));
        let on_caller = sh
            .task_state
            .compare_exchange(TASK_OFFERED, TASK_EMPTY, Acquire, Acquire)
            .is_ok();
        if !on_caller {
            if sh.task_state.load(Acquire) != TASK_DONE {
                let since = Instant::now();
                while sh.task_state.load(Acquire) != TASK_DONE {
                    std::hint::spin_loop();
                }
                sh.note_wait(since);
            }
            sh.task_state.store(TASK_EMPTY, Relaxed);
        }
        (ra, on_caller, task)
    }

    /// What the pool has done so far.
    pub fn stats(&self) -> PoolStats {
        let sh = &*self.shared;
        PoolStats {
            jobs: sh.jobs.load(Relaxed),
            parts_on_caller: sh.parts_on_caller.load(Relaxed),
            parts_on_workers: sh.parts_on_workers.load(Relaxed),
            longest_wait_us: sh.longest_wait_ns.load(Relaxed) / 1_000,
        }
    }
}

impl Drop for TickPool {
    /// Stops the workers and joins them (after their start hooks returned).
    fn drop(&mut self) {
        self.shared.stop.store(true, SeqCst);
        for t in &self.threads {
            t.unpark();
        }
        for h in self.handles.drain(..) {
            let _ = h.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Waits up to 5 s for `cond`; whether it held.
    fn eventually(cond: impl Fn() -> bool) -> bool {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(5) {
            if cond() {
                return true;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        false
    }

    #[test]
    fn a_hot_pool_wakes_its_parked_workers_and_keeps_them_awake_until_the_last_guard_drops() {
        let pool = TickPool::new(1, Arc::new(|_| {})).unwrap();
        let sleeping = || pool.shared.sleeping[0].load(SeqCst);
        // Idle, the worker parks after its spin.
        assert!(eventually(sleeping), "the idle worker never parked");
        let outer = pool.hot();
        assert!(
            eventually(|| !sleeping()),
            "a hot pool did not wake its worker"
        );
        let inner = pool.hot();
        drop(outer);
        // Still hot (the inner guard): the worker stays awake well past its spin.
        std::thread::sleep(Duration::from_micros(20 * SPIN_US));
        assert!(!sleeping(), "the worker parked while a guard lived");
        let mut items = [0_u32; 4];
        pool.for_each_mut(&mut items, &|p, v| *v = p as u32 + 1);
        assert_eq!(items, [1, 2, 3, 4]);
        drop(inner);
        assert!(
            eventually(sleeping),
            "the worker stayed awake after the last guard"
        );
        // The serial pool takes guards too (no workers to wake).
        let serial = TickPool::serial();
        let _g = serial.hot();
        assert_eq!(serial.shared.hot.load(SeqCst), 1);
    }

    #[test]
    fn the_serial_pool_runs_every_part_once_in_order_on_the_caller() {
        let pool = TickPool::serial();
        assert_eq!(pool.threads(), 1);
        let mut seen = vec![usize::MAX; 5];
        pool.for_each_mut(&mut seen, &|p, s| *s = p);
        assert_eq!(seen, [0, 1, 2, 3, 4]);
        let caller = std::thread::current().id();
        let (a, b) = pool.join(
            || std::thread::current().id(),
            || std::thread::current().id(),
        );
        assert_eq!((a, b), (caller, caller));
    }

    /// Parts that take long enough for an awake worker to claim one while the caller runs
    /// another; what ran them.
    fn slow_parts(pool: &TickPool) -> [Option<std::thread::ThreadId>; 4] {
        let mut by = [None; 4];
        pool.for_each_mut(&mut by, &|_, who| {
            let t0 = Instant::now();
            while t0.elapsed() < Duration::from_micros(300) {
                std::hint::spin_loop();
            }
            *who = Some(std::thread::current().id());
        });
        by
    }

    #[test]
    fn inactive_workers_park_claim_nothing_and_work_again_once_activated() {
        let pool = TickPool::new(2, Arc::new(|_| {})).unwrap();
        let caller = Some(std::thread::current().id());
        let sleeping = |k: usize| pool.shared.sleeping[k].load(SeqCst);
        // Lent out while a hot pool keeps them spinning: they park all the same.
        let _hot = pool.hot();
        assert!(
            eventually(|| !sleeping(0) && !sleeping(1)),
            "a hot pool's workers parked"
        );
        pool.set_active_workers(0);
        assert_eq!((pool.active_workers(), pool.threads()), (0, 3));
        assert!(
            eventually(|| sleeping(0) && sleeping(1)),
            "inactive workers never parked"
        );
        for _ in 0..20 {
            assert_eq!(
                slow_parts(&pool),
                [caller; 4],
                "an inactive worker ran a part"
            );
            let (a, b) = pool.join(
                || std::thread::current().id(),
                || {
                    std::thread::sleep(Duration::from_micros(300));
                    std::thread::current().id()
                },
            );
            assert_eq!((Some(a), Some(b)), (caller, caller));
        }
        assert!(
            sleeping(0) && sleeping(1),
            "a hot pool woke an inactive worker"
        );
        assert_eq!(pool.stats().parts_on_workers, 0);
        // One active: it wakes and takes parts, the other stays parked.
        pool.set_active_workers(1);
        let helpers = std::cell::RefCell::new(std::collections::HashSet::new());
        let jobs = |n: usize| {
            for _ in 0..n {
                let by = slow_parts(&pool);
                helpers
                    .borrow_mut()
                    .extend(by.into_iter().filter(|&w| w != caller));
            }
            !helpers.borrow().is_empty()
        };
        assert!(
            eventually(|| jobs(1)),
            "the active worker never took a part"
        );
        jobs(40);
        let helpers = helpers.into_inner();
        assert_eq!(helpers.len(), 1, "{helpers:?}: one active worker");
        assert!(sleeping(1) && !sleeping(0));
        pool.set_active_workers(5);
        assert_eq!(pool.active_workers(), 2, "at most the pool's workers");
        assert!(
            eventually(|| !sleeping(1)),
            "the hot pool's second worker stayed parked"
        );
    }

    #[test]
    fn too_many_workers_are_refused() {
        let hook: StartHook = Arc::new(|_| {});
        assert!(TickPool::new(MAX_WORKERS + 1, hook.clone()).is_err());
        assert_eq!(TickPool::new(0, hook).unwrap().threads(), 1);
    }
}
