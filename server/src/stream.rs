//! Surface streams: the frame task that turns servo snapshots into shared viewer frames, and one
//! task per `SurfaceStream.Watch` that samples them at the watcher's rate.
//!
//! - **Shared work, once per snapshot.** The frame task ([`spawn_frame_task`]) copies the
//!   snapshot into an `Arc<FrameData>` (a `tokio::sync::watch` slot: latest only) and, while a
//!   compact watcher exists, encodes the positions once as quantized deltas against the
//!   session's current reference keyframe ([`haptics_proto::delta`], 1 um). Every compact
//!   watcher sends those same bytes (`bytes::Bytes`, reference counted).
//! - **Reference keyframes** are renewed on a topology change, when a delta is not
//!   representable, every [`KeyframePolicy::max_interval_s`], and when the surface has settled
//!   in a new shape, so that a fresh keyframe pays for itself within
//!   [`KeyframePolicy::payback_frames`] frames ([`KeyframePolicy::should_renew`]). A renewal
//!   is chained where it can be: the new reference is the old one plus a delta, and a watcher
//!   that has the old one gets only that delta (`base_keyframe_id`, `reference_delta`), not
//!   float positions.
//! - **Each watcher** ([`spawn_watch`]) has its own rate, its own id (for `RequestKeyframe`)
//!   and a queue of [`WATCH_QUEUE_FRAMES`] frames: when the queue is full at a due frame, that
//!   frame is dropped and counted (a slow watcher never queues without bound and never slows
//!   the others or the servo). A keyframe that could not be queued is retried at the next due
//!   frame, and a late joiner's first frame is a keyframe. Counters live in [`WatcherStats`]
//!   (`GetStats`: watchers, frames sent and dropped, bytes sent and queued).
//!
//! Neighbours: [`crate::session`] owns the handoffs and calls [`spawn_frame_task`];
//! [`crate::service`] validates `WatchRequest`s with [`WatchParams::from_request`]. Nothing
//! here runs on the servo thread.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use haptics_proto::delta::{self, DEFAULT_QUANTUM_M, DeltaCodec};
use haptics_proto::v1::{AppliedForce, SurfaceEncoding, SurfaceFrame, Vec3, WatchRequest};
use prost::Message;
use prost::bytes::Bytes;
use tokio::sync::{mpsc, watch};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;

use crate::error::ServerError;
use crate::frame::{FrameData, Reference, Topology, WatcherGuard, WatcherStats, unix_time_us};
use crate::servo::{SessionShared, Snapshot};

/// Default watcher frame rate, Hz.
pub const DEFAULT_RATE_HZ: f64 = 30.0;
/// Smallest watcher frame rate, Hz (0 in a request means the default).
pub const MIN_RATE_HZ: f64 = 0.1;
/// Largest watcher frame rate, Hz (higher requests are clamped).
pub const MAX_RATE_HZ: f64 = 120.0;
/// Frames one watcher may have queued for its transport; a due frame beyond it is dropped.
pub const WATCH_QUEUE_FRAMES: usize = 2;

/// How one watcher wants its frames, validated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WatchParams {
    /// Frames per second, Hz, in `MIN_RATE_HZ..=MAX_RATE_HZ`.
    pub rate_hz: f64,
    /// `None`: full float positions in every frame; `Some(q)`: deltas in steps of `q` m.
    pub quantum_m: Option<f64>,
}

impl WatchParams {
    /// Validates a request: rate 0 (default, 30 Hz) or 0.1 Hz and more (clamped to 120 Hz),
    /// a known encoding, and for DELTA a quantum of 0 (1 um) or 1e-8 ..= 1e-3 m.
    ///
    /// # Errors
    /// [`ServerError::InvalidArgument`] naming the field.
    pub fn from_request(r: &WatchRequest) -> Result<Self, ServerError> {
        let rate = r.max_rate_hz;
        if !rate.is_finite() || rate < 0.0 || (rate > 0.0 && rate < MIN_RATE_HZ) {
            return Err(ServerError::InvalidArgument(format!(
                "max_rate_hz = {rate}: give 0 (server default, {DEFAULT_RATE_HZ} Hz) or a rate \
                 of at least {MIN_RATE_HZ} Hz"
            )));
        }
        let rate_hz = if rate == 0.0 {
            DEFAULT_RATE_HZ
        } else {
            rate.min(MAX_RATE_HZ)
        };
        let encoding = SurfaceEncoding::try_from(r.encoding).map_err(|_| {
            ServerError::InvalidArgument(format!("encoding = {} is not known", r.encoding))
        })?;
        let quantum_m = match encoding {
            SurfaceEncoding::Full => None,
            SurfaceEncoding::Delta if r.quantum_m == 0.0 => Some(DEFAULT_QUANTUM_M),
            SurfaceEncoding::Delta => Some(
                delta::check_quantum(r.quantum_m)
                    .map_err(|e| ServerError::InvalidArgument(format!("quantum_m: {e}")))?,
            ),
        };
        Ok(Self { rate_hz, quantum_m })
    }
}

/// When the frame task renews the reference keyframe of compact streams.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframePolicy {
    /// Never renew more often than this, s (bounds keyframe bursts during continuous motion).
    pub min_interval_s: f64,
    /// Always renew after this long, s (periodic keyframes).
    pub max_interval_s: f64,
    /// Renew when `(delta - step) * payback_frames > keyframe`, where `delta` is the encoded
    /// size against the reference, `step` against the previous snapshot and `keyframe` what
    /// the renewal costs (a chained one: about `delta`): the surface is in a shape far from
    /// the reference.
    pub payback_frames: f64,
}

impl Default for KeyframePolicy {
    fn default() -> Self {
        Self {
            min_interval_s: 0.5,
            max_interval_s: 10.0,
            payback_frames: 20.0,
        }
    }
}

impl KeyframePolicy {
    /// Whether to renew the reference now. Sizes in bytes, `since_s` since the last renewal.
    pub fn should_renew(
        &self,
        since_s: f64,
        delta_bytes: usize,
        step_bytes: usize,
        keyframe_bytes: usize,
    ) -> bool {
        if since_s >= self.max_interval_s {
            return true;
        }
        since_s >= self.min_interval_s
            && (delta_bytes.saturating_sub(step_bytes)) as f64 * self.payback_frames
                > keyframe_bytes as f64
    }
}

/// Spawns the frame task of a session: every 10 ms, while someone watches and the servo
/// published a new snapshot, publish a shared [`FrameData`] (with deltas while compact watchers
/// exist). Ends when the session stops.
pub fn spawn_frame_task(
    mut snap_out: triple_buffer::Output<Snapshot>,
    frame_tx: watch::Sender<Option<Arc<FrameData>>>,
    shared: Arc<SessionShared>,
    stats: Arc<WatcherStats>,
    policy: KeyframePolicy,
    tool_ids: ToolIds,
) {
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(10));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut frames = FrameBuilder::new(stats, policy);
        loop {
            tick.tick().await;
            if shared.finished.load(Ordering::Acquire) || shared.stop.load(Ordering::Acquire) {
                break;
            }
            if shared.watchers.load(Ordering::Acquire) == 0 || !snap_out.update() {
                continue;
            }
            let mut frame = frames.frame(snap_out.output_buffer());
            frame.tools = tool_probes(snap_out.output_buffer(), &tool_ids);
            if frame_tx.send(Some(Arc::new(frame))).is_err() {
                break; // no receiver left (the session was dropped)
            }
        }
    });
}

/// The tool id and probe radius (m) of a session's tool slot (for frames: the frame task does
/// not know sessions).
pub type ToolIds = Arc<dyn Fn(usize) -> (String, f64) + Send + Sync>;

/// The probes of the tool slots of `s` with a device, in slot order, named by `tool_ids`.
fn tool_probes(s: &Snapshot, tool_ids: &ToolIds) -> Vec<haptics_proto::v1::ToolProbe> {
    s.tools[..s.tool_count.min(s.tools.len())]
        .iter()
        .enumerate()
        .filter(|(_, t)| t.connected)
        .map(|(k, t)| {
            let (tool_id, probe_radius_m) = tool_ids(k);
            haptics_proto::v1::ToolProbe {
                tool_id,
                slot: k as u32,
                probe_position_m: Some(Vec3::from(t.probe_m.to_array())),
                contact_force_n: Some(Vec3::from(t.force_n.to_array())),
                in_contact: t.in_contact,
                probe_radius_m,
            }
        })
        .collect()
}

/// What the frame task carries from frame to frame: the topology, the delta reference and
/// when it was renewed, the last positions, and the encoders' buffers.
struct FrameBuilder {
    stats: Arc<WatcherStats>,
    policy: KeyframePolicy,
    topology: Option<Arc<Topology>>,
    reference: Option<Arc<Reference>>,
    renewed_at: tokio::time::Instant,
    previous: Vec<f32>,
    next_id: u64,
    buf: Vec<u8>,
    step_buf: Vec<u8>,
}

impl FrameBuilder {
    fn new(stats: Arc<WatcherStats>, policy: KeyframePolicy) -> Self {
        Self {
            stats,
            policy,
            topology: None,
            reference: None,
            renewed_at: tokio::time::Instant::now(),
            previous: Vec::new(),
            next_id: 1,
            buf: Vec::new(),
            step_buf: Vec::new(),
        }
    }

    /// The frame of snapshot `s`: its topology (shared while its version holds), the delta
    /// against the reference while compact watchers exist, the state.
    fn frame(&mut self, s: &Snapshot) -> FrameData {
        let topology = self.topology_of(s);
        let delta = if self.stats.delta_watchers.load(Ordering::Acquire) == 0 {
            self.reference = None;
            None
        } else if let Some(codec) = topology.codec.clone() {
            self.delta(s, &topology, &codec)
        } else {
            None
        };
        FrameData {
            tick: s.tick,
            sim_time_s: s.sim_time_s,
            topology,
            positions_m: s.positions_m.clone(),
            probe_m: s.probe_m.to_array(),
            force_n: s.force_n.to_array(),
            in_contact: s.in_contact,
            max_displacement_m: s.max_displacement_m,
            applied_forces: s.applied[..s.applied_len.min(s.applied.len())]
                .iter()
                .map(|a| AppliedForce {
                    index: a.index,
                    point_m: Some(Vec3::from(a.point_m.to_array())),
                    force_n: Some(Vec3::from(a.force_n.to_array())),
                    start_sim_time_s: a.start_sim_time_s,
                    duration_s: a.duration_s,
                })
                .collect(),
            applied_forces_total: s.applied_total,
            tools: Vec::new(),
            reference: self.reference.clone(),
            delta,
            other_deltas: Mutex::new(Vec::new()),
        }
    }

    /// The topology of `s`: the current one while its version holds, else a new one (and the
    /// watchers' queue limit for it).
    fn topology_of(&mut self, s: &Snapshot) -> Arc<Topology> {
        match &self.topology {
            Some(t) if t.version == s.topology_version => t.clone(),
            _ => {
                let n = s.rest_positions_m.len() / 3;
                let t = Arc::new(Topology {
                    version: s.topology_version,
                    triangles: s.triangles.clone(),
                    rest_positions_m: s.rest_positions_m.clone(),
                    codec: DeltaCodec::new(n, &s.triangles).ok().map(Arc::new),
                });
                self.stats
                    .queue_limit_bytes
                    .store(queue_limit_bytes(&t), Ordering::Relaxed);
                self.topology.insert(t).clone()
            }
        }
    }

    /// The delta of `s` against the reference, renewing the reference when the policy says
    /// so (chained when the old reference can express the new one).
    fn delta(
        &mut self,
        s: &Snapshot,
        topology: &Arc<Topology>,
        codec: &DeltaCodec,
    ) -> Option<Bytes> {
        let now = tokio::time::Instant::now();
        let buf = &mut self.buf;
        let encoded = match &self.reference {
            Some(r) if r.topology.version == topology.version => codec
                .encode(&r.positions_m, &s.positions_m, DEFAULT_QUANTUM_M, buf)
                .ok()
                .map(|()| buf.len()),
            _ => None,
        };
        let renew = match encoded {
            None => true,
            Some(len) => {
                let step = if self.previous.len() == s.positions_m.len() {
                    codec
                        .encode(
                            &self.previous,
                            &s.positions_m,
                            DEFAULT_QUANTUM_M,
                            &mut self.step_buf,
                        )
                        .map_or(usize::MAX, |()| self.step_buf.len())
                } else {
                    usize::MAX
                };
                // A chained renewal costs about one delta (`len`), not a float keyframe.
                self.policy
                    .should_renew((now - self.renewed_at).as_secs_f64(), len, step, len)
            }
        };
        let delta = if renew {
            // Chained when the old reference can express the new one: the new reference
            // is what a client decodes from the old one (within half a step of the
            // surface), so a renewal costs a delta instead of a float keyframe.
            let chained = match (&self.reference, encoded) {
                (Some(old), Some(_)) => {
                    let mut p = vec![0.0; s.positions_m.len()];
                    codec
                        .decode(&old.positions_m, &self.buf, DEFAULT_QUANTUM_M, &mut p)
                        .ok()
                        .map(|()| (p, (old.id, Bytes::copy_from_slice(&self.buf))))
                }
                _ => None,
            };
            let (positions_m, chain) = match chained {
                Some((p, c)) => (p, Some(c)),
                None => (s.positions_m.clone(), None),
            };
            let delta = codec
                .encode(
                    &positions_m,
                    &s.positions_m,
                    DEFAULT_QUANTUM_M,
                    &mut self.buf,
                )
                .ok()
                .map(|()| Bytes::copy_from_slice(&self.buf));
            self.reference = Some(Arc::new(Reference {
                id: self.next_id,
                topology: topology.clone(),
                positions_m,
                sim_time_s: s.sim_time_s,
                chain,
            }));
            self.next_id += 1;
            self.renewed_at = now;
            delta
        } else {
            Some(Bytes::copy_from_slice(&self.buf))
        };
        self.previous.clear();
        self.previous.extend_from_slice(&s.positions_m);
        delta
    }
}

/// The largest frame of a topology (keyframe with triangles, rest, positions and a full delta)
/// times the queue length, bytes.
fn queue_limit_bytes(t: &Topology) -> u64 {
    let values = t.rest_positions_m.len();
    let frame = 2 * (5 + 4 * values) // positions_m, rest_positions_m (packed floats)
        + 5 + 5 * t.triangles.len() // packed varints
        + t.codec.as_ref().map_or(0, |c| c.payload_len() + 5)
        + 256 // scalars, vectors
        + 96 * crate::servo::APPLIED_LOAD_CAPACITY; // applied forces
    (WATCH_QUEUE_FRAMES * frame) as u64
}

/// What one watcher has received so far.
#[derive(Debug, Default)]
struct WatcherState {
    /// Topology version the client has (triangles and rest positions).
    topology: Option<u64>,
    /// Reference keyframe id the client has (compact streams).
    reference: Option<u64>,
    frames: u64,
}

static NEXT_WATCH_ID: AtomicU64 = AtomicU64::new(1);

/// The stream a Watch handler returns.
pub type FrameStream =
    std::pin::Pin<Box<dyn Stream<Item = Result<SurfaceFrame, tonic::Status>> + Send>>;

/// Unregisters a watcher when its task ends.
struct WatchGuard {
    stats: Arc<WatcherStats>,
    id: u64,
    delta: bool,
}

impl Drop for WatchGuard {
    fn drop(&mut self) {
        self.stats.watchers.fetch_sub(1, Ordering::AcqRel);
        if self.delta {
            self.stats.delta_watchers.fetch_sub(1, Ordering::AcqRel);
        }
        if let Ok(mut r) = self.stats.requests.lock() {
            r.remove(&self.id);
        }
    }
}

/// The encoded size of one frame in a watcher's queue, counted in
/// [`WatcherStats::queued_bytes`] from before it is queued until it leaves the queue: taken by
/// the transport, refused by a full queue, or dropped with the queue of a watcher that
/// disconnected (the channel drops what it still holds, and so this guard).
struct QueuedBytes {
    stats: Arc<WatcherStats>,
    len: u64,
}

impl QueuedBytes {
    fn new(stats: &Arc<WatcherStats>, len: u64) -> Self {
        stats.queued_bytes.fetch_add(len, Ordering::Relaxed);
        Self {
            stats: stats.clone(),
            len,
        }
    }
}

impl Drop for QueuedBytes {
    fn drop(&mut self) {
        self.stats
            .queued_bytes
            .fetch_sub(self.len, Ordering::Relaxed);
    }
}

/// Starts a watcher of a session with `params`: returns its stream of frames (keyframe first).
///
/// `frames` and `servo_guard` come from [`crate::session::Session::watch`] (the servo publishes
/// while the guard lives), `stats` is the session's [`WatcherStats`] and `probe_radius_m` its
/// probe radius, m (sent in every frame).
pub fn spawn_watch(
    frames: watch::Receiver<Option<Arc<FrameData>>>,
    servo_guard: WatcherGuard,
    stats: Arc<WatcherStats>,
    probe_radius_m: f64,
    params: WatchParams,
) -> FrameStream {
    let id = NEXT_WATCH_ID.fetch_add(1, Ordering::Relaxed);
    let requested = Arc::new(AtomicBool::new(false));
    if let Ok(mut r) = stats.requests.lock() {
        r.insert(id, requested.clone());
    }
    stats.watchers.fetch_add(1, Ordering::AcqRel);
    if params.quantum_m.is_some() {
        stats.delta_watchers.fetch_add(1, Ordering::AcqRel);
    }
    let guard = WatchGuard {
        stats: stats.clone(),
        id,
        delta: params.quantum_m.is_some(),
    };
    let mut frames = frames;
    let (tx, rx) = mpsc::channel::<(SurfaceFrame, QueuedBytes)>(WATCH_QUEUE_FRAMES);
    tokio::spawn(async move {
        let _guards = (guard, servo_guard);
        let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / params.rate_hz));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let mut state = WatcherState::default();
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                () = tx.closed() => break,
            }
            // A new frame since the last one sent; wait for it if there is none yet.
            let changed = match frames.has_changed() {
                Ok(true) => Ok(()),
                Ok(false) => tokio::select! {
                    r = frames.changed() => r,
                    () = tx.closed() => break,
                },
                Err(e) => Err(e),
            };
            if changed.is_err() {
                break; // the session ended
            }
            let Some(f) = frames.borrow_and_update().clone() else {
                continue;
            };
            let force_topology = requested.swap(false, Ordering::AcqRel);
            let Some((frame, kept)) =
                build_frame(&f, probe_radius_m, &params, &state, id, force_topology)
            else {
                continue; // compact stream, no reference yet: wait for the next frame
            };
            let len = frame.encoded_len() as u64;
            // Counted before the send, so the transport never subtracts bytes not yet added.
            match tx.try_send((frame, QueuedBytes::new(&stats, len))) {
                Ok(()) => {
                    state = kept;
                    stats.frames_sent.fetch_add(1, Ordering::Relaxed);
                    stats.bytes_sent.fetch_add(len, Ordering::Relaxed);
                }
                Err(mpsc::error::TrySendError::Full(_)) => {
                    stats.frames_dropped.fetch_add(1, Ordering::Relaxed);
                    if force_topology {
                        requested.store(true, Ordering::Release);
                    }
                }
                Err(mpsc::error::TrySendError::Closed(_)) => break,
            }
        }
    });
    Box::pin(tokio_stream::StreamExt::map(
        ReceiverStream::new(rx),
        |(frame, _queued): (SurfaceFrame, QueuedBytes)| Ok(frame),
    ))
}

/// The next frame for a watcher whose client has `state`, and the state after it is sent.
/// `None` for a compact watcher while the session has no reference keyframe yet.
fn build_frame(
    f: &FrameData,
    probe_radius_m: f64,
    params: &WatchParams,
    state: &WatcherState,
    watch_id: u64,
    force_topology: bool,
) -> Option<(SurfaceFrame, WatcherState)> {
    let version = f.topology.version;
    let new_topology = force_topology || state.topology != Some(version);
    let mut frame = SurfaceFrame {
        frame: state.frames,
        sim_time_s: f.sim_time_s,
        probe_position_m: Some(Vec3::from(f.probe_m)),
        contact_force_n: Some(Vec3::from(f.force_n)),
        in_contact: f.in_contact,
        probe_radius_m,
        server_time_us: unix_time_us(),
        max_displacement_m: f.max_displacement_m,
        applied_forces: f.applied_forces.clone(),
        applied_forces_total: f.applied_forces_total,
        tools: f.tools.clone(),
        watch_id,
        topology_version: version,
        ..SurfaceFrame::default()
    };
    let mut next = WatcherState {
        topology: Some(version),
        reference: state.reference,
        frames: state.frames + 1,
    };
    let delta = match params.quantum_m {
        None => None,
        Some(q) => {
            let reference = f.reference.as_ref()?;
            Some((reference, f.delta_for(q), q))
        }
    };
    match delta {
        // Full positions: a keyframe when the client lacks the topology (FULL streams, and
        // compact frames that are not representable against the reference).
        None | Some((_, None, _)) => {
            frame.keyframe = new_topology;
            frame.positions_m = f.positions_m.clone();
            next.reference = None;
        }
        Some((reference, Some(bytes), q)) => {
            frame.quantum_m = q;
            frame.keyframe_id = reference.id;
            frame.position_delta = bytes;
            if new_topology || state.reference != Some(reference.id) {
                frame.keyframe = true;
                next.reference = Some(reference.id);
                match &reference.chain {
                    // The client has the previous reference: send only the step to this one.
                    Some((previous, step))
                        if !new_topology
                            && q == DEFAULT_QUANTUM_M
                            && state.reference == Some(*previous) =>
                    {
                        frame.base_keyframe_id = *previous;
                        frame.reference_delta = step.clone();
                    }
                    _ => frame.positions_m = reference.positions_m.clone(),
                }
            }
        }
    }
    if frame.keyframe && new_topology {
        frame.triangles = f.topology.triangles.clone();
        frame.rest_positions_m = f.topology.rest_positions_m.clone();
    }
    Some((frame, next))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keyframes_are_renewed_periodically_and_when_they_pay_for_themselves() {
        let p = KeyframePolicy::default();
        assert_eq!(
            (p.min_interval_s, p.max_interval_s, p.payback_frames),
            (0.5, 10.0, 20.0)
        );
        // Periodic: at the maximum interval whatever the sizes, even with nothing to gain.
        assert!(p.should_renew(10.0, 0, 0, 1 << 30));
        assert!(p.should_renew(10.0, 5, usize::MAX, 1 << 30));
        assert!(!p.should_renew(9.999, 0, 0, 1 << 30));
        // Payback: (delta - step) * 20 frames must exceed the keyframe's cost, strictly.
        assert!(!p.should_renew(1.0, 150, 100, 1000)); // 50 * 20 = 1000
        assert!(p.should_renew(1.0, 151, 100, 1000)); // 51 * 20 = 1020
        // ... and never before the minimum interval.
        assert!(!p.should_renew(0.499, 151, 100, 1000));
        assert!(p.should_renew(0.5, 151, 100, 1000));
        // A surface still moving (a step as large as the delta) or with no previous frame to
        // compare with (step unknown: usize::MAX) is not renewed before the maximum interval.
        assert!(!p.should_renew(5.0, 800, 900, 1));
        assert!(!p.should_renew(5.0, 800, usize::MAX, 1));
        // The rule follows its parameters.
        let eager = KeyframePolicy {
            min_interval_s: 0.0,
            max_interval_s: 1.0,
            payback_frames: 1.0,
        };
        assert!(eager.should_renew(0.0, 1001, 0, 1000));
        assert!(!eager.should_renew(0.0, 1000, 0, 1000));
        assert!(eager.should_renew(1.0, 0, 0, 1000));
    }
}
