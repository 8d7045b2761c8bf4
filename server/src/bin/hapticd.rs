//! `hapticd`: the haptic server daemon. Parses flags over the config file, starts logging,
//! binds, and calls [`haptic_server::run`] (which prints `listening on <addr>`) until SIGINT/SIGTERM.
//! With `--prepare-regions SCENE` it instead fills the region cache for a scene file and exits.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use haptic_server::config::{ConfigFile, LogFormat, ServoThreads};

/// Networked haptic server for real-time soft-body simulation.
#[derive(Parser, Debug)]
#[command(version)]
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
    /// Threads of each session's tick: "auto" (the model's wish, limited by the cores other
    /// sessions have not reserved) or 1..=16 (the servo thread plus tick-pool workers).
    #[arg(long, value_name = "auto|N", value_parser = parse_servo_threads)]
    servo_threads: Option<ServoThreads>,
    /// Largest number of concurrent sessions.
    #[arg(long)]
    max_sessions: Option<usize>,
    /// Directory that relative mesh paths in client-sent scene text resolve against (e.g.
    /// `deploy/scenes` for the shipped scene files); without one, client scenes may name files
    /// only by absolute path inside a --data-dir. The root and system directories are refused.
    #[arg(long)]
    scene_dir: Option<PathBuf>,
    /// Log format: text or json.
    #[arg(long)]
    log_format: Option<String>,
    /// Record sessions (scene and id) here so that a restarted daemon restores them and device
    /// bridges re-attach.
    #[arg(long)]
    state_dir: Option<PathBuf>,
    /// Keep the tiles following regions prepare (`active_region.tiles = "background"`) in
    /// this directory, so the next session of the same scene reads them instead of
    /// preparing them again.
    #[arg(long)]
    region_cache_dir: Option<PathBuf>,
    /// Do not serve: prepare every region of this scene file's region cache
    /// (`active_region.tiles = "background"`) into the region cache directory, reporting
    /// progress, and exit; the daemon's sessions of the scene then start with them ready.
    #[arg(long, value_name = "SCENE_FILE")]
    prepare_regions: Option<PathBuf>,
    /// A directory client-sent scenes may read mesh files from besides --scene-dir (repeat the
    /// flag for several; e.g. the shared LV meshes).
    #[arg(long = "data-dir")]
    data_dirs: Vec<PathBuf>,
    /// Serve Prometheus metrics (`GET /metrics`) on this address (port 0 picks a free port; the
    /// daemon prints `metrics on <addr>`).
    #[arg(long)]
    metrics_listen: Option<String>,
    /// Tokens file: calls must carry one of its tokens (created with one token per role, and
    /// a `<role>.token` file each beside it, mode 0600, when absent). Never a token itself.
    #[arg(long, env = "HAPTICD_TOKENS_FILE", value_name = "FILE")]
    tokens_file: Option<PathBuf>,
    /// TLS certificate chain (PEM); with --tls-key, the daemon speaks only TLS.
    #[arg(long, value_name = "PEM", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// TLS private key (PEM) of --tls-cert.
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Require client certificates signed by this CA (PEM); needs --tls-cert.
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    tls_client_ca: Option<PathBuf>,
    /// Listen beyond loopback without TLS and tokens (a trusted, isolated network only).
    #[arg(long)]
    allow_insecure_remote: bool,
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
    file.region_cache_dir = args.region_cache_dir.or(file.region_cache_dir);
    file.metrics_listen = args.metrics_listen.or(file.metrics_listen);
    file.data_dirs.extend(args.data_dirs);
    file.auth.tokens_file = args.tokens_file.or(file.auth.tokens_file);
    if let (Some(cert_file), Some(key_file)) = (args.tls_cert, args.tls_key) {
        file.tls = Some(haptic_server::config::TlsFiles {
            cert_file,
            key_file,
            client_ca_file: args.tls_client_ca,
        });
    }
    file.allow_insecure_remote |= args.allow_insecure_remote;
    file.servo.realtime |= args.realtime;
    file.servo.mlockall |= args.mlockall;
    if let Some(cpu) = args.cpu {
        // The flag replaces the file's pinning, whichever key the file used.
        file.servo.cpu = Some(cpu);
        file.servo.cpus.clear();
    }
    if let Some(t) = args.servo_threads {
        file.servo.threads = t;
    }
    let config = file.into_config()?;
    if let Some(scene) = &args.prepare_regions {
        return prepare_regions(scene, config.region_cache.as_ref());
    }
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    // Colour only on a terminal: the journal and log files get plain text (issue 47).
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    match config.log_format {
        LogFormat::Json => builder.json().init(),
        LogFormat::Text => builder.init(),
    }
    if haptic_server::servo::keep_freed_memory() {
        tracing::info!(
            "allocator: up to {} MiB freed at a heap's top kept for reuse (region tiles read back without fresh pages)",
            haptic_server::servo::KEPT_FREED_BYTES >> 20
        );
    }
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("binding {}", config.listen))?;
    // `run` prints `listening on ADDR` once tokens and TLS are set up.
    haptic_server::run(listener, config, shutdown_signal()).await?;
    Ok(())
}

/// `--prepare-regions`: fills the region cache `cache` with every region of the scene file
/// (`haptic_server::regions`: regions already there are left unread, missing ones built and
/// written), printing progress on stderr; fails when the scene has no region cache or a
/// region failed.
fn prepare_regions(
    path: &std::path::Path,
    cache: Option<&haptic_model::integrate::follow::RegionCacheDir>,
) -> anyhow::Result<()> {
    use haptic_server::regions;
    let cache = cache.context(
        "--prepare-regions needs a region cache: --region-cache-dir DIR or region_cache_dir",
    )?;
    let scene = regions::tiled_scene(path)?;
    let report =
        haptic_model::integrate::follow::RegionCacheReport(std::sync::Arc::new(|e: &str| {
            eprintln!("region cache: {e}")
        }));
    let mut progress = |s: &haptic_model::integrate::follow::FollowStats, t: f64| {
        eprintln!(
            "regions of {}: {}/{} ready ({} already there, {} written, {} refused) after {t:.1} s",
            scene.name,
            s.tiles_ready(),
            s.tiles,
            s.tiles_present,
            s.tiles_stored,
            s.tiles_refused
        );
    };
    let stop = std::sync::atomic::AtomicBool::new(false);
    let threads = regions::preparation_threads();
    let s = regions::fill_region_cache(
        &scene,
        cache,
        report,
        &mut progress,
        &mut || false,
        threads,
        &stop,
    )?
    .context("the fill stopped")?;
    anyhow::ensure!(
        s.tiles_failed == 0,
        "{} of {} regions failed",
        s.tiles_failed,
        s.tiles
    );
    println!(
        "prepared {} in {}",
        regions::summary(&scene.name, &s),
        cache.dir.display()
    );
    Ok(())
}

/// `--servo-threads`: `auto` or 1..=16 (the configuration key's rule).
fn parse_servo_threads(s: &str) -> Result<ServoThreads, String> {
    s.parse()
}

async fn shutdown_signal() {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate()).expect("installing the SIGTERM handler");
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = term.recv() => {}
    }
}
