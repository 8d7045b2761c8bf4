//! `haptic-bridge`: haptic device drivers behind a trait, a pure safety guard, and the
//! `DeviceLink` streaming client that connects a device to the haptic server (DESIGN.md
//! sections 1-4; device facts and safety numbers in `../shared/devices.md`).
//!
//! Modules: [`clock`] (injected time), [`device`] (the trait and spec), [`sim`] and [`replay`]
//! (drivers), [`guard`] (watchdog, clamp, slew, NaN), [`link`] (device thread + gRPC task,
//! [`link::run`]), [`record`] (per-tick CSV), [`cli`] (the binary's checked arguments).
//! The crate talks to the server only through `haptics_proto`; it never depends on the model.

pub mod cli;
pub mod clock;
pub mod device;
pub mod guard;
pub mod hapticmaster;
pub mod hbp;
pub mod link;
pub mod openhaptics;
pub mod passivity;
pub mod record;
pub mod replay;
pub mod serial;
pub mod sim;
pub mod thermal;
pub mod transform;

/// The model's counting allocator (thread-local counts), installed in this crate's unit-test
/// binary: the device loop's tick is checked allocation-free with it.
#[cfg(test)]
#[path = "../../server/model/tests/common/counting_alloc.rs"]
mod counting_alloc;

pub use clock::{Clock, ManualClock, MonotonicClock};
pub use device::{DeviceError, DeviceSpec, DeviceState, HapticDevice};
pub use link::{
    BridgeConfig, BridgeError, BridgeReport, BridgeSummary, FaultInjection, RearmButton, RearmMode,
    run,
};
