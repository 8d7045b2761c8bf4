//! `haptic-demo`: runs one scripted session of the whole product with the real binaries that
//! sit beside it (hapticd, hapticctl, haptic-viewer, haptic-bridge) and prints a summary.
//! Glue only: the work is in `haptic_e2e::demo`.
//!
//! Usage: `haptic-demo [--out DIR] [--bin-dir DIR] [--hold-s S]`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use haptic_e2e::demo::{self, DemoParams};

fn parse() -> Result<DemoParams> {
    let mut args = std::env::args().skip(1);
    let mut bin_dir = None;
    let mut out = None;
    let mut hold = None;
    while let Some(a) = args.next() {
        let mut value = || args.next().with_context(|| format!("{a} needs a value"));
        match a.as_str() {
            "--out" => out = Some(PathBuf::from(value()?)),
            "--bin-dir" => bin_dir = Some(PathBuf::from(value()?)),
            "--hold-s" => hold = Some(value()?.parse::<f64>().context("--hold-s")?),
            "-h" | "--help" => {
                println!("usage: haptic-demo [--out DIR (demo-out)] [--bin-dir DIR] [--hold-s S]");
                std::process::exit(0);
            }
            other => bail!("unknown argument {other:?} (try --help)"),
        }
    }
    let bin_dir = match bin_dir {
        Some(d) => d,
        None => haptic_e2e::sibling_bin_dir()?,
    };
    let mut p = DemoParams::new(bin_dir);
    if let Some(o) = out {
        p.out_dir = o;
    }
    if let Some(h) = hold {
        if !(h.is_finite() && (0.0..=60.0).contains(&h)) {
            bail!("--hold-s must be within 0..=60, got {h}");
        }
        p.hold_s = h;
    }
    Ok(p)
}

#[tokio::main]
async fn main() -> ExitCode {
    let result = async {
        let p = parse()?;
        let summary = demo::run(&p, &mut |line| println!("{line}")).await?;
        println!(
            "\n{}",
            demo::format_summary(&summary, &p.out_dir.join("summary.json"))
        );
        anyhow::Ok(())
    }
    .await;
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("haptic-demo failed: {e:#}");
            ExitCode::FAILURE
        }
    }
}
