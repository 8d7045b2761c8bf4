//! Viewer frames, shared by the session that publishes them and the streams that send them:
//! the surface [`Topology`], a [`FrameData`] per servo snapshot, the compact streams'
//! [`Reference`] keyframe, the watchers' counters ([`WatcherStats`]) and the servo's watcher
//! count ([`WatcherGuard`]).
//!
//! Neighbours: [`crate::stream`] builds and sends frames; [`crate::session`] owns the channel
//! they travel through. This module depends on neither (it breaks their import cycle).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};

use haptics_proto::delta::DEFAULT_QUANTUM_M;
use prost::bytes::Bytes;

use crate::error::ServerError;
use crate::servo::SessionShared;

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
    /// Injected loads acting at this frame or ended since the previous snapshot.
    pub applied_forces: Vec<haptics_proto::v1::AppliedForce>,
    /// Loads the session has accepted so far.
    pub applied_forces_total: u64,
    /// Every tool slot with a device, in slot order.
    pub tools: Vec<haptics_proto::v1::ToolProbe>,
    /// The reference keyframe of compact streams (`None` while no compact watcher exists).
    pub reference: Option<Arc<Reference>>,
    /// `positions_m` against `reference` at the default quantum (1 um), encoded; `None`
    /// without a reference. Empty when the positions are the reference.
    pub delta: Option<Bytes>,
    /// Deltas at other quanta, computed on demand ([`FrameData::delta_for`]).
    pub other_deltas: Mutex<Vec<(u64, Option<Bytes>)>>,
}

/// A reference keyframe of the compact streams: delta frames encode positions against it.
#[derive(Debug)]
pub struct Reference {
    /// Increasing per session from 1 (`SurfaceFrame.keyframe_id`).
    pub id: u64,
    /// The connectivity of these positions.
    pub topology: Arc<Topology>,
    /// Surface positions, xyz, m.
    pub positions_m: Vec<f32>,
    /// Simulated time of these positions, s.
    pub sim_time_s: f64,
    /// How a client that has the previous reference gets this one: `(previous id, delta)` with
    /// `positions_m = previous + delta` exactly as a client decodes it (1 um steps). `None` for
    /// a first reference, a new topology, or a displacement a delta cannot express.
    pub chain: Option<(u64, Bytes)>,
}

impl FrameData {
    /// The encoded delta of this frame against [`FrameData::reference`] in steps of
    /// `quantum_m` (computed once per quantum and shared); `None` without a reference or when
    /// not representable.
    pub fn delta_for(&self, quantum_m: f64) -> Option<Bytes> {
        let reference = self.reference.as_ref()?;
        if quantum_m == DEFAULT_QUANTUM_M {
            return self.delta.clone();
        }
        let key = quantum_m.to_bits();
        if let Ok(cache) = self.other_deltas.lock()
            && let Some((_, d)) = cache.iter().find(|(k, _)| *k == key)
        {
            return d.clone();
        }
        let codec = reference.topology.codec.as_ref()?;
        let mut buf = Vec::new();
        let d = codec
            .encode(
                &reference.positions_m,
                &self.positions_m,
                quantum_m,
                &mut buf,
            )
            .ok()
            .map(|()| Bytes::from(buf));
        if let Ok(mut cache) = self.other_deltas.lock()
            && cache.len() < 8
        {
            cache.push((key, d.clone()));
        }
        d
    }
}

/// Counters of a session's watchers (atomics: the watch tasks write, `GetStats` reads).
#[derive(Debug, Default)]
pub struct WatcherStats {
    /// Watch streams open now.
    pub watchers: AtomicUsize,
    /// Watch streams open now that asked for DELTA (the frame task encodes only for them).
    pub delta_watchers: AtomicUsize,
    /// Frames queued to watchers so far.
    pub frames_sent: AtomicU64,
    /// Frames a watcher was due while its queue was full.
    pub frames_dropped: AtomicU64,
    /// Encoded bytes of the frames sent.
    pub bytes_sent: AtomicU64,
    /// Encoded bytes waiting in watcher queues now (released when a frame leaves a queue,
    /// including with the queue of a watcher that disconnected).
    pub queued_bytes: AtomicU64,
    /// The most one watcher's queue can hold for the current topology, bytes.
    pub queue_limit_bytes: AtomicU64,
    /// Keyframe requests of the open streams, by watch id.
    pub(crate) requests: Mutex<HashMap<u64, Arc<AtomicBool>>>,
}

impl WatcherStats {
    /// Asks stream `watch_id` for a keyframe with its topology as its next frame.
    ///
    /// # Errors
    /// [`ServerError::UnknownWatch`] when no such stream is open on this session.
    pub fn request_keyframe(&self, watch_id: u64) -> Result<(), ServerError> {
        let requests = self
            .requests
            .lock()
            .map_err(|_| ServerError::Internal("keyframe requests poisoned".into()))?;
        let flag = requests
            .get(&watch_id)
            .ok_or(ServerError::UnknownWatch(watch_id))?;
        flag.store(true, Ordering::Release);
        Ok(())
    }
}

/// Decrements the watcher count when a viewer stream ends.
pub struct WatcherGuard(pub(crate) Arc<SessionShared>);

impl Drop for WatcherGuard {
    fn drop(&mut self) {
        self.0.watchers.fetch_sub(1, Ordering::AcqRel);
    }
}

/// Microseconds since the UNIX epoch (cross-process timestamps for frame age and latency).
pub fn unix_time_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_micros() as u64)
        .unwrap_or(0)
}
