//! The viewer against a mock server on a loopback port: pictures, counters, bad frames, stop
//! conditions. No assertion depends on wall-clock timing.

mod common;

use std::future::pending;
use std::time::Duration;

use haptic_client::raster::RenderParams;
use haptic_client::viewer::{self, StopReason, ViewerConfig};

fn config(url: &str, session: &str, name: &str) -> ViewerConfig {
    ViewerConfig {
        out_dir: common::out_dir(name),
        // Long interval: only the first picture and latest.png, whatever the machine's speed.
        interval_s: 1000.0,
        progress: false,
        render: RenderParams {
            width: 320,
            height: 240,
            ..RenderParams::default()
        },
        ..ViewerConfig::new(url, session)
    }
}

#[tokio::test]
async fn viewer_writes_pictures_counts_frames_and_shows_motion() {
    let server = common::serve().await;
    let cfg = config(&server.url, "ok", "ok");
    let s = viewer::run(cfg.clone(), pending()).await.unwrap();
    assert_eq!(s.stop_reason, StopReason::StreamEnded);
    assert_eq!((s.frames, s.keyframes, s.bad_frames), (6, 1, 0));
    assert_eq!(s.pictures_written, 2);
    assert_eq!(s.picture_errors, 0);
    assert!((s.max_displacement_m - 0.005).abs() < 1e-6);
    assert!(s.age_p50_ms.is_some() && s.age_p99_ms.is_some());
    assert_eq!(s.out_dir, cfg.out_dir);

    // The first picture shows the keyframe, latest.png the last frame: vertex 0 moved by 5 mm.
    let first = std::fs::read(cfg.out_dir.join("frame_00001.png")).unwrap();
    let latest = std::fs::read(cfg.out_dir.join("latest.png")).unwrap();
    assert_ne!(first, latest, "the picture must change when a vertex moves");
    let dec = png::Decoder::new(std::io::Cursor::new(&latest));
    let info = dec.read_info().unwrap();
    assert_eq!((info.info().width, info.info().height), (320, 240));
    eprintln!(
        "sample picture: {}",
        cfg.out_dir.join("latest.png").display()
    );

    // The summary serialises to one JSON object with the documented names.
    let json = serde_json::to_value(&s).unwrap();
    assert_eq!(json["stop_reason"], "stream_ended");
    assert_eq!(json["frames"], 6);
}

#[tokio::test]
async fn bad_frames_are_counted_and_skipped() {
    let server = common::serve().await;
    let s = viewer::run(config(&server.url, "bad", "bad"), pending())
        .await
        .unwrap();
    assert_eq!(s.stop_reason, StopReason::StreamEnded);
    assert_eq!((s.frames, s.keyframes, s.bad_frames), (3, 1, 2));
    assert!(s.last_error.as_deref().unwrap().contains("bad frame"));
    assert_eq!(s.pictures_written, 2);
}

#[tokio::test]
async fn unknown_session_is_not_found() {
    let server = common::serve().await;
    let e = viewer::run(config(&server.url, "nope", "nope"), pending())
        .await
        .unwrap_err();
    let status = e.status().expect("a gRPC status");
    assert_eq!(status.code(), tonic::Code::NotFound);
    assert_eq!(e.to_string(), "NOT_FOUND: no session 'nope'");
}

#[tokio::test]
async fn stream_failure_after_frames_keeps_the_summary() {
    let server = common::serve().await;
    let s = viewer::run(config(&server.url, "fail", "fail"), pending())
        .await
        .unwrap();
    assert_eq!(s.stop_reason, StopReason::StreamError);
    assert_eq!(s.frames, 2);
    assert!(s.last_error.as_deref().unwrap().contains("INTERNAL: boom"));
}

#[tokio::test]
async fn duration_ends_an_endless_stream() {
    let server = common::serve().await;
    let cfg = ViewerConfig {
        duration_s: Some(0.3),
        ..config(&server.url, "forever", "duration")
    };
    let s = viewer::run(cfg.clone(), pending()).await.unwrap();
    assert_eq!(s.stop_reason, StopReason::Duration);
    assert_eq!(s.bad_frames, 0);
    // Whatever arrived in that time, latest.png exists exactly when a keyframe did.
    assert_eq!(cfg.out_dir.join("latest.png").exists(), s.keyframes > 0);
}

#[tokio::test]
async fn shutdown_ends_an_endless_stream() {
    let server = common::serve().await;
    let cfg = config(&server.url, "forever", "shutdown");
    let shutdown = tokio::time::sleep(Duration::from_millis(200));
    let s = viewer::run(cfg, shutdown).await.unwrap();
    assert_eq!(s.stop_reason, StopReason::Shutdown);
}

#[tokio::test]
async fn unreachable_server_is_a_connect_error() {
    // Bind and drop a listener to get a port nobody listens on.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let cfg = config(&format!("127.0.0.1:{port}"), "ok", "unreachable");
    let e = viewer::run(cfg, pending()).await.unwrap_err();
    assert!(
        matches!(e, haptic_client::ClientError::Connect { .. }),
        "{e}"
    );
}

#[tokio::test]
async fn binary_prints_one_json_summary_line() {
    let server = common::serve().await;
    let dir = common::out_dir("binary");
    let out = tokio::process::Command::new(env!("CARGO_BIN_EXE_haptic-viewer"))
        .args([
            "--server",
            &server.url,
            "--session",
            "ok",
            "--json",
            "--quiet",
        ])
        .args(["--width", "64", "--height", "48", "--interval-s", "1000"])
        .arg("--out")
        .arg(&dir)
        .output()
        .await
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(stdout.lines().count(), 1);
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(v["frames"], 6);
    assert_eq!(v["keyframes"], 1);
    assert_eq!(v["pictures_written"], 2);
    assert!(dir.join("latest.png").exists());
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(stderr.contains("6 frames (1 keyframes, 0 bad)"), "{stderr}");

    let out = tokio::process::Command::new(env!("CARGO_BIN_EXE_haptic-viewer"))
        .args(["--server", &server.url, "--session", "nope", "--quiet"])
        .arg("--out")
        .arg(&dir)
        .output()
        .await
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("error: NOT_FOUND: no session 'nope'"));
}
