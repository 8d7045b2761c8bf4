//! Issue 15: `haptic-bridge` stops cleanly on SIGTERM (`kill`, `systemctl stop`), SIGINT
//! (Ctrl-C) and SIGHUP (the terminal closed). A HapticMaster keeps its last bias force when the
//! host just dies (no host watchdog in its public protocol), so each signal must end in the
//! driver's safe stop: force zero, effect disabled, effects removed, `set state stop`, then the
//! connection closed, and the bridge's summary with exit code 0.
//!
//! The real `hapticd` and `haptic-bridge --driver hapticmaster` run against the HapticMaster
//! TCP emulator of the `haptic-bridge` library (in this test process, on 127.0.0.1:0), whose
//! hand presses the built-in LV as the `emulator` example's does.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, ensure};
use haptic_bridge::hapticmaster::{Emulator, EmulatorLog};
use haptic_bridge::sim::Script;
use haptic_e2e::{BRIDGE, Daemon, STEP_TIMEOUT, finish, serial, session_control, spawn_bin};
use haptics_proto::v1::{StartSessionRequest, StopSessionRequest};

/// Force the emulator must render before the signal, N: the press is on (the LV press peaks
/// at 0.05-0.07 N).
const PRESSING_N: f64 = 0.01;

fn norm(f: [f64; 3]) -> f64 {
    (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt()
}

/// Polls the emulator's log until `done` holds (or `STEP_TIMEOUT`).
async fn wait_log(emu: &Emulator, what: &str, done: impl Fn(&EmulatorLog) -> bool) -> Result<()> {
    let deadline = Instant::now() + STEP_TIMEOUT;
    loop {
        let log = emu.log();
        if done(&log) {
            return Ok(());
        }
        ensure!(
            Instant::now() < deadline,
            "{what}: not within {STEP_TIMEOUT:?}; emulator log tail {:?}, rendered tail {:?}",
            log.recent_commands,
            log.rendered.iter().rev().take(5).collect::<Vec<_>>()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A zero bias force command of the driver's effect (`set bridgeForce force [0,0,0]` in any
/// number format).
fn is_zero_force(cmd: &str) -> bool {
    cmd.strip_prefix("set bridgeForce force ")
        .and_then(|v| haptic_bridge::hapticmaster::parse_vector(v).ok())
        .is_some_and(|f| f == [0.0; 3])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_sigint_and_sighup_stop_a_pressing_hapticmaster_bridge_safely() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let mut control = session_control(&url).await?;
    for (sig, name) in [
        (libc::SIGTERM, "SIGTERM"),
        (libc::SIGINT, "SIGINT"),
        (libc::SIGHUP, "SIGHUP"),
    ] {
        let id = control
            .start_session(StartSessionRequest {
                scene: "lv".into(),
                ..Default::default()
            })
            .await?
            .into_inner()
            .session_id;
        // Device (0.45, 0.014, 0) with the default axes y,z,x and offset (0, 0, -0.455) is the
        // scene's LV press start (0.014, 0, -0.005); device -y is scene -x. A long hold: the
        // signal comes while the hand presses.
        let emu = Emulator::spawn(
            Script::Press {
                start_m: [0.45, 0.014, 0.0],
                direction: [0.0, -1.0, 0.0],
                depth_m: 0.006,
                speed_m_per_s: 0.01,
                hold_s: 30.0,
            },
            Duration::from_millis(50),
        )?;
        let hm_addr = emu.addr().to_string();
        let bridge = spawn_bin(
            BRIDGE,
            &[
                "--server",
                &url,
                "--session",
                &id,
                "--driver",
                "hapticmaster",
                "--hm-addr",
                &hm_addr,
                "--offset-m",
                "0,0,-0.455",
                "--json",
            ],
        )?;
        let pid = libc::pid_t::try_from(bridge.child.id().context("bridge pid")?)?;
        wait_log(&emu, &format!("{name}: a press force"), |l| {
            l.rendered
                .last()
                .is_some_and(|(_, f)| norm(*f) > PRESSING_N)
        })
        .await?;
        // SAFETY: plain FFI; the pid is our child, alive until `finish` reaps it.
        unsafe { libc::kill(pid, sig) };
        let out = finish(bridge, STEP_TIMEOUT).await?;
        ensure!(
            out.status.code() == Some(0),
            "{name}: the bridge exited with {} (killed by the signal?); stderr:\n{}",
            out.status,
            out.stderr
        );
        ensure!(
            out.stderr.contains(&format!("{name}: zero force")),
            "{name}: not logged as the reason to stop:\n{}",
            out.stderr
        );
        let s = out
            .json()
            .with_context(|| format!("{name}: no JSON summary"))?;
        ensure!(s["streams_opened"].as_u64() >= Some(1), "{name}: {s}");
        ensure!(s["peak_force_n"].as_f64() > Some(PRESSING_N), "{name}: {s}");
        ensure!(
            s["final_force_n"] == serde_json::json!([0.0, 0.0, 0.0]),
            "{name}: {s}"
        );
        ensure!(s["device_fault"].is_null(), "{name}: {s}");
        // The device side: the exit sequence came last, and then the connection closed.
        wait_log(&emu, &format!("{name}: the connection closed"), |l| {
            l.closed_after_commands.last() == Some(&emu.commands())
        })
        .await?;
        let log = emu.log();
        let tail: Vec<&str> = log.recent_commands.iter().map(String::as_str).collect();
        let n = tail.len();
        ensure!(n >= 5, "{name}: {tail:?}");
        ensure!(
            is_zero_force(tail[n - 5])
                && is_zero_force(tail[n - 4])
                && tail[n - 3..] == ["set bridgeForce disable", "remove all", "set state stop"],
            "{name}: the last commands are not zero force (the loop's last write, then the \
             safe stop's), disable, remove all, stop: {tail:?}"
        );
        ensure!(
            log.states.last().map(String::as_str) == Some("stop"),
            "{name}: {log:?}"
        );
        ensure!(
            log.effects.is_empty(),
            "{name}: effects left: {:?}",
            log.effects
        );
        ensure!(
            log.rendered.last().is_some_and(|(_, f)| *f == [0.0; 3]),
            "{name}: the device still renders {:?}",
            log.rendered.last()
        );
        // One servo per session at a time on the 2-core machine.
        control
            .stop_session(StopSessionRequest { session_id: id })
            .await?;
    }
    Ok(())
}
