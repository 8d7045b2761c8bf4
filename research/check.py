"""Quick self-checks of contact_fem.py (about a minute): the materials' stress and tangent
against finite differences of the energy, and a coarse Hertz press (cells R/10) whose force is
within 10 % of Hertz's and equals the supports' reaction."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from contact_fem import (Body, ContactSolver, ContactSurface, Material, check_material,  # noqa
                         lame)
from meshing import hertz_block  # noqa: E402

lam, mu = lame(14.5e3, 0.45)
for model in ("stvk", "stable-neo-hookean"):
    err = check_material(Material(model, lam, mu))
    print(f"{model}: finite-difference error of P and A {err:.1e}")
    assert err < 1e-6
    f = np.eye(3)[:, :, None]
    assert abs(Material(model, lam, mu).energy(f)[0]) < 1e-9, "energy at rest"

R, E, NU = 2e-3, 10e3, 0.3
mesh, nv = hertz_block(R, R / 10, 0.5 * R, 3 * R, 8 * R)
body = Body(mesh, Material("stvk", *lame(E, NU)))
x0, size = body.x0, 7 * R
tol = 1e-9 * size
fixed = np.concatenate([3 * np.flatnonzero(np.abs(x0[:, 0]) < tol),
                        3 * np.flatnonzero(np.abs(x0[:, 1]) < tol) + 1,
                        (3 * np.flatnonzero(np.abs(x0[:, 2] + size) < tol)[:, None]
                         + np.arange(3)).ravel()])
surf = ContactSurface(body, lambda c: (np.abs(c[:, 2]) < tol) & (np.hypot(c[:, 0], c[:, 1]) < 2e-3))
solver = ContactSolver(body, surf, fixed, R, (0, 0, R), (0, 0, -1), log=lambda *a: None)
(res,) = solver.solve_depths([0.02 * R])
d = 0.02 * R
f = 4 * res.force_on_sphere[2]
f_h = 4 / 3 * E / (1 - NU**2) * np.sqrt(R) * d**1.5
reac = -4 * np.sum(res.reaction[(solver.fixed % 3) == 2])
print(f"coarse Hertz ({body.ndof} dofs): F {f:.4e} N vs Hertz {f_h:.4e} N ({100 * (f / f_h - 1):+.1f} %),"
      f" support reaction {reac:.4e} N, {res.newton} Newton iterations")
assert abs(f / f_h - 1) < 0.10
assert abs(reac / f - 1) < 1e-6
print("checks passed")
