//! The hybrid family through the server (issue 13): `ListScenes` lists both hybrid scenes, a
//! session of `ellipsoids-hybrid` runs in the servo, a probe pressing its outer surface
//! activates particles, and `GetStats` reports `total_particles` and `active_particles`.

use std::sync::Arc;
use std::time::Duration;

use haptic_model::DVec3;
use haptic_server::ServerConfig;
use haptic_server::service::Services;
use haptic_server::servo::Pose;
use haptic_server::session::SessionManager;
use haptics_proto::v1::session_control_server::SessionControl;
use haptics_proto::v1::{GetStatsRequest, ListScenesRequest};

#[tokio::test]
async fn a_probe_press_activates_particles_of_a_hybrid_session() {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let services = Services::new(manager.clone());
    let listed = services
        .list_scenes(tonic::Request::new(ListScenesRequest {}))
        .await
        .expect("list")
        .into_inner();
    for name in ["lv-hybrid", "ellipsoids-hybrid"] {
        assert!(
            listed.scenes.iter().any(|s| s.name == name),
            "{name} not listed"
        );
    }
    let scene = manager.load_scene("ellipsoids-hybrid", "").expect("scene");
    let session = manager.start(&scene).expect("session");
    let (tx, _rx) = tokio::sync::mpsc::channel(16);
    let mut pose = session.attach_device(tx).expect("device");
    // The outer ellipsoid's +x equator point is (10, 0, 0) mm; the probe (radius 2 mm) 0.5 mm in.
    let device = DVec3::new(11.5e-3, 0.0, 0.0);
    let start = tokio::time::Instant::now();
    let driver = tokio::spawn(async move {
        let mut seq = 0;
        while start.elapsed() < Duration::from_secs(20) {
            seq += 1;
            pose.write(Pose {
                seq,
                position_m: device,
                connected: true,
                ..Pose::default()
            });
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    });
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    let mut last = None;
    while tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let stats = services
            .get_stats(tonic::Request::new(GetStatsRequest {
                session_id: session.id.clone(),
            }))
            .await
            .expect("stats")
            .into_inner();
        let done = stats.active_particles > 0;
        last = Some((
            stats.total_particles,
            stats.active_particles,
            stats.fault.clone(),
        ));
        if done {
            break;
        }
    }
    driver.abort();
    manager.stop(&session.id).expect("stop");
    let (total, active, fault) = last.expect("stats");
    assert!(fault.is_empty(), "fault: {fault}");
    assert!(total > 20_000, "total_particles {total}");
    assert!(active > 0, "active_particles {active}");
}
