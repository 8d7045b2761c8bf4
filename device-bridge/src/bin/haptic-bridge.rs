//! `haptic-bridge`: streams a haptic device's poses to a hapticd session over
//! `DeviceLink.Connect` and renders the forces it answers. Glue only: the work is in the
//! `haptic_bridge` library (`cli::Args::setup`, then `link::run`). SIGINT, SIGTERM and SIGHUP
//! all stop it cleanly: zero force, the driver's safe stop, the summary, exit 0. Other exit
//! codes: 1 bad flags or set-up, 2 never connected, 3 the session is gone (NOT_FOUND), 4 the
//! daemon refused the credentials (UNAUTHENTICATED or PERMISSION_DENIED; not retried).

use std::process::ExitCode;
use std::sync::Arc;

use anyhow::Context;
use clap::Parser;
use haptic_bridge::{MonotonicClock, cli::Args, record, run};
use tracing_subscriber::EnvFilter;

#[tokio::main]
async fn main() -> anyhow::Result<ExitCode> {
    let args = Args::parse();
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Colour only on a terminal, never in a log file or the journal.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(filter)
        .init();
    // Installed before the device is opened: a signal during a hardware driver's set-up (a
    // HapticMaster calibrating, then put in force state) is held until the set-up returns and
    // stops the run at its start, with the driver's safe stop, instead of killing the process.
    let stop_signal = stop_signal()?;
    let setup = args.setup()?;
    let url = setup.config.server_url.clone();
    if let Some(button) = setup.rearm_button.clone() {
        // `--rearm key`: every line on standard input (Enter) is a re-arm request.
        std::thread::spawn(move || {
            for line in std::io::stdin().lines() {
                if line.is_err() {
                    break;
                }
                button.press();
            }
        });
    }
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        let name = stop_signal.await;
        tracing::info!("{name}: zero force, device safe stop, closing the stream");
        let _ = stop_tx.send(true);
    });
    let report = run(
        setup.device,
        Arc::new(MonotonicClock::new()),
        setup.config,
        stop_rx,
    )
    .await?;
    if let Some(path) = &setup.record_path {
        if record::is_mcap(path) {
            record::write_mcap_file(path, &report.ticks)
        } else {
            record::write_csv_file(path, &report.ticks)
        }
        .with_context(|| format!("writing the recording to {}", path.display()))?;
    }
    let s = &report.summary;
    if setup.json {
        println!("{}", serde_json::to_string(s)?);
    } else {
        println!("{s}");
    }
    if let Some(why) = &s.access_refused {
        eprintln!("error: {why}");
        return Ok(ExitCode::from(4));
    }
    if let Some(why) = &s.session_lost {
        eprintln!("error: {why}");
        return Ok(ExitCode::from(3));
    }
    if !s.connected() {
        let why = s.last_link_error.as_deref().unwrap_or("no attempt made");
        eprintln!("error: never connected to {url}: {why}");
        return Ok(ExitCode::from(2));
    }
    Ok(ExitCode::SUCCESS)
}

/// Resolves with the signal's name on the first SIGINT (Ctrl-C), SIGTERM (`kill`, `systemctl
/// stop`) or SIGHUP (the terminal closed): each stops the run the same way, zero force and the
/// driver's safe stop (a HapticMaster keeps its last bias force otherwise). The handlers are
/// installed when this is called, so the default action (exit at once) no longer applies.
///
/// # Errors
/// A handler cannot be installed.
fn stop_signal() -> anyhow::Result<impl std::future::Future<Output = &'static str>> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut int = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    let mut term = signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut hup = signal(SignalKind::hangup()).context("installing the SIGHUP handler")?;
    Ok(async move {
        tokio::select! {
            _ = int.recv() => "SIGINT",
            _ = term.recv() => "SIGTERM",
            _ = hup.recv() => "SIGHUP",
        }
    })
}
