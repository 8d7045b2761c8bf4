//! Programs a test needs from Debian (`chromium` for the browser test, `gmsh` for the surface
//! meshing test): found on PATH or installed by the project's script
//! (`tests/install-debian-package.sh` behind `install-chromium.sh` and `install-gmsh.sh`), and
//! the one rule for a test without its program ([`skip_or_fail`]): it skips, saying why where
//! `cargo test` shows it, only where the program cannot be installed; under `CI=true` any other
//! reason fails the test.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Exit status of `install-debian-package.sh` when this machine cannot install a package at all
/// (not root and no password-less sudo, no apt-get, or `apt-get update` fails: no network or no
/// reachable package registry). Any other failure exits 1.
pub const CANNOT_INSTALL_HERE: i32 = 2;

/// Why a test's program is missing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Missing {
    /// The install script said this machine cannot install it (the only reason to skip in CI).
    CannotInstallHere(String),
    /// Anything else: the install failed, installed but not on PATH, or installing was turned
    /// off by an environment variable.
    NotInstalled(String),
}

impl std::fmt::Display for Missing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Missing::CannotInstallHere(why) => write!(f, "cannot be installed here: {why}"),
            Missing::NotInstalled(why) => write!(f, "not installed: {why}"),
        }
    }
}

/// `program` on PATH, else runs `tests/<script>` and looks again; `skip_env`, when set in the
/// environment, turns the install off.
///
/// # Errors
/// [`Missing`] saying why there is no `program`.
pub fn find_or_install(
    program: &str,
    script: &str,
    skip_env: Option<&str>,
) -> Result<PathBuf, Missing> {
    if let Some(p) = which(program) {
        return Ok(p);
    }
    if let Some(var) = skip_env.filter(|v| std::env::var_os(v).is_some()) {
        return Err(Missing::NotInstalled(format!(
            "{program} is missing and {var} is set"
        )));
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join(script);
    let out = Command::new("bash")
        .arg(&script)
        .output()
        .map_err(|e| Missing::NotInstalled(format!("running {}: {e}", script.display())))?;
    if !out.status.success() {
        let why = format!(
            "{} (exit {:?}): {}",
            script.display(),
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).trim()
        );
        return Err(if out.status.code() == Some(CANNOT_INSTALL_HERE) {
            Missing::CannotInstallHere(why)
        } else {
            Missing::NotInstalled(why)
        });
    }
    which(program).ok_or_else(|| {
        Missing::NotInstalled(format!(
            "{} succeeded but {program} is not on PATH",
            script.display()
        ))
    })
}

fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join(name))
            .find(|p| p.is_file())
    })
}

/// Whether the environment says this is a CI run (`CI=true` or `CI=1`, as CI services set it).
pub fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v.eq_ignore_ascii_case("true") || v == "1")
}

/// What a test does without its program: `Ok(())` to skip (after printing `SKIPPED test: why`
/// straight to the process's stderr, which the test harness does not capture, so `cargo test`
/// shows it even for a passing test), or an error that fails the test: under CI
/// ([`in_ci`]) unless the program cannot be installed here.
///
/// # Errors
/// Under CI when `missing` is not [`Missing::CannotInstallHere`].
pub fn skip_or_fail(test: &str, missing: &Missing) -> anyhow::Result<()> {
    let line = rule(in_ci(), test, missing)?;
    // Best effort: a closed stderr must not fail the test.
    let _ = std::io::stderr().write_all(line.as_bytes());
    Ok(())
}

/// The skip line to print, or the error that fails the test.
fn rule(ci: bool, test: &str, missing: &Missing) -> anyhow::Result<String> {
    if ci && !matches!(missing, Missing::CannotInstallHere(_)) {
        anyhow::bail!(
            "{test}: its program is {missing}; under CI=true a test skips only where the program \
             cannot be installed"
        );
    }
    Ok(format!("SKIPPED {test}: its program is {missing}\n"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_machine_that_cannot_install_skips_under_ci() {
        let here = Missing::CannotInstallHere("no apt-get".into());
        let failed = Missing::NotInstalled("apt-get install chromium failed".into());
        assert!(rule(false, "t", &here).unwrap().starts_with("SKIPPED t: "));
        assert!(
            rule(false, "t", &failed)
                .unwrap()
                .contains("apt-get install")
        );
        assert!(
            rule(true, "t", &here)
                .unwrap()
                .contains("cannot be installed here")
        );
        assert!(rule(true, "t", &failed).is_err());
    }

    #[test]
    fn the_install_script_says_when_this_machine_cannot_install() {
        // The real script on a PATH with `id` but no apt-get (nor the program): exit 2, whether
        // it stops at "not root" or at "no apt-get".
        let dir = crate::unique_temp_dir("install-no-apt").unwrap();
        std::os::unix::fs::symlink(which("id").expect("id on PATH"), dir.join("id")).unwrap();
        let bash = which("bash").expect("bash on PATH");
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("install-debian-package.sh");
        let out = Command::new(bash)
            .arg(&script)
            .arg("haptic-no-such-package")
            .env("PATH", &dir)
            .output()
            .unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(CANNOT_INSTALL_HERE), "{stderr}");
        assert!(
            stderr.contains("cannot install haptic-no-such-package"),
            "{stderr}"
        );
    }

    #[test]
    fn a_failed_install_is_not_a_machine_that_cannot_install() {
        // A script that is not there: bash exits 127, not the "cannot install here" status.
        let e = find_or_install("haptic-no-such-program", "no-such-install-script.sh", None)
            .unwrap_err();
        assert!(
            matches!(&e, Missing::NotInstalled(w) if w.contains("no-such-install-script.sh")),
            "{e:?}"
        );
        let e = find_or_install("haptic-no-such-program", "x.sh", Some("PATH")).unwrap_err();
        assert!(
            matches!(&e, Missing::NotInstalled(w) if w.contains("PATH is set")),
            "{e:?}"
        );
    }
}
