//! The Python client (`client-viewer/python`, issue 19) against the real `hapticd` on 127.0.0.1:0: a
//! virtual environment under the target folder, `pip install ./client-viewer/python[test]` (the gRPC
//! stubs are generated from `proto/` by the package's build), then `client-viewer/python/tests/
//! live_test.py` (scenes, a session from a name and from TOML text, an injected force seen in
//! the frames, a scripted press, statistics, stop, errors, reflection `v1alpha` through
//! `grpcio-reflection`, a bridge recording read back, and a `hapticctl record` MCAP file
//! decoded by Foxglove's `mcap-protobuf-support` from the schemas inside it).
//!
//! Needs `python3` with `venv` and the PyPI registry (both on these machines); a missing one
//! fails the test with the reason, it is not skipped.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, ensure};
use haptic_e2e::{
    BRIDGE, CTL, Daemon, finish, run_bin, serial, spawn_bin, start_session, unique_temp_dir,
};

fn run(cmd: &mut Command, what: &str) -> Result<String> {
    let out = cmd
        .output()
        .with_context(|| format!("{what}: could not start {cmd:?}"))?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    ensure!(
        out.status.success(),
        "{what} failed ({}):\n{text}",
        out.status
    );
    Ok(text)
}

/// A venv with the package installed from this checkout (re-installed every run, so the stubs
/// follow `proto/`; pip's cache keeps the dependencies).
fn venv(repo: &Path) -> Result<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("python-venv");
    let python = dir.join("bin").join("python");
    if !python.exists() {
        run(
            Command::new("python3").args(["-m", "venv"]).arg(&dir),
            "python3 -m venv (the Python client test needs python3 with venv)",
        )?;
    }
    run(
        Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "--upgrade",
            ])
            .arg(format!(
                "{}[test]",
                repo.join("client-viewer/python").display()
            )),
        "pip install ./client-viewer/python[test]",
    )?;
    Ok(python)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_client_drives_a_live_daemon() -> Result<()> {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .context("repository root")?
        .to_path_buf();
    let python = tokio::task::spawn_blocking({
        let repo = repo.clone();
        move || venv(&repo)
    })
    .await??;

    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    // A recording for the client to read back: the bridge presses a session of its own.
    let id = start_session(&url, "lv").await?;
    let dir = unique_temp_dir("haptic-e2e-python")?;
    let csv = dir.join("press.csv");
    let csv_arg = csv.display().to_string();
    // ... while `hapticctl record` records the session to MCAP.
    let mcap = dir.join("session.mcap");
    let mcap_arg = mcap.display().to_string();
    let recorder = spawn_bin(
        CTL,
        &[
            "--server",
            &url,
            "record",
            &id,
            "--out",
            &mcap_arg,
            "--duration-s",
            "1.5",
        ],
    )?;
    run_bin(
        BRIDGE,
        &[
            "--server",
            &url,
            "--session",
            &id,
            "--script",
            "press",
            "--hold-s",
            "0.2",
            "--record",
            &csv_arg,
        ],
        haptic_e2e::STEP_TIMEOUT,
    )
    .await?
    .success()?;
    finish(recorder, haptic_e2e::STEP_TIMEOUT)
        .await?
        .success()?;

    let script = repo.join("client-viewer/python/tests/live_test.py");
    let out = tokio::task::spawn_blocking(move || {
        Command::new(&python)
            .arg(&script)
            .env("HAPTICS_SERVER", &url)
            .env("HAPTICS_RECORDING", &csv)
            .env("HAPTICS_MCAP", &mcap)
            .output()
    })
    .await??;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{text}");
    ensure!(
        out.status.success(),
        "live_test.py failed:\n{text}\ndaemon log:\n{}",
        daemon.log_tail()
    );
    ensure!(
        !text.contains("skipped"),
        "a Python test was skipped:\n{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
