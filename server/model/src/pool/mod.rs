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
//!
//! This module holds the API and the serial pool ([`TickPool::serial`]: every part runs on the
//! caller, in order). The threaded workers arrive behind the same API.

use std::sync::Arc;

use crate::ModelError;

/// Called on each worker thread as it starts, with its index `0..workers`: the server pins the
/// worker to a CPU and gives it the servo's scheduling policy there.
pub type StartHook = Arc<dyn Fn(usize) + Send + Sync>;

/// Most worker threads a pool takes (a body's tick is cut into at most `MAX_WORKERS + 1` parts).
pub const MAX_WORKERS: usize = 15;

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

/// The worker pool of one body (module documentation). Shared by the body and its workers.
pub struct TickPool {
    workers: usize,
}

impl std::fmt::Debug for TickPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TickPool")
            .field("threads", &self.threads())
            .finish()
    }
}

impl TickPool {
    /// The pool without workers: every call runs on the caller, in order (one core).
    pub fn serial() -> Arc<Self> {
        Arc::new(Self { workers: 0 })
    }

    /// A pool of `workers` threads beside the caller; `on_start(k)` runs first on worker `k`.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when `workers > MAX_WORKERS`.
    pub fn new(workers: usize, on_start: StartHook) -> Result<Arc<Self>, ModelError> {
        if workers > MAX_WORKERS {
            return Err(ModelError::InvalidInput(format!(
                "a tick pool takes at most {MAX_WORKERS} workers, not {workers}"
            )));
        }
        // The serial skeleton: workers arrive with the threaded implementation.
        let _ = on_start;
        Ok(Self::serial())
    }

    /// Threads that run a job: the workers plus the caller. Also the number of parts a body
    /// cuts a job into, so its arithmetic does not depend on scheduling.
    pub fn threads(&self) -> usize {
        self.workers + 1
    }

    /// Runs `f(p, &mut items[p])` once for every `p`, each on one thread, and returns when all
    /// are done. Allocation-free.
    pub fn for_each_mut<T: Send>(&self, items: &mut [T], f: &(dyn Fn(usize, &mut T) + Sync)) {
        for (p, item) in items.iter_mut().enumerate() {
            f(p, item);
        }
    }

    /// Runs `a` on the caller and `b` on a worker if one claims it (else on the caller after
    /// `a`); returns both results. Allocation-free.
    pub fn join<RA: Send, RB: Send>(
        &self,
        a: impl FnOnce() -> RA + Send,
        b: impl FnOnce() -> RB + Send,
    ) -> (RA, RB) {
        let ra = a();
        (ra, b())
    }

    /// What the pool has done so far.
    pub fn stats(&self) -> PoolStats {
        PoolStats::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn too_many_workers_are_refused() {
        let hook: StartHook = Arc::new(|_| {});
        assert!(TickPool::new(MAX_WORKERS + 1, hook.clone()).is_err());
        assert_eq!(TickPool::new(0, hook).unwrap().threads(), 1);
    }
}
