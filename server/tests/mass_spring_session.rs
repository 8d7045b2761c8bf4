//! The mass-spring family through the server (issue 18): a probe pressing the built-in
//! `hemisphere-springs` subdivides the surface around the contact node and, once it has left
//! and the area is back at rest, coarsens it again. The servo follows every topology change in
//! its snapshots without allocating (events included), a viewer watching the session gets a
//! new keyframe with the subdivided surface and another with the coarse one, and `GetStats`
//! reports the current node count (`surface_vertices`: every node of this family is a surface
//! vertex; `nodes` stays the count at the start of the session).

use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use haptic_model::DVec3;
use haptic_model::body::SoftBody;
use haptic_server::ServerConfig;
use haptic_server::service::Services;
use haptic_server::servo::{self, Clock, Pose, ServoCore, ServoHandles, SessionShared};
use haptic_server::session::SessionManager;
use haptics_proto::v1::session_control_server::SessionControl;
use haptics_proto::v1::surface_stream_server::SurfaceStream;
use haptics_proto::v1::{GetStatsRequest, ListScenesRequest, WatchRequest};
use tokio_stream::StreamExt;

use crate::counting_alloc;
use counting_alloc::counted;

/// The hemisphere's apex (rest position and outward normal), the probe radius.
fn apex() -> (DVec3, DVec3, f64) {
    let scene = haptic_model::scene::load_builtin("hemisphere-springs").expect("scene");
    let ms = scene.mass_spring.expect("mass-spring");
    (
        ms.surface.rest()[0],
        ms.surface.rest_normal(0),
        scene.probe.radius_m,
    )
}

/// The device path over the apex `(p, n, r)` ([`apex`]): 10 mm above it for 0.2 s, then 4 mm
/// into it over 0.2 s, held to 0.6 s, then 20 mm away.
fn device_at((p, n, r): (DVec3, DVec3, f64), t_s: f64) -> DVec3 {
    if t_s < 0.2 {
        p + n * (r + 0.01)
    } else if t_s < 0.6 {
        p + n * (r - 4e-3 * ((t_s - 0.2) / 0.2).min(1.0))
    } else {
        p + n * (r + 0.02)
    }
}

struct ManualClock(Cell<u64>);
impl Clock for ManualClock {
    fn now_us(&self) -> u64 {
        let t = self.0.get();
        self.0.set(t + 5);
        t
    }
}

#[test]
fn the_servo_follows_subdivision_and_coarsening_without_allocating() {
    let scene = haptic_model::scene::load_builtin("hemisphere-springs").expect("scene");
    let body: Box<dyn SoftBody> = haptic_model::build_body(&scene).expect("body");
    let coarse_vertices = body.surface_topology().vertex_count;
    let shared = Arc::new(SessionShared::default());
    let (ends, handles) = servo::channels(body.as_ref());
    let ServoHandles {
        pose: mut pose_in,
        snapshot: mut snap_out,
        ..
    } = handles;
    let mut core = ServoCore::new(body, ends, shared.clone(), 1, 10);
    shared.watchers.store(1, Ordering::Relaxed);
    let clock = ManualClock(Cell::new(0));
    let mut allocations = 0;
    let mut seen: Vec<(u64, usize)> = Vec::new();
    let apex = apex();
    for k in 0..2500 {
        pose_in.write(Pose {
            seq: k,
            position_m: device_at(apex, k as f64 * 1e-3),
            connected: true,
            ..Pose::default()
        });
        let now = clock.now_us();
        allocations += counted(|| core.tick(now, &clock)).1;
        snap_out.update();
        let s = snap_out.output_buffer();
        let vertices = s.positions_m.len() / 3;
        assert_eq!(s.rest_positions_m.len(), s.positions_m.len());
        assert!(s.triangles.iter().all(|&i| (i as usize) < vertices));
        if seen.last().map(|v| v.0) != Some(s.topology_version) {
            seen.push((s.topology_version, vertices));
        }
    }
    assert_eq!(allocations, 0, "a servo tick allocated (versions {seen:?})");
    // Coarse, subdivided while pressed, coarse again after the probe left.
    assert!(seen.len() >= 3, "{seen:?}");
    assert_eq!(seen[0].1, coarse_vertices);
    assert!(seen[1].1 > coarse_vertices, "{seen:?}");
    assert_eq!(seen.last().unwrap().1, coarse_vertices, "{seen:?}");
}

#[tokio::test]
async fn a_viewer_gets_keyframes_when_the_probe_subdivides_the_surface() {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let scene = manager.load_scene("hemisphere-springs", "").expect("scene");
    let session = manager.start(&scene).expect("session");
    let services = Services::new(manager.clone());
    let listed = services
        .list_scenes(tonic::Request::new(ListScenesRequest {}))
        .await
        .expect("list")
        .into_inner();
    for name in ["hemisphere-springs", "lv-surface-springs"] {
        assert!(
            listed.scenes.iter().any(|s| s.name == name),
            "{name} not listed"
        );
    }
    let response = services
        .watch(tonic::Request::new(WatchRequest {
            session_id: session.id.clone(),
            max_rate_hz: 100.0,
            ..WatchRequest::default()
        }))
        .await
        .expect("watch");
    let mut frames = response.into_inner();
    // The device: attach and drive the pose slot as the DeviceLink stream task does.
    let (tx, _rx) = tokio::sync::mpsc::channel(16);
    let mut pose = session.attach_device(tx).expect("device");
    let apex = apex();
    let start = tokio::time::Instant::now();
    let driver = tokio::spawn(async move {
        let mut seq = 0;
        while start.elapsed() < Duration::from_secs(4) {
            seq += 1;
            pose.write(Pose {
                seq,
                position_m: device_at(apex, start.elapsed().as_secs_f64()),
                connected: true,
                ..Pose::default()
            });
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    });
    let mut keyframes = Vec::new();
    let mut stats_vertices = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while keyframes.len() < 3 && tokio::time::Instant::now() < deadline {
        let Ok(Some(frame)) = tokio::time::timeout(Duration::from_secs(5), frames.next()).await
        else {
            break;
        };
        let frame = frame.expect("frame");
        let vertices = frame.positions_m.len() / 3;
        let stats = services
            .get_stats(tonic::Request::new(GetStatsRequest {
                session_id: session.id.clone(),
            }))
            .await
            .expect("stats")
            .into_inner();
        stats_vertices.push(stats.surface_vertices as usize);
        if frame.keyframe {
            keyframes.push((vertices, frame.triangles.len() / 3));
        } else {
            assert_eq!(Some(&vertices), keyframes.last().map(|k| &k.0));
        }
    }
    driver.abort();
    manager.stop(&session.id).expect("stop");
    assert!(keyframes.len() >= 3, "keyframes {keyframes:?}");
    let (coarse, fine) = (keyframes[0], keyframes[1]);
    assert!(fine.0 > coarse.0 && fine.1 > coarse.1, "{keyframes:?}");
    assert_eq!(keyframes[2], coarse, "coarsened back: {keyframes:?}");
    // Statistics are published every 100 ticks, so they lag the frames a little.
    assert!(
        stats_vertices.iter().any(|&v| v > coarse.0),
        "GetStats surface_vertices {stats_vertices:?} never showed the subdivision"
    );
}
