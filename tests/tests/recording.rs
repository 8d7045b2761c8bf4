//! Recordings end to end (issue 19): while the real `haptic-bridge` presses the LV and records
//! its side to MCAP, then `hapticctl force` injects two loads, `hapticctl record` records the
//! session's surface frames, the injected loads and statistics;
//! both files decode with their schemas, the bridge's recording replays through
//! `--driver replay` with the same held force, `haptic-viewer --replay` draws pictures from the
//! surface recording, and `hapticctl export-vtu` writes a ParaView series with one file per
//! frame.

use std::time::Duration;

use anyhow::{Context, Result, ensure};
use haptic_cli::recording::{read_topic, topic};
use haptic_e2e::{
    BRIDGE, CTL, Daemon, STEP_TIMEOUT, VIEWER, finish, run_bin, serial, spawn_bin, start_session,
    stop_session, unique_temp_dir,
};
use haptics_proto::v1::{AppliedForce, DeviceSample, ForceCommand, SessionStats, SurfaceFrame};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bridge_and_session_recordings_decode_replay_and_export() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-e2e-recording")?;
    let surface_mcap = dir.join("session.mcap");
    let press_mcap = dir.join("press.mcap");
    let (surface_arg, press_arg) = (
        surface_mcap.display().to_string(),
        press_mcap.display().to_string(),
    );

    let recorder = spawn_bin(
        CTL,
        &[
            "--server",
            &url,
            "record",
            &id,
            "--out",
            &surface_arg,
            "--duration-s",
            "4.5",
        ],
    )?;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let press = run_bin(
        BRIDGE,
        &[
            "--server",
            &url,
            "--session",
            &id,
            "--script",
            "press",
            "--depth-m",
            "0.005",
            "--hold-s",
            "1.0",
            "--record",
            &press_arg,
            "--json",
        ],
        Duration::from_secs(60),
    )
    .await?
    .success()?;
    // Two injected loads on the side away from the probe, the second overlapping the first,
    // after the press: the replay below runs on a session without them, and a load before the
    // press (0.05 N against a 0.03 N probe force) still deformed the ventricle under the probe
    // when it arrived (the held force was 19-26 % above the replay's; without the loads they
    // agree to 0.04 %).
    let loads = [
        ("0,0.00968,-0.005", "0,-0.05,0", "1.0"),
        ("0,-0.00968,-0.008", "0,0.03,0.01", "0.3"),
    ];
    for (point, force, duration) in loads {
        run_bin(
            CTL,
            &[
                "--server",
                &url,
                "force",
                &id,
                "--point",
                point,
                "--force",
                force,
                "--duration-s",
                duration,
            ],
            STEP_TIMEOUT,
        )
        .await?
        .success()?;
    }
    let peak = press.json()?["peak_force_n"]
        .as_f64()
        .context("peak_force_n")?;
    let rec = finish(recorder, Duration::from_secs(60)).await?.success()?;
    ensure!(rec.stdout.contains("surface frames"), "{}", rec.stdout);
    ensure!(rec.stdout.contains("2 injected loads"), "{}", rec.stdout);

    // The session recording: surface frames (keyframe first) that show the dent, statistics.
    let bytes = std::fs::read(&surface_mcap)?;
    let frames = read_topic::<SurfaceFrame>(&bytes, topic::SURFACE)?;
    ensure!(frames.len() > 20, "only {} surface frames", frames.len());
    let first = &frames[0].1;
    ensure!(
        first.keyframe && !first.triangles.is_empty(),
        "first frame is not a keyframe"
    );
    let vertices = first.positions_m.len() / 3;
    ensure!(
        frames
            .iter()
            .all(|(_, f)| f.positions_m.len() == 3 * vertices)
    );
    ensure!(
        frames.windows(2).all(|w| w[1].0 >= w[0].0),
        "log times go back"
    );
    let dent = frames
        .iter()
        .map(|(_, f)| f.max_displacement_m)
        .fold(0.0, f64::max);
    ensure!(dent > 5e-4, "no dent in the recorded frames: {dent} m");
    // Each injected load once on /loads, as sent, in order, and listed by the frames of the
    // simulated time it acted (snapshots every 16 ms: a frame may list it up to then after).
    let applied = read_topic::<AppliedForce>(&bytes, topic::LOADS)?;
    ensure!(
        applied.len() == 2,
        "{} loads recorded: {applied:?}",
        applied.len()
    );
    let v =
        |v: &Option<haptics_proto::v1::Vec3>| v.as_ref().map_or([f64::NAN; 3], |v| [v.x, v.y, v.z]);
    for ((_, a), (i, want)) in applied.iter().zip([
        (1, ([0.0, 0.00968, -0.005], [0.0, -0.05, 0.0], 1.0)),
        (2, ([0.0, -0.00968, -0.008], [0.0, 0.03, 0.01], 0.3)),
    ]) {
        ensure!(
            a.index == i
                && v(&a.point_m) == want.0
                && v(&a.force_n) == want.1
                && a.duration_s == want.2,
            "recorded load {a:?}, sent {want:?}"
        );
        let listing: Vec<f64> = frames
            .iter()
            .filter(|(_, f)| f.applied_forces.iter().any(|b| b.index == a.index))
            .map(|(_, f)| f.sim_time_s)
            .collect();
        ensure!(!listing.is_empty(), "no frame lists load {i}");
        ensure!(
            listing.iter().all(|&t| t >= a.start_sim_time_s - 1e-9
                && t <= a.start_sim_time_s + a.duration_s + 0.02),
            "load {i} from {} s for {} s listed at {listing:?}",
            a.start_sim_time_s,
            a.duration_s
        );
    }
    ensure!(applied[1].1.start_sim_time_s >= applied[0].1.start_sim_time_s);
    let stats = read_topic::<SessionStats>(&bytes, topic::STATS)?;
    ensure!(stats.len() >= 10, "only {} statistics", stats.len());
    ensure!(stats.iter().all(|(_, s)| s.session_id == id));
    ensure!(stats.windows(2).all(|w| w[1].1.steps >= w[0].1.steps));

    // The bridge's recording: one sample and one force per device tick, the press visible.
    let bytes = std::fs::read(&press_mcap)?;
    let samples = read_topic::<DeviceSample>(&bytes, topic::DEVICE_SAMPLE)?;
    let forces = read_topic::<ForceCommand>(&bytes, topic::DEVICE_FORCE)?;
    ensure!(samples.len() > 500 && samples.len() == forces.len());
    let x = |s: &DeviceSample| s.position_m.as_ref().map_or(f64::NAN, |p| p.x);
    let x_min = samples
        .iter()
        .map(|(_, s)| x(s))
        .fold(f64::INFINITY, f64::min);
    ensure!(
        (x_min - 0.009).abs() < 1e-4,
        "deepest x {x_min} m, expected 9 mm"
    );
    let recorded_peak = forces
        .iter()
        .filter_map(|(_, f)| f.force_n.as_ref())
        .map(|f| (f.x * f.x + f.y * f.y + f.z * f.z).sqrt())
        .fold(0.0, f64::max);
    ensure!(
        (recorded_peak - peak).abs() <= 1e-6 + 1e-3 * peak,
        "recorded peak {recorded_peak} N, bridge summary {peak} N"
    );

    // Replayed on a fresh session: the device goes through the recorded trajectory (same
    // deepest point), and the body answers with the same force once the 1 s hold has settled
    // (a servo that fell behind its device under load reaches the same state later).
    // The recorded session is done with (its recording is on disk): stopped, so the replay
    // does not share the machine with its servo.
    stop_session(&url, &id).await?;
    // A replay whose link fell so far behind that the bridge's watchdog latched the device
    // to zero force (seen with three busy loops on this 2-core machine) measured the machine,
    // not the replay: it is run again on a fresh session, at most three times in all.
    let latched = |json: &serde_json::Value| {
        json["latches"].as_u64().unwrap_or(0) + json["watchdog_expired"].as_u64().unwrap_or(0) > 0
    };
    let replay_mcap = dir.join("replay.mcap");
    let replay_arg = replay_mcap.display().to_string();
    let mut attempt = 0;
    let replay = loop {
        attempt += 1;
        let id2 = start_session(&url, "lv").await?;
        let replay = run_bin(
            BRIDGE,
            &[
                "--server",
                &url,
                "--session",
                &id2,
                "--driver",
                "replay",
                "--replay",
                &press_arg,
                "--record",
                &replay_arg,
                "--json",
            ],
            Duration::from_secs(60),
        )
        .await?
        .success()?;
        if !latched(&replay.json()?) || attempt == 3 {
            break replay;
        }
        stop_session(&url, &id2).await?;
        eprintln!(
            "replay {attempt}: the watchdog latched, run again: {}",
            replay.stdout.trim()
        );
    };
    let replay_bytes = std::fs::read(&replay_mcap)?;
    let (recorded_x, recorded_hold) = held_force_n(&bytes)?;
    let (replay_x, replay_hold) = held_force_n(&replay_bytes)?;
    eprintln!("hold force: recorded {recorded_hold:.5} N, replayed {replay_hold:.5} N");
    ensure!(
        (replay_x - recorded_x).abs() < 1e-5,
        "replayed deepest x {replay_x} m against {recorded_x} m"
    );
    ensure!(
        (replay_hold - recorded_hold).abs() < 0.03 * recorded_hold,
        "replayed hold force {replay_hold} N against {recorded_hold} N; press {}; replay {}",
        press.stdout.trim(),
        replay.stdout.trim()
    );

    // The viewer replays the surface recording into pictures.
    let pictures = dir.join("pictures");
    let pictures_arg = pictures.display().to_string();
    run_bin(
        VIEWER,
        &[
            "--replay",
            &surface_arg,
            "--out",
            &pictures_arg,
            "--interval-s",
            "0.5",
            "--quiet",
        ],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;
    let pngs = std::fs::read_dir(&pictures)?
        .filter_map(Result::ok)
        .filter(|e| e.file_name().to_string_lossy().starts_with("frame_"))
        .count();
    ensure!(pngs >= 2, "{pngs} pictures from the replay");

    // ParaView series: one .vtu per frame, listed in surface.pvd in time order.
    let vtu = dir.join("vtu");
    let vtu_arg = vtu.display().to_string();
    run_bin(
        CTL,
        &["export-vtu", &surface_arg, "--out", &vtu_arg],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;
    let pvd = std::fs::read_to_string(vtu.join("surface.pvd"))?;
    let listed = pvd.matches("<DataSet ").count();
    ensure!(
        listed == frames.len(),
        "{listed} datasets for {} frames",
        frames.len()
    );
    let first_vtu = std::fs::read_to_string(vtu.join("frame_00000.vtu"))?;
    ensure!(
        first_vtu.contains(&format!(
            "NumberOfPoints=\"{vertices}\" NumberOfCells=\"{}\"",
            first.triangles.len() / 3
        )),
        "frame_00000.vtu header does not match the keyframe"
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// The deepest device x of a bridge recording (m) and the 90th percentile of the force magnitude
/// over the later half (in time) of the samples within 0.1 mm of it (the press's hold), N.
fn held_force_n(bytes: &[u8]) -> Result<(f64, f64)> {
    let samples = read_topic::<DeviceSample>(bytes, topic::DEVICE_SAMPLE)?;
    let forces = read_topic::<ForceCommand>(bytes, topic::DEVICE_FORCE)?;
    ensure!(!samples.is_empty() && samples.len() == forces.len());
    let x = |s: &DeviceSample| s.position_m.as_ref().map_or(f64::NAN, |p| p.x);
    let x_min = samples
        .iter()
        .map(|(_, s)| x(s))
        .fold(f64::INFINITY, f64::min);
    let mut held: Vec<f64> = samples
        .iter()
        .zip(&forces)
        .filter(|((_, s), _)| x(s) < x_min + 1e-4)
        .filter_map(|(_, (_, f))| f.force_n.as_ref())
        .map(|f| (f.x * f.x + f.y * f.y + f.z * f.z).sqrt())
        .collect();
    ensure!(
        held.len() >= 50,
        "only {} samples at the deepest point",
        held.len()
    );
    // The later half of the hold: the body has settled there (on this machine the force is
    // within 0.1 % of its final value after the first tenth of a 1 s hold). The recording holds
    // the force written after the bridge's guard, which only ever scales a command down
    // (watchdog ramp on a late command, clamp, slew, passivity); on a loaded machine most hold
    // samples can be ramped (CI: a 0.2 s hold's median 7 % below the replay's; three busy loops
    // here: the later half's median 10 % below), so the 90th percentile, the commands passed
    // whole, is the body's answer.
    let mut settled = held.split_off(held.len() / 2);
    settled.sort_by(f64::total_cmp);
    Ok((x_min, settled[settled.len() * 9 / 10]))
}
