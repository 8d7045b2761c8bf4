//! `haptic-bridge`: streams a haptic device's poses to a hapticd session over
//! `DeviceLink.Connect` and renders the forces it answers. Glue only: the work is in the
//! `haptic_bridge` library (`cli::Args::setup`, then `link::run`). SIGINT, SIGTERM and SIGHUP
//! all stop it cleanly: zero force, the driver's safe stop, the summary, exit 0. Other exit
//! codes: 1 bad flags or set-up, 2 never connected, 3 the session is gone (NOT_FOUND), 4 the
//! daemon refused the credentials (UNAUTHENTICATED or PERMISSION_DENIED; not retried). With
//! `--tool` repeated (sim driver) the tools stream at once and the worst tool's code is returned.

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
    let setups = args.setups()?;
    let url = args.server.clone();
    let buttons: Vec<_> = setups
        .iter()
        .filter_map(|s| s.rearm_button.clone())
        .collect();
    if !buttons.is_empty() {
        // `--rearm key`: every line on standard input (Enter) is a re-arm request, for every
        // tool this process drives.
        std::thread::spawn(move || {
            for line in std::io::stdin().lines() {
                if line.is_err() {
                    break;
                }
                buttons.iter().for_each(|b| b.press());
            }
        });
    }
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        let name = stop_signal.await;
        tracing::info!("{name}: zero force, device safe stop, closing the stream");
        let _ = stop_tx.send(true);
    });
    // One stream per tool, all at once (`--tool` repeated with the sim driver).
    let clock = Arc::new(MonotonicClock::new());
    let several = setups.len() > 1;
    let runs: Vec<_> = setups
        .into_iter()
        .map(|setup| {
            let (clock, stop_rx) = (clock.clone(), stop_rx.clone());
            let tool = setup.config.tool_id.clone();
            let record_path = setup.record_path;
            let json = setup.json;
            let run = tokio::spawn(run(setup.device, clock, setup.config, stop_rx));
            (tool, record_path, json, run)
        })
        .collect();
    let mut code = ExitCode::SUCCESS;
    let mut worst = 0;
    for (tool, record_path, json, run) in runs {
        let report = run.await.context("the tool's stream task")??;
        if let Some(path) = &record_path {
            if record::is_mcap(path) {
                record::write_mcap_file(path, &report.ticks)
            } else {
                record::write_csv_file(path, &report.ticks)
            }
            .with_context(|| format!("writing the recording to {}", path.display()))?;
        }
        let s = &report.summary;
        if json {
            println!("{}", serde_json::to_string(s)?);
        } else if several {
            println!("tool {tool}:\n{s}");
        } else {
            println!("{s}");
        }
        let (rank, exit) = outcome(s, &url, &tool);
        if rank > worst {
            (worst, code) = (rank, exit);
        }
    }
    Ok(code)
}

/// How one tool's run ended, as (severity, exit code): 0 success, then 2 never connected, 3
/// the session is gone, 4 the credentials refused (the worst tool's is the process's); the
/// reason goes to standard error.
fn outcome(s: &haptic_bridge::link::BridgeSummary, url: &str, tool: &str) -> (u8, ExitCode) {
    let who = if tool.is_empty() {
        String::new()
    } else {
        format!(" (tool {tool})")
    };
    if let Some(why) = &s.access_refused {
        eprintln!("error{who}: {why}");
        return (3, ExitCode::from(4));
    }
    if let Some(why) = &s.session_lost {
        eprintln!("error{who}: {why}");
        return (2, ExitCode::from(3));
    }
    if !s.connected() {
        let why = s.last_link_error.as_deref().unwrap_or("no attempt made");
        eprintln!("error{who}: never connected to {url}: {why}");
        return (1, ExitCode::from(2));
    }
    (0, ExitCode::SUCCESS)
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
