//! What watchers cost the 1 kHz loop (issue 17, section 3): the real release `hapticd` with the
//! default `lv`, the real `haptic-bridge` pressing (3.7 mm into the epicardium, held), and 0, 1,
//! 10, 100 and 300 watchers at 30 Hz, each on its own connection, in three set-ups:
//!
//! - `grpc-compact`: the watchers call `SurfaceStream.Watch` on the daemon (DELTA, 1 um);
//! - `relay`: the watchers are WebSockets on one `haptic-viewer --web` relay, which holds one
//!   compact `Watch` on the daemon;
//! - `grpc-full`: `Watch` with full float frames (100 and 300 only, for comparison).
//!
//! Each run is a fresh session (so its step-time histogram and overrun count are its own):
//! start the session, attach the watchers, start the press, wait 1.5 s (the probe is in contact
//! after 0.85 s), then measure for `WINDOW_S`: the servo's step p50/p99/max (`GetStats`, over
//! the session's life), overruns during the window, CPU of the daemon, the relay and this
//! process (the watchers) during the window, their resident memory at its end, and frames per
//! watcher in the window. Loopback only, 33 runs of about 14 s.
//!
//! Writes `target/bench/watchers.json` (`-- --publish`: `docs/bench/`) and prints the table of `docs/benchmarks.md`.
//!
//! The plan (11 set-ups) runs `--repeat N` times (default 3), interleaved; the table gives the
//! median of each figure over the repetitions and the range of p99 and overruns.
//!
//! Run: `cargo bench -p haptic-e2e --bench watchers` (`-- --quick` for one 3 s window each;
//! `-- --realtime` runs the servo as deployed, SCHED_FIFO pinned to CPU 1, and writes
//! `watchers-realtime.json` instead; `-- --publish` writes into `docs/bench/`).
//! `-- --compact-only 0,100 --window 30 --repeat 6` runs only those grpc-compact set-ups with
//! longer windows (the overrun comparison), into `watchers-overruns[-realtime].json`.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use haptic_e2e::load::{Received, cpu_seconds, grpc_watcher, memory_bytes, percentile, ws_watcher};
use haptic_e2e::{BRIDGE, Daemon, session_control, spawn_bin, spawn_web_viewer, start_session};
use haptics_proto::v1::{GetStatsRequest, SessionStats, StopSessionRequest};
use serde_json::{Value, json};

const RATE_HZ: f64 = 30.0;

#[derive(Clone, Copy, PartialEq)]
enum Mode {
    GrpcCompact,
    Relay,
    GrpcFull,
}

impl Mode {
    fn name(self) -> &'static str {
        match self {
            Mode::GrpcCompact => "grpc-compact",
            Mode::Relay => "relay",
            Mode::GrpcFull => "grpc-full",
        }
    }
}

async fn stats(url: &str, id: &str) -> Result<SessionStats> {
    Ok(session_control(url)
        .await?
        .get_stats(GetStatsRequest {
            session_id: id.to_string(),
        })
        .await?
        .into_inner())
}

async fn relay_counters(addr: &str) -> Result<Value> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await?;
    s.write_all(
        format!("GET /api/relay HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes(),
    )
    .await?;
    let mut buf = String::new();
    s.read_to_string(&mut buf).await?;
    let body = buf.split_once("\r\n\r\n").map(|x| x.1).unwrap_or("{}");
    Ok(serde_json::from_str(body)?)
}

/// `n` watchers of session `id` in `mode`, 30 Hz each, until `stop`.
async fn attach_watchers(
    mode: Mode,
    n: usize,
    url: &str,
    id: &str,
    relay: Option<(&str, u32)>,
    stop: &Arc<AtomicBool>,
) -> Result<Vec<Arc<Received>>> {
    let mut watchers: Vec<Arc<Received>> = Vec::with_capacity(n);
    for _ in 0..n {
        let w = match mode {
            Mode::GrpcCompact => grpc_watcher(url, id, RATE_HZ, true, stop.clone()).await?,
            Mode::GrpcFull => grpc_watcher(url, id, RATE_HZ, false, stop.clone()).await?,
            Mode::Relay => {
                let (addr, _) = relay.context("relay")?;
                ws_watcher(addr, id, RATE_HZ, stop.clone()).await?
            }
        };
        watchers.push(w);
    }
    Ok(watchers)
}

/// CPU seconds used so far by the daemon, the relay (if any) and this process.
fn cpu_sample(
    daemon_pid: u32,
    relay: Option<(&str, u32)>,
    me: u32,
) -> Result<(f64, Option<f64>, f64)> {
    Ok((
        cpu_seconds(daemon_pid)?,
        relay.map(|(_, p)| cpu_seconds(p)).transpose()?,
        cpu_seconds(me)?,
    ))
}

#[allow(clippy::too_many_arguments)]
async fn run(
    mode: Mode,
    n: usize,
    window_s: f64,
    url: &str,
    daemon_pid: u32,
    relay: Option<(&str, u32)>,
) -> Result<Value> {
    let id = start_session(url, "lv").await?;
    let stop = Arc::new(AtomicBool::new(false));
    let watchers = attach_watchers(mode, n, url, &id, relay, &stop).await?;
    let hold_s = format!("{}", window_s + 4.0);
    let bridge = spawn_bin(
        BRIDGE,
        &[
            "--server",
            url,
            "--session",
            &id,
            "--script",
            "press",
            "--hold-s",
            &hold_s,
        ],
    )?;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let before: Vec<u64> = watchers.iter().map(|w| w.snapshot().0).collect();
    let s0 = stats(url, &id).await?;
    let me = std::process::id();
    let cpu0 = cpu_sample(daemon_pid, relay, me)?;
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_secs_f64(window_s)).await;
    let dt = t0.elapsed().as_secs_f64();
    let cpu1 = cpu_sample(daemon_pid, relay, me)?;
    let s1 = stats(url, &id).await?;
    let mem_daemon = memory_bytes(daemon_pid)?;
    let mem_relay = relay.map(|(_, p)| memory_bytes(p)).transpose()?;
    let relay_json = match relay {
        Some((addr, _)) if mode == Mode::Relay => relay_counters(addr).await.ok(),
        _ => None,
    };
    let per: Vec<f64> = watchers
        .iter()
        .zip(&before)
        .map(|(w, b)| (w.snapshot().0 - b) as f64)
        .collect();
    let failed = watchers
        .iter()
        .filter(|w| w.failed.load(Ordering::Relaxed))
        .count();
    stop.store(true, Ordering::Relaxed);
    drop(bridge);
    session_control(url)
        .await?
        .stop_session(StopSessionRequest { session_id: id })
        .await?;
    let pct = |c1: f64, c0: f64| 100.0 * (c1 - c0) / dt;
    let row = json!({
        "mode": mode.name(),
        "watchers": n,
        "window_s": dt,
        "step_p50_us": s1.step_p50_us,
        "step_p99_us": s1.step_p99_us,
        "step_max_us": s1.step_max_us,
        "loop_rate_hz": s1.loop_rate_hz,
        "overruns_in_window": s1.overruns - s0.overruns,
        "in_contact": s1.in_contact,
        "daemon_watchers": s1.watchers,
        "daemon_frames_dropped": s1.watcher_frames_dropped,
        "daemon_cpu_percent": pct(cpu1.0, cpu0.0),
        "relay_cpu_percent": cpu1.1.zip(cpu0.1).map(|(a, b)| pct(a, b)),
        "watchers_cpu_percent": pct(cpu1.2, cpu0.2),
        "daemon_rss_mb": mem_daemon.0 as f64 / 1e6,
        "relay_rss_mb": mem_relay.map(|m| m.0 as f64 / 1e6),
        "frames_per_watcher_min": per.iter().copied().reduce(f64::min).unwrap_or(0.0),
        "frames_per_watcher_p50": percentile(&per, 0.5),
        "frames_per_watcher_max": per.iter().copied().fold(0.0, f64::max),
        "expected_frames_per_watcher": RATE_HZ * dt,
        "failed_watchers": failed,
        "relay": relay_json,
    });
    eprintln!("{row}");
    Ok(row)
}

fn cell(v: &Value, key: &str, decimals: usize) -> String {
    v[key]
        .as_f64()
        .map_or("-".into(), |x| format!("{x:.decimals$}"))
}

/// The command line: `--quick`, `--window S`, `--compact-only N,M`, `--repeat R`, `--realtime`.
struct Options {
    window_s: f64,
    compact_only: Option<Vec<usize>>,
    repeat: usize,
    realtime: bool,
}

impl Options {
    fn parse(args: &[String]) -> Self {
        let quick = args.iter().any(|a| a == "--quick");
        let value = |flag: &str| {
            args.iter()
                .position(|a| a == flag)
                .and_then(|i| args.get(i + 1).cloned())
        };
        Self {
            // `--window S`: a longer window counts more overruns per run (the overrun question
            // of issue 17 needs them; the default 10 s gives a handful).
            window_s: value("--window")
                .and_then(|v| v.parse().ok())
                .unwrap_or(if quick { 3.0 } else { 10.0 }),
            // `--compact-only N,M`: only the grpc-compact set-ups with these watcher counts.
            compact_only: value("--compact-only")
                .map(|v| v.split(',').filter_map(|n| n.trim().parse().ok()).collect()),
            // Repetitions of the whole plan, interleaved, so that a slow minute of the shared
            // machine does not land on one set-up; the table gives medians over them.
            repeat: value("--repeat")
                .and_then(|v| v.parse().ok())
                .unwrap_or(if quick { 1 } else { 3 }),
            // `--realtime`: the servo as deployed (SCHED_FIFO, pinned to CPU 1), so that what
            // the watchers cost it is not hidden by the scheduler's noise.
            realtime: args.iter().any(|a| a == "--realtime"),
        }
    }

    /// The set-ups of one repetition.
    fn plan(&self) -> Vec<(Mode, usize)> {
        match &self.compact_only {
            Some(counts) => counts.iter().map(|&n| (Mode::GrpcCompact, n)).collect(),
            None => [0, 1, 10, 100, 300]
                .iter()
                .map(|&n| (Mode::GrpcCompact, n))
                .chain([1, 10, 100, 300].iter().map(|&n| (Mode::Relay, n)))
                .chain([100, 300].iter().map(|&n| (Mode::GrpcFull, n)))
                .collect(),
        }
    }

    /// The results file's name.
    fn file_name(&self) -> &'static str {
        match (self.compact_only.is_some(), self.realtime) {
            (true, true) => "watchers-overruns-realtime.json",
            (true, false) => "watchers-overruns.json",
            (false, true) => "watchers-realtime.json",
            (false, false) => "watchers.json",
        }
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let opts = Options::parse(&args);
    let daemon = if opts.realtime {
        Daemon::spawn(&["--realtime", "--cpu", "1"])?
    } else {
        Daemon::spawn(&[])?
    };
    let url = daemon.url();
    let daemon_pid = daemon.pid();
    let (relay_proc, relay_addr) = spawn_web_viewer(&url, &[]).await?;
    let relay_pid = relay_proc.child.id().context("relay pid")?;
    let mut rows = Vec::new();
    let plan = opts.plan();
    for rep in 0..opts.repeat {
        for &(mode, n) in &plan {
            let relay = Some((relay_addr.as_str(), relay_pid));
            let mut row = run(mode, n, opts.window_s, &url, daemon_pid, relay).await?;
            row["repetition"] = json!(rep);
            rows.push(row);
        }
    }
    let summary = summarize(&rows, &plan);
    print_table(&summary, opts.window_s);
    let out = results_dir()?.join(opts.file_name());
    let doc = json!({
        "what": "servo step time and overruns, CPU and memory against watchers at 30 Hz, default lv, bridge pressing",
        "command": format!(
            "cargo bench -p haptic-e2e --bench watchers --{}",
            args.iter()
                .skip(1)
                .filter(|a| *a != "--bench" && *a != "--publish")
                .fold(String::new(), |acc, a| acc + " " + a)
        ),
        "window_s": opts.window_s,
        "repetitions": opts.repeat,
        "realtime": opts.realtime,
        "summary": summary,
        "runs": rows,
    });
    std::fs::write(&out, serde_json::to_string_pretty(&doc)? + "\n")?;
    eprintln!("wrote {}", out.display());
    drop(relay_proc);
    Ok(())
}

/// Per set-up of `plan`, the medians over the repetitions in `rows` (memory: the first
/// repetition's), the p99 and overrun ranges, and the frames dropped in all of them.
fn summarize(rows: &[Value], plan: &[(Mode, usize)]) -> Vec<Value> {
    // Medians over the repetitions of each set-up.
    let median = |mode: &str, n: u64, key: &str| -> Option<f64> {
        let v: Vec<f64> = rows
            .iter()
            .filter(|r| r["mode"] == mode && r["watchers"] == n)
            .filter_map(|r| r[key].as_f64())
            .collect();
        (!v.is_empty()).then(|| percentile(&v, 0.5))
    };
    let range = |mode: &str, n: u64, key: &str| -> String {
        let v: Vec<f64> = rows
            .iter()
            .filter(|r| r["mode"] == mode && r["watchers"] == n)
            .filter_map(|r| r[key].as_f64())
            .collect();
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        format!("{lo:.0}-{hi:.0}")
    };
    let first = |mode: &str, n: u64, key: &str| -> Option<f64> {
        rows.iter()
            .find(|r| r["mode"] == mode && r["watchers"] == n)
            .and_then(|r| r[key].as_f64())
    };
    plan.iter()
        .map(|&(mode, n)| {
            let (m, n) = (mode.name(), n as u64);
            let dropped: u64 = rows
                .iter()
                .filter(|r| r["mode"] == m && r["watchers"] == n)
                .map(|r| {
                    r["daemon_frames_dropped"].as_u64().unwrap_or(0)
                        + r["relay"]["sessions"][0]["frames_dropped"]
                            .as_u64()
                            .unwrap_or(0)
                })
                .sum();
            json!({
                "mode": m,
                "watchers": n,
                "step_p50_us": median(m, n, "step_p50_us"),
                "step_p99_us": median(m, n, "step_p99_us"),
                "step_p99_us_range": range(m, n, "step_p99_us"),
                "step_max_us": median(m, n, "step_max_us"),
                "overruns_in_window": median(m, n, "overruns_in_window"),
                "overruns_range": range(m, n, "overruns_in_window"),
                "daemon_cpu_percent": median(m, n, "daemon_cpu_percent"),
                "relay_cpu_percent": median(m, n, "relay_cpu_percent"),
                "watchers_cpu_percent": median(m, n, "watchers_cpu_percent"),
                // Memory of the first repetition: the processes serve every run and the
                // allocator keeps what it freed, so later repetitions show the history.
                "daemon_rss_mb": first(m, n, "daemon_rss_mb"),
                "relay_rss_mb": first(m, n, "relay_rss_mb"),
                "frames_per_watcher_min": median(m, n, "frames_per_watcher_min"),
                "frames_per_watcher_p50": median(m, n, "frames_per_watcher_p50"),
                "dropped": dropped,
            })
        })
        .collect()
}

/// The summary as a Markdown table on stdout.
fn print_table(summary: &[Value], window_s: f64) {
    println!(
        "| set-up | watchers | step p50 / p99 (us) | p99 range | overruns in {window_s:.0} s (range) | daemon CPU | relay CPU | watchers' CPU | daemon / relay RSS (MB) | frames per watcher min / p50 (of {:.0}) | dropped |",
        RATE_HZ * window_s
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for r in summary {
        println!(
            "| {} | {} | {} / {} | {} | {} ({}) | {} % | {} % | {} % | {} / {} | {} / {} | {} |",
            r["mode"].as_str().unwrap_or(""),
            r["watchers"],
            cell(r, "step_p50_us", 0),
            cell(r, "step_p99_us", 0),
            r["step_p99_us_range"].as_str().unwrap_or(""),
            cell(r, "overruns_in_window", 0),
            r["overruns_range"].as_str().unwrap_or(""),
            cell(r, "daemon_cpu_percent", 0),
            cell(r, "relay_cpu_percent", 0),
            cell(r, "watchers_cpu_percent", 0),
            cell(r, "daemon_rss_mb", 0),
            cell(r, "relay_rss_mb", 0),
            cell(r, "frames_per_watcher_min", 0),
            cell(r, "frames_per_watcher_p50", 0),
            r["dropped"],
        );
    }
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
