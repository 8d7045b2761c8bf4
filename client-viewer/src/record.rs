//! Recordings: `hapticctl record` writes a session's surface frames and statistics to MCAP
//! ([`haptic_cli::recording`], opens in Foxglove), and `hapticctl export-vtu` turns the
//! frames of a recording into a ParaView time series (`surface.pvd` + one `.vtu` per frame).
//!
//! Injected loads (`ApplyForce`, from any client) reach the recording through the frames, which
//! list the loads acting or just ended: each is written once on `/loads`. The daemon does not
//! broadcast device traffic at the device rate, so the bridge records its own side
//! (`haptic-bridge --record FILE.mcap`, topics `/device/sample` and `/device/force`); the two
//! files share the schema set and open side by side in Foxglove. The frames carry the probe
//! position and its force at the frame rate.
//!
//! Neighbours: [`crate::ctl`] dispatches the commands (this module does not import it: `record`
//! takes the channel and makes its own `SessionControl` client); the viewer replays the
//! `/surface` topic (`haptic-viewer --replay`).

use std::future::Future;
use std::io::BufWriter;
use std::path::Path;
use std::time::Duration;

use haptic_cli::credentials::AuthChannel;
use haptic_cli::recording::{Recorder, read_topic, topic};
use haptic_cli::vtu::{self, Cells, DataArray, Grid, Layout, Values, VtuError};
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use haptics_proto::v1::{
    GetStatsRequest, SessionStats, SurfaceEncoding, SurfaceFrame, WatchRequest,
};
use tokio_stream::StreamExt;

use crate::ClientError;

/// What `record` wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RecordSummary {
    /// Surface frames written.
    pub frames: u64,
    /// Of which keyframes.
    pub keyframes: u64,
    /// Statistics messages written.
    pub stats: u64,
    /// Injected loads written on `/loads`.
    pub loads: u64,
    /// Loads the session accepted during the recording that no received frame listed (a frame
    /// dropped by a slow link, or a rate below the servo's snapshots): known from the indices.
    pub loads_missed: u64,
    /// File size, bytes.
    pub bytes: u64,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ClientError + '_ {
    move |source| ClientError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn rec_err(path: &Path, e: haptic_cli::recording::RecordingError) -> ClientError {
    ClientError::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    }
}

fn unix_time_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// How `record` samples a session.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecordParams {
    /// Stop after this long, s (`None`: until the session ends or shutdown).
    pub duration_s: Option<f64>,
    /// Surface frames per second, 0.1..=120.
    pub rate_hz: f64,
    /// Seconds between statistics messages, at least 0.01.
    pub stats_interval_s: f64,
}

impl RecordParams {
    /// Checks the ranges documented on the fields (and a positive duration).
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] naming the value.
    fn validate(&self) -> Result<(), ClientError> {
        if !(self.rate_hz.is_finite() && (0.1..=120.0).contains(&self.rate_hz)) {
            return Err(ClientError::InvalidConfig(format!(
                "rate {} Hz: expected 0.1..=120",
                self.rate_hz
            )));
        }
        if !(self.stats_interval_s.is_finite() && self.stats_interval_s >= 0.01) {
            return Err(ClientError::InvalidConfig(format!(
                "stats interval {} s: expected at least 0.01",
                self.stats_interval_s
            )));
        }
        if let Some(d) = self.duration_s
            && !(d.is_finite() && d > 0.0)
        {
            return Err(ClientError::InvalidConfig(format!(
                "duration {d} s: expected a positive number"
            )));
        }
        Ok(())
    }
}

/// Records `session_id` into `out` (MCAP) over `channel`: every surface frame of a
/// full-encoding `Watch` at up to `params.rate_hz` on `/surface` (log time: the server's send
/// time) and `GetStats` every `params.stats_interval_s` on `/stats` (log time: this machine's
/// clock), until `params.duration_s` passes, the session ends, or `shutdown` resolves. The file is complete (summary and index) on every
/// one of those exits.
///
/// # Errors
/// [`ClientError::InvalidConfig`] for a bad rate or interval, [`ClientError::Rpc`] when the
/// session is unknown at the start, [`ClientError::Io`] when the file cannot be written.
pub async fn record(
    channel: AuthChannel,
    session_id: &str,
    out: &Path,
    params: RecordParams,
    shutdown: impl Future<Output = ()>,
) -> Result<RecordSummary, ClientError> {
    let RecordParams {
        duration_s,
        rate_hz,
        stats_interval_s,
    } = params;
    params.validate()?;
    let mut control = SessionControlClient::new(channel.clone());
    // The first statistics answer also checks that the session exists before a file is made.
    let first_stats = stats(&mut control, session_id).await?;
    let mut frames = SurfaceStreamClient::new(channel)
        .max_decoding_message_size(256 << 20)
        .watch(WatchRequest {
            session_id: session_id.to_string(),
            max_rate_hz: rate_hz,
            encoding: SurfaceEncoding::Full as i32,
            quantum_m: 0.0,
        })
        .await?
        .into_inner();
    let file = std::fs::File::create(out).map_err(io(out))?;
    let mut rec = Recorder::new(BufWriter::new(file)).map_err(|e| rec_err(out, e))?;
    let mut summary = RecordSummary::default();
    rec.write(topic::STATS, unix_time_ns(), &first_stats)
        .map_err(|e| rec_err(out, e))?;
    summary.stats += 1;

    // Index of the last load written; loads accepted before the recording started are not
    // counted as missed.
    let mut last_load: Option<u64> = None;
    let mut stats_tick = tokio::time::interval(Duration::from_secs_f64(stats_interval_s));
    stats_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let deadline =
        tokio::time::sleep(duration_s.map_or(Duration::MAX / 4, Duration::from_secs_f64));
    tokio::pin!(deadline);
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            () = &mut deadline => break,
            () = &mut shutdown => break,
            frame = frames.next() => match frame {
                Some(Ok(f)) => write_frame(&mut rec, out, &f, &mut summary, &mut last_load)?,
                // The session ended (or the stream failed): keep what was recorded.
                Some(Err(_)) | None => break,
            },
            _ = stats_tick.tick() => match stats(&mut control, session_id).await {
                Ok(s) => {
                    summary.stats += 1;
                    rec.write(topic::STATS, unix_time_ns(), &s).map_err(|e| rec_err(out, e))?;
                }
                Err(_) => break,
            },
        }
    }
    rec.finish().map_err(|e| rec_err(out, e))?;
    summary.bytes = std::fs::metadata(out).map_err(io(out))?.len();
    Ok(summary)
}

/// Writes frame `f` on `/surface` and the loads it lists that are newer than `last_load` on
/// `/loads` (log time: the server's send time), counting frames, keyframes, loads, and the loads
/// no received frame listed (known from the indices and `applied_forces_total`).
fn write_frame<W: std::io::Write + std::io::Seek>(
    rec: &mut Recorder<W>,
    out: &Path,
    f: &SurfaceFrame,
    summary: &mut RecordSummary,
    last_load: &mut Option<u64>,
) -> Result<(), ClientError> {
    summary.frames += 1;
    summary.keyframes += u64::from(f.keyframe);
    let t_ns = f.server_time_us.saturating_mul(1000);
    for load in &f.applied_forces {
        if last_load.is_some_and(|last| load.index <= last) {
            continue;
        }
        if let Some(last) = *last_load {
            summary.loads_missed += load.index - last - 1;
        }
        rec.write(topic::LOADS, t_ns, load)
            .map_err(|e| rec_err(out, e))?;
        summary.loads += 1;
        *last_load = Some(load.index);
    }
    match *last_load {
        // Nothing listed yet: the session's loads so far came before us.
        None => *last_load = Some(f.applied_forces_total),
        // Accepted and ended between the frames this watcher received.
        Some(last) if f.applied_forces_total > last => {
            summary.loads_missed += f.applied_forces_total - last;
            *last_load = Some(f.applied_forces_total);
        }
        Some(_) => {}
    }
    rec.write(topic::SURFACE, t_ns, f)
        .map_err(|e| rec_err(out, e))?;
    Ok(())
}

/// `GetStats` of `session_id`.
async fn stats(
    control: &mut SessionControlClient<AuthChannel>,
    session_id: &str,
) -> Result<SessionStats, ClientError> {
    let request = GetStatsRequest {
        session_id: session_id.to_string(),
    };
    Ok(control.get_stats(request).await?.into_inner())
}

/// The `/surface` frames of a recording, in order.
///
/// # Errors
/// [`ClientError::Io`] when the file cannot be read or is not a recording with that topic's
/// type.
pub fn read_surface(path: &Path) -> Result<Vec<(u64, SurfaceFrame)>, ClientError> {
    let bytes = std::fs::read(path).map_err(io(path))?;
    read_topic::<SurfaceFrame>(&bytes, topic::SURFACE).map_err(|e| rec_err(path, e))
}

/// Writes the `/surface` frames of the recording `input` as `dir/frame_NNNNN.vtu` (triangles,
/// positions in m, point data `displacement_m` when rest positions are known) and
/// `dir/surface.pvd` (timestep = simulated time, s). Returns the number of frames written.
///
/// # Errors
/// [`ClientError::Io`] for unreadable input or unwritable output; [`ClientError::BadFrame`]
/// when a frame's positions do not match its keyframe's topology, or no keyframe precedes it.
pub fn export_vtu(input: &Path, dir: &Path) -> Result<usize, ClientError> {
    let frames = read_surface(input)?;
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let mut triangles: Option<Vec<u32>> = None;
    let mut rest: Option<Vec<f32>> = None;
    let mut series: Vec<(f64, String)> = Vec::with_capacity(frames.len());
    for (_, f) in &frames {
        if f.keyframe && !f.triangles.is_empty() {
            triangles = Some(f.triangles.clone());
        }
        if f.keyframe && !f.rest_positions_m.is_empty() {
            rest = Some(f.rest_positions_m.clone());
        }
        let bad = |reason: &str| ClientError::BadFrame {
            frame: f.frame,
            reason: reason.to_string(),
        };
        let tris = triangles
            .as_ref()
            .ok_or_else(|| bad("no keyframe before it"))?;
        let n = f.positions_m.len() / 3;
        if f.positions_m.len() % 3 != 0 || tris.iter().any(|&i| i as usize >= n) {
            return Err(bad("positions do not match the keyframe's triangles"));
        }
        let name = format!("frame_{:05}.vtu", series.len());
        let path = dir.join(&name);
        let rest_here = rest.as_ref().filter(|r| r.len() == f.positions_m.len());
        write_vtu(&path, &f.positions_m, tris, rest_here.map(Vec::as_slice))?;
        series.push((f.sim_time_s, name));
    }
    vtu::write_pvd(&dir.join("surface.pvd"), &series).map_err(vtu_err)?;
    Ok(series.len())
}

/// Writes one recorded surface as a `.vtu` ([`haptic_cli::vtu`]): positions in m (`Float32`),
/// triangles, and point data `displacement_m` (distance from the rest position) when `rest_m`
/// is given.
fn write_vtu(
    path: &Path,
    positions_m: &[f32],
    triangles: &[u32],
    rest_m: Option<&[f32]>,
) -> Result<(), ClientError> {
    let m = triangles.len() / 3;
    let offsets: Vec<u32> = (1..=m).map(|i| 3 * i as u32).collect();
    let types = vec![vtu::VTK_TRIANGLE; m];
    let displacement: Option<Vec<f32>> = rest_m.map(|rest| {
        positions_m
            .chunks_exact(3)
            .zip(rest.chunks_exact(3))
            .map(|(p, r)| {
                ((p[0] - r[0]).powi(2) + (p[1] - r[1]).powi(2) + (p[2] - r[2]).powi(2)).sqrt()
            })
            .collect()
    });
    let grid = Grid {
        version: vtu::Version::V0_1,
        points: DataArray {
            name: None,
            components: 3,
            values: Values::F32(positions_m),
            layout: Layout::Rows,
        },
        cells: Cells {
            connectivity: Values::U32(&triangles[..3 * m]),
            offsets: Values::U32(&offsets),
            types: Values::U8(&types),
            layout: Layout::Line,
        },
        point_data: displacement
            .as_deref()
            .map(|d| DataArray {
                name: Some("displacement_m"),
                components: 1,
                values: Values::F32(d),
                layout: Layout::Line,
            })
            .into_iter()
            .collect(),
        cell_data: Vec::new(),
        data_first: false,
    };
    vtu::write_vtu(path, &grid).map_err(vtu_err)
}

/// A [`VtuError`] as the client's error: the file, or why the grid is malformed.
fn vtu_err(e: VtuError) -> ClientError {
    match e {
        VtuError::Io { path, source } => ClientError::Io { path, source },
        VtuError::Shape(reason) => ClientError::InvalidConfig(reason),
    }
}
