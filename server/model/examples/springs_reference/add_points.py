#!/usr/bin/env python3
"""Prepare new points' raw reference (`haptic_subdivision reference` on them alone) for
deep_correct.py without re-solving lv-probe: writes RAW_NEW's comments and header, the lv-probe
raw rows rebuilt from a corrected reference file (its `force_hmin_0.42_n` column is our finest
level there: force_n; uncertainty_n twice its change from `force_hmin_0.6_n`), then RAW_NEW's
rows. deep_correct.py then applies the same lv-probe ratio as when REFERENCE was made.

    add_points.py REFERENCE.csv RAW_NEW.csv OUT.csv
"""
import sys


def main(ref, raw_new, out):
    lines = open(ref).read().splitlines()
    data = [l.split(",") for l in lines if l and not l.startswith("#")]
    header = data[0]
    i6, i42 = header.index("force_hmin_0.6_n"), header.index("force_hmin_0.42_n")
    probe = []
    for r in data[1:]:
        if r[0] != "lv-probe":
            continue
        f6, f42 = float(r[i6]), float(r[i42])
        r[8], r[9] = f"{f42:.6e}", f"{2 * abs(f42 - f6):.3e}"
        probe.append(",".join(r))
    if not probe:
        sys.exit(f"{ref}: no lv-probe rows")
    new = open(raw_new).read().splitlines()
    rows = [l for l in new if l and not l.startswith("#")]
    if rows[0].split(",") != header:
        sys.exit(f"{raw_new}: header differs from {ref}'s")
    comments = [l for l in new if l.startswith("#")]
    open(out, "w").write("\n".join(comments + [rows[0]] + probe + rows[1:]) + "\n")
    print(f"wrote {out} ({len(probe)} lv-probe rows, {len(rows) - 1} new rows)")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:])
