//! Real-time set-up of the servo thread and its tick-pool workers (affinity, `SCHED_FIFO`,
//! `mlockall`) and [`Yielding`]: the operating-system calls, made by the loop or a worker's start
//! hook, never inside the tick.

use std::sync::Arc;
use std::sync::atomic::{AtomicI32, Ordering};

use haptic_model::pool::{MAX_WORKERS, StartHook};

use super::ServoCore;
use crate::config::ServoConfig;

/// Real-time set-up outcome messages (logged by the caller, never from the tick): the servo
/// thread pinned to the first CPU of [`ServoConfig::pinned_cpus`].
pub fn setup_realtime(cfg: &ServoConfig) -> Vec<String> {
    setup_realtime_on(cfg, cfg.pinned_cpus().first().copied())
}

/// [`setup_realtime`] pinning the calling (servo) thread to `cpu` (`None`: unpinned).
pub fn setup_realtime_on(cfg: &ServoConfig, cpu: Option<usize>) -> Vec<String> {
    let mut warnings = schedule_thread(cfg, cpu, None);
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

/// Largest freed block glibc's allocator keeps at the top of a heap for the next allocation
/// instead of giving it back to the kernel ([`keep_freed_memory`]): 256 MiB, several region
/// tiles of the 100 000-tet LV (27-31 MB each).
pub const KEPT_FREED_BYTES: usize = 256 << 20;

/// Tunes glibc's allocator for the daemon's large short-lived arrays (a region tile read
/// back while another is dropped, a region prepared): blocks up to 32 MiB come from the
/// heaps (`M_MMAP_THRESHOLD`, the ceiling of glibc's own adaptive threshold on 64-bit;
/// larger ones stay separate mappings), and up to
/// [`KEPT_FREED_BYTES`] freed at a heap's top stays mapped (`M_TRIM_THRESHOLD`), so a tile
/// read after a drop reuses pages already faulted in (with `mlockall`, already locked). On
/// a 2-core Xeon a 100 000-tet tile's rebuild took 36-42 ms instead of 58-65 ms this way
/// (docs/benchmarks.md, "A tile file read into one buffer"). The process then keeps up to
/// that much freed memory per heap in use. Returns whether glibc took both settings; `false`
/// (nothing changed) elsewhere.
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let trim = libc::c_int::try_from(KEPT_FREED_BYTES).unwrap_or(libc::c_int::MAX);
        // SAFETY: mallopt only changes the allocator's parameters; it takes its own lock.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, trim) == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

/// Pins the calling thread to `cpu` and gives it `SCHED_FIFO` at `cfg.priority` when
/// `cfg.realtime`; what failed, as messages naming the servo thread or tick-pool worker `worker`.
/// Allocates only to report a failure (a worker may start while an allocation count runs).
fn schedule_thread(cfg: &ServoConfig, cpu: Option<usize>, worker: Option<usize>) -> Vec<String> {
    let what = |w: Option<usize>| match w {
        Some(k) => format!("tick-pool worker {k}"),
        None => "servo thread".to_owned(),
    };
    let mut warnings = Vec::new();
    if let Some(cpu) = cpu {
        let ok = core_affinity::get_core_ids()
            .and_then(|ids| ids.into_iter().find(|c| c.id == cpu))
            .map(core_affinity::set_for_current)
            .unwrap_or(false);
        if !ok {
            warnings.push(format!(
                "could not pin the {} to CPU {cpu}; running unpinned",
                what(worker)
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
                "SCHED_FIFO priority {} refused for the {} ({e:?}); running with normal \
                 scheduling",
                cfg.priority,
                what(worker)
            ));
        }
    }
    warnings
}

/// Whether this process may give a thread `SCHED_FIFO` at `priority`: tried on a short-lived
/// thread of its own (session set-up, not a tick).
pub fn fifo_permitted(priority: u8) -> bool {
    std::thread::spawn(move || {
        use thread_priority::*;
        let prio = ThreadPriority::Crossplatform(
            ThreadPriorityValue::try_from(priority.clamp(1, 99))
                .unwrap_or(ThreadPriorityValue::MAX),
        );
        let policy = ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo);
        set_thread_priority_and_policy(thread_native_id(), prio, policy).is_ok()
    })
    .join()
    .unwrap_or(false)
}

/// The kernel thread ids of a session's tick-pool workers, recorded by their start hook
/// ([`worker_start_hook`]) so that [`Yielding`] demotes and restores them with the servo.
/// Fixed size, atomics only: reading it after a tick neither locks nor allocates.
#[derive(Debug)]
pub struct WorkerThreads {
    /// Thread id of worker `k` (0: not started yet).
    tids: [AtomicI32; MAX_WORKERS],
}

impl Default for WorkerThreads {
    fn default() -> Self {
        Self {
            tids: std::array::from_fn(|_| AtomicI32::new(0)),
        }
    }
}

impl WorkerThreads {
    /// Records the calling thread as worker `k` (ignored past [`MAX_WORKERS`]).
    pub fn record_this_thread(&self, k: usize) {
        if let Some(slot) = self.tids.get(k) {
            // SAFETY: gettid has no preconditions; it returns the calling thread's id.
            let tid = unsafe { libc::syscall(libc::SYS_gettid) } as i32;
            slot.store(tid, Ordering::Release);
        }
    }

    /// Gives every recorded worker `policy` at `priority` (`sched_setscheduler`); returns how
    /// many accepted. A worker that has exited is skipped: the call fails for it and changes
    /// nothing else.
    pub fn set_policy(&self, policy: libc::c_int, priority: libc::c_int) -> usize {
        let param = libc::sched_param {
            sched_priority: priority,
        };
        self.started()
            // SAFETY: changes the policy of one of this session's own threads by id; `param`
            // outlives the call.
            .filter(|&tid| unsafe { libc::sched_setscheduler(tid, policy, &param) } == 0)
            .count()
    }

    /// The recorded workers' thread ids.
    pub fn started(&self) -> impl Iterator<Item = libc::pid_t> + '_ {
        self.tids
            .iter()
            .map(|t| t.load(Ordering::Acquire))
            .filter(|&t| t > 0)
    }
}

/// The tick pool's start hook of a session: worker `k` is pinned to `worker_cpus[k]` (when
/// given; the caller lists the CPUs after the servo's), gets the servo's `SCHED_FIFO` priority
/// when `cfg.realtime`, and records its thread id in `workers`. Failures are logged as
/// warnings naming `session`, on the worker before its first job.
pub fn worker_start_hook(
    cfg: &ServoConfig,
    worker_cpus: Vec<usize>,
    workers: Arc<WorkerThreads>,
    session: String,
) -> StartHook {
    let cfg = cfg.clone();
    Arc::new(move |k: usize| {
        workers.record_this_thread(k);
        for w in schedule_thread(&cfg, worker_cpus.get(k).copied(), Some(k)) {
            tracing::warn!(session = %session, "{w}");
        }
    })
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
/// The session's tick-pool workers ([`Yielding::with_workers`]) are demoted and restored with the
/// servo thread. It also holds the session's core reservation ([`Yielding::holding`]) and lets it
/// go when the session is quarantined (its body no longer steps) or the loop ends.
///
/// Called from the loop after each tick, never inside it: a demotion is one system call per
/// thread.
#[derive(Debug)]
pub struct Yielding {
    enabled: bool,
    workers: Option<Arc<WorkerThreads>>,
    reservation: Option<crate::cores::CoreReservation>,
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
            workers: None,
            reservation: None,
            running_sessions,
            original,
            demoted: false,
            stuck: false,
        }
    }

    /// Demotes and restores these tick-pool workers with the servo thread.
    pub fn with_workers(mut self, workers: Arc<WorkerThreads>) -> Self {
        self.workers = Some(workers);
        self
    }

    /// Holds the session's core reservation until the session is quarantined or the loop ends.
    pub fn holding(mut self, reservation: crate::cores::CoreReservation) -> Self {
        self.reservation = Some(reservation);
        self
    }

    /// Demotes or restores the thread as the session's state asks (see the type).
    pub fn after_tick(&mut self, core: &mut ServoCore) {
        if core.fault().is_some() {
            // A quarantined body no longer steps: its cores go back to the other sessions.
            self.reservation = None;
        }
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
        // The workers follow (they were given the servo's policy by their start hook).
        if let Some(w) = &self.workers {
            w.set_policy(policy, priority);
        }
    }
}

/// Puts the calling thread (and the threads it starts from now on) at the lowest scheduling
/// priority: `SCHED_IDLE`, or nice 19 when that is refused. For background work that must
/// never take CPU time a session wants (the region cache's fill, [`crate::regions`]).
pub fn lowest_priority() {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: `param` is a valid, initialised sched_param; pid 0 is the calling thread.
    let idle = unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } == 0;
    if !idle {
        // SAFETY: plain system calls on the calling thread (its own tid), no pointers.
        let tid = unsafe { libc::gettid() };
        // SAFETY: as above.
        let _ = unsafe { libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, 19) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Minor page faults of this thread while it fills a 20 MiB block allocated after an
    /// equal one was filled and freed (a tile read back after one was dropped).
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn faults_refilling_a_freed_block() -> i64 {
        const BYTES: usize = 20 << 20;
        let faults = || {
            // SAFETY: getrusage writes the struct it is given.
            let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
            unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut usage) };
            usage.ru_minflt
        };
        let fill = || {
            let mut block = Vec::<u8>::with_capacity(BYTES);
            block.resize(BYTES, 1);
            std::hint::black_box(block)
        };
        drop(fill());
        let before = faults();
        drop(fill());
        faults() - before
    }

    /// With [`keep_freed_memory`] a freed tile-sized block is reused without new pages; with
    /// glibc's defaults it is a fresh mapping each time (about 5 000 faults for 20 MiB). Each
    /// case runs in a fresh process (this test binary again), since the defaults adapt to
    /// what a process freed before.
    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn a_freed_tile_sized_block_is_reused_without_page_faults() {
        const PROBE: &str = "HAPTIC_ALLOCATOR_PROBE";
        if let Ok(mode) = std::env::var(PROBE) {
            if mode == "kept" {
                assert!(keep_freed_memory());
            }
            println!("faults={}", faults_refilling_a_freed_block());
            return;
        }
        let run = |mode: &str| -> i64 {
            let exe = std::env::current_exe().expect("test binary");
            let out = std::process::Command::new(exe)
                .args(["--exact", "--nocapture", "--test-threads=1"])
                .arg("servo::realtime::tests::a_freed_tile_sized_block_is_reused_without_page_faults")
                .env(PROBE, mode)
                .output()
                .expect("run the probe");
            let text = String::from_utf8_lossy(&out.stdout);
            text.lines()
                .find_map(|l| {
                    l.split("faults=")
                        .nth(1)?
                        .split_whitespace()
                        .next()?
                        .parse()
                        .ok()
                })
                .unwrap_or_else(|| panic!("no probe output: {text}"))
        };
        let (default, kept) = (run("default"), run("kept"));
        assert!(default > 2_000, "glibc's defaults: {default} faults");
        assert!(kept < 200, "kept: {kept} faults (defaults: {default})");
    }

    /// Runs `f` on a new thread that first calls `hook(k)`, and returns what `f` read there
    /// while the thread is still alive, together with `check`'s result (run meanwhile by the
    /// test thread).
    fn on_worker<T: Send + 'static>(
        hook: StartHook,
        k: usize,
        check: impl FnOnce() -> usize,
        f: impl FnOnce() -> T + Send + 'static,
    ) -> (T, usize) {
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
        let worker = std::thread::spawn(move || {
            hook(k);
            ready_tx.send(()).unwrap();
            done_rx.recv().unwrap();
            f()
        });
        ready_rx.recv().unwrap();
        let checked = check();
        done_tx.send(()).unwrap();
        (worker.join().unwrap(), checked)
    }

    /// The calling thread's scheduling policy.
    fn policy() -> libc::c_int {
        // SAFETY: reads the calling thread's policy.
        unsafe { libc::sched_getscheduler(0) }
    }

    #[test]
    fn the_hook_records_the_worker_and_yielding_can_demote_and_restore_it() {
        let workers = Arc::new(WorkerThreads::default());
        let hook = worker_start_hook(
            &ServoConfig::default(),
            Vec::new(),
            workers.clone(),
            "t".into(),
        );
        let w = workers.clone();
        let demote_and_restore = move || {
            assert_eq!(w.started().count(), 1, "worker 1 recorded its id");
            let demoted = w.set_policy(libc::SCHED_IDLE, 0);
            // SAFETY: reads another thread's policy by id.
            let seen = w
                .started()
                .map(|t| unsafe { libc::sched_getscheduler(t) })
                .next();
            assert_eq!(seen, Some(libc::SCHED_IDLE));
            // Leaving SCHED_IDLE needs CAP_SYS_NICE (root here and in CI).
            demoted + w.set_policy(libc::SCHED_OTHER, 0)
        };
        let (end_policy, accepted) = on_worker(hook, 1, demote_and_restore, policy);
        assert_eq!(accepted, 2);
        assert_eq!(end_policy, libc::SCHED_OTHER);
        // Worker slots past the pool's largest are ignored, not a panic.
        WorkerThreads::default().record_this_thread(MAX_WORKERS);
    }

    #[test]
    fn the_hook_pins_worker_k_to_its_listed_cpu() {
        let workers = Arc::new(WorkerThreads::default());
        let hook = worker_start_hook(&ServoConfig::default(), vec![5, 0], workers, "t".into());
        let cpus = || {
            // SAFETY: a zeroed cpu_set_t is a valid empty set; sched_getaffinity fills it for the
            // calling thread and is told its size.
            unsafe {
                let mut set: libc::cpu_set_t = std::mem::zeroed();
                libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set);
                (0..64)
                    .filter(|&c| libc::CPU_ISSET(c, &set))
                    .collect::<Vec<_>>()
            }
        };
        let (pinned, _) = on_worker(hook, 1, || 0, cpus);
        assert_eq!(pinned, [0], "worker 1 goes to the list's second CPU");
    }
}
