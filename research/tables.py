"""Prints the Markdown tables of README.md from results/*.csv (hertz_block.csv, lv_*_h*.csv,
lv_reference.csv)."""

import csv
from pathlib import Path

res = Path(__file__).resolve().parent / "results"


def rows(name):
    p = res / name
    return list(csv.DictReader(p.open())) if p.exists() else []


h = rows("hertz_block.csv")
if h:
    print("| d/R | depth mm | F, mN | Hertz F, mN | F vs Hertz | a, mm [bracket] | Hertz a, mm | a vs Hertz | active vertices | Newton | time per depth |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in h:
        f = float
        print(f"| {f(r['d_over_r']):.3f} | {1e3 * f(r['depth_m']):.3f} | {1e3 * f(r['force_n']):.4f} | "
              f"{1e3 * f(r['hertz_force_n']):.4f} | {f(r['force_err_pct']):+.2f} % | "
              f"{1e3 * f(r['a_mid_m']):.4f} [{1e3 * f(r['a_in_m']):.4f}, {1e3 * f(r['a_out_m']):.4f}] | "
              f"{1e3 * f(r['hertz_a_m']):.4f} | {f(r['a_err_pct']):+.1f} % | {r['active_vertices']} | "
              f"{r['newton']} | {f(r['seconds']):.0f} s |")
    print()

for mat in ("stvk", "stable-neo-hookean"):
    levels = sorted(res.glob(f"lv_{mat}_h*.csv"), key=lambda p: -float(p.stem.split("_h")[1]))
    if not levels:
        continue
    print(f"{mat}, per level (sphere depth s; |F| and F_x of the whole body, mN; device depth D = s + F_x/k):\n")
    print("| h mm | vertices / dofs | s mm | abs F | F_x | D mm | active | Newton | time |")
    print("|---|---|---|---|---|---|---|---|---|")
    for p in levels:
        for r in csv.DictReader(p.open()):
            f = float
            print(f"| {f(r['level_h_mm']):g} | {r['vertices']} / {r['dofs']} | {f(r['sphere_depth_mm']):g} | "
                  f"{1e3 * f(r['force_n']):.4f} | {1e3 * f(r['force_x_n']):.4f} | {f(r['device_depth_mm']):.4f} | "
                  f"{r['active_vertices']} | {r['newton']} | {f(r['seconds']):.0f} s |")
    print()

ref = rows("lv_reference.csv")
if ref:
    print("| material | convention | depth mm | levels h mm | forces, mN (fine to coarse) | Richardson, mN | GCI | order (3 finest) | order (coarser 3) | note |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in ref:
        fs = " / ".join(f"{1e3 * float(x):.3f}" for x in r["levels_force_n"].split())
        order = r["observed_order"]
        order = f"{float(order):.2f}" if order not in ("none", "") else order
        oc = r["observed_order_coarser"]
        oc = f"{float(oc):.2f}" if oc not in ("none", "") else oc
        print(f"| {r['material']} | {r['depth_convention']} | {float(r['depth_mm']):g} | "
              f"{r['levels_h_mm']} | {fs} | {1e3 * float(r['force_n']):.3f} | "
              f"{float(r['uncertainty_pct']):.1f} % | {order} | {oc} | {r['note']} |")
