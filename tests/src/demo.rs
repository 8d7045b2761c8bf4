//! The demo runner behind `haptic-demo` (README's first command): one scripted session of the
//! whole product with the real binaries, then a summary.
//!
//! Sequence: `hapticd --listen 127.0.0.1:0 --tokens-file OUT/auth/tokens.toml` (tokens made at
//! first start, one file per role); `hapticctl start lv` with the control token;
//! `haptic-viewer` (viewer token) writing PNGs; `haptic-bridge` (device token) pressing the left ventricle with the simulated probe (recording a CSV);
//! meanwhile `hapticctl force` pushes the epicardium elsewhere; then `hapticctl stats`, `stop`,
//! SIGTERM to the daemon. Every child is killed if a step fails (the handles kill on drop).
//! Neighbours: the harness in the crate root ([`crate::Daemon`], [`crate::run_bin_in`]).

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, bail, ensure};
use serde_json::{Value, json};

use crate::{BRIDGE, CTL, Daemon, HAPTICD, STEP_TIMEOUT, VIEWER, finish, run_bin_in, spawn_bin_in};

/// What the demo does; [`Default`] is what `haptic-demo` without flags runs.
#[derive(Debug, Clone)]
pub struct DemoParams {
    /// Output directory (pictures, the bridge CSV, `summary.json`).
    pub out_dir: PathBuf,
    /// Where the workspace binaries are.
    pub bin_dir: PathBuf,
    /// How long the simulated hand holds the press, seconds. Longer than the bridge default
    /// (1 s) so that the injected force (at [`DemoParams::force_after_s`]) lands during the hold.
    pub hold_s: f64,
    /// Delay from the bridge start to `hapticctl force`, seconds.
    pub force_after_s: f64,
}

impl DemoParams {
    /// Defaults with the binaries from `bin_dir`.
    pub fn new(bin_dir: PathBuf) -> Self {
        Self {
            out_dir: PathBuf::from("demo-out"),
            bin_dir,
            hold_s: 3.0,
            force_after_s: 2.0,
        }
    }
}

/// Press depth and speed of the bridge's default `press` script (device-bridge `cli.rs`).
const PRESS_DEPTH_M: f64 = 0.006;
const PRESS_SPEED_M_PER_S: f64 = 0.01;

/// Runs the demo; `progress` receives one line per step. Returns the summary (also written to
/// `OUT/summary.json`).
///
/// # Errors
/// Any step fails (missing binary, a child exits non-zero, a timeout); the message names it.
pub async fn run(p: &DemoParams, progress: &mut dyn FnMut(&str)) -> Result<Value> {
    let out = &p.out_dir;
    let pictures = out.join("pictures");
    if pictures.exists() {
        std::fs::remove_dir_all(&pictures)
            .with_context(|| format!("clearing {}", pictures.display()))?;
    }
    std::fs::create_dir_all(&pictures)
        .with_context(|| format!("creating {}", pictures.display()))?;
    let csv = out.join("bridge.csv");
    let (dir, s) = (&p.bin_dir, |p: &Path| p.display().to_string());
    // Fresh tokens each run: the daemon creates the tokens file and one `<role>.token` per
    // role (mode 0600) at first start; each client passes the file of its role.
    let auth = out.join("auth");
    if auth.exists() {
        std::fs::remove_dir_all(&auth).with_context(|| format!("clearing {}", auth.display()))?;
    }
    std::fs::create_dir_all(&auth).with_context(|| format!("creating {}", auth.display()))?;
    let tokens = s(&auth.join("tokens.toml"));
    let token = |role: &str| s(&auth.join(format!("{role}.token")));
    let (control, device, viewer_token) = (token("control"), token("device"), token("viewer"));

    progress(&format!(
        "starting {HAPTICD} --listen 127.0.0.1:0 --tokens-file {tokens} ..."
    ));
    let mut daemon = Daemon::spawn_from(
        &crate::binary_in(dir, HAPTICD)?,
        &["--tokens-file", &tokens],
    )?;
    let url = daemon.url();
    progress(&format!(
        "{HAPTICD} listening on {}; tokens in {}",
        daemon.addr,
        auth.display()
    ));

    progress("starting session: hapticctl --token-file control.token start lv ...");
    let started = run_bin_in(
        dir,
        CTL,
        &["--server", &url, "--token-file", &control, "start", "lv"],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;
    let id = started
        .stdout
        .lines()
        .map(str::trim)
        .rfind(|l| !l.is_empty())
        .context("hapticctl start printed no session id")?
        .to_string();
    progress(&format!("session {id}"));

    let bridge_s = 2.0 * PRESS_DEPTH_M / PRESS_SPEED_M_PER_S + p.hold_s;
    let viewer_s = format!("{:.1}", bridge_s + 3.0);
    progress(&format!(
        "starting {VIEWER} (pictures every 0.5 s for {viewer_s} s into {}) ...",
        pictures.display()
    ));
    let viewer = spawn_bin_in(
        dir,
        VIEWER,
        &[
            "--server",
            &url,
            "--token-file",
            &viewer_token,
            "--session",
            &id,
            "--out",
            &s(&pictures),
            "--interval-s",
            "0.5",
            "--duration-s",
            &viewer_s,
            "--json",
        ],
    )?;

    progress(&format!(
        "starting {BRIDGE} (sim probe, press {:.0} mm along -x, hold {} s, recording {}) ...",
        PRESS_DEPTH_M * 1e3,
        p.hold_s,
        csv.display()
    ));
    let hold = p.hold_s.to_string();
    let bridge = spawn_bin_in(
        dir,
        BRIDGE,
        &[
            "--server",
            &url,
            "--token-file",
            &device,
            "--session",
            &id,
            "--driver",
            "sim",
            "--script",
            "press",
            "--hold-s",
            &hold,
            "--record",
            &s(&csv),
            "--json",
        ],
    )?;

    tokio::time::sleep(Duration::from_secs_f64(p.force_after_s)).await;
    progress("applying 0.05 N along -y at (0, 9.68, -5) mm for 0.5 s: hapticctl force ...");
    run_bin_in(
        dir,
        CTL,
        &[
            "--server",
            &url,
            "--token-file",
            &control,
            "force",
            &id,
            "--point",
            "0,0.00968,-0.005",
            "--force",
            "0,-0.05,0",
            "--duration-s",
            "0.5",
        ],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;

    progress("waiting for the bridge to finish ...");
    let bridge_sum = finish(bridge, Duration::from_secs_f64(bridge_s + 30.0))
        .await?
        .success()?
        .json()?;
    progress("waiting for the viewer to finish ...");
    let viewer_sum = finish(viewer, Duration::from_secs_f64(bridge_s + 30.0))
        .await?
        .success()?
        .json()?;

    progress("reading statistics: hapticctl stats --json ...");
    let stats = run_bin_in(
        dir,
        CTL,
        &[
            "--server",
            &url,
            "--token-file",
            &control,
            "stats",
            &id,
            "--json",
        ],
        STEP_TIMEOUT,
    )
    .await?
    .success()?
    .json()?;
    progress("stopping the session: hapticctl stop ...");
    run_bin_in(
        dir,
        CTL,
        &["--server", &url, "--token-file", &control, "stop", &id],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;
    progress(&format!("stopping {HAPTICD} (SIGTERM) ..."));
    let status = daemon.terminate(Duration::from_secs(15))?;
    if !status.success() {
        bail!(
            "{HAPTICD} exited with {status} after SIGTERM; log:\n{}",
            daemon.log_tail()
        );
    }
    ensure!(
        stats["faulted"] != json!(true),
        "the session faulted: {}",
        stats["fault"]
    );

    let summary = json!({
        "session_id": id,
        "scene": stats["scene"],
        "nodes": stats["nodes"],
        "tetrahedra": stats["tetrahedra"],
        "loop_rate_hz": stats["loop_rate_hz"],
        "steps": stats["steps"],
        "step_p50_us": stats["step_p50_us"],
        "step_p99_us": stats["step_p99_us"],
        "step_max_us": stats["step_max_us"],
        "overruns": stats["overruns"],
        "pose_to_force_p50_us": stats["pose_to_force_p50_us"],
        "pose_to_force_p99_us": stats["pose_to_force_p99_us"],
        "bridge_rtt_p50_us": bridge_sum["rtt_p50_us"],
        "bridge_rtt_p99_us": bridge_sum["rtt_p99_us"],
        "bridge_samples_sent": bridge_sum["samples_sent"],
        "bridge_forces_received": bridge_sum["forces_received"],
        "bridge_contact_samples": bridge_sum["contact_samples"],
        "bridge_max_depth_m": bridge_sum["max_depth_m"],
        "peak_force_n": stats["peak_force_n"],
        "max_displacement_m": stats["max_displacement_m"],
        "viewer_frames": viewer_sum["frames"],
        "viewer_fps": viewer_sum["fps"],
        "pictures_written": viewer_sum["pictures_written"],
        "pictures_dir": s(&pictures),
        "bridge_csv": s(&csv),
        "stats": stats,
        "bridge": bridge_sum,
        "viewer": viewer_sum,
    });
    let path = out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(summary)
}

/// The human-readable summary of [`run`]'s result.
pub fn format_summary(v: &Value, summary_path: &Path) -> String {
    let f = |k: &str, d: usize| match v[k].as_f64() {
        Some(x) => format!("{x:.d$}"),
        None => "-".to_string(),
    };
    let mm = v["max_displacement_m"]
        .as_f64()
        .map_or("-".to_string(), |m| format!("{:.2}", m * 1e3));
    let scene = v["scene"].as_str().unwrap_or("-");
    let text = |k: &str| v[k].as_str().unwrap_or("-").to_string();
    [
        format!(
            "session {} (scene {scene}, {} nodes, {} tets)",
            text("session_id"),
            v["nodes"],
            v["tetrahedra"]
        ),
        format!("servo loop rate        {} Hz", f("loop_rate_hz", 1)),
        format!(
            "step time p50/p99/max  {} / {} / {} us",
            f("step_p50_us", 1),
            f("step_p99_us", 1),
            f("step_max_us", 1)
        ),
        format!("overruns               {}", v["overruns"]),
        format!(
            "pose-to-force (server) p50/p99 {} / {} us",
            f("pose_to_force_p50_us", 1),
            f("pose_to_force_p99_us", 1)
        ),
        format!(
            "bridge round trip      p50/p99 {} / {} us",
            f("bridge_rtt_p50_us", 0),
            f("bridge_rtt_p99_us", 0)
        ),
        format!("peak force             {} N", f("peak_force_n", 3)),
        format!("max displacement       {mm} mm"),
        format!(
            "pictures written       {} in {}",
            v["pictures_written"],
            text("pictures_dir")
        ),
        format!("bridge recording       {}", text("bridge_csv")),
        format!("summary                {}", summary_path.display()),
    ]
    .into_iter()
    .chain(overrun_hint(v))
    .collect::<Vec<_>>()
    .join("\n")
}

/// A note for the summary when the median servo tick exceeded the 1 ms period: the loop could
/// not keep 1 kHz on this machine. `None` otherwise.
fn overrun_hint(v: &Value) -> Option<String> {
    let p50_us = v["step_p50_us"].as_f64()?;
    (p50_us > 1000.0).then(|| {
        format!(
            "\nnote: the median servo tick ({:.2} ms) exceeds the 1 ms period on this machine, so the\n\
             loop ran at {} Hz instead of 1 kHz. The README's \"When the servo cannot keep 1 kHz\"\n\
             lists cheaper scene settings and the accuracy they cost.",
            p50_us / 1e3,
            v["loop_rate_hz"]
                .as_f64()
                .map_or("-".to_string(), |r| format!("{r:.0}"))
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn the_summary_explains_a_servo_that_cannot_keep_1_khz() {
        let path = Path::new("demo-out/summary.json");
        let slow = json!({"step_p50_us": 1417.0, "loop_rate_hz": 760.7, "overruns": 4999});
        let text = format_summary(&slow, path);
        assert!(
            text.contains("median servo tick (1.42 ms) exceeds"),
            "{text}"
        );
        assert!(text.contains("loop ran at 761 Hz"), "{text}");
        let fast = json!({"step_p50_us": 172.0, "loop_rate_hz": 999.1, "overruns": 4});
        assert!(!format_summary(&fast, path).contains("note:"));
    }
}
