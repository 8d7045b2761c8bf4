//! Sessions: a scene, its simulation on a servo thread, and the async-side ends of every
//! handoff. [`SessionManager`] owns all sessions of the daemon.
//!
//! Threads per session: the servo thread ([`crate::servo::run_loop`]), a forwarder thread that
//! drains the force ring into the attached DeviceLink stream (woken by the servo with
//! `Thread::unpark`, which is wait-free), and a tokio task that turns servo snapshots into
//! viewer frames while someone watches.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use haptic_model::scene::{self, Scene};
use haptics_proto::v1::{ForceCommand, Vec3};
use tokio::sync::{mpsc, watch};
use tonic::Status;

use crate::config::ServerConfig;
use crate::error::ServerError;
use crate::servo::{
    self, Command, ForceOut, MonotonicClock, Pose, ServoCore, SessionShared, StatsSnapshot,
};

/// Largest scene text accepted, bytes.
pub const MAX_SCENE_TOML_BYTES: usize = 1 << 20;

/// The surface connectivity of a session at one topology version (shared by every frame until
/// the version changes; a viewer gets a keyframe with it then).
#[derive(Debug, Clone, PartialEq)]
pub struct Topology {
    /// [`haptic_model::body::SurfaceTopology::version`].
    pub version: u64,
    /// Surface triangles, three vertex indices each.
    pub triangles: Vec<u32>,
    /// Rest positions of the surface vertices, xyz, m.
    pub rest_positions_m: Vec<f32>,
    /// Prediction order of compact streams for these triangles (`None` if they are invalid).
    pub codec: Option<Arc<haptics_proto::delta::DeltaCodec>>,
}

/// A viewer frame built from a servo snapshot (shared by all viewers of a session).
#[derive(Debug)]
pub struct FrameData {
    /// Snapshot tick.
    pub tick: u64,
    /// Simulated time, s.
    pub sim_time_s: f64,
    /// The surface connectivity these positions belong to.
    pub topology: Arc<Topology>,
    /// Surface positions, xyz, m.
    pub positions_m: Vec<f32>,
    /// Probe position, m (NaN when no device).
    pub probe_m: [f64; 3],
    /// Contact force, N.
    pub force_n: [f64; 3],
    /// In contact.
    pub in_contact: bool,
    /// Largest surface displacement, m.
    pub max_displacement_m: f64,
    /// The reference keyframe of compact streams (`None` while no compact watcher exists).
    pub reference: Option<Arc<crate::stream::Reference>>,
    /// `positions_m` against `reference` at the default quantum (1 um), encoded; `None`
    /// without a reference. Empty when the positions are the reference.
    pub delta: Option<prost::bytes::Bytes>,
    /// Deltas at other quanta, computed on demand ([`FrameData::delta_for`]).
    pub other_deltas: Mutex<Vec<(u64, Option<prost::bytes::Bytes>)>>,
}

/// Sender half of a DeviceLink response stream.
pub type ForceSender = mpsc::Sender<Result<ForceCommand, Status>>;

/// One running session.
pub struct Session {
    /// Session id.
    pub id: String,
    /// Scene name.
    pub scene: String,
    /// Model family of the body (`"fem"`, ...).
    pub family: &'static str,
    /// Node count.
    pub nodes: u32,
    /// Element count (tetrahedra for the FEM).
    pub tetrahedra: u32,
    /// Sub-steps per tick.
    pub substeps: u32,
    /// Critical time step, s.
    pub critical_dt_s: f64,
    /// Probe radius, m.
    pub probe_radius_m: f64,
    /// Shared atomics.
    pub shared: Arc<SessionShared>,
    /// Counters and keyframe requests of the session's watchers ([`crate::stream`]).
    pub watcher_stats: Arc<crate::stream::WatcherStats>,
    /// Session clock zero.
    pub epoch: Instant,
    commands: Mutex<rtrb::Producer<Command>>,
    pose_input: Mutex<Option<triple_buffer::Input<Pose>>>,
    link: Arc<Mutex<Option<ForceSender>>>,
    stats: Mutex<triple_buffer::Output<StatsSnapshot>>,
    frames: watch::Receiver<Option<Arc<FrameData>>>,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

/// Microseconds since the UNIX epoch (cross-process timestamps for frame age and latency).
pub fn unix_time_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}

impl Session {
    /// Queues a validated command for the servo.
    ///
    /// # Errors
    /// [`ServerError::Exhausted`] when the ring is full.
    pub fn send(&self, cmd: Command) -> Result<(), ServerError> {
        let mut p = self
            .commands
            .lock()
            .map_err(|_| ServerError::Internal("command ring poisoned".into()))?;
        p.push(cmd)
            .map_err(|_| ServerError::Exhausted("too many commands queued for this session".into()))
    }

    /// Latest published statistics.
    pub fn stats(&self) -> StatsSnapshot {
        match self.stats.lock() {
            Ok(mut o) => *o.read(),
            Err(_) => StatsSnapshot::default(),
        }
    }

    /// Attaches a device stream: returns the pose input to publish into.
    ///
    /// # Errors
    /// [`ServerError::FailedPrecondition`] when a device is already connected.
    pub fn attach_device(
        &self,
        tx: ForceSender,
    ) -> Result<triple_buffer::Input<Pose>, ServerError> {
        let input = self
            .pose_input
            .lock()
            .map_err(|_| ServerError::Internal("pose slot poisoned".into()))?
            .take()
            .ok_or_else(|| {
                ServerError::FailedPrecondition(format!(
                    "session {} already has a device connected",
                    self.id
                ))
            })?;
        *self
            .link
            .lock()
            .map_err(|_| ServerError::Internal("link poisoned".into()))? = Some(tx);
        Ok(input)
    }

    /// Detaches the device stream and returns the pose input (publishing "disconnected").
    pub fn detach_device(&self, mut input: triple_buffer::Input<Pose>) {
        input.write(Pose {
            connected: false,
            ..Pose::default()
        });
        if let Ok(mut l) = self.link.lock() {
            // While stopping, keep the sender: `stop` clears it after the final zero force.
            if !self.shared.stop.load(Ordering::Acquire) {
                *l = None;
            }
        }
        if let Ok(mut slot) = self.pose_input.lock() {
            *slot = Some(input);
        }
    }

    /// Subscribes to viewer frames (counts as a watcher until the guard drops).
    pub fn watch(self: &Arc<Self>) -> (watch::Receiver<Option<Arc<FrameData>>>, WatcherGuard) {
        self.shared.watchers.fetch_add(1, Ordering::AcqRel);
        (self.frames.clone(), WatcherGuard(self.shared.clone()))
    }

    /// Stops the servo (it sends a zero force), joins its threads. Idempotent.
    pub fn stop(&self) {
        self.shared.stop.store(true, Ordering::Release);
        let threads: Vec<_> = self
            .threads
            .lock()
            .map(|mut t| t.drain(..).collect())
            .unwrap_or_default();
        for t in threads {
            let _ = t.join();
        }
        if let Ok(mut l) = self.link.lock() {
            *l = None;
        }
    }

    /// Milliseconds-resolution session clock now, µs.
    pub fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }
}

/// Decrements the watcher count when a viewer stream ends.
pub struct WatcherGuard(Arc<SessionShared>);

impl Drop for WatcherGuard {
    fn drop(&mut self) {
        self.0.watchers.fetch_sub(1, Ordering::AcqRel);
    }
}

/// All sessions of the daemon.
pub struct SessionManager {
    config: ServerConfig,
    sessions: Mutex<HashMap<String, Arc<Session>>>,
}

impl SessionManager {
    /// An empty manager.
    pub fn new(config: ServerConfig) -> Self {
        Self {
            config,
            sessions: Mutex::new(HashMap::new()),
        }
    }

    /// The daemon configuration.
    pub fn config(&self) -> &ServerConfig {
        &self.config
    }

    /// Looks a session up.
    ///
    /// # Errors
    /// [`ServerError::UnknownSession`].
    pub fn get(&self, id: &str) -> Result<Arc<Session>, ServerError> {
        self.sessions
            .lock()
            .map_err(|_| ServerError::Internal("session table poisoned".into()))?
            .get(id)
            .cloned()
            .ok_or_else(|| ServerError::UnknownSession(id.to_string()))
    }

    /// Ids of all sessions, sorted.
    pub fn ids(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .sessions
            .lock()
            .map(|s| s.keys().cloned().collect())
            .unwrap_or_default();
        v.sort();
        v
    }

    /// Loads a scene from a built-in name or scene text (blocking: meshing and the critical
    /// step analysis take up to a few hundred ms).
    ///
    /// # Errors
    /// [`ServerError::InvalidArgument`] for an empty request or oversized text;
    /// [`ServerError::Model`] for scene errors.
    pub fn load_scene(&self, name: &str, toml_text: &str) -> Result<Scene, ServerError> {
        if !toml_text.trim().is_empty() {
            if toml_text.len() > MAX_SCENE_TOML_BYTES {
                return Err(ServerError::InvalidArgument(format!(
                    "scene_toml is {} bytes; the limit is {MAX_SCENE_TOML_BYTES}",
                    toml_text.len()
                )));
            }
            return Ok(scene::parse_scene_toml(toml_text, &self.config.scene_dir)?);
        }
        if name.is_empty() {
            return Err(ServerError::InvalidArgument(
                "give a built-in scene name or scene_toml".into(),
            ));
        }
        Ok(scene::load_builtin(name)?)
    }

    /// Starts a session for `scene`: builds the simulation, starts its threads and frame task.
    /// Must be called inside a tokio runtime (it spawns the frame task).
    ///
    /// # Errors
    /// [`ServerError::Exhausted`] at the session limit; [`ServerError::Model`] when the
    /// simulation cannot be built (e.g. an unstable explicit configuration).
    pub fn start(&self, scene: &Scene) -> Result<Arc<Session>, ServerError> {
        self.check_capacity()?;
        self.start_body(haptic_model::build_body(scene)?)
    }

    /// Refuses a new session at the session limit.
    fn check_capacity(&self) -> Result<(), ServerError> {
        if self.sessions.lock().map(|s| s.len()).unwrap_or(0) >= self.config.max_sessions {
            return Err(ServerError::Exhausted(format!(
                "the server runs its limit of {} sessions",
                self.config.max_sessions
            )));
        }
        Ok(())
    }

    /// Starts a session for a body already built (any model family, or a test body): its servo
    /// thread, forwarder and frame task. Must be called inside a tokio runtime.
    ///
    /// # Errors
    /// [`ServerError::Exhausted`] at the session limit; [`ServerError::Internal`] when a thread
    /// cannot be spawned.
    pub fn start_body(
        &self,
        body: Box<dyn haptic_model::body::SoftBody>,
    ) -> Result<Arc<Session>, ServerError> {
        self.check_capacity()?;
        let info = body.info();
        let size = body.stats();
        let id = uuid::Uuid::new_v4().simple().to_string()[..12].to_string();
        let shared = Arc::new(SessionShared::default());
        let (ends, handles) = servo::channels(body.as_ref());
        let servo::ServoHandles {
            commands: cmd_tx,
            pose: pose_in,
            forces: mut force_rx,
            snapshot: snap_out,
            stats: stats_out,
        } = handles;
        let period_us = (info.tick_s * 1e6).round().max(1.0) as u64;
        let epoch = Instant::now();
        let link: Arc<Mutex<Option<ForceSender>>> = Arc::new(Mutex::new(None));

        // Forwarder: force ring -> the attached DeviceLink stream.
        let fwd_shared = shared.clone();
        let fwd_link = link.clone();
        let forwarder = std::thread::Builder::new()
            .name(format!("fwd-{id}"))
            .spawn(move || {
                loop {
                    std::thread::park_timeout(Duration::from_millis(5));
                    while let Ok(f) = force_rx.pop() {
                        let sender = fwd_link.lock().ok().and_then(|l| l.clone());
                        if let Some(tx) = sender {
                            let _ = tx.try_send(Ok(force_command(&f)));
                        }
                    }
                    if fwd_shared.finished.load(Ordering::Acquire) && force_rx.is_empty() {
                        break;
                    }
                }
            })
            .map_err(|e| ServerError::Internal(format!("spawning the forwarder: {e}")))?;
        let servo_cfg = self.config.servo.clone();
        let core = ServoCore::new(
            body,
            ends,
            shared.clone(),
            servo_cfg.snapshot_every_ticks,
            servo_cfg.stats_every_ticks,
        );
        let fwd_thread = forwarder.thread().clone();
        let servo_id = id.clone();
        let servo = std::thread::Builder::new()
            .name(format!("servo-{id}"))
            .spawn(move || {
                for w in servo::setup_realtime(&servo_cfg) {
                    tracing::warn!(session = %servo_id, "{w}");
                }
                servo::run_loop(core, MonotonicClock::new(epoch), period_us, fwd_thread);
            })
            .map_err(|e| ServerError::Internal(format!("spawning the servo thread: {e}")))?;

        // Frame task: servo snapshots -> shared viewer frames, only while someone watches.
        let (frame_tx, frame_rx) = watch::channel(None);
        let watcher_stats = Arc::new(crate::stream::WatcherStats::default());
        crate::stream::spawn_frame_task(
            snap_out,
            frame_tx,
            shared.clone(),
            watcher_stats.clone(),
            crate::stream::KeyframePolicy::default(),
        );

        let session = Arc::new(Session {
            id: id.clone(),
            scene: info.scene,
            family: info.family,
            nodes: size.nodes as u32,
            tetrahedra: size.elements as u32,
            substeps: info.substeps,
            critical_dt_s: if info.critical_dt_s.is_finite() {
                info.critical_dt_s
            } else {
                0.0
            },
            probe_radius_m: info.probe_radius_m,
            shared,
            watcher_stats,
            epoch,
            commands: Mutex::new(cmd_tx),
            pose_input: Mutex::new(Some(pose_in)),
            link,
            stats: Mutex::new(stats_out),
            frames: frame_rx,
            threads: Mutex::new(vec![servo, forwarder]),
        });
        self.sessions
            .lock()
            .map_err(|_| ServerError::Internal("session table poisoned".into()))?
            .insert(id, session.clone());
        Ok(session)
    }

    /// Stops and removes a session (blocking: joins its threads).
    ///
    /// # Errors
    /// [`ServerError::UnknownSession`].
    pub fn stop(&self, id: &str) -> Result<(), ServerError> {
        let s = self
            .sessions
            .lock()
            .map_err(|_| ServerError::Internal("session table poisoned".into()))?
            .remove(id)
            .ok_or_else(|| ServerError::UnknownSession(id.to_string()))?;
        s.stop();
        Ok(())
    }

    /// Stops every session (shutdown path).
    pub fn stop_all(&self) {
        let all: Vec<Arc<Session>> = self
            .sessions
            .lock()
            .map(|mut s| s.drain().map(|(_, v)| v).collect())
            .unwrap_or_default();
        for s in all {
            s.stop();
        }
    }
}

fn force_command(f: &ForceOut) -> ForceCommand {
    ForceCommand {
        seq: f.seq,
        force_n: Some(Vec3::from(f.force_n.to_array())),
        server_time_us: unix_time_us(),
        in_contact: f.in_contact,
        stiffness_n_per_m: f.stiffness_n_per_m.to_vec(),
        proxy_position_m: Some(Vec3::from(f.proxy_m.to_array())),
    }
}
