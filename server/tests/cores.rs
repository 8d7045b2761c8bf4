//! Cores per session (issue 48 section 1): in `threads = "auto"` a session gets the threads its
//! body asks for and holds the cores of the `cpus` list that are free, fewer (never less than
//! one, never waiting) when they are not, takes the rest as other sessions give them back, and
//! gives them back when it stops or is quarantined.

use crate::common;

use std::sync::atomic::Ordering;
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
    assert_eq!(b.tick_threads, 2, "none free: started at once all the same");
    assert_eq!(
        manager.reserved_cores(),
        (3, 2),
        "b holds its servo thread's core only"
    );
    let c = manager.start_body(wanting(1, None)).unwrap();
    assert_eq!(c.tick_threads, 1);
    // GetStats says how many work once the servo has published (every 100 ticks): a lends
    // its worker out while b and c hold cores beyond the two, and takes it back after.
    let lent = || a.stats().threads == 1 && b.stats().threads == 1;
    assert!(common::wait_for(lent, Duration::from_secs(5)).await);
    manager.stop(&c.id).unwrap();
    manager.stop(&b.id).unwrap();
    assert_eq!(manager.reserved_cores(), (2, 2));
    let back = common::wait_for(|| a.stats().threads == 2, Duration::from_secs(5)).await;
    assert!(back, "{:?}", a.stats().threads);
    // A session started on a full budget takes the cores it wants once they are given back.
    let b = manager.start_body(wanting(2, None)).unwrap();
    assert_eq!(manager.reserved_cores(), (3, 2));
    manager.stop(&a.id).unwrap();
    let grown = || b.stats().threads == 2 && manager.reserved_cores() == (2, 2);
    let grown = common::wait_for(grown, Duration::from_secs(5)).await;
    assert!(
        grown,
        "{:?} {:?}",
        b.stats().threads,
        manager.reserved_cores()
    );
    let d = manager.start_body(wanting(2, None)).unwrap();
    assert_eq!(
        manager.reserved_cores(),
        (3, 2),
        "d holds one core: none is free"
    );
    let shared = || b.stats().threads == 1 && d.stats().threads == 1;
    assert!(common::wait_for(shared, Duration::from_secs(5)).await);
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

/// A body that keeps a thread busy beside its tick (a region cache being built): on two CPUs
/// its session reserves both but lends its worker out (parked, no part of a tick) until the
/// background work is done, then ticks on both; on three both work from the start.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_threads_lend_a_worker_to_the_bodys_background_thread_until_it_is_done() {
    for (cpus, working) in [("[0, 1]", 1), ("[0, 1, 2]", 2)] {
        let mut body = common::Burdened::wanting(common::builtin_body("ellipsoids"), 2, None);
        body.background.store(1, Ordering::Relaxed);
        body.part_us = 100;
        let (background, pool) = (body.background.clone(), body.pool.clone());
        let manager = SessionManager::new(config(&format!("threads = \"auto\"\ncpus = {cpus}")));
        let a = manager.start_body(Box::new(body)).unwrap();
        assert_eq!(
            a.tick_threads, 2,
            "cpus {cpus}: the tick's cores are reserved"
        );
        assert_eq!(manager.reserved_cores().0, 2, "cpus {cpus}");
        let pool = pool.get().expect("a tick pool").clone();
        assert_eq!(pool.active_workers(), working - 1, "cpus {cpus}");
        // GetStats says how many work, once the servo has published (every 100 ticks).
        let ticked = || a.stats().steps > 1000 && a.stats().threads != 0;
        assert!(common::wait_for(ticked, Duration::from_secs(10)).await);
        assert_eq!(a.stats().threads, working as u32, "cpus {cpus}");
        let on_workers = pool.stats().parts_on_workers;
        assert_eq!(
            on_workers == 0,
            working == 1,
            "cpus {cpus}: {:?}",
            pool.stats()
        );
        // The background work is done: the worker comes back within a statistics window.
        background.store(0, Ordering::Relaxed);
        let both = || a.stats().threads == 2 && pool.stats().parts_on_workers > on_workers;
        let back = common::wait_for(both, Duration::from_secs(10)).await;
        assert!(
            back,
            "cpus {cpus}: {:?} {:?}",
            a.stats().threads,
            pool.stats()
        );
        assert_eq!(pool.active_workers(), 1);
        manager.stop_all();
        assert_eq!(manager.reserved_cores().0, 0);
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
