#!/usr/bin/env bash
# Debian's `chromium` for the browser test (tests/tests/web_viewer.rs); the test runs this when
# it finds no browser, so `cargo test --workspace` from a fresh clone sets itself up. Exit 2: this
# machine cannot install it (the test skips, even under CI=true); 1: the install failed.
exec bash "$(dirname "$0")/install-debian-package.sh" chromium
