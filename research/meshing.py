"""Gmsh meshes (Python API, OpenCASCADE kernel) turned into scikit-fem ``MeshTet2``.

- ``hertz_block``: a quarter 7R x 7R x 7R block [0, 7R]^2 x [-7R, 0], refined to ``h_fine``
  around the sphere's first contact point (the origin), growing away from it.
- ``lv_half``: the idealized left ventricle of ``shared/data/lv/README.md`` (endocardium
  7, 7, 17 mm, epicardium 10, 10, 20 mm, cut at z = 5 mm), the half y >= 0, refined to ``h``
  around the lv-probe contact point; second order with the mid-edge nodes on the curved
  surfaces, then every node of the two ellipsoidal surfaces put on the analytic ellipsoid.
"""

from __future__ import annotations

import numpy as np
import gmsh

from contact_fem import mesh_from_gmsh_p2


def _threshold_field(point_tags, h_min, h_max, d_min, d_max):
    f = gmsh.model.mesh.field
    dist = f.add("Distance")
    f.setNumbers(dist, "PointsList", point_tags)
    thr = f.add("Threshold")
    f.setNumber(thr, "InField", dist)
    f.setNumber(thr, "SizeMin", h_min)
    f.setNumber(thr, "SizeMax", h_max)
    f.setNumber(thr, "DistMin", d_min)
    f.setNumber(thr, "DistMax", d_max)
    f.setAsBackgroundMesh(thr)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)


def _extract_p2(msh_path=None):
    """Corner coordinates, corner connectivity, node coordinates, mid-node connectivity."""
    gmsh.model.mesh.setOrder(2)
    if msh_path:
        gmsh.write(str(msh_path))
    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = coords.reshape(-1, 3)
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    _, ntags = gmsh.model.mesh.getElementsByType(11)  # 10-node tetrahedra
    conn = index[ntags.astype(np.int64)].reshape(-1, 10)
    corners = np.unique(conn[:, :4])
    cmap = np.full(len(tags), -1, dtype=np.int64)
    cmap[corners] = np.arange(len(corners))
    return coords[corners], cmap[conn[:, :4]], coords, conn[:, 4:]


def hertz_block(radius, h_fine, fine_radius, h_max, grow_dist, msh_path=None, threads=1):
    """Returns (MeshTet2, number of vertices)."""
    size = 7 * radius
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.model.add("hertz")
        gmsh.model.occ.addBox(0, 0, -size, size, size, size)
        gmsh.model.occ.synchronize()
        origin = [t for (_, t) in gmsh.model.getEntities(0)
                  if np.allclose(gmsh.model.getValue(0, t, []), 0)]
        _threshold_field(origin, h_fine, h_max, fine_radius, grow_dist)
        gmsh.model.mesh.generate(3)
        v, t4, x, tm = _extract_p2(msh_path)
    finally:
        gmsh.finalize()
    mesh, nv = mesh_from_gmsh_p2(v, t4, x, tm)
    return mesh, nv


LV_ENDO = (7.0, 7.0, 17.0)
LV_EPI = (10.0, 10.0, 20.0)
LV_BASE_Z = 5.0


def _ellipsoid_q(x, axes):
    return (x[..., 0] / axes[0]) ** 2 + (x[..., 1] / axes[1]) ** 2 + (x[..., 2] / axes[2]) ** 2


def lv_half(h, point_mm, fine_radius_mm, h_max_mm, grow_dist_mm, msh_path=None, threads=1,
            optimize=True):
    """The half LV (y >= 0), lengths in mm. Returns (MeshTet2 in mm, number of vertices,
    largest distance (mm) of a surface node from its analytic ellipsoid before projection)."""
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.model.add("lv")
        occ = gmsh.model.occ
        outer = occ.addSphere(0, 0, 0, 1)
        occ.dilate([(3, outer)], 0, 0, 0, *LV_EPI)
        inner = occ.addSphere(0, 0, 0, 1)
        occ.dilate([(3, inner)], 0, 0, 0, *LV_ENDO)
        shell, _ = occ.cut([(3, outer)], [(3, inner)])
        box = occ.addBox(-30, 0, -30, 60, 30, 30 + LV_BASE_Z)
        half, _ = occ.intersect(shell, [(3, box)])
        occ.synchronize()
        p = occ.addPoint(*point_mm)
        occ.synchronize()
        _threshold_field([p], h, h_max_mm, fine_radius_mm, grow_dist_mm)
        gmsh.option.setNumber("Mesh.ElementOrder", 1)
        gmsh.model.mesh.generate(3)
        if optimize:
            gmsh.model.mesh.optimize("Netgen")
        gmsh.option.setNumber("Mesh.HighOrderOptimize", 0)
        v, t4, x, tm = _extract_p2(msh_path)
    finally:
        gmsh.finalize()
    # snap the nodes of the ellipsoids (and their mid-edge nodes) onto the analytic surfaces
    dev = 0.0
    for axes in (LV_EPI, LV_ENDO):
        for arr in (v, x):
            q = _ellipsoid_q(arr, axes)
            on = (np.abs(np.sqrt(q) - 1) < 1e-3) & (arr[:, 2] <= LV_BASE_Z + 1e-9)
            s = 1 / np.sqrt(q[on])
            dev = max(dev, float(np.max(np.abs(s - 1) * np.linalg.norm(arr[on], axis=1)))
                      if on.any() else 0.0)
            z_base = np.abs(arr[on, 2] - LV_BASE_Z) < 1e-9
            # base-ring nodes stay on z = 5: scale x, y only
            sc = arr[on].copy()
            sc[~z_base] *= s[~z_base, None]
            rxy = np.sqrt(1 - (LV_BASE_Z / axes[2]) ** 2) * axes[0]
            if z_base.any():
                r = np.linalg.norm(sc[z_base, :2], axis=1)
                sc[z_base, :2] *= (rxy / r)[:, None]
            arr[on] = sc
    mesh, nv = mesh_from_gmsh_p2(v, t4, x, tm)
    return mesh, nv, dev
