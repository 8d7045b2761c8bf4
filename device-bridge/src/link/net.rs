//! The network side's state and counters ([`NetCtx`]): the sent ring that ages every command
//! from the pose it answers, fault injection, and the hand-over to the force slot.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use haptics_proto::v1::{DeviceSample, ForceCommand};
use hdrhistogram::Histogram;
use tokio::sync::mpsc;

use crate::clock::Clock;

use super::shared::{OutSample, ReceivedForce, Shared};
use super::{BridgeConfig, BridgeError, FaultInjection};

/// Number of sent `seq -> send time` entries kept for round-trip matching (4 s at 1 kHz).
pub(super) const RTT_RING: usize = 4096;

/// A small xorshift generator for fault injection (deterministic per seed, no dependency).
#[derive(Debug, Clone, Copy)]
pub(super) struct XorShift(pub(super) u64);

impl XorShift {
    fn next_f64(&mut self) -> f64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        (x >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Network-side state and counters.
pub(super) struct NetCtx {
    pub(super) clock: Arc<dyn Clock>,
    /// Puts the bridge's token on the device stream.
    pub(super) token: haptic_cli::credentials::BearerToken,
    pub(super) shared: Arc<Shared>,
    /// `seq -> (read time us, position m)` of recently sent samples, indexed by
    /// `seq % RTT_RING`.
    pub(super) sent: Vec<(u64, u64, [f64; 3])>,
    pub(super) rtt_us: Histogram<u64>,
    pub(super) generation: u64,
    pub(super) last_accepted_seq: Option<u64>,
    pub(super) samples_sent: u64,
    pub(super) samples_dropped: u64,
    pub(super) forces_received: u64,
    pub(super) unmatched_forces: u64,
    pub(super) stale_forces: u64,
    pub(super) contact_samples: u64,
    pub(super) streams_opened: u64,
    pub(super) reconnects: u64,
    pub(super) link_failures: u64,
    pub(super) attempts: u64,
    pub(super) last_link_error: Option<String>,
    pub(super) server_instance: Option<String>,
    pub(super) server_restarts: u64,
    pub(super) session_lost: Option<String>,
    pub(super) access_refused: Option<String>,
    pub(super) fault: Option<FaultInjection>,
    pub(super) rng: XorShift,
    pub(super) injected_drops: u64,
    /// Force commands held back by injected delay: (release time us, command).
    pub(super) delayed: VecDeque<(u64, ForceCommand)>,
}

pub(super) fn to_proto(s: &OutSample) -> DeviceSample {
    DeviceSample {
        session_id: String::new(),
        seq: s.seq,
        device_time_us: s.state.time_us,
        position_m: Some(s.state.position_m.into()),
        velocity_m_per_s: Some(s.state.velocity_m_per_s.into()),
        capabilities: None,
        tool_id: String::new(),
    }
}

impl NetCtx {
    /// A network side with nothing sent or received yet; `config.fault` seeds the injection.
    ///
    /// # Errors
    /// [`BridgeError::Config`] if the round-trip histogram cannot be built.
    pub(super) fn new(
        clock: Arc<dyn Clock>,
        shared: Arc<Shared>,
        token: haptic_cli::credentials::BearerToken,
        config: &BridgeConfig,
    ) -> Result<Self, BridgeError> {
        Ok(Self {
            clock,
            shared,
            sent: vec![(u64::MAX, 0, [0.0; 3]); RTT_RING],
            rtt_us: Histogram::new_with_bounds(1, 60_000_000, 3)
                .map_err(|e| BridgeError::Config(format!("histogram: {e}")))?,
            generation: 0,
            samples_sent: 0,
            samples_dropped: 0,
            forces_received: 0,
            unmatched_forces: 0,
            contact_samples: 0,
            streams_opened: 0,
            reconnects: 0,
            link_failures: 0,
            attempts: 0,
            last_link_error: None,
            last_accepted_seq: None,
            stale_forces: 0,
            server_instance: None,
            server_restarts: 0,
            session_lost: None,
            access_refused: None,
            fault: config.fault,
            token,
            rng: XorShift(config.fault.map_or(1, |f| f.seed.max(1))),
            injected_drops: 0,
            delayed: VecDeque::new(),
        })
    }

    fn injected_drop(&mut self) -> bool {
        let Some(f) = self.fault else { return false };
        let drop = f.drop_fraction > 0.0 && self.rng.next_f64() < f.drop_fraction;
        self.injected_drops += u64::from(drop);
        drop
    }

    pub(super) fn forward(&mut self, out: &mpsc::Sender<DeviceSample>, msg: DeviceSample) {
        let p = msg.position_m.as_ref().map_or([0.0; 3], |v| v.to_array());
        self.sent[(msg.seq % RTT_RING as u64) as usize] = (msg.seq, msg.device_time_us, p);
        if self.injected_drop() {
            return;
        }
        match out.try_send(msg) {
            Ok(()) => self.samples_sent += 1,
            Err(_) => self.samples_dropped += 1,
        }
    }

    /// A command from the stream: through fault injection, then [`NetCtx::on_force`].
    pub(super) fn receive(&mut self, cmd: ForceCommand) {
        if self.injected_drop() {
            return;
        }
        match self.fault {
            Some(f) if f.delay_max_us > 0 => {
                let span = (f.delay_max_us - f.delay_min_us) as f64;
                let delay = f.delay_min_us + (self.rng.next_f64() * span) as u64;
                let now = self.clock.now_us();
                let after_previous = self.delayed.back().map_or(0, |(t, _)| *t);
                self.delayed
                    .push_back(((now + delay).max(after_previous), cmd));
            }
            _ => self.on_force(&cmd),
        }
    }

    /// Delivers the delayed commands that are due.
    pub(super) fn release_delayed(&mut self) {
        let now = self.clock.now_us();
        while self.delayed.front().is_some_and(|(t, _)| *t <= now) {
            if let Some((_, cmd)) = self.delayed.pop_front() {
                self.on_force(&cmd);
            }
        }
    }

    pub(super) fn next_release(&self) -> Option<Duration> {
        let (t, _) = self.delayed.front()?;
        Some(Duration::from_micros(t.saturating_sub(self.clock.now_us())))
    }

    pub(super) fn on_force(&mut self, cmd: &ForceCommand) {
        let now = self.clock.now_us();
        self.forces_received += 1;
        let (seq, sample_time_us, sample_position_m) =
            self.sent[(cmd.seq % RTT_RING as u64) as usize];
        if seq != cmd.seq {
            self.unmatched_forces += 1;
            return;
        }
        if self.last_accepted_seq.is_some_and(|s| cmd.seq <= s) {
            self.stale_forces += 1;
            return;
        }
        self.last_accepted_seq = Some(cmd.seq);
        let rtt = now.saturating_sub(sample_time_us);
        self.rtt_us.saturating_record(rtt.max(1));
        self.contact_samples += u64::from(cmd.in_contact);
        self.generation += 1;
        // proto3: an absent vector is the zero vector; a stiffness that is not 3x3 is unknown
        // (no extrapolation). Non-finite values pass on to the guard, which rejects and counts
        // them.
        let force_n = cmd.force_n.as_ref().map_or([0.0; 3], |v| v.to_array());
        let mut stiffness_n_per_m = [0.0; 9];
        if cmd.stiffness_n_per_m.len() == 9 {
            stiffness_n_per_m.copy_from_slice(&cmd.stiffness_n_per_m);
        }
        let mut s = self.shared.slot();
        s.latest = Some(ReceivedForce {
            generation: self.generation,
            seq: cmd.seq,
            force_n,
            stiffness_n_per_m,
            in_contact: cmd.in_contact,
            sample_time_us,
            sample_position_m,
            rtt_us: Some(rtt),
        });
    }
}
