//! `hapticd`: the haptic server daemon. Parses flags over the config file, starts logging,
//! binds, prints `listening on <addr>`, and calls [`haptic_server::run`] until SIGINT/SIGTERM.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use haptic_server::config::{ConfigFile, LogFormat};

/// Networked haptic server for real-time soft-body simulation.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Configuration file (TOML); flags override it. See deploy/hapticd.toml.
    #[arg(long, env = "HAPTICD_CONFIG")]
    config: Option<PathBuf>,
    /// Listen address (port 0 picks a free port).
    #[arg(long)]
    listen: Option<String>,
    /// Request SCHED_FIFO for servo threads (falls back with a warning).
    #[arg(long)]
    realtime: bool,
    /// Lock memory with mlockall (falls back with a warning).
    #[arg(long)]
    mlockall: bool,
    /// Pin servo threads to this CPU.
    #[arg(long)]
    cpu: Option<usize>,
    /// Largest number of concurrent sessions.
    #[arg(long)]
    max_sessions: Option<usize>,
    /// Directory that relative mesh paths in client-sent scene text resolve against
    /// (e.g. `deploy/scenes` for the shipped scene files).
    #[arg(long)]
    scene_dir: Option<PathBuf>,
    /// Log format: text or json.
    #[arg(long)]
    log_format: Option<String>,
    /// Record sessions (scene and id) here so that a restarted daemon restores them and device
    /// bridges re-attach.
    #[arg(long)]
    state_dir: Option<PathBuf>,
    /// A directory client-sent scenes may read mesh files from besides --scene-dir (repeat the
    /// flag for several; e.g. the shared LV meshes).
    #[arg(long = "data-dir")]
    data_dirs: Vec<PathBuf>,
    /// Serve Prometheus metrics (`GET /metrics`) on this address (port 0 picks a free port; the
    /// daemon prints `metrics on <addr>`).
    #[arg(long)]
    metrics_listen: Option<String>,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut file = match &args.config {
        Some(p) => ConfigFile::load(p)?,
        None => ConfigFile::default(),
    };
    file.listen = args.listen.or(file.listen);
    file.max_sessions = args.max_sessions.or(file.max_sessions);
    file.log_format = args.log_format.or(file.log_format);
    file.scene_dir = args.scene_dir.or(file.scene_dir);
    file.state_dir = args.state_dir.or(file.state_dir);
    file.metrics_listen = args.metrics_listen.or(file.metrics_listen);
    file.data_dirs.extend(args.data_dirs);
    file.servo.realtime |= args.realtime;
    file.servo.mlockall |= args.mlockall;
    file.servo.cpu = args.cpu.or(file.servo.cpu);
    let config = file.into_config()?;
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match config.log_format {
        LogFormat::Json => builder.json().init(),
        LogFormat::Text => builder.init(),
    }
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("binding {}", config.listen))?;
    println!("listening on {}", listener.local_addr()?);
    haptic_server::run(listener, config, shutdown_signal()).await
}

async fn shutdown_signal() {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate()).expect("installing the SIGTERM handler");
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = term.recv() => {}
    }
}
