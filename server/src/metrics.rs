//! The Prometheus endpoint (`GET /metrics`, OpenMetrics text) with the official
//! `prometheus-client` crate: a [`Collector`] reads every session's published statistics at
//! scrape time, so nothing runs between scrapes and the servo does no extra work beyond
//! counting its step and pose-to-force times into fixed buckets
//! ([`crate::servo::LatencyBuckets`]).
//!
//! Per session (labels `session`, `scene`, `family`): loop rate, steps, overruns, step-time and
//! pose-to-force histograms (seconds), device samples accepted, rejected and outside the
//! device's declared workspace, faulted, in
//! contact, simulated time, peak force, watchers and their frames/bytes, active elements and
//! particles, surface vertices. Per tool slot (issue 50; labels `session`, `scene`, `family`,
//! `tool` (the tool id, "" for the default tool) and `slot`): connected, in contact, force,
//! pose-to-force histogram, samples accepted, rejected and outside the workspace. Process-wide:
//! the number of sessions.
//!
//! Neighbours: [`crate::run`] spawns [`serve`] when `metrics_listen` is configured; the data come
//! from [`crate::session::SessionManager`] and [`crate::servo::StatsSnapshot`].

use std::fmt;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;

use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric, MetricEncoder};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Registry;
use tokio::net::TcpListener;

use crate::servo::{LATENCY_BUCKET_BOUNDS_US, LatencyBuckets, StatsSnapshot, ToolStatsSnapshot};
use crate::session::{Session, SessionManager, ToolSlot};

/// OpenMetrics text, as Prometheus negotiates it.
pub const CONTENT_TYPE_OPENMETRICS: &str =
    "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Reads the sessions' statistics at each scrape.
pub struct SessionCollector {
    manager: Arc<SessionManager>,
}

impl fmt::Debug for SessionCollector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SessionCollector").finish_non_exhaustive()
    }
}

impl SessionCollector {
    /// A collector over `manager`'s sessions.
    pub fn new(manager: Arc<SessionManager>) -> Self {
        Self { manager }
    }
}

/// One session's row at scrape time.
struct Row {
    session: Arc<Session>,
    stats: StatsSnapshot,
}

impl Row {
    fn labels(&self) -> [(&'static str, &str); 3] {
        [
            ("session", self.session.id.as_str()),
            ("scene", self.session.scene.as_str()),
            ("family", self.session.family),
        ]
    }
}

/// What a per-session metric encodes.
enum Value {
    Gauge(f64),
    Counter(u64),
    Histogram(LatencyBuckets),
}

fn encode_value(m: &mut MetricEncoder<'_>, v: Value) -> fmt::Result {
    match v {
        Value::Gauge(g) => m.encode_gauge(&g),
        Value::Counter(c) => {
            m.encode_counter::<prometheus_client::encoding::NoLabelSet, _, u64>(&c, None)
        }
        Value::Histogram(b) => {
            let buckets: [(f64, u64); LATENCY_BUCKET_BOUNDS_US.len() + 1] =
                std::array::from_fn(|i| {
                    let le = LATENCY_BUCKET_BOUNDS_US
                        .get(i)
                        .map_or(f64::INFINITY, |&us| us as f64 / 1e6);
                    (le, b.counts[i])
                });
            m.encode_histogram::<prometheus_client::encoding::NoLabelSet>(
                b.sum_us as f64 / 1e6,
                b.count(),
                &buckets,
                None,
            )
        }
    }
}

fn per_session(
    enc: &mut DescriptorEncoder<'_>,
    rows: &[Row],
    name: &str,
    help: &str,
    metric_type: MetricType,
    value: impl Fn(&Row) -> Value,
) -> fmt::Result {
    let mut m = enc.encode_descriptor(name, help, None, metric_type)?;
    for r in rows {
        let labels = r.labels();
        let mut family = m.encode_family(&labels)?;
        encode_value(&mut family, value(r))?;
    }
    Ok(())
}

/// How one per-session metric is read from a session's row.
type Extract = fn(&Row) -> Value;

/// The per-session metrics: name, help, type and value, in scrape order.
const SESSION_METRICS: &[(&str, &str, MetricType, Extract)] = {
    use MetricType::{Counter, Gauge, Histogram};
    &[
        (
            "hapticd_loop_rate_hz",
            "Servo ticks per second of wall time",
            Gauge,
            |r| Value::Gauge(r.stats.loop_rate_hz),
        ),
        ("hapticd_steps", "Servo ticks run", Counter, |r| {
            Value::Counter(r.stats.steps)
        }),
        ("hapticd_overruns", "Late servo ticks", Counter, |r| {
            Value::Counter(r.stats.overruns)
        }),
        (
            "hapticd_step_time_seconds",
            "Servo step compute time",
            Histogram,
            |r| Value::Histogram(r.stats.step_buckets),
        ),
        (
            "hapticd_pose_to_force_seconds",
            "Device pose received to force command pushed",
            Histogram,
            |r| Value::Histogram(r.stats.pose_to_force_buckets),
        ),
        (
            "hapticd_device_samples",
            "Device samples accepted",
            Counter,
            |r| Value::Counter(r.stats.device_samples),
        ),
        (
            "hapticd_rejected_samples",
            "Device samples rejected (non-finite, absurd, out of order)",
            Counter,
            |r| Value::Counter(r.session.shared.rejected_samples.load(Relaxed)),
        ),
        (
            "hapticd_out_of_workspace_samples",
            "Device samples dropped outside the workspace the device declared",
            Counter,
            |r| Value::Counter(r.session.shared.out_of_workspace_samples.load(Relaxed)),
        ),
        (
            "hapticd_faulted",
            "1 when the session is quarantined (zero force) after a fault",
            Gauge,
            |r| Value::Gauge(if r.stats.fault.is_some() { 1.0 } else { 0.0 }),
        ),
        (
            "hapticd_in_contact",
            "1 while the probe touches the body",
            Gauge,
            |r| Value::Gauge(if r.stats.in_contact { 1.0 } else { 0.0 }),
        ),
        ("hapticd_sim_time_seconds", "Simulated time", Gauge, |r| {
            Value::Gauge(r.stats.sim_time_s)
        }),
        (
            "hapticd_peak_force_newtons",
            "Largest device force magnitude so far",
            Gauge,
            |r| Value::Gauge(r.stats.peak_force_n),
        ),
        ("hapticd_watchers", "Surface streams open", Gauge, |r| {
            Value::Gauge(r.session.watcher_stats.watchers.load(Relaxed) as f64)
        }),
        (
            "hapticd_watcher_frames_sent",
            "Frames queued to watchers",
            Counter,
            |r| Value::Counter(r.session.watcher_stats.frames_sent.load(Relaxed)),
        ),
        (
            "hapticd_watcher_frames_dropped",
            "Frames a watcher was due but its queue was full",
            Counter,
            |r| Value::Counter(r.session.watcher_stats.frames_dropped.load(Relaxed)),
        ),
        (
            "hapticd_watcher_bytes_sent",
            "Encoded bytes of frames queued to watchers",
            Counter,
            |r| Value::Counter(r.session.watcher_stats.bytes_sent.load(Relaxed)),
        ),
        (
            "hapticd_active_elements",
            "Elements simulated with full dynamics",
            Gauge,
            |r| Value::Gauge(r.stats.body.active_elements as f64),
        ),
        (
            "hapticd_region_swaps",
            "Active regions swapped in by a region that follows the probe",
            Counter,
            |r| Value::Counter(r.stats.body.region_swaps),
        ),
        (
            "hapticd_region_tiles",
            "Regions of a following region's cache (0 without one)",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tiles as f64),
        ),
        (
            "hapticd_region_tiles_ready",
            "Regions of a following region's cache prepared so far",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tiles_ready as f64),
        ),
        (
            "hapticd_region_tiles_loaded",
            "Regions of a following region's cache read from the region cache on disk",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tiles_loaded as f64),
        ),
        (
            "hapticd_region_tiles_refused",
            "Files of the region cache on disk refused (damaged, foreign: prepared again)",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tiles_refused as f64),
        ),
        (
            "hapticd_region_tile_memory_bytes",
            "Bytes the regions of a following region's cache hold in memory",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tile_memory_bytes as f64),
        ),
        (
            "hapticd_region_tiles_dropped",
            "Regions dropped from memory for region_cache_memory_bytes (their files stay)",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tiles_dropped as f64),
        ),
        (
            "hapticd_region_tiles_reloaded",
            "Dropped regions read back from the region cache on disk",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tiles_reloaded as f64),
        ),
        (
            "hapticd_region_tile_misses",
            "Region requests whose region was not in memory (read or prepared meanwhile)",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_tile_misses as f64),
        ),
        (
            "hapticd_region_unmapped_swaps",
            "Region swaps beyond the far nodes the previous region mapped",
            Gauge,
            |r| Value::Gauge(r.stats.body.region_unmapped_swaps as f64),
        ),
        (
            "hapticd_contact_ticks",
            "Servo ticks with the probe in contact",
            Counter,
            |r| Value::Counter(r.stats.contact_ticks),
        ),
        (
            "hapticd_companion_ticks",
            "Contact ticks to which a following region's coarse companion contributed",
            Counter,
            |r| Value::Counter(r.stats.body.companion_ticks),
        ),
        (
            "hapticd_session_threads",
            "Threads the session's tick uses (servo thread plus working tick-pool workers)",
            Gauge,
            |r| Value::Gauge(f64::from(r.session.threads_now(&r.stats))),
        ),
        (
            "hapticd_pool_wait_max_seconds",
            "Longest wait of the servo for a part of its tick a pool worker had claimed",
            Gauge,
            |r| Value::Gauge(r.stats.pool_wait_us_max as f64 * 1e-6),
        ),
        (
            "hapticd_active_particles",
            "Meshfree particles simulated now",
            Gauge,
            |r| Value::Gauge(r.stats.body.active_particles as f64),
        ),
        (
            "hapticd_surface_vertices",
            "Vertices of the surface viewers receive",
            Gauge,
            |r| Value::Gauge(r.stats.body.surface_vertices as f64),
        ),
    ]
};

/// One tool slot's row at scrape time.
struct ToolRow<'a> {
    session: &'a Row,
    tool: &'a ToolSlot,
    tool_id: String,
    slot: String,
    stats: ToolStatsSnapshot,
}

/// A 0/1 gauge.
fn flag(b: bool) -> Value {
    Value::Gauge(if b { 1.0 } else { 0.0 })
}

/// How one per-tool metric is read from a tool's row.
type ToolExtract = fn(&ToolRow<'_>) -> Value;

/// The per-tool metrics: name, help, type and value, in scrape order.
const TOOL_METRICS: &[(&str, &str, MetricType, ToolExtract)] = {
    use MetricType::{Counter, Gauge, Histogram};
    &[
        (
            "hapticd_tool_connected",
            "1 while a device stream drives the tool slot",
            Gauge,
            |r| flag(r.tool.connected()),
        ),
        (
            "hapticd_tool_in_contact",
            "1 while the tool touches the body",
            Gauge,
            |r| flag(r.stats.in_contact),
        ),
        (
            "hapticd_tool_force_newtons",
            "Force magnitude on the tool's device at the last statistics publication",
            Gauge,
            |r| Value::Gauge(r.stats.force_n),
        ),
        (
            "hapticd_tool_pose_to_force_seconds",
            "The tool's device pose received to force command pushed",
            Histogram,
            |r| Value::Histogram(r.stats.pose_to_force_buckets),
        ),
        (
            "hapticd_tool_device_samples",
            "The tool's device samples accepted",
            Counter,
            |r| Value::Counter(r.stats.device_samples),
        ),
        (
            "hapticd_tool_rejected_samples",
            "The tool's device samples rejected (non-finite, absurd, another session's)",
            Counter,
            |r| Value::Counter(r.tool.rejected_samples.load(Relaxed)),
        ),
        (
            "hapticd_tool_out_of_workspace_samples",
            "The tool's device samples dropped outside its declared workspace",
            Counter,
            |r| Value::Counter(r.tool.out_of_workspace_samples.load(Relaxed)),
        ),
    ]
};

fn per_tool(
    enc: &mut DescriptorEncoder<'_>,
    rows: &[ToolRow<'_>],
    (name, help, metric_type, value): (&str, &str, MetricType, ToolExtract),
) -> fmt::Result {
    let mut m = enc.encode_descriptor(name, help, None, metric_type)?;
    for r in rows {
        let [a, b, c] = r.session.labels();
        let labels = [
            a,
            b,
            c,
            ("tool", r.tool_id.as_str()),
            ("slot", r.slot.as_str()),
        ];
        let mut family = m.encode_family(&labels)?;
        encode_value(&mut family, value(r))?;
    }
    Ok(())
}

impl Collector for SessionCollector {
    fn encode(&self, mut enc: DescriptorEncoder<'_>) -> fmt::Result {
        let rows: Vec<Row> = self
            .manager
            .ids()
            .iter()
            .filter_map(|id| self.manager.get(id).ok())
            .map(|session| Row {
                stats: session.stats(),
                session,
            })
            .collect();
        let sessions = ConstGauge::new(rows.len() as i64);
        sessions.encode(enc.encode_descriptor(
            "hapticd_sessions",
            "Sessions running",
            None,
            MetricType::Gauge,
        )?)?;
        for &(name, help, metric_type, value) in SESSION_METRICS {
            per_session(&mut enc, &rows, name, help, metric_type, value)?;
        }
        let tools: Vec<ToolRow<'_>> = rows
            .iter()
            .flat_map(|r| {
                r.session.tools.iter().map(move |t| ToolRow {
                    session: r,
                    tool: t,
                    tool_id: t.tool_id(),
                    slot: t.slot.to_string(),
                    stats: r.stats.tools.get(t.slot).copied().unwrap_or_default(),
                })
            })
            .collect();
        for &metric in TOOL_METRICS {
            per_tool(&mut enc, &tools, metric)?;
        }
        Ok(())
    }
}

/// The registry with the session collector.
pub fn registry(manager: Arc<SessionManager>) -> Registry {
    let mut registry = Registry::default();
    registry.register_collector(Box::new(SessionCollector::new(manager)));
    registry
}

/// The scrape body: OpenMetrics text of `registry`.
///
/// # Errors
/// A formatting error of the encoder (not expected with a `String` writer).
pub fn render(registry: &Registry) -> Result<String, fmt::Error> {
    let mut text = String::new();
    prometheus_client::encoding::text::encode(&mut text, registry)?;
    Ok(text)
}

/// Serves `GET /metrics` on `listener` until the process ends. Errors of one connection are
/// logged, never fatal.
pub async fn serve(listener: TcpListener, manager: Arc<SessionManager>) {
    let registry = Arc::new(registry(manager));
    let app = axum::Router::new().route(
        "/metrics",
        axum::routing::get(move || {
            let registry = registry.clone();
            async move {
                match render(&registry) {
                    Ok(text) => ([(CONTENT_TYPE, CONTENT_TYPE_OPENMETRICS)], text).into_response(),
                    Err(_) => axum::http::StatusCode::INTERNAL_SERVER_ERROR.into_response(),
                }
            }
        }),
    );
    if let Err(e) = axum::serve(listener, app).await {
        tracing::warn!("metrics endpoint stopped: {e}");
    }
}
