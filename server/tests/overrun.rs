//! The overrun policy (issue 16, section 2): a session whose servo cannot keep its rate is
//! reported, and with `overrun_policy = "degrade"` quarantined (zero force, a fault naming the
//! policy) after a second below 90 % of its rate, while a session that keeps up is left alone.
//! The slow session is the built-in LV with 3 ms of extra work per tick (a model too heavy for
//! the machine, made deterministic). And the protection of the sessions that keep up: six
//! heavy sessions that also spin the CPU yield (`SCHED_IDLE`) to an LV that fits, whose loop
//! rate stays within 10 % of its own alone.

mod common;

use std::time::{Duration, Instant};

use common::{Burdened, genuine_run, lv_body, start_heavy, wait_for};
use haptic_server::ServerConfig;
use haptic_server::config::OverrunPolicy;
use haptic_server::session::SessionManager;

/// The tests of this file run one at a time: the yielding test compares loop rates and step
/// times, which the others' sessions would disturb.
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_session_that_cannot_keep_its_rate_is_quarantined_under_degrade_only() {
    let _serial = SERIAL.lock().await;
    for policy in [OverrunPolicy::Report, OverrunPolicy::Degrade] {
        let mut config = ServerConfig::default();
        config.servo.overrun_policy = policy;
        config.servo.stats_every_ticks = 20;
        let manager = SessionManager::new(config);
        let slow = manager
            .start_body(Box::new(Burdened::sleeping(
                lv_body(),
                Duration::from_millis(3),
            )))
            .unwrap();
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
    let _serial = SERIAL.lock().await;
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

/// Issue 16, section 2: heavy sessions next to the LV yield, and leave the LV's loop rate
/// within 10 % of its own alone. "Alone" is measured before and after (the machine's noise in
/// the same minute), and the LV beside the heavy sessions is compared with the worse of the
/// two. The step p99 of a 3 s run varies by up to a third between two runs alone on these
/// shared 2-core machines (about 0.1 ms), and where the LV step is shorter the machine's own
/// spikes dominate it (a Zen 5 with AVX-512: 50 to 117 us alone, four runs), so this test
/// only bounds it at 1.5 times or a tenth of the tick more, whichever is larger (a session
/// that did not yield would cost the LV milliseconds); the 10 % target is met as a median
/// over interleaved repetitions in `cargo bench -p haptic-server --bench yielding`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heavy_sessions_yield_to_the_lv_that_keeps_up() {
    let _serial = SERIAL.lock().await;
    let run = Duration::from_secs(3);
    let mut config = ServerConfig::default();
    config.servo.stats_every_ticks = 20;
    let manager = SessionManager::new(config);
    let before = genuine_run(&manager, run).await;
    // Six heavy sessions (the LV plus 3 ms of CPU work a tick, about 220 Hz) on two cores:
    // each is judged overrunning after a second and its servo thread yields (SCHED_IDLE).
    let heavy = start_heavy(&manager, 6);
    assert!(
        wait_for(
            || heavy.iter().all(|h| h.stats().demoted),
            Duration::from_secs(30)
        )
        .await,
        "heavy sessions not demoted: {:?}",
        heavy.iter().map(|h| h.stats().demoted).collect::<Vec<_>>()
    );
    assert!(heavy.iter().all(|h| h.stats().overrunning));
    let (rate_beside, p99_beside) = genuine_run(&manager, run).await;
    // Alone again, a heavy session is restored: there is nobody to yield to.
    for h in &heavy[1..] {
        manager.stop(&h.id).unwrap();
    }
    assert!(
        wait_for(|| !heavy[0].stats().demoted, Duration::from_secs(10)).await,
        "the last heavy session stayed demoted (restoring needs CAP_SYS_NICE)"
    );
    manager.stop(&heavy[0].id).unwrap();
    let after = genuine_run(&manager, run).await;
    println!(
        "the LV alone: {:.0} / {:.0} Hz, step p99 {} / {} us (before / after); beside six \
         heavy sessions: {rate_beside:.0} Hz, step p99 {p99_beside} us",
        before.0, after.0, before.1, after.1
    );
    let (rate_alone, p99_alone) = (before.0.min(after.0), before.1.max(after.1));
    assert!(
        rate_beside >= 0.9 * rate_alone,
        "loop rate {rate_beside:.0} Hz beside the heavy sessions, {rate_alone:.0} Hz alone"
    );
    let p99_bound = (1.5 * p99_alone).max(p99_alone + 100.0);
    assert!(
        p99_beside <= p99_bound,
        "step p99 {p99_beside} us beside the heavy sessions, {p99_alone} us alone (bound {p99_bound} us)"
    );
    manager.stop_all();
}
