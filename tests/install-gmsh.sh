#!/usr/bin/env bash
# Debian's `gmsh` for haptic-mesh and its test (tests/tests/surface_mesh.rs); the test runs this
# when it finds no gmsh, so `cargo test --workspace` from a fresh clone sets itself up.
exec bash "$(dirname "$0")/install-debian-package.sh" gmsh
