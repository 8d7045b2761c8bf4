//! Helpers of the viewer benchmarks (`tests/benches/stream_bytes.rs`, `tests/benches/watchers.rs`):
//! watchers that count what they receive (gRPC `Watch` streams and relay WebSockets), CPU time
//! and memory of a process from `/proc`, and nearest-rank percentiles (`hdrhistogram`). Loopback only; every
//! loop is bounded by a deadline or a stop flag.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context, Result};
use futures_util::StreamExt;
use haptics_proto::v1::{SurfaceEncoding, SurfaceFrame, WatchRequest};
use hdrhistogram::Histogram;
use prost::Message as _;

/// What one watcher received.
#[derive(Debug, Default)]
pub struct Received {
    /// Frames (binary messages) received.
    pub frames: AtomicU64,
    /// Keyframes among them.
    pub keyframes: AtomicU64,
    /// Encoded bytes of the frames (protobuf message sizes).
    pub bytes: AtomicU64,
    /// Keyframe bytes among them.
    pub keyframe_bytes: AtomicU64,
    /// Set when the stream failed or ended early.
    pub failed: AtomicBool,
}

impl Received {
    fn count(&self, f: &SurfaceFrame, len: u64) {
        self.frames.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(len, Ordering::Relaxed);
        if f.keyframe {
            self.keyframes.fetch_add(1, Ordering::Relaxed);
            self.keyframe_bytes.fetch_add(len, Ordering::Relaxed);
        }
    }

    /// `(frames, keyframes, bytes, keyframe_bytes)` now.
    pub fn snapshot(&self) -> (u64, u64, u64, u64) {
        (
            self.frames.load(Ordering::Relaxed),
            self.keyframes.load(Ordering::Relaxed),
            self.bytes.load(Ordering::Relaxed),
            self.keyframe_bytes.load(Ordering::Relaxed),
        )
    }
}

/// Starts a gRPC watcher of `session` on its own connection to `url`, counting frames until
/// `stop` is set. `compact`: DELTA encoding (1 um), else FULL.
///
/// # Errors
/// Connection or `Watch` failure.
pub async fn grpc_watcher(
    url: &str,
    session: &str,
    rate_hz: f64,
    compact: bool,
    stop: Arc<AtomicBool>,
) -> Result<Arc<Received>> {
    let mut client = crate::surface_stream(url)
        .await?
        .max_decoding_message_size(64 << 20);
    let mut stream = client
        .watch(WatchRequest {
            session_id: session.to_string(),
            max_rate_hz: rate_hz,
            encoding: if compact {
                SurfaceEncoding::Delta as i32
            } else {
                SurfaceEncoding::Full as i32
            },
            quantum_m: 0.0,
        })
        .await
        .context("Watch")?
        .into_inner();
    let rec = Arc::new(Received::default());
    let r = rec.clone();
    tokio::spawn(async move {
        while !stop.load(Ordering::Relaxed) {
            match tokio::time::timeout(Duration::from_millis(500), stream.message()).await {
                Err(_) => continue,
                Ok(Ok(Some(f))) => r.count(&f, f.encoded_len() as u64),
                Ok(_) => {
                    r.failed.store(true, Ordering::Relaxed);
                    break;
                }
            }
        }
    });
    Ok(rec)
}

/// Starts a WebSocket watcher of `session` on the relay at `addr`, counting binary frames
/// until `stop` is set.
///
/// # Errors
/// The connection or upgrade fails.
pub async fn ws_watcher(
    addr: &str,
    session: &str,
    rate_hz: f64,
    stop: Arc<AtomicBool>,
) -> Result<Arc<Received>> {
    let url = format!("ws://{addr}/ws?session={session}&rate={rate_hz}");
    let (mut ws, _) = tokio_tungstenite::connect_async(url.as_str())
        .await
        .with_context(|| format!("connecting to {url}"))?;
    let rec = Arc::new(Received::default());
    let r = rec.clone();
    tokio::spawn(async move {
        use tokio_tungstenite::tungstenite::Message;
        while !stop.load(Ordering::Relaxed) {
            match tokio::time::timeout(Duration::from_millis(500), ws.next()).await {
                Err(_) => continue,
                Ok(Some(Ok(Message::Binary(b)))) => {
                    if let Ok(f) = SurfaceFrame::decode(b.clone()) {
                        r.count(&f, b.len() as u64);
                    }
                }
                Ok(Some(Ok(_))) => {}
                Ok(_) => {
                    r.failed.store(true, Ordering::Relaxed);
                    break;
                }
            }
        }
    });
    Ok(rec)
}

/// CPU time (user + system) of process `pid`, seconds, from `/proc/PID/stat`.
///
/// # Errors
/// The file is missing or malformed (not Linux, process gone).
pub fn cpu_seconds(pid: u32) -> Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let rest = stat.rsplit_once(')').context("malformed stat")?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = f.get(11).context("utime")?.parse()?;
    let stime: f64 = f.get(12).context("stime")?.parse()?;
    // SAFETY: sysconf is a plain query.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    Ok((utime + stime) / hz)
}

/// `(VmRSS, VmHWM)` of process `pid`, bytes, from `/proc/PID/status`.
///
/// # Errors
/// The file is missing or lacks the fields.
pub fn memory_bytes(pid: u32) -> Result<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let field = |name: &str| -> Result<u64> {
        let line = status
            .lines()
            .find(|l| l.starts_with(name))
            .with_context(|| format!("{name} missing"))?;
        let kb: u64 = line.split_whitespace().nth(1).context("value")?.parse()?;
        Ok(kb * 1024)
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

/// Nearest-rank percentile `q` in `[0, 1]` of `v`; 0 when empty. The values go to an
/// `hdrhistogram` in thousandths (rounded; 3 significant digits): exact below 2.048, otherwise
/// the upper end of the sample's bucket, at most 0.1 % above it. Negative values count as 0.
pub fn percentile(v: &[f64], q: f64) -> f64 {
    // 3 significant digits is within the crate's 0..=5; the histogram grows to any value.
    let mut h = Histogram::<u64>::new(3).expect("3 significant digits is valid");
    for &x in v {
        let milli = (x.max(0.0) * 1e3).round() as u64;
        if h.record(milli).is_err() {
            h.saturating_record(milli);
        }
    }
    if h.is_empty() {
        return 0.0;
    }
    h.value_at_quantile(q.clamp(0.0, 1.0)) as f64 / 1e3
}

#[cfg(test)]
mod tests {
    use super::percentile;

    #[test]
    fn percentiles_are_nearest_rank_to_three_digits() {
        assert_eq!(percentile(&[], 0.5), 0.0);
        // Sorted 0.5, 1, 1.5, 2: ranks ceil(q n) = 2, 4, 1.
        let v = [2.0, 0.5, 1.5, 1.0];
        assert_eq!(percentile(&v, 0.5), 1.0);
        assert_eq!(percentile(&v, 0.99), 2.0);
        assert_eq!(percentile(&v, 0.0), 0.5);
        // 59.7 frames/s is 59 700 thousandths: within 0.1 %, never below.
        let p = percentile(&[59.7, 10.0, 80.25], 0.5);
        assert!((59.7..=59.7 * 1.001).contains(&p), "{p}");
    }
}
