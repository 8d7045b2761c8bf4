"""Independent static solver for rigid-sphere frictionless contact on hyperelastic bodies.

Total-Lagrangian hyperelastic statics on curved quadratic (10-node) tetrahedra, assembled from
scikit-fem's isoparametric P2 basis (``MeshTet2``: the mid-edge nodes carry the curved
geometry), Newton's method, and exact frictionless contact with a rigid sphere by a
semismooth Newton / primal-dual active-set method (Hueber & Wohlmuth 2005; Popp et al. 2009):

- weighted gaps at the vertices of the contact surface (the "mortar" normal gap):
  ``g_v = int_Gamma phi_v (|x - c| - R) dA`` with ``phi_v`` the linear hat function of vertex
  ``v`` on the surface triangulation, ``x`` the deformed P2 surface, ``c``/``R`` the sphere;
- non-negative multipliers ``lambda_v`` (force, N) with ``lambda_v >= 0``, ``g_v >= 0``,
  ``lambda_v g_v = 0``, solved as ``lambda_v - max(0, lambda_v - c_n g_v) = 0`` by Newton on
  the active set: the constraint holds exactly (``g_v = 0`` on the active set at convergence),
  no penalty parameter enters the converged answer;
- each Newton step solves the bordered (KKT) system ``[K - sum lambda_v H_v, C_A^T; C_A, 0]``
  with MKL Pardiso (``pypardiso``) when installed, else SciPy's SuperLU.

Materials, written to be the same energies as ``server/model/src/material/stvk.rs`` and
``neo_hookean.rs`` (Lame parameters from ``E, nu`` as in ``material/mod.rs``):

- St. Venant-Kirchhoff: ``Psi = lambda/2 tr(E)^2 + mu E:E``, ``E = (F^T F - I)/2``;
- stable neo-Hookean (Smith, de Goes, Kim 2018, eq. 14 without the log term):
  ``Psi = mu/2 (tr(F^T F) - 3) + ls/2 (J - alpha)^2 - mu^2/(2 ls)``, ``ls = lambda + mu``,
  ``alpha = 1 + mu/ls``.

Units: whatever the caller uses consistently (the scripts use SI: m, Pa, N).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from skfem import CellBasis, ElementTetP2, MeshTet1, MeshTet2
from skfem.quadrature import get_quadrature
from skfem.refdom import RefTri

try:  # MKL Pardiso from its PyPI wheel
    import pypardiso

    _SOLVER = "pardiso"
except ImportError:  # pragma: no cover
    pypardiso = None
    _SOLVER = "superlu"
import scipy.sparse.linalg as spla


def solver_name() -> str:
    """The sparse direct solver in use."""
    return "MKL Pardiso (pypardiso)" if _SOLVER == "pardiso" else "SciPy SuperLU"


def lame(e_pa: float, nu: float) -> tuple[float, float]:
    """Lame (lambda, mu) from Young's modulus and Poisson ratio (material/mod.rs from_youngs)."""
    return e_pa * nu / ((1 + nu) * (1 - 2 * nu)), e_pa / (2 * (1 + nu))


# ---------------------------------------------------------------------------------------------
# Materials: energy, first Piola-Kirchhoff stress, tangent A_iJkL = dP_iJ / dF_kL.
# F has shape (3, 3, ...) (any trailing shape).


def _eye_like(f):
    i = np.zeros_like(f)
    for k in range(3):
        i[k, k] = 1.0
    return i


def _det(f):
    return (f[0, 0] * (f[1, 1] * f[2, 2] - f[1, 2] * f[2, 1])
            - f[0, 1] * (f[1, 0] * f[2, 2] - f[1, 2] * f[2, 0])
            + f[0, 2] * (f[1, 0] * f[2, 1] - f[1, 1] * f[2, 0]))


def _cof(f):
    """Cofactor J F^-T: column j is the cross product of the other two columns, cyclic."""
    c = np.empty_like(f)
    cols = [f[:, 0], f[:, 1], f[:, 2]]
    for j in range(3):
        a, b = cols[(j + 1) % 3], cols[(j + 2) % 3]
        c[:, j] = np.stack([a[1] * b[2] - a[2] * b[1],
                            a[2] * b[0] - a[0] * b[2],
                            a[0] * b[1] - a[1] * b[0]])
    return c


# Levi-Civita symbol
_EPS = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_i, _j, _k] = 1.0
    _EPS[_i, _k, _j] = -1.0


# _EPS2[(i, J, k, L), (m, N)] = eps_ikm eps_JLN
_EPS2 = np.einsum("ikm,JLN->iJkLmN", _EPS, _EPS).reshape(81, 9)


@dataclass
class Material:
    """``model`` is ``"stvk"``, ``"stable-neo-hookean"`` or ``"linear"`` (small-strain linear
    elasticity in the deformation gradient, for comparing with Hertz); Lame parameters in Pa."""

    model: str
    lam: float
    mu: float

    def energy(self, f):
        lam, mu = self.lam, self.mu
        if self.model == "stvk":
            c = np.einsum("kI...,kJ...->IJ...", f, f)
            e = 0.5 * (c - _eye_like(c))
            tr = e[0, 0] + e[1, 1] + e[2, 2]
            return 0.5 * lam * tr**2 + mu * np.einsum("IJ...,IJ...->...", e, e)
        if self.model == "linear":
            e = 0.5 * (f + np.swapaxes(f, 0, 1)) - _eye_like(f)
            tr = e[0, 0] + e[1, 1] + e[2, 2]
            return 0.5 * lam * tr**2 + mu * np.einsum("IJ...,IJ...->...", e, e)
        ls = lam + mu
        alpha = 1 + mu / ls
        j = _det(f) - alpha
        return (0.5 * mu * (np.einsum("iJ...,iJ...->...", f, f) - 3)
                + 0.5 * ls * j**2 - 0.5 * mu**2 / ls)

    def stress_tangent(self, f):
        """(P, A) at F: P (3,3,...) Pa, A (3,3,3,3,...) with A[i,J,k,L] = dP_iJ/dF_kL."""
        lam, mu = self.lam, self.mu
        eye = np.eye(3)
        if self.model == "stvk":
            c = np.einsum("kI...,kJ...->IJ...", f, f)
            e = 0.5 * (c - _eye_like(c))
            tr = e[0, 0] + e[1, 1] + e[2, 2]
            s = 2 * mu * e
            for k in range(3):
                s[k, k] += lam * tr
            p = np.einsum("iK...,KJ...->iJ...", f, s)
            b = np.einsum("iK...,kK...->ik...", f, f)  # F F^T
            a = (np.einsum("ik,LJ...->iJkL...", eye, s)
                 + lam * np.einsum("iJ...,kL...->iJkL...", f, f)
                 + mu * np.einsum("ik...,JL->iJkL...", b, eye)
                 + mu * np.einsum("iL...,kJ...->iJkL...", f, f))
            return p, a
        if self.model == "linear":
            e = 0.5 * (f + np.swapaxes(f, 0, 1)) - _eye_like(f)
            tr = e[0, 0] + e[1, 1] + e[2, 2]
            p = 2 * mu * e
            for k in range(3):
                p[k, k] += lam * tr
            a = (lam * np.einsum("iJ,kL->iJkL", eye, eye)
                 + mu * (np.einsum("ik,JL->iJkL", eye, eye) + np.einsum("iL,Jk->iJkL", eye, eye)))
            return p, np.broadcast_to(a[(...,) + (None,) * (f.ndim - 2)], (3, 3, 3, 3) + f.shape[2:])
        if self.model == "stable-neo-hookean":
            ls = lam + mu
            alpha = 1 + mu / ls
            cof = _cof(f)
            jm = _det(f) - alpha
            p = mu * f + ls * jm * cof
            # d cof_iJ / dF_kL = eps_ikm eps_JLN F_mN
            dcof = (_EPS2 @ f.reshape(9, -1)).reshape((3, 3, 3, 3) + f.shape[2:])
            a = (mu * np.einsum("ik,JL->iJkL", eye, eye)[(...,) + (None,) * (f.ndim - 2)]
                 + ls * np.einsum("iJ...,kL...->iJkL...", cof, cof) + ls * jm * dcof)
            return p, a
        raise ValueError(f"unknown material model {self.model!r}")


def check_material(mat: Material, seed: int = 1) -> float:
    """Largest relative finite-difference error of P against Psi and of A against P."""
    rng = np.random.default_rng(seed)
    f = np.eye(3)[:, :, None] + 0.3 * rng.standard_normal((3, 3, 4))
    p, a = mat.stress_tangent(f)
    h = 1e-6
    err = 0.0
    for k in range(3):
        for l in range(3):
            d = np.zeros_like(f)
            d[k, l] = h
            dpsi = (mat.energy(f + d) - mat.energy(f - d)) / (2 * h)
            err = max(err, np.max(np.abs(dpsi - p[k, l])) / np.max(np.abs(p)))
            pp, _ = mat.stress_tangent(f + d)
            pm, _ = mat.stress_tangent(f - d)
            dp = (pp - pm) / (2 * h)
            err = max(err, np.max(np.abs(dp - a[:, :, k, l])) / np.max(np.abs(a)))
    return err


# ---------------------------------------------------------------------------------------------
# Mesh: gmsh second-order tetrahedra -> scikit-fem MeshTet2 with the curved mid-edge nodes.


def mesh_from_gmsh_p2(vert_xyz, tets4, mid_xyz, tets_mid):
    """Builds a ``MeshTet2`` from corner coordinates ``vert_xyz`` (nv, 3), corner connectivity
    ``tets4`` (nt, 4), and the mid-edge node coordinates ``mid_xyz[tets_mid]`` (nt, 6) of each
    tetrahedron in any order: each mid node is matched to the edge whose straight midpoint is
    nearest (the curved offset is far below the edge length)."""
    m1 = MeshTet1(np.ascontiguousarray(vert_xyz.T), np.ascontiguousarray(tets4.T))
    m2 = MeshTet2.from_mesh(m1)
    doflocs = m2.doflocs.copy()
    nv = m1.p.shape[1]
    t2e = m1.t2e  # (6, nt) edge index per local edge
    edges = m1.edges  # (2, ne)
    # straight midpoints of skfem's local edges (6, nt, 3)
    mids_straight = 0.5 * (m1.p[:, edges[0, t2e]] + m1.p[:, edges[1, t2e]]).transpose(1, 2, 0)
    gm = mid_xyz[tets_mid].transpose(1, 0, 2)  # (6, nt, 3) gmsh mid nodes
    d = np.linalg.norm(mids_straight[:, None] - gm[None, :], axis=3)  # (6 skfem, 6 gmsh, nt)
    match = np.argmin(d, axis=1)  # (6, nt)
    if not np.all(np.sort(match, axis=0) == np.arange(6)[:, None]):
        raise ValueError("mid-edge nodes do not match the edges one to one")
    chosen = np.take_along_axis(gm, match[:, :, None], axis=0)  # (6, nt, 3)
    doflocs[:, nv + t2e.ravel()] = chosen.reshape(-1, 3).T
    return MeshTet2(doflocs, m1.t), nv


# ---------------------------------------------------------------------------------------------
# The body: assembly of internal forces and tangent.


class Body:
    """Hyperelastic body on a ``MeshTet2``; dof ``3 * node + i``, nodes = scalar P2 dofs."""

    def __init__(self, mesh: MeshTet2, material: Material, intorder: int = 5, chunk=3000):
        self.mesh = mesh
        self.mat = material
        self.basis = CellBasis(mesh, ElementTetP2(), intorder=intorder)
        b = self.basis
        self.x0 = b.doflocs.T.copy()  # (nn, 3) reference node coordinates
        self.nn = self.x0.shape[0]
        self.ndof = 3 * self.nn
        self.edofs = b.element_dofs  # (10, ne)
        self.grad = np.array([b.basis[a][0].grad for a in range(10)])  # (10, 3, ne, nq)
        self.dx = b.dx  # (ne, nq)
        self.ne = self.edofs.shape[1]
        self.chunk = chunk
        # element dof indices (30, ne): local (a, i) -> 3 * node + i
        self.gdofs = (3 * self.edofs[:, None, :] + np.arange(3)[None, :, None]).reshape(30, -1)
        rows = np.repeat(self.gdofs, 30, axis=0).reshape(30, 30, -1)
        cols = np.tile(self.gdofs, (30, 1)).reshape(30, 30, -1)
        # per element, local (I, J) with J fastest, as the element matrices are stored
        lin = (rows.astype(np.int64) * self.ndof + cols).transpose(2, 0, 1).ravel()
        uniq, self._inv = np.unique(lin, return_inverse=True)
        self._rows = (uniq // self.ndof).astype(np.int32)
        self._cols = (uniq % self.ndof).astype(np.int32)
        self._indptr = np.searchsorted(self._rows, np.arange(self.ndof + 1)).astype(np.int32)
        self.volume = float(self.dx.sum())

    def _f(self, u, sl):
        ue = u.reshape(-1, 3)[self.edofs[:, sl]]  # (10, nec, 3)
        g = self.grad[:, :, sl]
        f = np.einsum("aei,aJeq->iJeq", ue, g)
        for k in range(3):
            f[k, k] += 1.0
        return f

    def energy(self, u):
        tot = 0.0
        for s in range(0, self.ne, self.chunk):
            sl = slice(s, min(s + self.chunk, self.ne))
            tot += float(np.sum(self.mat.energy(self._f(u, sl)) * self.dx[sl]))
        return tot

    def min_jacobian(self, u):
        return min(float(_det(self._f(u, slice(s, min(s + self.chunk, self.ne)))).min())
                   for s in range(0, self.ne, self.chunk))

    def assemble(self, u, tangent=True):
        """Internal force (ndof,) and, if ``tangent``, the stiffness (CSR)."""
        fint = np.zeros(self.ndof)
        vals = [] if tangent else None
        for s in range(0, self.ne, self.chunk):
            sl = slice(s, min(s + self.chunk, self.ne))
            f = self._f(u, sl)
            p, a = self.mat.stress_tangent(f)
            g = self.grad[:, :, sl]
            w = self.dx[sl]
            fe = np.einsum("iJeq,aJeq,eq->aie", p, g, w).reshape(30, -1)
            fint += np.bincount(self.gdofs[:, sl].ravel(), weights=fe.ravel(),
                                minlength=self.ndof)
            if tangent:
                ag = np.einsum("iJkLeq,bLeq,eq->iJkbeq", a, g, w)
                ke = np.einsum("aJeq,iJkbeq->aibke", g, ag, optimize=True)
                vals.append(ke.reshape(900, -1))
        if not tangent:
            return fint, None
        data = np.bincount(self._inv, weights=np.concatenate(vals, axis=1).T.ravel(),
                           minlength=len(self._rows))
        k = sp.csr_matrix((data, self._cols, self._indptr), shape=(self.ndof, self.ndof))
        return fint, k


# ---------------------------------------------------------------------------------------------
# Contact surface: weighted gaps on the P2 surface triangles.

_TRI_Q, _TRI_W = get_quadrature(RefTri, 6)  # 12 points, degree 6


def _p2_tri(xi):
    """P2 triangle shape functions (6, nq) and derivatives (6, 2, nq) at xi (2, nq); node order
    v0, v1, v2, e01, e12, e20."""
    x, y = xi
    l0, l1, l2 = 1 - x - y, x, y
    n = np.array([l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), l2 * (2 * l2 - 1),
                  4 * l0 * l1, 4 * l1 * l2, 4 * l2 * l0])
    dl = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # d l_k / d(x, y)
    ls = [l0, l1, l2]
    d = np.zeros((6, 2, xi.shape[1]))
    for k in range(3):
        d[k] = (4 * ls[k] - 1) * dl[k][:, None]
    for m, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        d[3 + m] = 4 * (ls[i] * dl[j][:, None] + ls[j] * dl[i][:, None])
    return n, d, np.array(ls)


class ContactSurface:
    """Boundary triangles of ``body`` (6 nodes each, curved) on which the sphere may press.

    ``facet_filter(centroids) -> bool mask`` picks them among the boundary facets."""

    def __init__(self, body: Body, facet_filter):
        mesh = body.mesh
        bf = mesh.boundary_facets()
        fv = mesh.facets[:, bf]  # (3, nb) vertex indices
        cen = body.x0[fv].mean(axis=0)
        keep = facet_filter(cen)
        fv = fv[:, keep]
        # edge index of each facet side
        edict = {}
        e = mesh.edges
        for k in range(e.shape[1]):
            edict[(e[0, k], e[1, k])] = k
            edict[(e[1, k], e[0, k])] = k
        nv = int(mesh.t.max()) + 1  # vertices (MeshTet2.p holds every node)
        tri = np.empty((6, fv.shape[1]), dtype=np.int64)
        tri[:3] = fv
        for m, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
            a, b = fv[i], fv[j]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            tri[3 + m] = [nv + edict[(p, q)] for p, q in zip(lo, hi)]
        self.tri = tri
        self.verts, self.tri_v = np.unique(fv, return_inverse=True)  # multiplier nodes
        self.tri_v = self.tri_v.reshape(3, -1)
        self.nvert = len(self.verts)
        n, d, l1 = _p2_tri(_TRI_Q)
        self.n, self.l1 = n, l1  # (6, nq), (3, nq)
        x0 = body.x0[tri]  # (6, nt, 3)
        jac = np.einsum("akq,ati->tqik", d, x0)  # (nt, nq, 3, 2)
        da = np.linalg.norm(np.cross(jac[..., 0], jac[..., 1]), axis=-1)
        self.dA = da * _TRI_W[None, :]  # reference area weights (nt, nq)
        self.area = float(self.dA.sum())
        # vertex "areas" int phi_v dA
        self.vert_area = np.zeros(self.nvert)
        np.add.at(self.vert_area, self.tri_v.ravel(),
                  np.einsum("kq,tq->kt", l1, self.dA).ravel())
        self.ndof = body.ndof
        self.x0_tri = body.x0[tri]

    def evaluate(self, u, centre, radius):
        """Weighted gaps g (nvert,), constraint gradient C (nvert x ndof, CSR), and the
        curvature terms as a function lam -> sum_v lam_v H_v (CSR)."""
        tri = self.tri
        x = self.x0_tri + u.reshape(-1, 3)[tri]  # (6, nt, 3)
        xq = np.einsum("aq,ati->tqi", self.n, x)
        r = xq - centre
        dist = np.linalg.norm(r, axis=-1)
        nu = r / dist[..., None]
        gap = dist - radius
        # g_v = sum phi_v gap dA
        g = np.zeros(self.nvert)
        np.add.at(g, self.tri_v.ravel(), np.einsum("kq,tq,tq->kt", self.l1, gap, self.dA).ravel())
        # C[v, 3 node_a + i] = sum phi_v N_a nu_i dA
        cvals = np.einsum("kq,aq,tqi,tq->kait", self.l1, self.n, nu, self.dA)  # (3,6,3,nt)
        rows = np.broadcast_to(self.tri_v[:, None, None, :], cvals.shape)
        cols = np.broadcast_to(3 * tri[None, :, None, :] + np.arange(3)[None, None, :, None],
                               cvals.shape)
        c = sp.csr_matrix((cvals.ravel(), (rows.ravel(), cols.ravel())),
                          shape=(self.nvert, self.ndof))
        proj = (np.eye(3)[None, None] - nu[..., :, None] * nu[..., None, :]) / dist[..., None, None]

        def curvature(lam):
            lt = lam[self.tri_v]  # (3, nt)
            wq = np.einsum("kt,kq,tq->tq", lt, self.l1, self.dA)
            hv = np.einsum("tq,aq,bq,tqik->aibkt", wq, self.n, self.n, proj)
            ri = 3 * tri[:, None, None, None, :] + np.arange(3)[None, :, None, None, None]
            ci = 3 * tri[None, None, :, None, :] + np.arange(3)[None, None, None, :, None]
            ri = np.broadcast_to(ri, hv.shape)
            ci = np.broadcast_to(ci, hv.shape)
            return sp.csr_matrix((hv.ravel(), (ri.ravel(), ci.ravel())),
                                 shape=(self.ndof, self.ndof))

        return g, c, curvature, xq, gap


# ---------------------------------------------------------------------------------------------
# Semismooth Newton with the active set.


_PARDISO = None


def _kkt_solve(kff, ca, rhs):
    """Solves the bordered system ``[kff, ca^T; ca, 0] x = rhs`` (kff symmetric). Pardiso:
    symmetric indefinite (mtype -2, upper triangle, Bunch-Kaufman pivoting with weighted
    matching and scaling); SuperLU otherwise."""
    global _PARDISO
    na = ca.shape[0]
    # row scaling of the constraints to the stiffness' scale (weighted gaps are m^3)
    nf = kff.shape[0]
    rn = np.sqrt(np.asarray(ca.multiply(ca).sum(axis=1)).ravel())
    dscale = np.median(kff.diagonal()) / np.where(rn > 0, rn, 1.0)
    ca = sp.diags(dscale) @ ca
    rhs = np.concatenate([rhs[:nf], dscale * rhs[nf:]])
    x = _kkt_solve_scaled(kff, ca, rhs)
    x[nf:] *= dscale
    return x


def _kkt_solve_scaled(kff, ca, rhs):
    global _PARDISO
    na = ca.shape[0]
    if _SOLVER == "pardiso":
        if _PARDISO is None:
            _PARDISO = pypardiso.PyPardisoSolver(mtype=-2)
            _PARDISO.set_iparm(11, 1)  # scaling
            _PARDISO.set_iparm(13, 1)  # weighted matching
        zero = sp.csr_matrix((np.zeros(na), (np.arange(na), np.arange(na))), shape=(na, na))
        upper = sp.bmat([[sp.triu(kff), ca.T], [None, zero]], format="csr")
        upper.sort_indices()
        x = _PARDISO.solve(upper, rhs)
        _PARDISO.free_memory(everything=False)
        return x
    kkt = sp.bmat([[kff, ca.T], [ca, None]], format="csc")
    return spla.spsolve(kkt, rhs)


@dataclass
class DepthResult:
    depth: float
    force_on_sphere: np.ndarray  # (3,) of the modelled part (before symmetry multiplication)
    active: int
    newton: int
    increments: int
    seconds: float
    max_penetration: float  # largest -g_v / vert_area over vertices (m)
    lam: np.ndarray = field(repr=False, default=None)
    u: np.ndarray = field(repr=False, default=None)
    reaction: np.ndarray = field(repr=False, default=None)


class ContactSolver:
    """Static rigid-sphere contact: the sphere centre is ``centre0 + depth * direction``."""

    def __init__(self, body: Body, surf: ContactSurface, fixed_dofs, radius, centre0,
                 direction, c_n=None, curvature=True, tol=1e-7, max_newton=40, log=print):
        self.body, self.surf = body, surf
        self.radius = radius
        self.centre0 = np.asarray(centre0, float)
        self.direction = np.asarray(direction, float) / np.linalg.norm(direction)
        self.fixed = np.unique(np.asarray(fixed_dofs))
        self.free = np.setdiff1d(np.arange(body.ndof), self.fixed)
        mu = body.mat.mu
        hmin = np.sqrt(surf.vert_area.min())
        # c_n turns a weighted gap (m^3) into a force (N): mu / h per unit area
        self.c_n = c_n if c_n is not None else mu / hmin
        self.curvature = curvature
        self.tol = tol
        self.max_newton = max_newton
        self.log = log
        self.u = np.zeros(body.ndof)
        self.lam = np.zeros(surf.nvert)
        self.cur = 0.0  # depth of (u, lam)
        self.prev = (None, None)  # the state before, for the extrapolated start

    def centre(self, depth):
        return self.centre0 + depth * self.direction

    def _newton(self, depth, u, lam):
        """Semismooth Newton at one depth from (u, lam). Returns (u, lam, iterations) or
        raises RuntimeError."""
        body, surf = self.body, self.surf
        c = self.centre(depth)
        free = self.free
        fscale = None
        prev_active = None
        for it in range(1, self.max_newton + 1):
            fint, _ = body.assemble(u, tangent=False)
            g, cmat, curv, _, _ = surf.evaluate(u, c, self.radius)
            active = (lam - self.c_n * g) > 0
            resid = fint - cmat.T @ lam
            fref = max(np.linalg.norm(cmat.T @ lam), fscale or 0.0)
            rn = np.linalg.norm(resid[free])
            gviol = np.max(np.maximum(-g, 0) / surf.vert_area) if surf.nvert else 0.0
            comp = np.max(np.abs(np.where(active, g, lam) /
                                 np.where(active, surf.vert_area, 1.0))) if surf.nvert else 0
            self.log(f"    it {it:2d}: |r| {rn:.3e} (|F_c| {fref:.3e}), active {active.sum()}, "
                     f"max pen {gviol:.2e}, min J {body.min_jacobian(u):.3f}")
            if (it > 1 and prev_active is not None and np.array_equal(active, prev_active)
                    and rn <= self.tol * max(fref, 1e-30) and gviol <= 1e-7 * self.radius
                    and np.all(lam >= 0)):
                return u, lam, it - 1
            prev_active = active
            _, k = body.assemble(u)
            if self.curvature and np.any(lam > 0):
                k = k - curv(np.maximum(lam, 0))
            ia = np.flatnonzero(active)
            kff = k[free][:, free]
            ca = cmat[ia][:, free]
            rhs = np.concatenate([-fint[free], -g[ia]])
            sol = _kkt_solve(kff, ca, rhs)
            if not np.all(np.isfinite(sol)):
                raise RuntimeError("linear solve failed")
            du = np.zeros(body.ndof)
            du[free] = sol[:len(free)]
            lam_new = np.zeros_like(lam)
            lam_new[ia] = -sol[len(free):]
            # damped step if the full one inverts an element (halved up to 6 times)
            alpha = 1.0
            while body.min_jacobian(u + alpha * du) <= 0:
                alpha *= 0.5
                if alpha < 1 / 64:
                    raise RuntimeError("an element inverted")
            u = u + alpha * du
            lam = lam + alpha * (lam_new - lam)
            fscale = np.linalg.norm(cmat.T @ lam)
        raise RuntimeError(f"Newton did not converge in {self.max_newton} iterations")

    def solve_depths(self, depths, min_step_fraction=1 / 64, max_step=None):
        """Continuation through ``depths`` (increasing). Each target depth is reached through
        increments of at most ``max_step``; a failed increment is halved (down to
        ``min_step_fraction`` of the gap to the target), else RuntimeError names the depth."""
        results = []
        cur = self.cur
        u, lam = self.u.copy(), self.lam.copy()
        u_prev, d_prev = self.prev
        for target in depths:
            t0 = time.perf_counter()
            newton_total, incs = 0, 0
            step = target - cur if max_step is None else min(max_step, target - cur)
            while cur < target - 1e-15:
                step = min(step, target - cur)
                nxt = cur + step
                # extrapolated start from the last two converged states
                if u_prev is not None and d_prev is not None and cur > d_prev:
                    u0 = u + (u - u_prev) * (step / (cur - d_prev))
                    if self.body.min_jacobian(u0) <= 0.05:
                        u0 = u
                else:
                    u0 = u
                try:
                    u_new, lam_new, nit = self._newton(nxt, u0, lam)
                except RuntimeError as err:
                    self.log(f"  increment {cur:.4g} -> {nxt:.4g} failed ({err}); halving")
                    step *= 0.5
                    if step < min_step_fraction * (target - cur):
                        raise RuntimeError(
                            f"no equilibrium found at depth {nxt:.6g} (last converged "
                            f"{cur:.6g}): {err}") from err
                    continue
                newton_total += nit
                incs += 1
                u_prev, d_prev = u, cur
                u, lam, cur = u_new, lam_new, nxt
                if max_step is not None:
                    step = min(2 * step, max_step)
                self.u, self.lam, self.cur, self.prev = u, lam, cur, (u_prev, d_prev)
            results.append(self._result(target, u, lam, newton_total, incs,
                                        time.perf_counter() - t0))
        return results

    def _result(self, depth, u, lam, nit, incs, secs):
        surf = self.surf
        g, cmat, _, _, _ = surf.evaluate(u, self.centre(depth), self.radius)
        fbody = cmat.T @ lam  # contact force on the body's dofs
        f_on_body = fbody.reshape(-1, 3).sum(axis=0)
        fint, _ = self.body.assemble(u, tangent=False)
        reaction = -fint[self.fixed]
        pen = float(np.max(np.maximum(-g, 0) / surf.vert_area))
        return DepthResult(depth, -f_on_body, int((lam > 0).sum()), nit, incs, secs, pen,
                           lam.copy(), u.copy(), reaction)


# ---------------------------------------------------------------------------------------------
# Richardson extrapolation and Roache's grid convergence index.


def richardson_gci(h, f, fs=1.25):
    """Three levels h1 < h2 < h3 (finest first) with values f1, f2, f3 (any ratio; Celik et al.
    2008 iteration for non-constant ratios). Returns dict with the observed order p (None when
    not monotone), the extrapolated value, the GCI of the finest level (absolute), and a note."""
    (h1, h2, h3), (f1, f2, f3) = h, f
    e21, e32 = f2 - f1, f3 - f2
    r21, r32 = h2 / h1, h3 / h2
    if e21 == 0 or e32 == 0 or np.sign(e21) != np.sign(e32):
        spread = max(f) - min(f)
        return dict(order=None, extrapolated=f1, gci=fs * spread, note="oscillatory / none")
    s = np.sign(e32 / e21)
    p = 1.0
    for _ in range(200):
        q = np.log((r21**p - s) / (r32**p - s))
        p_new = abs(np.log(abs(e32 / e21)) + q) / np.log(r21)
        if abs(p_new - p) < 1e-12:
            break
        p = p_new
    fext = (r21**p * f1 - f2) / (r21**p - 1)
    gci = fs * abs(e21) / (r21**p - 1)
    return dict(order=p, extrapolated=fext, gci=gci, note="monotone")
