#!/usr/bin/env bash
# The converged sphere reference of the lv-probe press (docs/accuracy.md, "A converged sphere
# reference"): the LV meshed by Gmsh at three sizes refined under the probe
# (lv_probe_refined.geo, hmin 0.6 / 0.42 / 0.3 mm, hmax = 5 hmin), the exact rigid 2 mm sphere
# pressed along the lv-probe line by `haptic-solve --indent` on each, then Richardson's
# extrapolation at the lv-probe device depths and the default servo's error against it, and
# the epicardium's extrapolated displacement at the benchmark's sample points
# (OUT_DIR/surface_reference_MATERIAL.csv).
#
#   server/model/examples/lv_sphere_reference.sh [OUT_DIR] [MATERIAL] [DEPTHS] [DEVICE_DEPTHS]
#
# DEPTHS: the sphere depths solved on each mesh, mm; DEVICE_DEPTHS: the lv-probe device depths
# reported (0.5 mm steps; each needs solved sphere depths around it).
#
# MATERIAL: stvk (default; St. Venant-Kirchhoff has no equilibrium much past 1.25 mm sphere
# depth on the finest mesh, so its default depths stop there) or stable-neo-hookean or
# corotational. Needs gmsh (tests/install-gmsh.sh installs Debian's). Run time on a 2-core
# AMD EPYC: about 30 min for stvk, the finest mesh most of it.
set -euo pipefail
root=$(cd "$(dirname "$0")/../../.." && pwd)
out=${1:-target/lv-sphere-reference}
material=${2:-stvk}
if [[ $material == stvk ]]; then default_depths=0.25,0.5,0.75,1,1.25; else default_depths=0.25,0.5,0.75,1,1.25,1.5,2,2.5,3; fi
depths=${3:-$default_depths}
command -v gmsh >/dev/null || { echo "gmsh not found: run tests/install-gmsh.sh" >&2; exit 1; }
mkdir -p "$out"
cd "$root"
cargo build --release -p haptic-server --bin haptic-solve
cargo build --release -p haptic-model --example lv_study
meshes=() csvs=()
for hmin in 0.6 0.42 0.3; do
  hmax=$(awk "BEGIN { print 5 * $hmin }")
  msh="$out/lvr_$hmin.msh"
  [[ -f $msh ]] || gmsh server/model/examples/lv_probe_refined.geo -3 -format msh22 \
    -setnumber hmin "$hmin" -setnumber hmax "$hmax" -o "$msh" > "$out/gmsh_$hmin.log"
  scene="$out/lvr_${hmin}_$material.toml"
  cat > "$scene" <<TOML
name = "lvr-$hmin-$material"
[mesh]
file = "lvr_$hmin.msh"
length_unit = "mm"
order = 2
[material]
model = "$material"
youngs_modulus_pa = 14500.0
poisson_ratio = 0.45
density_kg_per_m3 = 1060.0
[boundary]
clamped = ["BASE"]
touchable = ["EPI"]
[probe]
radius_m = 0.002
TOML
  echo "== hmin $hmin mm: haptic-solve --indent at $depths mm"
  target/release/haptic-solve "$scene" --indent --from 15,0,-5 --direction -1,0,0 \
    --depths "$depths" --out "$out/indent_${hmin}_$material"
  meshes+=("$msh:2") csvs+=("$out/indent_${hmin}_$material/indent.csv")
done
join() { local IFS=,; echo "$*"; }
servo_depths=${4:-$([[ $material == stvk ]] && echo 0.5,1 || echo 0.5,1,1.5,2,2.5,3)}
target/release/examples/lv_study reference --mesh "$(join "${meshes[@]}")" \
  --csv "$(join "${csvs[@]}")" --h 0.6,0.42,0.3 --material "$material" \
  --depths "$servo_depths" --servo --surface "$out/surface_reference_$material.csv"
# The St. Venant-Kirchhoff surface reference is the benchmark's
# (server/model/benches/precision/lv_probe_surface_reference.csv).
