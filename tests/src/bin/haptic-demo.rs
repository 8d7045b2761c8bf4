//! `haptic-demo`: runs one scripted session of the whole product with the real binaries that
//! sit beside it (hapticd, hapticctl, haptic-viewer, haptic-bridge) and prints a summary.
//! Glue only: the work is in `haptic_e2e::demo`.
//!
//! Usage: `haptic-demo [--out DIR] [--bin-dir DIR] [--hold-s S]` (`--help` lists them).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Result;
use clap::Parser;
use haptic_e2e::demo::{self, DemoParams};

/// Runs one scripted session of the whole product with the binaries beside this executable
/// and prints a summary.
#[derive(Debug, Parser)]
#[command(name = "haptic-demo")]
struct Args {
    /// Output directory (pictures, the bridge CSV, summary.json).
    #[arg(long, value_name = "DIR", default_value_os_t = DemoParams::new(PathBuf::new()).out_dir)]
    out: PathBuf,
    /// Where the workspace binaries are (default: beside this executable).
    #[arg(long, value_name = "DIR")]
    bin_dir: Option<PathBuf>,
    /// How long the simulated hand holds the press, seconds (0 to 60).
    #[arg(long, value_name = "S", value_parser = hold_s, default_value_t = DemoParams::new(PathBuf::new()).hold_s)]
    hold_s: f64,
}

/// `--hold-s`: a number of seconds within 0..=60.
fn hold_s(s: &str) -> Result<f64, String> {
    let h: f64 = s.parse().map_err(|e| format!("{s:?}: {e}"))?;
    if h.is_finite() && (0.0..=60.0).contains(&h) {
        Ok(h)
    } else {
        Err(format!("must be within 0..=60, got {h}"))
    }
}

impl Args {
    fn params(self) -> Result<DemoParams> {
        let bin_dir = match self.bin_dir {
            Some(d) => d,
            None => haptic_e2e::sibling_bin_dir()?,
        };
        let mut p = DemoParams::new(bin_dir);
        p.out_dir = self.out;
        p.hold_s = self.hold_s;
        Ok(p)
    }
}

#[tokio::main]
async fn main() -> ExitCode {
    let args = Args::parse();
    let result = async {
        let p = args.params()?;
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

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Args, clap::Error> {
        Args::try_parse_from(std::iter::once("haptic-demo").chain(args.iter().copied()))
    }

    #[test]
    fn the_flags_and_their_defaults() {
        let a = parse(&[]).unwrap();
        assert_eq!(a.out, PathBuf::from("demo-out"));
        assert_eq!((a.bin_dir, a.hold_s), (None, 3.0));
        let a = parse(&["--out", "o", "--bin-dir", "b", "--hold-s", "0.5"]).unwrap();
        assert_eq!(a.out, PathBuf::from("o"));
        assert_eq!(a.bin_dir, Some(PathBuf::from("b")));
        assert_eq!(a.hold_s, 0.5);
        let p = parse(&["--bin-dir", "b", "--hold-s", "60"])
            .unwrap()
            .params()
            .unwrap();
        assert_eq!(
            (p.out_dir, p.bin_dir, p.hold_s),
            ("demo-out".into(), "b".into(), 60.0)
        );
    }

    #[test]
    fn bad_flags_are_refused() {
        for bad in [
            &["--hold-s", "61"][..],
            &["--hold-s", "-0.1"],
            &["--hold-s", "NaN"],
            &["--hold-s", "inf"],
            &["--hold-s", "x"],
            &["--hold-s"],
            &["--out"],
            &["--frobnicate"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?}");
        }
        let e = parse(&["--hold-s", "61"]).unwrap_err().to_string();
        assert!(e.contains("0..=60"), "{e}");
    }
}
