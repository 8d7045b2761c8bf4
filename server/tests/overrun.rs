//! The overrun policy (issue 16, section 2): a session whose servo cannot keep its rate is
//! reported, and with `overrun_policy = "degrade"` quarantined (zero force, a fault naming the
//! policy) after a second below 90 % of its rate, while a session that keeps up is left alone.
//! The slow session is the built-in LV with 3 ms of extra work per tick (a model too heavy for
//! the machine, made deterministic).

use std::time::{Duration, Instant};

use haptic_model::body::{
    BodyInfo, BodyStats, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput, TickOutput,
};
use haptic_model::{DVec3, ModelError};
use haptic_server::ServerConfig;
use haptic_server::config::OverrunPolicy;
use haptic_server::session::SessionManager;

/// A real body whose tick takes 3 ms longer.
struct Slow(Box<dyn SoftBody>);

impl SoftBody for Slow {
    fn tick(&mut self, input: &TickInput) -> Result<TickOutput, ModelError> {
        std::thread::sleep(Duration::from_millis(3));
        self.0.tick(input)
    }
    fn add_point_load(&mut self, p: DVec3, f: DVec3, d: f64) -> Result<(), ModelError> {
        self.0.add_point_load(p, f, d)
    }
    fn surface_topology(&self) -> SurfaceTopology<'_> {
        self.0.surface_topology()
    }
    fn surface_capacity(&self) -> SurfaceCapacity {
        self.0.surface_capacity()
    }
    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        self.0.write_surface_positions(out)
    }
    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        self.0.write_surface_rest_positions(out)
    }
    fn stats(&self) -> BodyStats {
        self.0.stats()
    }
    fn info(&self) -> BodyInfo {
        self.0.info()
    }
}

fn lv_body() -> Box<dyn SoftBody> {
    let scene = haptic_model::scene::load_builtin("lv").unwrap();
    haptic_model::build_body(&scene).unwrap()
}

async fn wait_for(mut done: impl FnMut() -> bool, limit: Duration) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        if done() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    done()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_that_cannot_keep_its_rate_is_quarantined_under_degrade_only() {
    for policy in [OverrunPolicy::Report, OverrunPolicy::Degrade] {
        let mut config = ServerConfig::default();
        config.servo.overrun_policy = policy;
        config.servo.stats_every_ticks = 20;
        let manager = SessionManager::new(config);
        let slow = manager.start_body(Box::new(Slow(lv_body()))).unwrap();
        // About 250 ticks per second: judged after a second below 900 Hz.
        match policy {
            OverrunPolicy::Report => {
                assert!(wait_for(|| slow.stats().steps > 600, Duration::from_secs(30)).await);
                let st = slow.stats();
                assert!(st.loop_rate_hz < 500.0, "not slow: {} Hz", st.loop_rate_hz);
                assert!(st.fault.is_none(), "{:?}", st.fault);
            }
            OverrunPolicy::Degrade => {
                let t0 = Instant::now();
                assert!(
                    wait_for(|| slow.stats().fault.is_some(), Duration::from_secs(30)).await,
                    "not quarantined"
                );
                assert!(
                    t0.elapsed() >= Duration::from_millis(900),
                    "judged before a second"
                );
                let fault = slow.stats().fault.unwrap();
                assert!(fault.contains("overrun policy"), "{fault}");
            }
        }
        manager.stop_all();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_that_keeps_up_is_not_quarantined() {
    let mut config = ServerConfig::default();
    config.servo.overrun_policy = OverrunPolicy::Degrade;
    // Judged against a fifth of the nominal rate so that a loaded 2-core test machine (the
    // LV tick is about 0.4 ms) does not trip it.
    config.servo.min_rate_fraction = 0.2;
    let manager = SessionManager::new(config);
    let s = manager.start_body(lv_body()).unwrap();
    assert!(wait_for(|| s.stats().steps > 2500, Duration::from_secs(30)).await);
    assert!(s.stats().fault.is_none(), "{:?}", s.stats().fault);
    manager.stop_all();
}
