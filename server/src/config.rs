//! Daemon configuration, layered: built-in defaults < TOML file (`deploy/hapticd.toml`) < CLI
//! flags. The file is parsed with `deny_unknown_fields`, then validated into [`ServerConfig`].

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::error::ServerError;

/// When the servo ticks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Pacing {
    /// One tick as soon as a device sample arrives, on a 1 ms schedule of slots that keeps
    /// simulated time on wall-clock time; 1 ms ticks without a device
    /// ([`crate::servo::DevicePacer`]).
    #[default]
    Device,
    /// Fixed 1 ms absolute deadlines ([`crate::servo::Pacer`]); a sample waits for the next tick.
    Clock,
}

/// Scheduling of the region cache's background fill (`prepare_regions_priority`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FillPriority {
    /// Only while no session runs, and then at `SCHED_IDLE` (nice 19 when refused): a
    /// running session never shares the machine with the fill.
    #[default]
    Idle,
    /// Always, at the daemon's own normal priority: done sooner, beside the sessions (for a
    /// machine with cores to spare).
    Normal,
}

/// Servo-thread settings.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServoConfig {
    /// Ask for SCHED_FIFO for servo threads (falls back with a warning when not permitted).
    pub realtime: bool,
    /// SCHED_FIFO priority, 1..=99.
    pub priority: u8,
    /// Lock the process memory (`mlockall`) so page faults cannot stall the loop.
    pub mlockall: bool,
    /// Pin servo threads to this CPU index (none: let the OS choose); the same as
    /// `cpus = [cpu]` (giving both is an error).
    pub cpu: Option<usize>,
    /// The CPUs servo threads and their tick-pool workers are pinned to, in order (empty: no
    /// pinning); also the cores `threads = "auto"` shares out among sessions
    /// ([`ServoConfig::pinned_cpus`]).
    pub cpus: Vec<usize>,
    /// Threads of a session's tick (its servo thread plus tick-pool workers): `"auto"` (the
    /// body's wish, limited by the free cores) or a count 1..=[`MAX_SERVO_THREADS`].
    pub threads: ServoThreads,
    /// Publish a surface snapshot for viewers every this many ticks (16 -> 62.5 Hz at 1 kHz).
    pub snapshot_every_ticks: u32,
    /// Publish statistics for `GetStats` every this many ticks.
    pub stats_every_ticks: u32,
    /// `"device"` (tick on each device sample; default) or `"clock"` (fixed 1 ms deadlines).
    pub pacing: Pacing,
    /// A connected device silent for longer than this is treated as gone (zero force), ms.
    pub device_silence_ms: u32,
    /// What to do with a session whose servo cannot keep its rate: `"report"` (statistics
    /// only, the default) or `"degrade"` (quarantine it: zero force, `SessionStats.fault`).
    pub overrun_policy: OverrunPolicy,
    /// A servo below this fraction of its nominal rate for a whole second is overrunning.
    pub min_rate_fraction: f64,
    /// An overrunning session's servo thread yields to the sessions that keep up
    /// (`SCHED_IDLE` while it overruns and another session runs; [`crate::servo::Yielding`]).
    pub yield_when_overrunning: bool,
}

/// Most threads `[servo] threads` may give one session's tick (the servo thread plus at most
/// 15 tick-pool workers, `haptic_model::pool::MAX_WORKERS`).
pub const MAX_SERVO_THREADS: usize = 16;

/// [`ServoConfig::threads`]: how many threads a session's tick uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(try_from = "RawThreads")]
pub enum ServoThreads {
    /// The body's wish (`SoftBody::wants_threads`) limited by the cores no other session has
    /// reserved, less the threads the body keeps busy beside its tick
    /// (`SoftBody::background_threads`); one where `SCHED_FIFO` was asked for and refused.
    #[default]
    Auto,
    /// This many threads, 1..=[`MAX_SERVO_THREADS`], whatever the other sessions use.
    Fixed(usize),
}

/// `threads` as written in the file: `"auto"` or an integer.
#[derive(Deserialize)]
#[serde(untagged)]
enum RawThreads {
    Count(i64),
    Name(String),
}

impl TryFrom<RawThreads> for ServoThreads {
    type Error = String;
    fn try_from(raw: RawThreads) -> Result<Self, String> {
        match raw {
            RawThreads::Count(n) => n.to_string().parse(),
            RawThreads::Name(s) => s.parse(),
        }
    }
}

impl std::str::FromStr for ServoThreads {
    type Err = String;
    /// `"auto"` or an integer 1..=[`MAX_SERVO_THREADS`]; the error names `servo.threads`.
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(Self::Auto);
        }
        match s.parse::<i64>() {
            Ok(n) if (1..=MAX_SERVO_THREADS as i64).contains(&n) => Ok(Self::Fixed(n as usize)),
            // A number is quoted back; other text is not (configuration values never are).
            Ok(n) => Err(format!(
                "servo.threads = {n}: expected \"auto\" or 1..={MAX_SERVO_THREADS}"
            )),
            Err(_) => Err(format!(
                "servo.threads: expected \"auto\" or 1..={MAX_SERVO_THREADS}"
            )),
        }
    }
}

impl std::fmt::Display for ServoThreads {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Fixed(n) => write!(f, "{n}"),
        }
    }
}

impl ServoConfig {
    /// The CPUs to pin to, in order: `cpus`, or `[cpu]`; empty: no pinning.
    pub fn pinned_cpus(&self) -> Vec<usize> {
        match self.cpu {
            Some(c) if self.cpus.is_empty() => vec![c],
            _ => self.cpus.clone(),
        }
    }
}

/// [`ServoConfig::overrun_policy`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OverrunPolicy {
    /// Report in `GetStats` (loop rate, overruns) only.
    #[default]
    Report,
    /// Quarantine the session (zero force from then on) so that a model too heavy for this
    /// machine never renders forces late.
    Degrade,
}

impl Default for ServoConfig {
    fn default() -> Self {
        Self {
            realtime: false,
            priority: 80,
            mlockall: false,
            cpu: None,
            cpus: Vec::new(),
            threads: ServoThreads::Auto,
            snapshot_every_ticks: 16,
            stats_every_ticks: 100,
            pacing: Pacing::Device,
            device_silence_ms: 50,
            overrun_policy: OverrunPolicy::Report,
            min_rate_fraction: 0.9,
            yield_when_overrunning: true,
        }
    }
}

/// The daemon's configuration file, as written.
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct ConfigFile {
    /// Listen address, e.g. `127.0.0.1:50051`.
    pub listen: Option<String>,
    /// Largest number of concurrent sessions.
    pub max_sessions: Option<usize>,
    /// Directory that relative mesh paths in client-supplied scene text resolve against
    /// (relative to the configuration file's directory when given in the file).
    pub scene_dir: Option<PathBuf>,
    /// Log format: `text` or `json`.
    pub log_format: Option<String>,
    /// Servo settings.
    pub servo: ServoConfig,
    /// Directory where sessions are recorded (scene and id) so that a restarted daemon
    /// restores them; unset: sessions die with the process.
    pub state_dir: Option<PathBuf>,
    /// Prometheus metrics address (`GET /metrics`), e.g. `127.0.0.1:9464`; unset: no endpoint.
    pub metrics_listen: Option<String>,
    /// Directory where following regions keep their prepared tiles between sessions
    /// (`active_region.tiles = "background"`); unset: tiles live in a session's memory only.
    pub region_cache_dir: Option<PathBuf>,
    /// Largest total size of the region cache's files, bytes (default 8 GiB).
    pub region_cache_max_bytes: Option<u64>,
    /// Largest total size of the tiles one session keeps in memory, bytes (default 2 GiB);
    /// beyond it those farthest from the probe wait in their files.
    pub region_cache_memory_bytes: Option<u64>,
    /// Scene files (with `active_region.tiles = "background"`) whose regions the daemon
    /// writes to the region cache in the background from its start, at the lowest priority,
    /// so that their first sessions find them ready ([`crate::regions`]); needs
    /// `region_cache_dir`.
    pub prepare_regions: Vec<PathBuf>,
    /// Scheduling of that fill (default `idle`).
    pub prepare_regions_priority: FillPriority,
    /// Directories besides `scene_dir` that client-sent scenes may read mesh and table files
    /// from (e.g. the shared LV meshes).
    pub data_dirs: Vec<PathBuf>,
    /// Largest file a client-sent scene may make the daemon read, bytes.
    pub max_file_bytes: Option<u64>,
    /// Largest number of elements (tetrahedra or surface triangles) of a client-sent scene.
    pub max_elements: Option<usize>,
    /// Largest number of nodes of a client-sent scene.
    pub max_nodes: Option<usize>,
    /// Largest estimated number of meshfree particles of a client-sent hybrid scene.
    pub max_particles: Option<usize>,
    /// Scene builds running at once; further `StartSession` calls wait for a turn.
    pub max_concurrent_builds: Option<usize>,
    /// `StartSession` calls of one client address waiting or building at once.
    pub max_builds_per_client: Option<usize>,
    /// Sessions one client address may have running.
    pub max_sessions_per_client: Option<usize>,
    /// Deadline of a `StartSession` call (waiting and building), s.
    pub build_timeout_s: Option<f64>,
    /// Token authentication (`[auth]`).
    pub auth: AuthFile,
    /// TLS (`[tls]`); unset: plain HTTP/2.
    pub tls: Option<TlsFiles>,
    /// Listen beyond loopback without TLS and tokens (refused otherwise).
    pub allow_insecure_remote: bool,
}

/// The `[auth]` section: tokens and failed attempts ([`crate::auth`]).
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct AuthFile {
    /// The tokens file (created with one token per role at first start when absent); unset:
    /// no tokens, every call allowed.
    pub tokens_file: Option<PathBuf>,
    /// Failed calls one client address may make per window before it is refused (default 10).
    pub max_failures: Option<u32>,
    /// The failure window, s (default 10).
    pub failure_window_s: Option<f64>,
}

/// The `[tls]` section: the daemon's certificate and key, and optionally the CA whose client
/// certificates it requires (PEM files).
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsFiles {
    /// Certificate chain (PEM).
    pub cert_file: PathBuf,
    /// Private key (PEM).
    pub key_file: PathBuf,
    /// CA certificate (PEM); when set, every client must present a certificate it signed.
    pub client_ca_file: Option<PathBuf>,
}

/// Log output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

/// Validated daemon configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct ServerConfig {
    /// Listen address.
    pub listen: SocketAddr,
    /// Largest number of concurrent sessions.
    pub max_sessions: usize,
    /// Base directory for relative mesh paths in client-sent scene text, and the first
    /// directory such scenes may read from; `None`: client scenes may name files only by
    /// absolute path inside a data directory.
    pub scene_dir: Option<PathBuf>,
    /// Log format.
    pub log_format: LogFormat,
    /// Servo settings.
    pub servo: ServoConfig,
    /// Session records for restoring sessions after a restart (`None`: not recorded).
    pub state_dir: Option<PathBuf>,
    /// Prometheus metrics endpoint address (`None`: not served).
    pub metrics_listen: Option<SocketAddr>,
    /// Where following regions keep their tiles between sessions (`None`: not kept); an
    /// operator's setting, never a scene's ([`haptic_model::BodyOptions`]).
    pub region_cache: Option<haptic_model::integrate::follow::RegionCacheDir>,
    /// Scene files whose region caches [`crate::run`] fills in the background
    /// ([`crate::regions::spawn_background_fill`]); never empty without `region_cache`.
    pub prepare_regions: Vec<PathBuf>,
    /// Scheduling of that fill.
    pub prepare_regions_priority: FillPriority,
    /// Data directories client-sent scenes may read from (besides `scene_dir`).
    pub data_dirs: Vec<PathBuf>,
    /// Largest file a client-sent scene may make the daemon read, bytes.
    pub max_file_bytes: u64,
    /// Largest number of elements of a client-sent scene ([`DEFAULT_MAX_ELEMENTS`]).
    pub max_elements: usize,
    /// Largest number of nodes of a client-sent scene ([`DEFAULT_MAX_NODES`]).
    pub max_nodes: usize,
    /// Largest estimated number of particles of a client-sent hybrid scene
    /// ([`DEFAULT_MAX_PARTICLES`]).
    pub max_particles: usize,
    /// Scene builds running at once (default 2, one per core of the target machine).
    pub max_concurrent_builds: usize,
    /// `StartSession` calls of one client address waiting or building at once (default 2).
    pub max_builds_per_client: usize,
    /// Sessions one client address may have running (default 4).
    pub max_sessions_per_client: usize,
    /// Deadline of a `StartSession` call, waiting for a build turn included (default 30 s).
    /// A build still running at the deadline finishes in the background and its session is
    /// stopped at once: the client was told it failed.
    pub build_timeout: std::time::Duration,
    /// The tokens file ([`crate::auth`]); `None`: no tokens, every call allowed.
    pub tokens_file: Option<PathBuf>,
    /// Limits on failed authentication attempts.
    pub auth_limits: crate::auth::FailureLimits,
    /// TLS files; `None`: plain HTTP/2.
    pub tls: Option<TlsFiles>,
    /// Listening beyond loopback without TLS and tokens was explicitly allowed.
    pub allow_insecure_remote: bool,
}

/// Default [`ServerConfig::max_elements`]: 120 000 tetrahedra, so that every scene we ship
/// starts with the configuration we ship (`deploy/scenes/lv_100k_condensed.toml`: 100 260
/// tetrahedra, 20 328 nodes; set-up 20-24 s and about 0.9 GB on a 2-core AVX2 machine, bounded
/// by `build_timeout`). The limit bounds a client's set-up cost, not its tick: a whole-body
/// model steps at 1 kHz only to about 50 000 tetrahedra (a whole-body explicit LV tick costs
/// about 0.4 ms at 18 000 on these machines); larger ones need a condensed active region, and
/// a session that cannot keep its rate is reported (`overrunning`) and yields to the others.
pub const DEFAULT_MAX_ELEMENTS: usize = 120_000;

/// Default [`ServerConfig::max_nodes`]: 100 000 (quadratic meshes have about 2 nodes per
/// element).
pub const DEFAULT_MAX_NODES: usize = 100_000;

/// Default [`ServerConfig::max_particles`]: 500 000. The estimate is the mesh's volume over
/// the cube of `hybrid.spacing_m` (an upper bound: the layer is part of the wall; about 72 000
/// for the shipped `lv-hybrid`, which samples 53 268). Measured on the 2-core machine: a million
/// particles take 4.1 s to preprocess and 107 MiB (`hybrid_bench --spacing-m 0.00013`), so the
/// limit bounds a client's hybrid set-up at about 2 s and 55 MiB.
pub const DEFAULT_MAX_PARTICLES: usize = 500_000;

/// Default [`ServerConfig::max_file_bytes`]: 64 MiB (a Gmsh ASCII mesh of about 600 000
/// tetrahedra; the shipped LV meshes are 0.05-1 MB).
pub const DEFAULT_MAX_FILE_BYTES: u64 = 64 << 20;

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            listen: "127.0.0.1:50051".parse().expect("literal address"),
            max_sessions: 8,
            scene_dir: None,
            log_format: LogFormat::Text,
            servo: ServoConfig::default(),
            state_dir: None,
            metrics_listen: None,
            region_cache: None,
            prepare_regions: Vec::new(),
            prepare_regions_priority: FillPriority::Idle,
            data_dirs: Vec::new(),
            max_file_bytes: DEFAULT_MAX_FILE_BYTES,
            max_elements: DEFAULT_MAX_ELEMENTS,
            max_nodes: DEFAULT_MAX_NODES,
            max_particles: DEFAULT_MAX_PARTICLES,
            max_concurrent_builds: 2,
            max_builds_per_client: 2,
            max_sessions_per_client: 4,
            build_timeout: std::time::Duration::from_secs(30),
            tokens_file: None,
            auth_limits: crate::auth::FailureLimits::default(),
            tls: None,
            allow_insecure_remote: false,
        }
    }
}

impl ServerConfig {
    /// Start-up checks of what clients may make the daemon read: `scene_dir` and every data
    /// directory must exist and must not be the root or a system directory
    /// ([`crate::confine::check_root`]); they are replaced by their canonical paths. The tokens
    /// file, the TLS key and the state directory must not lie inside one of them (a client
    /// could otherwise name them in a scene).
    ///
    /// # Errors
    /// [`ServerError::Config`] naming the setting, the directory and the rule.
    pub fn check_directories(&mut self) -> Result<(), ServerError> {
        if let Some(d) = &self.scene_dir {
            self.scene_dir = Some(crate::confine::check_root("scene_dir", d)?);
        }
        for d in &mut self.data_dirs {
            *d = crate::confine::check_root("data_dirs", d)?;
        }
        let roots: Vec<&PathBuf> = self.scene_dir.iter().chain(&self.data_dirs).collect();
        let private = [
            ("[auth] tokens_file", self.tokens_file.as_deref()),
            (
                "[tls] key_file",
                self.tls.as_ref().map(|t| t.key_file.as_path()),
            ),
            ("state_dir", self.state_dir.as_deref()),
        ];
        for (field, path) in private {
            let Some(canonical) = path.and_then(canonical_even_if_missing) else {
                continue;
            };
            if let Some(root) = roots.iter().find(|r| canonical.starts_with(r)) {
                return Err(ServerError::Config(format!(
                    "{field} {} lies inside {}, a directory client scenes may read: move it out",
                    canonical.display(),
                    root.display()
                )));
            }
        }
        Ok(())
    }
}

/// `path` with its directory resolved (symlinks, `..`) when the file itself does not exist yet
/// (a tokens file made at first start); `None` when not even the directory resolves.
fn canonical_even_if_missing(path: &Path) -> Option<PathBuf> {
    if let Ok(c) = std::fs::canonicalize(path) {
        return Some(c);
    }
    let dir = std::fs::canonicalize(path.parent()?).ok()?;
    Some(dir.join(path.file_name()?))
}

/// The region cache of `region_cache_dir`, `region_cache_max_bytes` (default
/// [`haptic_model::integrate::follow::DEFAULT_REGION_CACHE_MAX_BYTES`]) and
/// `region_cache_memory_bytes` (default
/// [`haptic_model::integrate::follow::DEFAULT_REGION_CACHE_MEMORY_BYTES`]); `prepared`: the
/// file lists regions to prepare (`prepare_regions`), which need a cache.
///
/// # Errors
/// [`ServerError::Config`] for a limit of 0 bytes, or regions to prepare or limits without a
/// cache (a session without one keeps at most the default memory limit of regions).
fn region_cache(
    dir: Option<PathBuf>,
    (max_bytes, memory_bytes): (Option<u64>, Option<u64>),
    prepared: bool,
) -> Result<Option<haptic_model::integrate::follow::RegionCacheDir>, ServerError> {
    use haptic_model::integrate::follow::{
        DEFAULT_REGION_CACHE_MAX_BYTES, DEFAULT_REGION_CACHE_MEMORY_BYTES, RegionCacheDir,
    };
    if prepared && dir.is_none() {
        return Err(ServerError::Config(
            "prepare_regions needs a region cache: region_cache_dir (or --region-cache-dir)".into(),
        ));
    }
    for (name, limit) in [
        ("region_cache_max_bytes", max_bytes),
        ("region_cache_memory_bytes", memory_bytes),
    ] {
        if limit == Some(0) {
            return Err(ServerError::Config(format!("{name} must be at least 1")));
        }
        if limit.is_some() && dir.is_none() {
            return Err(ServerError::Config(format!(
                "{name} bounds the region cache: set region_cache_dir (or --region-cache-dir) \
                 too; without one a session keeps at most {} MiB of regions in memory",
                DEFAULT_REGION_CACHE_MEMORY_BYTES >> 20
            )));
        }
    }
    Ok(dir.map(|dir| RegionCacheDir {
        dir,
        max_bytes: max_bytes.unwrap_or(DEFAULT_REGION_CACHE_MAX_BYTES),
        memory_bytes: memory_bytes.unwrap_or(DEFAULT_REGION_CACHE_MEMORY_BYTES),
    }))
}

impl ConfigFile {
    /// Parses configuration text.
    ///
    /// # Errors
    /// [`ServerError::Config`] with the TOML error: its line and column, unknown key names and
    /// what was expected, never the file's text.
    pub fn parse(text: &str) -> Result<Self, ServerError> {
        toml::from_str(text)
            .map_err(|e| ServerError::Config(haptic_model::scene::describe_toml_error(text, &e)))
    }

    /// Reads and parses a configuration file.
    ///
    /// # Errors
    /// [`ServerError::Config`] when the file cannot be read or parsed.
    /// Relative paths in the file (`scene_dir`, `data_dirs`, `state_dir`, `region_cache_dir`,
    /// `prepare_regions`, `[auth] tokens_file`, the `[tls]` files) resolve against the file's directory, never the working directory:
    /// the daemon as installed runs in `/`.
    pub fn load(path: &Path) -> Result<Self, ServerError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ServerError::Config(format!("reading {}: {e}", path.display())))?;
        let mut file = Self::parse(&text)
            .map_err(|e| ServerError::Config(format!("{}: {e}", path.display())))?;
        let dir = std::path::absolute(path)
            .map_err(|e| ServerError::Config(format!("{}: {e}", path.display())))?
            .parent()
            .map_or_else(|| PathBuf::from("/"), Path::to_path_buf);
        file.resolve_paths_against(&dir);
        Ok(file)
    }

    /// Makes every relative path of the file relative to `dir` instead (see [`Self::load`]).
    pub fn resolve_paths_against(&mut self, dir: &Path) {
        let fix = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = dir.join(&*p);
            }
        };
        self.scene_dir.iter_mut().for_each(fix);
        self.data_dirs.iter_mut().for_each(fix);
        self.state_dir.iter_mut().for_each(fix);
        self.region_cache_dir.iter_mut().for_each(fix);
        self.prepare_regions.iter_mut().for_each(fix);
        self.auth.tokens_file.iter_mut().for_each(fix);
        if let Some(t) = &mut self.tls {
            fix(&mut t.cert_file);
            fix(&mut t.key_file);
            t.client_ca_file.iter_mut().for_each(fix);
        }
    }

    /// Validates the file over the defaults.
    ///
    /// # Errors
    /// [`ServerError::Config`] naming the bad field.
    pub fn into_config(self) -> Result<ServerConfig, ServerError> {
        let mut c = ServerConfig::default();
        if let Some(l) = self.listen {
            c.listen = l
                .parse()
                .map_err(|e| ServerError::Config(format!("listen = {l:?}: {e}")))?;
        }
        if let Some(m) = self.max_sessions {
            if m == 0 {
                return Err(ServerError::Config(
                    "max_sessions must be at least 1".into(),
                ));
            }
            c.max_sessions = m;
        }
        c.scene_dir = self.scene_dir;
        if let Some(f) = self.log_format {
            c.log_format = match f.as_str() {
                "text" => LogFormat::Text,
                "json" => LogFormat::Json,
                other => {
                    return Err(ServerError::Config(format!(
                        "log_format = {other:?}: expected \"text\" or \"json\""
                    )));
                }
            };
        }
        check_servo(&self.servo)?;
        c.servo = self.servo;
        c.state_dir = self.state_dir;
        c.data_dirs = self.data_dirs;
        c.region_cache = region_cache(
            self.region_cache_dir,
            (self.region_cache_max_bytes, self.region_cache_memory_bytes),
            !self.prepare_regions.is_empty(),
        )?;
        c.prepare_regions = self.prepare_regions;
        c.prepare_regions_priority = self.prepare_regions_priority;
        if let Some(n) = self.max_elements {
            c.max_elements = n.max(1);
        }
        if let Some(n) = self.max_nodes {
            c.max_nodes = n.max(1);
        }
        if let Some(n) = self.max_particles {
            c.max_particles = n.max(1);
        }
        if let Some(b) = self.max_file_bytes {
            if b == 0 {
                return Err(ServerError::Config(
                    "max_file_bytes must be at least 1".into(),
                ));
            }
            c.max_file_bytes = b;
        }
        for (name, value, field) in [
            (
                "max_concurrent_builds",
                self.max_concurrent_builds,
                &mut c.max_concurrent_builds,
            ),
            (
                "max_builds_per_client",
                self.max_builds_per_client,
                &mut c.max_builds_per_client,
            ),
            (
                "max_sessions_per_client",
                self.max_sessions_per_client,
                &mut c.max_sessions_per_client,
            ),
        ] {
            if let Some(n) = value {
                if n == 0 {
                    return Err(ServerError::Config(format!("{name} must be at least 1")));
                }
                *field = n;
            }
        }
        if let Some(t) = self.build_timeout_s {
            c.build_timeout = duration_s("build_timeout_s", t, 3600.0)?;
        }
        c.auth_limits = failure_limits(&self.auth, c.auth_limits)?;
        c.tokens_file = self.auth.tokens_file;
        c.tls = self.tls;
        c.allow_insecure_remote = self.allow_insecure_remote;
        check_remote(&c)?;
        if let Some(m) = self.metrics_listen {
            c.metrics_listen = Some(
                m.parse()
                    .map_err(|e| ServerError::Config(format!("metrics_listen = {m:?}: {e}")))?,
            );
        }
        Ok(c)
    }
}

/// The `[auth]` table's failure limits over `limits`: `max_failures` at least 1, the
/// window a duration of at most a day.
fn failure_limits(
    auth: &AuthFile,
    mut limits: crate::auth::FailureLimits,
) -> Result<crate::auth::FailureLimits, ServerError> {
    if let Some(n) = auth.max_failures {
        if n == 0 {
            return Err(ServerError::Config(
                "auth.max_failures must be at least 1".into(),
            ));
        }
        limits.max_failures = n;
    }
    if let Some(t) = auth.failure_window_s {
        limits.window = duration_s("auth.failure_window_s", t, 86_400.0)?;
    }
    Ok(limits)
}

/// The `[servo]` table's ranges: priority 1..=99, snapshot and statistics periods and the
/// device-silence timeout at least 1, `min_rate_fraction` in 0..=1, `threads` 1..=16,
/// `cpu` and `cpus` not both, no CPU listed twice.
fn check_servo(servo: &ServoConfig) -> Result<(), ServerError> {
    if !(1..=99).contains(&servo.priority) {
        return Err(ServerError::Config(format!(
            "servo.priority = {}: expected 1..=99",
            servo.priority
        )));
    }
    if servo.snapshot_every_ticks == 0 || servo.stats_every_ticks == 0 {
        return Err(ServerError::Config(
            "servo.snapshot_every_ticks and servo.stats_every_ticks must be >= 1".into(),
        ));
    }
    if !(servo.min_rate_fraction.is_finite() && (0.0..=1.0).contains(&servo.min_rate_fraction)) {
        return Err(ServerError::Config(format!(
            "servo.min_rate_fraction = {}: expected 0..=1",
            servo.min_rate_fraction
        )));
    }
    if let ServoThreads::Fixed(n) = servo.threads
        && !(1..=MAX_SERVO_THREADS).contains(&n)
    {
        return Err(ServerError::Config(format!(
            "servo.threads = {n}: expected \"auto\" or 1..={MAX_SERVO_THREADS}"
        )));
    }
    if servo.cpu.is_some() && !servo.cpus.is_empty() {
        return Err(ServerError::Config(
            "servo.cpu and servo.cpus are both given: keep one (cpu = N is cpus = [N])".into(),
        ));
    }
    for (i, c) in servo.cpus.iter().enumerate() {
        if servo.cpus[..i].contains(c) {
            return Err(ServerError::Config(format!(
                "servo.cpus lists CPU {c} twice: each CPU once"
            )));
        }
    }
    if servo.device_silence_ms == 0 {
        return Err(ServerError::Config(
            "servo.device_silence_ms must be at least 1".into(),
        ));
    }
    Ok(())
}

/// A duration key given in seconds: finite, from 1 ms to `max_s`.
fn duration_s(name: &str, t: f64, max_s: f64) -> Result<std::time::Duration, ServerError> {
    if !(t.is_finite() && (0.001..=max_s).contains(&t)) {
        return Err(ServerError::Config(format!(
            "{name} = {t}: expected 0.001..={max_s}"
        )));
    }
    Ok(std::time::Duration::from_secs_f64(t))
}

/// Refuses a non-loopback listen address without TLS and tokens unless
/// `allow_insecure_remote` says the network is trusted.
fn check_remote(c: &ServerConfig) -> Result<(), ServerError> {
    if !c.listen.ip().is_loopback()
        && (c.tls.is_none() || c.tokens_file.is_none())
        && !c.allow_insecure_remote
    {
        return Err(ServerError::Config(format!(
            "refusing to listen on {} without TLS and tokens: anyone on the network could \
             drive the arm. Set [tls] and [auth] tokens_file (docs/security.md), or \
             allow_insecure_remote = true (--allow-insecure-remote) on a trusted network",
            c.listen
        )));
    }
    Ok(())
}
