#!/usr/bin/env bash
# Regenerates the rigid-sphere reference of the lv-probe press,
# server/model/benches/precision/lv_sphere_reference.csv (docs/accuracy.md, "The sphere
# reference on four refined levels"): the half LV meshed by Gmsh at each size parameter
# (lv_probe_half.geo; s = element size under the probe, mm), every level solved by
# `lv_reference solve` for St. Venant-Kirchhoff (sphere depths 0.25, 0.5, 1 mm: it has no
# equilibrium past about 1.2-1.4 mm on the fine levels) and the stable neo-Hookean material
# (0.25 to 4 mm), then `lv_reference combine` (with four or more levels the least-squares
# estimate of Eca & Hoekstra 2014 over all of them; Richardson through the three finest levels
# and Roache's GCI are kept as columns). A level whose solve stops keeps the rows it converged
# (the log says why).
#
#   server/model/examples/lv_reference.sh [OUT_DIR] [LEVELS]
#
# Environment (defaults: the stored reference's family): GEO_ARGS, more Gmsh arguments (the
# second mesh family of docs/accuracy.md, "The shallow rows on a second mesh family":
# "-setnumber r0 0.75 -setnumber phimax 30"); DEPTHS, one depth list for both materials;
# REFERENCE, the combined CSV to write (default the stored reference below); ENSEMBLE, a
# fraction passed as `combine --ensemble` (sizes within it of each other are meshes of one
# level, averaged: docs/accuracy.md, "Mesh ensembles"); LEVELS_FROM, a reference CSV whose
# levels join the solved ones (`combine --levels-from`).
#
# LEVELS: the size parameters, coarse to fine (default "0.6 0.42 0.3 0.2121 0.15 0.10607:stvk");
# a level written S:MATERIAL is solved for that material only (the sixth level, 219 211 nodes,
# for StVK: about 1.7 h and 7.4 GB here; the stable neo-Hookean material to 4 mm there would
# take an estimated 5-8 h). A level already solved (OUT_DIR/level_S_MATERIAL.csv.done) is not
# solved again; one interrupted (killed, machine stopped) continues after its last finished
# depth from OUT_DIR/level_S_MATERIAL.ckpt, so a long level can be run a few depths at a time. Needs gmsh (tests/install-gmsh.sh). Run time on the shared 2-core machine:
# about 5 h, most of it the three finest levels (0.2121 mm, 31 403 nodes: about 16 min for
# StVK, 40-50 min for the stable neo-Hookean material to 4 mm; 0.15 mm, 82 389 nodes: about
# 25 min and 1 h).
set -euo pipefail
root=$(cd "$(dirname "$0")/../../.." && pwd)
cd "$root"
out=${1:-target/lv-reference}
levels=${2:-"0.6 0.42 0.3 0.2121 0.15 0.10607:stvk"}
reference=${REFERENCE:-server/model/benches/precision/lv_sphere_reference.csv}
read -r -a geo_args <<< "${GEO_ARGS:-}"
command -v gmsh >/dev/null || { echo "gmsh not found: run tests/install-gmsh.sh" >&2; exit 1; }
mkdir -p "$out"
cargo build --release -p haptic-model --example lv_reference
csvs=()
for level in $levels; do
  s=${level%%:*}
  materials="stvk stable-neo-hookean"
  [[ $level == *:* ]] && materials=${level#*:}
  msh="$out/half_$s.msh"
  [[ -f $msh ]] || gmsh server/model/examples/lv_probe_half.geo -3 -format msh22 \
    -setnumber s "$s" "${geo_args[@]}" -o "$msh" > "$out/gmsh_$s.log"
  for material in $materials; do
    if [[ $material == stvk ]]; then depths=0.25,0.5,1; else depths=0.25,0.5,1,1.5,2,3,4; fi
    depths=${DEPTHS:-$depths}
    csv="$out/level_${s}_$material.csv"
    csvs+=("$csv")
    [[ -f $csv.done ]] && continue
    ckpt="$out/level_${s}_$material.ckpt"
    [[ -f $ckpt ]] || rm -f "$csv"
    echo "== $(date +%T) level $s mm, $material, sphere depths $depths mm"
    if target/release/examples/lv_reference solve --msh "$msh" --h "$s" --material "$material" \
      --depths "$depths" --out "$csv" --checkpoint "$ckpt" >> "$out/log_${s}_$material.txt" 2>&1; then
      touch "$csv.done"
    else
      echo "   stopped: $(grep -m1 '^Error' "$out/log_${s}_$material.txt")"
    fi
  done
done
join() { local IFS=,; echo "$*"; }
existing=()
for c in "${csvs[@]}"; do [[ -f $c ]] && existing+=("$c"); done
extra=()
[[ -n ${ENSEMBLE:-} ]] && extra+=(--ensemble "$ENSEMBLE")
[[ -n ${LEVELS_FROM:-} ]] && extra+=(--levels-from "$LEVELS_FROM")
target/release/examples/lv_reference combine --csv "$(join "${existing[@]}")" \
  --out "$reference" --markdown "${extra[@]}"
