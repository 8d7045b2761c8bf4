//! A rigid sphere pressed into an elastic half-space of a given material, solved exactly (the
//! static, axisymmetric, finite-strain problem): the calibration of the probe's local contact
//! law ([`super::local_law`]). Not for the servo tick (it allocates and takes seconds).
//!
//! The half-space is the cylinder `0 <= R <= L`, `-L <= Z <= 0` (`L` = `domain` sphere radii)
//! in the axisymmetric reference coordinates `(R, Z)`, meshed with 9-node Lagrange quadrilaterals
//! on a tensor grid refined to `fine_cell` radii near the contact and growing geometrically
//! away from it. Total Lagrangian: with the current position `(r, z)`, the deformation gradient
//! in `(R, Z, theta)` is `[[dr/dR, dr/dZ, 0], [dz/dR, dz/dZ, 0], [0, 0, r/R]]`, and the material's
//! own first Piola-Kirchhoff stress ([`crate::material::first_piola`]) and its exact
//! differential give the residual `int P : dF dV` (`dV = 2 pi R dR dZ`, 3 x 3 Gauss points) and
//! Newton's tangent. The axis has `u_r = 0`, the base `Z = -L` is clamped, the rim `R = L` is on
//! a radial roller. The sphere (radius `a`, centre on the axis at `z = a - depth`) touches the
//! surface nodes through an augmented-Lagrangian contact (frictionless; each node's penalty is
//! its share of the surface area times `penalty_factor E / fine_cell`), updated until no node
//! penetrates more than `gap_tol` of the depth, Newton (with a backtracking line search) to a
//! residual below `newton_tol` of the contact force. Depths are solved in increasing order,
//! each from the previous solution. A depth that does not converge is an error naming it: no
//! silent caps.
//!
//! Checks (tests of this module): at small depth the force follows Hertz's
//! `F = 4/3 E/(1 - nu^2) a^(1/2) d^(3/2)` (Johnson, *Contact Mechanics*, 1985, eq. 4.23), and the
//! tangent equals finite differences of the residual.

use faer::Side;
use faer::sparse::{SparseColMat, Triplet};
use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::linalg::ordering::SparseCholesky;
use crate::material::{MaterialParams, first_piola, first_piola_differential};

/// Mesh and solver settings of [`indent_half_space`] (lengths in sphere radii).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfSpaceParams {
    /// Cell size near the contact, in sphere radii.
    pub fine_cell: f64,
    /// Radial extent of the fine cells from the axis, in sphere radii (below the surface the
    /// cells grow by 1.1 from the first row on to this depth, then by `growth`).
    pub fine_extent: f64,
    /// Growth ratio of the cells beyond the fine region.
    pub growth: f64,
    /// Radius and depth of the cylinder standing for the half-space, in sphere radii.
    pub domain: f64,
    /// Largest penetration of a surface node into the sphere, as a fraction of the depth.
    pub gap_tol: f64,
    /// Newton's tolerance on the largest residual component, as a fraction of the contact
    /// force (plus round-off: `1e-9 E a^2`).
    pub newton_tol: f64,
    /// Node penalty `penalty_factor E max(A_i / h, h)`, `h` the fine cell.
    pub penalty_factor: f64,
    /// Largest Newton iterations per augmentation.
    pub max_newton: usize,
    /// Largest augmentations per depth.
    pub max_augmentations: usize,
}

impl Default for HalfSpaceParams {
    /// Cells of `a / 40` within `1.4 a`, growing by 1.25 to a domain of `100 a`: the force
    /// within about 0.5 % of its mesh-converged value from `d / a = 0.01` to 1 (tests).
    fn default() -> Self {
        Self {
            fine_cell: 1.0 / 40.0,
            fine_extent: 1.2,
            growth: 1.25,
            domain: 100.0,
            gap_tol: 1e-3,
            newton_tol: 1e-8,
            penalty_factor: 100.0,
            max_newton: 25,
            max_augmentations: 30,
        }
    }
}

/// One solved depth of [`indent_half_space`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfSpacePoint {
    /// The sphere's travel below the undeformed surface, m.
    pub depth_m: f64,
    /// Force on the sphere along the axis, N.
    pub force_n: f64,
    /// Current radius of the outermost surface node pressed by the sphere, m.
    pub contact_radius_m: f64,
    /// Newton iterations over all augmentations.
    pub newton_iterations: usize,
}

/// Growth of the cells below the surface (from the first row on).
const DEPTH_GROWTH: f64 = 1.1;

/// Gauss-Legendre points and weights of order 3 on [-1, 1].
const GAUSS: [(f64, f64); 3] = [
    (-0.774_596_669_241_483_4, 5.0 / 9.0),
    (0.0, 8.0 / 9.0),
    (0.774_596_669_241_483_4, 5.0 / 9.0),
];

/// The quadratic Lagrange functions on [-1, 1] at nodes -1, 0, 1 and their derivatives.
fn lagrange(t: f64) -> ([f64; 3], [f64; 3]) {
    (
        [0.5 * t * (t - 1.0), 1.0 - t * t, 0.5 * t * (t + 1.0)],
        [t - 0.5, -2.0 * t, t + 0.5],
    )
}

/// Graded coordinates from 0: cells of `h` up to `fine`, then growing by `growth` to `length`.
fn graded(h: f64, fine: f64, growth: f64, length: f64) -> Vec<f64> {
    let mut xs = vec![0.0];
    let (mut x, mut step) = (0.0, h);
    while x < length - 1e-9 * length {
        if x >= fine - 1e-9 * fine {
            step *= growth;
        }
        x = (x + step).min(length);
        if length - x < 0.3 * step {
            x = length;
        }
        xs.push(x);
    }
    xs
}

/// Depth coordinates from the surface: cells of `h` growing by [`DEPTH_GROWTH`] to `switch`,
/// then by `growth` to `length`.
fn graded_depth(h: f64, switch: f64, growth: f64, length: f64) -> Vec<f64> {
    let mut zs = vec![0.0];
    let (mut z, mut step) = (0.0, h);
    while z < length - 1e-9 * length {
        z = (z + step).min(length);
        if length - z < 0.3 * step {
            z = length;
        }
        zs.push(z);
        step *= if z < switch { DEPTH_GROWTH } else { growth };
    }
    zs
}

/// The structured mesh of the half-space (see the module documentation).
struct Mesh {
    /// Reference `(R, Z)` of every node, m.
    nodes: Vec<[f64; 2]>,
    /// Nine nodes per element (lexicographic: `R` fastest, then `Z`), and the element's box
    /// `[R0, R1, Z0, Z1]`.
    elems: Vec<([usize; 9], [f64; 4])>,
    /// Surface nodes (`Z = 0`) within reach of the sphere and their area `int N_i 2 pi R dR`.
    top: Vec<(usize, f64)>,
    /// Per node: `[radial fixed, axial fixed]`.
    fixed: Vec<[bool; 2]>,
}

impl Mesh {
    fn new(a: f64, p: &HalfSpaceParams) -> Self {
        let rs = graded(p.fine_cell * a, p.fine_extent * a, p.growth, p.domain * a);
        let zs: Vec<f64> = graded_depth(p.fine_cell * a, p.fine_extent * a, p.growth, p.domain * a)
            .iter()
            .map(|z| -z)
            .collect();
        // Node grid with mid-points: (2 n_r + 1) x (2 n_z + 1).
        let refine = |c: &[f64]| {
            let mut out = Vec::with_capacity(2 * c.len());
            for w in c.windows(2) {
                out.push(w[0]);
                out.push(0.5 * (w[0] + w[1]));
            }
            out.push(*c.last().expect("coordinates"));
            out
        };
        let (nr, nz) = (refine(&rs), refine(&zs));
        let mut nodes = Vec::with_capacity(nr.len() * nz.len());
        let mut fixed = Vec::with_capacity(nodes.capacity());
        let rim = *nr.last().expect("radii");
        let base = *nz.last().expect("depths");
        for &z in &nz {
            for &r in &nr {
                nodes.push([r, z]);
                fixed.push([r == 0.0 || r == rim || z == base, z == base]);
            }
        }
        let id = |i: usize, j: usize| j * nr.len() + i;
        let mut elems = Vec::new();
        for j in 0..zs.len() - 1 {
            for i in 0..rs.len() - 1 {
                let mut e = [0; 9];
                for (b, jj) in (0..3).enumerate() {
                    for (a_, ii) in (0..3).enumerate() {
                        e[3 * b + a_] = id(2 * i + ii, 2 * j + jj);
                    }
                }
                // Z decreases with j: the element spans [zs[j + 1], zs[j]].
                elems.push((e, [rs[i], rs[i + 1], zs[j], zs[j + 1]]));
            }
        }
        // Surface areas of the top row's quadratic edges: int N 2 pi R dR by Gauss.
        let mut area = vec![0.0; nr.len()];
        for i in 0..rs.len() - 1 {
            let (r0, r1) = (rs[i], rs[i + 1]);
            for &(t, w) in &GAUSS {
                let (n, _) = lagrange(t);
                let r = 0.5 * (r0 + r1) + 0.5 * (r1 - r0) * t;
                for (k, nk) in n.iter().enumerate() {
                    area[2 * i + k] += w * nk * 2.0 * std::f64::consts::PI * r * 0.5 * (r1 - r0);
                }
            }
        }
        let reach = 1.6 * a;
        let top = (0..nr.len())
            .filter(|&i| nr[i] <= reach)
            .map(|i| (id(i, 0), area[i]))
            .collect();
        Self {
            nodes,
            elems,
            top,
            fixed,
        }
    }
}

/// One element's contribution: residual `int P : dF dV` over its 18 dofs and, when asked, the
/// tangent (row-major 18 x 18). `u` holds the nodal displacements `(u_r, u_z)`.
fn element(
    mat: &MaterialParams,
    e: &([usize; 9], [f64; 4]),
    u: &[[f64; 2]],
    res: &mut [f64; 18],
    tan: Option<&mut [f64; 324]>,
) {
    let (ids, [r0, r1, z0, z1]) = (e.0, e.1);
    let (hr, hz) = (r1 - r0, z1 - z0);
    res.fill(0.0);
    let mut tan = tan;
    if let Some(t) = tan.as_deref_mut() {
        t.fill(0.0);
    }
    let mut df = [DMat3::ZERO; 18];
    for &(s, ws) in &GAUSS {
        let (ns, ds) = lagrange(s);
        for &(t, wt) in &GAUSS {
            let (nt, dt) = lagrange(t);
            let rr = r0 + 0.5 * (s + 1.0) * hr;
            let dv = ws * wt * 0.25 * (hr * hz).abs() * 2.0 * std::f64::consts::PI * rr;
            let (f, grad) = deformation_gradient(&ns, &ds, &nt, &dt, hr, hz, rr, &ids, u);
            let p = first_piola(mat, &f);
            for (k, g) in grad.iter().enumerate() {
                df[2 * k] = DMat3::from_cols(
                    DVec3::new(g[1], 0.0, 0.0),
                    DVec3::new(g[2], 0.0, 0.0),
                    DVec3::new(0.0, 0.0, g[0] / rr),
                );
                df[2 * k + 1] = DMat3::from_cols(
                    DVec3::new(0.0, g[1], 0.0),
                    DVec3::new(0.0, g[2], 0.0),
                    DVec3::ZERO,
                );
            }
            for (q, dq) in df.iter().enumerate() {
                res[q] += dv * ddot(&p, dq);
            }
            if let Some(t) = tan.as_deref_mut() {
                for (b, db) in df.iter().enumerate() {
                    let dp = first_piola_differential(mat, &f, db);
                    for (a_, da) in df.iter().enumerate() {
                        t[a_ * 18 + b] += dv * ddot(&dp, da);
                    }
                }
            }
        }
    }
}

/// One element's elastic energy `int Psi(F) dV`, J (the residual's potential; tests).
#[cfg(test)]
fn element_energy(mat: &MaterialParams, e: &([usize; 9], [f64; 4]), u: &[[f64; 2]]) -> f64 {
    let (ids, [r0, r1, z0, z1]) = (e.0, e.1);
    let (hr, hz) = (r1 - r0, z1 - z0);
    let mut w = 0.0;
    for &(s, ws) in &GAUSS {
        let (ns, ds) = lagrange(s);
        for &(t, wt) in &GAUSS {
            let (nt, dt) = lagrange(t);
            let rr = r0 + 0.5 * (s + 1.0) * hr;
            let dv = ws * wt * 0.25 * (hr * hz).abs() * 2.0 * std::f64::consts::PI * rr;
            let f = deformation_gradient(&ns, &ds, &nt, &dt, hr, hz, rr, &ids, u).0;
            w += dv * crate::material::energy_density(mat, &f);
        }
    }
    w
}

/// The deformation gradient at a Gauss point and the reference shape gradients
/// `[N, dN/dR, dN/dZ]` of the nine nodes.
#[allow(clippy::too_many_arguments)]
fn deformation_gradient(
    ns: &[f64; 3],
    ds: &[f64; 3],
    nt: &[f64; 3],
    dt: &[f64; 3],
    hr: f64,
    hz: f64,
    rr: f64,
    ids: &[usize; 9],
    u: &[[f64; 2]],
) -> (DMat3, [[f64; 3]; 9]) {
    let mut grad = [[0.0; 3]; 9];
    for b in 0..3 {
        for a_ in 0..3 {
            grad[3 * b + a_] = [
                ns[a_] * nt[b],
                ds[a_] * nt[b] * 2.0 / hr,
                ns[a_] * dt[b] * 2.0 / hz,
            ];
        }
    }
    let (mut h, mut ur) = ([[0.0; 2]; 2], 0.0);
    for (k, g) in grad.iter().enumerate() {
        let d = u[ids[k]];
        ur += g[0] * d[0];
        for c in 0..2 {
            h[c][0] += d[c] * g[1];
            h[c][1] += d[c] * g[2];
        }
    }
    // Columns of F: (R, Z, theta).
    let f = DMat3::from_cols(
        DVec3::new(1.0 + h[0][0], h[1][0], 0.0),
        DVec3::new(h[0][1], 1.0 + h[1][1], 0.0),
        DVec3::new(0.0, 0.0, 1.0 + ur / rr),
    );
    (f, grad)
}

fn ddot(a: &DMat3, b: &DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

/// The solve's state: mesh, dof numbering, displacements, contact multipliers.
struct Solver<'a> {
    mat: &'a MaterialParams,
    a: f64,
    p: HalfSpaceParams,
    mesh: Mesh,
    /// Equation of each node's dof (`usize::MAX`: fixed).
    eq: Vec<[usize; 2]>,
    neq: usize,
    u: Vec<[f64; 2]>,
    /// Multiplier (N) and penalty (N/m) of each surface node in `mesh.top`.
    lambda: Vec<f64>,
    penalty: Vec<f64>,
    /// Smoothing width of each node's contact force (N).
    smooth: Vec<f64>,
    /// The last solved depth (m) and the one before with its displacements (the predictor's).
    depth: f64,
    prev_depth: f64,
    prev_u: Vec<[f64; 2]>,
    chol: Option<SparseCholesky>,
}

impl<'a> Solver<'a> {
    fn new(mat: &'a MaterialParams, a: f64, p: HalfSpaceParams) -> Self {
        let mesh = Mesh::new(a, &p);
        let mut eq = vec![[usize::MAX; 2]; mesh.nodes.len()];
        let mut neq = 0;
        for (i, f) in mesh.fixed.iter().enumerate() {
            for c in 0..2 {
                if !f[c] {
                    eq[i][c] = neq;
                    neq += 1;
                }
            }
        }
        let e = mat.youngs_modulus_pa();
        let penalty = mesh
            .top
            .iter()
            .map(|&(_, area)| {
                let h = p.fine_cell * a;
                p.penalty_factor * e * (area / h).max(h)
            })
            .collect();
        Self {
            mat,
            a,
            p,
            u: vec![[0.0; 2]; mesh.nodes.len()],
            lambda: vec![0.0; mesh.top.len()],
            smooth: vec![0.0; mesh.top.len()],
            depth: 0.0,
            prev_depth: 0.0,
            prev_u: vec![[0.0; 2]; mesh.nodes.len()],
            penalty,
            mesh,
            eq,
            neq,
            chol: None,
        }
    }

    /// Current position of node `i`, m.
    fn x(&self, i: usize) -> [f64; 2] {
        let (n, d) = (self.mesh.nodes[i], self.u[i]);
        [n[0] + d[0], n[1] + d[1]]
    }

    /// Contact of surface node `k` with the sphere centred at `(0, zc)`: pressure force `p`
    /// (N, pushing the node along `n`), its derivative `dp/ds` with respect to
    /// `s = lambda - k gap`, the unit normal from the centre and the distance. `p` is the
    /// augmented-Lagrangian `max(0, s)` smoothed over `|s| < w` (`(s + w)^2 / (4 w)`), so that
    /// Newton sees a continuous tangent as nodes enter and leave the contact.
    fn contact(&self, k: usize, zc: f64) -> (f64, f64, [f64; 2], f64) {
        let x = self.x(self.mesh.top[k].0);
        let (dx, dz) = (x[0], x[1] - zc);
        let d = (dx * dx + dz * dz).sqrt();
        let s = self.lambda[k] - self.penalty[k] * (d - self.a);
        let w = self.smooth[k];
        let (p, dp) = if s >= w {
            (s, 1.0)
        } else if s > -w {
            ((s + w) * (s + w) / (4.0 * w), (s + w) / (2.0 * w))
        } else {
            (0.0, 0.0)
        };
        (p, dp, [dx / d, dz / d], d)
    }

    /// Residual (free equations) and, when asked, the tangent triplets; returns the force on
    /// the sphere along +z (N).
    fn assemble(
        &self,
        zc: f64,
        r: &mut [f64],
        mut trip: Option<&mut Vec<Triplet<usize, usize, f64>>>,
    ) -> f64 {
        r.fill(0.0);
        if let Some(t) = trip.as_deref_mut() {
            t.clear();
        }
        let (mut res, mut tan) = ([0.0; 18], [0.0; 324]);
        for e in &self.mesh.elems {
            let want = trip.is_some();
            element(self.mat, e, &self.u, &mut res, want.then_some(&mut tan));
            let eqs: [usize; 18] = std::array::from_fn(|q| self.eq[e.0[q / 2]][q % 2]);
            for (q, &ea) in eqs.iter().enumerate() {
                if ea == usize::MAX {
                    continue;
                }
                r[ea] += res[q];
                if let Some(t) = trip.as_deref_mut() {
                    for (b, &eb) in eqs.iter().enumerate() {
                        if eb != usize::MAX && eb >= ea {
                            t.push(Triplet::new(eb, ea, tan[q * 18 + b]));
                        }
                    }
                }
            }
        }
        let mut force = 0.0;
        for k in 0..self.mesh.top.len() {
            let (p, dp, n, d) = self.contact(k, zc);
            if p <= 0.0 {
                continue;
            }
            force -= p * n[1];
            let i = self.mesh.top[k].0;
            for c in 0..2 {
                if self.eq[i][c] != usize::MAX {
                    r[self.eq[i][c]] -= p * n[c];
                }
            }
            if let Some(t) = trip.as_deref_mut() {
                // d(p n)/dx = -p' k n n^T + p (I - n n^T) / d; the residual carries -(p n).
                for c in 0..2 {
                    for c2 in 0..2 {
                        let (ea, eb) = (self.eq[i][c], self.eq[i][c2]);
                        if ea == usize::MAX || eb == usize::MAX || eb < ea {
                            continue;
                        }
                        let id = if c == c2 { 1.0 } else { 0.0 };
                        let v = dp * self.penalty[k] * n[c] * n[c2] - p * (id - n[c] * n[c2]) / d;
                        t.push(Triplet::new(eb, ea, v));
                    }
                }
            }
        }
        force
    }

    fn add(&mut self, du: &[f64], s: f64) {
        for (i, eq) in self.eq.iter().enumerate() {
            for c in 0..2 {
                if eq[c] != usize::MAX {
                    self.u[i][c] += s * du[eq[c]];
                }
            }
        }
    }

    /// Newton to equilibrium for the current multipliers; returns the iterations.
    fn newton(&mut self, zc: f64, depth_m: f64) -> Result<usize, ModelError> {
        let e = self.mat.youngs_modulus_pa();
        let mut r = vec![0.0; self.neq];
        let mut trial = vec![0.0; self.neq];
        let mut trip = Vec::new();
        let mut last = f64::INFINITY;
        for it in 0..self.p.max_newton {
            let force = self.assemble(zc, &mut r, Some(&mut trip));
            let norm = r.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let tol = self.p.newton_tol * force.abs() + ROUND_OFF * e * self.a * self.a;
            // Converged, or stalled at round-off close to it.
            if norm <= tol || norm <= STALL * force.abs() && norm > 0.5 * last {
                return Ok(it);
            }
            last = norm;
            let k = SparseColMat::try_new_from_triplets(self.neq, self.neq, &trip)
                .map_err(|e| ModelError::InvalidInput(format!("half-space tangent: {e:?}")))?;
            if self.chol.is_none() {
                let group: Vec<usize> = (0..self.neq).collect();
                self.chol = Some(SparseCholesky::analyse(k.symbolic(), Side::Lower, &group)?);
            }
            let chol = self.chol.as_mut().expect("analysed");
            if chol.factor_llt(k.as_ref(), Side::Lower).is_err() {
                chol.factor_ldlt(k.as_ref(), Side::Lower)?;
            }
            let mut du: Vec<f64> = r.iter().map(|v| -v).collect();
            chol.solve_in_place(faer::MatMut::from_column_major_slice_mut(
                &mut du, self.neq, 1,
            ));
            // Backtracking on the directional derivative `g(s) = r(u + s du) . du` (the
            // energy itself is too inexact to compare near the rest state: its terms cancel
            // to round-off over the far field's large volumes): flip an ascent direction,
            // which an indefinite tangent can give, and halve the step while it overshoots
            // the minimum along the line by more than half the initial slope.
            let mut slope: f64 = r.iter().zip(&du).map(|(a, b)| a * b).sum();
            if slope > 0.0 {
                du.iter_mut().for_each(|v| *v = -*v);
                slope = -slope;
            }
            let mut s = 1.0;
            self.add(&du, s);
            for _ in 0..30 {
                self.assemble(zc, &mut trial, None);
                let g: f64 = trial.iter().zip(&du).map(|(a, b)| a * b).sum();
                if g.is_finite() && g <= -0.5 * slope {
                    break;
                }
                self.add(&du, -0.5 * s);
                s *= 0.5;
            }
        }
        Err(ModelError::InvalidInput(format!(
            "sphere on a half-space: Newton did not converge in {} iterations at depth {:.4e} m",
            self.p.max_newton, depth_m
        )))
    }

    /// Solves `depth_m` from the last solved depth `self.depth` in increments of at most
    /// [`MAX_INCREMENT`] sphere radii and half the last depth.
    fn solve_depth(&mut self, depth_m: f64) -> Result<HalfSpacePoint, ModelError> {
        let mut iterations = 0;
        // The increment is cut in half when an increment fails, and may grow back by half
        // after one that converged.
        let mut cut = 1.0f64;
        loop {
            let nominal =
                (MAX_INCREMENT * self.a).min((0.5 * self.depth).max(FIRST_INCREMENT * self.a));
            let next = (self.depth + cut * nominal).min(depth_m);
            // Predictor: the last two solutions extrapolated linearly in depth.
            let grow = (next - self.depth) / (self.depth - self.prev_depth).max(f64::MIN_POSITIVE);
            let (last_u, last_lambda) = (self.u.clone(), self.lambda.clone());
            if self.depth > 0.0 {
                for (u, p) in self.u.iter_mut().zip(&self.prev_u) {
                    for c in 0..2 {
                        u[c] += grow * (u[c] - p[c]);
                    }
                }
            }
            match self.equilibrium(next) {
                Ok(n) => iterations += n,
                Err(e) => {
                    self.u = last_u;
                    self.lambda = last_lambda;
                    cut *= 0.5;
                    if cut < MIN_CUT {
                        return Err(e);
                    }
                    continue;
                }
            }
            cut = (1.5 * cut).min(1.0);
            self.prev_u = last_u;
            self.prev_depth = self.depth;
            self.depth = next;
            if next >= depth_m * (1.0 - 1e-12) {
                break;
            }
        }
        let zc = self.a - depth_m;
        let force = self.multiplier_force(zc);
        let contact_radius_m = (0..self.mesh.top.len())
            .filter(|&k| self.lambda[k] > 0.0)
            .map(|k| self.x(self.mesh.top[k].0)[0])
            .fold(0.0, f64::max);
        Ok(HalfSpacePoint {
            depth_m,
            force_n: force,
            contact_radius_m,
            newton_iterations: iterations,
        })
    }

    /// The force on the sphere of the converged multipliers, N.
    fn multiplier_force(&self, zc: f64) -> f64 {
        (0..self.mesh.top.len())
            .map(|k| -self.lambda[k] * self.contact(k, zc).2[1])
            .sum()
    }

    /// Augmented-Lagrangian loop at one depth; returns Newton's iterations.
    fn equilibrium(&mut self, depth_m: f64) -> Result<usize, ModelError> {
        let zc = self.a - depth_m;
        for k in 0..self.mesh.top.len() {
            self.smooth[k] = SMOOTHING * self.penalty[k] * self.p.gap_tol * depth_m;
        }
        let mut iterations = 0;
        for _ in 0..self.p.max_augmentations {
            iterations += self.newton(zc, depth_m)?;
            // Converged when no node penetrates and every pressing node touches, within the
            // tolerance (a stale multiplier must not push a node that has separated), and the
            // multipliers no longer change: the force is then the multipliers' (to
            // `force_tol`).
            let (mut worst, mut change, mut total) = (0.0f64, 0.0, 0.0);
            for k in 0..self.mesh.top.len() {
                let (p, _, _, d) = self.contact(k, zc);
                change += (p - self.lambda[k]).abs();
                total += p;
                self.lambda[k] = p;
                let gap = d - self.a;
                worst = worst.max(if p > 0.0 { gap.abs() } else { -gap });
            }
            if worst <= self.p.gap_tol * depth_m && change <= FORCE_TOL * total {
                return Ok(iterations);
            }
        }
        Err(ModelError::InvalidInput(format!(
            "sphere on a half-space: a surface node still penetrates the sphere after {} augmentations at depth {:.4e} m",
            self.p.max_augmentations, depth_m
        )))
    }
}

/// Residual Newton cannot go below (round-off in the stresses), in units of `E a^2`.
const ROUND_OFF: f64 = 1e-9;

/// A residual below this fraction of the force that no longer halves per Newton iteration is
/// round-off: converged.
const STALL: f64 = 1e-6;

/// Largest change of the multipliers (sum over the nodes) in the last augmentation, as a
/// fraction of their sum.
const FORCE_TOL: f64 = 1e-5;

/// Smallest fraction of the nominal increment tried before a depth is declared failed.
const MIN_CUT: f64 = 1.0 / 64.0;

/// Largest depth increment, in sphere radii.
const MAX_INCREMENT: f64 = 0.025;

/// First depth increment from the undeformed surface, in sphere radii.
const FIRST_INCREMENT: f64 = 0.005;

/// Width of the contact force's smoothing, as a fraction of the force of a node penetrating
/// the gap tolerance.
const SMOOTHING: f64 = 0.1;

/// Presses a rigid frictionless sphere of radius `radius_m` into a half-space of material
/// `mat` to each of `depths_m` (m, increasing) and returns the force per depth (module
/// documentation); `progress` sees each depth as it is solved (a caller that wants the depths
/// before a failure keeps them). Isotropic materials only (the problem is solved as
/// axisymmetric). Takes seconds to minutes (about 0.5 s per Newton iteration with the default
/// mesh, 25 000 equations).
///
/// # Errors
/// [`ModelError::InvalidInput`] for a non-positive radius, depths that are not positive and
/// increasing, an anisotropic material, or a depth that does not converge (named): St.
/// Venant-Kirchhoff, which softens in compression, has no equilibrium past a depth of about
/// a quarter of the radius at Poisson ratio 0.45.
pub fn indent_half_space(
    mat: &MaterialParams,
    radius_m: f64,
    depths_m: &[f64],
    params: &HalfSpaceParams,
    progress: &mut dyn FnMut(&HalfSpacePoint),
) -> Result<Vec<HalfSpacePoint>, ModelError> {
    if !(radius_m > 0.0 && radius_m.is_finite()) {
        return Err(ModelError::InvalidInput(format!(
            "sphere on a half-space: radius {radius_m} m must be positive"
        )));
    }
    if depths_m.iter().any(|d| !(*d > 0.0 && d.is_finite()))
        || depths_m.windows(2).any(|w| w[1] <= w[0])
    {
        return Err(ModelError::InvalidInput(
            "sphere on a half-space: depths must be positive and increasing".into(),
        ));
    }
    if mat.is_anisotropic() {
        return Err(ModelError::InvalidInput(
            "sphere on a half-space: the axisymmetric solve needs an isotropic material".into(),
        ));
    }
    let mut solver = Solver::new(mat, radius_m, *params);
    let mut out = Vec::with_capacity(depths_m.len());
    for &d in depths_m {
        let p = solver.solve_depth(d)?;
        progress(&p);
        out.push(p);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::MaterialModel;

    /// The element tangent is the derivative of the element residual (central differences).
    #[test]
    fn element_tangent_matches_finite_differences() {
        for model in [
            MaterialModel::StVenantKirchhoff,
            MaterialModel::Corotational,
            MaterialModel::StableNeoHookean,
        ] {
            let mut mat = MaterialParams::from_youngs(14.5e3, 0.45, 1000.0);
            mat.model = model;
            let e = ([0, 1, 2, 3, 4, 5, 6, 7, 8], [0.5e-3, 0.8e-3, 0.0, -0.4e-3]);
            let mut u: Vec<[f64; 2]> = (0..9)
                .map(|k| {
                    let t = k as f64;
                    [2e-5 * (t * 1.3).sin(), -3e-5 * (t * 0.7).cos()]
                })
                .collect();
            let (mut res, mut tan) = ([0.0; 18], [0.0; 324]);
            element(&mat, &e, &u, &mut res, Some(&mut tan));
            let h = 1e-9;
            let mut worst = 0.0f64;
            let scale = tan.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for b in 0..18 {
                let (mut rp, mut rm) = ([0.0; 18], [0.0; 18]);
                u[b / 2][b % 2] += h;
                element(&mat, &e, &u, &mut rp, None);
                u[b / 2][b % 2] -= 2.0 * h;
                element(&mat, &e, &u, &mut rm, None);
                u[b / 2][b % 2] += h;
                for a_ in 0..18 {
                    let fd = (rp[a_] - rm[a_]) / (2.0 * h);
                    worst = worst.max((fd - tan[a_ * 18 + b]).abs() / scale);
                }
            }
            assert!(
                worst < 1e-6,
                "{model:?}: tangent off finite differences by {worst:e}"
            );
            // The residual is the energy's gradient.
            let rscale = res.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let mut worst_r = 0.0f64;
            for b in 0..18 {
                u[b / 2][b % 2] += h;
                let ep = element_energy(&mat, &e, &u);
                u[b / 2][b % 2] -= 2.0 * h;
                let em = element_energy(&mat, &e, &u);
                u[b / 2][b % 2] += h;
                worst_r = worst_r.max(((ep - em) / (2.0 * h) - res[b]).abs() / rscale);
            }
            assert!(
                worst_r < 1e-5,
                "{model:?}: residual off the energy's gradient by {worst_r:e}"
            );
        }
    }

    /// At small depth every material's law is Hertz's, `F = 4/3 E/(1 - nu^2) a^(1/2) d^(3/2)`
    /// (Johnson 1985, eq. 4.23), and the contact radius `(a d)^(1/2)`. The finite-strain laws
    /// depart from it as the strain, about `(d / a)^(1/2)` (at nu = 0.45 and `d / a = 0.01`: St.
    /// Venant-Kirchhoff -4.5 %, corotational -1.9 %, stable neo-Hookean -0.3 %), so the check
    /// is at `d / a = 5e-4` on a mesh refined to match (cells of `a / 1000`), within 1.5 %, for
    /// the two materials the compiled-in table holds (the corotational law is Hertz's itself).
    #[test]
    fn small_depths_follow_hertz() {
        let a = 2e-3;
        let cases = [
            (MaterialModel::StableNeoHookean, 5e-4, 1.0 / 1000.0, 0.015),
            (MaterialModel::StVenantKirchhoff, 5e-4, 1.0 / 1000.0, 0.015),
        ];
        for (model, ratio, cell, tol) in cases {
            let mut mat = MaterialParams::from_youngs(14.5e3, 0.45, 1000.0);
            mat.model = model;
            let params = HalfSpaceParams {
                fine_cell: cell,
                fine_extent: 40.0 * cell,
                growth: 1.5,
                domain: 20.0,
                ..HalfSpaceParams::default()
            };
            let depth = ratio * a;
            let p = indent_half_space(&mat, a, &[depth], &params, &mut |_| {}).unwrap();
            let e_star = 14.5e3 / (1.0 - 0.45f64 * 0.45);
            let hertz = 4.0 / 3.0 * e_star * a.sqrt() * depth.powf(1.5);
            let (ef, ea) = (
                p[0].force_n / hertz - 1.0,
                p[0].contact_radius_m / (a * depth).sqrt() - 1.0,
            );
            eprintln!(
                "{model:?} at d/a {ratio}: force {ef:+.4} against Hertz, contact radius {ea:+.4}"
            );
            assert!(
                ef.abs() < tol,
                "{model:?} at d/a {ratio}: force off Hertz by {ef:+.4}"
            );
            assert!(
                ea.abs() < 0.1,
                "{model:?} at d/a {ratio}: contact radius off by {ea:+.4}"
            );
        }
    }
}
