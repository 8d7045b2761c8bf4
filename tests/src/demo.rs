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

use crate::{
    BRIDGE, CTL, Daemon, HAPTICD, STEP_TIMEOUT, Spawned, VIEWER, finish, run_bin_in, spawn_bin_in,
};

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
    fresh_dir(&pictures)?;
    let csv = out.join("bridge.csv");
    // Fresh tokens each run: the daemon creates the tokens file and one `<role>.token` per
    // role (mode 0600) at first start; each client passes the file of its role.
    let auth = out.join("auth");
    fresh_dir(&auth)?;
    let mut daemon = start_daemon(&p.bin_dir, &auth, progress)?;
    let token = |role: &str| shown(&auth.join(format!("{role}.token")));
    let c = Clients {
        dir: &p.bin_dir,
        url: daemon.url(),
        control: token("control"),
        device: token("device"),
        viewer: token("viewer"),
    };
    let id = c.start_session(progress).await?;

    let bridge_s = 2.0 * PRESS_DEPTH_M / PRESS_SPEED_M_PER_S + p.hold_s;
    let viewer = c.start_viewer(&id, &pictures, bridge_s + 3.0, progress)?;
    let bridge = c.start_bridge(&id, p.hold_s, &csv, progress)?;
    tokio::time::sleep(Duration::from_secs_f64(p.force_after_s)).await;
    c.push_epicardium(&id, progress).await?;

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
    let stats = c.stats_and_stop(&id, &mut daemon, progress).await?;

    let summary = summary_of(&id, stats, bridge_sum, viewer_sum, &pictures, &csv);
    let path = out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(summary)
}

/// `path` as shown in arguments and messages.
fn shown(path: &Path) -> String {
    path.display().to_string()
}

/// Empties `dir` (removing what an earlier run left) and creates it.
fn fresh_dir(dir: &Path) -> Result<()> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("clearing {}", dir.display()))?;
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))
}

/// Starts `hapticd` on 127.0.0.1 port 0 with a new tokens file in `auth`.
fn start_daemon(dir: &Path, auth: &Path, progress: &mut dyn FnMut(&str)) -> Result<Daemon> {
    let tokens = shown(&auth.join("tokens.toml"));
    progress(&format!(
        "starting {HAPTICD} --listen 127.0.0.1:0 --tokens-file {tokens} ..."
    ));
    let daemon = Daemon::spawn_from(
        &crate::binary_in(dir, HAPTICD)?,
        &["--tokens-file", &tokens],
    )?;
    progress(&format!(
        "{HAPTICD} listening on {}; tokens in {}",
        daemon.addr,
        auth.display()
    ));
    Ok(daemon)
}

/// What every client step needs: where the binaries are, the daemon's URL and the token file
/// of each role.
struct Clients<'a> {
    dir: &'a Path,
    url: String,
    control: String,
    device: String,
    viewer: String,
}

impl Clients<'_> {
    /// `hapticctl --server URL --token-file CONTROL ARGS...`, which must succeed within
    /// [`STEP_TIMEOUT`].
    async fn ctl(&self, args: &[&str]) -> Result<crate::CmdOutput> {
        let mut all = vec!["--server", &self.url, "--token-file", &self.control];
        all.extend_from_slice(args);
        run_bin_in(self.dir, CTL, &all, STEP_TIMEOUT)
            .await?
            .success()
    }

    /// `hapticctl start lv`: returns the new session's id.
    async fn start_session(&self, progress: &mut dyn FnMut(&str)) -> Result<String> {
        progress("starting session: hapticctl --token-file control.token start lv ...");
        let started = self.ctl(&["start", "lv"]).await?;
        let id = started
            .stdout
            .lines()
            .map(str::trim)
            .rfind(|l| !l.is_empty())
            .context("hapticctl start printed no session id")?
            .to_string();
        progress(&format!("session {id}"));
        Ok(id)
    }

    /// The viewer, writing a picture every 0.5 s into `pictures` for `viewer_s` seconds.
    fn start_viewer(
        &self,
        id: &str,
        pictures: &Path,
        viewer_s: f64,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Spawned> {
        let viewer_s = format!("{viewer_s:.1}");
        progress(&format!(
            "starting {VIEWER} (pictures every 0.5 s for {viewer_s} s into {}) ...",
            pictures.display()
        ));
        spawn_bin_in(
            self.dir,
            VIEWER,
            &[
                "--server",
                &self.url,
                "--token-file",
                &self.viewer,
                "--session",
                id,
                "--out",
                &shown(pictures),
                "--interval-s",
                "0.5",
                "--duration-s",
                &viewer_s,
                "--json",
            ],
        )
    }

    /// The bridge with the simulated probe's press script, holding `hold_s` seconds and
    /// recording `csv`.
    fn start_bridge(
        &self,
        id: &str,
        hold_s: f64,
        csv: &Path,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Spawned> {
        progress(&format!(
            "starting {BRIDGE} (sim probe, press {:.0} mm along -x, hold {} s, recording {}) ...",
            PRESS_DEPTH_M * 1e3,
            hold_s,
            csv.display()
        ));
        let hold = hold_s.to_string();
        spawn_bin_in(
            self.dir,
            BRIDGE,
            &[
                "--server",
                &self.url,
                "--token-file",
                &self.device,
                "--session",
                id,
                "--driver",
                "sim",
                "--script",
                "press",
                "--hold-s",
                &hold,
                "--record",
                &shown(csv),
                "--json",
            ],
        )
    }

    /// `hapticctl force`: pushes the epicardium elsewhere during the hold.
    async fn push_epicardium(&self, id: &str, progress: &mut dyn FnMut(&str)) -> Result<()> {
        progress("applying 0.05 N along -y at (0, 9.68, -5) mm for 0.5 s: hapticctl force ...");
        self.ctl(&[
            "force",
            id,
            "--point",
            "0,0.00968,-0.005",
            "--force",
            "0,-0.05,0",
            "--duration-s",
            "0.5",
        ])
        .await?;
        Ok(())
    }

    /// `hapticctl stats --json`, `hapticctl stop`, then SIGTERM to the daemon (which must exit
    /// cleanly); fails if the session faulted. Returns the statistics.
    async fn stats_and_stop(
        &self,
        id: &str,
        daemon: &mut Daemon,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Value> {
        progress("reading statistics: hapticctl stats --json ...");
        let stats = self.ctl(&["stats", id, "--json"]).await?.json()?;
        progress("stopping the session: hapticctl stop ...");
        self.ctl(&["stop", id]).await?;
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
        Ok(stats)
    }
}

/// The demo's summary: the headline numbers of the daemon's statistics, the bridge's and the
/// viewer's summaries, where the outputs are, and the three summaries in full.
fn summary_of(
    id: &str,
    stats: Value,
    bridge_sum: Value,
    viewer_sum: Value,
    pictures: &Path,
    csv: &Path,
) -> Value {
    json!({
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
        "pictures_dir": shown(pictures),
        "bridge_csv": shown(csv),
        "stats": stats,
        "bridge": bridge_sum,
        "viewer": viewer_sum,
    })
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
