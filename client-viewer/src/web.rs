//! `web`: the browser viewer of `haptic-viewer --web ADDR`, a relay between the daemon and
//! many browsers.
//!
//! The relay serves the page and its assets (`client-viewer/web/`, compiled into the binary
//! with `include_bytes!`), a small JSON API, and one WebSocket per browser:
//!
//! - `GET /` the page; `GET /app.js`, `GET /vendor/*` (three.js 0.187.0, MIT, from the npm
//!   registry: `web/vendor/README.md`);
//! - `GET /api/sessions`: the daemon's sessions with their scene and statistics (JSON array);
//! - `GET /api/relay`: the relay's own counters per session (browsers, frames, drops, bytes);
//! - `GET /overview`, `GET /api/overview`, `GET /api/picture`: the session overview of this
//!   daemon and the `--stations` ones ([`overview`]);
//! - `GET /ws?session=ID&rate=HZ`: a WebSocket. Binary messages from the relay are
//!   `haptics.v1.SurfaceFrame` protobuf encodings of the compact stream (keyframes and
//!   quantized deltas, `haptics_proto::delta`); text messages are JSON: `{"type":"status",...}`
//!   once a second (the session's `GetStats` and the relay's counters), `{"type":"error",
//!   "message":...}` and `{"type":"ended"}`. The browser may send text `{"type":"keyframe"}`
//!   (its next frame is a keyframe with the topology) and `{"type":"rate","hz":X}`; anything
//!   else gets an error message, never a panic.
//!
//! **One upstream per session.** The first browser of a session makes the relay call
//! `SurfaceStream.Watch` (compact, [`WebConfig::upstream_rate_hz`]) and `GetStats` once a
//! second; every further browser costs the daemon nothing. Each upstream frame is encoded once
//! for all browsers; a browser that lacks the frame's reference keyframe (a late joiner, a new
//! reference, a topology change, a request) gets a keyframe message built once per frame and
//! shared. The upstream ends when the last browser leaves.
//!
//! **Slow browsers.** Each browser has its own rate and a queue of [`BROWSER_QUEUE`] messages
//! in front of its socket; a frame due while the queue is full is dropped and counted, a
//! keyframe that could not be queued is retried at the next due frame. Memory per browser is
//! bounded by the queue.
//!
//! Neighbours: [`crate::compact`] tracks the reference keyframes; the daemon side is
//! `haptic_server::stream`.

use std::collections::HashMap;
use std::future::Future;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use axum::Router;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use futures_util::{SinkExt, StreamExt};
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use haptics_proto::v1::{
    GetStatsRequest, ListSessionsRequest, SessionStats, SurfaceEncoding, SurfaceFrame, WatchRequest,
};
use prost::Message as _;
use prost::bytes::Bytes;
use serde_json::{Value, json};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};

use crate::ClientError;
use crate::compact::CompactState;

pub mod overview;

/// Messages one browser may have queued in front of its socket.
pub const BROWSER_QUEUE: usize = 4;
/// Smallest browser frame rate, Hz.
pub const MIN_BROWSER_RATE_HZ: f64 = 0.1;
/// Largest browser frame rate, Hz (the upstream rate caps what arrives).
pub const MAX_BROWSER_RATE_HZ: f64 = 60.0;

const INDEX_HTML: &[u8] = include_bytes!("../web/index.html");
const APP_JS: &[u8] = include_bytes!("../web/app.js");
const THREE_MODULE_JS: &[u8] = include_bytes!("../web/vendor/three.module.js");
const THREE_CORE_JS: &[u8] = include_bytes!("../web/vendor/three.core.js");
const ORBIT_CONTROLS_JS: &[u8] = include_bytes!("../web/vendor/OrbitControls.js");
const THREE_LICENSE: &[u8] = include_bytes!("../web/vendor/LICENSE");

/// What the relay does.
#[derive(Debug, Clone, PartialEq)]
pub struct WebConfig {
    /// Daemon URL, e.g. `http://127.0.0.1:50051`.
    pub server: String,
    /// Token and TLS files for the daemon (a `viewer` token is enough).
    pub credentials: haptic_cli::credentials::ClientCredentials,
    /// Rate the relay asks of the daemon per session, Hz (browsers can ask up to this).
    pub upstream_rate_hz: f64,
    /// Browser rate when the page does not ask, Hz.
    pub default_rate_hz: f64,
    /// Other daemons the overview page shows besides `server` ([`overview`]).
    pub stations: Vec<overview::StationConfig>,
}

impl WebConfig {
    /// Defaults: upstream 60 Hz, browsers 30 Hz.
    pub fn new(server: impl Into<String>) -> Self {
        Self {
            server: server.into(),
            credentials: haptic_cli::credentials::ClientCredentials::default(),
            upstream_rate_hz: 60.0,
            default_rate_hz: 30.0,
            stations: Vec::new(),
        }
    }

    /// Checks the rates.
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] for a rate outside 0.1 ..= 120 Hz.
    pub fn validate(&self) -> Result<(), ClientError> {
        for (name, r) in [
            ("upstream rate", self.upstream_rate_hz),
            ("default browser rate", self.default_rate_hz),
        ] {
            if !(r.is_finite() && (MIN_BROWSER_RATE_HZ..=120.0).contains(&r)) {
                return Err(ClientError::InvalidConfig(format!(
                    "{name} {r} Hz: expected 0.1 ..= 120 Hz"
                )));
            }
        }
        Ok(())
    }
}

/// Counters of one session's relay.
#[derive(Debug, Default)]
pub struct RelayCounters {
    /// Browsers watching now.
    pub browsers: AtomicUsize,
    /// Frames received from the daemon.
    pub upstream_frames: AtomicU64,
    /// Encoded bytes received from the daemon (frame payloads).
    pub upstream_bytes: AtomicU64,
    /// Messages queued to browsers (frames and keyframes).
    pub frames_sent: AtomicU64,
    /// Frames a browser was due while its queue was full.
    pub frames_dropped: AtomicU64,
    /// Bytes of the binary messages queued to browsers.
    pub bytes_sent: AtomicU64,
}

/// Triangles and rest positions of a topology, shared by the frames that use it.
type SharedTopology = (Arc<Vec<u32>>, Arc<Vec<f32>>);

/// One upstream frame, encoded once for every browser.
struct RelayFrame {
    /// Increasing per session relay (browsers send a frame once).
    seq: u64,
    /// The frame as received (compact form).
    frame: SurfaceFrame,
    /// `frame` encoded, for browsers that have its reference and topology.
    encoded: Bytes,
    /// Reference positions of `frame` (its keyframe), for keyframe messages.
    reference: Option<Arc<Vec<f32>>>,
    /// The topology of `frame`.
    topology: Option<SharedTopology>,
    /// How the reference of `frame` chains from the one before (`base id`, delta).
    chain: Option<(u64, Bytes)>,
    /// Keyframe messages built on demand: chained, full without and with the topology.
    chained: OnceLock<Bytes>,
    keyframe: OnceLock<Bytes>,
    keyframe_with_topology: OnceLock<Bytes>,
}

impl RelayFrame {
    /// True when a browser that has reference `reference` and topology `topology` can apply
    /// the frame as it is.
    fn fits(&self, reference: Option<u64>, topology: Option<u64>) -> bool {
        let f = &self.frame;
        if f.position_delta.is_empty() && !f.positions_m.is_empty() && !f.keyframe {
            return topology == Some(f.topology_version); // absolute positions
        }
        !f.keyframe && reference == Some(f.keyframe_id) && topology == Some(f.topology_version)
    }

    /// A chained keyframe message for a browser that has reference `base`: the step from it to
    /// this frame's reference, and this frame's delta. `None` when the reference is not
    /// chained from `base`.
    fn chained(&self, base: Option<u64>) -> Option<Bytes> {
        let (from, step) = self.chain.as_ref().filter(|c| Some(c.0) == base)?;
        Some(
            self.chained
                .get_or_init(|| {
                    let mut k = self.frame.clone();
                    k.keyframe = true;
                    k.positions_m.clear();
                    k.triangles.clear();
                    k.rest_positions_m.clear();
                    k.base_keyframe_id = *from;
                    k.reference_delta = step.clone();
                    Bytes::from(k.encode_to_vec())
                })
                .clone(),
        )
    }

    /// A keyframe message: the reference positions, this frame's delta, and the topology when
    /// `with_topology`. `None` before any keyframe was seen.
    fn keyframe(&self, with_topology: bool) -> Option<Bytes> {
        let slot = if with_topology {
            &self.keyframe_with_topology
        } else {
            &self.keyframe
        };
        let reference = self.reference.as_ref()?;
        let (triangles, rest) = self.topology.as_ref()?;
        Some(
            slot.get_or_init(|| {
                let mut k = self.frame.clone();
                k.keyframe = true;
                k.positions_m = reference.to_vec();
                k.base_keyframe_id = 0;
                k.reference_delta = Bytes::new();
                if with_topology {
                    k.triangles = triangles.to_vec();
                    k.rest_positions_m = rest.to_vec();
                } else {
                    k.triangles.clear();
                    k.rest_positions_m.clear();
                }
                Bytes::from(k.encode_to_vec())
            })
            .clone(),
        )
    }
}

/// The relay of one session: its upstream, latest frame and status.
///
/// The three channels are written with `send_replace` / `send_if_modified`, which store the
/// value even while no receiver exists: a plain `send` drops it then, and an upstream that
/// failed before its first browser subscribed (an unknown session answers at once) left that
/// browser waiting for an error that never came.
struct SessionRelay {
    counters: RelayCounters,
    latest: watch::Sender<Option<Arc<RelayFrame>>>,
    /// JSON text messages for browsers (status once a second, then `error`/`ended`).
    status: watch::Sender<Option<Arc<String>>>,
    /// Set when the last browser left (the upstream tasks end).
    stop: watch::Sender<bool>,
}

/// The relay: upstream connections and the browsers of every session.
pub struct Relay {
    cfg: WebConfig,
    channel: haptic_cli::credentials::AuthChannel,
    sessions: Mutex<HashMap<String, Arc<SessionRelay>>>,
    /// Set when the daemon refused the relay's credentials: [`run`] then stops and reports it
    /// instead of serving pages that can only fail (issue 47).
    refused: watch::Sender<Option<(tonic::Code, String)>>,
    /// The overview's daemons: `server` first, then [`WebConfig::stations`].
    stations: Vec<overview::StationLink>,
    pictures: overview::Pictures,
}

/// True for the statuses that retrying cannot fix: no or a wrong token, or a role that may
/// not watch.
pub fn is_refusal(code: tonic::Code) -> bool {
    matches!(
        code,
        tonic::Code::Unauthenticated | tonic::Code::PermissionDenied
    )
}

impl Relay {
    /// A relay for `cfg.server` (the connection is made on first use).
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] for bad rates; [`ClientError::Connect`] for a malformed URL.
    pub fn new(cfg: WebConfig) -> Result<Arc<Self>, ClientError> {
        cfg.validate()?;
        let url = haptic_cli::connect::normalize_url(&cfg.server);
        let token = cfg.credentials.interceptor()?;
        let channel = token.wrap(
            cfg.credentials
                .endpoint(&url)?
                .connect_timeout(Duration::from_secs(5))
                .tcp_nodelay(true)
                .connect_lazy(),
        );
        let mut stations = vec![overview::StationLink {
            name: cfg.server.clone(),
            url: url.clone(),
            channel: channel.clone(),
        }];
        for s in &cfg.stations {
            stations.push(overview::StationLink::new(s)?);
        }
        Ok(Arc::new(Self {
            cfg,
            channel,
            sessions: Mutex::new(HashMap::new()),
            refused: watch::channel(None).0,
            stations,
            pictures: overview::Pictures::default(),
        }))
    }

    /// The overview's daemons: the relay's own first.
    pub(crate) fn stations(&self) -> &[overview::StationLink] {
        &self.stations
    }

    /// The overview's pictures.
    pub(crate) fn pictures(&self) -> &overview::Pictures {
        &self.pictures
    }

    /// Notes a refusal of the relay's credentials (see [`Relay::refused`]); other statuses are
    /// left to the caller.
    fn note_refusal(&self, status: &tonic::Status) {
        if is_refusal(status.code()) {
            self.refused.send_if_modified(|r| {
                let first = r.is_none();
                if first {
                    *r = Some((status.code(), status.message().to_string()));
                }
                first
            });
        }
    }

    /// Asks the daemon for its sessions once: credentials it refuses are an error now, before
    /// any browser connects; a daemon that cannot be reached yet is only a warning (the relay
    /// connects on first use).
    ///
    /// # Errors
    /// [`ClientError::Rpc`] with UNAUTHENTICATED or PERMISSION_DENIED.
    pub async fn check_access(&self) -> Result<(), ClientError> {
        let mut ctl = SessionControlClient::new(self.channel.clone());
        match ctl.list_sessions(ListSessionsRequest {}).await {
            Ok(_) => Ok(()),
            Err(status) if is_refusal(status.code()) => Err(status.into()),
            Err(status) => {
                tracing::warn!(
                    "daemon {} not answering yet: {}",
                    self.cfg.server,
                    ClientError::from(status)
                );
                Ok(())
            }
        }
    }

    /// The relay of `id`, started (upstream and stats poller) if no browser watches it yet;
    /// counts one browser.
    fn join(self: &Arc<Self>, id: &str) -> Arc<SessionRelay> {
        let mut sessions = self.sessions.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(s) = sessions.get(id) {
            s.counters.browsers.fetch_add(1, Ordering::AcqRel);
            return s.clone();
        }
        let s = Arc::new(SessionRelay {
            counters: RelayCounters::default(),
            latest: watch::channel(None).0,
            status: watch::channel(None).0,
            stop: watch::channel(false).0,
        });
        s.counters.browsers.fetch_add(1, Ordering::AcqRel);
        sessions.insert(id.to_string(), s.clone());
        tokio::spawn(upstream(self.clone(), id.to_string(), s.clone()));
        tokio::spawn(poll_stats(self.clone(), id.to_string(), s.clone()));
        s
    }

    /// One browser of `id` left; the last one stops the upstream.
    fn leave(&self, id: &str, s: &Arc<SessionRelay>) {
        if s.counters.browsers.fetch_sub(1, Ordering::AcqRel) == 1 {
            s.stop.send_replace(true);
            let mut sessions = self.sessions.lock().unwrap_or_else(|e| e.into_inner());
            if sessions.get(id).is_some_and(|x| Arc::ptr_eq(x, s)) {
                sessions.remove(id);
            }
        }
    }

    /// The upstream of `id` ended (error, or the session stopped): its browsers get the last
    /// message and close; a later browser starts a new upstream.
    fn forget(&self, id: &str, s: &Arc<SessionRelay>) {
        s.stop.send_replace(true);
        let mut sessions = self.sessions.lock().unwrap_or_else(|e| e.into_inner());
        if sessions.get(id).is_some_and(|x| Arc::ptr_eq(x, s)) {
            sessions.remove(id);
        }
    }

    /// The relay's counters per session, as JSON.
    pub fn counters_json(&self) -> Value {
        let sessions = self.sessions.lock().unwrap_or_else(|e| e.into_inner());
        let mut v: Vec<Value> = sessions
            .iter()
            .map(|(id, s)| {
                let c = &s.counters;
                json!({
                    "session_id": id,
                    "browsers": c.browsers.load(Ordering::Relaxed),
                    "upstream_frames": c.upstream_frames.load(Ordering::Relaxed),
                    "upstream_bytes": c.upstream_bytes.load(Ordering::Relaxed),
                    "frames_sent": c.frames_sent.load(Ordering::Relaxed),
                    "frames_dropped": c.frames_dropped.load(Ordering::Relaxed),
                    "bytes_sent": c.bytes_sent.load(Ordering::Relaxed),
                })
            })
            .collect();
        v.sort_by(|a, b| a["session_id"].as_str().cmp(&b["session_id"].as_str()));
        json!({ "sessions": v })
    }
}

/// The session's `Watch` stream (compact) until the last browser leaves or the stream ends.
async fn upstream(relay: Arc<Relay>, id: String, s: Arc<SessionRelay>) {
    let mut stop = s.stop.subscribe();
    let mut client =
        SurfaceStreamClient::new(relay.channel.clone()).max_decoding_message_size(64 << 20);
    let request = WatchRequest {
        session_id: id.clone(),
        max_rate_hz: relay.cfg.upstream_rate_hz,
        encoding: SurfaceEncoding::Delta as i32,
        quantum_m: 0.0,
    };
    let watched = tokio::select! {
        r = client.watch(request) => r,
        _ = stop.wait_for(|v| *v) => return,
    };
    let mut stream = match watched {
        Ok(r) => r.into_inner(),
        Err(status) => {
            relay.note_refusal(&status);
            let e = ClientError::from(status);
            s.status.send_replace(Some(Arc::new(
                json!({"type": "error", "message": e.to_string()}).to_string(),
            )));
            relay.forget(&id, &s);
            return;
        }
    };
    let mut compact = CompactState::new();
    let mut seq = 0u64;
    let ended = loop {
        let msg = tokio::select! {
            m = stream.message() => m,
            _ = stop.wait_for(|v| *v) => return,
        };
        let f = match msg {
            Ok(Some(f)) => f,
            Ok(None) => break json!({"type": "ended"}),
            Err(status) => {
                break json!({"type": "error", "message": ClientError::from(status).to_string()});
            }
        };
        let encoded = Bytes::from(f.encode_to_vec());
        s.counters.upstream_frames.fetch_add(1, Ordering::Relaxed);
        s.counters
            .upstream_bytes
            .fetch_add(encoded.len() as u64, Ordering::Relaxed);
        if let Err(e) = compact.track(&f) {
            tracing::warn!(session = %id, "{e}");
            continue;
        }
        seq += 1;
        let frame = RelayFrame {
            seq,
            reference: compact
                .reference
                .as_ref()
                .filter(|r| r.id == f.keyframe_id)
                .map(|r| r.positions_m.clone()),
            topology: compact
                .topology
                .as_ref()
                .filter(|t| t.version == f.topology_version)
                .map(|t| (t.triangles.clone(), t.rest_positions_m.clone())),
            chain: compact.chain.clone().filter(|_| {
                compact
                    .reference
                    .as_ref()
                    .is_some_and(|r| r.id == f.keyframe_id)
            }),
            frame: f,
            encoded,
            chained: OnceLock::new(),
            keyframe: OnceLock::new(),
            keyframe_with_topology: OnceLock::new(),
        };
        s.latest.send_replace(Some(Arc::new(frame)));
    };
    s.status.send_replace(Some(Arc::new(ended.to_string())));
    relay.forget(&id, &s);
}

/// `GetStats` once a second while browsers watch, as `{"type":"status",...}` for them.
async fn poll_stats(relay: Arc<Relay>, id: String, s: Arc<SessionRelay>) {
    let mut stop = s.stop.subscribe();
    let mut client = SessionControlClient::new(relay.channel.clone());
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.wait_for(|v| *v) => return,
        }
        let request = GetStatsRequest {
            session_id: id.clone(),
        };
        let r = match client.get_stats(request).await {
            Ok(r) => r,
            Err(status) => {
                relay.note_refusal(&status);
                continue; // the upstream task reports unknown or ended sessions
            }
        };
        let st = r.into_inner();
        let c = &s.counters;
        let mut v = stats_json(&st);
        v["type"] = json!("status");
        v["relay_browsers"] = json!(c.browsers.load(Ordering::Relaxed));
        v["relay_frames_sent"] = json!(c.frames_sent.load(Ordering::Relaxed));
        v["relay_frames_dropped"] = json!(c.frames_dropped.load(Ordering::Relaxed));
        // Errors and the end of the stream stay: only replace an earlier status (checked and
        // replaced under the channel's lock, so an error sent meanwhile is never overwritten).
        let v = Arc::new(v.to_string());
        s.status.send_if_modified(|cur| {
            let keep = cur
                .as_ref()
                .is_some_and(|m| !m.contains("\"type\":\"status\""));
            if !keep {
                *cur = Some(v);
            }
            !keep
        });
    }
}

/// The statistics fields the page shows, by their proto names.
pub(crate) fn stats_json(st: &SessionStats) -> Value {
    json!({
        "session_id": st.session_id,
        "scene": st.scene,
        "nodes": st.nodes,
        "tetrahedra": st.tetrahedra,
        "surface_vertices": st.surface_vertices,
        "loop_rate_hz": st.loop_rate_hz,
        "step_p50_us": st.step_p50_us,
        "step_p99_us": st.step_p99_us,
        "pose_to_force_p50_us": st.pose_to_force_p50_us,
        "pose_to_force_p99_us": st.pose_to_force_p99_us,
        "overruns": st.overruns,
        "in_contact": st.in_contact,
        "peak_force_n": st.peak_force_n,
        "faulted": st.faulted,
        "fault": st.fault,
        "watchers": st.watchers,
        "watcher_frames_dropped": st.watcher_frames_dropped,
        "max_tools": st.max_tools,
        // Each tool's figures (issue 50), for its strip chart and the overview's card.
        "tools": st.tools.iter().map(|t| json!({
            "tool_id": t.tool_id,
            "slot": t.slot,
            "connected": t.connected,
            "in_contact": t.in_contact,
            "force_n": t.force_n,
            "peak_force_n": t.peak_force_n,
            "device": t.device.as_ref().map(|d| d.name.clone()),
            "pose_to_force_p50_us": t.pose_to_force_p50_us,
            "pose_to_force_p99_us": t.pose_to_force_p99_us,
        })).collect::<Vec<_>>(),
    })
}

/// The routes of the web viewer over `relay`.
pub fn router(relay: Arc<Relay>) -> Router {
    Router::new()
        .route(
            "/",
            get(|| async { asset("text/html; charset=utf-8", INDEX_HTML) }),
        )
        .route(
            "/app.js",
            get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }),
        )
        .route(
            "/vendor/three.module.js",
            get(|| async { asset("text/javascript; charset=utf-8", THREE_MODULE_JS) }),
        )
        .route(
            "/vendor/three.core.js",
            get(|| async { asset("text/javascript; charset=utf-8", THREE_CORE_JS) }),
        )
        .route(
            "/vendor/OrbitControls.js",
            get(|| async { asset("text/javascript; charset=utf-8", ORBIT_CONTROLS_JS) }),
        )
        .route(
            "/vendor/LICENSE",
            get(|| async { asset("text/plain; charset=utf-8", THREE_LICENSE) }),
        )
        .route("/overview", get(overview::page))
        .route("/api/overview", get(overview::api_overview))
        .route("/api/picture", get(overview::api_picture))
        .route("/api/sessions", get(api_sessions))
        .route("/api/relay", get(api_relay))
        .route("/ws", get(ws_upgrade))
        .with_state(relay)
}

fn asset(content_type: &'static str, body: &'static [u8]) -> Response {
    ([(header::CONTENT_TYPE, content_type)], body).into_response()
}

async fn api_relay(State(relay): State<Arc<Relay>>) -> Response {
    axum::Json(relay.counters_json()).into_response()
}

async fn api_sessions(State(relay): State<Arc<Relay>>) -> Response {
    let mut ctl = SessionControlClient::new(relay.channel.clone());
    let ids = match ctl.list_sessions(ListSessionsRequest {}).await {
        Ok(r) => r.into_inner().session_ids,
        Err(status) => {
            relay.note_refusal(&status);
            let e = ClientError::from(status);
            return (
                StatusCode::BAD_GATEWAY,
                axum::Json(json!({"error": e.to_string()})),
            )
                .into_response();
        }
    };
    let mut out = Vec::new();
    for id in ids {
        let request = GetStatsRequest {
            session_id: id.clone(),
        };
        if let Ok(r) = ctl.get_stats(request).await {
            out.push(stats_json(&r.into_inner()));
        }
    }
    axum::Json(Value::Array(out)).into_response()
}

/// A session id as the daemon makes them (and nothing that could be anything else).
pub(crate) fn valid_session_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 64
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// Parses a browser rate: a number in 0.1 ..= 60 Hz.
fn parse_rate(text: &str) -> Option<f64> {
    text.trim()
        .parse::<f64>()
        .ok()
        .filter(|r| r.is_finite() && (MIN_BROWSER_RATE_HZ..=MAX_BROWSER_RATE_HZ).contains(r))
}

async fn ws_upgrade(
    State(relay): State<Arc<Relay>>,
    Query(q): Query<HashMap<String, String>>,
    ws: WebSocketUpgrade,
) -> Response {
    let id = q.get("session").cloned().unwrap_or_default();
    if !valid_session_id(&id) {
        return (
            StatusCode::BAD_REQUEST,
            "session: give the id of a running session (letters, digits, - and _)",
        )
            .into_response();
    }
    let rate = match q.get("rate") {
        None => relay.cfg.default_rate_hz.min(MAX_BROWSER_RATE_HZ),
        Some(t) => {
            match parse_rate(t) {
                Some(r) => r,
                None => {
                    return (
                    StatusCode::BAD_REQUEST,
                    format!("rate = {t:?}: expected {MIN_BROWSER_RATE_HZ} ..= {MAX_BROWSER_RATE_HZ} Hz"),
                )
                    .into_response();
                }
            }
        }
    };
    ws.max_message_size(64 << 10)
        .on_upgrade(move |socket| browser(relay, id, rate, socket))
}

/// What one browser has and wants.
struct BrowserState {
    reference: Option<u64>,
    topology: Option<u64>,
    last_seq: u64,
    rate_hz: f64,
}

/// One browser: a writer task behind a bounded queue, and a loop that samples the session's
/// latest frame at the browser's rate.
async fn browser(relay: Arc<Relay>, id: String, rate_hz: f64, socket: WebSocket) {
    let (mut sink, mut incoming) = socket.split();
    let (tx, mut rx) = mpsc::channel::<Message>(BROWSER_QUEUE);
    let writer = tokio::spawn(async move {
        while let Some(m) = rx.recv().await {
            if sink.send(m).await.is_err() {
                break;
            }
        }
        let _ = sink.close().await;
    });
    let s = relay.join(&id);
    let mut latest = s.latest.subscribe();
    let mut status = s.status.subscribe();
    // The current message first (an error that came before this browser, or the last status).
    status.mark_changed();
    let mut st = BrowserState {
        reference: None,
        topology: None,
        last_seq: 0,
        rate_hz,
    };
    let hello = json!({"type": "hello", "session_id": id, "rate_hz": rate_hz});
    let _ = tx.try_send(Message::Text(hello.to_string().into()));
    let mut tick = interval(st.rate_hz);
    loop {
        tokio::select! {
            _ = tick.tick() => {
                let frame = latest.borrow_and_update().clone();
                if let Some(f) = frame.filter(|f| f.seq != st.last_seq) {
                    send_frame(&f, &mut st, &tx, &s.counters);
                }
            }
            r = status.changed() => {
                if r.is_err() {
                    break;
                }
                let m = status.borrow_and_update().clone();
                if let Some(m) = m {
                    let last = !m.contains("\"type\":\"status\"");
                    let _ = tx.try_send(Message::Text(m.as_str().into()));
                    if last {
                        break; // error or ended: the socket closes after it
                    }
                }
            }
            m = incoming.next() => match m {
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => break,
                Some(Ok(Message::Text(t))) => {
                    if let Some(reply) = control(t.as_str(), &mut st) {
                        let _ = tx.try_send(Message::Text(reply.into()));
                    } else {
                        tick = interval(st.rate_hz);
                    }
                }
                Some(Ok(Message::Binary(_))) => {
                    let e = json!({"type": "error", "message": "binary messages are not accepted"});
                    let _ = tx.try_send(Message::Text(e.to_string().into()));
                }
                Some(Ok(_)) => {}
            }
        }
    }
    relay.leave(&id, &s);
    drop(tx);
    let _ = writer.await;
}

fn interval(rate_hz: f64) -> tokio::time::Interval {
    let mut t = tokio::time::interval(Duration::from_secs_f64(1.0 / rate_hz));
    t.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    t
}

/// Queues frame `f` (or a keyframe for it) for a browser with state `st`; a full queue drops
/// it (counted) and leaves `st` as it was, so a missing keyframe is retried.
fn send_frame(
    f: &RelayFrame,
    st: &mut BrowserState,
    tx: &mpsc::Sender<Message>,
    c: &RelayCounters,
) {
    let (bytes, reference, topology) = if f.fits(st.reference, st.topology) {
        (f.encoded.clone(), st.reference, st.topology)
    } else if f.frame.position_delta.is_empty()
        && !f.frame.positions_m.is_empty()
        && f.frame.keyframe_id == 0
    {
        // Absolute positions: only needs the topology.
        let Some(k) = f.keyframe(st.topology != Some(f.frame.topology_version)) else {
            return;
        };
        (k, None, Some(f.frame.topology_version))
    } else {
        let with_topology = st.topology != Some(f.frame.topology_version);
        let chained = if with_topology {
            None
        } else {
            f.chained(st.reference)
        };
        let Some(k) = chained.or_else(|| f.keyframe(with_topology)) else {
            return;
        };
        (k, Some(f.frame.keyframe_id), Some(f.frame.topology_version))
    };
    let len = bytes.len() as u64;
    match tx.try_send(Message::Binary(bytes)) {
        Ok(()) => {
            st.reference = reference;
            st.topology = topology;
            st.last_seq = f.seq;
            c.frames_sent.fetch_add(1, Ordering::Relaxed);
            c.bytes_sent.fetch_add(len, Ordering::Relaxed);
        }
        Err(_) => {
            c.frames_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Applies a browser's control message; `Some(reply)` is an error to send back.
fn control(text: &str, st: &mut BrowserState) -> Option<String> {
    let err = |m: String| Some(json!({"type": "error", "message": m}).to_string());
    let Ok(v) = serde_json::from_str::<Value>(text) else {
        return err("control messages are JSON objects with a \"type\"".into());
    };
    match v.get("type").and_then(Value::as_str) {
        Some("keyframe") => {
            st.reference = None;
            st.topology = None;
            st.last_seq = 0;
            None
        }
        Some("rate") => match v.get("hz").and_then(Value::as_f64) {
            Some(hz)
                if hz.is_finite() && (MIN_BROWSER_RATE_HZ..=MAX_BROWSER_RATE_HZ).contains(&hz) =>
            {
                st.rate_hz = hz;
                None
            }
            _ => err(format!(
                "rate: \"hz\" must be a number in {MIN_BROWSER_RATE_HZ} ..= {MAX_BROWSER_RATE_HZ}"
            )),
        },
        _ => err("unknown control message; expected type \"keyframe\" or \"rate\"".into()),
    }
}

/// Binds the web viewer's listener on `addr`, `HOST:PORT`: a numeric address (`127.0.0.1:8080`,
/// `0.0.0.0:0`, `[::1]:0`) or a host name the system resolves (`localhost:8080`). Of several
/// resolved addresses (`localhost` may give `::1` and `127.0.0.1`) the first one, in the
/// resolver's order, that can be bound is used: one listener, whose address `local_addr` gives
/// (with port 0 several listeners would each get a different port).
///
/// # Errors
/// [`ClientError::Listen`] when `addr` is not `HOST:PORT`, does not resolve, resolves to no
/// address, or no resolved address can be bound (the last one tried and its error).
pub async fn bind(addr: &str) -> Result<TcpListener, ClientError> {
    let listen = |reason: String| ClientError::Listen {
        addr: addr.to_string(),
        reason,
    };
    let resolved: Vec<std::net::SocketAddr> = tokio::net::lookup_host(addr)
        .await
        .map_err(|e| {
            listen(format!(
                "{e} (expected HOST:PORT, e.g. 127.0.0.1:8080, localhost:8080 or [::1]:8080)"
            ))
        })?
        .collect();
    let mut last = None;
    for a in &resolved {
        match TcpListener::bind(a).await {
            Ok(l) => return Ok(l),
            Err(e) => last = Some(format!("{a}: {e}")),
        }
    }
    Err(listen(last.unwrap_or_else(|| {
        "the name resolves to no address".into()
    })))
}

/// Serves the web viewer on `listener` until `shutdown` completes.
///
/// # Errors
/// [`ClientError::InvalidConfig`] for bad rates; [`ClientError::Connect`] for a malformed
/// server URL; [`ClientError::Io`] when serving fails.
pub async fn run(
    listener: TcpListener,
    cfg: WebConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ClientError> {
    let relay = Relay::new(cfg)?;
    serve(listener, relay, shutdown).await
}

/// Serves `relay` on `listener` until `shutdown` resolves, or until the daemon refuses the
/// relay's credentials (an error then: the relay reports and stops rather than serve pages
/// that can only fail).
///
/// # Errors
/// [`ClientError::Io`] when serving fails; [`ClientError::Rpc`] with the daemon's refusal.
pub async fn serve(
    listener: TcpListener,
    relay: Arc<Relay>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ClientError> {
    let addr = listener.local_addr().map_err(|source| ClientError::Io {
        path: "listener".into(),
        source,
    })?;
    tracing::info!("web viewer on http://{addr}/");
    let mut refused = relay.refused.subscribe();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let served = axum::serve(listener, router(relay.clone())).with_graceful_shutdown(async move {
        tokio::select! {
            () = shutdown => {}
            _ = stop_rx => {}
        }
    });
    let mut server = tokio::spawn(async move { served.await });
    let io = |source| ClientError::Io {
        path: format!("http://{addr}/").into(),
        source,
    };
    let task = |e: tokio::task::JoinError| ClientError::Task(e.to_string());
    let refusal = tokio::select! {
        done = &mut server => return done.map_err(task)?.map_err(io),
        r = refused.wait_for(Option::is_some) => match r {
            Ok(r) => r.clone(),
            // The relay outlives the server, so its sender cannot go first; serve on.
            Err(_) => return server.await.map_err(task)?.map_err(io),
        },
    };
    let _ = stop_tx.send(());
    server.await.map_err(task)?.map_err(io)?;
    match refusal {
        Some((code, message)) => {
            tracing::error!("the daemon refused the relay's credentials: {message}");
            Err(tonic::Status::new(code, message).into())
        }
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_listen_address_may_be_a_host_name_or_a_numeric_address() {
        let local = |l: TcpListener| l.local_addr().unwrap();
        let a = local(bind("localhost:0").await.unwrap());
        assert!(
            a.ip().is_loopback() && a.port() != 0,
            "localhost:0 bound {a}"
        );
        let a = local(bind("0.0.0.0:0").await.unwrap());
        assert!(
            a.ip().is_unspecified() && a.is_ipv4(),
            "0.0.0.0:0 bound {a}"
        );
        let a = local(bind("127.0.0.1:0").await.unwrap());
        assert_eq!(a.ip(), std::net::Ipv4Addr::LOCALHOST);
        // IPv6 loopback, where the machine has one.
        match std::net::TcpListener::bind("[::1]:0") {
            Ok(_) => {
                let a = local(bind("[::1]:0").await.unwrap());
                assert_eq!(a.ip(), std::net::Ipv6Addr::LOCALHOST);
            }
            Err(e) => {
                use std::io::Write;
                let _ = std::io::stderr().write_all(
                    format!("SKIPPED [::1]:0 in web::bind's test: no IPv6 loopback here: {e}\n")
                        .as_bytes(),
                );
            }
        }
        for bad in [
            "localhost",
            "no-such-host.invalid:0",
            "127.0.0.1:99999",
            ":",
        ] {
            let e = bind(bad).await.expect_err(bad);
            assert!(
                matches!(&e, ClientError::Listen { addr, .. } if addr == bad),
                "{bad}: {e:?}"
            );
            assert!(e.to_string().starts_with("cannot listen on "), "{e}");
        }
        // A port in use is reported with the address tried.
        let taken = bind("127.0.0.1:0").await.unwrap();
        let spec = taken.local_addr().unwrap().to_string();
        let e = bind(&spec).await.expect_err("port in use");
        assert!(e.to_string().contains(&spec), "{e}");
    }

    #[test]
    fn control_messages_are_checked() {
        let mut st = BrowserState {
            reference: Some(3),
            topology: Some(0),
            last_seq: 9,
            rate_hz: 30.0,
        };
        assert!(control(r#"{"type":"rate","hz":10}"#, &mut st).is_none());
        assert_eq!(st.rate_hz, 10.0);
        for bad in [
            "",
            "nope",
            "[]",
            r#"{"type":"rate","hz":"x"}"#,
            r#"{"type":"rate","hz":1e9}"#,
            r#"{"type":"rate","hz":0}"#,
            r#"{"type":"boom"}"#,
        ] {
            let reply = control(bad, &mut st).unwrap_or_else(|| panic!("accepted {bad:?}"));
            assert!(reply.contains("\"error\""), "{reply}");
        }
        assert_eq!(st.rate_hz, 10.0);
        assert!(control(r#"{"type":"keyframe"}"#, &mut st).is_none());
        assert_eq!((st.reference, st.topology, st.last_seq), (None, None, 0));
    }

    fn frame(seq: u64, keyframe_id: u64, keyframe: bool) -> RelayFrame {
        let f = SurfaceFrame {
            keyframe,
            positions_m: if keyframe { vec![0.0; 9] } else { vec![] },
            triangles: if keyframe { vec![0, 1, 2] } else { vec![] },
            quantum_m: 1e-6,
            keyframe_id,
            ..Default::default()
        };
        RelayFrame {
            seq,
            encoded: Bytes::from(f.encode_to_vec()),
            reference: Some(Arc::new(vec![0.0; 9])),
            topology: Some((Arc::new(vec![0, 1, 2]), Arc::new(vec![0.0; 9]))),
            chain: None,
            frame: f,
            chained: OnceLock::new(),
            keyframe: OnceLock::new(),
            keyframe_with_topology: OnceLock::new(),
        }
    }

    #[test]
    fn a_slow_browser_drops_frames_and_gets_its_keyframe_later() {
        let (tx, mut rx) = mpsc::channel(1);
        let c = RelayCounters::default();
        let mut st = BrowserState {
            reference: None,
            topology: None,
            last_seq: 0,
            rate_hz: 30.0,
        };
        tx.try_send(Message::Text("busy".into())).unwrap();
        // The queue is full: the keyframe this browser needs is dropped and counted, and its
        // state still says it lacks the reference.
        let f = frame(1, 1, false);
        send_frame(&f, &mut st, &tx, &c);
        assert_eq!(c.frames_dropped.load(Ordering::Relaxed), 1);
        assert_eq!((st.reference, st.topology, st.last_seq), (None, None, 0));
        // Room again: it gets a keyframe with the topology, then plain frames.
        let _ = rx.try_recv();
        send_frame(&f, &mut st, &tx, &c);
        let Ok(Message::Binary(b)) = rx.try_recv() else {
            panic!("no binary message");
        };
        let k = SurfaceFrame::decode(b).unwrap();
        assert!(k.keyframe && k.triangles == [0, 1, 2] && k.positions_m.len() == 9);
        assert_eq!(
            (st.reference, st.topology, st.last_seq),
            (Some(1), Some(0), 1)
        );
        send_frame(&frame(2, 1, false), &mut st, &tx, &c);
        let Ok(Message::Binary(b)) = rx.try_recv() else {
            panic!("no binary message");
        };
        assert!(!SurfaceFrame::decode(b).unwrap().keyframe);
        assert_eq!(c.frames_sent.load(Ordering::Relaxed), 2);
    }

    #[test]
    fn session_ids_and_rates_are_checked() {
        assert!(valid_session_id("8a765e80f817"));
        for bad in ["", "../etc", "a b", &"x".repeat(65), "é"] {
            assert!(!valid_session_id(bad), "{bad:?}");
        }
        assert_eq!(parse_rate("30"), Some(30.0));
        for bad in ["0", "-1", "NaN", "inf", "61", "x", "1e400"] {
            assert_eq!(parse_rate(bad), None, "{bad:?}");
        }
    }
}
