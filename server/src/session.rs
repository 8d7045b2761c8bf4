//! Sessions: a scene, its simulation on a servo thread, and the async-side ends of every
//! handoff. [`SessionManager`] owns all sessions of the daemon.
//!
//! Threads per session: the servo thread ([`crate::servo::run_loop`]), a forwarder thread that
//! drains the force ring into the attached DeviceLink stream (through [`crate::deadband`];
//! woken by the servo with `Thread::unpark`, which is wait-free), and a tokio task that turns servo snapshots into
//! viewer frames while someone watches.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use haptic_model::ModelError;
use haptic_model::scene::{self, Scene};
use haptics_proto::v1::ForceCommand;
use tokio::sync::{mpsc, watch};
use tonic::Status;

use crate::config::ServerConfig;
use crate::error::ServerError;
use crate::frame::{FrameData, WatcherGuard, WatcherStats};
use crate::servo::{
    self, Command, ForceOut, MonotonicClock, Pose, ServoCore, SessionShared, StatsSnapshot,
};
use crate::tool::NamedTool;

use crate::deadband::force_command;
pub use crate::deadband::{
    DEADBAND_FLOOR_N, DEADBAND_HEARTBEAT_US, DeadbandShared, force_deadband_passes,
};

/// Largest scene text accepted, bytes.
pub const MAX_SCENE_TOML_BYTES: usize = 1 << 20;

/// Hand speed the scene's force-rate limit assumes, m/s (devices.md S7: a wall hit at 1 m/s).
pub const REFERENCE_SPEED_M_PER_S: f64 = 1.0;

/// Application-level limits of a session, sent to the device bridge at connect time (response
/// headers of `DeviceLink.Connect`); the bridge applies the lower of these and its device's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkLimits {
    /// The scene's `probe.max_force_n`, N.
    pub max_force_n: f64,
    /// A force-rate limit on the scale of the scene's forces, N/s: the coupling stiffness
    /// times [`REFERENCE_SPEED_M_PER_S`] (300 N/s for the LV scenes, so a 5 N fault needs
    /// 17 ms to reach the hand instead of 5 ms at a device's 1 N/ms).
    pub max_force_rate_n_per_s: f64,
}

impl LinkLimits {
    /// The limits of `scene`.
    pub fn of_scene(scene: &Scene) -> Self {
        Self {
            max_force_n: scene.probe.max_force_n,
            max_force_rate_n_per_s: scene.probe.coupling_stiffness_n_per_m
                * REFERENCE_SPEED_M_PER_S,
        }
    }
}

/// Where a session's scene came from, as recorded for a restart (`StartSession`'s fields).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionRecord {
    /// Session id.
    pub id: String,
    /// Built-in scene name (empty when `scene_toml` is given).
    #[serde(default)]
    pub scene: String,
    /// Scene file text (empty for a built-in scene).
    #[serde(default)]
    pub scene_toml: String,
}

/// Sender half of a DeviceLink response stream.
pub type ForceSender = mpsc::Sender<Result<ForceCommand, Status>>;

/// One tool slot of a session (issue 50; [`crate::tool`]): the async-side end of its pose
/// buffer (taken while a stream drives it), its force stream, deadband, device, and its
/// sample counters. Shared by the stream task, the forwarder and the statistics.
pub struct ToolSlot {
    /// Slot index, 0-based.
    pub slot: usize,
    /// Tool id of the connected stream, or of the last one ("" = the default tool).
    tool_id: Mutex<String>,
    /// The force-stream deadband of this slot's stream and its counters.
    pub deadband: Arc<DeadbandShared>,
    /// The device on this slot as it introduced itself, and its limits.
    pub device: Arc<crate::device::DeviceShared>,
    /// Samples rejected (non-finite, absurd, another session's).
    pub rejected_samples: std::sync::atomic::AtomicU64,
    /// Samples dropped: `seq` not newer than the last accepted.
    pub out_of_order_samples: std::sync::atomic::AtomicU64,
    /// Samples dropped outside the declared workspace.
    pub out_of_workspace_samples: std::sync::atomic::AtomicU64,
    /// This slot's probe radius, m: its named tool's (`[[probe.tool]] radius_m`), else the
    /// scene's.
    pub probe_radius_m: f64,
    /// This slot's force limit, N, when its named tool has its own (`[[probe.tool]]
    /// max_force_n`; sent to its bridge when lower than the scene's).
    pub max_force_n: Option<f64>,
    pose_input: Mutex<Option<triple_buffer::Input<Pose>>>,
    link: Mutex<Option<ForceSender>>,
}

impl ToolSlot {
    fn new(
        slot: usize,
        pose_input: triple_buffer::Input<Pose>,
        probe_radius_m: f64,
        named: Option<&NamedTool>,
    ) -> Self {
        Self {
            slot,
            probe_radius_m: named.and_then(|n| n.radius_m).unwrap_or(probe_radius_m),
            max_force_n: named.and_then(|n| n.max_force_n),
            tool_id: Mutex::new(String::new()),
            deadband: Arc::default(),
            device: Arc::default(),
            rejected_samples: Default::default(),
            out_of_order_samples: Default::default(),
            out_of_workspace_samples: Default::default(),
            pose_input: Mutex::new(Some(pose_input)),
            link: Mutex::new(None),
        }
    }

    /// The tool id of the connected (or last) stream.
    pub fn tool_id(&self) -> String {
        self.tool_id.lock().map(|t| t.clone()).unwrap_or_default()
    }

    /// A stream drives this slot now.
    pub fn connected(&self) -> bool {
        self.pose_input.lock().is_ok_and(|p| p.is_none())
    }

    /// The id of the stream driving this slot, if one does.
    fn occupant(&self) -> Option<String> {
        self.connected().then(|| self.tool_id())
    }

    /// Sets this slot's force deadband (fraction, 0 = off; from the `haptics-force-deadband`
    /// request header); a value outside `[0, 1)` or not finite is 0.
    pub fn set_force_deadband(&self, k: f64) {
        let k = if k.is_finite() && (0.0..1.0).contains(&k) {
            k
        } else {
            0.0
        };
        self.deadband
            .fraction_bits
            .store(k.to_bits(), Ordering::Relaxed);
    }

    /// The force stream attached to this slot, if any.
    fn sender(&self) -> Option<ForceSender> {
        self.link.lock().ok().and_then(|l| l.clone())
    }
}

/// A device stream attached to a tool slot ([`Session::attach_tool`]).
pub struct ToolAttachment {
    /// The slot it drives.
    pub slot: usize,
    /// Its pose input: the stream task publishes each accepted sample here.
    pub pose: triple_buffer::Input<Pose>,
}

/// A reserved session slot ([`SessionManager::reserve_slot`]); released on drop unless a
/// session took it.
struct SlotReservation<'a> {
    manager: &'a SessionManager,
    taken: bool,
}

impl Drop for SlotReservation<'_> {
    fn drop(&mut self) {
        if !self.taken {
            self.manager.pending.fetch_sub(1, Ordering::AcqRel);
        }
    }
}

/// What a session's region cache on disk complained about: each complaint (a file refused, a
/// write that failed or did not fit) is logged as a warning naming the session when it
/// happens, on the region worker's thread, and the last one is kept for `GetStats`
/// (`region_cache_error`).
#[derive(Debug, Default)]
pub struct RegionCacheLog {
    last: Mutex<Option<String>>,
}

impl RegionCacheLog {
    /// The sink a body of session `id` reports to ([`haptic_model::BodyOptions`]).
    fn report_for(
        self: &Arc<Self>,
        id: &str,
    ) -> haptic_model::integrate::follow::RegionCacheReport {
        let log = Arc::clone(self);
        let id = id.to_owned();
        haptic_model::integrate::follow::RegionCacheReport(Arc::new(move |e: &str| {
            tracing::warn!(session = %id, "region cache: {e}");
            if let Ok(mut last) = log.last.lock() {
                *last = Some(e.to_owned());
            }
        }))
    }

    /// The last complaint, or `None`.
    pub fn last(&self) -> Option<String> {
        self.last.lock().ok().and_then(|l| l.clone())
    }
}

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
    /// Where the body takes point loads (`ApplyForce` outside it is refused before it is
    /// queued: the servo drops a load the body refuses, silently).
    pub point_loads: haptic_model::body::PointLoadZone,
    /// Shared atomics.
    pub shared: Arc<SessionShared>,
    /// Counters and keyframe requests of the session's watchers ([`crate::stream`]).
    pub watcher_stats: Arc<WatcherStats>,
    /// Session clock zero.
    pub epoch: Instant,
    /// The scene's limits for the device bridge (`None` for a body started without a scene).
    pub limits: Option<LinkLimits>,
    /// The region cache's last complaint about this session's files (`GetStats`).
    pub region_cache_log: Arc<RegionCacheLog>,
    /// The servo thread, unparked when a device sample arrives (device pacing).
    servo_thread: std::thread::Thread,
    /// Threads the session's tick has: its servo thread plus tick-pool workers, those lent
    /// out included ([`crate::cores`]; [`Self::threads_now`] says how many work).
    pub tick_threads: u32,
    /// The force-stream deadband of tool slot 0 and its counters (`tools[0].deadband`).
    pub deadband: Arc<DeadbandShared>,
    /// The device on tool slot 0 as it introduced itself, and its limits ([`crate::device`];
    /// `tools[0].device`).
    pub device: Arc<crate::device::DeviceShared>,
    /// The tool slots (issue 50): `SoftBody::max_tools()` of them, at least one.
    pub tools: Vec<Arc<ToolSlot>>,
    /// The ids of the tools the scene names and their slots (`SoftBody::tool_slot`).
    named_tools: Vec<(String, usize)>,
    /// Held while a stream chooses and takes its slot.
    attach_lock: Mutex<()>,
    commands: Mutex<rtrb::Producer<Command>>,
    stats: Mutex<triple_buffer::Output<StatsSnapshot>>,
    frames: watch::Receiver<Option<Arc<FrameData>>>,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
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

    /// Threads the tick uses now: as `stats` (the servo's last publication) says, or until
    /// the servo has published, the session's [`Self::tick_threads`].
    pub fn threads_now(&self, stats: &StatsSnapshot) -> u32 {
        if stats.threads > 0 {
            stats.threads
        } else {
            self.tick_threads
        }
    }

    /// Sets the force deadband of tool slot 0's stream (fraction, 0 = off; from the
    /// bridge's `haptics-force-deadband` request header).
    pub fn set_force_deadband(&self, k: f64) {
        self.tools[0].set_force_deadband(k);
    }

    /// Attaches a device stream of tool `tool_id` ("" = the default tool) to its slot
    /// ([`crate::tool::choose_slot`]): the slot and the pose input to publish into.
    ///
    /// # Errors
    /// [`ServerError::InvalidArgument`] for a bad tool id;
    /// [`ServerError::FailedPrecondition`] when that tool is already connected;
    /// [`ServerError::Exhausted`] when the session has no free slot for it.
    pub fn attach_tool(
        &self,
        tool_id: &str,
        tx: ForceSender,
    ) -> Result<ToolAttachment, ServerError> {
        crate::tool::check_tool_id(tool_id)?;
        let poisoned = |what: &str| ServerError::Internal(format!("{what} poisoned"));
        let _guard = self.attach_lock.lock().map_err(|_| poisoned("attach"))?;
        let occupied: Vec<Option<String>> = self.tools.iter().map(|t| t.occupant()).collect();
        let slot = crate::tool::choose_slot(&self.id, tool_id, &self.named_tools, &occupied)?;
        let tool = &self.tools[slot];
        let pose = tool
            .pose_input
            .lock()
            .map_err(|_| poisoned("pose slot"))?
            .take()
            .ok_or_else(|| {
                ServerError::Internal("a free tool slot without its pose input".into())
            })?;
        *tool.tool_id.lock().map_err(|_| poisoned("tool id"))? = tool_id.to_owned();
        *tool.link.lock().map_err(|_| poisoned("link"))? = Some(tx);
        Ok(ToolAttachment { slot, pose })
    }

    /// Attaches the default tool's device stream ([`Session::attach_tool`] with id ""):
    /// returns the pose input to publish into.
    ///
    /// # Errors
    /// As [`Session::attach_tool`]: [`ServerError::FailedPrecondition`] when the default tool
    /// is already connected.
    pub fn attach_device(
        &self,
        tx: ForceSender,
    ) -> Result<triple_buffer::Input<Pose>, ServerError> {
        self.attach_tool("", tx).map(|a| a.pose)
    }

    /// A device stream is attached (any tool).
    pub fn has_device(&self) -> bool {
        self.tools.iter().any(|t| t.connected())
    }

    /// The tool slots a stream drives now.
    pub fn connected_tools(&self) -> impl Iterator<Item = &Arc<ToolSlot>> {
        self.tools.iter().filter(|t| t.connected())
    }

    /// Detaches tool slot `slot`'s stream and returns its pose input (publishing
    /// "disconnected": the tool's contact is released, the others continue) and forgets its
    /// device.
    pub fn detach_tool(&self, slot: usize, mut input: triple_buffer::Input<Pose>) {
        let Some(tool) = self.tools.get(slot) else {
            return;
        };
        input.write(Pose {
            connected: false,
            ..Pose::default()
        });
        tool.device.detach();
        if let Ok(mut l) = tool.link.lock() {
            // While stopping, keep the sender: `stop` clears it after the final zero force.
            if !self.shared.stop.load(Ordering::Acquire) {
                *l = None;
            }
        }
        if let Ok(mut p) = tool.pose_input.lock() {
            *p = Some(input);
        }
    }

    /// Detaches the default tool's stream ([`Session::attach_device`]'s): the lowest
    /// connected slot of tool id "".
    pub fn detach_device(&self, input: triple_buffer::Input<Pose>) {
        let slot = self
            .tools
            .iter()
            .find(|t| t.occupant().as_deref() == Some(""))
            .map_or(0, |t| t.slot);
        self.detach_tool(slot, input);
    }

    /// Subscribes to viewer frames (counts as a watcher until the guard drops).
    pub fn watch(self: &Arc<Self>) -> (watch::Receiver<Option<Arc<FrameData>>>, WatcherGuard) {
        self.shared.watchers.fetch_add(1, Ordering::AcqRel);
        // The channel still holds the frame published when the last watcher left (the servo
        // publishes only while someone watches): a new watcher waits for the next one, which
        // the servo publishes now that the count is up, instead of seeing the stale surface.
        let mut frames = self.frames.clone();
        frames.mark_unchanged();
        (frames, WatcherGuard(self.shared.clone()))
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
        for tool in &self.tools {
            if let Ok(mut l) = tool.link.lock() {
                *l = None;
            }
        }
    }

    /// Wakes the servo thread (a device sample was published). Wait-free for the caller.
    pub fn wake_servo(&self) {
        self.servo_thread.unpark();
    }

    /// Milliseconds-resolution session clock now, µs.
    pub fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }
}

/// All sessions of the daemon.
pub struct SessionManager {
    config: ServerConfig,
    sessions: Mutex<HashMap<String, Arc<Session>>>,
    /// Sessions being built (their slot reserved under the `sessions` lock, so concurrent
    /// starts never exceed the limit).
    pending: std::sync::atomic::AtomicUsize,
    /// Random id of this daemon process, sent to device bridges so they notice a restart.
    instance: String,
    /// Sessions in the table, for the servo threads' [`servo::Yielding`].
    running: Arc<std::sync::atomic::AtomicUsize>,
    /// The cores the running sessions' ticks hold ([`crate::cores`]).
    cores: crate::cores::CoreBudget,
    /// `SCHED_FIFO` is permitted (tried once, at the first session start that needs to know).
    fifo_permitted: std::sync::OnceLock<bool>,
}

/// Refuses an offline reference (`[model] offline`: its tick is slower than the 1 kHz loop)
/// for a session, naming the key and quoting the scene's reason.
fn refuse_offline(scene: &Scene) -> Result<(), ModelError> {
    match &scene.offline {
        Some(reason) => Err(ModelError::field(
            "model.offline",
            format!(
                "scene `{}` is an offline reference, not run in the haptic loop: {reason}",
                scene.name
            ),
        )),
        None => Ok(()),
    }
}

impl SessionManager {
    /// An empty manager.
    pub fn new(config: ServerConfig) -> Self {
        Self {
            sessions: Mutex::new(HashMap::new()),
            pending: std::sync::atomic::AtomicUsize::new(0),
            instance: uuid::Uuid::new_v4().simple().to_string()[..12].to_string(),
            running: Arc::new(std::sync::atomic::AtomicUsize::new(0)),
            cores: crate::cores::CoreBudget::for_cpus(&config.servo.pinned_cpus()),
            fifo_permitted: std::sync::OnceLock::new(),
            config,
        }
    }

    /// The number of sessions in the table, kept up to date as they start and stop (the
    /// region cache's background fill pauses while it is not zero, [`crate::regions`]).
    pub fn running_sessions(&self) -> Arc<std::sync::atomic::AtomicUsize> {
        Arc::clone(&self.running)
    }

    /// Cores the running sessions' ticks hold now (servo threads and tick-pool workers), and the
    /// cores there are to share ([`crate::cores::CoreBudget`]).
    pub fn reserved_cores(&self) -> (usize, usize) {
        (self.cores.reserved(), self.cores.capacity())
    }

    /// `SCHED_FIFO` was asked for (`[servo] realtime`) and is refused to this process.
    fn fifo_refused(&self) -> bool {
        let servo = &self.config.servo;
        servo.realtime
            && !*self
                .fifo_permitted
                .get_or_init(|| servo::fifo_permitted(servo.priority))
    }

    /// Decides and reserves the threads of session `id`'s tick, creates its tick pool
    /// (`threads - 1` workers set up by [`servo::worker_start_hook`]) and hands it to `body`.
    /// A pool that cannot be created leaves the session on one thread (logged).
    fn tick_threads(
        &self,
        id: &str,
        body: &mut dyn haptic_model::body::SoftBody,
    ) -> (TickThreads, Option<Arc<haptic_model::pool::TickPool>>) {
        let servo_cfg = &self.config.servo;
        let wants = body.wants_threads();
        let mut reservation = self
            .cores
            .reserve(servo_cfg.threads, wants, self.fifo_refused());
        let cpus = servo_cfg.pinned_cpus();
        let cpu_at = |i: usize| (!cpus.is_empty()).then(|| cpus[i % cpus.len()]);
        let first = reservation.first();
        let workers = Arc::new(servo::WorkerThreads::default());
        let mut pool = None;
        if reservation.threads() > 1 {
            let worker_cpus = (1..reservation.threads())
                .filter_map(|k| cpu_at(first + k))
                .collect();
            let hook =
                servo::worker_start_hook(servo_cfg, worker_cpus, workers.clone(), id.to_owned());
            match haptic_model::pool::TickPool::new(reservation.threads() - 1, hook) {
                Ok(p) => {
                    body.set_tick_pool(p.clone());
                    pool = Some(p);
                }
                Err(e) => {
                    tracing::warn!(session = %id, "no tick pool ({e}); one thread");
                    reservation.shrink_to_one();
                }
            }
        }
        let plan = TickThreads {
            servo_cpu: cpu_at(first),
            workers,
            reservation,
            running: self.running.clone(),
        };
        (plan, pool)
    }

    /// This daemon process's instance id (new at every start).
    pub fn instance(&self) -> &str {
        &self.instance
    }

    /// Records how session `id` was started (`StartSession`'s `scene` / `scene_toml`) in the
    /// state directory, so that a restarted daemon restores it. Nothing without a state dir.
    ///
    /// # Errors
    /// [`ServerError::Internal`] when the record cannot be written.
    pub fn record(&self, id: &str, scene: &str, scene_toml: &str) -> Result<(), ServerError> {
        let Some(dir) = &self.config.state_dir else {
            return Ok(());
        };
        let rec = SessionRecord {
            id: id.to_owned(),
            scene: scene.to_owned(),
            scene_toml: scene_toml.to_owned(),
        };
        let text = toml::to_string(&rec)
            .map_err(|e| ServerError::Internal(format!("session record: {e}")))?;
        std::fs::create_dir_all(dir)
            .and_then(|()| std::fs::write(dir.join(format!("{id}.toml")), text))
            .map_err(|e| {
                ServerError::Internal(format!(
                    "writing the session record in {}: {e}",
                    dir.display()
                ))
            })
    }

    /// Restores the sessions recorded in the state directory (same ids, scenes rebuilt from
    /// rest: the simulation state itself is not kept). Returns one line per record (restored or
    /// why not); a record that cannot be restored is removed. Must be called inside a tokio
    /// runtime (blocking: each scene is built).
    pub fn restore(&self) -> Vec<String> {
        let Some(dir) = self.config.state_dir.clone() else {
            return Vec::new();
        };
        let Ok(entries) = std::fs::read_dir(&dir) else {
            return Vec::new();
        };
        let mut paths: Vec<_> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "toml"))
            .collect();
        paths.sort();
        let mut out = Vec::new();
        for path in paths {
            let outcome = std::fs::read_to_string(&path)
                .map_err(|e| e.to_string())
                .and_then(|t| toml::from_str::<SessionRecord>(&t).map_err(|e| e.to_string()))
                .and_then(|rec| {
                    let scene = self
                        .load_scene(&rec.scene, &rec.scene_toml)
                        .map_err(|e| e.to_string())?;
                    refuse_offline(&scene).map_err(|e| e.to_string())?;
                    let slot = self.reserve_slot().map_err(|e| e.to_string())?;
                    let log = Arc::new(RegionCacheLog::default());
                    let body = haptic_model::build_body_with_options(
                        &scene,
                        &self.body_options(&rec.id, &log),
                        &mut |_, _| {},
                    )
                    .map_err(|e| e.to_string())?;
                    let names = crate::tool::scene_tools(&scene);
                    let limits = Some(LinkLimits::of_scene(&scene));
                    self.start_in_slot(slot, &rec.id, body, limits, &names, log)
                        .map_err(|e| e.to_string())?;
                    Ok(rec)
                });
            match outcome {
                Ok(rec) => out.push(format!("restored session {} (scene {:?})", rec.id, {
                    if rec.scene.is_empty() {
                        "from text"
                    } else {
                        rec.scene.as_str()
                    }
                })),
                Err(e) => {
                    let _ = std::fs::remove_file(&path);
                    out.push(format!(
                        "could not restore {}: {e}; record removed",
                        path.display()
                    ));
                }
            }
        }
        out
    }

    /// The daemon configuration.
    pub fn config(&self) -> &ServerConfig {
        &self.config
    }

    /// What this daemon gives every body beside its scene: the region cache's directory, and
    /// where its complaints go for the session `id` (`log`).
    fn body_options(&self, id: &str, log: &Arc<RegionCacheLog>) -> haptic_model::BodyOptions {
        haptic_model::BodyOptions {
            region_cache: self.config.region_cache.clone(),
            region_cache_report: self
                .config
                .region_cache
                .as_ref()
                .map(|_| log.report_for(id)),
            region_cache_fill_only: false,
        }
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
            // Files the text names must be allowed ones (issue 16) before the model opens any.
            crate::confine::FileRoots::new(
                self.config.scene_dir.as_deref(),
                &self.config.data_dirs,
                self.config.max_file_bytes,
            )
            .check_scene(toml_text)?;
            crate::confine::FileRoots::check_generated_size(toml_text, self.config.max_elements)?;
            // Without a scene directory every allowed path is absolute (checked above).
            let base = self
                .config
                .scene_dir
                .as_deref()
                .unwrap_or(std::path::Path::new("/"));
            let scene = scene::parse_scene_toml(toml_text, base)?;
            // Tetrahedra, or the triangles of a mass-spring surface.
            let triangles: usize = scene.mesh.surfaces.iter().map(|g| g.triangles.len()).sum();
            let elements = scene.mesh.tet_count().max(triangles);
            crate::confine::check_counts(
                scene.mesh.node_count(),
                elements,
                self.config.max_nodes,
                self.config.max_elements,
            )?;
            if let Some(h) = &scene.hybrid {
                crate::confine::check_particles(
                    scene.mesh.volume(),
                    h.params.meshfree.spacing_m,
                    self.config.max_particles,
                )?;
            }
            return Ok(scene);
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
    /// simulation cannot be built (e.g. an unstable explicit configuration), or naming
    /// `model.offline` with the scene's reason for an offline reference (its tick is slower
    /// than the 1 kHz loop).
    pub fn start(&self, scene: &Scene) -> Result<Arc<Session>, ServerError> {
        self.start_with_tools(scene, &[])
    }

    /// [`SessionManager::start`] for a scene that names the tools `tool_names`
    /// ([`crate::tool::scene_tools`]): each takes its own slot and parameters.
    ///
    /// # Errors
    /// As [`SessionManager::start`].
    pub fn start_with_tools(
        &self,
        scene: &Scene,
        tool_names: &[NamedTool],
    ) -> Result<Arc<Session>, ServerError> {
        refuse_offline(scene)?;
        // The slot is taken before the (possibly long) build, so concurrent starts cannot all
        // pass a check and then exceed the limit.
        let slot = self.reserve_slot()?;
        let id = uuid::Uuid::new_v4().simple().to_string()[..12].to_string();
        // Families that preprocess (the hybrid model) report their stages; logged here, off
        // the servo thread.
        let name = scene.name.clone();
        let log = Arc::new(RegionCacheLog::default());
        let body = haptic_model::build_body_with_options(
            scene,
            &self.body_options(&id, &log),
            &mut |stage, fraction| tracing::info!(scene = %name, "preprocessing {:3.0} %: {stage}", 100.0 * fraction),
        )?;
        self.start_in_slot(
            slot,
            &id,
            body,
            Some(LinkLimits::of_scene(scene)),
            tool_names,
            log,
        )
    }

    /// Reserves a session slot: running plus pending sessions stay at most `max_sessions`
    /// (checked and counted under the session table's lock). The slot is released when the
    /// returned guard drops unless a session took it.
    ///
    /// # Errors
    /// [`ServerError::Exhausted`] at the limit.
    fn reserve_slot(&self) -> Result<SlotReservation<'_>, ServerError> {
        let sessions = self
            .sessions
            .lock()
            .map_err(|_| ServerError::Internal("session table poisoned".into()))?;
        if sessions.len() + self.pending.load(Ordering::Acquire) >= self.config.max_sessions {
            return Err(ServerError::Exhausted(format!(
                "the server runs its limit of {} sessions",
                self.config.max_sessions
            )));
        }
        self.pending.fetch_add(1, Ordering::AcqRel);
        Ok(SlotReservation {
            manager: self,
            taken: false,
        })
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
        let id = uuid::Uuid::new_v4().simple().to_string()[..12].to_string();
        self.start_body_as(&id, body, None)
    }

    /// [`SessionManager::start_body`] with a given session id (a restored session keeps its
    /// id) and the limits sent to device bridges.
    ///
    /// # Errors
    /// As [`SessionManager::start_body`]; [`ServerError::FailedPrecondition`] when the id is in
    /// use.
    pub fn start_body_as(
        &self,
        id: &str,
        body: Box<dyn haptic_model::body::SoftBody>,
        limits: Option<LinkLimits>,
    ) -> Result<Arc<Session>, ServerError> {
        let slot = self.reserve_slot()?;
        self.start_in_slot(slot, id, body, limits, &[], Arc::default())
    }

    /// [`SessionManager::start_body`] for a body whose tools `tool_names` are named (each
    /// takes the slot `SoftBody::tool_slot` gives it; other tools take the free slots left).
    ///
    /// # Errors
    /// As [`SessionManager::start_body`].
    pub fn start_body_with_tools(
        &self,
        body: Box<dyn haptic_model::body::SoftBody>,
        tool_names: &[NamedTool],
    ) -> Result<Arc<Session>, ServerError> {
        let id = uuid::Uuid::new_v4().simple().to_string()[..12].to_string();
        let slot = self.reserve_slot()?;
        self.start_in_slot(slot, &id, body, None, tool_names, Arc::default())
    }

    /// [`SessionManager::start_body_as`] in a reserved slot, with the tool names of its scene.
    fn start_in_slot(
        &self,
        slot: SlotReservation<'_>,
        id: &str,
        mut body: Box<dyn haptic_model::body::SoftBody>,
        limits: Option<LinkLimits>,
        tool_names: &[NamedTool],
        region_cache_log: Arc<RegionCacheLog>,
    ) -> Result<Arc<Session>, ServerError> {
        if self.get(id).is_ok() {
            return Err(ServerError::FailedPrecondition(format!(
                "session {id} exists already"
            )));
        }
        let id = id.to_owned();
        let info = body.info();
        let size = body.stats();
        let shared = Arc::new(SessionShared::default());
        let (ends, handles, more_tools) = servo::tool_channels(body.as_ref());
        let named_tools = named_tool_slots(body.as_ref(), tool_names, ends.tools.len());
        let servo::ServoHandles {
            commands: cmd_tx,
            pose: pose_in,
            forces: force_rx,
            snapshot: snap_out,
            stats: stats_out,
        } = handles;
        let period_us = (info.tick_s * 1e6).round().max(1.0) as u64;
        let epoch = Instant::now();
        let first = servo::ToolHandles {
            pose: pose_in,
            forces: force_rx,
        };
        let (rings, tools, named_tools) =
            tool_slots(first, more_tools, info.probe_radius_m, named_tools);

        // Forwarder: each tool's force ring -> its DeviceLink stream (through its deadband).
        let forwarder = spawn_forwarder(&id, rings, shared.clone(), tools.clone())?;
        let servo_cfg = self.config.servo.clone();
        let (plan, pool) = self.tick_threads(&id, body.as_mut());
        let threads = plan.reservation.threads();
        let core = servo_core(&servo_cfg, body, ends, shared.clone(), period_us)
            .with_tick_pool(pool, plan.reservation.share());
        let servo = spawn_servo(
            &id,
            servo_cfg,
            core,
            epoch,
            period_us,
            forwarder.thread().clone(),
            plan,
        )?;

        // Frame task: servo snapshots -> shared viewer frames, only while someone watches.
        let (frame_tx, frame_rx) = watch::channel(None);
        let watcher_stats = Arc::new(WatcherStats::default());
        crate::stream::spawn_frame_task(
            snap_out,
            frame_tx,
            shared.clone(),
            watcher_stats.clone(),
            crate::stream::KeyframePolicy::default(),
            tool_ids(&tools),
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
            point_loads: info.point_loads,
            shared,
            watcher_stats,
            epoch,
            limits,
            region_cache_log,
            tick_threads: threads as u32,
            servo_thread: servo.thread().clone(),
            deadband: tools[0].deadband.clone(),
            device: tools[0].device.clone(),
            tools,
            named_tools,
            attach_lock: Mutex::new(()),
            commands: Mutex::new(cmd_tx),
            stats: Mutex::new(stats_out),
            frames: frame_rx,
            threads: Mutex::new(vec![servo, forwarder]),
        });
        self.insert_session(slot, id, session.clone())?;
        Ok(session)
    }

    /// Puts a started session in the table; its slot's reservation ends under the same lock.
    fn insert_session(
        &self,
        mut slot: SlotReservation<'_>,
        id: String,
        session: Arc<Session>,
    ) -> Result<(), ServerError> {
        let mut sessions = self
            .sessions
            .lock()
            .map_err(|_| ServerError::Internal("session table poisoned".into()))?;
        sessions.insert(id, session);
        self.running.store(sessions.len(), Ordering::Relaxed);
        // The session now counts in the table: its reservation ends under the same lock.
        slot.taken = true;
        self.pending.fetch_sub(1, Ordering::AcqRel);
        Ok(())
    }

    /// Stops and removes a session (blocking: joins its threads).
    ///
    /// # Errors
    /// [`ServerError::UnknownSession`].
    pub fn stop(&self, id: &str) -> Result<(), ServerError> {
        let s = {
            let mut sessions = self
                .sessions
                .lock()
                .map_err(|_| ServerError::Internal("session table poisoned".into()))?;
            let s = sessions
                .remove(id)
                .ok_or_else(|| ServerError::UnknownSession(id.to_string()))?;
            self.running.store(sessions.len(), Ordering::Relaxed);
            s
        };
        s.stop();
        if let Some(dir) = &self.config.state_dir {
            // A stopped session is not restored (a missing record is fine).
            let _ = std::fs::remove_file(dir.join(format!("{id}.toml")));
        }
        Ok(())
    }

    /// Stops every session (shutdown path).
    pub fn stop_all(&self) {
        let all: Vec<Arc<Session>> = self
            .sessions
            .lock()
            .map(|mut s| s.drain().map(|(_, v)| v).collect())
            .unwrap_or_default();
        self.running.store(0, Ordering::Relaxed);
        for s in all {
            s.stop();
        }
    }
}
/// The servo core of a body as the daemon's servo configuration asks, for a tick of
/// `period_us`.
fn servo_core(
    servo_cfg: &crate::config::ServoConfig,
    body: Box<dyn haptic_model::body::SoftBody>,
    ends: servo::ServoEnds,
    shared: Arc<SessionShared>,
    period_us: u64,
) -> ServoCore {
    let core = ServoCore::new(
        body,
        ends,
        shared,
        servo_cfg.snapshot_every_ticks,
        servo_cfg.stats_every_ticks,
    )
    .with_device_silence_us(u64::from(servo_cfg.device_silence_ms) * 1000);
    // Overrunning: a whole second below the fraction of the nominal rate.
    let min_rate_hz = servo_cfg.min_rate_fraction * 1e6 / period_us as f64;
    match servo_cfg.overrun_policy {
        crate::config::OverrunPolicy::Report => core.with_overrun_limit(min_rate_hz, 1_000_000),
        crate::config::OverrunPolicy::Degrade => core.with_overrun_degrade(min_rate_hz, 1_000_000),
    }
}

/// Where a session's tick runs ([`SessionManager::start_body_as`]): the servo's CPU, the pool
/// workers' thread ids, the cores reserved, and the daemon's running-session count (for
/// [`servo::Yielding`]).
struct TickThreads {
    servo_cpu: Option<usize>,
    workers: Arc<servo::WorkerThreads>,
    reservation: crate::cores::CoreReservation,
    running: Arc<std::sync::atomic::AtomicUsize>,
}

/// Spawns the servo thread of session `id`: real-time set-up (its warnings logged here, before
/// the loop), then the loop the configuration's pacing names until the session stops. The
/// loop's [`servo::Yielding`] demotes the pool's workers with the servo and holds the session's
/// core reservation, given back when the loop ends or the session is quarantined.
fn spawn_servo(
    id: &str,
    servo_cfg: crate::config::ServoConfig,
    core: ServoCore,
    epoch: Instant,
    period_us: u64,
    fwd_thread: std::thread::Thread,
    plan: TickThreads,
) -> Result<std::thread::JoinHandle<()>, ServerError> {
    let servo_id = id.to_owned();
    let pacing = servo_cfg.pacing;
    std::thread::Builder::new()
        .name(format!("servo-{id}"))
        .spawn(move || {
            for w in servo::setup_realtime_on(&servo_cfg, plan.servo_cpu) {
                tracing::warn!(session = %servo_id, "{w}");
            }
            let clock = MonotonicClock::new(epoch);
            let yielding = servo::Yielding::new(servo_cfg.yield_when_overrunning, plan.running)
                .with_workers(plan.workers)
                .holding(plan.reservation);
            match pacing {
                crate::config::Pacing::Device => {
                    servo::run_loop_device_paced(core, clock, period_us, fwd_thread, yielding)
                }
                crate::config::Pacing::Clock => {
                    servo::run_loop(core, clock, period_us, fwd_thread, yielding)
                }
            }
        })
        .map_err(|e| ServerError::Internal(format!("spawning the servo thread: {e}")))
}

/// The tool slots of a session from the async ends of its slots (`first`, then `more`), the
/// scene's probe radius (m) and the named tools' slots: each slot's force ring (for the
/// forwarder), the slots, and the named tools' ids and slots.
#[allow(clippy::type_complexity)]
fn tool_slots(
    first: servo::ToolHandles,
    more: Vec<servo::ToolHandles>,
    probe_radius_m: f64,
    named: Vec<(NamedTool, usize)>,
) -> (
    Vec<rtrb::Consumer<ForceOut>>,
    Vec<Arc<ToolSlot>>,
    Vec<(String, usize)>,
) {
    let named_in = |k: usize| named.iter().find(|(_, s)| *s == k).map(|(n, _)| n);
    let (mut rings, mut tools) = (Vec::new(), Vec::new());
    for (k, h) in std::iter::once(first).chain(more).enumerate() {
        rings.push(h.forces);
        tools.push(Arc::new(ToolSlot::new(
            k,
            h.pose,
            probe_radius_m,
            named_in(k),
        )));
    }
    let ids = named.into_iter().map(|(n, k)| (n.id, k)).collect();
    (rings, tools, ids)
}

/// Names the tool slots `tools` for the frame task, with their probe radii
/// ([`crate::stream::ToolIds`]).
fn tool_ids(tools: &[Arc<ToolSlot>]) -> crate::stream::ToolIds {
    let tools = tools.to_vec();
    Arc::new(move |k| {
        tools
            .get(k)
            .map_or((String::new(), 0.0), |t| (t.tool_id(), t.probe_radius_m))
    })
}

/// The slots `body` gives the named tools `named` (those within its `slots`), as (tool, slot).
fn named_tool_slots(
    body: &dyn haptic_model::body::SoftBody,
    named: &[NamedTool],
    slots: usize,
) -> Vec<(NamedTool, usize)> {
    named
        .iter()
        .filter_map(|n| {
            body.tool_slot(&n.id)
                .filter(|&k| k < slots)
                .map(|k| (n.clone(), k))
        })
        .collect()
}

/// Spawns the forwarder thread of session `id`: drains each tool slot's force ring (`rings[k]`
/// for `tools[k]`) into that slot's DeviceLink stream through its deadband and its device's
/// limits, until the servo has finished and the rings are empty.
fn spawn_forwarder(
    id: &str,
    mut rings: Vec<rtrb::Consumer<ForceOut>>,
    fwd_shared: Arc<SessionShared>,
    tools: Vec<Arc<ToolSlot>>,
) -> Result<std::thread::JoinHandle<()>, ServerError> {
    std::thread::Builder::new()
        .name(format!("fwd-{id}"))
        .spawn(move || {
            let mut last: Vec<Option<(ForceOut, Instant)>> = vec![None; tools.len()];
            loop {
                std::thread::park_timeout(Duration::from_millis(5));
                for ((ring, tool), last) in rings.iter_mut().zip(&tools).zip(&mut last) {
                    forward_tool(ring, tool, last, &fwd_shared);
                }
                if fwd_shared.finished.load(Ordering::Acquire) && rings.iter().all(|r| r.is_empty())
                {
                    break;
                }
            }
        })
        .map_err(|e| ServerError::Internal(format!("spawning the forwarder: {e}")))
}

/// Drains one tool's force ring into its stream (the forwarder's work for one slot): `last` is
/// the last command sent and when, for the deadband.
fn forward_tool(
    ring: &mut rtrb::Consumer<ForceOut>,
    tool: &ToolSlot,
    last: &mut Option<(ForceOut, Instant)>,
    shared: &SessionShared,
) {
    while let Ok(f) = ring.pop() {
        let k = f64::from_bits(tool.deadband.fraction_bits.load(Ordering::Relaxed));
        let finishing = shared.stop.load(Ordering::Acquire);
        let since = last.map_or(u64::MAX, |(_, t)| t.elapsed().as_micros() as u64);
        if !finishing && !force_deadband_passes(k, last.as_ref().map(|(l, _)| l), since, &f) {
            tool.deadband.suppressed.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        if let Some(tx) = tool.sender() {
            let limits = tool.device.limits();
            if tx.try_send(Ok(force_command(&f, limits))).is_ok() {
                tool.deadband.sent.fetch_add(1, Ordering::Relaxed);
            }
            *last = Some((f, Instant::now()));
        } else {
            *last = None;
        }
    }
}
