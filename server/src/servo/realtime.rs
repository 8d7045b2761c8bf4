//! Real-time set-up of the servo thread (affinity, `SCHED_FIFO`, `mlockall`) and [`Yielding`]:
//! the operating-system calls, made by the loop, never inside the tick.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use super::ServoCore;

/// Real-time set-up outcome messages (logged by the caller, never from the tick).
pub fn setup_realtime(cfg: &crate::config::ServoConfig) -> Vec<String> {
    let mut warnings = Vec::new();
    if let Some(cpu) = cfg.cpu {
        let ok = core_affinity::get_core_ids()
            .and_then(|ids| ids.into_iter().find(|c| c.id == cpu))
            .map(core_affinity::set_for_current)
            .unwrap_or(false);
        if !ok {
            warnings.push(format!(
                "could not pin the servo thread to CPU {cpu}; running unpinned"
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
                "SCHED_FIFO priority {} refused ({e:?}); running with normal scheduling",
                cfg.priority
            ));
        }
    }
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

/// Lets an overrunning session's servo thread yield to the sessions that keep up (issue 16,
/// section 2). While the session is overrunning ([`ServoCore::overrunning`]) and another
/// session runs, its thread is moved to `SCHED_IDLE`: it then gets only the CPU time the
/// others leave, so a model too heavy for the machine cannot slow a session that fits. When
/// it keeps its rate again, or is alone, the thread's original policy (normal or
/// `SCHED_FIFO`) comes back. Linux lets a thread leave `SCHED_IDLE` only with
/// `CAP_SYS_NICE` (the systemd unit grants it); without it a demoted thread stays demoted,
/// which `GetStats` shows (`demoted`).
///
/// Called from the loop after each tick, never inside it: a demotion is one system call.
#[derive(Debug)]
pub struct Yielding {
    enabled: bool,
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
            running_sessions,
            original,
            demoted: false,
            stuck: false,
        }
    }

    /// Demotes or restores the thread as the session's state asks (see the type).
    pub fn after_tick(&mut self, core: &mut ServoCore) {
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
    }
}
