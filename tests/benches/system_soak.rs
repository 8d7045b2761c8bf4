//! System soak (issue 16): "a documented 30-minute soak (bridge at 1 kHz, 50 watchers, scripted
//! force injections, a heavy session started and stopped every minute): memory bounded, no
//! overruns attributable to the others; the figures in the closing note".
//!
//! What runs, all real processes over loopback: the release `hapticd` (port 0, with its
//! Prometheus endpoint on port 0) and in it the genuine session (the built-in `lv` unless
//! `--scene`); the real `haptic-bridge` on it at 1 kHz for the whole soak (simulated probe,
//! `--script poke`: 6 mm pokes at 0.25 Hz from 14 mm off the axis, in contact about a third of
//! each 4 s cycle; restarted if it ends early); `--watchers` gRPC `Watch` streams (compact, 30 Hz)
//! on their own connections; `SessionControl.ApplyForce` every 3 s (0.02 N inward for 0.2 s at
//! the epicardium point the surface tests load, 9.68 mm off the axis on +y at z = -5 mm); and,
//! every minute, a heavy second session: `deploy/scenes/lv.toml` (the built-in `lv`) refined to
//! `--heavy-tets` (default 1 500: about 3 000 nodes and 19 sub-steps, several ms per tick on a
//! 2-core machine, so it overruns all the time), started 15 s into the minute and stopped at
//! 45 s.
//!
//! What it measures, in 10 s windows: the daemon's resident memory (`VmRSS`, `VmHWM`) and CPU,
//! the genuine session's `GetStats` (ticks, overruns, loop rate, step p50/p99 over its life) and
//! its step-time histogram from `/metrics` (the window's own p99, as the upper bound of the
//! bucket holding it), frames the watchers received, and whether the heavy session was there:
//! `quiet` (absent the whole window), `heavy` (present the whole window) or `switch` (started or
//! stopped inside it, build included). Every minute a progress line goes to stderr.
//!
//! Verdicts (the exit code is non-zero when one fails; the figures are printed either way):
//!
//! 1. Memory bounded: the daemon's RSS at the end of the soak is less than 10 % above its RSS at
//!    the end of minute 5 (of minute `minutes / 2` for runs shorter than 10 minutes; not judged
//!    for a 1-minute run). Both samples are taken 15 s after a heavy session stopped.
//! 2. No overruns attributable to the others: over the windows touched by the heavy session
//!    (`heavy` and `switch`), the genuine session's overruns per second, and its lost slots per
//!    second (1 ms slots in which no tick ran at all: `1000 - ticks per second`), are not larger
//!    than over the `quiet` windows plus [`OVERRUN_TOLERANCE_PER_S`] (1 % of the 1 kHz slots).
//!    Both, because an overrun is a late tick however late: a loop whose every tick overruns
//!    (the default `lv` takes about 1.5 ms per tick on the 2-core development machine) shows
//!    fewer overruns, not more, when a neighbour starves it, since it runs fewer ticks; the lost
//!    slots show that. Also printed, not judged: the mean step time and the ticks longer than
//!    10 ms (the bridge's watchdog) in each kind of window.
//!
//! A genuine session that faults (quarantined, zero force) fails the run as well.
//!
//! Run: `cargo bench -p haptic-e2e --bench system_soak -- --minutes 30` (the default; also
//! `--watchers N` (50), `--scene NAME` (`lv`), `--heavy-tets N` (1500), `--realtime` (the servo
//! threads as deployed: `hapticd --realtime --cpu 1`, both sessions on CPU 1 with SCHED_FIFO),
//! `--publish` (write `docs/bench/system-soak.json` instead of `target/bench/system-soak.json`)).
//! Prints a table per minute and one per kind of window, then the verdicts.
//!
//! Neighbours: `watchers.rs` (what watchers cost the loop, one set-up at a time) and the helpers
//! in `tests/src/load.rs`.

use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail, ensure};
use haptic_e2e::load::{Received, cpu_seconds, grpc_watcher, memory_bytes, percentile};
use haptic_e2e::{BRIDGE, Daemon, finish, session_control, spawn_bin, start_session};
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::{
    ApplyForceRequest, GetStatsRequest, SessionStats, StartSessionRequest, StopSessionRequest, Vec3,
};
use serde_json::{Value, json};
use tonic::transport::Channel;

#[path = "system_soak/report.rs"]
mod report;
use report::{Report, report};

/// Watchers' frame rate, Hz (a viewer's).
const WATCH_RATE_HZ: f64 = 30.0;
/// The servo's slot rate (1 ms slots, the bridge's rate), Hz.
const SLOT_RATE_HZ: f64 = 1000.0;
/// Sampling window, s.
const WINDOW_S: u64 = 10;
/// Windows per minute.
const WINDOWS_PER_MINUTE: u64 = 60 / WINDOW_S;
/// The heavy session starts in this window of each minute, [`ACTION_OFFSET_S`] into it...
const HEAVY_START_WINDOW: u64 = 1;
/// ... and stops in this one: 30 s of heavy session, 15 s to 45 s of each minute.
const HEAVY_STOP_WINDOW: u64 = 4;
/// Where in its window a start or stop happens, s.
const ACTION_OFFSET_S: u64 = 5;
/// Time between the start of the bridge and watchers and the first sample, s.
const SETTLE_S: u64 = 5;
/// Scripted force: period, point (the epicardium at z = -5 mm on +y, as tests/tests/surface.rs
/// loads it), force (inward) and duration.
const FORCE_PERIOD: Duration = Duration::from_secs(3);
const FORCE_POINT_M: [f64; 3] = [0.0, 0.00968, -0.005];
const FORCE_N: [f64; 3] = [0.0, -0.02, 0.0];
const FORCE_DURATION_S: f64 = 0.2;
/// The bridge's pokes: amplitude from the default start (14 mm off the axis, so 6 mm reaches
/// 8 mm: 3.7 mm into the epicardium) and frequency.
const POKE_AMPLITUDE_M: f64 = 0.006;
const POKE_FREQUENCY_HZ: f64 = 0.25;
/// Verdict 1: largest RSS growth from the end of the warm-up to the end, fraction.
const RSS_GROWTH_LIMIT: f64 = 0.10;
/// Verdict 1: warm-up, minutes (halved for short runs).
const WARMUP_MINUTES: u64 = 5;
/// Verdict 2: how much larger the overrun and lost-slot rates may be with the heavy session
/// than without, per second (1 % of the 1 kHz slots: the window-to-window noise of a shared
/// 2-core machine, well below what a starved loop loses).
const OVERRUN_TOLERANCE_PER_S: f64 = 10.0;
/// The heavy session's scene: the built-in `lv` text, refined.
const LV_SCENE_TOML: &str = include_str!("../../deploy/scenes/lv.toml");

/// The checked command line.
#[derive(Debug, Clone)]
struct SoakConfig {
    minutes: u64,
    watchers: usize,
    scene: String,
    heavy_tets: u32,
    realtime: bool,
    publish: bool,
}

impl SoakConfig {
    /// Parses `--minutes N --watchers N --scene NAME --heavy-tets N --realtime --publish`
    /// (and ignores the `--bench` cargo passes).
    fn parse(args: impl IntoIterator<Item = String>) -> Result<SoakConfig> {
        let mut c = SoakConfig {
            minutes: 30,
            watchers: 50,
            scene: "lv".into(),
            heavy_tets: 1500,
            realtime: false,
            publish: false,
        };
        let mut args = args.into_iter();
        while let Some(a) = args.next() {
            let mut value = || args.next().with_context(|| format!("{a} needs a value"));
            match a.as_str() {
                "--bench" => {}
                "--realtime" => c.realtime = true,
                "--publish" => c.publish = true,
                "--minutes" => c.minutes = value()?.parse().context("--minutes")?,
                "--watchers" => c.watchers = value()?.parse().context("--watchers")?,
                "--scene" => c.scene = value()?,
                "--heavy-tets" => c.heavy_tets = value()?.parse().context("--heavy-tets")?,
                other => bail!(
                    "unknown argument {other:?} (expected --minutes N, --watchers N, --scene NAME, \
                     --heavy-tets N, --realtime, --publish)"
                ),
            }
        }
        ensure!(c.minutes >= 1, "--minutes must be at least 1");
        ensure!(c.heavy_tets >= 1, "--heavy-tets must be at least 1");
        Ok(c)
    }

    /// The command that reproduces this run.
    fn command(&self) -> String {
        let mut s = format!(
            "cargo bench -p haptic-e2e --bench system_soak -- --minutes {} --watchers {} --scene {} --heavy-tets {}",
            self.minutes, self.watchers, self.scene, self.heavy_tets
        );
        if self.realtime {
            s.push_str(" --realtime");
        }
        if self.publish {
            s.push_str(" --publish");
        }
        s
    }
}

/// `deploy/scenes/lv.toml` renamed `soak-heavy` with `target_tets = TETS`.
fn heavy_scene_toml(tets: u32) -> Result<String> {
    let (mut named, mut sized) = (0, 0);
    let lines: Vec<String> = LV_SCENE_TOML
        .lines()
        .map(|l| {
            if l.starts_with("name = ") {
                named += 1;
                "name = \"soak-heavy\"".to_string()
            } else if l.starts_with("target_tets = ") {
                sized += 1;
                format!("target_tets = {tets}")
            } else {
                l.to_string()
            }
        })
        .collect();
    ensure!(
        named == 1 && sized == 1,
        "deploy/scenes/lv.toml no longer has one `name = ` and one `target_tets = ` line"
    );
    Ok(lines.join("\n") + "\n")
}

/// Whether the heavy session was there during a window.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Presence {
    /// Absent the whole window.
    Quiet,
    /// Present the whole window.
    Heavy,
    /// Started (built) or stopped inside the window.
    Switch,
}

impl Presence {
    fn name(self) -> &'static str {
        match self {
            Presence::Quiet => "quiet",
            Presence::Heavy => "heavy",
            Presence::Switch => "switch",
        }
    }
}

/// The genuine session's step-time histogram from `/metrics`: cumulative counts per upper
/// bound (s), in the endpoint's order (ascending, `+Inf` last), and the sum of step times (s).
#[derive(Debug, Clone, Default)]
struct StepHistogram {
    buckets: Vec<(f64, u64)>,
    sum_s: f64,
}

impl StepHistogram {
    /// Parses the `hapticd_step_time_seconds` lines of session `id` from OpenMetrics text.
    fn parse(text: &str, id: &str) -> Option<StepHistogram> {
        let mut h = StepHistogram::default();
        let label = format!("session=\"{id}\"");
        for line in text.lines() {
            let Some((name_labels, value)) = line.rsplit_once(' ') else {
                continue;
            };
            let Some((name, labels)) = name_labels.split_once('{') else {
                continue;
            };
            if !labels.contains(&label) {
                continue;
            }
            match name {
                "hapticd_step_time_seconds_bucket" => {
                    let le = labels.split_once("le=\"")?.1.split_once('"')?.0;
                    let le = if le == "+Inf" {
                        f64::INFINITY
                    } else {
                        le.parse().ok()?
                    };
                    h.buckets.push((le, value.parse().ok()?));
                }
                "hapticd_step_time_seconds_sum" => h.sum_s = value.parse().ok()?,
                _ => {}
            }
        }
        (!h.buckets.is_empty()).then_some(h)
    }

    /// Counts per bucket (not cumulative) between `before` and `self`.
    fn delta(&self, before: &StepHistogram) -> Option<WindowSteps> {
        if self.buckets.len() != before.buckets.len() {
            return None;
        }
        let mut prev = 0;
        let counts = self
            .buckets
            .iter()
            .zip(&before.buckets)
            .map(|(a, b)| {
                let cum = a.1.saturating_sub(b.1);
                let c = cum.saturating_sub(prev);
                prev = cum;
                c
            })
            .collect();
        Some(WindowSteps {
            bounds_s: self.buckets.iter().map(|b| b.0).collect(),
            counts,
            sum_s: self.sum_s - before.sum_s,
        })
    }
}

/// Step times of the ticks of one or more windows: counts per bucket of upper bound
/// `bounds_s[i]` (s), and their sum (s).
#[derive(Debug, Clone)]
struct WindowSteps {
    bounds_s: Vec<f64>,
    counts: Vec<u64>,
    sum_s: f64,
}

impl WindowSteps {
    fn add(&mut self, o: &WindowSteps) {
        if self.bounds_s == o.bounds_s {
            self.counts
                .iter_mut()
                .zip(&o.counts)
                .for_each(|(a, b)| *a += b);
            self.sum_s += o.sum_s;
        }
    }

    fn count(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// Mean step time, µs.
    fn mean_us(&self) -> Option<f64> {
        let n = self.count();
        (n > 0).then(|| 1e6 * self.sum_s / n as f64)
    }

    /// Ticks above the last finite bound (10 ms: the bridge's watchdog).
    fn stalls(&self) -> u64 {
        self.bounds_s
            .iter()
            .zip(&self.counts)
            .filter(|(b, _)| b.is_infinite())
            .map(|(_, c)| c)
            .sum()
    }

    /// Upper bound of the bucket holding the `q` quantile, µs (infinite: above the last bound).
    fn quantile_bound_us(&self, q: f64) -> Option<f64> {
        let n = self.count();
        if n == 0 {
            return None;
        }
        let rank = (q * n as f64).ceil().max(1.0) as u64;
        let mut cum = 0;
        for (b, c) in self.bounds_s.iter().zip(&self.counts) {
            cum += c;
            if cum >= rank {
                return Some(b * 1e6);
            }
        }
        None
    }
}

/// One sample: taken at the end of each window.
struct Sample {
    at: Instant,
    rss_bytes: u64,
    hwm_bytes: u64,
    daemon_cpu_s: f64,
    own_cpu_s: f64,
    stats: SessionStats,
    steps: Option<StepHistogram>,
    frames: u64,
}

/// What the soak shares with its sampler.
struct Probe {
    ctl: SessionControlClient<Channel>,
    id: String,
    daemon_pid: u32,
    metrics_addr: Option<String>,
    watchers: Vec<Arc<Received>>,
}

impl Probe {
    async fn sample(&mut self) -> Result<Sample> {
        let at = Instant::now();
        let (rss_bytes, hwm_bytes) = memory_bytes(self.daemon_pid)?;
        let daemon_cpu_s = cpu_seconds(self.daemon_pid)?;
        let own_cpu_s = cpu_seconds(std::process::id())?;
        let stats = stats(&mut self.ctl, &self.id).await?;
        let steps = match &self.metrics_addr {
            Some(addr) => match http_get(addr, "/metrics").await {
                Ok(text) => StepHistogram::parse(&text, &self.id),
                Err(e) => {
                    eprintln!("system_soak: scraping /metrics failed: {e:#}");
                    None
                }
            },
            None => None,
        };
        let frames = self.watchers.iter().map(|w| w.snapshot().0).sum();
        Ok(Sample {
            at,
            rss_bytes,
            hwm_bytes,
            daemon_cpu_s,
            own_cpu_s,
            stats,
            steps,
            frames,
        })
    }
}

async fn stats(ctl: &mut SessionControlClient<Channel>, id: &str) -> Result<SessionStats> {
    Ok(ctl
        .get_stats(GetStatsRequest {
            session_id: id.to_string(),
        })
        .await
        .with_context(|| format!("GetStats {id}"))?
        .into_inner())
}

/// The body of `GET path` from `addr` (HTTP/1.1, `Connection: close`).
async fn http_get(addr: &str, path: &str) -> Result<String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let io = async {
        let mut s = tokio::net::TcpStream::connect(addr).await?;
        s.write_all(
            format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes(),
        )
        .await?;
        let mut buf = String::new();
        s.read_to_string(&mut buf).await?;
        anyhow::Ok(buf)
    };
    let buf = tokio::time::timeout(Duration::from_secs(5), io)
        .await
        .context("timed out")??;
    let (head, body) = buf.split_once("\r\n\r\n").context("no HTTP header")?;
    ensure!(
        head.starts_with("HTTP/1.1 200"),
        "{}",
        head.lines().next().unwrap_or("")
    );
    Ok(body.to_string())
}

/// The metrics address the daemon printed (`metrics on ADDR`), waiting up to 5 s.
async fn metrics_addr(daemon: &Daemon) -> Option<String> {
    for _ in 0..50 {
        let log = daemon.log_tail();
        if let Some(a) = log
            .lines()
            .find_map(|l| l.trim().strip_prefix("metrics on "))
        {
            return Some(a.trim().to_string());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    None
}

/// Runs the bridge on `session` until `deadline`, restarting it when it ends early; returns
/// each run's `--json` summary (or its failure).
async fn bridge_loop(url: String, session: String, deadline: Instant) -> Vec<Value> {
    let mut runs = Vec::new();
    loop {
        let left_s = deadline
            .saturating_duration_since(Instant::now())
            .as_secs_f64();
        if left_s < 1.0 {
            return runs;
        }
        let cycles = ((left_s * POKE_FREQUENCY_HZ).ceil() as u64 + 1).to_string();
        let (amplitude, frequency, duration) = (
            POKE_AMPLITUDE_M.to_string(),
            POKE_FREQUENCY_HZ.to_string(),
            format!("{left_s:.3}"),
        );
        let args = [
            "--server",
            &url,
            "--session",
            &session,
            "--script",
            "poke",
            "--amplitude-m",
            &amplitude,
            "--frequency-hz",
            &frequency,
            "--cycles",
            &cycles,
            "--duration-s",
            &duration,
            // Forces come back on by themselves after a link hiccup (no operator here).
            "--rearm",
            "auto",
            "--json",
        ];
        let started = Instant::now();
        let run = async {
            let p = spawn_bin(BRIDGE, &args)?;
            finish(p, Duration::from_secs_f64(left_s + 30.0)).await
        };
        let row = match run.await {
            Ok(out) => json!({
                "ran_s": started.elapsed().as_secs_f64(),
                "exit": out.status.code(),
                "summary": out.json().ok(),
                "stderr_tail": (!out.status.success()).then(|| tail(&out.stderr, 2000)),
            }),
            Err(e) => json!({"ran_s": started.elapsed().as_secs_f64(), "error": format!("{e:#}")}),
        };
        eprintln!("system_soak: bridge run ended: {row}");
        runs.push(row);
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

fn tail(s: &str, n: usize) -> String {
    let mut cut = s.len().saturating_sub(n);
    while !s.is_char_boundary(cut) {
        cut += 1;
    }
    s[cut..].to_string()
}

/// Applies the scripted force every [`FORCE_PERIOD`] until `stop`; counts answers in `ok`/`failed`.
async fn force_loop(
    mut ctl: SessionControlClient<Channel>,
    id: String,
    stop: Arc<AtomicBool>,
    ok: Arc<AtomicU64>,
    failed: Arc<AtomicU64>,
) {
    let mut every = tokio::time::interval(FORCE_PERIOD);
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    while !stop.load(Ordering::Relaxed) {
        every.tick().await;
        let r = ctl
            .apply_force(ApplyForceRequest {
                session_id: id.clone(),
                point_m: Some(Vec3::from(FORCE_POINT_M)),
                force_n: Some(Vec3::from(FORCE_N)),
                duration_s: FORCE_DURATION_S,
            })
            .await;
        match r {
            Ok(_) => ok.fetch_add(1, Ordering::Relaxed),
            Err(_) => failed.fetch_add(1, Ordering::Relaxed),
        };
    }
}

/// One window's figures.
struct Window {
    index: u64,
    presence: Presence,
    dt_s: f64,
    rss_mb: f64,
    hwm_mb: f64,
    daemon_cpu_percent: f64,
    own_cpu_percent: f64,
    ticks: u64,
    overruns: u64,
    steps: Option<WindowSteps>,
    stats: SessionStats,
    frames_per_watcher_per_s: f64,
}

impl Window {
    fn new(index: u64, presence: Presence, a: &Sample, b: &Sample, watchers: usize) -> Window {
        let dt_s = (b.at - a.at).as_secs_f64().max(1e-9);
        Window {
            index,
            presence,
            dt_s,
            rss_mb: b.rss_bytes as f64 / 1e6,
            hwm_mb: b.hwm_bytes as f64 / 1e6,
            daemon_cpu_percent: 100.0 * (b.daemon_cpu_s - a.daemon_cpu_s) / dt_s,
            own_cpu_percent: 100.0 * (b.own_cpu_s - a.own_cpu_s) / dt_s,
            ticks: b.stats.steps.saturating_sub(a.stats.steps),
            overruns: b.stats.overruns.saturating_sub(a.stats.overruns),
            steps: b
                .steps
                .as_ref()
                .zip(a.steps.as_ref())
                .and_then(|(b, a)| b.delta(a)),
            stats: b.stats.clone(),
            frames_per_watcher_per_s: b.frames.saturating_sub(a.frames) as f64
                / watchers.max(1) as f64
                / dt_s,
        }
    }

    fn minute(&self) -> u64 {
        self.index / WINDOWS_PER_MINUTE
    }

    fn overruns_per_s(&self) -> f64 {
        self.overruns as f64 / self.dt_s
    }

    /// 1 ms slots in which no tick ran, per second.
    fn lost_slots_per_s(&self) -> f64 {
        (SLOT_RATE_HZ - self.ticks as f64 / self.dt_s).max(0.0)
    }

    fn json(&self) -> Value {
        json!({
            "window": self.index,
            "minute": self.minute(),
            "heavy": self.presence.name(),
            "window_s": self.dt_s,
            "daemon_rss_mb": self.rss_mb,
            "daemon_hwm_mb": self.hwm_mb,
            "daemon_cpu_percent": self.daemon_cpu_percent,
            "bench_cpu_percent": self.own_cpu_percent,
            "ticks": self.ticks,
            "overruns": self.overruns,
            "overruns_per_s": self.overruns_per_s(),
            "lost_slots_per_s": self.lost_slots_per_s(),
            "loop_rate_hz": self.ticks as f64 / self.dt_s,
            "window_step_mean_us": self.steps.as_ref().and_then(WindowSteps::mean_us),
            "window_step_p99_bound_us": self.steps.as_ref().and_then(|s| finite(s.quantile_bound_us(0.99))),
            "window_ticks_over_10ms": self.steps.as_ref().map(WindowSteps::stalls),
            "life_step_p50_us": self.stats.step_p50_us,
            "life_step_p99_us": self.stats.step_p99_us,
            "life_step_max_us": self.stats.step_max_us,
            "stats_loop_rate_hz": self.stats.loop_rate_hz,
            "pose_to_force_p99_us": self.stats.pose_to_force_p99_us,
            "watchers": self.stats.watchers,
            "watcher_frames_dropped": self.stats.watcher_frames_dropped,
            "frames_per_watcher_per_s": self.frames_per_watcher_per_s,
            "device_samples": self.stats.device_samples,
            "faulted": self.stats.faulted,
            "overrunning": self.stats.overrunning,
            "demoted": self.stats.demoted,
        })
    }
}

/// `Some(x)` for finite `x`; JSON has no infinity (above the last bucket: `null`).
fn finite(x: Option<f64>) -> Option<f64> {
    x.filter(|v| v.is_finite())
}

/// Figures of a group of windows.
struct Group {
    windows: usize,
    overruns_per_s: f64,
    lost_slots_per_s: f64,
    loop_rate_hz: f64,
    daemon_cpu_percent: f64,
    steps: Option<WindowSteps>,
}

impl Group {
    fn of<'a>(ws: impl IntoIterator<Item = &'a Window>) -> Option<Group> {
        let ws: Vec<&Window> = ws.into_iter().collect();
        if ws.is_empty() {
            return None;
        }
        let t: f64 = ws.iter().map(|w| w.dt_s).sum();
        let sum = |f: &dyn Fn(&Window) -> f64| ws.iter().map(|w| f(w) * w.dt_s).sum::<f64>() / t;
        let mut steps: Option<WindowSteps> = None;
        for s in ws.iter().filter_map(|w| w.steps.as_ref()) {
            match &mut steps {
                Some(acc) => acc.add(s),
                None => steps = Some(s.clone()),
            }
        }
        Some(Group {
            windows: ws.len(),
            overruns_per_s: sum(&Window::overruns_per_s),
            lost_slots_per_s: sum(&Window::lost_slots_per_s),
            loop_rate_hz: sum(&|w| w.ticks as f64 / w.dt_s),
            daemon_cpu_percent: sum(&|w| w.daemon_cpu_percent),
            steps,
        })
    }

    fn json(&self) -> Value {
        json!({
            "windows": self.windows,
            "overruns_per_s": self.overruns_per_s,
            "lost_slots_per_s": self.lost_slots_per_s,
            "loop_rate_hz": self.loop_rate_hz,
            "daemon_cpu_percent": self.daemon_cpu_percent,
            "step_mean_us": self.steps.as_ref().and_then(WindowSteps::mean_us),
            "step_p99_bound_us": self.steps.as_ref().and_then(|s| finite(s.quantile_bound_us(0.99))),
            "ticks_over_10ms": self.steps.as_ref().map(WindowSteps::stalls),
        })
    }
}

/// The bridge's figures summed over its runs (from their `--json` summaries).
fn bridge_line(runs: &[Value]) -> String {
    let sum = |k: &str| -> u64 { runs.iter().filter_map(|r| r["summary"][k].as_u64()).sum() };
    let max = |k: &str| -> f64 {
        runs.iter()
            .filter_map(|r| r["summary"][k].as_f64())
            .fold(0.0, f64::max)
    };
    let ran_s: f64 = runs.iter().filter_map(|r| r["ran_s"].as_f64()).sum();
    format!(
        "bridge: {} run(s), {ran_s:.0} s, {} device ticks ({:.0} Hz), {} device-loop overruns, force round trip p50 / p99 {:.0} / {:.0} us (worst run), {} watchdog expiries, {} latches and {} re-arms, peak force {:.3} N",
        runs.len(),
        sum("ticks"),
        sum("ticks") as f64 / ran_s.max(1e-9),
        sum("overruns"),
        max("rtt_p50_us"),
        max("rtt_p99_us"),
        sum("watchdog_expired"),
        sum("latches"),
        sum("rearms"),
        max("peak_force_n"),
    )
}

/// A step-time bucket bound for the table (`>10000` above the last finite bound).
fn bound_cell(steps: Option<&WindowSteps>) -> String {
    let Some(s) = steps else { return "-".into() };
    match s.quantile_bound_us(0.99) {
        Some(b) if b.is_finite() => format!("<={b:.0}"),
        Some(_) => {
            let last = s
                .bounds_s
                .iter()
                .rev()
                .find(|b| b.is_finite())
                .copied()
                .unwrap_or(0.0);
            format!(">{:.0}", last * 1e6)
        }
        None => "-".into(),
    }
}

fn opt_cell(x: Option<f64>, decimals: usize) -> String {
    x.map_or("-".into(), |v| format!("{v:.decimals$}"))
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> ExitCode {
    match soak().await {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => {
            eprintln!("system_soak: a verdict failed (figures above)");
            ExitCode::FAILURE
        }
        Err(e) => {
            eprintln!("system_soak: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// The daemon with its metrics listener (SCHED_FIFO on CPU 1 when `realtime`), and the
/// metrics address it printed.
async fn start_daemon(realtime: bool) -> Result<(Daemon, Option<String>)> {
    let mut daemon_args = vec!["--metrics-listen", "127.0.0.1:0"];
    if realtime {
        daemon_args.extend(["--realtime", "--cpu", "1"]);
    }
    let daemon = Daemon::spawn(&daemon_args)?;
    let metrics = metrics_addr(&daemon).await;
    if metrics.is_none() {
        eprintln!("system_soak: the daemon printed no metrics address: no per-window step times");
    }
    Ok((daemon, metrics))
}

/// `n` compact gRPC watchers of session `id` at [`WATCH_RATE_HZ`], until `stop`.
async fn start_watchers(
    url: &str,
    id: &str,
    n: usize,
    stop: &Arc<AtomicBool>,
) -> Result<Vec<Arc<Received>>> {
    let mut watchers = Vec::with_capacity(n);
    for _ in 0..n {
        watchers.push(grpc_watcher(url, id, WATCH_RATE_HZ, true, stop.clone()).await?);
    }
    Ok(watchers)
}

/// The soak; `Ok(false)` when a verdict failed.
async fn soak() -> Result<bool> {
    let cfg = SoakConfig::parse(std::env::args().skip(1))?;
    let heavy_toml = heavy_scene_toml(cfg.heavy_tets)?;
    let (daemon, metrics) = start_daemon(cfg.realtime).await?;
    let url = daemon.url();
    let id = start_session(&url, &cfg.scene).await?;
    let ctl = session_control(&url).await?;
    eprintln!(
        "system_soak: {} min, session {id} ({}), {} watchers, heavy {} tets, daemon {url}",
        cfg.minutes, cfg.scene, cfg.watchers, cfg.heavy_tets
    );

    let stop = Arc::new(AtomicBool::new(false));
    let watchers = start_watchers(&url, &id, cfg.watchers, &stop).await?;
    let soak_s = cfg.minutes * 60;
    let t0 = Instant::now() + Duration::from_secs(SETTLE_S);
    // The bridge outlasts the last sample by 2 s.
    let bridge = tokio::spawn(bridge_loop(
        url.clone(),
        id.clone(),
        t0 + Duration::from_secs(soak_s + 2),
    ));
    let (forces_ok, forces_failed) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let forces = tokio::spawn(force_loop(
        ctl.clone(),
        id.clone(),
        stop.clone(),
        forces_ok.clone(),
        forces_failed.clone(),
    ));

    let mut probe = Probe {
        ctl: ctl.clone(),
        id: id.clone(),
        daemon_pid: daemon.pid(),
        metrics_addr: metrics,
        watchers,
    };
    tokio::time::sleep_until(t0.into()).await;
    let mut prev = probe.sample().await?;
    let first_rss_mb = prev.rss_bytes as f64 / 1e6;
    let mut windows: Vec<Window> = Vec::new();
    let mut cycles: Vec<Value> = Vec::new();
    let mut heavy = Heavy {
        ctl: ctl.clone(),
        toml: heavy_toml,
        running: None,
    };
    for k in 0..cfg.minutes * WINDOWS_PER_MINUTE {
        let start = t0 + Duration::from_secs(k * WINDOW_S);
        let present_at_start = heavy.running.is_some();
        let mut switched = false;
        let phase = k % WINDOWS_PER_MINUTE;
        if phase == HEAVY_START_WINDOW || phase == HEAVY_STOP_WINDOW {
            tokio::time::sleep_until((start + Duration::from_secs(ACTION_OFFSET_S)).into()).await;
            switched = true;
            let minute = k / WINDOWS_PER_MINUTE;
            heavy
                .switch(phase == HEAVY_START_WINDOW, minute, &mut cycles)
                .await;
        }
        tokio::time::sleep_until((start + Duration::from_secs(WINDOW_S)).into()).await;
        let now = probe.sample().await?;
        let presence = match (present_at_start, heavy.running.is_some(), switched) {
            (false, false, false) => Presence::Quiet,
            (true, true, false) => Presence::Heavy,
            _ => Presence::Switch,
        };
        windows.push(Window::new(k, presence, &prev, &now, cfg.watchers));
        prev = now;
        if phase == WINDOWS_PER_MINUTE - 1 {
            let minute = k / WINDOWS_PER_MINUTE;
            progress(&windows, minute, cfg.minutes, &cycles, &forces_ok);
        }
    }

    // Wind down: forces, bridge, watchers, a heavy session left over, the genuine session.
    stop.store(true, Ordering::Relaxed);
    let heavy_left = heavy.running.take().map(|(hid, _)| hid);
    let (bridge_runs, last, watchers_failed) =
        wind_down(forces, bridge, heavy_left, &mut heavy.ctl, &probe).await?;
    drop(daemon);

    report(Report {
        cfg: &cfg,
        windows: &windows,
        cycles: &cycles,
        bridge_runs: &bridge_runs,
        forces: (
            forces_ok.load(Ordering::Relaxed),
            forces_failed.load(Ordering::Relaxed),
        ),
        watchers_failed,
        first_rss_mb,
        last: &last,
    })
}

/// After the soak (the stop flag set): waits for the force task and the bridge, stops a heavy
/// session left over and the genuine one; returns the bridge's runs, the genuine session's
/// last statistics and how many watchers failed.
async fn wind_down(
    forces: tokio::task::JoinHandle<()>,
    bridge: tokio::task::JoinHandle<Vec<Value>>,
    heavy_left: Option<String>,
    heavy_ctl: &mut SessionControlClient<Channel>,
    probe: &Probe,
) -> Result<(Vec<Value>, SessionStats, usize)> {
    let id = &probe.id;
    let _ = tokio::time::timeout(Duration::from_secs(10), forces).await;
    let bridge_runs = match tokio::time::timeout(Duration::from_secs(60), bridge).await {
        Ok(Ok(runs)) => runs,
        _ => vec![json!({"error": "the bridge did not end within 60 s of the soak (killed)"})],
    };
    if let Some(hid) = heavy_left {
        let _ = heavy_ctl
            .stop_session(StopSessionRequest { session_id: hid })
            .await;
    }
    let last = stats(&mut probe.ctl.clone(), id).await?;
    let watchers_failed = probe
        .watchers
        .iter()
        .filter(|w| w.failed.load(Ordering::Relaxed))
        .count();
    let _ = probe
        .ctl
        .clone()
        .stop_session(StopSessionRequest {
            session_id: id.to_string(),
        })
        .await;
    Ok((bridge_runs, last, watchers_failed))
}

/// The heavy session that comes and goes during the soak.
struct Heavy {
    ctl: SessionControlClient<Channel>,
    /// Its scene.
    toml: String,
    /// Its id and start time while it runs.
    running: Option<(String, Instant)>,
}

impl Heavy {
    /// At a heavy window's action time: starts the heavy session (`starting`, when none runs) or
    /// stops the running one, recording the cycle (or the start's error) in `cycles`.
    async fn switch(&mut self, starting: bool, minute: u64, cycles: &mut Vec<Value>) {
        let (heavy, heavy_ctl) = (&mut self.running, &mut self.ctl);
        if starting && heavy.is_none() {
            let t = Instant::now();
            match heavy_ctl
                .start_session(StartSessionRequest {
                    scene: String::new(),
                    scene_toml: self.toml.clone(),
                })
                .await
            {
                Ok(r) => *heavy = Some((r.into_inner().session_id, t)),
                Err(e) => cycles.push(json!({
                    "minute": minute,
                    "error": format!("StartSession: {e}"),
                })),
            }
        } else if let Some((hid, t)) = heavy.take() {
            let s = stats(heavy_ctl, &hid).await.ok();
            let stopped = heavy_ctl
                .stop_session(StopSessionRequest {
                    session_id: hid.clone(),
                })
                .await;
            cycles.push(json!({
                "minute": minute,
                "session": hid,
                "ran_s": t.elapsed().as_secs_f64(),
                "nodes": s.as_ref().map(|s| s.nodes),
                "tetrahedra": s.as_ref().map(|s| s.tetrahedra),
                "substeps": s.as_ref().map(|s| s.substeps),
                "step_p50_us": s.as_ref().map(|s| s.step_p50_us),
                "step_p99_us": s.as_ref().map(|s| s.step_p99_us),
                "steps": s.as_ref().map(|s| s.steps),
                "overruns": s.as_ref().map(|s| s.overruns),
                "demoted": s.as_ref().map(|s| s.demoted),
                "stop_error": stopped.err().map(|e| e.to_string()),
            }));
        }
    }
}

/// The quiet windows of `this` and those the heavy session touched.
fn quiet_and_heavy(this: &[&Window]) -> (Option<Group>, Option<Group>) {
    let of = |quiet: bool| {
        Group::of(
            this.iter()
                .copied()
                .filter(move |w| (w.presence == Presence::Quiet) == quiet),
        )
    };
    (of(true), of(false))
}

/// One progress line on stderr for minute `m`.
fn progress(windows: &[Window], m: u64, minutes: u64, cycles: &[Value], forces: &AtomicU64) {
    let this: Vec<&Window> = windows.iter().filter(|w| w.minute() == m).collect();
    let (q, h) = quiet_and_heavy(&this);
    let Some(end) = this.last() else { return };
    let heavy = cycles
        .iter()
        .rev()
        .find(|c| c["minute"] == m)
        .map_or("-".to_string(), |c| {
            if let Some(e) = c["error"].as_str() {
                e.to_string()
            } else {
                format!(
                    "step p50 {} us, {} overruns",
                    c["step_p50_us"], c["overruns"]
                )
            }
        });
    eprintln!(
        "minute {}/{minutes}: RSS {:.1} MB, daemon CPU {:.0} %, loop {:.0} Hz, overruns/s quiet {} heavy {}, lost slots/s quiet {} heavy {}, step p99 (life) {:.0} us, heavy: {heavy}, forces {}",
        m + 1,
        end.rss_mb,
        this.iter().map(|w| w.daemon_cpu_percent).sum::<f64>() / this.len() as f64,
        this.iter().map(|w| w.ticks as f64 / w.dt_s).sum::<f64>() / this.len() as f64,
        opt_cell(q.as_ref().map(|g| g.overruns_per_s), 0),
        opt_cell(h.as_ref().map(|g| g.overruns_per_s), 0),
        opt_cell(q.as_ref().map(|g| g.lost_slots_per_s), 0),
        opt_cell(h.as_ref().map(|g| g.lost_slots_per_s), 0),
        end.stats.step_p99_us,
        forces.load(Ordering::Relaxed),
    );
}

/// Where results go: `target/bench/` (or `$CARGO_TARGET_DIR/bench/`), or `docs/bench/` with
/// `--publish`, so that a run leaves the work tree clean unless asked.
fn results_dir(publish: bool) -> Result<std::path::PathBuf> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = if publish {
        root.join("docs/bench")
    } else {
        std::env::var_os("CARGO_TARGET_DIR")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| root.join("target"))
            .join("bench")
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir)
}
