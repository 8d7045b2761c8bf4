//! Each of the package's programs introduces itself (issue 47): `--help` begins with the
//! program's own description, not the daemon's (clap's bare `about` took the crate's).

use std::process::Command;

#[test]
fn help_begins_with_each_programs_own_description() {
    for (exe, first) in [
        (
            env!("CARGO_BIN_EXE_hapticd"),
            "Networked haptic server for real-time soft-body simulation",
        ),
        (
            env!("CARGO_BIN_EXE_haptic-solve"),
            "Static equilibrium of a scene",
        ),
        (
            env!("CARGO_BIN_EXE_haptic-mesh"),
            "Turn a closed organ surface into a tetrahedral mesh and a scene",
        ),
        (
            env!("CARGO_BIN_EXE_haptic-calibrate"),
            "Calibrate the subdivided spring constants of a mass-spring scene",
        ),
    ] {
        for flag in ["--help", "-h"] {
            let out = Command::new(exe).arg(flag).output().expect("runs");
            assert!(out.status.success(), "{exe} {flag}: {out:?}");
            let text = String::from_utf8_lossy(&out.stdout);
            assert!(text.starts_with(first), "{exe} {flag}:\n{text}");
            // The crate's description ("hapticd: the haptic server daemon ...") is nobody's.
            assert!(
                !text.contains("hapticd: the haptic server daemon"),
                "{exe}:\n{text}"
            );
        }
    }
}
