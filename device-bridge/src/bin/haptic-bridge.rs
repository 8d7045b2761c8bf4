//! `haptic-bridge`: streams a haptic device's poses to a hapticd session over
//! `DeviceLink.Connect` and renders the forces it answers. Glue only: the work is in the
//! `haptic_bridge` library (`cli::Args::setup`, then `link::run`).

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
        .with_env_filter(filter)
        .init();
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
        if tokio::signal::ctrl_c().await.is_ok() {
            let _ = stop_tx.send(true); // Ctrl-C: zero force, close the stream, summary.
        }
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
