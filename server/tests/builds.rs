//! Scene builds are bounded (issue 16, section 2; `haptic_server::builds`): a client over its
//! limits is refused at once without disturbing another client, no more builds than the pool
//! allows run together, and a call past its deadline is refused while the session its build
//! makes later is stopped. Builds here are closures that sleep, then start the built-in `lv`
//! (or fail), so the timing is the test's own.

use std::net::IpAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use haptic_server::builds::{BuildGate, BuildLimits};
use haptic_server::config::ServerConfig;
use haptic_server::error::ServerError;
use haptic_server::session::{Session, SessionManager};

fn limits(concurrent: usize, per_client: usize, sessions: usize, timeout_ms: u64) -> BuildLimits {
    BuildLimits {
        max_concurrent_builds: concurrent,
        max_builds_per_client: per_client,
        max_sessions_per_client: sessions,
        build_timeout: Duration::from_millis(timeout_ms),
    }
}

fn client(last: u8) -> Option<IpAddr> {
    Some(IpAddr::from([10, 0, 0, last]))
}

/// A build that sleeps `ms`, then starts the built-in `lv`.
fn slow_lv(
    manager: &Arc<SessionManager>,
    ms: u64,
) -> impl FnOnce() -> Result<Arc<Session>, ServerError> + Send + 'static {
    let m = manager.clone();
    move || {
        std::thread::sleep(Duration::from_millis(ms));
        let scene = m.load_scene("lv", "")?;
        m.start(&scene)
    }
}

fn manager() -> Arc<SessionManager> {
    Arc::new(SessionManager::new(ServerConfig::default()))
}

/// A call's result, printable (sessions are not `Debug`).
fn shown(r: &Result<Arc<Session>, ServerError>) -> String {
    match r {
        Ok(s) => format!("session {}", s.id),
        Err(e) => format!("{e:?}"),
    }
}

fn exhausted(r: Result<Arc<Session>, ServerError>, limit: &str) {
    match r {
        Err(ServerError::Exhausted(m)) => assert!(m.contains(limit), "{m}"),
        other => panic!(
            "expected RESOURCE_EXHAUSTED naming {limit}, got {}",
            shown(&other)
        ),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_over_its_limits_is_refused_at_once_and_others_are_not() {
    let m = manager();
    let gate = Arc::new(BuildGate::new(limits(2, 1, 2, 10_000)));
    // Client 1 has a build in flight: its second call is refused at once, client 2's is not.
    let first = {
        let (gate, m) = (gate.clone(), m.clone());
        tokio::spawn(async move { gate.run(client(1), &m, slow_lv(&m, 400)).await })
    };
    tokio::time::sleep(Duration::from_millis(100)).await;
    let t = Instant::now();
    exhausted(
        gate.run(client(1), &m, slow_lv(&m, 0)).await,
        "max_builds_per_client",
    );
    assert!(
        t.elapsed() < Duration::from_millis(200),
        "not refused at once"
    );
    let other = gate.run(client(2), &m, slow_lv(&m, 0)).await.unwrap();
    let one = first.await.unwrap().unwrap();
    // Two sessions per client: the third is refused until one stops.
    let two = gate.run(client(1), &m, slow_lv(&m, 0)).await.unwrap();
    exhausted(
        gate.run(client(1), &m, slow_lv(&m, 0)).await,
        "max_sessions_per_client",
    );
    m.stop(&one.id).unwrap();
    let three = gate.run(client(1), &m, slow_lv(&m, 0)).await.unwrap();
    for s in [&other, &two, &three] {
        m.stop(&s.id).unwrap();
    }
    assert!(m.ids().is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_more_builds_than_the_pool_run_together() {
    let m = manager();
    let gate = Arc::new(BuildGate::new(limits(1, 8, 8, 10_000)));
    let running = Arc::new(AtomicUsize::new(0));
    let most = Arc::new(AtomicUsize::new(0));
    let calls: Vec<_> = (1..=4)
        .map(|c| {
            let (gate, m) = (gate.clone(), m.clone());
            let (running, most) = (running.clone(), most.clone());
            tokio::spawn(async move {
                gate.run(client(c), &m, move || {
                    let now = running.fetch_add(1, Ordering::SeqCst) + 1;
                    most.fetch_max(now, Ordering::SeqCst);
                    std::thread::sleep(Duration::from_millis(100));
                    running.fetch_sub(1, Ordering::SeqCst);
                    Err(ServerError::InvalidArgument("no scene".into()))
                })
                .await
            })
        })
        .collect();
    for c in calls {
        // Each build ran and its own error came back.
        assert!(matches!(
            c.await.unwrap(),
            Err(ServerError::InvalidArgument(_))
        ));
    }
    assert_eq!(most.load(Ordering::SeqCst), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_call_past_its_deadline_is_refused_and_the_late_session_stopped() {
    let m = manager();
    // The deadline leaves a plain LV build room on a loaded 2-core machine (the other tests of
    // this binary run live 1 kHz sessions beside it: 150 ms was too tight once, 2026-11-23; a
    // debug-profile LV build took 300-680 ms in the VM's fast and slow modes, 2026-11-25, so
    // 400 ms failed there too).
    let gate = Arc::new(BuildGate::new(limits(1, 8, 8, 1_500)));
    // The build outlives the deadline: refused at the deadline (1.5 s), not when the build ends
    // (after 4 s).
    let t = Instant::now();
    let late = gate.run(client(1), &m, slow_lv(&m, 4_000)).await;
    assert!(
        matches!(&late, Err(ServerError::DeadlineExceeded(msg)) if msg.contains("did not build")),
        "{}",
        shown(&late)
    );
    assert!(
        t.elapsed() < Duration::from_millis(3_000),
        "{:?}",
        t.elapsed()
    );
    // While it still builds (holding the only turn), a second call times out waiting.
    let waiting = gate.run(client(2), &m, slow_lv(&m, 0)).await;
    assert!(
        matches!(&waiting, Err(ServerError::DeadlineExceeded(msg)) if msg.contains("turn")),
        "{}",
        shown(&waiting)
    );
    // The late build's session was stopped as soon as it existed.
    let t = Instant::now();
    while t.elapsed() < Duration::from_secs(10) {
        tokio::time::sleep(Duration::from_millis(50)).await;
        if m.ids().is_empty() && gate.run(client(3), &m, slow_lv(&m, 0)).await.is_ok() {
            break;
        }
    }
    // One session: the last call's, which got a turn once the late build gave it back.
    let ids = m.ids();
    assert_eq!(ids.len(), 1, "{ids:?}");
    m.stop_all();
}
