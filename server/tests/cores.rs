//! Cores per session (issue 48 section 1): in `threads = "auto"` a session gets the threads its
//! body asks for while cores of the `cpus` list are free, fewer (never less than one, never
//! waiting) when they are not, and gives them back when it stops or is quarantined.

use crate::common;

use std::time::Duration;

use haptic_model::body::SoftBody;
use haptic_server::config::{ConfigFile, ServerConfig};
use haptic_server::session::SessionManager;

fn wanting(threads: usize, fail_at: Option<u64>) -> Box<dyn SoftBody> {
    Box::new(common::Burdened::wanting(
        common::builtin_body("ellipsoids"),
        threads,
        fail_at,
    ))
}

fn config(servo: &str) -> ServerConfig {
    ConfigFile::parse(&format!("[servo]\n{servo}"))
        .unwrap()
        .into_config()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_threads_share_the_listed_cpus_and_come_back_when_a_session_stops() {
    let manager = SessionManager::new(config("threads = \"auto\"\ncpus = [0, 1]"));
    assert_eq!(manager.reserved_cores(), (0, 2));
    let a = manager.start_body(wanting(2, None)).unwrap();
    assert_eq!(a.tick_threads, 2, "both listed CPUs are free");
    let b = manager.start_body(wanting(2, None)).unwrap();
    assert_eq!(
        b.tick_threads, 1,
        "none free: fewer threads, started at once"
    );
    assert_eq!(manager.reserved_cores(), (3, 2));
    let c = manager.start_body(wanting(1, None)).unwrap();
    assert_eq!(c.tick_threads, 1);
    // GetStats says the same once the servo has published (every 100 ticks).
    let published = common::wait_for(|| a.stats().threads != 0, Duration::from_secs(5)).await;
    assert!(published);
    assert_eq!(a.stats().threads, 2);
    manager.stop(&a.id).unwrap();
    assert_eq!(manager.reserved_cores(), (2, 2), "a's two cores came back");
    manager.stop(&c.id).unwrap();
    let d = manager.start_body(wanting(2, None)).unwrap();
    assert_eq!(d.tick_threads, 1, "b holds one core: one is free");
    manager.stop(&b.id).unwrap();
    manager.stop(&d.id).unwrap();
    assert_eq!(manager.reserved_cores(), (0, 2));
    // A quarantined session's body no longer steps: its cores come back too.
    let e = manager.start_body(wanting(2, Some(20))).unwrap();
    assert_eq!(e.tick_threads, 2);
    let released =
        common::wait_for(|| manager.reserved_cores().0 == 0, Duration::from_secs(5)).await;
    assert!(released, "{:?} {:?}", manager.reserved_cores(), e.stats());
    assert!(e.stats().fault.is_some() || e.stats().steps == 0);
    let f = manager.start_body(wanting(2, None)).unwrap();
    assert_eq!(f.tick_threads, 2);
    manager.stop_all();
    assert_eq!(manager.reserved_cores(), (0, 2));
}

/// A body that keeps a thread busy beside its tick (a region cache being built) gets one core
/// less in `auto`: on two CPUs it ticks alone, on three with the worker it asks for; it
/// reserves its tick's cores only.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_threads_leave_a_core_to_the_bodys_background_thread() {
    let busy = || {
        let mut body = common::Burdened::wanting(common::builtin_body("ellipsoids"), 2, None);
        body.background = 1;
        Box::new(body)
    };
    for (cpus, expected) in [("[0, 1]", 1), ("[0, 1, 2]", 2)] {
        let manager = SessionManager::new(config(&format!("threads = \"auto\"\ncpus = {cpus}")));
        let a = manager.start_body(busy()).unwrap();
        assert_eq!(a.tick_threads, expected, "cpus {cpus}");
        // The background thread is not reserved (it idles once the cache is full).
        assert_eq!(
            manager.reserved_cores().0,
            a.tick_threads as usize,
            "cpus {cpus}"
        );
        manager.stop_all();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fixed_thread_count_is_given_whatever_is_free() {
    let manager = SessionManager::new(config("threads = 2\ncpus = [0]"));
    let a = manager.start_body(wanting(1, None)).unwrap();
    let b = manager.start_body(wanting(1, None)).unwrap();
    assert_eq!((a.tick_threads, b.tick_threads), (2, 2));
    assert_eq!(manager.reserved_cores(), (4, 1));
    manager.stop_all();
    assert_eq!(manager.reserved_cores(), (0, 1));
}
