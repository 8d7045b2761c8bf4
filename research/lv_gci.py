"""Richardson extrapolation and Roache's GCI over the lv_probe.py levels.

Reads ``results/lv_<material>_h<h>.csv`` (one per level), and for each material, depth
convention and depth:

- ``sphere``: sphere travel ``s`` from the analytic epicardium (the solved depths);
- ``device``: device travel ``D = s + F_x / k`` (k = 300 N/m), the force at the wanted ``D``
  interpolated (monotone cubic, PCHIP) through the level's solved points, only between the
  first and the last (never extrapolated);

takes the three finest levels for Richardson's extrapolation (observed order from the three,
Celik et al. 2008 for non-constant ratios) and the GCI (safety factor 1.25) of the finest level
as the uncertainty; with four or more levels the order of the coarser triple is reported too.
Writes ``results/lv_levels.csv`` (every level's force), ``results/lv_reference.csv`` (the
extrapolated values, and ``recommended_force_n``: the extrapolation where the order is between
0.5 and 4 and the three levels monotone, else the finest level), and, with ``--preliminary
PATH``, the long table ``material, depth_convention, depth_mm, level_h_mm, force_n`` (level 0 =
the recommended value).
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from contact_fem import richardson_gci  # noqa: E402

DEVICE_DEPTHS = [0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0]


def load(results):
    runs = defaultdict(dict)  # material -> h -> rows
    for p in sorted(Path(results).glob("lv_*_h*.csv")):
        m = re.match(r"lv_(.+)_h([0-9.]+)\.csv$", p.name)
        if not m or m.group(1) in ("levels", "reference"):
            continue
        with p.open() as fh:
            rows = list(csv.DictReader(fh))
        if rows:
            runs[m.group(1)][float(m.group(2))] = rows
    return runs


def level_forces(rows):
    s = np.array([float(r["sphere_depth_mm"]) for r in rows])
    f = np.array([float(r["force_n"]) for r in rows])
    fx = np.array([float(r["force_x_n"]) for r in rows])
    d = np.array([float(r["device_depth_mm"]) for r in rows])
    out = {("sphere", float(si)): (fi, fxi) for si, fi, fxi in zip(s, f, fx)}
    if len(d) >= 2:
        # F(D) through (0, 0) and the solved points, used only within the solved range
        dd, ff, ffx = np.r_[0.0, d], np.r_[0.0, f], np.r_[0.0, fx]
        pf, pfx = PchipInterpolator(dd, ff), PchipInterpolator(dd, ffx)
        for t in DEVICE_DEPTHS:
            if d.min() - 1e-12 <= t <= d.max() + 1e-12:
                out[("device", t)] = (float(pf(t)), float(pfx(t)))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    here = Path(__file__).resolve().parent
    ap.add_argument("--results", default=str(here / "results"))
    ap.add_argument("--preliminary", default=None)
    args = ap.parse_args()
    runs = load(args.results)
    long_rows, ref_rows = [], []
    for material, levels in sorted(runs.items()):
        per = {h: level_forces(rows) for h, rows in levels.items()}
        keys = sorted(set().union(*[set(v) for v in per.values()]))
        for conv, depth in keys:
            hs = sorted(h for h in per if (conv, depth) in per[h])  # fine first
            for h in hs:
                f, fx = per[h][(conv, depth)]
                long_rows.append(dict(material=material, depth_convention=conv,
                                      depth_mm=depth, level_h_mm=h, force_n=f, force_x_n=fx))
            if len(hs) < 3:
                continue
            fs = [per[h][(conv, depth)][0] for h in hs]
            r = richardson_gci(hs[:3], fs[:3])
            coarse = richardson_gci(hs[1:4], fs[1:4]) if len(hs) >= 4 else None
            row = dict(material=material, depth_convention=conv, depth_mm=depth,
                       force_n=r["extrapolated"], uncertainty_n=r["gci"],
                       uncertainty_pct=100 * r["gci"] / abs(r["extrapolated"]),
                       observed_order=r["order"] if r["order"] is not None else "none",
                       observed_order_coarser=(coarse["order"] if coarse and
                                               coarse["order"] is not None else
                                               ("none" if coarse else "")),
                       note=("oscillatory: finest level, spread as the band" if r["order"] is None
                             else "order under 0.5: extrapolation not trusted" if r["order"] < 0.5
                             else "order over 4: extrapolation not trusted" if r["order"] > 4
                             else "monotone"),
                       finest_h_mm=hs[0], finest_force_n=fs[0],
                       levels_h_mm=" ".join(f"{h:g}" for h in hs),
                       levels_force_n=" ".join(f"{f:.6e}" for f in fs))
            # the value to aim at: the extrapolation where the order is usable, else the finest
            row["recommended_force_n"] = (r["extrapolated"] if row["note"] == "monotone"
                                          else fs[0])
            ref_rows.append(row)
            long_rows.append(dict(material=material, depth_convention=conv, depth_mm=depth,
                                  level_h_mm=0.0, force_n=row["recommended_force_n"],
                                  force_x_n=float("nan")))
    res = Path(args.results)
    write(res / "lv_levels.csv", long_rows)
    write(res / "lv_reference.csv", ref_rows)
    for r in ref_rows:
        print(f"{r['material']:>18} {r['depth_convention']:>6} {r['depth_mm']:4.2f} mm: "
              f"{1e3 * r['force_n']:.4f} +- {1e3 * r['uncertainty_n']:.4f} mN "
              f"({r['uncertainty_pct']:.1f} %), order {r['observed_order']}, levels "
              f"{r['levels_h_mm']}: {r['levels_force_n']}")
    if args.preliminary:
        write(Path(args.preliminary),
              [{k: r[k] for k in ("material", "depth_convention", "depth_mm", "level_h_mm",
                                  "force_n")} for r in long_rows])


def write(path, rows):
    if not rows:
        return
    with Path(path).open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6e}" if isinstance(v, float) and k.startswith("force")
                            or k.startswith("uncertainty_n") else
                            (f"{v:.4g}" if isinstance(v, float) else v))
                        for k, v in r.items()})


if __name__ == "__main__":
    main()
