"""Peer StVK gradient (pbatoolkit) on the case written by examples/export_peer_case.rs.

Usage: peer_stvk.py CASE_DIR [REPEATS]. Prints the peer's timing, the constant factor between
the peer's gradient and our force (least squares fit c in  grad_peer = -c f_ours), and the
relative difference after scaling, and writes CASE_DIR/peer.json.
"""
import json
import os
import sys
import time

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
from pbatoolkit import pbat  # noqa: E402

fem = pbat.fem


def main():
    case = sys.argv[1]
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 50
    X = np.loadtxt(os.path.join(case, "nodes.txt")).T.copy(order="F")  # 3 x n
    E = np.loadtxt(os.path.join(case, "tets.txt"), dtype=np.int64).T.copy(order="F")  # 4 x e
    x = np.loadtxt(os.path.join(case, "deformed.txt"))  # n x 3
    ours = np.loadtxt(os.path.join(case, "ours_force.txt"))
    info = json.load(open(os.path.join(case, "ours.json")))
    element = fem.Element.Tetrahedron
    n = X.shape[1]
    wg = fem.mesh_quadrature_weights(E, X, element, order=1, quadrature_order=1)
    eg = fem.mesh_quadrature_elements(E, wg)
    GNeg = fem.shape_function_gradients(E, X, element=element, order=1, dims=3, quadrature_order=1)
    mug = np.full(wg.size, info["mu_pa"])
    lamg = np.full(wg.size, info["lambda_pa"])
    xf = np.ravel(x)  # node-major: x0 y0 z0 x1 ...

    def grad():
        _, G, _ = fem.hyper_elastic_potential(
            E=E, n_nodes=n, eg=np.ravel(eg), wg=np.ravel(wg), GNeg=GNeg,
            mug=mug, lambdag=lamg, x=xf,
            energy=fem.HyperElasticEnergy.SaintVenantKirchhoff,
            flags=fem.ElementElasticityComputationFlags.Gradient,
            spd_correction=fem.HyperElasticSpdCorrection.NoCorrection,
            element=element, order=1, dims=3)
        return G

    G = grad()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        grad()
        times.append((time.perf_counter() - t) * 1e6)
    med = float(np.median(times))
    g = G.reshape(-1, 3)
    f = -ours
    c = float(np.dot(g.ravel(), f.ravel()) / np.dot(f.ravel(), f.ravel()))
    rel_raw = float(np.linalg.norm(g - f) / np.linalg.norm(f))
    rel = float(np.linalg.norm(g / c - f) / np.linalg.norm(f))
    worst = float(np.max(np.linalg.norm(g / c - f, axis=1)) / np.max(np.linalg.norm(f, axis=1)))
    out = {
        "peer": "pbatoolkit",
        "peer_version": getattr(pbat, "__version__", None),
        "nodes": n,
        "tets": E.shape[1],
        "repeats": repeats,
        "peer_gradient_median_us": med,
        "ours_force_median_us": info["force_median_us"],
        "time_ratio_peer_over_ours": med / info["force_median_us"],
        "scale_factor_peer_over_textbook": c,
        "relative_difference_unscaled": rel_raw,
        "relative_difference_after_scaling": rel,
        "max_nodal_difference_after_scaling_rel_to_max_force": worst,
    }
    threads = os.path.join(case, "threads", "ours.json")
    if os.path.exists(threads):
        # ours in parts on a tick pool (run_peer.sh: export_peer_case --threads 2, unpinned)
        t = json.load(open(threads))
        out["ours_threads"] = t["threads"]
        out["ours_force_median_us_threads"] = t["force_median_us_threads"]
        out["time_ratio_peer_over_ours_threads"] = med / t["force_median_us_threads"]
    json.dump(out, open(os.path.join(case, "peer.json"), "w"), indent=2)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
