//! Several tools on one organ end to end (issue 50, section 1): two real `haptic-bridge`
//! processes (`--tool left`, `--tool right`, the sim arm's press script each) press opposite
//! sides of the built-in LV at once. Each holds steady (within the 7 % JND over its hold), the
//! net reaction balances at the clamp (the two forces on the devices cancel along x within 7 %
//! of either: the LV is symmetric under a half turn about its axis; one tool alone 5 mm in at
//! +x / -x holds +0.0288 / -0.0295 N in the model, 2.1 % apart), `GetStats` shows both tools in
//! contact, and the right tool's force stays continuous (7 % per fresh tick) while the left one
//! releases and disconnects.
//!
//! The simulated arm also runs both tools from one process (`haptic-bridge --tool left --tool
//! right`: the second plays the script turned half a turn about the LV's axis): the same
//! holds and balance.

use std::time::Duration;

use anyhow::{Context, Result, ensure};
use haptic_e2e::{
    BRIDGE, Daemon, run_bin, serial, session_control, start_session, unique_temp_dir,
};
use haptics_proto::v1::GetStatsRequest;

/// One row of a bridge's `--record` CSV: time s, x m, force N (x), fresh command at full gain.
#[derive(Debug, Clone, Copy)]
struct Row {
    t_s: f64,
    fx_n: f64,
    fresh: bool,
}

fn read_recording(path: &std::path::Path) -> Result<Vec<Row>> {
    let mut r = csv::Reader::from_path(path).with_context(|| format!("opening {path:?}"))?;
    let headers = r.headers()?.clone();
    let col = |name: &str| {
        headers
            .iter()
            .position(|h| h == name)
            .with_context(|| format!("column {name}"))
    };
    let (t, fx, state) = (col("t_s")?, col("fx_n")?, col("state")?);
    let mut rows = Vec::new();
    for rec in r.records() {
        let rec = rec?;
        rows.push(Row {
            t_s: rec[t].parse()?,
            fx_n: rec[fx].parse()?,
            fresh: &rec[state] == "fresh",
        });
    }
    Ok(rows)
}

/// A bridge pressing `depth` from `start` along `direction` as tool `tool`, holding `hold_s`,
/// recording to `csv`.
async fn bridge(
    url: &str,
    id: &str,
    tool: &str,
    start: &str,
    direction: &str,
    hold_s: &str,
    csv: &std::path::Path,
) -> Result<haptic_e2e::CmdOutput> {
    let csv = csv.display().to_string();
    run_bin(
        BRIDGE,
        &[
            "--server",
            url,
            "--session",
            id,
            "--tool",
            tool,
            "--driver",
            "sim",
            "--script",
            "press",
            "--start-m",
            start,
            "--direction",
            direction,
            "--depth-m",
            "0.005",
            "--hold-s",
            hold_s,
            "--record",
            &csv,
            "--json",
        ],
        Duration::from_secs(90),
    )
    .await?
    .success()
}

/// Mean fx of the fresh rows with `t_s` in `window`, and their largest relative spread.
fn hold(rows: &[Row], window: (f64, f64)) -> Result<(f64, f64)> {
    let held: Vec<f64> = rows
        .iter()
        .filter(|r| r.fresh && (window.0..window.1).contains(&r.t_s))
        .map(|r| r.fx_n)
        .collect();
    ensure!(
        held.len() > 100,
        "only {} fresh rows in the hold",
        held.len()
    );
    let mean = held.iter().sum::<f64>() / held.len() as f64;
    let spread = held
        .iter()
        .map(|f| (f - mean).abs() / mean.abs())
        .fold(0.0, f64::max);
    Ok((mean, spread))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_bridges_press_opposite_sides_of_the_lv_and_balance_at_the_clamp() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let mut control = session_control(&url).await?;
    let stats = |id: &str| GetStatsRequest {
        session_id: id.to_owned(),
    };
    let before = control.get_stats(stats(&id)).await?.into_inner();
    ensure!(
        before.max_tools >= 2,
        "the LV session takes {} tool(s): this test needs the model's several-tools support \
         (probe.max_tools, branch tools-model)",
        before.max_tools
    );
    let dir = unique_temp_dir("haptic-e2e-tools")?;
    let (left_csv, right_csv) = (dir.join("left.csv"), dir.join("right.csv"));
    // 14 mm off the axis on either side, 5 mm in at 10 mm/s (0.5 s), then hold: left 1.5 s,
    // right 2.5 s (it is still holding when the left tool leaves).
    let (left, right) = tokio::join!(
        bridge(
            &url,
            &id,
            "left",
            "0.014,0,-0.005",
            "-1,0,0",
            "1.5",
            &left_csv
        ),
        bridge(
            &url,
            &id,
            "right",
            "-0.014,0,-0.005",
            "1,0,0",
            "2.5",
            &right_csv
        ),
    );
    let (left, right) = (left?, right?);
    for (name, out) in [("left", &left), ("right", &right)] {
        let s = out.json()?;
        let peak = s["peak_force_n"].as_f64().context("peak_force_n")?;
        ensure!((0.01..=1.0).contains(&peak), "{name}: peak force {peak} N");
    }
    let (l, r) = (read_recording(&left_csv)?, read_recording(&right_csv)?);
    // The holds, in each bridge's own time (they start within a few hundred ms of each other).
    let (fl, spread_l) = hold(&l, (0.9, 1.8))?;
    let (fr, spread_r) = hold(&r, (0.9, 1.8))?;
    eprintln!(
        "hold: left {fl:.4} N (spread {spread_l:.3}), right {fr:.4} N (spread {spread_r:.3})"
    );
    ensure!(
        fl > 0.01 && fr < -0.01,
        "each pushed back out: left {fl}, right {fr}"
    );
    ensure!(spread_l <= 0.07 && spread_r <= 0.07, "holds not steady");
    ensure!(
        (fl + fr).abs() <= 0.07 * fl.abs().min(fr.abs()),
        "net reaction at the clamp {:.4} N of forces {fl:.4} / {fr:.4} N",
        fl + fr
    );
    // While the left tool releases and leaves, the right one's force stays continuous: no
    // change between commands above 7 % of its hold force (the JND, as issue 46 measures
    // steadiness), up to the end of the right tool's own hold (2.9 s of its 0.5 s press and
    // 2.5 s hold: after it the right tool retracts itself). Only successive fresh commands
    // are compared: across a dropout (commands late on a loaded machine: the bridge ramps
    // the force down and back up) the force may have moved on.
    let left_end = l.last().context("left rows")?.t_s;
    let window = 1.8..(left_end + 0.5).min(2.9);
    let mut previous: Option<f64> = None;
    let mut compared = 0;
    for row in r.iter().filter(|row| window.contains(&row.t_s)) {
        if !row.fresh {
            previous = None;
            continue;
        }
        compared += 1;
        if let Some(p) = previous {
            ensure!(
                (row.fx_n - p).abs() <= 0.07 * fr.abs(),
                "right jumped {p:.4} -> {:.4} N at {:.3} s",
                row.fx_n,
                row.t_s
            );
        }
        previous = Some(row.fx_n);
    }
    ensure!(
        compared > 50,
        "only {compared} commands while the left tool left"
    );
    let stats = control.get_stats(stats(&id)).await?.into_inner();
    for name in ["left", "right"] {
        let t = stats
            .tools
            .iter()
            .find(|t| t.tool_id == name)
            .with_context(|| format!("tool {name} in {:?}", stats.tools))?;
        ensure!(t.contact_ticks > 500 && t.device_samples > 1000, "{t:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_bridge_process_drives_two_simulated_tools_on_opposite_sides() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-e2e-tools-one")?;
    let record = dir.join("press.csv");
    let record_arg = record.display().to_string();
    // The default press (14 mm off the axis at +x, 6 mm in at 10 mm/s), its mirror at -x.
    let out = run_bin(
        BRIDGE,
        &[
            "--server",
            &url,
            "--session",
            &id,
            "--tool",
            "left",
            "--tool",
            "right",
            "--hold-s",
            "1.0",
            "--record",
            &record_arg,
            "--json",
        ],
        Duration::from_secs(90),
    )
    .await?
    .success()?;
    let lines: Vec<serde_json::Value> = out
        .stdout
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(serde_json::from_str)
        .collect::<Result<_, _>>()?;
    ensure!(lines.len() == 2, "one summary per tool: {}", out.stdout);
    let l = read_recording(&dir.join("press-left.csv"))?;
    let r = read_recording(&dir.join("press-right.csv"))?;
    // The script starts with the stream (about 0.3 s after the recording), presses for 0.6 s
    // and holds 1 s: the hold is about 0.93-1.9 s of each recording.
    let (fl, spread_l) = hold(&l, (1.0, 1.8))?;
    let (fr, spread_r) = hold(&r, (1.0, 1.8))?;
    eprintln!(
        "one process: left {fl:.4} N (spread {spread_l:.3}), right {fr:.4} N (spread {spread_r:.3})"
    );
    ensure!(fl > 0.01 && fr < -0.01, "each pushed back out: {fl} / {fr}");
    ensure!(spread_l <= 0.07 && spread_r <= 0.07, "holds not steady");
    ensure!(
        (fl + fr).abs() <= 0.07 * fl.abs().min(fr.abs()),
        "net reaction at the clamp {:.4} N of forces {fl:.4} / {fr:.4} N",
        fl + fr
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
