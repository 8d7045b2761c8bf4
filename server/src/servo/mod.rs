//! The servo loop: one OS thread per session running the model at the servo rate (1 kHz).
//!
//! A tick has a fixed shape (STYLE.md habit 6): wait for the absolute deadline, drain commands
//! (SPSC ring, wait-free), read the latest device pose (triple buffer, wait-free), step the
//! model, guard the force, push it to the force ring and wake the forwarder, publish a surface
//! snapshot every k-th tick while someone watches, publish statistics every m-th tick, record
//! timing in preallocated histograms. Nothing in [`ServoCore::tick`] allocates, locks, blocks or
//! logs; `tests/servo_no_alloc.rs` proves it with a counting allocator.
//!
//! Late ticks are counted as overruns and the schedule is re-based on the current time: the loop
//! never "catches up" with a burst of back-to-back ticks ([`Pacer`]).
//!
//! Neighbours: [`crate::session`] creates the rings/buffers and threads; the gRPC services in
//! [`crate::service`] sit on the other side of every handoff.

mod core;
mod handoff;
mod pacer;
mod params;
mod realtime;
mod run;
mod stats;

pub use self::core::{DEFAULT_DEVICE_SILENCE_US, ServoCore};
pub use handoff::{
    APPLIED_LOAD_CAPACITY, AppliedLoad, COMMAND_CAPACITY, Command, FORCE_CAPACITY, ForceOut,
    LATENCY_BUCKET_BOUNDS_US, LatencyBuckets, Pose, ServoEnds, ServoHandles, SessionShared,
    Snapshot, StatsSnapshot, ToolEnds, ToolHandles, ToolProbeSnapshot, ToolStatsSnapshot, channels,
    tool_channels, tool_slots,
};
pub use pacer::{Clock, DevicePacer, Flow, MonotonicClock, Pacer, Wake};
pub use realtime::{
    KEPT_FREED_BYTES, WorkerThreads, Yielding, fifo_permitted, keep_freed_memory, lowest_priority,
    setup_realtime, setup_realtime_on, worker_start_hook,
};
pub use run::{run_loop, run_loop_device_paced};
