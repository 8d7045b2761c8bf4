"""The lv-probe press on the idealized left ventricle with an exact rigid sphere, scikit-fem.

Half LV (y >= 0, mirror plane y = 0 on rollers), base z = 5 mm clamped, the epicardium
touchable; a rigid frictionless sphere of radius 2 mm moving along -x at y = 0, z = -5 mm,
first touching the analytic epicardium with its centre at x = 9.682458 + 2 mm; E = 14.5 kPa,
nu = 0.45, St. Venant-Kirchhoff or the stable neo-Hookean material of the Rust model
(``contact_fem.Material``). One mesh level per run (``--h``: element size in mm within
``--fine-radius`` of the contact point, growing to ``min(6 h, 3 mm)`` at 12 mm), one
continuation through the sphere depths; a CSV row per depth with the whole-body force (twice
the half model's, y component zero by symmetry).

Run: ``research/run.sh lv --material stvk --h 0.3`` (see README.md).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np
from skfem import MeshTet2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from contact_fem import (Body, ContactSolver, ContactSurface, Material, check_material,  # noqa
                         lame, solver_name)
from meshing import LV_BASE_Z, LV_EPI, lv_half  # noqa: E402

E_PA = 14.5e3
NU = 0.45
R_MM = 2.0
X_TOUCH_MM = 10.0 * np.sqrt(1 - (5.0 / 20.0) ** 2)  # 9.682458
POINT_MM = (X_TOUCH_MM, 0.0, -5.0)
K_COUPLING = 300.0  # N/m
DEPTHS = {
    "stvk": [0.25, 0.5, 0.75, 1.0, 1.25, 1.5],
    "stable-neo-hookean": [0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0],
}


def build(h, fine_radius, material):
    mesh_mm, nv, dev = lv_half(h, POINT_MM, fine_radius, min(6 * h, 3.0), 12.0)
    mesh = MeshTet2(mesh_mm.doflocs * 1e-3, mesh_mm.t)
    lam, mu = lame(E_PA, NU)
    mat = Material(material, lam, mu)
    assert check_material(mat) < 1e-6, "tangent does not match the stress"
    body = Body(mesh, mat)
    x0 = body.x0 * 1e3  # mm
    tol = 1e-7
    fixed = np.concatenate([
        3 * np.flatnonzero(np.abs(x0[:, 1]) < tol) + 1,
        (3 * np.flatnonzero(np.abs(x0[:, 2] - LV_BASE_Z) < tol)[:, None]
         + np.arange(3)).ravel(),
    ])

    def on_epi(c):
        cm = c * 1e3
        q = (cm[:, 0] / LV_EPI[0]) ** 2 + (cm[:, 1] / LV_EPI[1]) ** 2 + (cm[:, 2] / LV_EPI[2]) ** 2
        near = np.linalg.norm(cm - np.array(POINT_MM), axis=1) < 6.5
        return (np.abs(q - 1) < 2e-2) & near

    surf = ContactSurface(body, on_epi)
    return body, surf, fixed, nv, dev


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--material", default="stvk", choices=sorted(DEPTHS))
    ap.add_argument("--h", type=float, required=True, help="element size under the probe, mm")
    ap.add_argument("--fine-radius", type=float, default=3.0, help="mm")
    ap.add_argument("--depths", default=None, help="sphere depths, mm, comma-separated")
    ap.add_argument("--max-step", type=float, default=0.25, help="largest increment, mm")
    ap.add_argument("--out", default=None)
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    depths = ([float(s) for s in args.depths.split(",")] if args.depths
              else DEPTHS[args.material])
    out = Path(args.out or Path(__file__).parent / "results" /
               f"lv_{args.material}_h{args.h:g}.csv")
    t0 = time.perf_counter()
    body, surf, fixed, nv, dev = build(args.h, args.fine_radius, args.material)
    print(f"LV half, h {args.h} mm: {nv} vertices, {body.nn} nodes, {body.ndof} dofs, "
          f"{body.ne} tets, volume x2 {2e9 * body.volume:.2f} mm^3 (exact 3234.73); "
          f"surface nodes moved onto the ellipsoids by at most {dev:.1e} mm; contact surface "
          f"{surf.tri.shape[1]} triangles, {surf.nvert} vertices; {solver_name()}; set-up "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    log = print if args.verbose else (lambda *a: None)
    c0 = np.array([X_TOUCH_MM + R_MM, 0.0, -5.0]) * 1e-3
    solver = ContactSolver(body, surf, fixed, R_MM * 1e-3, c0, (-1, 0, 0), log=log)
    out.parent.mkdir(parents=True, exist_ok=True)
    fields = ["material", "level_h_mm", "vertices", "nodes", "dofs", "sphere_depth_mm",
              "force_x_n", "force_z_n", "force_n", "device_depth_mm", "active_vertices",
              "max_active_dist_mm", "newton", "increments", "seconds", "min_jacobian"]
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        for d in depths:
            try:
                (res,) = solver.solve_depths([d * 1e-3], max_step=args.max_step * 1e-3)
            except RuntimeError as err:
                print(f"STOPPED at sphere depth {d} mm: {err}", flush=True)
                break
            f = 2 * res.force_on_sphere  # whole body
            fmag = float(np.hypot(f[0], f[2]))
            act = res.lam > 0
            dist = np.linalg.norm(body.x0[surf.verts[act]] * 1e3 - np.array(POINT_MM), axis=1)
            row = dict(material=args.material, level_h_mm=args.h, vertices=nv, nodes=body.nn,
                       dofs=body.ndof, sphere_depth_mm=d, force_x_n=f[0], force_z_n=f[2],
                       force_n=fmag, device_depth_mm=d + 1e3 * f[0] / K_COUPLING,
                       active_vertices=res.active,
                       max_active_dist_mm=float(dist.max()) if act.any() else 0.0,
                       newton=res.newton, increments=res.increments, seconds=res.seconds,
                       min_jacobian=body.min_jacobian(res.u))
            w.writerow({k: (f"{v:.7e}" if isinstance(v, float) else v) for k, v in row.items()})
            fh.flush()
            print(f"h {args.h} {args.material} s {d:.3f} mm: |F| {1e3 * fmag:.4f} mN, Fx "
                  f"{1e3 * f[0]:.4f} mN, D {row['device_depth_mm']:.4f} mm, {res.active} active "
                  f"(within {row['max_active_dist_mm']:.2f} mm), {res.newton} Newton in "
                  f"{res.increments} increments, {res.seconds:.1f} s, min J "
                  f"{row['min_jacobian']:.3f}", flush=True)
    print(f"total {time.perf_counter() - t0:.1f} s; wrote {out}", flush=True)


if __name__ == "__main__":
    main()
