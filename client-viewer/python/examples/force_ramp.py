"""Force ramp on the built-in LV: inject growing forces at the epicardium and plot the
displacement response (largest surface displacement under load).

    python examples/force_ramp.py --server 127.0.0.1:50051 [--out force_ramp.png]
"""

import argparse
import time

import numpy as np

from haptics import Client

POINT_M = (0.0097, 0.0, -0.005)  # on the LV epicardium (9.68 mm from the axis at z = -5 mm)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--server", required=True)
    ap.add_argument("--scene", default="lv")
    ap.add_argument("--max-force-n", type=float, default=0.05)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--out", default="force_ramp.png")
    args = ap.parse_args()

    with Client(args.server) as client, client.start(args.scene) as session:
        forces = np.linspace(0.0, args.max_force_n, args.steps)
        response = []
        for f in forces:
            if f > 0:
                session.apply_force(POINT_M, (-f, 0.0, 0.0), duration_s=0.6)
            time.sleep(0.4)  # the load acts in simulated time, which runs at the wall clock
            frame = next(session.watch(frames=1))
            response.append(frame.max_displacement_m)
            print(f"force {f * 1e3:6.1f} mN  max displacement {frame.max_displacement_m * 1e3:.3f} mm")
            time.sleep(0.3)  # the load ends; the next one starts from near rest

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.array(response) * 1e3, forces * 1e3, "o-")
    ax.set_xlabel("largest surface displacement (mm)")
    ax.set_ylabel("injected force (mN)")
    ax.set_title(f"{args.scene}: force ramp at the epicardium")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
