"""Sweep Young's modulus on the LV scene and plot the probe's force-indentation curves.

Each run starts a session from the scene TOML with `youngs_modulus_pa` replaced, presses with
the scripted probe (DeviceLink) and stops the session.

    python examples/youngs_sweep.py --server 127.0.0.1:50051 --scene-file deploy/scenes/lv.toml
"""

import argparse
import re
from pathlib import Path

import numpy as np

from haptics import Client


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--server", required=True)
    ap.add_argument("--scene-file", default="deploy/scenes/lv.toml")
    ap.add_argument("--youngs-pa", default="7250,14500,29000")
    ap.add_argument("--depth-m", type=float, default=0.005)
    ap.add_argument("--out", default="youngs_sweep.png")
    args = ap.parse_args()

    text = Path(args.scene_file).read_text()
    if not re.search(r"(?m)^youngs_modulus_pa\s*=", text):
        raise SystemExit(f"{args.scene_file} has no youngs_modulus_pa line")
    curves = {}
    with Client(args.server) as client:
        for e in [float(v) for v in args.youngs_pa.split(",")]:
            scene = re.sub(r"(?m)^youngs_modulus_pa\s*=.*$", f"youngs_modulus_pa = {e}", text)
            with client.start(toml=scene) as session:
                press = session.press(depth_m=args.depth_m, hold_s=0.1)
            pressing = press.t_s <= args.depth_m / 0.01
            depth, fx = press.depth_m[pressing], press.force_n[pressing, 0]
            curves[e] = (depth, fx)
            print(f"E = {e:8.0f} Pa: peak force {np.nanmax(fx) * 1e3:.1f} mN")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    for e, (depth, fx) in curves.items():
        ax.plot(depth * 1e3, fx * 1e3, label=f"E = {e / 1e3:g} kPa")
    ax.set_xlabel("probe travel (mm)")
    ax.set_ylabel("force on the hand, x (mN)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
