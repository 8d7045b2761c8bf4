//! The end-to-end tests, one module per file of this folder, in one test binary (as the model's
//! and the server's: `docs/decisions.md`, "The integration tests in a few binaries"; each binary
//! linked the whole dependency graph on its own, 24 of them). Every test that starts a daemon or
//! an in-process server takes [`haptic_e2e::serial`], so they run one at a time as they did in
//! their own binaries. Run one file's tests with `cargo test -p haptic-e2e --test e2e <file>::`.

mod common;

mod auth;
mod bad_inputs;
mod bridge_signals;
mod demo;
mod device;
mod docs_commands;
mod faults;
mod fuzz_requests;
mod hostile;
mod house_rules;
mod hybrid;
mod installed;
mod python;
mod recording;
mod refused_clients;
mod relay;
mod services;
mod surface;
mod surface_mesh;
mod tools;
mod web_overview;
mod web_viewer;
