//! `viewer`: watches a session's deformed surface and writes pictures of it.
//!
//! [`run`] connects to the server, calls `SurfaceStream.Watch` and hands the stream to
//! [`run_stream`], which does the work (tests feed it any stream of frames):
//!
//! - a [`SurfaceState`] keeps the latest keyframe's triangles and rest positions (the keyframe's
//!   `rest_positions_m`, or its positions when absent) and applies each position frame,
//!   rejecting frames whose sizes or numbers do not fit (counted, reported, skipped);
//! - pictures are rendered with [`crate::raster`] on a blocking worker thread fed by a one-slot
//!   channel, so a slow render never stalls the stream (a periodic picture is skipped and retried
//!   on the next frame instead); the first state after a keyframe is always written as
//!   `frame_00001.png`, then one picture every `interval_s` of wall time, and a final
//!   `latest.png`;
//! - it measures the received frame rate and the frame age (local wall clock minus
//!   `SurfaceFrame.server_time_us`, both microseconds since the UNIX epoch) and prints a progress
//!   line every second.
//!
//! It stops after `duration_s`, when the server ends the stream (the session was stopped: not an
//! error), when the stream fails after it started (reported in [`ViewerSummary::stop_reason`]),
//! or when the `shutdown` future completes.

use std::fmt;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use glam::DVec3;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use haptics_proto::v1::{SurfaceEncoding, SurfaceFrame, WatchRequest};
use hdrhistogram::Histogram;
use serde::Serialize;
use tokio::sync::mpsc;
use tokio_stream::{Stream, StreamExt};

use crate::ClientError;
use crate::raster::{Camera, ProbeView, RenderParams, SurfaceView, bounding_box, render_surface};

/// What the viewer does, checked by [`ViewerConfig::validate`].
#[derive(Debug, Clone, PartialEq)]
pub struct ViewerConfig {
    /// Server URL, e.g. `http://127.0.0.1:50051`.
    pub server: String,
    /// Token and TLS files for the server.
    pub credentials: haptic_cli::credentials::ClientCredentials,
    /// Session to watch.
    pub session_id: String,
    /// Directory for the pictures (created when missing).
    pub out_dir: PathBuf,
    /// Wall-clock time between numbered pictures, seconds (> 0).
    pub interval_s: f64,
    /// Stop after this much wall-clock time, seconds; `None` runs until the stream ends.
    pub duration_s: Option<f64>,
    /// Frame rate asked of the server, hertz (0 = server default).
    pub max_rate_hz: f64,
    /// Picture size, camera and colours.
    pub render: RenderParams,
    /// Print a progress line to stderr every second.
    pub progress: bool,
    /// Ask for the compact stream (quantized deltas, `SURFACE_ENCODING_DELTA`) instead of full
    /// float positions in every frame.
    pub compact: bool,
}

impl ViewerConfig {
    /// A configuration with the CLI defaults: `./viewer-out`, a picture every 0.5 s, 30 Hz,
    /// 640 x 480, no duration limit, progress lines on.
    pub fn new(server: impl Into<String>, session_id: impl Into<String>) -> Self {
        Self {
            server: server.into(),
            credentials: haptic_cli::credentials::ClientCredentials::default(),
            session_id: session_id.into(),
            out_dir: PathBuf::from("viewer-out"),
            interval_s: 0.5,
            duration_s: None,
            max_rate_hz: 30.0,
            render: RenderParams::default(),
            progress: true,
            compact: true,
        }
    }

    /// Checks every value before anything starts.
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] naming the first bad value.
    pub fn validate(&self) -> Result<(), ClientError> {
        let bad = |m: &str| Err(ClientError::InvalidConfig(m.to_string()));
        if self.session_id.is_empty() {
            return bad("session id must not be empty");
        }
        if !(self.interval_s.is_finite() && self.interval_s > 0.0) {
            return bad("interval must be a positive number of seconds");
        }
        if let Some(d) = self.duration_s
            && !(d.is_finite() && d >= 0.0)
        {
            return bad("duration must be a non-negative number of seconds");
        }
        if !(self.max_rate_hz.is_finite() && self.max_rate_hz >= 0.0) {
            return bad("max rate must be a non-negative number of hertz");
        }
        self.render.validate()
    }
}

/// Command-line arguments of `haptic-viewer`, turned into a [`ViewerConfig`] by
/// [`ViewerArgs::into_config`].
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "haptic-viewer",
    version,
    about = "Watch a haptic session's deformed surface and write PNG pictures of it."
)]
pub struct ViewerArgs {
    /// Server URL.
    #[arg(long, env = "HAPTICD_ADDR", default_value = haptic_cli::connect::DEFAULT_SERVER)]
    pub server: String,
    /// Token and TLS files (a `viewer` token is enough).
    #[command(flatten)]
    pub credentials: haptic_cli::credentials::ClientCredentials,
    /// Session id to watch (PNG mode; the web viewer lets the browser choose).
    #[arg(long, required_unless_present_any = ["web", "replay"])]
    pub session: Option<String>,
    /// Replay the `/surface` frames of a recording (`hapticctl record`, .mcap) instead of
    /// watching a server, paced by their simulated time; pictures as in PNG mode.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["web", "session"])]
    pub replay: Option<PathBuf>,
    /// Serve the browser viewer on this address, HOST:PORT (e.g. `127.0.0.1:8080`,
    /// `localhost:8080`, `[::1]:8080`, `0.0.0.0:8080`; a host name is bound on its first resolved
    /// address that can be bound) instead of writing PNGs: a relay that subscribes once per
    /// session and fans frames out to browsers over WebSocket.
    #[arg(long, value_name = "ADDR")]
    pub web: Option<String>,
    /// With --web: a TOML file of other daemons the session overview page (`/overview`) shows
    /// besides --server (`[[station]]` tables with `url`, optional `name`, `token_file`,
    /// `tls_ca`; docs/tools.md).
    #[arg(long, value_name = "FILE", requires = "web")]
    pub stations: Option<PathBuf>,
    /// Output directory for frame_NNNNN.png and latest.png.
    #[arg(long, default_value = "viewer-out")]
    pub out: PathBuf,
    /// Seconds of wall time between numbered pictures.
    #[arg(long, default_value_t = 0.5)]
    pub interval_s: f64,
    /// Stop after this many seconds (default: until the session ends or Ctrl-C).
    #[arg(long)]
    pub duration_s: Option<f64>,
    /// Frame rate asked of the server, Hz (0 = server default).
    #[arg(long, default_value_t = 30.0)]
    pub max_rate_hz: f64,
    /// Picture width, pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Picture height, pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Camera direction from the model centre, X,Y,Z (default 1,1,0.4: from +x+y, above).
    #[arg(long, allow_hyphen_values = true)]
    pub view_from: Option<String>,
    /// Displacement shown as full red, metres (default: the frame's largest).
    #[arg(long)]
    pub displacement_scale_m: Option<f64>,
    /// Force arrow length per newton, metres (100 mm/N suits soft-tissue forces of about 0.1 N).
    #[arg(long, default_value_t = 0.1)]
    pub force_scale_m_per_n: f64,
    /// Do not draw the colour bar.
    #[arg(long)]
    pub no_legend: bool,
    /// No progress lines on stderr.
    #[arg(long)]
    pub quiet: bool,
    /// Print the summary as one JSON line on stdout.
    #[arg(long)]
    pub json: bool,
    /// Surface encoding asked of the server: `delta` (quantized deltas, 1 um) or `full`.
    #[arg(long, default_value = "delta", value_parser = ["delta", "full"])]
    pub encoding: String,
}

impl ViewerArgs {
    /// The web viewer's configuration when `--web` was given: the address to bind with
    /// [`crate::web::bind`] (`HOST:PORT`, host names resolved there) and a
    /// [`crate::web::WebConfig`] (browsers get `--max-rate-hz` by default, clamped to 60 Hz).
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] for an address that is not `HOST:PORT` (a port from 0 to
    /// 65535), bad rates or a bad `--stations` file.
    pub fn web_config(&self) -> Result<Option<(String, crate::web::WebConfig)>, ClientError> {
        let Some(addr) = &self.web else {
            return Ok(None);
        };
        let port = addr
            .rsplit_once(':')
            .filter(|(host, _)| !host.is_empty())
            .map(|(_, port)| port.parse::<u16>());
        if !matches!(port, Some(Ok(_))) {
            return Err(ClientError::InvalidConfig(format!(
                "--web {addr:?}: expected HOST:PORT (e.g. 127.0.0.1:8080, localhost:8080, \
                 [::1]:8080)"
            )));
        }
        let addr = addr.clone();
        let mut cfg = crate::web::WebConfig::new(self.server.clone());
        cfg.credentials = self.credentials.clone();
        if let Some(path) = &self.stations {
            cfg.stations = crate::web::overview::read_stations(path)?;
        }
        if self.max_rate_hz > 0.0 {
            cfg.default_rate_hz = self.max_rate_hz.min(crate::web::MAX_BROWSER_RATE_HZ);
        }
        cfg.validate()?;
        Ok(Some((addr, cfg)))
    }

    /// Builds and validates the configuration.
    ///
    /// # Errors
    /// [`ClientError::InvalidVector`] for a malformed `--view-from`;
    /// [`ClientError::InvalidConfig`] for out-of-range values.
    pub fn into_config(self) -> Result<ViewerConfig, ClientError> {
        let mut render = RenderParams {
            width: self.width,
            height: self.height,
            force_scale_m_per_n: self.force_scale_m_per_n,
            legend: !self.no_legend,
            ..RenderParams::default()
        };
        if let Some(v) = &self.view_from {
            render.view_from = DVec3::from_array(crate::ctl::parse_vec3(v)?);
        }
        if let Some(m) = self.displacement_scale_m {
            render.displacement_scale = crate::raster::DisplacementScale::FixedM(m);
        }
        let cfg = ViewerConfig {
            server: self.server,
            credentials: self.credentials,
            session_id: match (&self.replay, self.session) {
                (Some(path), _) => format!("replay of {}", path.display()),
                (None, s) => s.unwrap_or_default(),
            },
            out_dir: self.out,
            interval_s: self.interval_s,
            duration_s: self.duration_s,
            max_rate_hz: self.max_rate_hz,
            render,
            progress: !self.quiet,
            compact: self.encoding == "delta",
        };
        cfg.validate()?;
        Ok(cfg)
    }
}

/// Why the viewer stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// `duration_s` elapsed.
    Duration,
    /// The server ended the stream (normally: the session was stopped).
    StreamEnded,
    /// The shutdown future completed (Ctrl-C).
    Shutdown,
    /// The stream failed after it had started; see [`ViewerSummary::last_error`].
    StreamError,
}

/// What a viewer run saw. Serialises to one JSON object.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ViewerSummary {
    /// The watched session.
    pub session_id: String,
    /// Valid frames received, keyframes included.
    pub frames: u64,
    /// Valid keyframes received (the first one, then one per topology change).
    pub keyframes: u64,
    /// Frames rejected because their sizes or numbers did not fit (skipped, not fatal).
    pub bad_frames: u64,
    /// Wall-clock time from the start of the stream to the stop, seconds.
    pub elapsed_s: f64,
    /// Received frame rate `frames / elapsed_s`, hertz.
    pub fps: f64,
    /// Median frame age (local clock minus server send time), milliseconds; `None` without
    /// timestamped frames.
    pub age_p50_ms: Option<f64>,
    /// 99th-percentile frame age, milliseconds.
    pub age_p99_ms: Option<f64>,
    /// PNG files written, `latest.png` included.
    pub pictures_written: u64,
    /// Pictures that could not be written (disk full, permissions).
    pub picture_errors: u64,
    /// Where the pictures are.
    pub out_dir: PathBuf,
    /// Largest `SurfaceFrame.max_displacement_m` seen, metres.
    pub max_displacement_m: f64,
    /// Simulated time of the last valid frame, seconds.
    pub last_sim_time_s: f64,
    /// Why the viewer stopped.
    pub stop_reason: StopReason,
    /// The last bad-frame, picture or stream error message, if any.
    pub last_error: Option<String>,
}

impl fmt::Display for ViewerSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let ms = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
        writeln!(
            f,
            "session {}: {} frames ({} keyframes, {} bad) in {:.1} s = {:.1} fps",
            self.session_id, self.frames, self.keyframes, self.bad_frames, self.elapsed_s, self.fps
        )?;
        writeln!(
            f,
            "frame age p50 {} ms, p99 {} ms; max displacement {:.3} mm",
            ms(self.age_p50_ms),
            ms(self.age_p99_ms),
            self.max_displacement_m * 1e3
        )?;
        write!(
            f,
            "{} pictures written to {} ({} errors); stopped: {:?}",
            self.pictures_written,
            self.out_dir.display(),
            self.picture_errors,
            self.stop_reason
        )?;
        if let Some(e) = &self.last_error {
            write!(f, "; last error: {e}")?;
        }
        Ok(())
    }
}

/// What [`SurfaceState::apply`] accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameKind {
    /// A keyframe: new topology and rest positions.
    Keyframe,
    /// New positions for the current topology.
    Positions,
}

/// The surface as the viewer knows it: the latest keyframe's topology and rest positions, the
/// latest positions, probe and camera.
#[derive(Debug, Clone, Default)]
pub struct SurfaceState {
    rest_m: Arc<Vec<f32>>,
    triangles: Arc<Vec<u32>>,
    positions_m: Vec<f32>,
    probe: Option<ProbeView>,
    camera: Option<Camera>,
}

impl SurfaceState {
    /// An empty state waiting for its first keyframe.
    pub fn new() -> Self {
        Self::default()
    }

    /// True once a keyframe has been accepted.
    pub fn has_keyframe(&self) -> bool {
        self.camera.is_some()
    }

    /// Number of surface vertices of the current keyframe.
    pub fn vertex_count(&self) -> usize {
        self.rest_m.len() / 3
    }

    /// Current positions, metres, xyz interleaved.
    pub fn positions_m(&self) -> &[f32] {
        &self.positions_m
    }

    /// Applies a frame. A keyframe replaces topology, rest positions (its own positions) and the
    /// camera (framed on its bounding box with `params`); another frame replaces the positions.
    /// The probe is taken from every valid frame.
    ///
    /// # Errors
    /// [`ClientError::BadFrame`], leaving the state unchanged, when: no keyframe was seen yet; the
    /// positions are not `3 x` the keyframe vertex count (or, in a keyframe, not a multiple of 3);
    /// the triangle list is not a multiple of 3 or references a missing vertex; a position is NaN
    /// or infinite.
    pub fn apply(
        &mut self,
        f: &SurfaceFrame,
        params: &RenderParams,
    ) -> Result<FrameKind, ClientError> {
        let bad = |reason: String| ClientError::BadFrame {
            frame: f.frame,
            reason,
        };
        let p = &f.positions_m;
        if f.keyframe {
            if !p.len().is_multiple_of(3) {
                return Err(bad(format!(
                    "keyframe has {} position values, not a multiple of 3",
                    p.len()
                )));
            }
            if !f.triangles.len().is_multiple_of(3) {
                return Err(bad(format!(
                    "keyframe has {} triangle indices, not a multiple of 3",
                    f.triangles.len()
                )));
            }
            let n = p.len() / 3;
            if let Some(&i) = f.triangles.iter().find(|&&i| i as usize >= n) {
                return Err(bad(format!(
                    "triangle references vertex {i} but the keyframe has {n} vertices"
                )));
            }
        } else {
            if !self.has_keyframe() {
                return Err(bad("positions before the first keyframe".to_string()));
            }
            if p.len() != self.rest_m.len() {
                return Err(bad(format!(
                    "{} position values, expected 3 x {} vertices = {}",
                    p.len(),
                    self.vertex_count(),
                    self.rest_m.len()
                )));
            }
        }
        if let Some(i) = p.iter().position(|v| !v.is_finite()) {
            return Err(bad(format!("position value {i} is not finite")));
        }
        let kind = if f.keyframe {
            // Rest positions come with the keyframe when the server sends them (field 12);
            // otherwise the keyframe's own positions serve as rest.
            let rest = &f.rest_positions_m;
            let rest_ok = rest.len() == p.len() && rest.iter().all(|v| v.is_finite());
            self.rest_m = Arc::new(if rest_ok { rest.clone() } else { p.clone() });
            self.triangles = Arc::new(f.triangles.clone());
            let (min, max) = bounding_box(p).unwrap_or((DVec3::splat(-0.05), DVec3::splat(0.05)));
            self.camera = Some(Camera::auto_frame(min, max, params));
            FrameKind::Keyframe
        } else {
            FrameKind::Positions
        };
        self.positions_m.clear();
        self.positions_m.extend_from_slice(p);
        self.probe = f.probe_position_m.as_ref().map(|pos| ProbeView {
            position_m: DVec3::from_array(pos.to_array()),
            radius_m: f.probe_radius_m,
            force_n: f
                .contact_force_n
                .as_ref()
                .map_or(DVec3::ZERO, |v| DVec3::from_array(v.to_array())),
            in_contact: f.in_contact,
        });
        Ok(kind)
    }

    /// Renders the current state, `None` before the first keyframe.
    pub fn render(&self, params: &RenderParams) -> Option<crate::raster::Image> {
        self.job(PathBuf::new()).map(|j| j.render(params))
    }

    fn job(&self, path: PathBuf) -> Option<RenderJob> {
        Some(RenderJob {
            path,
            rest_m: self.rest_m.clone(),
            triangles: self.triangles.clone(),
            positions_m: self.positions_m.clone(),
            probe: self.probe,
            camera: self.camera?,
        })
    }
}

/// A self-contained snapshot for the picture worker.
struct RenderJob {
    path: PathBuf,
    rest_m: Arc<Vec<f32>>,
    triangles: Arc<Vec<u32>>,
    positions_m: Vec<f32>,
    probe: Option<ProbeView>,
    camera: Camera,
}

impl RenderJob {
    fn render(&self, params: &RenderParams) -> crate::raster::Image {
        let view = SurfaceView {
            rest_m: &self.rest_m,
            positions_m: &self.positions_m,
            triangles: &self.triangles,
            probe: self.probe,
        };
        render_surface(&view, &self.camera, params)
    }
}

/// Result of the picture worker: files written, failures, last failure message.
#[derive(Default)]
struct WorkerReport {
    written: u64,
    errors: u64,
    last_error: Option<String>,
}

fn spawn_worker(
    params: RenderParams,
) -> (
    mpsc::Sender<RenderJob>,
    tokio::task::JoinHandle<WorkerReport>,
) {
    // One slot: at most one picture waits while another is rendered.
    let (tx, mut rx) = mpsc::channel::<RenderJob>(1);
    let handle = tokio::task::spawn_blocking(move || {
        let mut report = WorkerReport::default();
        while let Some(job) = rx.blocking_recv() {
            match job.render(&params).write_png(&job.path) {
                Ok(()) => report.written += 1,
                Err(e) => {
                    tracing::error!("cannot write picture: {e}");
                    report.errors += 1;
                    report.last_error = Some(e.to_string());
                }
            }
        }
        report
    });
    (tx, handle)
}

/// Frame ages (local wall clock minus server send time) in microseconds, kept in two HDR
/// histograms of 3 significant digits: ages >= 0, and the magnitudes of negative ones (the
/// local clock behind the server's, which the summary must still show as a negative age).
/// Memory is bounded whatever the run's length.
#[derive(Debug, Clone)]
pub struct FrameAges {
    late: Histogram<u64>,
    early: Histogram<u64>,
}

impl Default for FrameAges {
    fn default() -> Self {
        // 3 significant digits is within the crate's 0..=5; auto-resizing covers any age.
        let h = || Histogram::new(3).expect("3 significant digits is valid");
        Self {
            late: h(),
            early: h(),
        }
    }
}

impl FrameAges {
    /// Records one frame age, microseconds (negative when the local clock is behind).
    pub fn record(&mut self, age_us: i64) {
        let h = if age_us >= 0 {
            &mut self.late
        } else {
            &mut self.early
        };
        // The histogram grows to hold any age; clamped only past its largest trackable value.
        let v = age_us.unsigned_abs();
        if h.record(v).is_err() {
            h.saturating_record(v);
        }
    }

    /// Forgets every age recorded.
    pub fn clear(&mut self) {
        self.late.reset();
        self.early.reset();
    }

    /// Nearest-rank quantile `q` in `[0, 1]` of the recorded ages, milliseconds; `None` when
    /// none was recorded. Exact below 2.048 ms; above, the upper end of the sample's histogram
    /// bucket, at most 0.1 % above the sample.
    pub fn quantile_ms(&self, q: f64) -> Option<f64> {
        let (n_early, n) = (self.early.len(), self.early.len() + self.late.len());
        if n == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * n as f64).ceil() as u64).clamp(1, n);
        let us = if rank <= n_early {
            // The rank-th smallest age is the (n_early - rank + 1)-th smallest magnitude.
            let v = value_at_rank(&self.early, n_early - rank + 1);
            -(self.early.lowest_equivalent(v) as f64)
        } else {
            value_at_rank(&self.late, rank - n_early) as f64
        };
        Some(us / 1e3)
    }
}

/// The value of the `rank`-th smallest sample of `h` (1-based; the upper end of its bucket).
fn value_at_rank(h: &Histogram<u64>, rank: u64) -> u64 {
    let mut seen = 0;
    for v in h.iter_recorded() {
        seen += v.count_since_last_iteration();
        if seen >= rank {
            return v.value_iterated_to();
        }
    }
    h.max()
}

/// Microseconds since the UNIX epoch on the local wall clock.
fn now_unix_us() -> i128 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as i128)
}

/// Path of numbered picture `index` (1-based): `<dir>/frame_00001.png`.
pub fn picture_path(dir: &Path, index: u64) -> PathBuf {
    dir.join(format!("frame_{index:05}.png"))
}

/// Connects to `cfg.server`, watches `cfg.session_id` and writes pictures until a stop condition
/// (see the module docs); `shutdown` ends the run early (e.g. Ctrl-C).
///
/// # Errors
/// [`ClientError::InvalidConfig`] for a bad configuration; [`ClientError::Connect`] when the
/// server cannot be reached; [`ClientError::Rpc`] when `Watch` is refused (e.g. `NOT_FOUND` for an
/// unknown session) or the stream fails before its first frame; [`ClientError::Io`] when the
/// output directory cannot be created.
pub async fn run(
    cfg: ViewerConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<ViewerSummary, ClientError> {
    cfg.validate()?;
    let channel = haptic_cli::connect::connect(&cfg.server, &cfg.credentials).await?;
    let mut client = SurfaceStreamClient::new(channel).max_decoding_message_size(256 << 20);
    let stream = client
        .watch(WatchRequest {
            session_id: cfg.session_id.clone(),
            max_rate_hz: cfg.max_rate_hz,
            encoding: if cfg.compact {
                SurfaceEncoding::Delta as i32
            } else {
                SurfaceEncoding::Full as i32
            },
            quantum_m: 0.0,
        })
        .await?
        .into_inner();
    run_stream(stream, &cfg, shutdown).await
}

/// Replays the `/surface` frames of the recording `path` through [`run_stream`], paced by
/// their simulated time (a frame is delivered when as much wall time has passed since the
/// first as simulated time).
///
/// # Errors
/// [`ClientError::Io`] when the recording cannot be read; then as [`run_stream`].
pub async fn replay(
    path: &Path,
    cfg: &ViewerConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<ViewerSummary, ClientError> {
    let frames = crate::record::read_surface(path)?;
    let stream = replay_stream(frames.into_iter().map(|(_, f)| f).collect());
    run_stream(stream, cfg, shutdown).await
}

/// `frames` as a stream paced by their simulated time from now on, each stamped with the time
/// it was due on this replay's clock: its `server_time_us` becomes the replay's start plus its
/// simulated time since the first frame, so the frame age the viewer reports is how late the
/// replay delivered it, not how old the recording is (issue 47: a replay showed 152 s).
pub fn replay_stream(
    frames: Vec<SurfaceFrame>,
) -> std::pin::Pin<Box<dyn Stream<Item = Result<SurfaceFrame, tonic::Status>> + Send>> {
    let t0 = frames.first().map_or(0.0, |f| f.sim_time_s);
    let start = tokio::time::Instant::now();
    let start_unix_us = now_unix_us();
    Box::pin(tokio_stream::StreamExt::then(
        tokio_stream::iter(frames),
        move |mut f| async move {
            let due_s = (f.sim_time_s - t0).max(0.0);
            if due_s.is_finite() {
                let due = Duration::from_secs_f64(due_s.min(1e6));
                tokio::time::sleep_until(start + due).await;
                if f.server_time_us > 0 {
                    f.server_time_us = u64::try_from(start_unix_us + due.as_micros() as i128)
                        .unwrap_or(f.server_time_us);
                }
            }
            Ok::<_, tonic::Status>(f)
        },
    ))
}

/// Running counters of [`run_stream`].
struct Counters {
    frames: u64,
    keyframes: u64,
    bad_frames: u64,
    ages: FrameAges,
    max_displacement_m: f64,
    last_sim_time_s: f64,
    last_error: Option<String>,
}

/// What [`run_stream`] carries from one frame to the next: the surface, the counters, the
/// picture schedule and the progress line's one-second window.
struct Viewing {
    state: SurfaceState,
    compact: crate::compact::CompactState,
    c: Counters,
    /// The picture worker's queue (one slot).
    tx: mpsc::Sender<RenderJob>,
    /// Time between two pictures.
    interval: Duration,
    pictures_queued: u64,
    next_picture: Option<Instant>,
    start: Instant,
    window_frames: u64,
    window_ages: FrameAges,
    window_start: Instant,
}

impl Viewing {
    /// Prints the progress line of the last window to standard error and starts a new window.
    fn progress(&mut self) {
        let c = &self.c;
        let dt = self.window_start.elapsed().as_secs_f64().max(1e-9);
        let ms = |q| {
            self.window_ages
                .quantile_ms(q)
                .map_or("-".into(), |v| format!("{v:.1}"))
        };
        eprintln!(
            "viewer: t={:.0}s frames={} ({:.1} fps) age p50 {} ms p99 {} ms, \
             pictures {}, bad {}, max disp {:.3} mm",
            self.start.elapsed().as_secs_f64(),
            c.frames,
            self.window_frames as f64 / dt,
            ms(0.5),
            ms(0.99),
            self.pictures_queued,
            c.bad_frames,
            c.max_displacement_m * 1e3
        );
        (self.window_frames, self.window_start) = (0, Instant::now());
        self.window_ages.clear();
    }

    /// Counts a frame that could not be used (logged; the run goes on).
    fn bad_frame(&mut self, e: &dyn fmt::Display) {
        tracing::error!("{e}");
        self.c.bad_frames += 1;
        self.c.last_error = Some(e.to_string());
    }

    /// One frame from the stream: expanded (compact frames) and applied to the surface, its
    /// age and displacement counted, and a picture queued when one is due.
    async fn on_frame(&mut self, frame: SurfaceFrame, cfg: &ViewerConfig) {
        let recv_us = now_unix_us();
        // Compact frames become full ones (absolute positions) first.
        let frame = match self.compact.expand(frame) {
            Ok(f) => f,
            Err(e) => return self.bad_frame(&e),
        };
        match self.state.apply(&frame, &cfg.render) {
            Err(e) => return self.bad_frame(&e),
            Ok(kind) => {
                self.c.frames += 1;
                self.window_frames += 1;
                if kind == FrameKind::Keyframe {
                    self.c.keyframes += 1;
                }
            }
        }
        let c = &mut self.c;
        if frame.server_time_us > 0 {
            let age = recv_us - i128::from(frame.server_time_us);
            let age_us = i64::try_from(age).unwrap_or(i64::MAX);
            c.ages.record(age_us);
            self.window_ages.record(age_us);
        }
        if frame.max_displacement_m.is_finite() {
            c.max_displacement_m = c.max_displacement_m.max(frame.max_displacement_m);
        }
        c.last_sim_time_s = frame.sim_time_s;
        self.queue_picture(cfg).await;
    }

    /// Queues a picture of the current surface: always the first one (waiting for the worker),
    /// then one per interval when the worker is free (a busy worker skips to the next frame).
    async fn queue_picture(&mut self, cfg: &ViewerConfig) {
        let now = Instant::now();
        if self.next_picture.is_none() {
            // The first state after the first keyframe is always written.
            let path = picture_path(&cfg.out_dir, self.pictures_queued + 1);
            if let Some(job) = self.state.job(path)
                && self.tx.send(job).await.is_ok()
            {
                self.pictures_queued += 1;
                self.next_picture = Some(now + self.interval);
            }
        } else if self.next_picture.is_some_and(|t| now >= t) {
            let path = picture_path(&cfg.out_dir, self.pictures_queued + 1);
            // Busy worker: skip, try again on the next frame.
            if let Some(job) = self.state.job(path)
                && self.tx.try_send(job).is_ok()
            {
                self.pictures_queued += 1;
                self.next_picture = Some(now + self.interval);
            }
        }
    }

    /// Writes `latest.png`, waits for the worker and sums the run up.
    async fn finish(
        self,
        worker: tokio::task::JoinHandle<WorkerReport>,
        cfg: &ViewerConfig,
        stop_reason: StopReason,
        elapsed_s: f64,
    ) -> Result<ViewerSummary, ClientError> {
        if let Some(job) = self.state.job(cfg.out_dir.join("latest.png")) {
            let _ = self.tx.send(job).await;
        }
        drop(self.tx);
        let report = worker.await.map_err(|e| ClientError::Task(e.to_string()))?;
        let c = self.c;
        Ok(ViewerSummary {
            session_id: cfg.session_id.clone(),
            frames: c.frames,
            keyframes: c.keyframes,
            bad_frames: c.bad_frames,
            elapsed_s,
            fps: c.frames as f64 / elapsed_s.max(1e-9),
            age_p50_ms: c.ages.quantile_ms(0.5),
            age_p99_ms: c.ages.quantile_ms(0.99),
            pictures_written: report.written,
            picture_errors: report.errors,
            out_dir: cfg.out_dir.clone(),
            max_displacement_m: c.max_displacement_m,
            last_sim_time_s: c.last_sim_time_s,
            stop_reason,
            last_error: report.last_error.or(c.last_error),
        })
    }
}

/// Consumes a stream of surface frames as [`run`] does (everything but connecting), so it can be
/// fed by any source. `cfg.server` is not used.
///
/// # Errors
/// [`ClientError::InvalidConfig`], [`ClientError::Io`] (output directory), and
/// [`ClientError::Rpc`] when the stream fails before delivering any frame. A failure after frames
/// arrived ends the run with [`StopReason::StreamError`] instead, so the summary is not lost.
pub async fn run_stream<S>(
    mut stream: S,
    cfg: &ViewerConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<ViewerSummary, ClientError>
where
    S: Stream<Item = Result<SurfaceFrame, tonic::Status>> + Unpin,
{
    cfg.validate()?;
    std::fs::create_dir_all(&cfg.out_dir).map_err(|source| ClientError::Io {
        path: cfg.out_dir.clone(),
        source,
    })?;
    let (tx, worker) = spawn_worker(cfg.render.clone());
    let start = Instant::now();
    let deadline = cfg
        .duration_s
        .map(|d| tokio::time::Instant::from_std(start + Duration::from_secs_f64(d)));
    let sleep = tokio::time::sleep_until(
        deadline.unwrap_or_else(|| tokio::time::Instant::now() + Duration::from_secs(86_400 * 365)),
    );
    tokio::pin!(sleep);
    tokio::pin!(shutdown);
    let mut tick = tokio::time::interval_at(
        tokio::time::Instant::now() + Duration::from_secs(1),
        Duration::from_secs(1),
    );
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut v = Viewing {
        state: SurfaceState::new(),
        compact: crate::compact::CompactState::new(),
        c: Counters {
            frames: 0,
            keyframes: 0,
            bad_frames: 0,
            ages: FrameAges::default(),
            max_displacement_m: 0.0,
            last_sim_time_s: 0.0,
            last_error: None,
        },
        tx,
        interval: Duration::from_secs_f64(cfg.interval_s),
        pictures_queued: 0,
        next_picture: None,
        start,
        window_frames: 0,
        window_ages: FrameAges::default(),
        window_start: Instant::now(),
    };
    let stop_reason = loop {
        tokio::select! {
            biased;
            () = &mut shutdown => break StopReason::Shutdown,
            () = &mut sleep, if deadline.is_some() => break StopReason::Duration,
            _ = tick.tick(), if cfg.progress => v.progress(),
            msg = stream.next() => match msg {
                None => break StopReason::StreamEnded,
                Some(Err(status)) => {
                    if v.c.frames == 0 && v.c.bad_frames == 0 {
                        drop(v);
                        let _ = worker.await;
                        return Err(status.into());
                    }
                    let e = ClientError::from(status);
                    tracing::error!("stream failed: {e}");
                    v.c.last_error = Some(e.to_string());
                    break StopReason::StreamError;
                }
                Some(Ok(frame)) => v.on_frame(frame, cfg).await,
            }
        }
    };
    let elapsed_s = v.start.elapsed().as_secs_f64();
    v.finish(worker, cfg, stop_reason, elapsed_s).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_nearest_rank() {
        let mut a = FrameAges::default();
        assert_eq!(a.quantile_ms(0.5), None);
        // Below 2.048 ms the histogram is exact.
        for us in [500, 100, 300, 200, 400] {
            a.record(us);
        }
        assert_eq!(a.quantile_ms(0.5), Some(0.3));
        assert_eq!(a.quantile_ms(0.99), Some(0.5));
        assert_eq!(a.quantile_ms(0.0), Some(0.1));
        // Negative ages (the local clock behind the server's) keep their sign and rank.
        a.clear();
        for us in [700, -1500, 1200, -200, 100] {
            a.record(us);
        }
        // Sorted: -1.5, -0.2, 0.1, 0.7, 1.2 ms; nearest rank ceil(q n).
        assert_eq!(a.quantile_ms(0.0), Some(-1.5));
        assert_eq!(a.quantile_ms(0.2), Some(-1.5));
        assert_eq!(a.quantile_ms(0.4), Some(-0.2));
        assert_eq!(a.quantile_ms(0.5), Some(0.1));
        assert_eq!(a.quantile_ms(0.99), Some(1.2));
        // Large ages within the 3 significant digits (0.1 %), rounded up (toward +inf).
        a.clear();
        a.record(152_000_000);
        a.record(-152_000_000);
        let (hi, lo) = (a.quantile_ms(1.0).unwrap(), a.quantile_ms(0.0).unwrap());
        assert!((152_000.0..=152_000.0 * 1.001).contains(&hi), "{hi}");
        assert!((-152_000.0..=-152_000.0 * 0.999).contains(&lo), "{lo}");
    }

    #[test]
    fn web_addresses_are_host_and_port() {
        use clap::Parser;
        let cfg = |a: &str| {
            ViewerArgs::try_parse_from(["haptic-viewer", "--web", a])
                .unwrap()
                .web_config()
        };
        for good in [
            "localhost:0",
            "0.0.0.0:8080",
            "[::1]:0",
            "viewer.example:80",
        ] {
            let (addr, _) = cfg(good).unwrap().unwrap();
            assert_eq!(addr, good);
        }
        for bad in ["localhost", ":80", "localhost:", "localhost:65536", "[::1]"] {
            assert!(
                matches!(cfg(bad), Err(ClientError::InvalidConfig(m)) if m.contains("HOST:PORT")),
                "{bad} accepted"
            );
        }
    }

    #[test]
    fn picture_names_are_numbered() {
        assert_eq!(
            picture_path(Path::new("out"), 1),
            PathBuf::from("out/frame_00001.png")
        );
    }

    fn key() -> SurfaceFrame {
        SurfaceFrame {
            keyframe: true,
            positions_m: vec![0., 0., 0., 1., 0., 0., 0., 1., 0.],
            triangles: vec![0, 1, 2],
            ..Default::default()
        }
    }

    #[test]
    fn state_rejects_bad_frames_and_keeps_going() {
        let p = RenderParams::default();
        let mut s = SurfaceState::new();
        let pos = SurfaceFrame {
            positions_m: vec![0.0; 9],
            ..Default::default()
        };
        assert!(s.apply(&pos, &p).is_err(), "no keyframe yet");
        assert_eq!(s.apply(&key(), &p).unwrap(), FrameKind::Keyframe);
        let short = SurfaceFrame {
            frame: 7,
            positions_m: vec![0.0; 6],
            ..Default::default()
        };
        let e = s.apply(&short, &p).unwrap_err().to_string();
        assert!(
            e.contains("bad frame 7") && e.contains("expected 3 x 3"),
            "{e}"
        );
        let nan = SurfaceFrame {
            positions_m: vec![f32::NAN; 9],
            ..Default::default()
        };
        assert!(s.apply(&nan, &p).is_err());
        let mut missing = key();
        missing.triangles = vec![0, 1, 3];
        assert!(s.apply(&missing, &p).is_err());
        assert_eq!(s.apply(&pos, &p).unwrap(), FrameKind::Positions);
        assert_eq!(s.positions_m(), &[0.0; 9]);
    }

    /// Issue 47: the frames of a recording made 152 s ago replay with the age of their
    /// delivery on the replay's clock, not the recording's age.
    #[tokio::test]
    async fn replayed_frames_age_on_the_replay_clock() {
        let recorded_us = (now_unix_us() - 152_000_000) as u64;
        let frames: Vec<SurfaceFrame> = (0..5)
            .map(|k| SurfaceFrame {
                frame: k,
                sim_time_s: 10.0 + 0.02 * k as f64,
                server_time_us: recorded_us + 20_000 * k,
                ..if k == 0 {
                    key()
                } else {
                    SurfaceFrame {
                        positions_m: vec![0.0; 9],
                        ..Default::default()
                    }
                }
            })
            .collect();
        let dir = std::env::temp_dir().join(format!("viewer-replay-age-{}", std::process::id()));
        let mut cfg = ViewerConfig::new("http://unused", "replay");
        cfg.out_dir = dir.clone();
        cfg.progress = false;
        let s = run_stream(replay_stream(frames), &cfg, std::future::pending())
            .await
            .unwrap();
        assert_eq!(s.frames, 5);
        // The old behaviour gives about 152 000 ms; a replay on a busy machine a few ms.
        let p99 = s.age_p99_ms.unwrap();
        assert!((-1.0..10_000.0).contains(&p99), "age p99 {p99} ms");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn config_validation() {
        let mut c = ViewerConfig::new("http://x", "s");
        assert!(c.validate().is_ok());
        c.interval_s = 0.0;
        assert!(c.validate().is_err());
    }
}
