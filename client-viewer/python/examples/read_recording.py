"""Read a bridge recording (`haptic-bridge ... --record press.csv`) back and summarise it.

    python examples/read_recording.py press.csv [--plot press.png]
"""

import argparse

import numpy as np

from haptics import read_recording


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv")
    ap.add_argument("--plot")
    args = ap.parse_args()
    rec = read_recording(args.csv)
    f = np.linalg.norm(rec["force_n"], axis=1)
    fresh = sum(s == "fresh" for s in rec["state"])
    print(f"{len(rec['t_s'])} device ticks over {rec['t_s'][-1] - rec['t_s'][0]:.3f} s")
    print(f"peak force {f.max() * 1e3:.1f} mN, in contact {rec['in_contact'].mean() * 100:.0f} % of ticks")
    print(f"round trip p50 {np.nanpercentile(rec['rtt_us'], 50):.0f} us, p99 {np.nanpercentile(rec['rtt_us'], 99):.0f} us")
    print(f"fresh commands on {fresh} ticks")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot(rec["t_s"], f * 1e3)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("|force| (mN)")
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)


if __name__ == "__main__":
    main()
