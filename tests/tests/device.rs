//! The device side end to end: the real `haptic-bridge` pressing the left ventricle of a real
//! `hapticd` (force profile from its recording), and the daemon's shutdown path with a device
//! stream attached (zero force last, then a clean exit).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result, ensure};
use haptic_e2e::{
    BRIDGE, Daemon, STEP_TIMEOUT, device_link, run_bin, serial, signal, start_session,
    unique_temp_dir, wait_timeout,
};
use haptics_proto::v1::{DeviceSample, ForceCommand, Vec3};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

/// One row of the bridge's `--record` CSV.
#[derive(Debug, Clone, Copy)]
struct Row {
    t_s: f64,
    x_m: f64,
    f_n: [f64; 3],
    /// The guard passed a fresh command through this tick at full gain (state `fresh`).
    fresh: bool,
    /// The command was fresh (state `fresh`, or `rising`: the gain coming back along its 200 ms
    /// ramp after a stall, so the force is scaled down).
    fresh_command: bool,
}

impl Row {
    fn norm(&self) -> f64 {
        self.f_n.iter().map(|c| c * c).sum::<f64>().sqrt()
    }
}

fn read_recording(path: &std::path::Path) -> Result<Vec<Row>> {
    let mut r = csv::Reader::from_path(path).with_context(|| format!("opening {path:?}"))?;
    let headers = r.headers()?.clone();
    assert_eq!(
        headers.iter().collect::<Vec<_>>(),
        [
            "t_s",
            "x_m",
            "y_m",
            "z_m",
            "fx_n",
            "fy_n",
            "fz_n",
            "in_contact",
            "rtt_us",
            "age_us",
            "state",
            "command_n"
        ]
    );
    let mut rows = Vec::new();
    for rec in r.records() {
        let rec = rec?;
        let num = |i: usize| -> Result<f64> {
            rec[i]
                .parse()
                .with_context(|| format!("column {i} of {rec:?}"))
        };
        rows.push(Row {
            t_s: num(0)?,
            x_m: num(1)?,
            f_n: [num(4)?, num(5)?, num(6)?],
            fresh: &rec[10] == "fresh",
            fresh_command: matches!(&rec[10], "fresh" | "rising"),
        });
    }
    Ok(rows)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probe_press_force_profile() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-e2e-press")?;
    let csv = dir.join("press.csv");
    let csv_arg = csv.display().to_string();
    let out = run_bin(
        BRIDGE,
        &[
            "--server",
            &url,
            "--session",
            &id,
            "--driver",
            "sim",
            "--script",
            "press",
            "--hold-s",
            "0.5",
            "--record",
            &csv_arg,
            "--json",
        ],
        Duration::from_secs(60),
    )
    .await?
    .success()?;
    let summary = out.json()?;
    let peak = summary["peak_force_n"].as_f64().context("peak_force_n")?;
    assert!((0.03..=1.0).contains(&peak), "peak force {peak} N");
    assert!(
        summary["contact_samples"].as_u64().unwrap_or(0) > 0,
        "{summary}"
    );
    assert!(
        summary["forces_received"].as_u64().unwrap_or(0) > 100,
        "{summary}"
    );

    let rows = read_recording(&csv)?;
    ensure!(rows.len() > 100, "only {} rows recorded", rows.len());

    // The passivity controller may dissipate a leftover energy deficit as the probe leaves the
    // surface: a drag against the motion of at most the sim device's 2 N s/m times 10 mm/s.
    let moving_out = |i: usize| i > 0 && rows[i].x_m > rows[i - 1].x_m;
    let drag = |i: usize| {
        let r = &rows[i];
        moving_out(i) && r.f_n[0] < 0.0 && r.norm() <= 0.02 + 1e-9
    };
    // A late command (the watchdog's ramp after a stall of the command stream: `ramp`, not
    // `fresh`) carries the force of a pose some milliseconds earlier, so on the way out it may
    // outlast the contact by the stall; bounded like the drag. (A 20-30 ms stall on a loaded
    // 2-core machine held a 0.3 mN force from the last contact ticks 0.03-0.1 mm past 11.8 mm.)
    let late = |i: usize| {
        let r = &rows[i];
        moving_out(i) && !r.fresh_command && r.norm() <= 0.02 + 1e-9
    };
    // Free space: the probe (radius 2 mm) is clear of the epicardium (9.68 mm from the axis at
    // z = -5 mm) while x > 11.8 mm, so no force there on the way in, and at most that drag (or
    // a late command) on the way out.
    for (i, r) in rows.iter().enumerate().filter(|(_, r)| r.x_m > 0.0118) {
        assert!(
            r.norm() < 1e-9 || drag(i) || late(i),
            "force in free space: {r:?}"
        );
    }

    // The force pushes the probe back out (+x) whenever it is noticeable; on the way out the
    // drag may take up to 0.02 N off it.
    for (i, r) in rows.iter().enumerate().filter(|(_, r)| r.norm() > 0.01) {
        let released = moving_out(i) && r.f_n[0] >= -0.02 - 1e-9;
        assert!(
            r.f_n[0] / r.norm() > 0.9 || released,
            "force not along +x: {r:?}"
        );
    }

    // Pressing phase: until the deepest point is first reached. Binned means of fx over 0.5 mm
    // depth bins grow with depth once in contact (a little ripple allowed).
    let x_min = rows.iter().map(|r| r.x_m).fold(f64::INFINITY, f64::min);
    let end_press = rows
        .iter()
        .position(|r| r.x_m <= x_min + 1e-9)
        .context("deepest row")?;
    let start_x = rows[0].x_m;
    const BIN_M: f64 = 0.0005;
    // Only ticks whose force command is fresh and at full gain show the model's force: on a
    // loaded machine a late command is ramped down by the bridge's watchdog, and after such a
    // stall the gain comes back along a 200 ms ramp (the guard's own tests check both). One
    // 20 ms hiccup thus scales 200 ticks, so only stale commands must stay a minority; the
    // depth bins below use the full-gain ticks.
    let pressing = &rows[..=end_press];
    let stale = pressing.iter().filter(|r| !r.fresh_command).count();
    ensure!(
        stale * 5 < pressing.len(),
        "{stale} of {} pressing ticks had no fresh command",
        pressing.len()
    );
    let mut bins: Vec<(f64, usize)> = Vec::new();
    for r in pressing.iter().filter(|r| r.fresh) {
        let b = ((start_x - r.x_m) / BIN_M).floor().max(0.0) as usize;
        if bins.len() <= b {
            bins.resize(b + 1, (0.0, 0));
        }
        bins[b].0 += r.f_n[0];
        bins[b].1 += 1;
    }
    let means: Vec<f64> = bins
        .iter()
        .map(|(s, n)| if *n > 0 { s / *n as f64 } else { f64::NAN })
        .collect();
    let contact_bin = means
        .iter()
        .position(|m| *m > 1e-3)
        .with_context(|| format!("no contact while pressing; bin means {means:?}"))?;
    let pressed: Vec<f64> = means[contact_bin..]
        .iter()
        .copied()
        .filter(|m| m.is_finite())
        .collect();
    eprintln!("press: peak {peak:.4} N; fx bin means (0.5 mm bins) {means:.4?}");
    ensure!(
        pressed.len() >= 4,
        "too few depth bins in contact: {means:?}"
    );
    for w in pressed.windows(2) {
        assert!(
            w[1] >= w[0] - 0.005,
            "force fell with depth while pressing: bin means {means:?}"
        );
    }
    // Each 0.5 mm bin is a mean over the bin; the last in-contact bin lies about 3 mm past the
    // first contact, where the default `lv` holds about 30-38 mN (its model-level staircase,
    // `scene_table` in docs/accuracy.md). A stall at the onset can leave the shallow bins
    // without a full-gain tick (seen once under load: bins 5-7 empty, the first filled one
    // already at 20 mN), so the deepest bin is checked against the force that depth holds, and
    // the growth from the first filled bin more loosely.
    let (first, last) = (pressed[0], pressed[pressed.len() - 1]);
    assert!(
        last > 0.025 && last > first + 0.01,
        "force hardly grew with depth: bin means {means:?}"
    );

    // Released: the last 0.2 s carry no force.
    let t_end = rows[rows.len() - 1].t_s;
    for r in rows.iter().filter(|r| r.t_s > t_end - 0.2) {
        assert!(r.norm() < 1e-9, "force after release: {r:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

fn norm(v: &Option<Vec3>) -> f64 {
    v.as_ref()
        .map_or(0.0, |v| (v.x * v.x + v.y * v.y + v.z * v.z).sqrt())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_on_sigterm_sends_zero_force_and_exits() -> Result<()> {
    let _serial = serial().await;
    let mut daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;

    // A hand-written device: about 1 kHz of samples moving in along -x from 14 mm to 9.5 mm
    // (4.5 mm of travel, contact after ~2.3 mm), then holding.
    let (tx, rx) = mpsc::channel::<DeviceSample>(64);
    let stop = Arc::new(AtomicBool::new(false));
    let sender_stop = stop.clone();
    let sender_id = id.clone();
    let sender = tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(1));
        let t0 = tokio::time::Instant::now();
        for seq in 1..=60_000u64 {
            tick.tick().await;
            if sender_stop.load(Ordering::Acquire) {
                break;
            }
            let t = t0.elapsed().as_secs_f64();
            let x = 0.014 - (0.01 * t).min(0.0045);
            let s = DeviceSample {
                session_id: sender_id.clone(),
                seq,
                device_time_us: (t * 1e6) as u64,
                position_m: Some(Vec3::new(x, 0.0, -0.005)),
                velocity_m_per_s: Some(Vec3::new(0.0, 0.0, 0.0)),
                capabilities: None,
                tool_id: String::new(),
            };
            if tx.send(s).await.is_err() {
                break;
            }
        }
    });
    let mut forces = device_link(&url)
        .await?
        .connect(ReceiverStream::new(rx))
        .await?
        .into_inner();

    // Wait (bounded) for a firm contact.
    let mut last: Option<ForceCommand>;
    let deadline = tokio::time::Instant::now() + STEP_TIMEOUT;
    loop {
        let f = tokio::time::timeout_at(deadline, forces.message())
            .await
            .context("no contact force within the timeout")??
            .context("force stream ended before contact")?;
        let firm = f.in_contact && norm(&f.force_n) > 0.01;
        last = Some(f);
        if firm {
            break;
        }
    }
    let in_contact = last.clone().context("a force")?;
    assert!(norm(&in_contact.force_n) > 0.01, "{in_contact:?}");

    let mut child = daemon.child.take().context("daemon child")?;
    signal(&child, libc::SIGTERM);

    // The force stream must end, and its last command must be zero force.
    let mut received_after = 0u64;
    let ended = loop {
        match tokio::time::timeout(Duration::from_secs(10), forces.message()).await {
            Err(_) => break false,
            Ok(Ok(Some(f))) => {
                received_after += 1;
                last = Some(f);
            }
            Ok(Ok(None)) | Ok(Err(_)) => break true,
        }
    };
    stop.store(true, Ordering::Release);
    let status = tokio::task::spawn_blocking(move || {
        let s = wait_timeout(&mut child, Duration::from_secs(10));
        if !matches!(s, Ok(Some(_))) {
            let _ = child.kill();
            let _ = child.wait();
        }
        s
    })
    .await??;
    assert!(ended, "the force stream did not end within 10 s of SIGTERM");
    let last = last.context("no force at all")?;
    assert!(
        received_after > 0,
        "no force command after SIGTERM (the zero force was not sent)"
    );
    assert_eq!(
        norm(&last.force_n),
        0.0,
        "the last force command before the stream ended was not zero: {last:?}"
    );
    let status = status.context("hapticd did not exit within 10 s of SIGTERM")?;
    assert!(status.success(), "hapticd exited with {status}");
    let _ = tokio::time::timeout(STEP_TIMEOUT, sender).await;
    Ok(())
}
