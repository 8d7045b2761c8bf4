//! Shared by the overrun tests and the `yielding` benchmark (`#[path]`-included there): a body
//! too heavy for the machine, built-in bodies, waiting, and one measured run of a genuine LV.

#![allow(dead_code)] // each includer uses its part

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

use haptic_model::body::{
    BodyInfo, BodyStats, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput, TickOutput,
};
use haptic_model::{DVec3, ModelError};
use haptic_server::session::{Session, SessionManager};

/// A real body whose tick takes `extra` longer: asleep (a model too slow for the machine,
/// made deterministic) or spinning (one that also takes the CPU from everyone else); it asks
/// for `threads` threads and, with `fail_at`, fails its tick from that tick on (a fault
/// quarantines the session).
pub struct Burdened {
    /// The real body.
    pub body: Box<dyn SoftBody>,
    /// Extra time per tick.
    pub extra: Duration,
    /// Spin the CPU for it (true) or sleep.
    pub spin: bool,
    /// What [`SoftBody::wants_threads`] answers.
    pub threads: usize,
    /// What [`SoftBody::background_threads`] answers (the test may change it meanwhile).
    pub background: Arc<AtomicUsize>,
    /// The tick pool the session handed the body ([`SoftBody::set_tick_pool`]).
    pub pool: Arc<OnceLock<Arc<haptic_model::pool::TickPool>>>,
    /// With a pool, each tick also runs one part of this many microseconds per pool thread
    /// on it (the pool kept hot through the tick, as the models do).
    pub part_us: u64,
    /// The tick (counted from 1) from which every tick fails.
    pub fail_at: Option<u64>,
    /// Ticks so far.
    pub ticks: u64,
}

impl Burdened {
    /// Sleeps `extra` per tick.
    pub fn sleeping(body: Box<dyn SoftBody>, extra: Duration) -> Self {
        Self {
            body,
            extra,
            spin: false,
            threads: 1,
            background: Arc::new(AtomicUsize::new(0)),
            pool: Arc::new(OnceLock::new()),
            part_us: 0,
            fail_at: None,
            ticks: 0,
        }
    }

    /// No extra time; asks for `threads` threads and fails from tick `fail_at` on.
    #[allow(dead_code)]
    pub fn wanting(body: Box<dyn SoftBody>, threads: usize, fail_at: Option<u64>) -> Self {
        Self {
            threads,
            fail_at,
            ..Self::sleeping(body, Duration::ZERO)
        }
    }
}

impl SoftBody for Burdened {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        self.ticks += 1;
        if self.fail_at.is_some_and(|t| self.ticks >= t) {
            return Err(ModelError::InvalidInput("a test fault".into()));
        }
        if self.spin {
            let t0 = Instant::now();
            while t0.elapsed() < self.extra {
                std::hint::spin_loop();
            }
        } else if !self.extra.is_zero() {
            std::thread::sleep(self.extra);
        }
        if let Some(pool) = self.pool.get().filter(|_| self.part_us > 0) {
            let _hot = pool.hot();
            let mut parts = [0_u8; haptic_model::pool::MAX_WORKERS + 1];
            let part = Duration::from_micros(self.part_us);
            pool.for_each_mut(&mut parts[..pool.threads()], &|_, _| {
                let t0 = Instant::now();
                while t0.elapsed() < part {
                    std::hint::spin_loop();
                }
            });
        }
        self.body.tick(input)
    }
    fn add_point_load(&mut self, p: DVec3, f: DVec3, d: f64) -> Result<(), ModelError> {
        self.body.add_point_load(p, f, d)
    }
    fn surface_topology(&self) -> SurfaceTopology<'_> {
        self.body.surface_topology()
    }
    fn surface_capacity(&self) -> SurfaceCapacity {
        self.body.surface_capacity()
    }
    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        self.body.write_surface_positions(out)
    }
    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        self.body.write_surface_rest_positions(out)
    }
    fn stats(&self) -> BodyStats {
        self.body.stats()
    }
    fn info(&self) -> BodyInfo {
        self.body.info()
    }
    fn wants_threads(&self) -> usize {
        self.threads
    }

    fn background_threads(&self) -> usize {
        self.background.load(Ordering::Relaxed)
    }

    fn set_tick_pool(&mut self, pool: Arc<haptic_model::pool::TickPool>) {
        let _ = self.pool.set(pool);
    }
}

/// Starts `n` heavy sessions in `manager`: the default LV plus 3 ms of CPU spinning a tick
/// (about 220 Hz on two cores, never keeping up).
pub fn start_heavy(manager: &SessionManager, n: usize) -> Vec<std::sync::Arc<Session>> {
    (0..n)
        .map(|_| {
            manager
                .start_body(Box::new(Burdened {
                    spin: true,
                    ..Burdened::sleeping(lv_body(), Duration::from_millis(3))
                }))
                .expect("a heavy session")
        })
        .collect()
}

/// A built-in scene's body.
pub fn builtin_body(name: &str) -> Box<dyn SoftBody> {
    let scene = haptic_model::scene::load_builtin(name).unwrap();
    haptic_model::build_body(&scene).unwrap()
}

/// The default LV's body.
pub fn lv_body() -> Box<dyn SoftBody> {
    builtin_body("lv")
}

/// Polls `done` every 20 ms until it holds or `limit` passes; its last answer.
pub async fn wait_for(mut done: impl FnMut() -> bool, limit: Duration) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        if done() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    done()
}

/// Loop rate (ticks per second of wall time over the run) and step p99 (µs) of a genuine
/// session run alone in `manager` for `run`, then stopped.
pub async fn genuine_run(manager: &SessionManager, run: Duration) -> (f64, f64) {
    // The LV epicardium as a mass-spring surface: about 0.1 ms a tick, it fits in 1 ms here.
    let s = manager
        .start_body(builtin_body("lv-surface-springs"))
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (t0, steps0) = (Instant::now(), s.stats().steps);
    tokio::time::sleep(run).await;
    let st = s.stats();
    let rate = (st.steps - steps0) as f64 / t0.elapsed().as_secs_f64();
    manager.stop(&s.id).unwrap();
    (rate, st.step_p99_us)
}
