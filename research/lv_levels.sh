#!/usr/bin/env bash
# Runs lv_probe.py for one material over the given mesh levels, coarse to fine, one after the
# other (each level's CSV in research/results/, its log in target/research-logs/).
# Usage: research/lv_levels.sh MATERIAL "H1 H2 ..." [extra lv_probe.py arguments]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(dirname "$here")"
py="$root/target/research-venv/bin/python"
material="$1"; levels="$2"; shift 2
mkdir -p "$root/target/research-logs"
for h in $levels; do
  "$py" "$here/lv_probe.py" --material "$material" --h "$h" "$@" \
    > "$root/target/research-logs/lv_${material}_h${h}.log" 2>&1 || echo "level $h failed"
done
