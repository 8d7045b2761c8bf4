//! The bridge's checked configuration, the operator's re-arm button and what stops a run.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use haptics_proto::v1::DeviceCapabilities;
use thiserror::Error;

use crate::device::{DeviceError, DeviceSpec};
use crate::guard::GuardParams;

/// The operator's re-arm button: a counter of presses shared with the device thread (the
/// binary presses it for every line read on standard input).
#[derive(Debug, Clone, Default)]
pub struct RearmButton(Arc<AtomicU64>);

impl RearmButton {
    /// A button never pressed.
    pub fn new() -> Self {
        Self::default()
    }

    /// Presses the button once.
    pub fn press(&self) {
        self.0.fetch_add(1, Ordering::AcqRel);
    }

    /// Presses so far.
    pub fn presses(&self) -> u64 {
        self.0.load(Ordering::Acquire)
    }
}

impl PartialEq for RearmButton {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// Who re-arms the forces after the guard disabled them (devices.md S9).
#[derive(Debug, Clone, PartialEq)]
pub enum RearmMode {
    /// Re-arm as soon as the link has been healthy for 500 ms (the operator consented up front
    /// with `--rearm auto`).
    Auto,
    /// Re-arm when the operator presses the button after the link has been healthy for 500 ms.
    Operator(RearmButton),
}

/// Injected network faults (tests and demos only; never in a lab session).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaultInjection {
    /// Fraction of messages dropped, each way (0..=1).
    pub drop_fraction: f64,
    /// Smallest added delay of a force command, us.
    pub delay_min_us: u64,
    /// Largest added delay of a force command, us (uniformly drawn; commands stay in order).
    pub delay_max_us: u64,
    /// Seed of the generator (the same seed drops the same messages).
    pub seed: u64,
}

/// Checked run-time configuration of the bridge.
#[derive(Debug, Clone, PartialEq)]
pub struct BridgeConfig {
    /// Server URL, `http://host:port` (or `https://` with a CA in `credentials`).
    pub server_url: String,
    /// Token and TLS files (a `device` token is enough; [`haptic_cli::credentials`]).
    pub credentials: haptic_cli::credentials::ClientCredentials,
    /// Session id sent on the first sample of every stream.
    pub session_id: String,
    /// Device loop rate, in Hz.
    pub rate_hz: f64,
    /// Guard limits.
    pub guard: GuardParams,
    /// First reconnect delay (doubles after each failure).
    pub backoff_initial: Duration,
    /// Largest reconnect delay.
    pub backoff_max: Duration,
    /// TCP connect timeout per attempt.
    pub connect_timeout: Duration,
    /// Hard stop after this long, if set.
    pub max_duration: Option<Duration>,
    /// Keep one [`crate::record::TickRecord`] per device tick.
    pub record: bool,
    /// Capacity of the device -> network sample queue (and of the outbound stream queue).
    pub sample_queue: usize,
    /// Who re-arms after the guard disabled the forces.
    pub rearm: RearmMode,
    /// Injected network faults (`None` in normal use).
    pub fault: Option<FaultInjection>,
    /// Pose deadband (fraction of the predicted force, e.g. 0.07; `None`: every sample is sent).
    pub deadband: Option<f64>,
    /// What the first sample of every stream tells the daemon about the device
    /// ([`capabilities_of`] its spec; `None`: nothing, as bridges before issue 50 did).
    pub capabilities: Option<DeviceCapabilities>,
    /// The tool this bridge drives in the session (`DeviceSample.tool_id` of each stream's
    /// first sample; "" = the default tool; issue 50): a session takes several tools at once.
    pub tool_id: String,
}

impl BridgeConfig {
    /// Defaults for `spec`: its rate and guard limits, 50 ms -> 1 s backoff, 500 ms connect
    /// timeout, no hard stop, no recording, 256-sample queues, automatic re-arm, no fault
    /// injection, no deadband.
    pub fn new(
        server_url: impl Into<String>,
        session_id: impl Into<String>,
        spec: &DeviceSpec,
    ) -> Self {
        Self {
            server_url: server_url.into(),
            credentials: Default::default(),
            session_id: session_id.into(),
            rate_hz: spec.rate_hz,
            guard: GuardParams::from_spec(spec),
            backoff_initial: Duration::from_millis(50),
            backoff_max: Duration::from_secs(1),
            connect_timeout: Duration::from_millis(500),
            max_duration: None,
            record: false,
            sample_queue: 256,
            rearm: RearmMode::Auto,
            fault: None,
            deadband: None,
            capabilities: Some(capabilities_of(spec)),
            tool_id: String::new(),
        }
    }

    /// Checks the fields.
    ///
    /// # Errors
    /// [`BridgeError::Config`] naming the field.
    pub fn validate(&self) -> Result<(), BridgeError> {
        let bad = |m: String| Err(BridgeError::Config(m));
        let plain = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.' | ':');
        if self.tool_id.len() > 64 || !self.tool_id.chars().all(plain) {
            return bad(
                "tool id must be at most 64 ASCII letters, digits, '-', '_', '.' or ':'".into(),
            );
        }
        if !(self.server_url.starts_with("http://") || self.server_url.starts_with("https://")) {
            return bad(format!(
                "server URL must start with http:// or https://, got `{}`",
                self.server_url
            ));
        }
        if self.session_id.is_empty() {
            return bad("session id must not be empty".to_owned());
        }
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0 && self.rate_hz <= 100_000.0) {
            return bad(format!(
                "rate_hz must be in (0, 100000], got {}",
                self.rate_hz
            ));
        }
        let g = &self.guard;
        if !(g.max_force_n.is_finite() && g.max_force_n >= 0.0) {
            return bad(format!(
                "max_force_n must be finite and >= 0, got {}",
                g.max_force_n
            ));
        }
        if g.max_rate_n_per_s.is_nan() || g.max_rate_n_per_s <= 0.0 {
            return bad(format!(
                "max_rate_n_per_s must be > 0, got {}",
                g.max_rate_n_per_s
            ));
        }
        if g.zero_us <= g.fresh_us {
            return bad(format!(
                "watchdog: zero_us ({}) must exceed fresh_us ({})",
                g.zero_us, g.fresh_us
            ));
        }
        if self.backoff_initial.is_zero() || self.backoff_max < self.backoff_initial {
            return bad("backoff: need 0 < initial <= max".to_owned());
        }
        if self.sample_queue == 0 {
            return bad("sample_queue must be >= 1".to_owned());
        }
        if !(g.fresh_us < g.zero_us && g.zero_us < g.latch_us) {
            return bad(format!(
                "watchdog: need fresh_us < zero_us < latch_us, got {} / {} / {}",
                g.fresh_us, g.zero_us, g.latch_us
            ));
        }
        if let Some(f) = &self.fault
            && !((0.0..=1.0).contains(&f.drop_fraction) && f.delay_min_us <= f.delay_max_us)
        {
            return bad(format!(
                "fault injection: need 0 <= drop <= 1 and min <= max delay, got {f:?}"
            ));
        }
        if let Some(k) = self.deadband
            && !(k.is_finite() && k > 0.0 && k < 1.0)
        {
            return bad(format!("deadband must be in (0, 1), got {k}"));
        }
        Ok(())
    }
}

/// What can stop the bridge from running at all (link trouble is not an error: it is retried and
/// reported in [`super::BridgeSummary`]).
#[derive(Debug, Error)]
pub enum BridgeError {
    /// A configuration field is out of range.
    #[error("invalid bridge configuration: {0}")]
    Config(String),
    /// The server URL does not parse.
    #[error("invalid server URL `{url}`: {message}")]
    InvalidUrl {
        /// The URL as given.
        url: String,
        /// Why it was rejected.
        message: String,
    },
    /// The device or its spec is unusable.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The device thread could not start or panicked.
    #[error("device thread: {0}")]
    Thread(String),
}

/// The capabilities message of a device spec (scene frame when the spec is a
/// [`crate::transform::Transformed`] device's): name, degrees of freedom, workspace box, peak and
/// continuous force, stiffness limit and rate.
pub fn capabilities_of(spec: &DeviceSpec) -> DeviceCapabilities {
    DeviceCapabilities {
        name: spec.name.clone(),
        sensed_degrees_of_freedom: spec.sensed_degrees_of_freedom,
        actuated_degrees_of_freedom: spec.actuated_degrees_of_freedom,
        workspace_min_m: Some(spec.workspace_min_m.into()),
        workspace_max_m: Some(spec.workspace_max_m.into()),
        max_force_n: spec.max_force_n,
        max_continuous_force_n: spec.max_continuous_force_n,
        max_stiffness_n_per_m: spec.max_stiffness_n_per_m,
        native_rate_hz: spec.rate_hz,
    }
}
