//! Issue 15, section 4: fault tests with the real binaries on loopback. A `haptic-bridge`
//! (simulated probe, `--rearm auto`) presses the LV of a real `hapticd` and records every
//! device tick; during the hold the test kills the daemon (`kill -9`, then restarts it with the
//! same state dir and port), stops it (SIGSTOP for 50 ms, 500 ms, 5 s), stops the bridge for
//! 200 ms, or makes the bridge drop 10 % of the messages or delay commands by 5, 20, 50 ms or a
//! random 5-50 ms.
//!
//! Every case checks, on the recording, the properties the guard promises whatever the timing
//! on a loaded machine: the force never exceeds the limits, every tick whose command answers a
//! pose 60 ms old or older renders exactly zero, no tick-to-tick step exceeds the slew limit
//! (the scene's 300 N/s: 0.3 N per 1 ms tick), the force is zero while disabled, and the
//! bridge reconnects when the daemon returns. The largest step and the time to zero (the age
//! of the command at the first zero tick) are printed for docs/benchmarks.md. Durations are
//! bounded: each case runs one bridge script of 3-9 s.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, ensure};
use haptic_e2e::{
    BRIDGE, Daemon, finish, serial, signal, spawn_bin, start_session, unique_temp_dir,
};

/// The scene's force-rate limit times one device tick, N (LV: 300 N/m coupling x 1 m/s).
const SLEW_STEP_N: f64 = 0.3;
/// The scene's and the sim device's force limit, N.
const MAX_FORCE_N: f64 = 10.0;

#[derive(Debug, Clone)]
struct Row {
    t_s: f64,
    f_n: f64,
    age_us: Option<u64>,
    state: String,
}

fn read_rows(path: &Path) -> Result<Vec<Row>> {
    let mut r = csv::Reader::from_path(path).with_context(|| format!("opening {path:?}"))?;
    let mut rows = Vec::new();
    for rec in r.records() {
        let rec = rec?;
        let num = |i: usize| -> Result<f64> { Ok(rec[i].parse()?) };
        let f = [num(4)?, num(5)?, num(6)?];
        rows.push(Row {
            t_s: num(0)?,
            f_n: (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt(),
            age_us: rec[9].parse().ok(),
            state: rec[10].to_string(),
        });
    }
    Ok(rows)
}

/// What a recording shows around a fault.
#[derive(Debug)]
struct Outcome {
    peak_n: f64,
    largest_step_n: f64,
    /// In the first stall (a command reaching 60 ms of age), the age of the command at the
    /// first tick that rendered zero, ms: the time from the last pose answered to zero force.
    time_to_zero_ms: Option<f64>,
    /// Largest force after the fault's first stale tick, N.
    after_n: f64,
    /// The longest gap between two ticks, ms (a stopped bridge).
    longest_gap_ms: f64,
}

/// Checks the guard's promises on every tick and measures the fault.
fn analyse(rows: &[Row]) -> Result<Outcome> {
    ensure!(rows.len() > 500, "only {} ticks recorded", rows.len());
    let mut o = Outcome {
        peak_n: 0.0,
        largest_step_n: 0.0,
        time_to_zero_ms: None,
        after_n: 0.0,
        longest_gap_ms: 0.0,
    };
    let mut stale_at: Option<usize> = None;
    // The current stale episode (ages above 10 ms): the age at its first zero tick.
    let mut episode_zero: Option<Option<u64>> = None;
    for (i, r) in rows.iter().enumerate() {
        match (r.age_us, &mut episode_zero) {
            (Some(a), _) if a <= 10_000 => episode_zero = None,
            (Some(a), None) => episode_zero = Some((r.f_n == 0.0).then_some(a)),
            (Some(a), Some(z)) => {
                if z.is_none() && r.f_n == 0.0 {
                    *z = Some(a);
                }
            }
            (None, _) => {}
        }
        if o.time_to_zero_ms.is_none()
            && r.age_us.is_some_and(|a| a >= 60_000)
            && let Some(Some(z)) = episode_zero
        {
            o.time_to_zero_ms = Some(z as f64 * 1e-3);
        }
        o.peak_n = o.peak_n.max(r.f_n);
        ensure!(r.f_n <= MAX_FORCE_N + 1e-9, "force above the limit: {r:?}");
        if let Some(a) = r.age_us
            && a >= 60_000
        {
            ensure!(
                r.f_n == 0.0,
                "a command 60 ms old or older still renders: {r:?}"
            );
        }
        if r.state == "disabled" || r.state == "ready-to-rearm" {
            ensure!(r.f_n == 0.0, "force while disabled: {r:?}");
        }
        if i > 0 {
            let p = &rows[i - 1];
            o.largest_step_n = o.largest_step_n.max((r.f_n - p.f_n).abs());
            o.longest_gap_ms = o.longest_gap_ms.max((r.t_s - p.t_s) * 1e3);
            // The magnitude step bounds the vector step from below; the vector step is what
            // the slew limit bounds, and forces here stay along one axis.
            ensure!(
                (r.f_n - p.f_n).abs() <= SLEW_STEP_N + 1e-9,
                "step above the slew limit: {p:?} -> {r:?}"
            );
            let stale = r.age_us.is_some_and(|a| a > 10_000) || r.state == "disabled";
            if stale_at.is_none() && stale && p.f_n > 0.0 {
                stale_at = Some(i);
            }
        }
    }
    if let Some(i) = stale_at {
        o.after_n = rows[i..].iter().map(|r| r.f_n).fold(0.0, f64::max);
    }
    Ok(o)
}

struct Run {
    csv: PathBuf,
    summary: serde_json::Value,
    status: std::process::ExitStatus,
    stderr: String,
}

/// Starts the bridge pressing session `id` at `url` with `hold_s` of hold, calls `fault` with
/// the bridge's pid once it is in contact, and collects the result.
async fn press_with_fault<F, Fut>(
    url: &str,
    id: &str,
    dir: &Path,
    hold_s: f64,
    extra: &[&str],
    fault: F,
) -> Result<Run>
where
    F: FnOnce(u32) -> Fut,
    Fut: std::future::Future<Output = Result<()>>,
{
    let csv = dir.join("bridge.csv");
    let (csv_arg, hold) = (csv.display().to_string(), hold_s.to_string());
    let mut args = vec![
        "--server",
        url,
        "--session",
        id,
        "--driver",
        "sim",
        "--script",
        "press",
        "--hold-s",
        &hold,
        "--rearm",
        "auto",
        "--record",
        &csv_arg,
        "--json",
    ];
    args.extend_from_slice(extra);
    let bridge = spawn_bin(BRIDGE, &args)?;
    let pid = bridge.child.id().context("bridge pid")?;
    // The press reaches firm contact about 1 s after the start (0.3 s settle, 2.3 mm at
    // 10 mm/s to the surface, then deeper); the hold starts at 0.9 s.
    tokio::time::sleep(Duration::from_millis(1_300)).await;
    fault(pid).await?;
    let out = finish(bridge, Duration::from_secs(60)).await?;
    let summary = out.json().unwrap_or(serde_json::Value::Null);
    Ok(Run {
        csv,
        summary,
        status: out.status,
        stderr: out.stderr,
    })
}

fn report(case: &str, run: &Run, o: &Outcome) {
    let s = &run.summary;
    eprintln!(
        "FAULT {case}: peak {:.4} N, largest step {:.5} N, time to zero {}, longest tick gap {:.1} ms, \
         force after {:.4} N; disabled {}, re-armed {}, reconnects {}, daemon restarts {}, stale/unknown dropped {}/{}",
        o.peak_n,
        o.largest_step_n,
        o.time_to_zero_ms
            .map_or_else(|| "-".to_owned(), |t| format!("{t:.1} ms")),
        o.longest_gap_ms,
        o.after_n,
        s["latches"],
        s["rearms"],
        s["reconnects"],
        s["server_restarts"],
        s["stale_forces"],
        s["unmatched_forces"],
    );
}

async fn sigstop_daemon(ms: u64, hold_s: f64, case: &str) -> Result<(Outcome, Run)> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let id = start_session(&daemon.url(), "lv").await?;
    let dir = unique_temp_dir("haptic-fault")?;
    let child = daemon.child.as_ref().context("daemon")?;
    let run = press_with_fault(&daemon.url(), &id, &dir, hold_s, &[], |_| async {
        signal(child, libc::SIGSTOP);
        tokio::time::sleep(Duration::from_millis(ms)).await;
        signal(child, libc::SIGCONT);
        Ok(())
    })
    .await?;
    ensure!(run.status.success(), "bridge failed: {}", run.stderr);
    let o = analyse(&read_rows(&run.csv)?)?;
    report(case, &run, &o);
    let _ = std::fs::remove_dir_all(&dir);
    Ok((o, run))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigstop_the_daemon_for_50_ms() -> Result<()> {
    let (o, run) = sigstop_daemon(50, 2.0, "SIGSTOP hapticd 50 ms").await?;
    ensure!(o.peak_n > 0.03, "no press force: {o:?}");
    // Whether the ramp reached zero depends on how long the stop really lasted on this
    // machine; a stop this short must not disable the forces unless it stretched past 100 ms.
    let _ = run;
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigstop_the_daemon_for_500_ms() -> Result<()> {
    let (o, run) = sigstop_daemon(500, 2.5, "SIGSTOP hapticd 500 ms").await?;
    ensure!(
        run.summary["latches"].as_u64() >= Some(1),
        "{}",
        run.summary
    );
    ensure!(run.summary["rearms"].as_u64() >= Some(1), "{}", run.summary);
    ensure!(o.time_to_zero_ms.is_some_and(|t| t <= 70.0), "{o:?}");
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigstop_the_daemon_for_5_s() -> Result<()> {
    let (o, run) = sigstop_daemon(5_000, 7.0, "SIGSTOP hapticd 5 s").await?;
    ensure!(
        run.summary["latches"].as_u64() >= Some(1),
        "{}",
        run.summary
    );
    ensure!(run.summary["rearms"].as_u64() >= Some(1), "{}", run.summary);
    ensure!(o.time_to_zero_ms.is_some_and(|t| t <= 70.0), "{o:?}");
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigstop_the_bridge_for_200_ms() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let id = start_session(&daemon.url(), "lv").await?;
    let dir = unique_temp_dir("haptic-fault")?;
    let run = press_with_fault(&daemon.url(), &id, &dir, 2.5, &[], |pid| async move {
        let pid = libc::pid_t::try_from(pid)?;
        // SAFETY: plain FFI; the pid is our child, alive until `finish` reaps it.
        unsafe { libc::kill(pid, libc::SIGSTOP) };
        tokio::time::sleep(Duration::from_millis(200)).await;
        // SAFETY: as above.
        unsafe { libc::kill(pid, libc::SIGCONT) };
        Ok(())
    })
    .await?;
    ensure!(run.status.success(), "bridge failed: {}", run.stderr);
    let rows = read_rows(&run.csv)?;
    let o = analyse(&rows)?;
    report("SIGSTOP haptic-bridge 200 ms", &run, &o);
    // The first tick after the gap finds a command 200 ms old: zero, then disabled until
    // re-armed (never the old force, never a step).
    let gap = rows
        .windows(2)
        .position(|w| w[1].t_s - w[0].t_s > 0.1)
        .context("no 100+ ms gap in the ticks")?;
    let resumed = &rows[gap + 1];
    ensure!(
        resumed.f_n == 0.0,
        "force right after the stop: {resumed:?}"
    );
    ensure!(
        run.summary["latches"].as_u64() >= Some(1),
        "{}",
        run.summary
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_the_daemon_and_restart_it_with_its_sessions() -> Result<()> {
    let _serial = serial().await;
    let state = unique_temp_dir("haptic-state")?;
    let state_arg = state.display().to_string();
    let mut daemon = Daemon::spawn(&["--state-dir", &state_arg])?;
    let url = daemon.url();
    let port = daemon.addr.to_string();
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-fault")?;
    let mut child = daemon.child.take().context("daemon")?;
    let holder = std::sync::Mutex::new(None);
    let run = press_with_fault(&url, &id, &dir, 4.0, &[], |_| async {
        signal(&child, libc::SIGKILL);
        let _ = child.wait();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let d = Daemon::spawn(&["--listen", &port, "--state-dir", &state_arg])?;
        *holder.lock().unwrap() = Some(d);
        Ok(())
    })
    .await?;
    ensure!(run.status.success(), "bridge failed: {}", run.stderr);
    let o = analyse(&read_rows(&run.csv)?)?;
    report("kill -9 hapticd, restart", &run, &o);
    let s = &run.summary;
    ensure!(s["server_restarts"].as_u64() == Some(1), "{s}");
    ensure!(s["streams_opened"].as_u64() >= Some(2), "{s}");
    ensure!(s["rearms"].as_u64() >= Some(1), "{s}");
    ensure!(
        run.stderr.contains("restarted") && run.stderr.contains("restored"),
        "{}",
        run.stderr
    );
    ensure!(o.time_to_zero_ms.is_some_and(|t| t <= 70.0), "{o:?}");
    drop(holder);
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&state);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_daemon_restarted_without_the_session_ends_the_bridge_clearly() -> Result<()> {
    let _serial = serial().await;
    let mut daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let port = daemon.addr.to_string();
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-fault")?;
    let mut child = daemon.child.take().context("daemon")?;
    let holder = std::sync::Mutex::new(None);
    let run = press_with_fault(&url, &id, &dir, 20.0, &[], |_| async {
        signal(&child, libc::SIGKILL);
        let _ = child.wait();
        let d = Daemon::spawn(&["--listen", &port])?;
        *holder.lock().unwrap() = Some(d);
        Ok(())
    })
    .await?;
    ensure!(
        run.status.code() == Some(3),
        "exit {:?}: {}",
        run.status,
        run.stderr
    );
    ensure!(
        run.stderr.contains("no longer has session") && run.stderr.contains("--state-dir"),
        "{}",
        run.stderr
    );
    drop(holder);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

async fn injected(case: &str, extra: &[&str]) -> Result<(Outcome, Run)> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let id = start_session(&daemon.url(), "lv").await?;
    let dir = unique_temp_dir("haptic-fault")?;
    let run = press_with_fault(&daemon.url(), &id, &dir, 1.0, extra, |_| async { Ok(()) }).await?;
    ensure!(run.status.success(), "bridge failed: {}", run.stderr);
    let o = analyse(&read_rows(&run.csv)?)?;
    report(case, &run, &o);
    let _ = std::fs::remove_dir_all(&dir);
    Ok((o, run))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drop_10_percent_of_the_messages() -> Result<()> {
    let (o, run) = injected("drop 10 %", &["--fault-drop", "0.1"]).await?;
    ensure!(
        run.summary["injected_drops"].as_u64() > Some(50),
        "{}",
        run.summary
    );
    ensure!(o.peak_n > 0.03, "{o:?}");
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delay_commands_by_5_20_and_50_ms_and_by_a_random_5_to_50_ms() -> Result<()> {
    // Fixed delays: the watchdog scales the force by its age (1, 0.8, 0.2).
    for ms in ["5", "20", "50"] {
        let (o, run) = injected(&format!("delay {ms} ms"), &["--fault-delay-ms", ms]).await?;
        ensure!(
            run.summary["forces_received"].as_u64() > Some(500),
            "{}",
            run.summary
        );
        if ms == "5" {
            ensure!(o.peak_n > 0.0, "{o:?}");
        }
    }
    // A random 5-50 ms per command, delivered in order (as TCP would): a late command holds
    // back the ones behind it, so ages reach 100 ms and the guard may disable and re-arm.
    let (_, run) = injected("delay 5-50 ms, in order", &["--fault-delay-ms", "5,50"]).await?;
    ensure!(
        run.summary["forces_received"].as_u64() > Some(500),
        "{}",
        run.summary
    );
    Ok(())
}
