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
        // The workers follow (they were given the servo's policy by their start hook). A worker
        // that has exited is skipped: the call fails for it and changes nothing else.
        for tid in self.workers.iter().flat_map(|w| w.started()) {
            // SAFETY: changes the policy of one of this session's own threads by id; `param`
            // outlives the call.
            unsafe { libc::sched_setscheduler(tid, policy, &param) };
        }
    }
}
