//! `haptic-viewer`: watches a session's deformed surface over `SurfaceStream.Watch` and writes
//! PNG pictures (`frame_00001.png`, ..., `latest.png`) without a GPU or display.
//!
//! Glue only: parse arguments, start logging, call `haptic_client::viewer::run`, print the
//! summary (stderr; one JSON line on stdout with `--json`). Exit code 1 on errors, including a
//! stream that failed mid-way.

use anyhow::Context;
use clap::Parser;
use haptic_client::viewer::{self, StopReason, ViewerArgs};

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .init();
    let args = ViewerArgs::parse();
    let json = args.json;
    let cfg = args.into_config()?;
    let shutdown = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    let summary = viewer::run(cfg, shutdown).await.context("viewer failed")?;
    eprintln!("{summary}");
    if json {
        println!("{}", serde_json::to_string(&summary)?);
    }
    if summary.stop_reason == StopReason::StreamError {
        anyhow::bail!("the surface stream failed");
    }
    Ok(())
}
