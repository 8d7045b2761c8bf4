//! The gRPC services of `haptics.v1`: SessionControl, DeviceLink and SurfaceStream.
//! Every handler validates its input first; errors go through the one
//! `From<ServerError> for Status` mapping.

use std::pin::Pin;
use std::sync::Arc;

use haptic_model::DVec3;
use haptic_model::body::{self, MAX_DEVICE_DISTANCE_M};
use haptics_proto::v1::device_link_server::DeviceLink;
use haptics_proto::v1::session_control_server::SessionControl;
use haptics_proto::v1::surface_stream_server::SurfaceStream;
use haptics_proto::v1::*;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::auth::{Action, Auth};
use crate::builds::{BuildGate, BuildLimits};
use crate::error::ServerError;
use crate::servo::{Command, Pose};
use crate::session::SessionManager;

/// Largest accepted device speed, m/s (a haptic arm moves well below 5 m/s).
pub const MAX_DEVICE_SPEED_M_PER_S: f64 = 20.0;
/// Default viewer frame rate, Hz.
pub const DEFAULT_VIEWER_RATE_HZ: f64 = crate::stream::DEFAULT_RATE_HZ;
/// Largest viewer frame rate, Hz.
pub const MAX_VIEWER_RATE_HZ: f64 = crate::stream::MAX_RATE_HZ;

/// Shared handler state.
#[derive(Clone)]
pub struct Services {
    manager: Arc<SessionManager>,
    builds: Arc<BuildGate>,
    auth: Arc<Auth>,
}

impl Services {
    /// Handlers over `manager` (scene builds bounded by its configuration's limits) that
    /// allow every call (no tokens; as in-process tests use them).
    pub fn new(manager: Arc<SessionManager>) -> Self {
        Self::with_auth(manager, Arc::new(Auth::open()))
    }

    /// Handlers that check each call's [`crate::auth::Caller`] against `auth` (the
    /// interceptor in front of them authenticates it).
    pub fn with_auth(manager: Arc<SessionManager>, auth: Arc<Auth>) -> Self {
        let c = manager.config();
        let builds = Arc::new(BuildGate::new(BuildLimits {
            max_concurrent_builds: c.max_concurrent_builds,
            max_builds_per_client: c.max_builds_per_client,
            max_sessions_per_client: c.max_sessions_per_client,
            build_timeout: c.build_timeout,
        }));
        Self {
            manager,
            builds,
            auth,
        }
    }
}

fn vec3(v: &Option<Vec3>, field: &str) -> Result<DVec3, ServerError> {
    let v = v
        .as_ref()
        .ok_or_else(|| ServerError::InvalidArgument(format!("{field} is missing")))?;
    if !v.is_finite() {
        return Err(ServerError::InvalidArgument(format!(
            "{field} has a non-finite component ({}, {}, {})",
            v.x, v.y, v.z
        )));
    }
    Ok(DVec3::new(v.x, v.y, v.z))
}

/// Checks a device sample: its position and velocity (m, m/s), or what is wrong with it (a
/// sample without a position is rejected).
fn validate_sample(s: &DeviceSample) -> Result<(DVec3, DVec3), &'static str> {
    let p = s.position_m.as_ref().ok_or("position_m missing")?;
    if !p.is_finite() {
        return Err("position_m not finite");
    }
    let p = DVec3::new(p.x, p.y, p.z);
    if p.abs().max_element() > MAX_DEVICE_DISTANCE_M {
        return Err("position_m absurdly far");
    }
    let v = match &s.velocity_m_per_s {
        Some(v) if !v.is_finite() => return Err("velocity not finite"),
        Some(v) => DVec3::new(v.x, v.y, v.z),
        None => DVec3::ZERO,
    };
    if v.length() > MAX_DEVICE_SPEED_M_PER_S {
        return Err("velocity absurd");
    }
    Ok((p, v))
}

#[tonic::async_trait]
impl SessionControl for Services {
    async fn list_scenes(
        &self,
        req: Request<ListScenesRequest>,
    ) -> Result<Response<ListScenesResponse>, Status> {
        self.auth.authorize(&req, Action::ListScenes, None)?;
        let scenes = tokio::task::spawn_blocking(|| {
            haptic_model::scene::builtin_scene_names()
                .iter()
                .map(|(name, description)| {
                    let (nodes, tets) = haptic_model::scene::load_builtin(name)
                        .map(|s| (s.mesh.node_count() as u32, s.mesh.tet_count() as u32))
                        .unwrap_or((0, 0));
                    SceneInfo {
                        name: name.to_string(),
                        description: description.to_string(),
                        nodes,
                        tetrahedra: tets,
                    }
                })
                .collect::<Vec<_>>()
        })
        .await
        .map_err(|e| Status::internal(e.to_string()))?;
        Ok(Response::new(ListScenesResponse { scenes }))
    }

    async fn start_session(
        &self,
        req: Request<StartSessionRequest>,
    ) -> Result<Response<StartSessionResponse>, Status> {
        let caller = self.auth.authorize(&req, Action::StartSession, None)?;
        let client = req.remote_addr().map(|a| a.ip());
        let r = req.into_inner();
        let manager = self.manager.clone();
        let session = self
            .builds
            .run(client, &self.manager, move || {
                let scene = manager.load_scene(&r.scene, &r.scene_toml)?;
                let tools = crate::tool::scene_tools(&scene);
                let session = manager.start_with_tools(&scene, &tools)?;
                // Recorded for a restart (with a state dir); a failure to record is logged,
                // the session runs anyway.
                if let Err(e) = manager.record(&session.id, &r.scene, &r.scene_toml) {
                    tracing::warn!(session = %session.id, "{e}");
                }
                Ok(session)
            })
            .await?;
        self.auth.set_owner(&session.id, &caller);
        tracing::info!(session = %session.id, owner = %caller.name, scene = %session.scene, nodes = session.nodes, tets = session.tetrahedra,
            substeps = session.substeps, critical_dt_s = session.critical_dt_s, "session started");
        Ok(Response::new(StartSessionResponse {
            session_id: session.id.clone(),
            nodes: session.nodes,
            tetrahedra: session.tetrahedra,
            substeps: session.substeps,
            critical_dt_s: session.critical_dt_s,
        }))
    }

    async fn stop_session(
        &self,
        req: Request<StopSessionRequest>,
    ) -> Result<Response<StopSessionResponse>, Status> {
        self.auth
            .authorize(&req, Action::StopSession, Some(&req.get_ref().session_id))?;
        let id = req.into_inner().session_id;
        let manager = self.manager.clone();
        let id2 = id.clone();
        tokio::task::spawn_blocking(move || manager.stop(&id2))
            .await
            .map_err(|e| Status::internal(e.to_string()))??;
        self.auth.forget(&id);
        tracing::info!(session = %id, "session stopped");
        Ok(Response::new(StopSessionResponse {}))
    }

    async fn apply_force(
        &self,
        req: Request<ApplyForceRequest>,
    ) -> Result<Response<ApplyForceResponse>, Status> {
        self.auth
            .authorize(&req, Action::ApplyForce, Some(&req.get_ref().session_id))?;
        let r = req.into_inner();
        let point = vec3(&r.point_m, "point_m")?;
        let force = vec3(&r.force_n, "force_n")?;
        body::validate_point_load(point, force, r.duration_s).map_err(ServerError::from)?;
        let session = self.manager.get(&r.session_id)?;
        if let Some(fault) = session.stats().fault {
            return Err(ServerError::FailedPrecondition(format!(
                "session is quarantined: {fault}"
            ))
            .into());
        }
        session
            .point_loads
            .check(point)
            .map_err(|e| ServerError::FailedPrecondition(e.to_string()))?;
        session.send(Command::ApplyForce {
            point_m: point,
            force_n: force,
            duration_s: r.duration_s,
        })?;
        Ok(Response::new(ApplyForceResponse {}))
    }

    async fn get_stats(
        &self,
        req: Request<GetStatsRequest>,
    ) -> Result<Response<SessionStats>, Status> {
        self.auth
            .authorize(&req, Action::GetStats, Some(&req.get_ref().session_id))?;
        let id = req.into_inner().session_id;
        let s = self.manager.get(&id)?;
        let st = s.stats();
        Ok(Response::new(SessionStats {
            session_id: id,
            loop_rate_hz: st.loop_rate_hz,
            step_p50_us: st.step_p50_us,
            step_p99_us: st.step_p99_us,
            step_max_us: st.step_max_us,
            overruns: st.overruns,
            steps: st.steps,
            pose_to_force_p50_us: st.pose_to_force_p50_us,
            pose_to_force_p99_us: st.pose_to_force_p99_us,
            rejected_samples: s
                .shared
                .rejected_samples
                .load(std::sync::atomic::Ordering::Relaxed),
            sim_time_s: st.sim_time_s,
            substeps: s.substeps,
            in_contact: st.in_contact,
            peak_force_n: st.peak_force_n,
            max_displacement_m: st.max_displacement_m,
            faulted: st.fault.is_some(),
            fault: st.fault.unwrap_or("").to_string(),
            device_samples: st.device_samples,
            scene: s.scene.clone(),
            nodes: s.nodes,
            tetrahedra: s.tetrahedra,
            model_family: s.family.to_string(),
            active_elements: st.body.active_elements as u32,
            region_swaps: st.body.region_swaps,
            region_preparation_s: st.body.region_preparation_s,
            region_tiles: st.body.region_tiles,
            region_tiles_ready: st.body.region_tiles_ready,
            region_tiles_loaded: st.body.region_tiles_loaded,
            region_tiles_refused: st.body.region_tiles_refused,
            region_tile_memory_bytes: st.body.region_tile_memory_bytes,
            region_tiles_dropped: st.body.region_tiles_dropped,
            region_tiles_reloaded: st.body.region_tiles_reloaded,
            region_tile_misses: st.body.region_tile_misses,
            region_unmapped_swaps: st.body.region_unmapped_swaps,
            region_cache_error: s.region_cache_log.last().unwrap_or_default(),
            contact_ticks: st.contact_ticks,
            companion_ticks: st.body.companion_ticks,
            total_particles: st.body.particles as u32,
            active_particles: st.body.active_particles as u32,
            surface_vertices: st.body.surface_vertices as u32,
            topology_version: st.body.topology_version,
            out_of_order_samples: s
                .shared
                .out_of_order_samples
                .load(std::sync::atomic::Ordering::Relaxed),
            device_silent: st.device_silent,
            device_silences: st.device_silences,
            overrunning: st.overrunning,
            demoted: st.demoted,
            threads: s.threads_now(&st),
            pool_wait_us_max: st.pool_wait_us_max,
            device: first_device(&s),
            max_tools: s.tools.len() as u32,
            tools: tool_stats(&s, &st),
            out_of_workspace_samples: s
                .shared
                .out_of_workspace_samples
                .load(std::sync::atomic::Ordering::Relaxed),
            ..watcher_stats(&s.watcher_stats)
        }))
    }

    async fn list_sessions(
        &self,
        req: Request<ListSessionsRequest>,
    ) -> Result<Response<ListSessionsResponse>, Status> {
        let caller = self.auth.authorize(&req, Action::ListSessions, None)?;
        let session_ids = self.auth.visible(&caller, self.manager.ids());
        // A session stopped between the two calls is left out of the details.
        let sessions = session_ids
            .iter()
            .filter_map(|id| self.manager.get(id).ok())
            .map(|s| SessionSummary {
                session_id: s.id.clone(),
                scene: s.scene.clone(),
                model_family: s.family.to_string(),
                device_connected: s.has_device(),
                device: first_device(&s),
                max_tools: s.tools.len() as u32,
                tools: s
                    .connected_tools()
                    .map(|t| ToolSummary {
                        tool_id: t.tool_id(),
                        slot: t.slot as u32,
                        device: t.device.capabilities(),
                    })
                    .collect(),
            })
            .collect();
        Ok(Response::new(ListSessionsResponse {
            session_ids,
            sessions,
        }))
    }
}

/// Response header of `DeviceLink.Connect`: the scene's force limit, N.
pub const HEADER_MAX_FORCE: &str = "haptics-max-force-n";
/// Response header: the scene's force-rate limit, N/s.
pub const HEADER_MAX_FORCE_RATE: &str = "haptics-max-force-rate-n-per-s";
/// Request header of `DeviceLink.Connect`: the perceptual deadband on the force stream, a
/// fraction (e.g. `0.07`); absent or 0: every force command is sent.
pub const HEADER_FORCE_DEADBAND: &str = "haptics-force-deadband";
/// Response header: this daemon process's instance id.
pub const HEADER_SERVER_INSTANCE: &str = "haptics-server-instance";

/// Writes the connect-time headers of a device stream: the session's limits (when it has a
/// scene) and the daemon instance.
fn link_headers(
    md: &mut tonic::metadata::MetadataMap,
    limits: Option<crate::session::LinkLimits>,
    instance: &str,
) {
    let mut put = |k: &'static str, v: String| {
        if let Ok(v) = v.parse() {
            md.insert(k, v);
        }
    };
    if let Some(l) = limits {
        put(HEADER_MAX_FORCE, l.max_force_n.to_string());
        put(HEADER_MAX_FORCE_RATE, l.max_force_rate_n_per_s.to_string());
    }
    put(HEADER_SERVER_INSTANCE, instance.to_owned());
}

/// The capabilities of the first connected tool (lowest slot) that introduced itself: the
/// session-level `device` of `GetStats` and `ListSessions`.
fn first_device(s: &crate::session::Session) -> Option<DeviceCapabilities> {
    s.connected_tools().find_map(|t| t.device.capabilities())
}

/// `SessionStats.tools`: every slot of `s`, from the servo's statistics `st` and the stream
/// tasks' counters.
fn tool_stats(s: &crate::session::Session, st: &crate::servo::StatsSnapshot) -> Vec<ToolStats> {
    use std::sync::atomic::Ordering::Relaxed;
    s.tools
        .iter()
        .map(|t| {
            let ts = st.tools.get(t.slot).copied().unwrap_or_default();
            ToolStats {
                tool_id: t.tool_id(),
                slot: t.slot as u32,
                connected: t.connected(),
                in_contact: ts.in_contact,
                force_n: ts.force_n,
                peak_force_n: ts.peak_force_n,
                pose_to_force_p50_us: ts.pose_to_force_p50_us,
                pose_to_force_p99_us: ts.pose_to_force_p99_us,
                device_samples: ts.device_samples,
                rejected_samples: t.rejected_samples.load(Relaxed),
                out_of_order_samples: t.out_of_order_samples.load(Relaxed),
                out_of_workspace_samples: t.out_of_workspace_samples.load(Relaxed),
                device_silent: ts.device_silent,
                contact_ticks: ts.contact_ticks,
                device: t.device.capabilities(),
            }
        })
        .collect()
}

/// The watcher fields of `SessionStats` (40-45).
fn watcher_stats(w: &crate::frame::WatcherStats) -> SessionStats {
    use std::sync::atomic::Ordering::Relaxed;
    SessionStats {
        watchers: w.watchers.load(Relaxed) as u32,
        watcher_frames_sent: w.frames_sent.load(Relaxed),
        watcher_frames_dropped: w.frames_dropped.load(Relaxed),
        watcher_bytes_sent: w.bytes_sent.load(Relaxed),
        watcher_queued_bytes: w.queued_bytes.load(Relaxed),
        watcher_queue_limit_bytes: w.queue_limit_bytes.load(Relaxed),
        ..SessionStats::default()
    }
}

type ForceStream = Pin<Box<dyn Stream<Item = Result<ForceCommand, Status>> + Send>>;

#[tonic::async_trait]
impl DeviceLink for Services {
    type ConnectStream = ForceStream;

    async fn connect(
        &self,
        req: Request<Streaming<DeviceSample>>,
    ) -> Result<Response<Self::ConnectStream>, Status> {
        // Any session: the session id comes with the first sample.
        self.auth.authorize(&req, Action::DeviceLink, None)?;
        let deadband = req
            .metadata()
            .get(HEADER_FORCE_DEADBAND)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.trim().parse::<f64>().ok())
            .unwrap_or(0.0);
        let mut inbound = req.into_inner();
        let first = inbound.message().await?.ok_or_else(|| {
            Status::invalid_argument("the device stream ended before its first sample")
        })?;
        if first.session_id.is_empty() {
            return Err(Status::invalid_argument(
                "the first DeviceSample must carry session_id",
            ));
        }
        // A device that introduces itself is checked before the session is touched.
        if let Some(c) = &first.capabilities {
            crate::device::check(c).map_err(Status::invalid_argument)?;
        }
        crate::tool::check_tool_id(&first.tool_id)?;
        let session = self.manager.get(&first.session_id)?;
        let (tx, rx) = mpsc::channel(256);
        let attached = session.attach_tool(&first.tool_id, tx)?;
        let tool = session.tools[attached.slot].clone();
        let caps = first.capabilities.clone();
        let workspace = caps.as_ref().and_then(crate::device::workspace);
        let device_force_n = caps
            .as_ref()
            .map_or(f64::INFINITY, crate::device::force_limit_n);
        // The lowest of the scene's, the tool's own and the device's force limits.
        let tool_force_n = tool.max_force_n.unwrap_or(f64::INFINITY);
        let limits = session.limits.map(|l| crate::session::LinkLimits {
            max_force_n: l.max_force_n.min(tool_force_n).min(device_force_n),
            ..l
        });
        let instance = self.manager.instance().to_owned();
        tool.set_force_deadband(deadband);
        let name = caps.as_ref().map_or("", |c| c.name.as_str());
        tracing::info!(session = %session.id, tool = %first.tool_id, slot = attached.slot, device = %name, "device connected");
        tool.device.attach(caps);
        tokio::spawn(pump_device_samples(
            DeviceStream {
                session,
                tool,
                pose_in: attached.pose,
                workspace,
            },
            first,
            inbound,
        ));
        let mut response = Response::new(Box::pin(ReceiverStream::new(rx)) as ForceStream);
        link_headers(response.metadata_mut(), limits, &instance);
        Ok(response)
    }
}

/// A device stream attached to a tool slot, as its task holds it.
struct DeviceStream {
    session: Arc<crate::session::Session>,
    tool: Arc<crate::session::ToolSlot>,
    pose_in: triple_buffer::Input<Pose>,
    /// The declared workspace box, if any.
    workspace: Option<(DVec3, DVec3)>,
}

/// Why a device sample was dropped.
#[derive(Clone, Copy)]
enum Dropped {
    /// Non-finite, absurd, or another session's.
    Rejected,
    /// `seq` not newer than the last accepted.
    OutOfOrder,
    /// Outside the declared workspace.
    OutOfWorkspace,
}

impl DeviceStream {
    /// Counts a dropped sample in the tool's counter and the session's.
    fn count(&self, why: Dropped) {
        use std::sync::atomic::Ordering::Relaxed;
        let (t, s) = (&self.tool, &self.session.shared);
        let (tool, session) = match why {
            Dropped::Rejected => (&t.rejected_samples, &s.rejected_samples),
            Dropped::OutOfOrder => (&t.out_of_order_samples, &s.out_of_order_samples),
            Dropped::OutOfWorkspace => (&t.out_of_workspace_samples, &s.out_of_workspace_samples),
        };
        tool.fetch_add(1, Relaxed);
        session.fetch_add(1, Relaxed);
    }
}

/// The device stream's task: every sample of one tool's stream (the first already read) is
/// checked (session id, rising sequence number, finite and bounded pose, inside the declared
/// workspace) and written to its slot's pose buffer, or dropped and counted (in the tool's and
/// the session's counters); the tool is detached when the stream ends or the session stops.
async fn pump_device_samples(
    mut link: DeviceStream,
    first: DeviceSample,
    mut inbound: Streaming<DeviceSample>,
) {
    let mut next = Some(first);
    let mut last_seq: Option<u64> = None;
    loop {
        let sample = match next.take() {
            Some(s) => s,
            None => match inbound.next().await {
                Some(Ok(s)) => s,
                _ => break,
            },
        };
        if !sample.session_id.is_empty() && sample.session_id != link.session.id {
            link.count(Dropped::Rejected);
            continue;
        }
        // Sequence numbers only go up: an older or repeated one (a replay, a duplicate
        // with a new position) is dropped and counted, never applied unanswered.
        if last_seq.is_some_and(|l| sample.seq <= l) {
            link.count(Dropped::OutOfOrder);
            continue;
        }
        match validate_sample(&sample) {
            Ok((p, _))
                if link
                    .workspace
                    .is_some_and(|ws| !crate::device::in_workspace(ws, p)) =>
            {
                link.count(Dropped::OutOfWorkspace);
            }
            Ok((p, v)) => {
                last_seq = Some(sample.seq);
                link.pose_in.write(Pose {
                    seq: sample.seq,
                    position_m: p,
                    velocity_m_per_s: v,
                    received_us: link.session.now_us(),
                    connected: true,
                });
                // Device pacing: the servo ticks for this sample now.
                link.session.wake_servo();
            }
            Err(_) => link.count(Dropped::Rejected),
        }
        if link
            .session
            .shared
            .stop
            .load(std::sync::atomic::Ordering::Acquire)
        {
            break;
        }
    }
    let DeviceStream {
        session,
        tool,
        pose_in,
        ..
    } = link;
    tracing::info!(session = %session.id, tool = %tool.tool_id(), slot = tool.slot, "device disconnected");
    session.detach_tool(tool.slot, pose_in);
}

#[tonic::async_trait]
impl SurfaceStream for Services {
    type WatchStream = crate::stream::FrameStream;

    async fn watch(
        &self,
        req: Request<WatchRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        self.auth
            .authorize(&req, Action::Watch, Some(&req.get_ref().session_id))?;
        let r = req.into_inner();
        let params = crate::stream::WatchParams::from_request(&r)?;
        let session = self.manager.get(&r.session_id)?;
        let (frames, servo_guard) = session.watch();
        Ok(Response::new(crate::stream::spawn_watch(
            frames,
            servo_guard,
            session.watcher_stats.clone(),
            session.probe_radius_m,
            params,
        )))
    }

    async fn request_keyframe(
        &self,
        req: Request<KeyframeRequest>,
    ) -> Result<Response<KeyframeResponse>, Status> {
        self.auth
            .authorize(&req, Action::Watch, Some(&req.get_ref().session_id))?;
        let r = req.into_inner();
        let session = self.manager.get(&r.session_id)?;
        session.watcher_stats.request_keyframe(r.watch_id)?;
        Ok(Response::new(KeyframeResponse {}))
    }
}
