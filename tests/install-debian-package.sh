#!/usr/bin/env bash
# Installs one Debian package for a test that needs a program (tests/install-chromium.sh,
# tests/install-gmsh.sh), from Debian's package registry and nothing else. Idempotent: does
# nothing when the program is on PATH. Needs root (or sudo without a password) and apt.
# Usage: install-debian-package.sh PACKAGE [PROGRAM]   (PROGRAM defaults to PACKAGE)
# Exit codes: 0 installed or present; 2 this machine cannot install packages (not root and no
# password-less sudo, no apt-get, or apt-get update fails: no network or registry), where a test
# skips saying why, even in CI; 1 the install failed otherwise (a test fails under CI=true).
# tests/src/install.rs reads them.
set -euo pipefail
package="$1"
program="${2:-$1}"
present() {
    if command -v "$program" >/dev/null 2>&1; then
        echo "$program present: $("$program" --version 2>/dev/null | head -n 1 || echo unknown version)"
        exit 0
    fi
}
present
# Tests run in parallel: two of them may want the same package at once. One install at a time
# (flock on a file of ours), and the program looked for again once the lock is held; apt-get
# also waits for dpkg's own lock (another apt on the machine) instead of failing at once.
lock="${TMPDIR:-/tmp}/haptic-install-debian-package.lock"
(umask 000; touch "$lock") 2>/dev/null || true   # any user's install may take it later
if command -v flock >/dev/null 2>&1 && [ -w "$lock" ]; then
    exec 9>"$lock"
    flock 9
    present
fi
apt_wait=(-o DPkg::Lock::Timeout=600)
if [ "$(id -u)" -eq 0 ]; then
    as_root=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    as_root=(sudo -n)
else
    echo "cannot install $package: not root and no password-less sudo" >&2
    exit 2
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "cannot install $package: no apt-get (not a Debian system)" >&2
    exit 2
fi
export DEBIAN_FRONTEND=noninteractive
"${as_root[@]}" apt-get "${apt_wait[@]}" update -qq >&2 \
    || { echo "cannot install $package: apt-get update failed (no network or registry)" >&2; exit 2; }
"${as_root[@]}" apt-get "${apt_wait[@]}" install -y -qq --no-install-recommends "$package" >&2 \
    || { echo "apt-get install $package failed" >&2; exit 1; }
echo "$program installed: $("$program" --version 2>/dev/null | head -n 1 || echo unknown version)"
