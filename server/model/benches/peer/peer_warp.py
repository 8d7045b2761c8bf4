"""Peer StVK force in NVIDIA Warp (CPU device, double precision) on the case written by
examples/export_peer_case.rs, the peer issue 48 names ("Warp 1.19's CPU kernel").

Usage: peer_warp.py CASE_DIR [REPEATS]. The kernel is the textbook linear tetrahedron with the
same law as ours: F = Ds Dm^-1, E = (F^T F - I) / 2, S = lambda tr(E) I + 2 mu E, P = F S, the
force on corners 1-3 the columns of -V P Dm^-T and on corner 0 minus their sum, added to the
nodes with atomics; Dm^-1 and V precomputed once (as ours does at set-up). Times a launch plus
its synchronisation (the force array zeroed inside the timed region, as ours is), prints the
median and the largest nodal difference to our forces relative to the largest force, and adds
the `warp_*` fields to CASE_DIR/peer.json (written by peer_stvk.py first).
"""
import json
import os
import sys
import time

import numpy as np
import warp as wp


@wp.kernel
def stvk_forces(
    x: wp.array(dtype=wp.vec3d),
    tets: wp.array2d(dtype=wp.int32),
    dm_inv: wp.array(dtype=wp.mat33d),
    volume: wp.array(dtype=wp.float64),
    lam: wp.float64,
    mu: wp.float64,
    f: wp.array(dtype=wp.vec3d),
):
    t = wp.tid()
    i0 = tets[t, 0]
    i1 = tets[t, 1]
    i2 = tets[t, 2]
    i3 = tets[t, 3]
    x0 = x[i0]
    ds = wp.matrix_from_cols(x[i1] - x0, x[i2] - x0, x[i3] - x0)
    a = dm_inv[t]
    F = ds * a
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    ident = wp.identity(n=3, dtype=wp.float64)
    E = (wp.transpose(F) * F - ident) * half
    S = ident * (lam * wp.trace(E)) + E * (wp.float64(2.0) * mu)
    H = F * S * wp.transpose(a) * (-volume[t] * one)
    f1 = wp.vec3d(H[0, 0], H[1, 0], H[2, 0])
    f2 = wp.vec3d(H[0, 1], H[1, 1], H[2, 1])
    f3 = wp.vec3d(H[0, 2], H[1, 2], H[2, 2])
    wp.atomic_add(f, i1, f1)
    wp.atomic_add(f, i2, f2)
    wp.atomic_add(f, i3, f3)
    wp.atomic_add(f, i0, -(f1 + f2 + f3))


def main():
    case = sys.argv[1]
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 50
    X = np.loadtxt(os.path.join(case, "nodes.txt"))  # n x 3, m
    T = np.loadtxt(os.path.join(case, "tets.txt"), dtype=np.int32)  # e x 4
    x = np.loadtxt(os.path.join(case, "deformed.txt"))
    ours = np.loadtxt(os.path.join(case, "ours_force.txt"))
    info = json.load(open(os.path.join(case, "ours.json")))
    dm = np.stack([X[T[:, k]] - X[T[:, 0]] for k in (1, 2, 3)], axis=2)  # e x 3 x 3, columns
    vol = np.abs(np.linalg.det(dm)) / 6.0
    wp.init()
    dev = "cpu"
    xw = wp.array(x, dtype=wp.vec3d, device=dev)
    tw = wp.array(T, dtype=wp.int32, device=dev)
    aw = wp.array(np.linalg.inv(dm), dtype=wp.mat33d, device=dev)
    vw = wp.array(vol, dtype=wp.float64, device=dev)
    fw = wp.zeros(len(X), dtype=wp.vec3d, device=dev)
    lam, mu = wp.float64(info["lambda_pa"]), wp.float64(info["mu_pa"])

    def run():
        fw.zero_()
        wp.launch(stvk_forces, dim=len(T), inputs=[xw, tw, aw, vw, lam, mu, fw], device=dev)
        wp.synchronize_device(dev)

    run()  # compiles the kernel (cached)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        times.append((time.perf_counter() - t) * 1e6)
    med = float(np.median(times))
    f = fw.numpy()
    worst = float(np.max(np.linalg.norm(f - ours, axis=1)) / np.max(np.linalg.norm(ours, axis=1)))
    out = {
        "warp_version": wp.__version__,
        "warp_device": dev,
        "warp_force_median_us": med,
        "time_ratio_warp_over_ours": med / info["force_median_us"],
        "warp_max_nodal_difference_rel_to_max_force": worst,
    }
    path = os.path.join(case, "peer.json")
    peer = json.load(open(path)) if os.path.exists(path) else {}
    threads = peer.get("ours_force_median_us_threads")
    if threads:
        out["time_ratio_warp_over_ours_threads"] = med / threads
    peer.update(out)
    json.dump(peer, open(path, "w"), indent=2)
    print(json.dumps(out, indent=2))
    if not worst < 1e-10:
        sys.exit(f"Warp's forces differ from ours by {worst:.3e} of the largest force")


if __name__ == "__main__":
    main()
