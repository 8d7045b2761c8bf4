//! Bytes of the surface streams, full against compact (issue 17, section 2): the real release
//! `hapticd` with the default `lv`, two watchers at 30 Hz on their own connections (FULL and
//! DELTA at 1 um), and the real `haptic-bridge` for three phases, one after the other:
//!
//! - rest: no device, 5 s;
//! - press: `--script press` (6 mm along -x at 10 mm/s from 14 mm, 3.7 mm into the epicardium,
//!   hold 3 s, release; 4.7 s);
//! - stroke: `--script stroke --along 0,0,1 --length-m 0.01` (press 6 mm, slide 10 mm, release;
//!   2.7 s).
//!
//! Each frame is counted in the phase during which it arrived; bytes are the encoded protobuf
//! message sizes (what gRPC carries, before HTTP/2 framing). Writes
//! `target/bench/stream_bytes.json` (`-- --publish`: `docs/bench/`) and prints the table of
//! `docs/benchmarks.md`.
//!
//! Run: `cargo bench -p haptic-e2e --bench stream_bytes`.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use anyhow::{Result, ensure};
use haptic_e2e::load::{Received, grpc_watcher};
use haptic_e2e::{BRIDGE, Daemon, finish, spawn_bin, start_session};
use serde_json::json;

async fn phase(
    name: &str,
    bridge: Option<Vec<&str>>,
    rest_s: f64,
    watchers: &[(&str, Arc<Received>)],
) -> Result<serde_json::Value> {
    let before: Vec<_> = watchers.iter().map(|(_, r)| r.snapshot()).collect();
    let t0 = Instant::now();
    match bridge {
        Some(args) => {
            let b = spawn_bin(BRIDGE, &args)?;
            finish(b, Duration::from_secs(60)).await?.success()?;
        }
        None => tokio::time::sleep(Duration::from_secs_f64(rest_s)).await,
    }
    let secs = t0.elapsed().as_secs_f64();
    let mut out = json!({"phase": name, "seconds": secs});
    for ((label, r), b) in watchers.iter().zip(before) {
        let a = r.snapshot();
        let (frames, keys, bytes, key_bytes) = (a.0 - b.0, a.1 - b.1, a.2 - b.2, a.3 - b.3);
        out[label] = json!({
            "frames": frames,
            "keyframes": keys,
            "bytes": bytes,
            "keyframe_bytes": key_bytes,
            "bytes_per_frame": bytes as f64 / frames.max(1) as f64,
            "bytes_per_s": bytes as f64 / secs,
        });
    }
    let full = out["full"]["bytes_per_frame"].as_f64().unwrap_or(0.0);
    let compact = out["compact"]["bytes_per_frame"].as_f64().unwrap_or(1.0);
    out["ratio"] = json!(full / compact.max(1e-9));
    Ok(out)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> Result<()> {
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let stop = Arc::new(AtomicBool::new(false));
    let full = grpc_watcher(&url, &id, 30.0, false, stop.clone()).await?;
    let compact = grpc_watcher(&url, &id, 30.0, true, stop.clone()).await?;
    let watchers = [("full", full.clone()), ("compact", compact.clone())];
    tokio::time::sleep(Duration::from_secs(1)).await;
    let common = ["--server", url.as_str(), "--session", id.as_str()];
    let mut press = common.to_vec();
    press.extend(["--script", "press"]);
    let mut stroke = common.to_vec();
    stroke.extend([
        "--script",
        "stroke",
        "--along",
        "0,0,1",
        "--length-m",
        "0.01",
    ]);
    let rows = vec![
        phase("rest", None, 5.0, &watchers).await?,
        phase("press", Some(press), 0.0, &watchers).await?,
        phase("stroke", Some(stroke), 0.0, &watchers).await?,
    ];
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    ensure!(
        !full.failed.load(std::sync::atomic::Ordering::Relaxed)
            && !compact.failed.load(std::sync::atomic::Ordering::Relaxed),
        "a watcher failed"
    );
    println!(
        "| phase | seconds | full: frames, B/frame, kB/s | compact: frames (keyframes), B/frame, kB/s | ratio |"
    );
    println!("|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {:.1} | {}, {:.0}, {:.1} | {} ({}), {:.0}, {:.1} | {:.1}x |",
            r["phase"].as_str().unwrap_or(""),
            r["seconds"].as_f64().unwrap_or(0.0),
            r["full"]["frames"],
            r["full"]["bytes_per_frame"].as_f64().unwrap_or(0.0),
            r["full"]["bytes_per_s"].as_f64().unwrap_or(0.0) / 1e3,
            r["compact"]["frames"],
            r["compact"]["keyframes"],
            r["compact"]["bytes_per_frame"].as_f64().unwrap_or(0.0),
            r["compact"]["bytes_per_s"].as_f64().unwrap_or(0.0) / 1e3,
            r["ratio"].as_f64().unwrap_or(0.0),
        );
    }
    let out = results_dir()?.join("stream_bytes.json");
    let doc = json!({
        "what": "encoded SurfaceFrame bytes, FULL vs DELTA (1 um), default lv, 30 Hz watchers",
        "command": "cargo bench -p haptic-e2e --bench stream_bytes",
        "phases": rows,
    });
    std::fs::write(&out, serde_json::to_string_pretty(&doc)? + "\n")?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

/// Where results go: `target/bench/` (or `$CARGO_TARGET_DIR/bench/`), or `docs/bench/` with
/// `--publish`, so that a benchmark run leaves the work tree clean unless asked.
fn results_dir() -> std::io::Result<std::path::PathBuf> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = if std::env::args().any(|a| a == "--publish") {
        root.join("docs/bench")
    } else {
        std::env::var_os("CARGO_TARGET_DIR")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| root.join("target"))
            .join("bench")
    };
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}
