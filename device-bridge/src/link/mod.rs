//! The bridge loop: a device thread at the device rate and a network task holding one
//! `DeviceLink.Connect` stream (devices.md section 3.1).
//!
//! ```text
//! [device thread, std::thread, absolute deadlines, no catch-up]      [tokio network task]
//!   read pose ----- try_send (bounded mpsc, never blocks) ----------> DeviceSample stream
//!   latest ForceCommand <-- force slot (std Mutex, held for a copy) <-- ForceCommand stream
//!   guard: age by seq, watchdog, latch/re-arm, local contact model,     seq -> pose time, x0;
//!     passivity, clamp, slew -> write_force                             drop unknown/old seq
//!   (optional) append TickRecord to a pre-reserved Vec                  reconnect + backoff
//! ```
//!
//! Choices:
//! - **Force slot = `std::sync::Mutex<ForceSlot>`.** Both sides hold it only to copy ~80 bytes;
//!   the network task never awaits or allocates while holding it, so the device thread waits at
//!   most a few hundred nanoseconds (no priority inversion worth a wait-free structure in a
//!   separate process whose only other thread is the network task). The server's servo loop
//!   uses wait-free slots instead (DESIGN.md section 3).
//! - **Samples go out through a bounded tokio mpsc with `try_send`.** A full queue drops the
//!   sample and counts it; the device thread never blocks on the network.
//! - **The round trip** is measured pose-to-force: from the device read (`device_time_us`) to
//!   the arrival of the `ForceCommand` echoing that `seq`, on the same injected clock, recorded
//!   in an hdrhistogram by the network task (microseconds).
//! - **Every command is aged from the pose it answers.** The network task keeps `seq -> (read
//!   time, position)` of the samples it sent; a command whose `seq` is unknown (not sent, or
//!   too old for the ring) or not newer than the last accepted one is dropped and counted, the
//!   others reach the guard with the read time and position of their pose.
//! - **Limits at connect time.** The server's response headers carry the scene's force and
//!   force-rate limits (`haptics-max-force-n`, `haptics-max-force-rate-n-per-s`, see the proto)
//!   and its instance id (`haptics-server-instance`); the guard applies the lower of the
//!   scene's and the device's limits.
//! - **Link loss** (no server, stream error, server closed the stream) marks the link down; the
//!   held command keeps ageing, so the force ramps to zero by 60 ms and is disabled at 100 ms
//!   (re-armed as the guard says). The task reconnects with exponential backoff (default 50 ms
//!   doubling to 1 s) until the script finishes or shutdown. A server that answers NOT_FOUND
//!   for the session (it restarted without restoring it) ends the run with a clear message; a
//!   new server instance that restored the session is reported and re-attached to.
//! - **Fault injection** ([`FaultInjection`], for tests and demos only): drops a fraction of the
//!   messages both ways and delays force commands by a random 5-50 ms (in order, as TCP would).
//!
//! Neighbours: [`crate::device`] (the device), [`crate::guard`] (per-tick safety),
//! [`crate::record`] (per-tick rows), `haptics_proto::v1` (the wire contract).

mod config;
mod device_loop;
mod net;
mod shared;
mod stream;
mod summary;

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tonic::transport::Endpoint;
use tracing::{debug, info, warn};

use crate::clock::Clock;
use crate::device::HapticDevice;
use crate::guard::GuardState;

pub use config::{
    BridgeConfig, BridgeError, FaultInjection, RearmButton, RearmMode, capabilities_of,
};
pub use device_loop::{DEADBAND_FLOOR_N, DEADBAND_HEARTBEAT_US, DEADBAND_MOVE_M};
pub use summary::{BridgeReport, BridgeSummary};

use device_loop::device_loop;
use net::NetCtx;
use shared::{OutSample, Shared};
use stream::{StreamEnd, run_stream, wait_shutdown};

/// Response header with the scene's force limit, N (decimal text).
pub const HEADER_MAX_FORCE: &str = "haptics-max-force-n";
/// Response header with the scene's force-rate limit, N/s (decimal text).
pub const HEADER_MAX_FORCE_RATE: &str = "haptics-max-force-rate-n-per-s";
/// Request header asking the server for a force-stream deadband (fraction, decimal text).
pub const HEADER_FORCE_DEADBAND: &str = "haptics-force-deadband";
/// Response header with the server's instance id (changes when the daemon restarts).
pub const HEADER_SERVER_INSTANCE: &str = "haptics-server-instance";

/// Logs the guard's transitions (the device thread cannot: it must not allocate or block).
async fn monitor(shared: Arc<Shared>, rearm: RearmMode) {
    let mut last = GuardState::NoCommand;
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    while !shared.stop.load(Ordering::Acquire) {
        tick.tick().await;
        let now = GuardState::from_code(shared.guard_state.load(Ordering::Acquire));
        if now == last {
            continue;
        }
        match now {
            GuardState::Disabled if !last.is_disabled() => warn!(
                "forces DISABLED: no fresh force command for 100 ms; they stay off until the \
                 link has been healthy for 0.5 s and they are re-armed"
            ),
            GuardState::ReadyToRearm => match rearm {
                RearmMode::Operator(_) => warn!(
                    "link healthy for 0.5 s: press Enter to re-arm the forces (they ramp up over 0.2 s)"
                ),
                RearmMode::Auto => info!("link healthy for 0.5 s: re-arming (--rearm auto)"),
            },
            GuardState::Rising if last.is_disabled() => {
                info!("forces re-armed: ramping up over 0.2 s")
            }
            GuardState::Ramp => debug!("force commands older than 10 ms: ramping down"),
            _ => {}
        }
        last = now;
    }
}

async fn network_loop(
    endpoint: Endpoint,
    config: &BridgeConfig,
    mut samples: mpsc::Receiver<OutSample>,
    mut shutdown: watch::Receiver<bool>,
    ctx: &mut NetCtx,
) {
    let mut backoff = config.backoff_initial;
    loop {
        // Every stream starts with a fresh sample, which carries the session id.
        let first = tokio::select! {
            biased;
            _ = wait_shutdown(&mut shutdown) => return,
            s = samples.recv() => match s {
                Some(s) => s,
                None => return,
            },
        };
        let opened_before = ctx.streams_opened;
        match run_stream(&endpoint, config, first, &mut samples, &mut shutdown, ctx).await {
            StreamEnd::Finished | StreamEnd::Shutdown => return,
            StreamEnd::SessionGone(msg) => {
                let why = if ctx.streams_opened > 0 {
                    format!(
                        "hapticd at {} no longer has session {} ({msg}): it restarted without \
                         restoring it (run hapticd with --state-dir to restore sessions); giving up",
                        config.server_url, config.session_id
                    )
                } else {
                    format!(
                        "hapticd at {} has no session {} ({msg}): check --session",
                        config.server_url, config.session_id
                    )
                };
                warn!("{why}");
                ctx.session_lost = Some(why);
                return;
            }
            StreamEnd::Refused(msg) => {
                let why = format!(
                    "hapticd at {} refused the device link ({msg}): give a `device` (or \
                     `admin`) token with --token-file or HAPTICD_TOKEN_FILE (docs/security.md); \
                     not retrying",
                    config.server_url
                );
                warn!("{why}");
                ctx.last_link_error = Some(msg);
                ctx.access_refused = Some(why);
                return;
            }
            StreamEnd::Failed(msg) => {
                ctx.link_failures += 1;
                if ctx.streams_opened > opened_before {
                    backoff = config.backoff_initial;
                }
                warn!(error = %msg, retry_in_ms = backoff.as_millis() as u64, "DeviceLink down; zero force");
                ctx.last_link_error = Some(msg);
            }
        }
        // Back off, discarding samples (force is zero meanwhile) but noticing the end.
        let sleep = tokio::time::sleep(backoff);
        tokio::pin!(sleep);
        loop {
            tokio::select! {
                biased;
                _ = wait_shutdown(&mut shutdown) => return,
                _ = &mut sleep => break,
                s = samples.recv() => if s.is_none() { return },
            }
        }
        backoff = (backoff * 2).min(config.backoff_max);
    }
}

/// Runs the bridge until the device finishes, `config.max_duration` passes, or `true` is sent
/// on `shutdown`: streams the device's samples to `DeviceLink.Connect` at `config.server_url`,
/// renders the guarded forces it answers, reconnects with backoff when the link fails, and ends
/// with zero force and `safe_stop`.
///
/// `clock` times the device loop, the guard and the round trips; pass a
/// [`crate::clock::MonotonicClock`] for real runs. Never connecting is not an error: check
/// [`BridgeSummary::connected`].
///
/// # Errors
/// [`BridgeError::Config`] / [`BridgeError::InvalidUrl`] / [`BridgeError::Device`] before
/// anything starts; [`BridgeError::Thread`] if the device thread cannot start or panics.
pub async fn run(
    device: Box<dyn HapticDevice>,
    clock: Arc<dyn Clock>,
    config: BridgeConfig,
    shutdown: watch::Receiver<bool>,
) -> Result<BridgeReport, BridgeError> {
    config.validate()?;
    device.spec().validate()?;
    let (token, endpoint) = connection_of(&config)?;
    let config = Arc::new(config);
    let shared = Arc::new(Shared::default());
    let (sample_tx, sample_rx) = mpsc::channel(config.sample_queue);
    let handle = {
        let (clock, shared, config) = (clock.clone(), shared.clone(), config.clone());
        std::thread::Builder::new()
            .name("bridge-device".to_owned())
            .spawn(move || device_loop(device, clock, shared, sample_tx, &config))
            .map_err(|e| BridgeError::Thread(format!("cannot start: {e}")))?
    };
    let monitor_task = tokio::spawn(monitor(shared.clone(), config.rearm.clone()));
    let mut ctx = NetCtx::new(clock, shared.clone(), token, &config)?;
    network_loop(endpoint, &config, sample_rx, shutdown, &mut ctx).await;
    shared.stop.store(true, Ordering::Release);
    shared.set_link(false, None);
    let _ = monitor_task.await;
    let dev = tokio::task::spawn_blocking(move || handle.join())
        .await
        .map_err(|e| BridgeError::Thread(e.to_string()))?
        .map_err(|_| BridgeError::Thread("device thread panicked".to_owned()))?;
    let summary = BridgeSummary::of_run(&ctx, &dev, &config);
    info!(
        ticks = summary.ticks,
        forces = summary.forces_received,
        "bridge finished"
    );
    Ok(BridgeReport {
        summary,
        ticks: dev.records,
    })
}

/// The bearer token and the endpoint (TCP_NODELAY, connect timeout) of `config`'s server.
fn connection_of(
    config: &BridgeConfig,
) -> Result<(haptic_cli::credentials::BearerToken, Endpoint), BridgeError> {
    let token = config
        .credentials
        .interceptor()
        .map_err(|e| BridgeError::Config(e.to_string()))?;
    let endpoint = config
        .credentials
        .endpoint(&config.server_url)
        .map_err(|e| BridgeError::InvalidUrl {
            url: config.server_url.clone(),
            message: e.to_string(),
        })?
        .tcp_nodelay(true)
        .connect_timeout(config.connect_timeout);
    Ok((token, endpoint))
}
