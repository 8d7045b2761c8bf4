//! `haptic-viewer`: watches a session's deformed surface over `SurfaceStream.Watch` and writes
//! PNG pictures (`frame_00001.png`, ..., `latest.png`) without a GPU or display; with
//! `--web ADDR` it serves the browser viewer instead (prints `listening on ADDR` on stdout).
//!
//! Glue only: parse arguments, start logging, call `haptic_client::viewer::run`, print the
//! summary (stderr; one JSON line on stdout with `--json`). Exit code 0 when the run ended
//! normally (duration, session stopped, Ctrl-C), 2 for gRPC errors, 1 for anything else
//! (including a stream that failed mid-way, after printing the summary).

use std::process::ExitCode;

use clap::Parser;
use haptic_client::viewer::{self, StopReason, ViewerArgs};

async fn run(args: ViewerArgs) -> anyhow::Result<ExitCode> {
    if let Some((addr, cfg)) = args.web_config()? {
        // Credentials the daemon refuses end the relay at once, with the reason, before it
        // serves a page (issue 47); later refusals stop it too (`web::serve`).
        let relay = haptic_client::web::Relay::new(cfg.clone())?;
        relay.check_access().await?;
        let listener = haptic_client::web::bind(&addr).await?;
        let addr = listener.local_addr()?;
        println!("listening on {addr}");
        eprintln!("web viewer on http://{addr}/ (daemon {})", cfg.server);
        let shutdown = async {
            let _ = tokio::signal::ctrl_c().await;
        };
        haptic_client::web::serve(listener, relay, shutdown).await?;
        return Ok(ExitCode::SUCCESS);
    }
    let json = args.json;
    let replay = args.replay.clone();
    let cfg = args.into_config()?;
    let shutdown = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    let summary = match &replay {
        Some(path) => viewer::replay(path, &cfg, shutdown).await?,
        None => viewer::run(cfg, shutdown).await?,
    };
    eprintln!("{summary}");
    if json {
        println!("{}", serde_json::to_string(&summary)?);
    }
    let failed = summary.stop_reason == StopReason::StreamError;
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

#[tokio::main]
async fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        // Colour only on a terminal, never in a log file or the journal.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .init();
    run(ViewerArgs::parse()).await.unwrap_or_else(|e| {
        // ClientError messages already carry their cause; `{e}` avoids printing it twice.
        eprintln!("error: {e}");
        let rpc = e
            .downcast_ref::<haptic_client::ClientError>()
            .is_some_and(|c| c.is_rpc());
        ExitCode::from(if rpc { 2 } else { 1 })
    })
}
