#!/usr/bin/env bash
# Peer measurement (issue 3, section 4): our StVK force against pbatoolkit's StVK gradient on
# lv_h1.msh (17 924 tets) with a smooth analytic deformation, both on one core, in one run.
# Also NVIDIA Warp's CPU kernel (pip install warp-lang; peer_warp.py) on the same case.
# Creates target/peer-venv (pip install pbatoolkit numpy scipy), exports the case with
# `cargo run --release -p haptic-model --example export_peer_case` (one thread pinned to core 0
# like the peer, then two threads unpinned into $case_dir/threads), runs the peer, and prints
# and writes target/bench/peer.json; with --publish, docs/bench/peer.json (the committed result)
# instead. Not part of `cargo test`.
# Usage: server/model/benches/peer/run_peer.sh [--publish] [REPEATS]
set -euo pipefail
cd "$(dirname "$0")/../../../.."
out=target/bench
if [ "${1:-}" = "--publish" ]; then
  out=docs/bench
  shift
fi
repeats="${1:-50}"
venv=target/peer-venv
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
fi
"$venv/bin/pip" install -q pbatoolkit numpy scipy
case_dir=target/peer-case
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
taskset -c 0 cargo run --release -q -p haptic-model --example export_peer_case -- "$case_dir" 200 \
  || cargo run --release -q -p haptic-model --example export_peer_case -- "$case_dir" 200
# ours in two parts on two threads (issue 48 s3), unpinned: the same case in a subfolder
cargo run --release -q -p haptic-model --example export_peer_case -- "$case_dir/threads" 200 --threads 2
if command -v taskset >/dev/null; then pin="taskset -c 0"; else pin=""; fi
$pin "$venv/bin/python" server/model/benches/peer/peer_stvk.py "$case_dir" "$repeats"
# NVIDIA Warp's CPU kernel in double precision (the peer issue 48 names), beside the same case
if "$venv/bin/pip" install -q warp-lang; then
  $pin "$venv/bin/python" server/model/benches/peer/peer_warp.py "$case_dir" "$repeats"
else
  echo "warp-lang not installed: peer.json has no warp_* fields"
fi
mkdir -p "$out"
cp "$case_dir/peer.json" "$out/peer.json"
echo "wrote $out/peer.json"
