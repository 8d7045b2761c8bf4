#!/usr/bin/env bash
# Installs Debian's `gmsh` for the surface-meshing test (tests/tests/surface_mesh.rs) and haptic-mesh, from Debian's
# package registry and nothing else. Idempotent: does nothing when `gmsh` is on PATH.
# The surface-meshing test calls it when it finds no gmsh, so `cargo test --workspace` from a fresh
# clone sets itself up; it needs root (or sudo without a password) and the package registry.
# Exit codes: 0 installed or present, 1 could not install (the test then skips, saying why).
set -euo pipefail
if command -v gmsh >/dev/null 2>&1; then
    echo "gmsh present: $(gmsh --version 2>/dev/null || echo unknown version)"
    exit 0
fi
if [ "$(id -u)" -eq 0 ]; then
    as_root=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    as_root=(sudo -n)
else
    echo "cannot install gmsh: not root and no password-less sudo" >&2
    exit 1
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "cannot install gmsh: no apt-get (not a Debian system)" >&2
    exit 1
fi
export DEBIAN_FRONTEND=noninteractive
"${as_root[@]}" apt-get update -qq >&2 || { echo "apt-get update failed" >&2; exit 1; }
"${as_root[@]}" apt-get install -y -qq --no-install-recommends gmsh >&2 \
    || { echo "apt-get install gmsh failed" >&2; exit 1; }
echo "gmsh installed: $(gmsh --version 2>/dev/null || echo unknown version)"
