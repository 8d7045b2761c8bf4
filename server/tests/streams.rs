//! Surface streams in process (issue 17): compact frames decode to the full frames' positions
//! within half a quantum, a late joiner's first frame is a keyframe, `RequestKeyframe` gives a
//! keyframe with the topology, a watcher that does not read drops frames with bounded queues and
//! GetStats reports it (and no longer counts its queue once it leaves), compact frames with a
//! non-default quantum decode within half of it, and bad Watch requests get INVALID_ARGUMENT. No
//! assertion on timing.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use haptic_model::DVec3;
use haptic_server::ServerConfig;
use haptic_server::service::Services;
use haptic_server::servo::Command;
use haptic_server::session::{Session, SessionManager};
use haptics_proto::delta::DeltaCodec;
use haptics_proto::v1::session_control_server::SessionControl;
use haptics_proto::v1::surface_stream_server::SurfaceStream;
use haptics_proto::v1::{
    GetStatsRequest, KeyframeRequest, SurfaceEncoding, SurfaceFrame, WatchRequest,
};
use tokio_stream::StreamExt;

type Frames = haptic_server::stream::FrameStream;

async fn watch(services: &Services, id: &str, rate: f64, compact: bool) -> Frames {
    watch_q(services, id, rate, compact, 0.0).await
}

/// A watch with an explicit `quantum_m` (0: the default, 1 um).
async fn watch_q(
    services: &Services,
    id: &str,
    rate: f64,
    compact: bool,
    quantum_m: f64,
) -> Frames {
    services
        .watch(tonic::Request::new(WatchRequest {
            session_id: id.to_string(),
            max_rate_hz: rate,
            encoding: if compact {
                SurfaceEncoding::Delta as i32
            } else {
                SurfaceEncoding::Full as i32
            },
            quantum_m,
        }))
        .await
        .unwrap()
        .into_inner()
}

async fn next(frames: &mut Frames) -> SurfaceFrame {
    tokio::time::timeout(Duration::from_secs(20), frames.next())
        .await
        .expect("a frame within 20 s")
        .expect("stream open")
        .expect("frame")
}

fn push(session: &Session, force_y_n: f64) {
    session
        .send(Command::ApplyForce {
            point_m: DVec3::new(0.0, 0.00968, -0.005),
            force_n: DVec3::new(0.0, force_y_n, 0.0),
            duration_s: 0.4,
        })
        .unwrap();
}

fn start() -> (Arc<SessionManager>, Services, Arc<Session>) {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let scene = manager.load_scene("lv", "").unwrap();
    let session = manager.start(&scene).unwrap();
    (manager.clone(), Services::new(manager), session)
}

/// The positions of the first `count` frames of a FULL stream by simulated time (the bits of
/// `sim_time_s`), collected in a task; every frame must carry floats and no delta fields.
fn collect_full(mut full: Frames, count: usize) -> tokio::task::JoinHandle<HashMap<u64, Vec<f32>>> {
    tokio::spawn(async move {
        let mut by_time = HashMap::new();
        for _ in 0..count {
            let f = next(&mut full).await;
            assert_eq!(f.quantum_m, 0.0, "a FULL stream carries no delta fields");
            assert!(f.position_delta.is_empty());
            by_time.insert(f.sim_time_s.to_bits(), f.positions_m);
        }
        by_time
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compact_frames_decode_to_the_full_positions() {
    let (manager, services, session) = start();
    let full = watch(&services, &session.id, 60.0, false).await;
    let mut compact = watch(&services, &session.id, 60.0, true).await;
    push(&session, -0.05);
    let collect = collect_full(full, 60);
    let first = next(&mut compact).await;
    assert!(
        first.keyframe && !first.triangles.is_empty(),
        "keyframe first"
    );
    assert!(first.keyframe_id >= 1 && first.quantum_m == 1e-6);
    let n = first.positions_m.len() / 3;
    let codec = DeltaCodec::new(n, &first.triangles).unwrap();
    let mut reference = (first.keyframe_id, first.positions_m.clone());
    let mut decoded = Vec::new();
    let (mut deltas, mut keyframes, mut moving, mut chained) = (0, 1, 0, 0);
    for _ in 0..60 {
        let f = next(&mut compact).await;
        if f.keyframe {
            keyframes += 1;
            assert!(f.triangles.is_empty(), "same topology: no triangles again");
            if f.positions_m.is_empty() {
                // Chained: our reference plus the step.
                assert_eq!(f.base_keyframe_id, reference.0, "chained from what we have");
                let mut p = vec![0.0; 3 * n];
                codec
                    .decode(&reference.1, &f.reference_delta, f.quantum_m, &mut p)
                    .unwrap();
                reference = (f.keyframe_id, p);
                chained += 1;
            } else {
                reference = (f.keyframe_id, f.positions_m.clone());
            }
        } else {
            assert!(f.positions_m.is_empty(), "delta frames carry no floats");
            assert_eq!(f.keyframe_id, reference.0);
            deltas += 1;
        }
        if !f.position_delta.is_empty() {
            moving += 1;
        }
        let mut p = vec![0.0; 3 * n];
        codec
            .decode(&reference.1, &f.position_delta, f.quantum_m, &mut p)
            .unwrap();
        decoded.push((f.sim_time_s, p));
    }
    let by_time = collect.await.unwrap();
    let mut compared = 0;
    for (t, p) in &decoded {
        if let Some(q) = by_time.get(&t.to_bits()) {
            for (a, b) in p.iter().zip(q) {
                assert!((a - b).abs() <= 0.5e-6 + 1e-8, "{a} vs {b} at t = {t}");
            }
            compared += 1;
        }
    }
    manager.stop(&session.id).unwrap();
    assert!(
        compared >= 10,
        "only {compared} frames seen by both streams"
    );
    assert!(
        deltas > 0 && moving > 0,
        "{deltas} deltas, {moving} with motion"
    );
    eprintln!(
        "{compared} frames compared; {keyframes} keyframes ({chained} chained), {deltas} deltas"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compact_frames_with_a_coarser_quantum_decode_within_half_of_it() {
    const Q: f64 = 1e-5;
    let (manager, services, session) = start();
    let full = watch(&services, &session.id, 60.0, false).await;
    let mut compact = watch_q(&services, &session.id, 60.0, true, Q).await;
    push(&session, -0.05);
    let collect = collect_full(full, 60);
    let first = next(&mut compact).await;
    assert!(
        first.keyframe && !first.triangles.is_empty(),
        "keyframe first"
    );
    assert_eq!(first.quantum_m, Q);
    let n = first.positions_m.len() / 3;
    let codec = DeltaCodec::new(n, &first.triangles).unwrap();
    let mut reference = (first.keyframe_id, first.positions_m.clone());
    let mut decoded = Vec::new();
    let mut moving = 0;
    for _ in 0..60 {
        let f = next(&mut compact).await;
        assert_eq!(f.quantum_m, Q, "every frame in the asked quantum");
        if f.keyframe {
            // Chains are in 1 um steps only: a coarser stream gets float keyframes.
            assert!(f.reference_delta.is_empty() && f.positions_m.len() == 3 * n);
            reference = (f.keyframe_id, f.positions_m.clone());
        }
        assert_eq!(f.keyframe_id, reference.0);
        if !f.position_delta.is_empty() {
            moving += 1;
        }
        let mut p = vec![0.0; 3 * n];
        codec
            .decode(&reference.1, &f.position_delta, Q, &mut p)
            .unwrap();
        decoded.push((f.sim_time_s, p));
    }
    let by_time = collect.await.unwrap();
    manager.stop(&session.id).unwrap();
    let (mut compared, mut worst) = (0, 0.0f64);
    for (t, p) in &decoded {
        if let Some(q) = by_time.get(&t.to_bits()) {
            for (a, b) in p.iter().zip(q) {
                let e = f64::from((a - b).abs());
                assert!(e <= Q / 2.0 + 1e-8, "{a} vs {b} at t = {t}: {e:e} m");
                worst = worst.max(e);
            }
            compared += 1;
        }
    }
    assert!(
        compared >= 10,
        "only {compared} frames seen by both streams"
    );
    assert!(moving > 0, "no frame moved");
    // The quantum is really coarser: some error is above what a 1 um stream could have.
    assert!(worst > 0.5e-6 + 1e-8, "largest error {worst:e} m");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn late_joiners_and_requests_get_keyframes_and_slow_watchers_drop_frames() {
    let (manager, services, session) = start();
    let mut early = watch(&services, &session.id, 60.0, true).await;
    let first = next(&mut early).await;
    assert!(first.keyframe);
    // A watcher that never reads: its queue fills, then its due frames are dropped.
    let _slow = watch(&services, &session.id, 60.0, true).await;
    push(&session, 0.05);
    for _ in 0..30 {
        next(&mut early).await;
    }
    // A late joiner gets a keyframe with the topology at once.
    let mut late = watch(&services, &session.id, 30.0, true).await;
    let f = next(&mut late).await;
    assert!(f.keyframe && !f.triangles.is_empty() && !f.rest_positions_m.is_empty());
    // On demand: the next frame of that stream is a keyframe with the topology again.
    services
        .request_keyframe(tonic::Request::new(KeyframeRequest {
            session_id: session.id.clone(),
            watch_id: f.watch_id,
        }))
        .await
        .unwrap();
    let mut got = false;
    for _ in 0..3 {
        let g = next(&mut late).await;
        if g.keyframe && !g.triangles.is_empty() {
            got = true;
            break;
        }
    }
    assert!(got, "no keyframe after RequestKeyframe");
    let e = services
        .request_keyframe(tonic::Request::new(KeyframeRequest {
            session_id: session.id.clone(),
            watch_id: 0,
        }))
        .await
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::NotFound);
    let stats = services
        .get_stats(tonic::Request::new(GetStatsRequest {
            session_id: session.id.clone(),
        }))
        .await
        .unwrap()
        .into_inner();
    manager.stop(&session.id).unwrap();
    assert_eq!(stats.watchers, 3);
    assert!(stats.watcher_frames_dropped > 0, "{stats:?}");
    assert!(stats.watcher_frames_sent > 30 && stats.watcher_bytes_sent > 0);
    // Bounded: no watcher holds more than its limit (the slow one holds its whole queue).
    assert!(stats.watcher_queue_limit_bytes > 0);
    assert!(stats.watcher_queued_bytes <= 3 * stats.watcher_queue_limit_bytes);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watcher_after_a_gap_sees_the_current_surface_not_the_last_one_sent() {
    // The servo publishes frames only while someone watches; the channel keeps the frame of
    // the moment the last watcher left. A watcher that joins later must not be shown it.
    let (manager, services, session) = start();
    let mut first = watch(&services, &session.id, 60.0, false).await;
    let rest = next(&mut first).await;
    drop(first);
    // Nobody watches while a load dents the surface.
    push(&session, -0.05);
    let t0 = rest.sim_time_s;
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while session.stats().sim_time_s < t0 + 0.3 && std::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let mut second = watch(&services, &session.id, 60.0, false).await;
    let f = next(&mut second).await;
    manager.stop(&session.id).unwrap();
    assert!(f.keyframe, "a new watcher's first frame is a keyframe");
    assert!(
        f.sim_time_s >= t0 + 0.3,
        "stale first frame: sim time {} s, left at {} s",
        f.sim_time_s,
        t0
    );
    assert!(
        f.max_displacement_m > 1e-4,
        "the dent is not shown: {} m",
        f.max_displacement_m
    );
}

#[tokio::test]
async fn bad_watch_requests_are_invalid_arguments() {
    let (manager, services, session) = start();
    let bad = [
        (f64::NAN, 0, 0.0),
        (-1.0, 0, 0.0),
        (1e-300, 0, 0.0), // once a panic: a period of 1e300 s
        (30.0, 7, 0.0),
        (30.0, 1, f64::NAN),
        (30.0, 1, -1e-6),
        (30.0, 1, 1.0),
        (30.0, 1, 1e-12),
    ];
    for (rate, encoding, quantum) in bad {
        let e = services
            .watch(tonic::Request::new(WatchRequest {
                session_id: session.id.clone(),
                max_rate_hz: rate,
                encoding,
                quantum_m: quantum,
            }))
            .await
            .err()
            .unwrap_or_else(|| panic!("accepted {rate} {encoding} {quantum}"));
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e:?}");
    }
    // A huge rate is clamped, not refused.
    let mut ok = watch(&services, &session.id, 1e9, true).await;
    assert!(next(&mut ok).await.keyframe);
    manager.stop(&session.id).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disconnected_watcher_releases_its_queued_bytes() {
    // Regression (issue 17 audit): queued bytes were subtracted only when the transport took a
    // frame, so the frames still queued when a watcher left stayed counted for ever.
    let (manager, services, session) = start();
    let stats = || async {
        services
            .get_stats(tonic::Request::new(GetStatsRequest {
                session_id: session.id.clone(),
            }))
            .await
            .unwrap()
            .into_inner()
    };
    // A watcher that never reads: wait until its queue is full (a due frame was dropped).
    let slow = watch(&services, &session.id, 60.0, true).await;
    push(&session, 0.05);
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let full = loop {
        let s = stats().await;
        if s.watcher_frames_dropped > 0 || std::time::Instant::now() > deadline {
            break s;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert!(
        full.watcher_frames_dropped > 0,
        "the queue never filled: {full:?}"
    );
    assert_eq!(full.watchers, 1);
    assert!(
        full.watcher_queued_bytes > 0,
        "a full queue holds bytes: {full:?}"
    );
    drop(slow);
    // The watch task notices the closed stream at its next due frame (60 Hz).
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let after = loop {
        let s = stats().await;
        if s.watchers == 0 || std::time::Instant::now() > deadline {
            break s;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    manager.stop(&session.id).unwrap();
    assert_eq!(after.watchers, 0, "{after:?}");
    assert_eq!(
        after.watcher_queued_bytes, 0,
        "bytes of the dropped queue still counted: {after:?}"
    );
    assert!(after.watcher_frames_sent >= 2, "{after:?}");
}
