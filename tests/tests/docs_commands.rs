//! Every command block of `README.md` and `docs/tools.md` runs as written (issue 47), so the
//! documents cannot drift from the programs.
//!
//! How. Each fenced block must name its language; `sh`/`bash` blocks are commands, the others
//! (`text` output, `toml`) are not. The blocks of a file run in order with `bash -eo pipefail`
//! from a copy of the repository's layout in a temporary folder (its entries are symlinks to
//! the repository's, so outputs such as `out/`, `demo-out/` and `.venv` land in the temporary
//! folder, never in the checkout), exported variables carried from one block to the next.
//! Background jobs (`&`) are waited for at the end of each block. The substitutions, each
//! explicit and small:
//!
//! - `target/release` is a symlink to the binaries the harness built for this test (`cargo
//!   build --locked --workspace --bins --tests` in the test's profile), and the command
//!   `cargo build --release --workspace` is replaced by `:` (nothing left to build);
//! - `target/release/haptic-demo` runs with `--hold-s 0.5` (its short mode: a 0.5 s hold
//!   instead of 3 s);
//! - a line that starts the daemon (`hapticd ...` or `target/release/hapticd ...`, which a user
//!   runs in its own terminal) is started by the harness with the same flags and `--listen
//!   127.0.0.1:0`, and the address the line names (`--listen ADDR`) is replaced by the real one
//!   in every later line; `docs/tools.md` assumes the README's daemon, which the test starts from
//!   the README's line before that file's first block;
//! - nothing for `.venv`: the Python block makes a real one in the temporary folder (Python's
//!   `venv` refuses a symlinked directory, and a failed `venv` would let `pip` install into the
//!   system interpreter: the harness checks the environment was made); pip's download cache
//!   keeps later runs cheap;
//! - `../shared` (the LV meshes beside the repository) is a symlink to the repository's.
//!
//! Blocks not run are listed in [`NOT_RUN`] with the reason; the Gmsh block skips (saying why)
//! only where Gmsh cannot be installed, as `surface_mesh.rs` does.
//!
//! Cost: about 2-4 minutes on the 2-core machine, most of it the Python block (`pip install`,
//! from the cache after the first run) and the demo; the rest is seconds per block. The blocks
//! hold the binary's serial lock ([`haptic_e2e::serial`]) except while they install (the venv
//! and `pip install` lines), so the other end-to-end tests run meanwhile.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{Context, Result, bail, ensure};
use haptic_e2e::{
    Daemon, HAPTICD, binary, install, serial_blocking, unique_temp_dir, wait_timeout,
};

/// Blocks that are not run: (file, a line of the block, why).
const NOT_RUN: &[(&str, &str, &str)] = &[(
    "README.md",
    "cargo test --workspace --tests",
    "it runs the suite this test belongs to",
)];

/// The block that needs Gmsh (skipped only where Gmsh cannot be installed).
const GMSH_BLOCK: &str = "bash tests/install-gmsh.sh";

/// Longest time one block may take (pip from an empty cache is the slowest); never a
/// performance bound.
const BLOCK_TIMEOUT: Duration = Duration::from_secs(900);

/// A fenced block: its language, first line number (1-based) and text.
struct Block {
    lang: String,
    line: usize,
    text: String,
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("repository root")
        .to_path_buf()
}

/// The fenced blocks of `text`.
fn blocks(text: &str) -> Result<Vec<Block>> {
    let mut out = Vec::new();
    let mut open: Option<Block> = None;
    for (i, line) in text.lines().enumerate() {
        match (&mut open, line.strip_prefix("```")) {
            (None, Some(lang)) => {
                open = Some(Block {
                    lang: lang.trim().to_string(),
                    line: i + 1,
                    text: String::new(),
                })
            }
            (Some(_), Some("")) => out.extend(open.take()),
            (Some(b), _) => {
                b.text.push_str(line);
                b.text.push('\n');
            }
            (None, None) => {}
        }
    }
    ensure!(open.is_none(), "an unclosed fenced block");
    Ok(out)
}

/// The block's logical lines (`\` continuations joined), comments and blank lines kept.
fn logical_lines(text: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    let mut cont = false;
    for line in text.lines() {
        if cont {
            let last = out.last_mut().expect("a line to continue");
            last.push('\n');
            last.push_str(line);
        } else {
            out.push(line.to_string());
        }
        cont = line.trim_end().ends_with('\\');
    }
    out
}

/// Whether `line` only installs (makes the Python environment or runs `pip install`): the
/// documents run no session meanwhile (their daemons are idle), so it needs no serial lock.
fn is_install(line: &str) -> bool {
    let code = line.split('#').next().unwrap_or_default().trim();
    code.starts_with("python3 -m venv ") || code.starts_with("pip install ")
}

/// The daemon's arguments if `line` starts it.
fn daemon_args(line: &str) -> Option<Vec<String>> {
    let code = line.split('#').next()?.trim();
    let rest = code
        .strip_prefix("target/release/hapticd ")
        .or_else(|| code.strip_prefix("hapticd "))?;
    Some(rest.split_whitespace().map(str::to_string).collect())
}

/// A temporary copy of the repository's layout (see the module docs).
fn mirror(bin_dir: &Path) -> Result<PathBuf> {
    let root = unique_temp_dir("haptic-docs")?;
    let repo = repo();
    let m = root.join("repo");
    std::fs::create_dir_all(m.join("target"))?;
    for entry in [
        "ARCHITECTURE.md",
        "Cargo.lock",
        "Cargo.toml",
        "cli",
        "README.md",
        "client-viewer",
        "deploy",
        "device-bridge",
        "docs",
        "proto",
        "server",
        "tests",
    ] {
        std::os::unix::fs::symlink(repo.join(entry), m.join(entry))?;
    }
    std::os::unix::fs::symlink(bin_dir, m.join("target/release"))?;
    std::os::unix::fs::symlink(repo.join("../shared"), root.join("shared"))?;
    Ok(m)
}

/// Runs `script` with bash in `dir`, the exported variables of earlier blocks from `state`
/// and saved back to it.
fn run_script(dir: &Path, state: &Path, script: &str, what: &str) -> Result<()> {
    let full = format!(
        "set -eo pipefail\n[ -f {state} ] && . {state}\n{script}\nwait\nexport -p > {state}\n",
        state = state.display()
    );
    let out_path = state.with_extension("out");
    let err_path = state.with_extension("err");
    let mut child = Command::new("bash")
        .arg("-c")
        .arg(&full)
        .current_dir(dir)
        // The user's own settings must not leak in: the documents set what they need.
        .env_remove("HAPTICD_ADDR")
        .env_remove("HAPTICD_TOKEN_FILE")
        .env_remove("HAPTICD_TOKEN")
        .env_remove("HAPTICS_TOKEN_FILE")
        .env_remove("HAPTICS_TOKEN")
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out_path)?)
        .stderr(std::fs::File::create(&err_path)?)
        .spawn()?;
    let status = match wait_timeout(&mut child, BLOCK_TIMEOUT)? {
        Some(s) => s,
        None => {
            let _ = child.kill();
            let _ = child.wait();
            bail!("{what} did not finish within {BLOCK_TIMEOUT:?}");
        }
    };
    let out = std::fs::read_to_string(&out_path).unwrap_or_default();
    let err = std::fs::read_to_string(&err_path).unwrap_or_default();
    eprintln!(
        "---- {what}: {status}\n{}",
        tail(&format!("{out}{err}"), 1500)
    );
    ensure!(
        status.success(),
        "{what} failed ({status}):\n{script}\n---- stdout\n{}\n---- stderr\n{}",
        tail(&out, 4000),
        tail(&err, 4000)
    );
    Ok(())
}

fn tail(s: &str, n: usize) -> &str {
    let mut start = s.len().saturating_sub(n);
    while !s.is_char_boundary(start) {
        start += 1;
    }
    &s[start..]
}

/// The documents' runner state for one file: its daemons and address substitutions.
struct Runner {
    dir: PathBuf,
    state: PathBuf,
    hapticd: PathBuf,
    daemons: Vec<Daemon>,
    addresses: Vec<(String, String)>,
}

impl Runner {
    /// Starts the daemon of a document line (see the module docs).
    fn start_daemon(&mut self, args: &[String], what: &str) -> Result<()> {
        let named = args
            .iter()
            .position(|a| a == "--listen")
            .and_then(|i| args.get(i + 1))
            .cloned()
            .unwrap_or_else(|| "127.0.0.1:50051".to_string());
        let mut args: Vec<&str> = args.iter().map(String::as_str).collect();
        if let Some(i) = args.iter().position(|a| *a == "--listen") {
            args.drain(i..i + 2);
        }
        let d = Daemon::spawn_in(&self.hapticd, &args, Some(&self.dir))
            .with_context(|| format!("{what}: starting `hapticd {}`", args.join(" ")))?;
        self.addresses.push((named, d.addr.to_string()));
        self.daemons.push(d);
        Ok(())
    }

    fn substitute(&self, line: &str) -> String {
        let mut l = line
            .replace("cargo build --release --workspace", ":")
            .replace(
                "target/release/haptic-demo",
                "target/release/haptic-demo --hold-s 0.5",
            );
        for (from, to) in &self.addresses {
            l = l.replace(from.as_str(), to);
        }
        l
    }

    /// Runs one block: segments between daemon lines, as scripts.
    /// Runs block `b` of `file`: its lines in segments, a segment ending at a daemon line or
    /// where lines change between installing ([`is_install`]) and the rest. Only installing
    /// runs without the [`serial_blocking`] lock, so the other end-to-end tests go on meanwhile.
    fn run_block(&mut self, file: &str, b: &Block) -> Result<()> {
        let what = format!("{file}:{}", b.line);
        let mut segment = String::new();
        let mut installing = false;
        for line in logical_lines(&b.text) {
            let (daemon, install) = (daemon_args(&line), is_install(&line));
            if daemon.is_some() || install != installing {
                self.run_segment(&segment, installing, &what)?;
                segment.clear();
                installing = install;
            }
            if let Some(args) = daemon {
                let _serial = serial_blocking();
                self.start_daemon(&args, &what)?;
            } else {
                segment.push_str(&self.substitute(&line));
                segment.push('\n');
            }
        }
        self.run_segment(&segment, installing, &what)
    }

    /// Runs `segment` of block `what` (nothing when blank), holding the serial lock unless it
    /// is `installing`.
    fn run_segment(&self, segment: &str, installing: bool, what: &str) -> Result<()> {
        if segment.trim().is_empty() {
            return Ok(());
        }
        let _serial = (!installing).then(serial_blocking);
        run_script(&self.dir, &self.state, segment, what)
    }
}

/// Runs every command block of `file`; `before` is a daemon line to start first.
fn run_file(dir: &Path, file: &str, before: Option<&str>) -> Result<Vec<String>> {
    let text = std::fs::read_to_string(repo().join(file))?;
    let mut runner = Runner {
        dir: dir.to_path_buf(),
        state: unique_temp_dir("haptic-docs-state")?.join("env.sh"),
        hapticd: binary(HAPTICD)?,
        daemons: Vec::new(),
        addresses: Vec::new(),
    };
    if let Some(line) = before {
        let args = daemon_args(line).context("not a daemon line")?;
        let _serial = serial_blocking();
        runner.start_daemon(&args, &format!("{file} (the README's daemon)"))?;
    }
    let mut report = Vec::new();
    for b in blocks(&text)? {
        ensure!(
            !b.lang.is_empty(),
            "{file}:{}: a fenced block without a language (`sh` for commands, `text` for \
             output)",
            b.line
        );
        if !matches!(b.lang.as_str(), "sh" | "bash") {
            continue;
        }
        if let Some((_, _, why)) = NOT_RUN
            .iter()
            .find(|(f, l, _)| *f == file && b.text.lines().any(|x| x.trim() == *l))
        {
            report.push(format!("{file}:{}: not run: {why}", b.line));
            continue;
        }
        if b.text.contains(GMSH_BLOCK)
            && let Err(missing) = install::find_or_install("gmsh", "install-gmsh.sh", None)
        {
            install::skip_or_fail(&format!("{file}:{} (Gmsh)", b.line), &missing)?;
            report.push(format!("{file}:{}: skipped: gmsh {missing}", b.line));
            continue;
        }
        // A failing block does not hide the others: all run, the failures are reported together.
        let t = std::time::Instant::now();
        match runner.run_block(file, &b) {
            Ok(()) => report.push(format!(
                "{file}:{}: ran ({:.0} s)",
                b.line,
                t.elapsed().as_secs_f64()
            )),
            Err(e) => report.push(format!("{file}:{}: FAILED: {e:#}", b.line)),
        }
    }
    Ok(report)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_command_block_of_the_readme_and_tools_md_runs_as_written() -> Result<()> {
    // The blocks take the serial lock themselves, all but the installing lines
    // (`Runner::run_block`).
    let bin_dir = binary(HAPTICD)?
        .parent()
        .context("binary directory")?
        .to_path_buf();
    let dir = mirror(&bin_dir)?;
    let readme = std::fs::read_to_string(repo().join("README.md"))?;
    let readme_daemon = readme
        .lines()
        .find(|l| l.starts_with("target/release/hapticd "))
        .context("the README starts no daemon")?
        .to_string();
    let result = tokio::task::spawn_blocking(move || -> Result<Vec<String>> {
        let mut report = run_file(&dir, "README.md", None)?;
        report.extend(run_file(&dir, "docs/tools.md", Some(&readme_daemon))?);
        // What the commands wrote stayed in the copy.
        for out in [
            "out/press.csv",
            "out/viewer-out/latest.png",
            "out/solve-out/nodes.csv",
            "out/session.mcap",
            "out/vtu/surface.pvd",
            ".venv/bin/python",
        ] {
            if !dir.join(out).is_file() {
                report.push(format!("{out}: FAILED: not written"));
            }
        }
        let _ = std::fs::remove_dir_all(dir.parent().unwrap_or(&dir));
        Ok(report)
    })
    .await??;
    eprintln!("{}", result.join("\n"));
    let failed: Vec<&str> = result
        .iter()
        .map(String::as_str)
        .filter(|l| l.contains(": FAILED: "))
        .collect();
    assert!(
        failed.is_empty(),
        "{} block(s) failed:\n{}",
        failed.len(),
        failed.join("\n\n")
    );
    assert!(result.iter().any(|l| l.contains("not run")), "{result:?}");
    Ok(())
}
