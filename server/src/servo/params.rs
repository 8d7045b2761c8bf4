//! The servo's fixed parameters ([`ServoParams`]), written once by the builders of
//! [`super::ServoCore`] and only read by the tick.

/// When a session counts as overrunning, and what follows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct OverrunLimit {
    /// Minimum loop rate of a statistics window, Hz.
    pub(super) min_rate_hz: f64,
    /// How long the rate must stay below `min_rate_hz`, µs of wall time.
    pub(super) for_us: u64,
    /// Quarantine an overrunning session (overrun policy `degrade`).
    pub(super) degrade: bool,
}

/// The servo's parameters (set before the loop starts, read-only in the tick).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ServoParams {
    /// A snapshot every this many ticks (>= 1) while someone watches.
    pub(super) snapshot_every: u64,
    /// Statistics every this many ticks (>= 1).
    pub(super) stats_every: u64,
    /// A connected device silent for longer than this is treated as gone, µs.
    pub(super) device_silence_us: u64,
    /// The overrun judgement (`None`: never judged).
    pub(super) overrun: Option<OverrunLimit>,
}
