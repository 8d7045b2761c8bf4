//! `ctl`: the scripted client of `SessionControl` behind `hapticctl`.
//!
//! [`Ctl`] wraps the generated client with one method per RPC; the formatting functions
//! ([`scenes_table`], [`stats_table`], [`stats_json`]) are pure so they are tested without a
//! server; [`CtlCommand`] is the command line and [`execute`] runs one command, writing results
//! to `out` (script-friendly: `start` prints only the session id) and details to `err`.
//!
//! Neighbours: [`haptic_cli::connect`] opens the channel; the server implements the service.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use haptic_cli::credentials::{AuthChannel, ClientCredentials};
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::{
    ApplyForceRequest, GetStatsRequest, ListScenesRequest, ListSessionsRequest, SceneInfo,
    SessionStats, StartSessionRequest, StartSessionResponse, StopSessionRequest, ToolStats, Vec3,
};

use crate::ClientError;

/// Parses `X,Y,Z` into three finite numbers (SI units as the caller says) with
/// [`haptic_cli::vec3::parse_vec3`]: whitespace around a component is allowed; anything else
/// (missing or extra components, empty ones, words, NaN, infinity) is refused.
///
/// # Errors
/// [`ClientError::InvalidVector`] with the input, saying which component is wrong and why.
pub fn parse_vec3(input: &str) -> Result<[f64; 3], ClientError> {
    haptic_cli::vec3::parse_vec3(input).map_err(|source| ClientError::InvalidVector {
        input: input.to_string(),
        source,
    })
}

/// Where a new session's scene comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SceneSource {
    /// A built-in scene name (see [`Ctl::scenes`]).
    Name(String),
    /// The full text of a scene TOML file.
    Toml(String),
}

/// A connected `SessionControl` client.
#[derive(Debug, Clone)]
pub struct Ctl {
    client: SessionControlClient<AuthChannel>,
    channel: AuthChannel,
}

impl Ctl {
    /// Wraps an open channel.
    pub fn new(channel: AuthChannel) -> Self {
        Self {
            client: SessionControlClient::new(channel.clone()),
            channel,
        }
    }

    /// The channel, for the other services (`SurfaceStream` in `record`).
    pub fn channel(&self) -> AuthChannel {
        self.channel.clone()
    }

    /// Connects to `url` with `credentials` (see [`haptic_cli::connect::connect`]).
    ///
    /// # Errors
    /// [`ClientError::Connect`], [`ClientError::Credentials`].
    pub async fn connect(url: &str, credentials: &ClientCredentials) -> Result<Self, ClientError> {
        Ok(Self::new(
            haptic_cli::connect::connect(url, credentials).await?,
        ))
    }

    /// The built-in scenes.
    ///
    /// # Errors
    /// [`ClientError::Rpc`] with the server's status.
    pub async fn scenes(&mut self) -> Result<Vec<SceneInfo>, ClientError> {
        Ok(self
            .client
            .list_scenes(ListScenesRequest {})
            .await?
            .into_inner()
            .scenes)
    }

    /// Starts a session from a built-in scene or scene text.
    ///
    /// # Errors
    /// [`ClientError::Rpc`], e.g. `NOT_FOUND` for an unknown scene or `INVALID_ARGUMENT` for
    /// malformed scene text.
    pub async fn start(&mut self, scene: SceneSource) -> Result<StartSessionResponse, ClientError> {
        let req = match scene {
            SceneSource::Name(scene) => StartSessionRequest {
                scene,
                scene_toml: String::new(),
            },
            SceneSource::Toml(scene_toml) => StartSessionRequest {
                scene: String::new(),
                scene_toml,
            },
        };
        Ok(self.client.start_session(req).await?.into_inner())
    }

    /// Stops a session.
    ///
    /// # Errors
    /// [`ClientError::Rpc`], e.g. `NOT_FOUND` for an unknown session.
    pub async fn stop(&mut self, session_id: &str) -> Result<(), ClientError> {
        self.client
            .stop_session(StopSessionRequest {
                session_id: session_id.to_string(),
            })
            .await?;
        Ok(())
    }

    /// Ids of the running sessions.
    ///
    /// # Errors
    /// [`ClientError::Rpc`].
    pub async fn sessions(&mut self) -> Result<Vec<String>, ClientError> {
        Ok(self
            .client
            .list_sessions(ListSessionsRequest {})
            .await?
            .into_inner()
            .session_ids)
    }

    /// The running sessions with their scene, family and device.
    ///
    /// # Errors
    /// [`ClientError::Rpc`].
    pub async fn session_summaries(
        &mut self,
    ) -> Result<Vec<haptics_proto::v1::SessionSummary>, ClientError> {
        Ok(self
            .client
            .list_sessions(ListSessionsRequest {})
            .await?
            .into_inner()
            .sessions)
    }

    /// Applies `force_n` (newtons) at `point_m` (metres, scene frame) for `duration_s` seconds of
    /// simulated time.
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] for a non-finite or negative duration or non-finite vectors
    /// (checked before sending); [`ClientError::Rpc`] for the server's refusal.
    pub async fn force(
        &mut self,
        session_id: &str,
        point_m: [f64; 3],
        force_n: [f64; 3],
        duration_s: f64,
    ) -> Result<(), ClientError> {
        if !(duration_s.is_finite() && duration_s >= 0.0) {
            return Err(ClientError::InvalidConfig(
                "duration must be a non-negative number of seconds".into(),
            ));
        }
        if !point_m.iter().chain(&force_n).all(|v| v.is_finite()) {
            return Err(ClientError::InvalidConfig(
                "point and force must be finite".into(),
            ));
        }
        self.client
            .apply_force(ApplyForceRequest {
                session_id: session_id.to_string(),
                point_m: Some(Vec3::from(point_m)),
                force_n: Some(Vec3::from(force_n)),
                duration_s,
            })
            .await?;
        Ok(())
    }

    /// Statistics of a session.
    ///
    /// # Errors
    /// [`ClientError::Rpc`], e.g. `NOT_FOUND` for an unknown session.
    pub async fn stats(&mut self, session_id: &str) -> Result<SessionStats, ClientError> {
        Ok(self
            .client
            .get_stats(GetStatsRequest {
                session_id: session_id.to_string(),
            })
            .await?
            .into_inner())
    }
}

/// Formats rows as left-aligned columns separated by two spaces (header first).
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for r in rows {
        for (w, c) in widths.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let mut out = String::new();
    let header: Vec<String> = header.iter().map(|h| h.to_string()).collect();
    for r in std::iter::once(&header).chain(rows) {
        let mut line = String::new();
        for (k, (c, w)) in r.iter().zip(&widths).enumerate() {
            if k + 1 == r.len() {
                line.push_str(c);
            } else {
                line.push_str(&format!("{c:<w$}  "));
            }
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    out
}

/// The scenes as a table: `NAME  NODES  TETS  DESCRIPTION`, one line per scene.
pub fn scenes_table(scenes: &[SceneInfo]) -> String {
    let rows: Vec<Vec<String>> = scenes
        .iter()
        .map(|s| {
            vec![
                s.name.clone(),
                s.nodes.to_string(),
                s.tetrahedra.to_string(),
                s.description.clone(),
            ]
        })
        .collect();
    table(&["NAME", "NODES", "TETS", "DESCRIPTION"], &rows)
}

/// A value of one [`SessionStats`] field.
#[derive(Debug, Clone, PartialEq)]
pub enum StatValue {
    /// A floating-point quantity, printed with `decimals` digits after the point.
    F64 {
        /// The value.
        value: f64,
        /// Digits after the decimal point in the table.
        decimals: usize,
    },
    /// A counter.
    U64(u64),
    /// A flag.
    Bool(bool),
    /// Text.
    Str(String),
}

/// One [`SessionStats`] field: its proto name, value and unit (`""` when unitless).
#[derive(Debug, Clone, PartialEq)]
pub struct StatRow {
    /// The proto field name, e.g. `step_p99_us`.
    pub name: &'static str,
    /// The value.
    pub value: StatValue,
    /// The unit as printed, e.g. `us`, `Hz`, `N`, `m`, `count`.
    pub unit: &'static str,
}

/// Every field of [`SessionStats`], in proto field order, with its unit. The single source for
/// [`stats_table`] and [`stats_json`], so both always list the same fields.
pub fn stats_rows(s: &SessionStats) -> Vec<StatRow> {
    use StatValue::*;
    let f = |value: f64, decimals: usize| F64 { value, decimals };
    let row = |name, value, unit| StatRow { name, value, unit };
    vec![
        row("session_id", Str(s.session_id.clone()), ""),
        row("loop_rate_hz", f(s.loop_rate_hz, 1), "Hz"),
        row("step_p50_us", f(s.step_p50_us, 1), "us"),
        row("step_p99_us", f(s.step_p99_us, 1), "us"),
        row("step_max_us", f(s.step_max_us, 1), "us"),
        row("overruns", U64(s.overruns), "count"),
        row("steps", U64(s.steps), "count"),
        row("pose_to_force_p50_us", f(s.pose_to_force_p50_us, 1), "us"),
        row("pose_to_force_p99_us", f(s.pose_to_force_p99_us, 1), "us"),
        row("rejected_samples", U64(s.rejected_samples), "count"),
        row("sim_time_s", f(s.sim_time_s, 3), "s"),
        row("substeps", U64(s.substeps.into()), "per tick"),
        row("in_contact", Bool(s.in_contact), ""),
        row("peak_force_n", f(s.peak_force_n, 3), "N"),
        row("max_displacement_m", f(s.max_displacement_m, 6), "m"),
        row("faulted", Bool(s.faulted), ""),
        row("fault", Str(s.fault.clone()), ""),
        row("device_samples", U64(s.device_samples), "count"),
        row("scene", Str(s.scene.clone()), ""),
        row("nodes", U64(s.nodes.into()), "count"),
        row("tetrahedra", U64(s.tetrahedra.into()), "count"),
        row("model_family", Str(s.model_family.clone()), ""),
        row("active_elements", U64(s.active_elements.into()), "count"),
        row("total_particles", U64(s.total_particles.into()), "count"),
        row("active_particles", U64(s.active_particles.into()), "count"),
        row("surface_vertices", U64(s.surface_vertices.into()), "count"),
        row("topology_version", U64(s.topology_version), ""),
        row("out_of_order_samples", U64(s.out_of_order_samples), "count"),
        row("device_silent", Bool(s.device_silent), ""),
        row("device_silences", U64(s.device_silences), "count"),
        row("overrunning", Bool(s.overrunning), ""),
        row("demoted", Bool(s.demoted), ""),
        row("watchers", U64(s.watchers.into()), "count"),
        row("watcher_frames_sent", U64(s.watcher_frames_sent), "count"),
        row(
            "watcher_frames_dropped",
            U64(s.watcher_frames_dropped),
            "count",
        ),
        row("watcher_bytes_sent", U64(s.watcher_bytes_sent), "bytes"),
        row("watcher_queued_bytes", U64(s.watcher_queued_bytes), "bytes"),
        row(
            "watcher_queue_limit_bytes",
            U64(s.watcher_queue_limit_bytes),
            "bytes",
        ),
        row("region_swaps", U64(s.region_swaps), "count"),
        row("region_preparation_s", f(s.region_preparation_s, 3), "s"),
        row("region_tiles", U64(s.region_tiles), "count"),
        row("region_tiles_ready", U64(s.region_tiles_ready), "count"),
        row("region_tiles_loaded", U64(s.region_tiles_loaded), "count"),
        row("region_tiles_refused", U64(s.region_tiles_refused), "count"),
        row(
            "region_tile_memory_bytes",
            U64(s.region_tile_memory_bytes),
            "bytes",
        ),
        row("region_tiles_dropped", U64(s.region_tiles_dropped), "count"),
        row(
            "region_tiles_reloaded",
            U64(s.region_tiles_reloaded),
            "count",
        ),
        row("region_tile_misses", U64(s.region_tile_misses), "count"),
        row(
            "region_unmapped_swaps",
            U64(s.region_unmapped_swaps),
            "count",
        ),
        row("region_cache_error", Str(s.region_cache_error.clone()), ""),
        row("contact_ticks", U64(s.contact_ticks), "count"),
        row("companion_ticks", U64(s.companion_ticks), "count"),
        row(
            "device",
            Str(s.device.as_ref().map_or_else(String::new, device_summary)),
            "",
        ),
        row(
            "out_of_workspace_samples",
            U64(s.out_of_workspace_samples),
            "count",
        ),
        row("threads", U64(s.threads.into()), "count"),
        row("pool_wait_us_max", U64(s.pool_wait_us_max), "us"),
        row("max_tools", U64(s.max_tools.into()), "count"),
        row("tools", Str(tools_summary(&s.tools)), ""),
    ]
}

/// The `tools` row of the statistics table: "N connected of M slots" (the per-tool table
/// follows the main one, [`tools_table`]).
fn tools_summary(tools: &[ToolStats]) -> String {
    if tools.is_empty() {
        return String::new();
    }
    let connected = tools.iter().filter(|t| t.connected).count();
    format!("{connected} connected of {} slots", tools.len())
}

/// The per-tool table of `hapticctl stats` (one row per tool slot): tool id ("-" for the
/// default tool), slot, connected, in contact, force N, pose-to-force p50 / p99 us, samples
/// accepted, rejected, outside the workspace, device.
pub fn tools_table(tools: &[ToolStats]) -> String {
    let rows: Vec<Vec<String>> = tools
        .iter()
        .map(|t| {
            vec![
                if t.tool_id.is_empty() {
                    "-".to_string()
                } else {
                    t.tool_id.clone()
                },
                t.slot.to_string(),
                t.connected.to_string(),
                t.in_contact.to_string(),
                format!("{:.3}", t.force_n),
                format!("{:.1}", t.pose_to_force_p50_us),
                format!("{:.1}", t.pose_to_force_p99_us),
                t.device_samples.to_string(),
                t.rejected_samples.to_string(),
                t.out_of_workspace_samples.to_string(),
                t.device
                    .as_ref()
                    .map_or_else(|| "-".to_string(), device_summary),
            ]
        })
        .collect();
    table(
        &[
            "TOOL",
            "SLOT",
            "CONNECTED",
            "IN_CONTACT",
            "FORCE_N",
            "P2F_P50_US",
            "P2F_P99_US",
            "SAMPLES",
            "REJECTED",
            "OUT_OF_WORKSPACE",
            "DEVICE",
        ],
        &rows,
    )
}

/// One tool's statistics as a JSON object keyed by the `ToolStats` proto field names.
pub fn tool_json(t: &ToolStats) -> serde_json::Value {
    serde_json::json!({
        "tool_id": t.tool_id,
        "slot": t.slot,
        "connected": t.connected,
        "in_contact": t.in_contact,
        "force_n": t.force_n,
        "peak_force_n": t.peak_force_n,
        "pose_to_force_p50_us": t.pose_to_force_p50_us,
        "pose_to_force_p99_us": t.pose_to_force_p99_us,
        "device_samples": t.device_samples,
        "rejected_samples": t.rejected_samples,
        "out_of_order_samples": t.out_of_order_samples,
        "out_of_workspace_samples": t.out_of_workspace_samples,
        "device_silent": t.device_silent,
        "contact_ticks": t.contact_ticks,
        "device": t.device.as_ref().map(device_summary),
    })
}

/// One line for a device's capabilities (`hapticctl stats`, `hapticctl sessions --long`):
/// name, degrees of freedom sensed / actuated, peak and continuous force, stiffness limit,
/// rate and workspace box (mm), the undeclared ones left out.
pub fn device_summary(c: &haptics_proto::v1::DeviceCapabilities) -> String {
    let mut parts = vec![format!(
        "{} ({}/{} DOF)",
        if c.name.is_empty() {
            "unnamed"
        } else {
            &c.name
        },
        c.sensed_degrees_of_freedom,
        c.actuated_degrees_of_freedom
    )];
    let mut put = |v: f64, text: String| {
        if v > 0.0 {
            parts.push(text);
        }
    };
    put(c.max_force_n, format!("{} N peak", c.max_force_n));
    put(
        c.max_continuous_force_n,
        format!("{} N continuous", c.max_continuous_force_n),
    );
    put(
        c.max_stiffness_n_per_m,
        format!("{} N/m", c.max_stiffness_n_per_m),
    );
    put(c.native_rate_hz, format!("{} Hz", c.native_rate_hz));
    if let (Some(lo), Some(hi)) = (&c.workspace_min_m, &c.workspace_max_m) {
        let mm = |v: f64| format!("{:.0}", v * 1e3);
        parts.push(format!(
            "workspace {},{},{}..{},{},{} mm",
            mm(lo.x),
            mm(lo.y),
            mm(lo.z),
            mm(hi.x),
            mm(hi.y),
            mm(hi.z)
        ));
    }
    parts.join(", ")
}

/// The statistics as a `FIELD  VALUE  UNIT` table, one line per [`SessionStats`] field.
pub fn stats_table(s: &SessionStats) -> String {
    let rows: Vec<Vec<String>> = stats_rows(s)
        .into_iter()
        .map(|r| {
            let v = match r.value {
                StatValue::F64 { value, decimals } => format!("{value:.decimals$}"),
                StatValue::U64(v) => v.to_string(),
                StatValue::Bool(b) => b.to_string(),
                StatValue::Str(s) if s.is_empty() => "-".to_string(),
                StatValue::Str(s) => s,
            };
            vec![r.name.to_string(), v, r.unit.to_string()]
        })
        .collect();
    let main = table(&["FIELD", "VALUE", "UNIT"], &rows);
    if s.tools.is_empty() {
        main
    } else {
        // One blank line between the two tables (`main` ends with its newline).
        format!("{main}\n{}", tools_table(&s.tools))
    }
}

/// The statistics as one JSON object keyed by the proto field names (numbers as JSON numbers,
/// 64-bit counters included; a non-finite float becomes `null`); `tools` is an array of
/// [`tool_json`] objects.
pub fn stats_json(s: &SessionStats) -> serde_json::Value {
    let mut map: serde_json::Map<String, serde_json::Value> = stats_rows(s)
        .into_iter()
        .map(|r| {
            let v = match r.value {
                StatValue::F64 { value, .. } => serde_json::json!(value),
                StatValue::U64(v) => serde_json::json!(v),
                StatValue::Bool(b) => serde_json::json!(b),
                StatValue::Str(s) => serde_json::json!(s),
            };
            (r.name.to_string(), v)
        })
        .collect();
    map.insert(
        "tools".into(),
        serde_json::Value::Array(s.tools.iter().map(tool_json).collect()),
    );
    serde_json::Value::Object(map)
}

/// A `hapticctl` command.
#[derive(Debug, Clone, PartialEq, clap::Subcommand)]
pub enum CtlCommand {
    /// List the built-in scenes (name, nodes, tets, description).
    Scenes,
    /// Start a session; prints only its id on stdout, details on stderr.
    Start {
        /// Built-in scene name.
        #[arg(required_unless_present = "scene_file", conflicts_with = "scene_file")]
        scene: Option<String>,
        /// Scene TOML file, sent as text.
        #[arg(long)]
        scene_file: Option<PathBuf>,
    },
    /// Stop a session.
    Stop {
        /// Session id.
        id: String,
    },
    /// List the running session ids, one per line.
    Sessions {
        /// One row per session: id, scene, model family and the connected device as it
        /// introduced itself (`-` for none; `connected` for a device that sent no
        /// capabilities).
        #[arg(long)]
        long: bool,
    },
    /// Apply a force to a session's surface.
    Force {
        /// Session id.
        id: String,
        /// Application point X,Y,Z in metres (scene frame).
        #[arg(long, allow_hyphen_values = true)]
        point: String,
        /// Force X,Y,Z in newtons.
        #[arg(long, allow_hyphen_values = true)]
        force: String,
        /// How long the force acts, seconds of simulated time.
        #[arg(long, default_value_t = 0.5)]
        duration_s: f64,
    },
    /// Show a session's statistics.
    Stats {
        /// Session id.
        id: String,
        /// One JSON object keyed by proto field names instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Print statistics repeatedly (one JSON line each with --json).
    WatchStats {
        /// Session id.
        id: String,
        /// Seconds between reports.
        #[arg(long, default_value_t = 1.0)]
        interval_s: f64,
        /// Number of reports (0 = until interrupted).
        #[arg(long, default_value_t = 0)]
        count: u64,
        /// JSON lines instead of tables.
        #[arg(long)]
        json: bool,
    },
    /// Record a session's surface frames, injected loads and statistics to MCAP (Foxglove); ends after
    /// --duration-s, when the session ends, or on Ctrl-C.
    Record {
        /// Session id.
        id: String,
        /// Output file (.mcap).
        #[arg(long)]
        out: PathBuf,
        /// Seconds to record (default: until the session ends or Ctrl-C).
        #[arg(long)]
        duration_s: Option<f64>,
        /// Surface frames per second (0.1..=120).
        #[arg(long, default_value_t = 30.0)]
        rate_hz: f64,
        /// Seconds between statistics messages.
        #[arg(long, default_value_t = 0.1)]
        stats_interval_s: f64,
    },
    /// Write the surface frames of a recording as a ParaView time series (DIR/surface.pvd and
    /// one .vtu per frame). Needs no server.
    ExportVtu {
        /// Recording (.mcap) from `hapticctl record`.
        input: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
}

fn io_err(path: &str) -> impl FnOnce(std::io::Error) -> ClientError + '_ {
    move |source| ClientError::Io {
        path: PathBuf::from(path),
        source,
    }
}

/// Runs one command against `ctl`: results go to `out` (stdout), details to `err` (stderr).
///
/// # Errors
/// [`ClientError::Rpc`] for server refusals; [`ClientError::InvalidVector`] /
/// [`ClientError::InvalidConfig`] for bad arguments (checked before sending);
/// [`ClientError::Io`] when a scene file cannot be read or output cannot be written.
pub async fn execute(
    ctl: &mut Ctl,
    cmd: CtlCommand,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> Result<(), ClientError> {
    let o = io_err("<stdout>");
    match cmd {
        CtlCommand::Scenes => write!(out, "{}", scenes_table(&ctl.scenes().await?)).map_err(o)?,
        CtlCommand::Start { scene, scene_file } => {
            start_session(ctl, scene, scene_file, out, err).await?;
        }
        CtlCommand::Stop { id } => {
            ctl.stop(&id).await?;
            writeln!(err, "stopped session {id}").map_err(io_err("<stderr>"))?;
        }
        CtlCommand::Sessions { long: false } => {
            for id in ctl.sessions().await? {
                writeln!(out, "{id}").map_err(io_err("<stdout>"))?;
            }
        }
        CtlCommand::Sessions { long: true } => list_sessions_long(ctl, out).await?,
        CtlCommand::Force {
            id,
            point,
            force,
            duration_s,
        } => apply_force(ctl, &id, &point, &force, duration_s, err).await?,
        CtlCommand::Stats { id, json } => {
            let s = ctl.stats(&id).await?;
            if json {
                writeln!(out, "{}", stats_json(&s)).map_err(o)?;
            } else {
                write!(out, "{}", stats_table(&s)).map_err(o)?;
            }
        }
        CtlCommand::WatchStats {
            id,
            interval_s,
            count,
            json,
        } => watch_stats(ctl, &id, interval_s, count, json, out).await?,
        CtlCommand::Record {
            id,
            out: path,
            duration_s,
            rate_hz,
            stats_interval_s,
        } => {
            let params = crate::record::RecordParams {
                duration_s,
                rate_hz,
                stats_interval_s,
            };
            record_session(ctl, &id, &path, params, out).await?;
        }
        CtlCommand::ExportVtu { input, out: dir } => {
            let n = crate::record::export_vtu(&input, &dir)?;
            writeln!(out, "{}: {n} frames", dir.join("surface.pvd").display()).map_err(o)?;
        }
    }
    Ok(())
}

/// `start`: a session of the named built-in scene or of a scene file; prints its id to `out`
/// and its size to `err`.
async fn start_session(
    ctl: &mut Ctl,
    scene: Option<String>,
    scene_file: Option<PathBuf>,
    out: &mut dyn Write,
    err: &mut dyn Write,
) -> Result<(), ClientError> {
    let source = match (scene, scene_file) {
        (_, Some(path)) => {
            SceneSource::Toml(
                std::fs::read_to_string(&path).map_err(|source| ClientError::Io {
                    path: path.clone(),
                    source,
                })?,
            )
        }
        (Some(name), None) => SceneSource::Name(name),
        (None, None) => {
            return Err(ClientError::InvalidConfig(
                "give a scene name or --scene-file".into(),
            ));
        }
    };
    let r = ctl.start(source).await?;
    writeln!(out, "{}", r.session_id).map_err(io_err("<stdout>"))?;
    writeln!(
        err,
        "started session {}: {} nodes, {} tetrahedra, {} substeps per tick, critical dt {:.3e} s",
        r.session_id, r.nodes, r.tetrahedra, r.substeps, r.critical_dt_s
    )
    .map_err(io_err("<stderr>"))?;
    Ok(())
}

/// `sessions --long`: one row per session (id, scene, family, tools, device). Tools:
/// `CONNECTED/MAX:ID,...` (issue 50; `(default)` for the default tool's "").
async fn list_sessions_long(ctl: &mut Ctl, out: &mut dyn Write) -> Result<(), ClientError> {
    let rows: Vec<Vec<String>> = ctl
        .session_summaries()
        .await?
        .iter()
        .map(|s| {
            let device = match (&s.device, s.device_connected) {
                (Some(c), _) => device_summary(c),
                (None, true) => "connected".into(),
                (None, false) => "-".into(),
            };
            let ids: Vec<&str> = s
                .tools
                .iter()
                .map(|t| {
                    if t.tool_id.is_empty() {
                        "(default)"
                    } else {
                        t.tool_id.as_str()
                    }
                })
                .collect();
            let mut tools = format!("{}/{}", s.tools.len(), s.max_tools);
            if !ids.is_empty() {
                tools = format!("{tools}:{}", ids.join(","));
            }
            vec![
                s.session_id.clone(),
                s.scene.clone(),
                s.model_family.clone(),
                tools,
                device,
            ]
        })
        .collect();
    let text = table(&["ID", "SCENE", "FAMILY", "TOOLS", "DEVICE"], &rows);
    write!(out, "{text}").map_err(io_err("<stdout>"))?;
    Ok(())
}

/// `force`: checks the two vectors before sending, then applies the force.
async fn apply_force(
    ctl: &mut Ctl,
    id: &str,
    point: &str,
    force: &str,
    duration_s: f64,
    err: &mut dyn Write,
) -> Result<(), ClientError> {
    let (p, f) = (parse_vec3(point)?, parse_vec3(force)?);
    ctl.force(id, p, f, duration_s).await?;
    writeln!(
        err,
        "applied force {f:?} N at {p:?} m for {duration_s} s to session {id}"
    )
    .map_err(io_err("<stderr>"))?;
    Ok(())
}

/// `watch-stats`: `count` reports (0: until interrupted), one every `interval_s` seconds.
async fn watch_stats(
    ctl: &mut Ctl,
    id: &str,
    interval_s: f64,
    count: u64,
    json: bool,
    out: &mut dyn Write,
) -> Result<(), ClientError> {
    if !(interval_s.is_finite() && interval_s > 0.0) {
        return Err(ClientError::InvalidConfig(
            "interval must be a positive number of seconds".into(),
        ));
    }
    let mut tick = tokio::time::interval(Duration::from_secs_f64(interval_s));
    let mut n = 0;
    while count == 0 || n < count {
        tick.tick().await;
        let s = ctl.stats(id).await?;
        if json {
            writeln!(out, "{}", stats_json(&s)).map_err(io_err("<stdout>"))?;
        } else {
            writeln!(out, "{}", stats_table(&s)).map_err(io_err("<stdout>"))?;
        }
        out.flush().map_err(io_err("<stdout>"))?;
        n += 1;
    }
    Ok(())
}

/// `record`: records until the duration, the session's end or Ctrl-C, then prints what the
/// file holds.
async fn record_session(
    ctl: &mut Ctl,
    id: &str,
    path: &std::path::Path,
    params: crate::record::RecordParams,
    out: &mut dyn Write,
) -> Result<(), ClientError> {
    let channel = ctl.channel();
    let shutdown = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    let r = crate::record::record(channel, id, path, params, shutdown).await?;
    writeln!(
        out,
        "{}: {} surface frames ({} keyframes), {} statistics, {} injected loads{}, {} bytes",
        path.display(),
        r.frames,
        r.keyframes,
        r.stats,
        r.loads,
        if r.loads_missed > 0 {
            format!(" ({} missed: raise --rate-hz)", r.loads_missed)
        } else {
            String::new()
        },
        r.bytes
    )
    .map_err(io_err("<stdout>"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_parse_strictly() {
        assert_eq!(parse_vec3("1,-2.5, 3e-3").unwrap(), [1.0, -2.5, 0.003]);
        for bad in [
            "", "1,2", "1,2,3,4", "1,,3", "a,2,3", "1,2,NaN", "1,2,inf", "1;2;3",
        ] {
            let e = parse_vec3(bad).unwrap_err();
            assert!(matches!(e, ClientError::InvalidVector { .. }), "{bad}: {e}");
        }
        let e = parse_vec3("1,x,3").unwrap_err().to_string();
        assert!(e.contains("Y") && e.contains("not a number"), "{e}");
    }

    #[test]
    fn scenes_table_lists_every_scene() {
        let t = scenes_table(&[SceneInfo {
            name: "lv".into(),
            description: "left ventricle".into(),
            nodes: 412,
            tetrahedra: 1352,
        }]);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 2);
        assert!(lines[0].starts_with("NAME"));
        assert!(lines[1].contains("1352") && lines[1].ends_with("left ventricle"));
    }
}
