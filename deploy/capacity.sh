#!/usr/bin/env bash
# Capacity of one machine (issue 48, section 4): N concurrent sessions of one scene in one
# daemon, each pressed by its own simulated arm (`haptic-bridge --script press`, the demo's
# press: from 14 mm off the LV's long axis at z = -5 mm, 6 mm along -x at 10 mm/s, i.e. 3.7 mm
# into the epicardium, then held), and each session's statistics read after the arms let go.
#
#   deploy/capacity.sh [SCENE] [N] [HOLD_S]
#
# SCENE: a built-in name (default lv) or a scene file (sent as text; relative mesh paths
# resolve against deploy/scenes). N: sessions (default 2). HOLD_S: hold at depth (default 5).
# Binaries: $HAPTIC_BIN (default target/release). The press point and direction can be moved
# with START_M, DIRECTION, DEPTH_M (m, as haptic-bridge takes them). THREADS (auto or 1..16,
# default: the daemon's default, auto) is passed as `hapticd --servo-threads`, REGION_CACHE_DIR
# (a directory of region-cache tiles, `hapticd --prepare-regions`) as `--region-cache-dir`. One row per
# session: threads of its tick (servo thread plus tick-pool workers), loop rate over the last
# statistics window, step time p50 / p99 / max, overruns (late ticks), pose-to-force p50 / p99
# (device sample received to force sent, server side), peak force; then the machine (CPU
# model, cores). What the figures mean: docs/benchmarks.md, "Capacity".
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bin=${HAPTIC_BIN:-$root/target/release}
scene=${1:-lv}
n=${2:-2}
hold_s=${3:-5}
start_m=${START_M:-0.014,0,-0.005}
direction=${DIRECTION:--1,0,0}
depth_m=${DEPTH_M:-0.006}
[[ $n =~ ^[1-9][0-9]*$ && $n -le 64 ]] || { echo "capacity: N must be 1..64, not $n" >&2; exit 2; }
threads=${THREADS:-}
[[ -z $threads || $threads == auto || ( $threads =~ ^[1-9][0-9]?$ && $threads -le 16 ) ]] || {
  echo "capacity: THREADS must be auto or 1..16, not $threads" >&2; exit 2; }
[[ $hold_s =~ ^[0-9]+([.][0-9]+)?$ ]] || { echo "capacity: HOLD_S must be seconds, not $hold_s" >&2; exit 2; }
for b in hapticd hapticctl haptic-bridge; do
  [[ -x $bin/$b ]] || { echo "capacity: $bin/$b missing: cargo build --release --workspace" >&2; exit 1; }
done

work=$(mktemp -d)
daemon=
cleanup() {
  [[ -n $daemon ]] && kill "$daemon" 2>/dev/null && wait "$daemon" 2>/dev/null
  rm -rf "$work"
}
trap cleanup EXIT

daemon_args=(--listen 127.0.0.1:0 --scene-dir "$root/deploy/scenes" --data-dir "$root/../shared/data")
[[ -n $threads ]] && daemon_args+=(--servo-threads "$threads")
[[ -n ${REGION_CACHE_DIR:-} ]] && daemon_args+=(--region-cache-dir "$REGION_CACHE_DIR")
"$bin/hapticd" "${daemon_args[@]}" > "$work/hapticd.log" 2>&1 &
daemon=$!
addr=
for _ in $(seq 1 100); do
  addr=$(grep -m1 -o 'listening on [0-9.:]*' "$work/hapticd.log" | awk '{print $3}') || true
  [[ -n $addr ]] && break
  kill -0 "$daemon" 2>/dev/null || { cat "$work/hapticd.log" >&2; exit 1; }
  sleep 0.1
done
[[ -n $addr ]] || { echo "capacity: hapticd did not say where it listens" >&2; exit 1; }
export HAPTICD_ADDR=http://$addr

sids=()
for i in $(seq 1 "$n"); do
  t0=$(date +%s.%N)
  if [[ -f $scene ]]; then
    args=(start --scene-file "$scene")
  else
    args=(start "$scene")
  fi
  sid=$("$bin/hapticctl" "${args[@]}" 2> "$work/start.err") || {
    echo "capacity: session $i did not start:" >&2
    cat "$work/start.err" >&2
    exit 1
  }
  t1=$(date +%s.%N)
  printf 'session %2d: %s set up in %.2f s\n' "$i" "$sid" "$(awk -v a="$t0" -v b="$t1" 'BEGIN {print b - a}')" >&2
  sids+=("$sid")
done

pids=()
for sid in "${sids[@]}"; do
  "$bin/haptic-bridge" --server "$HAPTICD_ADDR" --session "$sid" --script press --start-m "$start_m" \
    --direction "$direction" --depth-m "$depth_m" --hold-s "$hold_s" \
    > "$work/bridge-$sid.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do
  wait "$p" || { echo "capacity: a bridge failed:" >&2; cat "$work"/bridge-*.log >&2; exit 1; }
done

# One row per session from `hapticctl stats` (FIELD VALUE UNIT lines).
field() { awk -v k="$2" '$1 == k {print $2}' "$1"; }
printf '%-4s %-14s %7s %9s %22s %9s %16s %10s\n' "#" session threads "rate Hz" "step p50/p99/max us" overruns "p2f p50/p99 us" "peak N"
i=0
for sid in "${sids[@]}"; do
  i=$((i + 1))
  "$bin/hapticctl" stats "$sid" > "$work/stats"
  printf '%-4s %-14s %7s %9s %22s %9s %16s %10s\n' "$i" "$sid" "$(field "$work/stats" threads)" \
    "$(field "$work/stats" loop_rate_hz)" \
    "$(field "$work/stats" step_p50_us)/$(field "$work/stats" step_p99_us)/$(field "$work/stats" step_max_us)" \
    "$(field "$work/stats" overruns)" \
    "$(field "$work/stats" pose_to_force_p50_us)/$(field "$work/stats" pose_to_force_p99_us)" \
    "$(field "$work/stats" peak_force_n)"
  "$bin/hapticctl" stop "$sid"
done
echo "scene $scene, $n session(s), threads ${threads:-auto}, hold ${hold_s} s; $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'), $(nproc) cores"
