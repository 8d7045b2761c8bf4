#!/usr/bin/env bash
# Installs Debian's `chromium` for the browser test (tests/tests/web_viewer.rs), from Debian's
# package registry and nothing else. Idempotent: does nothing when `chromium` is on PATH.
# The browser test calls it when it finds no browser, so `cargo test --workspace` from a fresh
# clone sets itself up; it needs root (or sudo without a password) and the package registry.
# Exit codes: 0 installed or present, 1 could not install (the test then skips, saying why).
set -euo pipefail
if command -v chromium >/dev/null 2>&1; then
    echo "chromium present: $(chromium --version 2>/dev/null || echo unknown version)"
    exit 0
fi
if [ "$(id -u)" -eq 0 ]; then
    as_root=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    as_root=(sudo -n)
else
    echo "cannot install chromium: not root and no password-less sudo" >&2
    exit 1
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "cannot install chromium: no apt-get (not a Debian system)" >&2
    exit 1
fi
export DEBIAN_FRONTEND=noninteractive
"${as_root[@]}" apt-get update -qq >&2 || { echo "apt-get update failed" >&2; exit 1; }
"${as_root[@]}" apt-get install -y -qq --no-install-recommends chromium >&2 \
    || { echo "apt-get install chromium failed" >&2; exit 1; }
echo "chromium installed: $(chromium --version 2>/dev/null || echo unknown version)"
