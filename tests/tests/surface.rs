//! The deformed surface end to end: `SurfaceStream.Watch` while the real bridge presses, while
//! `ApplyForce` loads the epicardium, and the real `haptic-viewer` writing pictures.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context, Result, ensure};
use haptic_e2e::{
    BRIDGE, Daemon, STEP_TIMEOUT, VIEWER, finish, nearest_vertex, run_bin, serial, session_control,
    spawn_bin, start_session, surface_stream, unique_temp_dir, vertex,
};
use haptics_proto::v1::{ApplyForceRequest, SurfaceFrame, Vec3, WatchRequest};

/// Surface point of the left ventricle at z = -5 mm on the +x side (epicardium 9.68 mm from
/// the axis there), under the bridge's default press.
const PRESS_POINT_M: [f64; 3] = [0.00968, 0.0, -0.005];
/// The same height on the +y side, where the ApplyForce test pushes.
const LOAD_POINT_M: [f64; 3] = [0.0, 0.00968, -0.005];

/// `(sim_time_s, position_m)` of one vertex, frame after frame.
type Trace = Arc<Mutex<Vec<(f64, [f64; 3])>>>;

/// The keyframe of a watch stream and what a background task saw of one vertex since.
struct Watched {
    vertex: usize,
    rest_m: [f64; 3],
    frames: Trace,
    task: tokio::task::JoinHandle<Result<()>>,
}

/// Opens a watch stream, checks its keyframe, picks the rest vertex nearest `p` and records
/// `(sim_time_s, position)` of that vertex for every later frame.
async fn watch_vertex(url: &str, session: &str, p: [f64; 3]) -> Result<Watched> {
    let mut stream = surface_stream(url)
        .await?
        .watch(WatchRequest {
            session_id: session.to_string(),
            max_rate_hz: 60.0,
            ..WatchRequest::default()
        })
        .await?
        .into_inner();
    let key: SurfaceFrame = tokio::time::timeout(STEP_TIMEOUT, stream.message())
        .await
        .context("no keyframe")??
        .context("watch stream ended before the keyframe")?;
    assert!(key.keyframe, "first frame is not a keyframe");
    assert!(!key.triangles.is_empty() && key.triangles.chunks_exact(3).remainder().is_empty());
    assert_eq!(key.rest_positions_m.len(), key.positions_m.len());
    let n = key.positions_m.len() / 3;
    assert!(key.triangles.iter().all(|&i| (i as usize) < n));
    let vertex_index = nearest_vertex(&key.rest_positions_m, p);
    let rest_m = vertex(&key.rest_positions_m, vertex_index);
    let d: f64 = (0..3)
        .map(|k| (rest_m[k] - p[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        d < 0.002,
        "no surface vertex near {p:?} (nearest {rest_m:?})"
    );
    let frames = Arc::new(Mutex::new(Vec::new()));
    let sink = frames.clone();
    let task = tokio::spawn(async move {
        while let Some(f) = stream.message().await? {
            ensure!(f.positions_m.len() == 3 * n, "frame size changed");
            let v = vertex(&f.positions_m, vertex_index);
            sink.lock().expect("frames lock").push((f.sim_time_s, v));
        }
        Ok(())
    });
    Ok(Watched {
        vertex: vertex_index,
        rest_m,
        frames,
        task,
    })
}

impl Watched {
    fn len(&self) -> usize {
        self.frames.lock().expect("frames lock").len()
    }

    fn snapshot(&self) -> Vec<(f64, [f64; 3])> {
        self.frames.lock().expect("frames lock").clone()
    }

    /// Waits (bounded) until `more` frames arrived after the current ones; returns the newest.
    async fn fresh(&self, more: usize) -> Result<(f64, [f64; 3])> {
        let want = self.len() + more;
        for _ in 0..600 {
            if self.len() >= want {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        ensure!(self.len() >= want, "the watch stream stalled");
        self.snapshot().last().copied().context("no frame")
    }
}

impl Watched {
    /// Waits (bounded) for the first frame at or after simulated time `t_s`.
    async fn at_sim_time(&self, t_s: f64) -> Result<(f64, [f64; 3])> {
        for _ in 0..600 {
            if let Some(f) = self.snapshot().into_iter().find(|(t, _)| *t >= t_s) {
                return Ok(f);
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        anyhow::bail!("no frame reached simulated time {t_s} s")
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn surface_moves_inward_and_recovers() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let w = watch_vertex(&url, &id, PRESS_POINT_M).await?;

    let bridge = spawn_bin(
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
            "1.0",
            "--json",
        ],
    )?;
    let out = finish(bridge, Duration::from_secs(60)).await?.success()?;
    let peak = out.json()?["peak_force_n"].as_f64().unwrap_or(0.0);
    assert!(peak > 0.03, "the bridge barely touched: {peak} N");

    let during = w.snapshot();
    let (t_min, p_min) = during
        .iter()
        .min_by(|a, b| a.1[0].total_cmp(&b.1[0]))
        .copied()
        .context("no frames while pressing")?;
    let inward = w.rest_m[0] - p_min[0];
    eprintln!(
        "press: vertex {} at {:?} m moved inward {:.3} mm",
        w.vertex,
        w.rest_m,
        inward * 1e3
    );
    assert!(
        inward > 0.001,
        "vertex {} moved inward only {:.3} mm (deepest at sim {t_min:.3} s)",
        w.vertex,
        inward * 1e3
    );

    // Recovery: 1.5 s of simulated time after the bridge ended (the servo may run slower than
    // the wall clock on a loaded machine, so wait on simulated time, bounded in wall time).
    let (t_end, _) = w.fresh(1).await?;
    let (t, p) = w.at_sim_time(t_end + 1.5).await?;
    let back: f64 = (0..3)
        .map(|k| (p[k] - w.rest_m[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    eprintln!("press: {:.4} mm from rest at sim {t:.3} s", back * 1e3);
    assert!(
        back < 0.0002,
        "vertex {} still {:.3} mm from rest at sim {t:.3} s",
        w.vertex,
        back * 1e3
    );
    w.task.abort();
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn apply_force_moves_loaded_region_along_force() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let w = watch_vertex(&url, &id, LOAD_POINT_M).await?;
    let (t0, _) = w.fresh(2).await?;

    session_control(&url)
        .await?
        .apply_force(ApplyForceRequest {
            session_id: id.clone(),
            point_m: Some(Vec3::from(LOAD_POINT_M)),
            force_n: Some(Vec3::new(0.0, -0.05, 0.0)),
            duration_s: 0.5,
        })
        .await?;

    // Watch about 1 s of simulated time after the request (bounded in wall time too).
    for _ in 0..600 {
        if w.snapshot().last().is_some_and(|(t, _)| *t > t0 + 1.0) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let frames = w.snapshot();
    let (t, p) = frames
        .iter()
        .filter(|(t, _)| *t >= t0)
        .min_by(|a, b| a.1[1].total_cmp(&b.1[1]))
        .copied()
        .context("no frames after ApplyForce")?;
    let d = [p[0] - w.rest_m[0], p[1] - w.rest_m[1], p[2] - w.rest_m[2]];
    eprintln!(
        "apply force: vertex {} displaced {:.3?} mm",
        w.vertex,
        d.map(|c| c * 1e3)
    );
    assert!(
        d[1] < -0.0002,
        "vertex {} moved {:.3} mm along y (want < -0.2 mm) at sim {t:.3} s",
        w.vertex,
        d[1] * 1e3
    );
    assert!(
        d[1].abs() > d[0].abs() && d[1].abs() > d[2].abs(),
        "displacement {d:?} m is not mostly along -y"
    );
    w.task.abort();
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewer_gets_keyframe_then_frames() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-e2e-viewer")?;
    let dir_arg = dir.display().to_string();
    let out = run_bin(
        VIEWER,
        &[
            "--server",
            &url,
            "--session",
            &id,
            "--out",
            &dir_arg,
            "--interval-s",
            "0.5",
            "--duration-s",
            "3",
            "--json",
        ],
        Duration::from_secs(60),
    )
    .await?
    .success()?;
    let s = out.json()?;
    assert_eq!(s["session_id"], id.as_str());
    assert!(s["keyframes"].as_u64().unwrap_or(0) >= 1, "{s}");
    assert!(s["frames"].as_u64().unwrap_or(0) > 5, "{s}");
    assert_eq!(s["bad_frames"].as_u64(), Some(0), "{s}");
    let pngs: Vec<_> = std::fs::read_dir(&dir)?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "png"))
        .collect();
    assert!(!pngs.is_empty(), "no PNG in {dir:?}");
    let written = s["pictures_written"].as_u64().unwrap_or(0);
    assert!(written >= 1, "{s}");
    for p in &pngs {
        let bytes = std::fs::read(p)?;
        assert!(
            bytes.starts_with(b"\x89PNG\r\n\x1a\n"),
            "{p:?} is not a PNG"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
