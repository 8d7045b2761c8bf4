#!/usr/bin/env bash
# Replaces the vendored three.js files with those of `three@VERSION` from the npm registry
# (npm pack: the package tarball only, no install scripts) and prints their sha256 for README.md.
set -euo pipefail
version="${1:?usage: update.sh VERSION (e.g. 0.187.0)}"
here="$(cd "$(dirname "$0")" && pwd)"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm pack --silent "three@${version}" >/dev/null && tar xzf "three-${version}.tgz")
cp "$tmp/package/build/three.module.js" "$tmp/package/build/three.core.js" \
   "$tmp/package/examples/jsm/controls/OrbitControls.js" "$tmp/package/LICENSE" "$here/"
sha256sum "$tmp/three-${version}.tgz" "$here"/three.module.js "$here"/three.core.js \
    "$here"/OrbitControls.js "$here"/LICENSE
