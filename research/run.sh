#!/usr/bin/env bash
# Runs one study of the independent scikit-fem contact solver (see research/README.md).
# Makes the virtual environment target/research-venv (from requirements.txt) if missing.
#
#   research/run.sh hertz                 # Hertz block, six depths, per-depth time
#   research/run.sh lv MATERIAL H [ARGS]  # one LV level: stvk | stable-neo-hookean, H in mm
#   research/run.sh lv-levels MATERIAL "H1 H2 ..." [ARGS]   # several levels in sequence
#   research/run.sh gci [--preliminary PATH]                # Richardson + GCI over the levels
#   research/run.sh check                 # quick self-checks (material tangents, a tiny press)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(dirname "$here")"
venv="$root/target/research-venv"
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet --upgrade pip
  "$venv/bin/pip" install --quiet -r "$here/requirements.txt"
fi
py="$venv/bin/python"
study="${1:-}"; shift || true
case "$study" in
  hertz) exec "$py" "$here/hertz_block.py" "$@" ;;
  lv) material="$1"; h="$2"; shift 2
      exec "$py" "$here/lv_probe.py" --material "$material" --h "$h" "$@" ;;
  lv-levels) exec "$here/lv_levels.sh" "$@" ;;
  gci) exec "$py" "$here/lv_gci.py" "$@" ;;
  check) exec "$py" "$here/check.py" "$@" ;;
  *) echo "usage: research/run.sh hertz|lv|lv-levels|gci|check [args]" >&2; exit 2 ;;
esac
