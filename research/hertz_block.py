"""Hertz block: a rigid sphere (R = 2 mm) pressed into a quarter block, scikit-fem.

Quarter of 7R x 7R x 7R ([0, 7R]^2 x [-7R, 0] m), rollers on x = 0 and y = 0, base z = -7R
clamped, E = 10 kPa, nu = 0.3, St. Venant-Kirchhoff, quadratic tetrahedra from Gmsh refined to
R/30 within 0.65 R of the first contact point (growing to 1.5 R at 4 R): 4 712 vertices,
34 930 nodes, 104 790 dofs. Six sphere depths 0.04 .. 0.2 mm (d/R 0.02 .. 0.1) in one
continuation; the force and the contact radius against Hertz
``F = 4/3 E/(1 - nu^2) R^1/2 d^3/2`` and ``a = (R d)^1/2``.

Run: ``research/run.sh hertz`` (or ``python research/hertz_block.py [--out CSV]``).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from contact_fem import (Body, ContactSolver, ContactSurface, Material, check_material,  # noqa
                         lame, solver_name)
from meshing import hertz_block  # noqa: E402

R = 2e-3
E = 10e3
NU = 0.3
DEPTHS_OVER_R = [0.02, 0.036, 0.052, 0.068, 0.084, 0.1]


def contact_radius(surf, lam, x0):
    """Bracket of the contact radius from the multiplier vertices: the largest radial distance
    (in the reference configuration) of a vertex carrying force, and the smallest of a vertex
    beyond it carrying none; and the area estimate sqrt(4 A / pi) over the vertices carrying
    force (A = sum of their int phi_v dA, quarter model)."""
    r = np.linalg.norm(x0[surf.verts, :2], axis=1)
    act = lam > 0
    if not act.any():
        return 0.0, 0.0, 0.0
    r_in = r[act].max()
    beyond = r[(~act) & (r > r_in)]
    r_out = beyond.min() if len(beyond) else np.nan
    area = surf.vert_area[act].sum()
    return r_in, r_out, np.sqrt(4 * area / np.pi)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "hertz_block.csv"))
    ap.add_argument("--fine-radius", type=float, default=0.65, help="of R")
    ap.add_argument("--h-fine", type=float, default=1 / 30, help="of R")
    ap.add_argument("--depths", default=",".join(str(d) for d in DEPTHS_OVER_R),
                    help="d/R list")
    ap.add_argument("--material", default="stvk", choices=["stvk", "linear"])
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    t_start = time.perf_counter()
    lam_, mu_ = lame(E, NU)
    mat = Material(args.material, lam_, mu_)
    assert check_material(mat) < 1e-6
    mesh, nv = hertz_block(R, args.h_fine * R, args.fine_radius * R, 1.5 * R, 4 * R)
    body = Body(mesh, mat)
    x0 = body.x0
    size = 7 * R
    tol = 1e-9 * size
    fixed = np.concatenate([
        3 * np.flatnonzero(np.abs(x0[:, 0]) < tol) + 0,
        3 * np.flatnonzero(np.abs(x0[:, 1]) < tol) + 1,
        (3 * np.flatnonzero(np.abs(x0[:, 2] + size) < tol)[:, None] + np.arange(3)).ravel(),
    ])
    surf = ContactSurface(
        body, lambda c: (np.abs(c[:, 2]) < tol) & (np.hypot(c[:, 0], c[:, 1]) < 1.2e-3))
    print(f"Hertz block: {nv} vertices, {body.nn} nodes, {body.ndof} dofs, {body.ne} tets, "
          f"volume {body.volume:.6e} m^3 (exact {size**3:.6e}); contact surface "
          f"{surf.tri.shape[1]} triangles, {surf.nvert} multiplier vertices; solver "
          f"{solver_name()}; set-up {time.perf_counter() - t_start:.1f} s", flush=True)
    log = print if args.verbose else (lambda *a: None)
    solver = ContactSolver(body, surf, fixed, R, (0, 0, R), (0, 0, -1), log=log)
    depths = [float(s) * R for s in args.depths.split(",")]
    e_star = E / (1 - NU**2)
    rows = []
    t_solve = time.perf_counter()
    for d in depths:
        (res,) = solver.solve_depths([d])
        f = 4 * res.force_on_sphere[2]
        f_h = 4 / 3 * e_star * np.sqrt(R) * d**1.5
        a_h = np.sqrt(R * d)
        r_in, r_out, a_area = contact_radius(surf, res.lam, x0)
        a_mid = 0.5 * (r_in + r_out)
        # clamp + roller reactions in z (quarter): equals the contact force at equilibrium
        fz_reac = -np.sum(res.reaction[(solver.fixed % 3) == 2])
        row = dict(d_over_r=d / R, depth_m=d, force_n=f, hertz_force_n=f_h,
                   force_err_pct=100 * (f / f_h - 1), reaction_z_n=4 * fz_reac,
                   a_mid_m=a_mid, a_in_m=r_in, a_out_m=r_out, a_area_m=a_area,
                   hertz_a_m=a_h, a_err_pct=100 * (a_mid / a_h - 1),
                   active_vertices=res.active, newton=res.newton, seconds=res.seconds,
                   max_penetration_m=res.max_penetration)
        rows.append(row)
        print(f"d/R {d / R:.3f}: F {f:.5e} N vs Hertz {f_h:.5e} ({row['force_err_pct']:+.2f} %), "
              f"reaction {4 * fz_reac:.5e} N; a {a_mid:.4e} m [{r_in:.4e}, {r_out:.4e}] vs "
              f"Hertz {a_h:.4e} ({row['a_err_pct']:+.1f} %), area-based {a_area:.4e}; "
              f"{res.active} active, {res.newton} Newton, {res.seconds:.1f} s", flush=True)
    total = time.perf_counter() - t_solve
    print(f"{len(depths)} depths solved in {total:.1f} s (set-up and meshing included: "
          f"{time.perf_counter() - t_start:.1f} s) on {os.cpu_count()} cores", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0].keys()))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6e}" if isinstance(v, float) else v) for k, v in r.items()})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
