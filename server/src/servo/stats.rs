//! The servo's statistics accumulators ([`ServoStats`]): preallocated histograms and counters,
//! copied into a [`StatsSnapshot`] every statistics window.

use haptic_model::body::{BodyStats, MAX_TOOLS};
use hdrhistogram::Histogram;

use super::{LatencyBuckets, StatsSnapshot, ToolStatsSnapshot};

/// The loop rate's current window: ticks since `start_us`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(super) struct RateWindow {
    /// Start of the window, µs.
    pub(super) start_us: u64,
    /// Ticks in the window.
    pub(super) ticks: u64,
}

/// Accumulated statistics of a servo (sized at construction: recording never allocates).
pub(super) struct ServoStats {
    pub(super) step_hist: Histogram<u64>,
    pub(super) p2f_hist: Histogram<u64>,
    pub(super) step_buckets: LatencyBuckets,
    pub(super) p2f_buckets: LatencyBuckets,
    pub(super) peak_force_n: f64,
    pub(super) contact_ticks: u64,
    pub(super) max_displacement_m: f64,
    pub(super) device_samples: u64,
    pub(super) device_silences: u64,
    pub(super) window: RateWindow,
    /// Overruns, maintained by the loop's [`super::Pacer`].
    pub(super) overruns: u64,
    /// Per tool slot (issue 50); the fields above add up all tools.
    pub(super) tools: [ToolAccum; MAX_TOOLS],
}

/// One tool slot's accumulators.
pub(super) struct ToolAccum {
    pub(super) p2f_hist: Histogram<u64>,
    pub(super) p2f_buckets: LatencyBuckets,
    pub(super) peak_force_n: f64,
    pub(super) contact_ticks: u64,
    pub(super) device_samples: u64,
    pub(super) device_silences: u64,
}

impl ToolAccum {
    fn new() -> Self {
        Self {
            p2f_hist: histogram(),
            p2f_buckets: LatencyBuckets::default(),
            peak_force_n: 0.0,
            contact_ticks: 0,
            device_samples: 0,
            device_silences: 0,
        }
    }

    /// This tool's part of a statistics snapshot (the caller fills in the tick's state:
    /// connected, contact, force, silence).
    pub(super) fn snapshot(&self) -> ToolStatsSnapshot {
        ToolStatsSnapshot {
            peak_force_n: self.peak_force_n,
            pose_to_force_p50_us: quantile(&self.p2f_hist, 0.5),
            pose_to_force_p99_us: quantile(&self.p2f_hist, 0.99),
            device_samples: self.device_samples,
            contact_ticks: self.contact_ticks,
            device_silences: self.device_silences,
            pose_to_force_buckets: self.p2f_buckets,
            ..ToolStatsSnapshot::default()
        }
    }
}

/// The `q` quantile of `h`, 0 when it is empty.
fn quantile(h: &Histogram<u64>, q: f64) -> f64 {
    if h.is_empty() {
        0.0
    } else {
        h.value_at_quantile(q) as f64
    }
}

fn histogram() -> Histogram<u64> {
    // 1 µs .. 60 s at 3 significant digits; fixed size, so recording never allocates.
    Histogram::new_with_bounds(1, 60_000_000, 3).expect("static histogram bounds")
}

impl ServoStats {
    /// Empty accumulators.
    pub(super) fn new() -> Self {
        Self {
            step_hist: histogram(),
            p2f_hist: histogram(),
            step_buckets: LatencyBuckets::default(),
            p2f_buckets: LatencyBuckets::default(),
            peak_force_n: 0.0,
            contact_ticks: 0,
            max_displacement_m: 0.0,
            device_samples: 0,
            device_silences: 0,
            window: RateWindow::default(),
            overruns: 0,
            tools: std::array::from_fn(|_| ToolAccum::new()),
        }
    }

    /// Records the duration of one model step, µs.
    pub(super) fn record_step(&mut self, us: u64) {
        self.step_hist.saturating_record(us.max(1));
        self.step_buckets.record(us);
    }

    /// Records one pose-to-force latency of tool slot `slot`, µs (the session's and the
    /// tool's).
    pub(super) fn record_pose_to_force(&mut self, slot: usize, us: u64) {
        self.p2f_hist.saturating_record(us.max(1));
        self.p2f_buckets.record(us);
        let t = &mut self.tools[slot];
        t.p2f_hist.saturating_record(us.max(1));
        t.p2f_buckets.record(us);
    }

    /// The statistics snapshot of these accumulators with the servo state's fields: `steps`
    /// ticks so far, loop rate `rate_hz`, and the caller's `state` part (copied as is).
    pub(super) fn snapshot(&self, steps: u64, rate_hz: f64, body: BodyStats) -> StatsSnapshot {
        StatsSnapshot {
            steps,
            overruns: self.overruns,
            loop_rate_hz: rate_hz,
            step_p50_us: self.step_hist.value_at_quantile(0.5) as f64,
            step_p99_us: self.step_hist.value_at_quantile(0.99) as f64,
            step_max_us: self.step_hist.max() as f64,
            pose_to_force_p50_us: quantile(&self.p2f_hist, 0.5),
            pose_to_force_p99_us: quantile(&self.p2f_hist, 0.99),
            contact_ticks: self.contact_ticks,
            peak_force_n: self.peak_force_n,
            max_displacement_m: self.max_displacement_m,
            device_samples: self.device_samples,
            device_silences: self.device_silences,
            body,
            step_buckets: self.step_buckets,
            pose_to_force_buckets: self.p2f_buckets,
            ..StatsSnapshot::default()
        }
    }
}
