#!/usr/bin/env bash
# FEM references of the mass-spring scenes at their press points (docs/accuracy.md, "The
# mass-spring surfaces calibrated to the organ"): for each point of POINTS_CSV, the body meshed
# by Gmsh refined under the point (GEO) at each size of HMINS (hmax = HMAX_FACTOR * hmin; the
# hemisphere keeps hmax = 10 mm: its 50 mm half ball is large against the 4 mm probe),
# quadratic tetrahedra, the stable neo-Hookean material (E = 14.5 kPa, nu = 0.45, the LV
# scenes' moduli), and the scene's rigid sphere pressed along the point's direction by
# `haptic-solve --indent` (exact sphere, frictionless, static). The indent.csv files are then
# turned into the reference CSV (`haptic_subdivision reference`).
#
#   server/model/examples/springs_reference/run.sh lv|hemisphere [OUT_DIR] [HMINS] [POINTS]
#
# POINTS: names of POINTS_CSV rows (default all). Needs gmsh (tests/install-gmsh.sh).
# HAPTIC_SOLVE overrides the solver binary (default target/release/haptic-solve).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../../.." && pwd)
body=${1:?lv or hemisphere}
out=${2:-$root/target/springs-reference/$body}
case $body in
  lv) geo=$here/lv_point_refined.geo points_csv=$here/lv_points.csv radius_mm=2
      hmins_default=0.6,0.42 hmax_factor=5 hmax_fixed= rfine=2.5 rcoarse=9 surfaces='clamped = ["BASE"]
touchable = ["EPI"]' ;;
  hemisphere) geo=$here/hemisphere_point_refined.geo points_csv=$here/hemisphere_points.csv
      radius_mm=4 hmins_default=1.2,0.85 hmax_factor= hmax_fixed=10 rfine=6 rcoarse=15 surfaces='clamped = ["BASE"]
touchable = ["SURFACE"]' ;;
  *) echo "unknown body $body (lv or hemisphere)" >&2; exit 2 ;;
esac
hmins=${3:-$hmins_default}
only=${4:-}
case $body in
  lv) depths_default=0.1,0.25,0.5,0.75,1,1.25,1.5,2,2.5,3,3.5,4,4.25 ;;
  hemisphere) depths_default=0.1,0.25,0.5,0.75,1,1.5,2,2.5,3,4,4.25 ;;
esac
depths=${DEPTHS:-$depths_default}
solve=${HAPTIC_SOLVE:-$root/target/release/haptic-solve}
command -v gmsh >/dev/null || { echo "gmsh not found: run tests/install-gmsh.sh" >&2; exit 1; }
[[ -x $solve ]] || { echo "$solve not found: cargo build --release -p haptic-server --bin haptic-solve" >&2; exit 1; }
mkdir -p "$out"
grep -v '^#' "$points_csv" | tail -n +2 | while IFS=, read -r name x y z dx dy dz; do
  [[ -z $only || ",$only," == *",$name,"* ]] || continue
  # The sphere starts 1 mm clear of the point along the press line.
  from=$(awk -v x="$x" -v y="$y" -v z="$z" -v dx="$dx" -v dy="$dy" -v dz="$dz" -v r="$radius_mm" \
    'BEGIN { s = r + 1; printf "%.6f,%.6f,%.6f", x - s * dx, y - s * dy, z - s * dz }')
  for hmin in ${hmins//,/ }; do
    if [[ -n $hmax_fixed ]]; then hmax=$hmax_fixed; else hmax=$(awk "BEGIN { print $hmax_factor * $hmin }"); fi
    tag="${name}_$hmin"
    msh="$out/$tag.msh"
    [[ -f $msh ]] || gmsh "$geo" -3 -format msh22 -setnumber hmin "$hmin" -setnumber hmax "$hmax" \
      -setnumber rfine "$rfine" -setnumber rcoarse "$rcoarse" \
      -setnumber px "$x" -setnumber py "$y" -setnumber pz "$z" -o "$msh" > "$out/gmsh_$tag.log"
    cat > "$out/$tag.toml" <<TOML
name = "$body-$tag"
[mesh]
file = "$tag.msh"
length_unit = "mm"
order = 2
[material]
model = "stable-neo-hookean"
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
density_kg_per_m3 = 1060.0
[boundary]
$surfaces
[probe]
radius_m = $(awk "BEGIN { print $radius_mm / 1000 }")
TOML
    if [[ -f $out/indent_$tag/done ]]; then echo "== $tag: done before"; continue; fi
    echo "== $tag: hmin $hmin mm, from $from along $dx,$dy,$dz, depths $depths mm ($(date +%T))"
    start=$(date +%s)
    "$solve" "$out/$tag.toml" --indent --from "$from" --direction "$dx,$dy,$dz" \
      --depths "$depths" --out "$out/indent_$tag" > "$out/solve_$tag.log" 2>&1
    echo "$(( $(date +%s) - start ))" > "$out/indent_$tag/done"
    echo "   $tag: $(( $(date +%s) - start )) s"
  done
done
