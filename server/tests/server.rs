//! The server's integration tests, one module per file of this folder, in one test binary
//! (`docs/decisions.md`, "The integration tests in a few binaries"). Run one file's tests with
//! `cargo test -p haptic-server --test server <file>::`. In their own binaries: the tests that
//! count allocations (`server_alloc.rs`) and `overrun.rs` (it measures loop rates against a
//! session alone, so it runs beside no other test file).

mod common;

mod builds;
mod cli_help;
mod config;
mod confine;
mod cores;
mod device_capabilities;
mod follow_session;
mod hybrid_session;
mod link_limits;
mod metrics;
mod servo_loop;
mod solve;
mod streams;
mod tools;
