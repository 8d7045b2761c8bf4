//! What the device thread and the network task share: the force slot, the stop flag, the
//! guard state for the log monitor, and the samples on their way out.

use std::sync::atomic::{AtomicBool, AtomicU8};
use std::sync::{Mutex, PoisonError};

use crate::device::DeviceState;
use crate::guard::Limits;

/// The latest force command, as handed from the network task to the device thread.
#[derive(Debug, Clone, Copy)]
pub(super) struct ReceivedForce {
    pub(super) generation: u64,
    pub(super) seq: u64,
    pub(super) force_n: [f64; 3],
    pub(super) stiffness_n_per_m: [f64; 9],
    pub(super) in_contact: bool,
    /// Read time and position of the pose this answers (from the sent ring).
    pub(super) sample_time_us: u64,
    pub(super) sample_position_m: [f64; 3],
    pub(super) rtt_us: Option<u64>,
}

/// The latest-value slot between the network task (writer) and the device thread (reader).
#[derive(Debug, Default)]
pub(super) struct ForceSlot {
    /// A stream is open (health needs it; the guard ages the held command either way).
    pub(super) link_up: bool,
    pub(super) latest: Option<ReceivedForce>,
    /// The scene's limits sent by the server at connect time.
    pub(super) limits: Option<Limits>,
}

#[derive(Debug, Default)]
pub(super) struct Shared {
    pub(super) slot: Mutex<ForceSlot>,
    /// Set by the network side to stop the device thread (shutdown).
    pub(super) stop: AtomicBool,
    /// The guard's state code ([`GuardState::code`]), for the log monitor.
    pub(super) guard_state: AtomicU8,
}

impl Shared {
    pub(super) fn slot(&self) -> std::sync::MutexGuard<'_, ForceSlot> {
        // A panic elsewhere must not stop the device loop from commanding zero.
        self.slot.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub(super) fn set_link(&self, up: bool, limits: Option<Limits>) {
        let mut s = self.slot();
        s.link_up = up;
        if up {
            s.limits = limits;
        }
    }
}

/// One device sample on its way to the network task.
#[derive(Debug, Clone, Copy)]
pub(super) struct OutSample {
    pub(super) seq: u64,
    pub(super) state: DeviceState,
}
