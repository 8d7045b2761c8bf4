//! One failing client does not lock out the others (issue 47, section 2), with the real
//! binaries against a daemon with tokens, all from 127.0.0.1 as on a lab machine:
//!
//! - a bridge without a token, a bridge with a `viewer` token, `hapticctl` and `haptic-viewer`
//!   without one, and the browser relay without one each exit at once with the daemon's
//!   reason instead of retrying (the relay before it serves a page);
//! - after those failures, more than the address's failure limit, valid `device`, `control` and
//!   `viewer` tokens from the same address still work;
//! - the environment variables follow one scheme: `HAPTICD_ADDR` for every client including
//!   the bridge, `HAPTICD_TOKEN_FILE`, and the older `HAPTICS_TOKEN_FILE` still answered.

use std::time::Duration;

use anyhow::{Context, Result};
use haptic_e2e::{
    BRIDGE, CTL, Daemon, STEP_TIMEOUT, VIEWER, run_bin, run_bin_env, serial, unique_temp_dir,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_clients_exit_at_once_and_never_lock_out_valid_tokens() -> Result<()> {
    let _serial = serial().await;
    let dir = unique_temp_dir("haptic-refused")?;
    let tokens = dir.join("tokens.toml");
    let daemon = Daemon::spawn(&["--tokens-file", &tokens.display().to_string()])?;
    let url = daemon.url();
    let token = |role: &str| dir.join(format!("{role}.token")).display().to_string();
    let (control, device, viewer) = (token("control"), token("device"), token("viewer"));

    // A session, started with the new variable names only.
    let started = run_bin_env(
        CTL,
        &["start", "lv"],
        &[("HAPTICD_ADDR", &url), ("HAPTICD_TOKEN_FILE", &control)],
        STEP_TIMEOUT,
    )
    .await?
    .success()?;
    let id = started.stdout.trim().to_string();

    // Refused bridges: no token, then a role without the device link. Each stops at once
    // (exit 4) with the reason, where it used to retry for as long as it ran.
    let press = [
        "--session",
        &id,
        "--rearm",
        "auto",
        "--duration-s",
        "60",
        "--json",
    ];
    for (env, code) in [
        (vec![("HAPTICD_ADDR", url.as_str())], "Unauthenticated"),
        (
            vec![
                ("HAPTICD_ADDR", url.as_str()),
                ("HAPTICS_TOKEN_FILE", viewer.as_str()),
            ],
            "PermissionDenied",
        ),
    ] {
        let out = run_bin_env(BRIDGE, &press, &env, STEP_TIMEOUT).await?;
        assert_eq!(out.status.code(), Some(4), "{out:?}");
        assert!(
            out.stderr.contains("refused the device link") && out.stderr.contains(code),
            "{out:?}"
        );
        let summary = out.json()?;
        assert_eq!(summary["streams_opened"], 0, "{summary}");
        assert!(summary["access_refused"].is_string(), "{summary}");
    }

    // More failures from this address than its limit (10 per 10 s): hapticctl and the viewer
    // without a token report the code and exit 2.
    for _ in 0..10 {
        let out = run_bin(CTL, &["--server", &url, "sessions"], STEP_TIMEOUT).await?;
        assert_eq!(out.status.code(), Some(2), "{out:?}");
        assert!(out.stderr.contains("UNAUTHENTICATED"), "{out:?}");
    }
    let out = run_bin(
        VIEWER,
        &[
            "--server",
            &url,
            "--session",
            &id,
            "--out",
            &dir.join("v").display().to_string(),
        ],
        STEP_TIMEOUT,
    )
    .await?;
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(out.stderr.contains("UNAUTHENTICATED"), "{out:?}");
    // The browser relay checks its credentials before serving anything.
    let out = run_bin(
        VIEWER,
        &["--server", &url, "--web", "127.0.0.1:0"],
        STEP_TIMEOUT,
    )
    .await?;
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(
        out.stderr.contains("UNAUTHENTICATED") && !out.stdout.contains("listening on"),
        "{out:?}"
    );

    // Valid tokens from the same address still pass: a device press (the older variable name),
    // statistics with the control token, a viewer.
    let out = run_bin_env(
        BRIDGE,
        &[
            "--session",
            &id,
            "--rearm",
            "auto",
            "--hold-s",
            "0.2",
            "--depth-m",
            "0.002",
            "--json",
        ],
        &[("HAPTICD_ADDR", &url), ("HAPTICS_TOKEN_FILE", &device)],
        Duration::from_secs(60),
    )
    .await?
    .success()?;
    let summary = out.json()?;
    assert!(
        summary["forces_received"].as_u64().unwrap_or(0) > 0,
        "{summary}"
    );
    assert!(summary["access_refused"].is_null(), "{summary}");
    run_bin_env(
        CTL,
        &["stats", &id],
        &[("HAPTICD_ADDR", &url), ("HAPTICD_TOKEN_FILE", &control)],
        STEP_TIMEOUT,
    )
    .await?
    .success()
    .context("a control token after the failures")?;
    run_bin_env(
        VIEWER,
        &[
            "--session",
            &id,
            "--duration-s",
            "0.5",
            "--out",
            &dir.join("v").display().to_string(),
        ],
        &[("HAPTICD_ADDR", &url), ("HAPTICD_TOKEN_FILE", &viewer)],
        STEP_TIMEOUT,
    )
    .await?
    .success()
    .context("a viewer token after the failures")?;
    drop(daemon);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
