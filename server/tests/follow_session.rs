//! A condensed scene whose active region follows the probe, through the server (issue 20): a
//! scene file with `active_region.follow` starts a session, a device slides around the
//! ventricle in the servo, the region is swapped in as it goes (the worker thread runs beside
//! the servo), and `GetStats` reports the swaps, the last preparation time and the contact
//! ticks (none answered by a companion: this scene has none); `ApplyForce`
//! is refused with a clear error (one contact per following region). The session runs with
//! `[servo] threads = 2` (issue 48): a tick pool with one worker beside the servo. With a
//! region cache (`active_region.tiles = "background"`), `GetStats` and the metrics say how
//! many of its regions are prepared, so a client can wait for the cache before fast strokes.

use std::sync::Arc;
use std::time::Duration;

use haptic_model::DVec3;
use haptic_server::ServerConfig;
use haptic_server::service::Services;
use haptic_server::servo::Pose;
use haptic_server::session::SessionManager;
use haptics_proto::v1::session_control_server::SessionControl;
use haptics_proto::v1::{ApplyForceRequest, GetStatsRequest, Vec3};

/// The built-in LV on about 2 000 linear tets, backward Euler, a 6 mm region that follows.
const SCENE: &str = r#"
name = "lv-follow"
[mesh]
builtin = "lv"
target_tets = 2000
order = 1
[material]
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
density_kg_per_m3 = 1060.0
phi_pa_s = 0.05
psi_pa_s = 0.05
mass_damping_per_s = 5.0
[boundary]
clamped = ["BASE"]
touchable = ["EPI"]
[integrator]
kind = "backward-euler"
substeps = 1
[active_region]
centre_m = [0.00968, 0.0, -0.005]
radius_m = 0.006
follow = true
"#;

#[tokio::test]
async fn a_following_region_swaps_as_the_device_slides() {
    let mut config = ServerConfig::default();
    config.servo.threads = haptic_server::config::ServoThreads::Fixed(2);
    let manager = Arc::new(SessionManager::new(config));
    let services = Services::new(manager.clone());
    let scene = manager.load_scene("", SCENE).expect("scene");
    let session = manager.start(&scene).expect("session");
    let (tx, _rx) = tokio::sync::mpsc::channel(16);
    let mut pose = session.attach_device(tx).expect("device");
    // Pressed 1 mm at the equator on +x, then slid around the long axis at 5 mm/s, sampled
    // every 2 ms (the servo ticks once per sample).
    const R_EPI: f64 = 0.00968;
    let start = tokio::time::Instant::now();
    let clock = session.clone();
    let driver = tokio::spawn(async move {
        let mut seq = 0;
        loop {
            let t = start.elapsed().as_secs_f64();
            let theta = ((t - 0.5).max(0.0) * 0.005 / R_EPI).min(std::f64::consts::PI);
            let radius = R_EPI + 0.002 - 0.001 * (t / 0.3).min(1.0);
            seq += 1;
            pose.write(Pose {
                seq,
                position_m: DVec3::new(radius * theta.cos(), radius * theta.sin(), -0.005),
                velocity_m_per_s: DVec3::new(-theta.sin(), theta.cos(), 0.0) * 0.005,
                received_us: clock.now_us(),
                connected: true,
            });
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    });
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
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
        let done = stats.region_swaps >= 3 || !stats.fault.is_empty();
        last = Some(stats);
        if done {
            break;
        }
    }
    // A point load (a second contact far from the probe) is refused with a clear error
    // before it reaches the servo, which would drop it silently.
    let refused = services
        .apply_force(tonic::Request::new(ApplyForceRequest {
            session_id: session.id.clone(),
            point_m: Some(Vec3 {
                x: -0.00968,
                y: 0.0,
                z: -0.005,
            }),
            force_n: Some(Vec3 {
                x: 0.01,
                y: 0.0,
                z: 0.0,
            }),
            duration_s: 0.1,
        }))
        .await
        .expect_err("a following region refuses point loads");
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
    assert!(
        refused.message().contains("follows the probe"),
        "{}",
        refused.message()
    );
    driver.abort();
    manager.stop(&session.id).expect("stop");
    let stats = last.expect("stats");
    assert!(stats.fault.is_empty(), "fault: {}", stats.fault);
    assert!(stats.region_swaps >= 3, "{stats:?}");
    assert!(
        stats.region_preparation_s > 0.0 && stats.region_preparation_s < 5.0,
        "{stats:?}"
    );
    assert!(stats.in_contact, "{stats:?}");
    assert!(stats.active_elements > 0 && stats.active_elements < stats.tetrahedra);
    // Who answered: the probe (2 mm) touches from the first samples on, and this scene has
    // no coarse companion.
    assert!(
        stats.contact_ticks > stats.steps / 2 && stats.contact_ticks <= stats.steps,
        "{stats:?}"
    );
    assert_eq!(stats.companion_ticks, 0, "{stats:?}");
    assert_eq!(stats.threads, 2, "{stats:?}");
    // No region cache in this scene.
    assert_eq!((stats.region_tiles, stats.region_tiles_ready), (0, 0));
}

/// The same scene with a region cache: `GetStats` reports its regions and counts them ready as
/// the worker builds them, up to all of them, with the daemon's metrics agreeing. With the
/// daemon's `region_cache_dir`, the next session of the scene reads every region the first
/// one wrote instead of preparing it (`region_tiles_loaded`); a file damaged before a third
/// session is refused, counted and explained (`region_tiles_refused`, `region_cache_error`).
#[tokio::test]
async fn get_stats_reports_the_region_cache_filling() {
    let dir = std::env::temp_dir().join(format!("hapticd-region-cache-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let config = ServerConfig {
        region_cache: Some(haptic_model::integrate::follow::RegionCacheDir {
            dir: dir.clone(),
            max_bytes: 1 << 30,
            memory_bytes: 1 << 30,
        }),
        ..ServerConfig::default()
    };
    let manager = Arc::new(SessionManager::new(config));
    let services = Services::new(manager.clone());
    // A 5 mm cover instead of the default 2.5 mm: about 20 regions, so the cache fills in
    // seconds.
    let tiled = format!("{SCENE}tiles = \"background\"\ntile_cover_m = 0.005\n");
    let scene = manager.load_scene("", &tiled).expect("scene");
    let mut written = None;
    let mut damaged = String::new();
    for run in ["writes", "reads", "refuses"] {
        if run == "refuses" {
            // One file damaged between sessions: refused (counted, logged, its reason in
            // GetStats), prepared again and replaced; the others are read.
            let mut files: Vec<_> = std::fs::read_dir(&dir)
                .expect("the cache directory")
                .map(|e| e.expect("entry").path())
                .collect();
            files.sort();
            let mut bytes = std::fs::read(&files[1]).expect("read");
            let mid = bytes.len() / 2;
            bytes[mid] ^= 0x10;
            std::fs::write(&files[1], &bytes).expect("damage");
            damaged = files[1].to_string_lossy().into_owned();
        }
        let session = manager.start(&scene).expect("session");
        let stats = || async {
            services
                .get_stats(tonic::Request::new(GetStatsRequest {
                    session_id: session.id.clone(),
                }))
                .await
                .expect("stats")
                .into_inner()
        };
        // The servo publishes the body's statistics once it ticks.
        let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
        let first = loop {
            let s = stats().await;
            if s.steps > 0 || tokio::time::Instant::now() > deadline {
                break s;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert!(first.region_tiles >= 5, "{first:?}");
        assert!(first.region_tiles_ready <= first.region_tiles, "{first:?}");
        let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
        let mut seen = vec![first.region_tiles_ready];
        let last = loop {
            let s = stats().await;
            assert!(s.fault.is_empty(), "fault: {}", s.fault);
            assert_eq!(s.region_tiles, first.region_tiles, "{s:?}");
            assert!(
                s.region_tiles_ready >= *seen.last().unwrap(),
                "ready went down: {seen:?} then {s:?}"
            );
            seen.push(s.region_tiles_ready);
            if s.region_tiles_ready == s.region_tiles {
                break s;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "the cache did not fill in 300 s: {seen:?}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        let registry = haptic_server::metrics::registry(manager.clone());
        let text = haptic_server::metrics::render(&registry).expect("metrics");
        let gauge = |name: &str| {
            text.lines()
                .find(|l| l.starts_with(name) && l.contains(&session.id))
                .and_then(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        };
        let (loaded, refused) = match run {
            "writes" => (0, 0),
            "reads" => (last.region_tiles, 0),
            _ => (last.region_tiles - 1, 1),
        };
        assert_eq!(last.region_tiles_loaded, loaded, "{run}: {last:?}");
        assert_eq!(last.region_tiles_refused, refused, "{run}: {last:?}");
        // Under the 1 GiB memory limit every region stays in memory.
        assert_eq!(last.region_tiles_dropped, 0, "{run}: {last:?}");
        assert!(last.region_tile_memory_bytes > 0, "{run}: {last:?}");
        if refused == 0 {
            assert_eq!(last.region_cache_error, "", "{run}");
        } else {
            assert!(
                last.region_cache_error.contains(&damaged)
                    && last.region_cache_error.contains("damaged"),
                "{run}: {}",
                last.region_cache_error
            );
        }
        for (name, value) in [
            ("hapticd_region_tiles{", last.region_tiles),
            ("hapticd_region_tiles_ready{", last.region_tiles),
            ("hapticd_region_tiles_loaded{", loaded),
            ("hapticd_region_tiles_refused{", refused),
            ("hapticd_region_tiles_dropped{", 0),
        ] {
            assert_eq!(gauge(name), Some(value as f64), "{run}: {name}");
        }
        if run == "writes" {
            written = Some(last.region_tiles);
        }
        manager.stop(&session.id).expect("stop");
    }
    let files = std::fs::read_dir(&dir)
        .expect("the cache directory")
        .count();
    assert_eq!(Some(files as u64), written, "one file per region");
    memory_limited_session(&dir, &tiled).await;
    std::fs::remove_dir_all(&dir).expect("clean up");
}

/// A session over the full region cache in `dir` (scene `scene`) with room in memory for one
/// region: GetStats and the metrics show every region read, all but one dropped from memory,
/// and the bytes of the one kept.
async fn memory_limited_session(dir: &std::path::Path, scene: &str) {
    let config = ServerConfig {
        region_cache: Some(haptic_model::integrate::follow::RegionCacheDir {
            dir: dir.to_path_buf(),
            max_bytes: 1 << 30,
            memory_bytes: 1,
        }),
        ..ServerConfig::default()
    };
    let manager = Arc::new(SessionManager::new(config));
    let services = Services::new(manager.clone());
    let scene = manager.load_scene("", scene).expect("scene");
    let session = manager.start(&scene).expect("session");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
    let last = loop {
        let s = services
            .get_stats(tonic::Request::new(GetStatsRequest {
                session_id: session.id.clone(),
            }))
            .await
            .expect("stats")
            .into_inner();
        if s.region_tiles > 0 && s.region_tiles_ready == s.region_tiles {
            break s;
        }
        assert!(tokio::time::Instant::now() < deadline, "{s:?}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(last.region_tiles_loaded >= last.region_tiles, "{last:?}");
    assert!(
        last.region_tiles_dropped >= last.region_tiles - 1,
        "{last:?}"
    );
    assert!(last.region_tile_memory_bytes > 0, "{last:?}");
    let registry = haptic_server::metrics::registry(manager.clone());
    let text = haptic_server::metrics::render(&registry).expect("metrics");
    let line = text
        .lines()
        .find(|l| l.starts_with("hapticd_region_tiles_dropped{") && l.contains(&session.id))
        .expect("the gauge");
    let dropped: f64 = line
        .rsplit(' ')
        .next()
        .and_then(|v| v.parse().ok())
        .expect("value");
    assert!(dropped >= (last.region_tiles - 1) as f64, "{line}");
    manager.stop(&session.id).expect("stop");
}
