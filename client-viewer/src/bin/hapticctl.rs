//! `hapticctl`: scripted client of a `hapticd` server (`SessionControl`).
//!
//! Glue only: parse arguments, connect, call `haptic_client::ctl::execute`. gRPC errors print
//! `error: <CODE>: <message>` on stderr and exit with code 2; other errors exit with code 1.

use std::process::ExitCode;

use clap::Parser;
use haptic_client::ClientError;
use haptic_client::ctl::{self, Ctl, CtlCommand};

/// Command line: the server and one command.
#[derive(Debug, Parser)]
#[command(
    name = "hapticctl",
    version,
    about = "Control a hapticd server: scenes, sessions, forces, statistics."
)]
struct Cli {
    /// Server URL.
    #[arg(long, global = true, env = "HAPTICD_ADDR", default_value = haptic_cli::connect::DEFAULT_SERVER)]
    server: String,
    /// Token and TLS files (`control` starts and drives its own sessions; `viewer` reads).
    #[command(flatten)]
    credentials: haptic_cli::credentials::ClientCredentials,
    #[command(subcommand)]
    command: CtlCommand,
}

async fn run(cli: Cli) -> Result<(), ClientError> {
    // Converting a recording needs no server.
    if let CtlCommand::ExportVtu { input, out } = &cli.command {
        let n = haptic_client::record::export_vtu(input, out)?;
        println!("{}: {n} frames", out.join("surface.pvd").display());
        return Ok(());
    }
    let mut ctl = Ctl::connect(&cli.server, &cli.credentials).await?;
    let (mut out, mut err) = (std::io::stdout().lock(), std::io::stderr());
    ctl::execute(&mut ctl, cli.command, &mut out, &mut err).await
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
    match run(Cli::parse()).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(if e.is_rpc() { 2 } else { 1 })
        }
    }
}
