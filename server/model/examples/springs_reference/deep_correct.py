#!/usr/bin/env python3
"""Correct a two-level springs reference (`haptic_subdivision reference`) to the deep lv-probe
reference: at the lv-probe point the deep reference replaces ours, and every other point's force
is multiplied by the same depth-dependent ratio (deep / ours at lv-probe), i.e. the mesh error of
our two levels measured at lv-probe is taken to be the same at the other points (the meshes are
made by the same script with the same sizes under each point).

    deep_correct.py RAW.csv DEEP.csv OUT.csv

DEEP.csv: `depth_convention,depth_mm,force_n` rows (`#` comments): `device` depths are turned
into sphere depths with the scenes' 300 N/m coupling (s = D - F / 300 N/m). The ratio is
interpolated linearly in the sphere depth between the deep rows, constant beyond them. The
uncertainty of a corrected point adds the deep reference's (DEEP_UNCERTAINTY of the force) to
its own (two-level) uncertainty in quadrature; lv-probe's is DEEP_UNCERTAINTY alone.
"""
import sys

COUPLING_N_PER_M = 300.0
DEEP_UNCERTAINTY = 0.03
PROBE = "lv-probe"


def interp(xs, ys, x):
    if x <= xs[0]:
        return ys[0]
    if x >= xs[-1]:
        return ys[-1]
    for k in range(1, len(xs)):
        if x <= xs[k]:
            t = (x - xs[k - 1]) / (xs[k] - xs[k - 1])
            return ys[k - 1] + t * (ys[k] - ys[k - 1])
    return ys[-1]


def main(raw_path, deep_path, out_path):
    lines = open(raw_path).read().splitlines()
    comments = [l for l in lines if l.startswith("#")]
    rows = [l for l in lines if l and not l.startswith("#")]
    header, data = rows[0], [r.split(",") for r in rows[1:]]
    probe = [(float(r[7]), float(r[8])) for r in data if r[0] == PROBE]
    if not probe:
        sys.exit(f"{raw_path}: no {PROBE} rows")
    ps, pf = [p[0] for p in probe], [p[1] for p in probe]
    deep = []
    for l in open(deep_path).read().splitlines():
        if not l.strip() or l.startswith("#") or l.startswith("depth_convention"):
            continue
        conv, d, f = l.split(",")[:3]
        d, f = float(d), float(f)
        s = d - f / COUPLING_N_PER_M * 1e3 if conv == "device" else d
        deep.append((s, f / interp(ps, pf, s)))
    deep.sort()
    ds, ratio = [d[0] for d in deep], [d[1] for d in deep]
    out = comments + [
        f"# corrected by deep_correct.py to the deep lv-probe reference {deep_path.split('/')[-1]}: "
        f"ratio deep / ours at lv-probe from {min(ratio):.4f} to {max(ratio):.4f}, applied to every point; "
        f"uncertainty + {100 * DEEP_UNCERTAINTY:.0f} % in quadrature",
        header,
    ]
    for r in data:
        s, f, u = float(r[7]), float(r[8]), float(r[9])
        k = interp(ds, ratio, s)
        fc = f * k
        uc = DEEP_UNCERTAINTY * fc if r[0] == PROBE else (u * u * k * k + (DEEP_UNCERTAINTY * fc) ** 2) ** 0.5
        r[8], r[9] = f"{fc:.6e}", f"{uc:.3e}"
        r[10] = f"{s + fc / COUPLING_N_PER_M * 1e3:.6f}"
        out.append(",".join(r))
    open(out_path, "w").write("\n".join(out) + "\n")
    print(f"wrote {out_path} (ratio {min(ratio):.4f}..{max(ratio):.4f})")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
