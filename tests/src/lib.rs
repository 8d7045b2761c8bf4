//! End-to-end harness: builds the workspace binaries (`hapticd`, `haptic-bridge`,
//! `haptic-viewer`, `hapticctl`) it runs ([`binary`]), starts `hapticd` on `127.0.0.1:0` as a
//! child process ([`Daemon`]), runs the client binaries with timeouts ([`run_bin`],
//! [`spawn_bin`], [`finish`]) and builds gRPC clients ([`session_control`], [`device_link`],
//! [`surface_stream`]).
//!
//! Which binaries run: the tests never pick up whatever happens to sit in the target folder
//! (with `cargo test -p haptic-e2e`, cargo builds none of the other packages' binaries, so those
//! could be stale). The first [`binary`] call of a test process runs one
//! `cargo build --locked --workspace --bins --tests` (with `escargot`; `build_all` says why the
//! tests too), in the same profile as the test executable and in the same target directory
//! (`CARGO_TARGET_DIR` or `build.target-dir` if set, else the workspace's `target/`; a
//! `--target-dir` flag given to the outer cargo is not seen, use the variable instead); the
//! paths are cached for the rest of the process. After `cargo test --workspace`, or when
//! nothing changed, that costs one cargo no-op check. `HAPTIC_BIN_DIR=DIR` is the explicit override: the tests then run the binaries
//! in `DIR` as they are and build nothing.
//!
//! The `haptic-demo` runner is not a test: it runs the binaries beside its own executable
//! ([`sibling_bin_dir`], after `cargo build --release --workspace`) or from `--bin-dir`.
//!
//! Neighbours: the tests in `tests/tests/*.rs` use it, and so does the `haptic-demo` runner
//! ([`demo`]). Nothing here asserts wall-clock timing: the machines are 2-core and shared, so
//! every wait is a generous, bounded timeout.

pub mod browser;
pub mod demo;
pub mod install;
pub mod load;
pub mod source_scan;

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, ExitStatus, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, mpsc};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail, ensure};
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use tonic::transport::{Channel, Endpoint};

/// The daemon binary.
pub const HAPTICD: &str = "hapticd";
/// The device bridge binary.
pub const BRIDGE: &str = "haptic-bridge";
/// The headless viewer binary.
pub const VIEWER: &str = "haptic-viewer";
/// The scripted client binary.
pub const CTL: &str = "hapticctl";
/// The surface-to-volume mesher (`haptic-mesh`, runs Gmsh).
pub const MESH: &str = "haptic-mesh";

/// Generous default timeout for one step (start-up, an RPC, a short client run); never a
/// performance assertion.
pub const STEP_TIMEOUT: Duration = Duration::from_secs(30);

/// Largest daemon log kept in memory (the tail is printed when a test fails).
const LOG_CAP_BYTES: usize = 64 * 1024;

/// The environment variable naming a directory of prebuilt binaries to use instead of building.
pub const BIN_DIR_ENV: &str = "HAPTIC_BIN_DIR";

/// The workspace binaries the harness runs, with the package that builds each.
const PACKAGES: [(&str, &str); 5] = [
    (HAPTICD, "haptic-server"),
    (BRIDGE, "haptic-bridge"),
    (VIEWER, "haptic-client"),
    (CTL, "haptic-client"),
    (MESH, "haptic-server"),
];

/// The directory the binaries sit in next to the running executable (for `haptic-demo` after
/// `cargo build --release --workspace`: `target/release`). Nothing is built.
///
/// Order: `HAPTIC_BIN_DIR` if set; the directory of the current executable (one level up from
/// `deps/` for test binaries, e.g. `target/debug`); then `$CARGO_TARGET_DIR/<profile>` and
/// `$CARGO_TARGET_DIR/debug`. The first candidate that holds `hapticd` wins.
///
/// # Errors
/// None of the candidates holds `hapticd`; the message says to build the binaries.
pub fn sibling_bin_dir() -> Result<PathBuf> {
    let mut candidates = Vec::new();
    if let Some(d) = std::env::var_os(BIN_DIR_ENV) {
        candidates.push(PathBuf::from(d));
    }
    let mut profile = "debug".to_string();
    let exe_dir = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(Path::to_path_buf));
    if let Some(mut dir) = exe_dir {
        if dir.file_name().is_some_and(|n| n == "deps") {
            dir.pop();
        }
        if let Some(n) = dir.file_name() {
            profile = n.to_string_lossy().into_owned();
        }
        candidates.push(dir);
    }
    if let Some(t) = std::env::var_os("CARGO_TARGET_DIR") {
        let t = PathBuf::from(t);
        candidates.push(t.join(&profile));
        candidates.push(t.join("debug"));
    }
    candidates
        .iter()
        .find(|d| d.join(HAPTICD).is_file())
        .cloned()
        .ok_or_else(|| {
            anyhow!(
                "the workspace binaries ({HAPTICD}, {BRIDGE}, {VIEWER}, {CTL}) were not found in \
                 {candidates:?}: run `cargo build --workspace --bins` first (or set {BIN_DIR_ENV})"
            )
        })
}

/// Path of the workspace binary `name` (one of [`HAPTICD`], [`BRIDGE`], [`VIEWER`], [`CTL`]),
/// built fresh for this test process.
///
/// The first call builds all the binaries in one `cargo build --locked --workspace --bins --tests`
/// ([`build_profile_args`] selects the profile) and blocks until it is done (minutes on a cold
/// target folder, a fraction of a second when nothing changed); later calls, from any thread,
/// get the cached path or the cached failure. All at once, rather than each when first
/// needed, so that no build competes for the 2 cores with a daemon a test has already started
/// (its 1 kHz servo would overrun), and one cargo check per process instead of one per binary.
/// With `HAPTIC_BIN_DIR` set, nothing is built: the binary is taken from that directory.
///
/// `--locked`: the nested build never rewrites `Cargo.lock`. The outer `cargo test` has
/// already resolved the lock file (or refused to, under `--locked`), so this only fails where
/// the outer command would have.
///
/// # Errors
/// `name` is not a workspace binary; the build fails (the compiler's and cargo's messages are
/// in the error); or, with `HAPTIC_BIN_DIR`, the file is missing.
pub fn binary(name: &str) -> Result<PathBuf> {
    static BUILT: OnceLock<Result<Vec<PathBuf>, String>> = OnceLock::new();
    let i = PACKAGES
        .iter()
        .position(|(bin, _)| *bin == name)
        .with_context(|| format!("{name} is not one of the workspace binaries {PACKAGES:?}"))?;
    if let Some(dir) = std::env::var_os(BIN_DIR_ENV) {
        return binary_in(Path::new(&dir), name)
            .with_context(|| format!("{BIN_DIR_ENV} is set: nothing is built"));
    }
    match BUILT.get_or_init(|| build_all().map_err(|e| format!("{e:#}"))) {
        Ok(paths) => Ok(paths[i].clone()),
        Err(e) => Err(anyhow!("{e}")),
    }
}

/// The directory holding the workspace binaries, built as by [`binary`] (or
/// `HAPTIC_BIN_DIR` as it is), for callers that take a directory (the demo runner).
///
/// # Errors
/// As [`binary`]; or the binaries did not land in one directory.
pub fn built_bin_dir() -> Result<PathBuf> {
    let mut dir: Option<PathBuf> = None;
    for (name, _) in PACKAGES {
        let exe = binary(name)?;
        let parent = exe
            .parent()
            .with_context(|| format!("{} has no parent directory", exe.display()))?;
        match &dir {
            None => dir = Some(parent.to_path_buf()),
            Some(d) if d == parent => {}
            Some(d) => bail!(
                "the workspace binaries were built into different directories: {} and {}",
                d.display(),
                parent.display()
            ),
        }
    }
    dir.context("no workspace binaries")
}

/// Cargo arguments that select the profile (and target triple) this executable was built
/// with, read from its location (see [`profile_args_for`]). An executable outside cargo's
/// layout falls back to this crate's `debug_assertions` (dev profile or `--release`).
pub fn build_profile_args() -> Vec<String> {
    std::env::current_exe()
        .ok()
        .and_then(|exe| profile_args_for(&exe, escargot::CURRENT_TARGET))
        .unwrap_or_else(|| {
            if cfg!(debug_assertions) {
                Vec::new()
            } else {
                vec!["--release".to_string()]
            }
        })
}

/// Cargo arguments for the profile of a test executable at
/// `TARGET_DIR/[TRIPLE/]PROFILE_DIR/deps/NAME-HASH`: `debug` is the dev profile (what
/// `cargo test` uses: no argument), `release` is `--release`, any other folder is a custom
/// `--profile NAME`. A `TRIPLE` folder equal to `host` adds `--target TRIPLE`, since
/// `cargo test --target TRIPLE` builds there and a build without it would start from scratch.
/// `None` when `exe` is not in a `deps` folder.
pub fn profile_args_for(exe: &Path, host: &str) -> Option<Vec<String>> {
    let deps = exe.parent()?;
    if deps.file_name()? != "deps" {
        return None;
    }
    let profile_dir = deps.parent()?;
    let mut args = match profile_dir.file_name()?.to_str()? {
        "debug" => Vec::new(),
        "release" => vec!["--release".to_string()],
        other => vec!["--profile".to_string(), other.to_string()],
    };
    if profile_dir
        .parent()
        .and_then(Path::file_name)
        .is_some_and(|t| t == host)
    {
        args.extend(["--target".to_string(), host.to_string()]);
    }
    Some(args)
}

/// One `cargo build --locked --workspace --bins --tests` plus [`build_profile_args`], for the
/// workspace this crate belongs to; returns the [`PACKAGES`] executables in that order.
/// Compiler errors (which cargo prints as JSON on stdout with `--message-format=json`) are
/// kept for the error message.
///
/// Why the whole workspace with its tests: that resolves dependency features as
/// `cargo test --workspace --tests` (the README's test command) does, dev-dependencies
/// included, so after it the build is a no-op. A build of only the binaries' packages resolved some
/// features differently (bytemuck's `extern_crate_alloc` from a dev-dependency's `image`,
/// clap's `wrap_help`, ...) and so compiled bytemuck, glam, faer, the model and the servers a
/// second time: about 2 minutes of every CI run (2026-11-25).
fn build_all() -> Result<Vec<PathBuf>> {
    use escargot::format::{Message, diagnostic::DiagnosticLevel};
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
    let mut args: Vec<String> = ["--locked", "--workspace", "--bins", "--tests"]
        .map(String::from)
        .to_vec();
    args.extend(build_profile_args());
    let command = format!("cargo build {}", args.join(" "));
    eprintln!("haptic-e2e: {command}");
    let mut build = escargot::CargoBuild::new()
        .manifest_path(&manifest)
        .args(&args);
    for key in package_env_keys(std::env::vars_os().map(|(k, _)| k)) {
        build = build.env_remove(key);
    }
    let messages = build
        .exec()
        .with_context(|| format!("starting `{command}`"))?;
    let mut exes: Vec<Option<PathBuf>> = vec![None; PACKAGES.len()];
    let mut errors = String::new();
    for m in messages {
        // The last item is cargo's failure (its stderr) when the build failed.
        let m = m.map_err(|e| anyhow!("`{command}` failed:\n{errors}{e}"))?;
        match m.decode() {
            // A binary's own unit-test executable has its name too (`profile.test`).
            Ok(Message::CompilerArtifact(a))
                if !a.profile.test && a.target.kind.iter().any(|k| k == "bin") =>
            {
                if let Some(i) = PACKAGES.iter().position(|(bin, _)| a.target.name == *bin) {
                    exes[i] = a.executable.map(|p| p.into_owned());
                }
            }
            Ok(Message::CompilerMessage(c))
                if matches!(
                    c.message.level,
                    DiagnosticLevel::Error | DiagnosticLevel::Ice
                ) =>
            {
                errors.push_str(c.message.rendered.as_deref().unwrap_or(&c.message.message));
                errors.push('\n');
            }
            _ => {}
        }
    }
    PACKAGES
        .iter()
        .zip(exes)
        .map(|((bin, _), exe)| {
            let exe = exe.with_context(|| format!("`{command}` reported no executable {bin}"))?;
            ensure!(
                exe.is_file(),
                "`{command}` reported {} but it is not a file",
                exe.display()
            );
            Ok(exe)
        })
        .collect()
}

/// The variables among `keys` that cargo sets for the package whose test is running
/// (`CARGO_MANIFEST_DIR`, `CARGO_PKG_*`, ...), which the nested build must not inherit: a build
/// script that reads one at run time (ring's reads `CARGO_MANIFEST_DIR`) declares it with
/// `rerun-if-env-changed`, and cargo compares the value in its own environment, so the nested
/// build and the outer `cargo test` would rebuild ring, rustls, tonic and everything above
/// them for each other, every run.
fn package_env_keys(keys: impl Iterator<Item = std::ffi::OsString>) -> Vec<std::ffi::OsString> {
    const EXACT: [&str; 7] = [
        "CARGO_MANIFEST_DIR",
        "CARGO_MANIFEST_PATH",
        "CARGO_CRATE_NAME",
        "CARGO_BIN_NAME",
        "CARGO_PRIMARY_PACKAGE",
        "CARGO_TARGET_TMPDIR",
        "OUT_DIR",
    ];
    keys.filter(|k| {
        k.to_str()
            .is_some_and(|k| EXACT.contains(&k) || k.starts_with("CARGO_PKG_"))
    })
    .collect()
}

/// Path of `name` in `dir`, checked to exist.
///
/// # Errors
/// The file is missing; the message says to run `cargo build --workspace --bins`.
pub fn binary_in(dir: &Path, name: &str) -> Result<PathBuf> {
    let p = dir.join(name);
    if p.is_file() {
        Ok(p)
    } else {
        bail!(
            "{} not found: run `cargo build --workspace --bins` first",
            p.display()
        )
    }
}

/// A `hapticd` child process listening on a loopback port. SIGTERM, then SIGKILL, on drop.
pub struct Daemon {
    /// The address it printed (`listening on ADDR`).
    pub addr: SocketAddr,
    /// The process; `None` once [`Daemon::terminate`] reaped it.
    pub child: Option<Child>,
    log: Arc<Mutex<String>>,
}

impl Daemon {
    /// Starts `hapticd` (built by [`binary`]) with `args`, adding `--listen 127.0.0.1:0` unless
    /// `args` has `--listen`, and waits (up to [`STEP_TIMEOUT`]) for `listening on ADDR`.
    ///
    /// # Errors
    /// The binary is missing, does not start, exits or stays silent before printing its address.
    pub fn spawn(args: &[&str]) -> Result<Daemon> {
        Self::spawn_from(&binary(HAPTICD)?, args)
    }

    /// As [`Daemon::spawn`], with an explicit binary path.
    ///
    /// # Errors
    /// As [`Daemon::spawn`].
    pub fn spawn_from(exe: &Path, args: &[&str]) -> Result<Daemon> {
        Self::spawn_in(exe, args, None)
    }

    /// As [`Daemon::spawn_from`], in the working directory `cwd` when given (the systemd
    /// unit's daemon runs in `/`).
    ///
    /// # Errors
    /// As [`Daemon::spawn`].
    pub fn spawn_in(exe: &Path, args: &[&str], cwd: Option<&Path>) -> Result<Daemon> {
        let mut cmd = std::process::Command::new(exe);
        if let Some(dir) = cwd {
            cmd.current_dir(dir);
        }
        if !args.contains(&"--listen") {
            cmd.args(["--listen", "127.0.0.1:0"]);
        }
        let mut child = cmd
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting {}", exe.display()))?;
        let log = Arc::new(Mutex::new(String::new()));
        // Both pipes are drained for the child's whole life so that it never blocks on a full
        // pipe; stderr (the log) is kept for failure reports.
        let stderr = child.stderr.take().expect("piped stderr");
        let err_log = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                append_log(&err_log, &line);
            }
        });
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = mpsc::channel();
        let out_log = log.clone();
        std::thread::spawn(move || {
            let mut tx = Some(tx);
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(rest) = line.trim().strip_prefix("listening on ") {
                    if let Some(tx) = tx.take() {
                        let _ = tx.send(rest.trim().to_string());
                    }
                } else {
                    append_log(&out_log, &line);
                }
            }
        });
        let mut daemon = Daemon {
            addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            child: Some(child),
            log,
        };
        match rx.recv_timeout(STEP_TIMEOUT) {
            Ok(a) => {
                daemon.addr = a
                    .parse()
                    .with_context(|| format!("hapticd printed a bad address {a:?}"))?;
                Ok(daemon)
            }
            Err(_) => {
                let status = daemon
                    .child
                    .as_mut()
                    .and_then(|c| c.try_wait().ok().flatten());
                bail!(
                    "hapticd did not print `listening on ADDR` within {STEP_TIMEOUT:?} \
                     (exit status: {status:?}); log:\n{}",
                    daemon.log_tail()
                )
            }
        }
    }

    /// `http://ADDR`, for gRPC clients and the client binaries' `--server`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// The process id (0 once reaped).
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// The last few KiB of the daemon's log (stderr and unexpected stdout).
    pub fn log_tail(&self) -> String {
        self.log.lock().map(|l| l.clone()).unwrap_or_default()
    }

    /// Sends SIGTERM and waits up to `timeout` for the exit.
    ///
    /// # Errors
    /// The process did not exit in time (it is then killed) or could not be waited for.
    pub fn terminate(&mut self, timeout: Duration) -> Result<ExitStatus> {
        let mut child = self.child.take().context("hapticd was already reaped")?;
        signal(&child, libc::SIGTERM);
        match wait_timeout(&mut child, timeout)? {
            Some(status) => Ok(status),
            None => {
                let _ = child.kill();
                let _ = child.wait();
                bail!(
                    "hapticd did not exit within {timeout:?} of SIGTERM; log:\n{}",
                    self.log_tail()
                )
            }
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            signal(&child, libc::SIGTERM);
            if !matches!(
                wait_timeout(&mut child, Duration::from_secs(10)),
                Ok(Some(_))
            ) {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
        if std::thread::panicking() {
            eprintln!(
                "---- hapticd {} log (tail) ----\n{}",
                self.addr,
                self.log_tail()
            );
        }
    }
}

fn append_log(log: &Mutex<String>, line: &str) {
    if let Ok(mut l) = log.lock() {
        l.push_str(line);
        l.push('\n');
        if l.len() > LOG_CAP_BYTES {
            let mut cut = l.len() - LOG_CAP_BYTES / 2;
            while !l.is_char_boundary(cut) {
                cut += 1;
            }
            l.drain(..cut);
        }
    }
}

/// Sends `sig` to a child that has not been reaped yet.
pub fn signal(child: &Child, sig: libc::c_int) {
    let Ok(pid) = libc::pid_t::try_from(child.id()) else {
        return;
    };
    // SAFETY: plain FFI call; the child is not reaped yet (we own its `Child`), so the pid
    // still names it.
    unsafe {
        libc::kill(pid, sig);
    }
}

/// Polls `child` until it exits or `timeout` passes (`Ok(None)`).
///
/// # Errors
/// `waitpid` failed.
pub fn wait_timeout(child: &mut Child, timeout: Duration) -> Result<Option<ExitStatus>> {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(s) = child.try_wait()? {
            return Ok(Some(s));
        }
        if Instant::now() >= deadline {
            return Ok(None);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A finished client process: its status and captured output.
#[derive(Debug)]
pub struct CmdOutput {
    /// What was run (for messages).
    pub command: String,
    /// Exit status.
    pub status: ExitStatus,
    /// Standard output, lossily decoded.
    pub stdout: String,
    /// Standard error, lossily decoded.
    pub stderr: String,
}

impl CmdOutput {
    /// `self` when the exit status is success.
    ///
    /// # Errors
    /// A non-zero exit, with the command, status and stderr in the message.
    pub fn success(self) -> Result<CmdOutput> {
        if self.status.success() {
            Ok(self)
        } else {
            bail!(
                "`{}` failed ({}):\nstdout: {}\nstderr: {}",
                self.command,
                self.status,
                self.stdout.trim(),
                self.stderr.trim()
            )
        }
    }

    /// The last non-empty stdout line parsed as JSON (the `--json` summaries).
    ///
    /// # Errors
    /// No line, or not JSON.
    pub fn json(&self) -> Result<serde_json::Value> {
        let line = self
            .stdout
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .with_context(|| format!("`{}` printed nothing on stdout", self.command))?;
        serde_json::from_str(line)
            .with_context(|| format!("`{}` printed non-JSON {line:?}", self.command))
    }
}

/// A client binary running in the background (stdout and stderr piped; killed on drop).
pub struct Spawned {
    /// What was run (for messages).
    pub command: String,
    /// The process.
    pub child: tokio::process::Child,
}

/// Starts the workspace binary `name` from `dir` with `args` in the background.
///
/// # Errors
/// Missing binary or spawn failure.
pub fn spawn_bin_in(dir: &Path, name: &str, args: &[&str]) -> Result<Spawned> {
    spawn_exe(&binary_in(dir, name)?, name, args)
}

/// Starts the executable `exe` (called `name` in messages) with `args` in the background.
fn spawn_exe(exe: &Path, name: &str, args: &[&str]) -> Result<Spawned> {
    spawn_exe_env(exe, name, args, &[])
}

/// [`spawn_exe`] with environment variables `env` added.
fn spawn_exe_env(exe: &Path, name: &str, args: &[&str], env: &[(&str, &str)]) -> Result<Spawned> {
    let command = format!("{name} {}", args.join(" "));
    let child = tokio::process::Command::new(exe)
        .args(args)
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .with_context(|| format!("starting `{command}`"))?;
    Ok(Spawned { command, child })
}

/// Starts the workspace binary `name` (built by [`binary`]) with `args` in the background.
///
/// # Errors
/// Build failure, missing binary or spawn failure.
pub fn spawn_bin(name: &str, args: &[&str]) -> Result<Spawned> {
    spawn_exe(&binary(name)?, name, args)
}

/// Starts `haptic-viewer --server URL --web 127.0.0.1:0 ARGS...` (built by [`binary`]) and
/// waits (up to [`STEP_TIMEOUT`]) for its `listening on ADDR`; returns the process and `ADDR`.
///
/// # Errors
/// Build or spawn failure, or no address printed in time.
pub async fn spawn_web_viewer(url: &str, args: &[&str]) -> Result<(Spawned, String)> {
    use tokio::io::AsyncBufReadExt;
    let mut all = vec!["--server", url, "--web", "127.0.0.1:0"];
    all.extend_from_slice(args);
    let mut web = spawn_bin(VIEWER, &all)?;
    let stdout = web.child.stdout.take().context("piped stdout")?;
    let mut lines = tokio::io::BufReader::new(stdout).lines();
    let addr = tokio::time::timeout(STEP_TIMEOUT, async {
        while let Some(l) = lines.next_line().await? {
            if let Some(a) = l.strip_prefix("listening on ") {
                return anyhow::Ok(a.trim().to_string());
            }
        }
        bail!("haptic-viewer --web ended without printing its address")
    })
    .await
    .context("haptic-viewer --web did not print its address in time")??;
    // Keep draining stdout so the relay never blocks on a full pipe.
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
    Ok((web, addr))
}

/// Waits up to `timeout` for a background binary and collects its output (any exit status;
/// see [`CmdOutput::success`]).
///
/// # Errors
/// Timeout (the process is killed) or I/O failure.
pub async fn finish(p: Spawned, timeout: Duration) -> Result<CmdOutput> {
    let Spawned { command, mut child } = p;
    let mut out = child.stdout.take().context("stdout not piped")?;
    let mut err = child.stderr.take().context("stderr not piped")?;
    let collect = async {
        use tokio::io::AsyncReadExt;
        let (mut o, mut e) = (Vec::new(), Vec::new());
        let (ro, re, status) = tokio::join!(
            out.read_to_end(&mut o),
            err.read_to_end(&mut e),
            child.wait()
        );
        ro?;
        re?;
        anyhow::Ok((status?, o, e))
    };
    match tokio::time::timeout(timeout, collect).await {
        Ok(r) => {
            let (status, o, e) = r.with_context(|| format!("waiting for `{command}`"))?;
            Ok(CmdOutput {
                command,
                status,
                stdout: String::from_utf8_lossy(&o).into_owned(),
                stderr: String::from_utf8_lossy(&e).into_owned(),
            })
        }
        Err(_) => {
            let _ = child.start_kill();
            bail!("`{command}` did not finish within {timeout:?} (killed)")
        }
    }
}

/// Runs the workspace binary `name` with `args` to completion (up to `timeout`).
///
/// # Errors
/// Missing binary, spawn failure or timeout; a non-zero exit is *not* an error here.
pub async fn run_bin(name: &str, args: &[&str], timeout: Duration) -> Result<CmdOutput> {
    finish(spawn_bin(name, args)?, timeout).await
}

/// [`run_bin`] with environment variables `env` added (`HAPTICD_ADDR`, token files ...).
///
/// # Errors
/// As [`run_bin`].
pub async fn run_bin_env(
    name: &str,
    args: &[&str],
    env: &[(&str, &str)],
    timeout: Duration,
) -> Result<CmdOutput> {
    finish(spawn_exe_env(&binary(name)?, name, args, env)?, timeout).await
}

/// Same as [`run_bin`] for a binary in `dir`.
///
/// # Errors
/// As [`run_bin`].
pub async fn run_bin_in(
    dir: &Path,
    name: &str,
    args: &[&str],
    timeout: Duration,
) -> Result<CmdOutput> {
    finish(spawn_bin_in(dir, name, args)?, timeout).await
}

/// A gRPC channel to `url` (`http://ADDR`), connected within [`STEP_TIMEOUT`].
///
/// # Errors
/// Bad URL or no connection.
pub async fn channel(url: &str) -> Result<Channel> {
    let ep = Endpoint::from_shared(url.to_string())
        .with_context(|| format!("bad server URL {url:?}"))?
        .connect_timeout(STEP_TIMEOUT)
        .tcp_nodelay(true);
    tokio::time::timeout(STEP_TIMEOUT, ep.connect())
        .await
        .with_context(|| format!("connecting to {url} timed out"))?
        .with_context(|| format!("connecting to {url}"))
}

/// `SessionControl` client for `url`.
///
/// # Errors
/// As [`channel`].
pub async fn session_control(url: &str) -> Result<SessionControlClient<Channel>> {
    Ok(SessionControlClient::new(channel(url).await?))
}

/// `DeviceLink` client for `url`.
///
/// # Errors
/// As [`channel`].
pub async fn device_link(url: &str) -> Result<DeviceLinkClient<Channel>> {
    Ok(DeviceLinkClient::new(channel(url).await?))
}

/// `SurfaceStream` client for `url`.
///
/// # Errors
/// As [`channel`].
pub async fn surface_stream(url: &str) -> Result<SurfaceStreamClient<Channel>> {
    Ok(SurfaceStreamClient::new(channel(url).await?))
}

/// A fresh, empty directory under the system temp dir, named after `prefix`, the process id
/// and a counter, so parallel tests never share one.
///
/// # Errors
/// The directory cannot be created.
pub fn unique_temp_dir(prefix: &str) -> Result<PathBuf> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    let dir = std::env::temp_dir().join(format!("{prefix}-{}-{n}-{nanos}", std::process::id()));
    if dir.exists() {
        std::fs::remove_dir_all(&dir)?;
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir)
}

/// Index of the vertex of `xyz` (interleaved `[x, y, z, ...]`, metres) nearest to `p`.
///
/// # Panics
/// `xyz` is empty.
pub fn nearest_vertex(xyz: &[f32], p: [f64; 3]) -> usize {
    assert!(!xyz.is_empty(), "no vertices");
    xyz.chunks_exact(3)
        .enumerate()
        .map(|(i, v)| {
            let d: f64 = (0..3).map(|k| (f64::from(v[k]) - p[k]).powi(2)).sum();
            (i, d)
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
        .expect("non-empty")
}

/// Vertex `i` of interleaved `xyz` as `f64` metres.
pub fn vertex(xyz: &[f32], i: usize) -> [f64; 3] {
    [
        f64::from(xyz[3 * i]),
        f64::from(xyz[3 * i + 1]),
        f64::from(xyz[3 * i + 2]),
    ]
}

/// The lock of [`serial`] and [`serial_blocking`].
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Serializes the end-to-end tests of one test binary: each runs a daemon with a 1 kHz servo
/// thread, and several at once on a shared 2-core machine only measure the machine. An async
/// lock, since the guard is held across the whole test.
pub async fn serial() -> tokio::sync::MutexGuard<'static, ()> {
    SERIAL.lock().await
}

/// [`serial`] for blocking code (a `spawn_blocking` task or a plain thread), for a test that
/// holds the lock only while its daemons run sessions and lets others run while it installs.
///
/// # Panics
/// Called from an async context (tokio's `blocking_lock`).
pub fn serial_blocking() -> tokio::sync::MutexGuard<'static, ()> {
    SERIAL.blocking_lock()
}

/// Starts the built-in scene `scene` over gRPC and returns the session id.
///
/// # Errors
/// Connection or RPC failure.
pub async fn start_session(url: &str, scene: &str) -> Result<String> {
    let mut ctl = session_control(url).await?;
    let r = ctl
        .start_session(haptics_proto::v1::StartSessionRequest {
            scene: scene.to_string(),
            scene_toml: String::new(),
        })
        .await
        .with_context(|| format!("StartSession {scene}"))?;
    Ok(r.into_inner().session_id)
}

/// Stops session `id` over gRPC (its servo thread joined, its device released).
///
/// # Errors
/// Connection or RPC failure (an unknown session is `NOT_FOUND`).
pub async fn stop_session(url: &str, id: &str) -> Result<()> {
    let mut ctl = session_control(url).await?;
    ctl.stop_session(haptics_proto::v1::StopSessionRequest {
        session_id: id.to_string(),
    })
    .await
    .with_context(|| format!("StopSession {id}"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nested_builds_use_the_profile_and_target_of_the_test_executable() {
        let host = "x86_64-unknown-linux-gnu";
        let args = |p: &str| profile_args_for(Path::new(p), host);
        assert_eq!(args("/w/target/debug/deps/surface-0123"), Some(vec![]));
        assert_eq!(
            args("/w/target/release/deps/surface-0123"),
            Some(vec!["--release".to_string()])
        );
        assert_eq!(
            args("/w/target/ci/deps/surface-0123"),
            Some(vec!["--profile".to_string(), "ci".to_string()])
        );
        assert_eq!(
            args("/w/target/x86_64-unknown-linux-gnu/debug/deps/surface-0123"),
            Some(vec!["--target".to_string(), host.to_string()])
        );
        assert_eq!(args("/w/target/release/haptic-demo"), None);
        assert_eq!(args("surface"), None);
    }

    #[test]
    fn the_nested_build_drops_the_running_packages_cargo_variables() {
        let keys = [
            "CARGO_MANIFEST_DIR",
            "CARGO_PKG_NAME",
            "CARGO_PKG_VERSION_MAJOR",
            "OUT_DIR",
            "CARGO_TARGET_DIR",
            "CARGO_HOME",
            "CARGO",
            "PATH",
            "CI",
        ]
        .map(std::ffi::OsString::from);
        let dropped = package_env_keys(keys.into_iter());
        assert_eq!(
            dropped,
            [
                "CARGO_MANIFEST_DIR",
                "CARGO_PKG_NAME",
                "CARGO_PKG_VERSION_MAJOR",
                "OUT_DIR"
            ]
            .map(std::ffi::OsString::from)
        );
    }

    #[test]
    fn every_harness_binary_has_a_package() {
        for name in [HAPTICD, BRIDGE, VIEWER, CTL] {
            assert!(PACKAGES.iter().any(|(bin, _)| *bin == name), "{name}");
        }
        let e = binary("cargo").unwrap_err().to_string();
        assert!(e.contains("not one of the workspace binaries"), "{e}");
    }
}
