//! Newton's method for the static equilibrium of a body pressed by a rigid frictionless
//! sphere, with the contact of the surface nodes enforced exactly by an active set.
//!
//! Each touchable node `i` may not enter the sphere: `g_i = R - |x_i - c| <= 0`, with a
//! multiplier (contact force) `lambda_i >= 0` acting along the outward normal `n_i = (x_i -
//! c) / |x_i - c|`, and `lambda_i g_i = 0`. The active set is updated at every iteration by
//! the primal-dual rule `lambda_i + c_i g_i > 0` (Hintermueller, Ito & Kunisch 2002: the
//! semismooth Newton method of this complementarity problem), `c_i` the node's diagonal rest
//! stiffness, `lambda_i` the node's reaction `-n_i . r_i` at the current iterate. The Newton
//! step of an active set moves each active node onto the linearised sphere (`n_i . dx_i =
//! g_i`) and solves the equilibrium on the others' directions: `P K P z = P (r - K y_0)` with
//! `P` the projector onto the directions the constraints leave free, `y_0` the prescribed
//! normal moves ([`super::linear::System::project`]). No penalty enters the converged answer;
//! the contact forces are the reactions.
//!
//! The iteration stops when the active set repeats, the projected residual is within the
//! tolerance (relative to the force scale: the contact forces, with a floor at the round-off
//! of the assembled forces), every active node is on the sphere within the gap tolerance and
//! no inactive node is inside it. A backtracking line search on the residual and gap norms
//! keeps the iteration from wandering; an iterate with an inverted element is refused.
//!
//! Surfaces coarser than the sphere also carry contact points inside their triangles
//! (augmented Lagrangian, [`super::points`]), whose multipliers stay frozen here and are
//! updated outside ([`super::Indentation`]).
//!
//! Owns: the iteration. Uses: [`super::linear`] for the systems, [`crate::element`] for
//! forces and tangents, [`crate::statics::StaticTerm`] for the points' term.

use glam::{DMat3, DVec3};

use super::linear::{NodeConstraint, System, outer};
use super::points::SphereContact;
use crate::ModelError;
use crate::element::FemModel;
use crate::statics::StaticTerm;

/// Settings of one solve ([`Newton::solve`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Settings {
    /// Relative tolerance on the projected residual against the force scale.
    pub rel_tol: f64,
    /// Absolute residual tolerance, N.
    pub abs_tol_n: f64,
    /// Largest number of iterations.
    pub max_iterations: usize,
    /// Gap tolerance, m.
    pub gap_tol_m: f64,
    /// Relative residual of the linear solves (inexact Newton's forcing term).
    pub linear_rel_tol: f64,
    /// Whether the tangent carries the sphere's curvature term at the active nodes.
    pub curvature_stiffness: bool,
}

/// Round-off allowance: the residual cannot go below about this many machine epsilons of the
/// size of the terms it sums ([`System::abs_product_norm`]).
const ROUNDOFF_FACTOR: f64 = 256.0;

/// What a converged solve reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Converged {
    /// Newton iterations.
    pub iterations: usize,
    /// Final projected residual, N.
    pub residual_n: f64,
    /// The tolerance it met, N.
    pub tolerance_n: f64,
}

/// The contact nodes and the iteration's state.
pub(super) struct Newton<'a> {
    fem: &'a FemModel,
    /// The linear systems (pattern, preconditioner, statistics).
    pub sys: System,
    /// Touchable nodes that are not fully constrained.
    pub nodes: Vec<u32>,
    /// 1 in each free component of each contact node, 0 in a constrained one.
    free: Vec<DVec3>,
    /// Rest diagonal stiffness per contact node, N/m (the active-set rule's `c_i`).
    scale: Vec<f64>,
    /// Whether each contact node is in contact.
    pub active: Vec<bool>,
    /// Contact force of each contact node, N (zero when inactive).
    pub lambda: Vec<f64>,
    /// The sphere's centre and radius, m.
    pub centre: DVec3,
    pub radius: f64,
    /// Contact points inside coarse triangles (augmented Lagrangian; may be empty).
    pub points: SphereContact,
}

/// Geometry of a contact node against the sphere.
#[derive(Debug, Clone, Copy)]
struct NodeGeometry {
    /// Gap `R - |x - c|` (positive inside the sphere), m.
    g: f64,
    /// Distance from the centre, m.
    rho: f64,
    /// Outward normal.
    n: DVec3,
    /// Constrained direction: `n` in the free components, normalised (zero when the node
    /// cannot move along `n`).
    m: DVec3,
    /// `m . n`.
    mn: f64,
}

impl<'a> Newton<'a> {
    /// The contact nodes of `triangles` (the touchable surface) of `fem`, with the points of
    /// its coarse triangles.
    pub fn new(
        fem: &'a FemModel,
        triangles: &[[u32; 3]],
        points: SphereContact,
    ) -> Result<Self, ModelError> {
        let sys = System::new(fem)?;
        let mut nodes: Vec<u32> = triangles.iter().flatten().copied().collect();
        nodes.sort_unstable();
        nodes.dedup();
        let masks = fem.constraints();
        nodes.retain(|&i| masks[i as usize] != crate::element::CLAMPED);
        let free: Vec<DVec3> = nodes
            .iter()
            .map(|&i| {
                let m = masks[i as usize];
                DVec3::new(
                    f64::from(u8::from(m & 1 == 0)),
                    f64::from(u8::from(m & 2 == 0)),
                    f64::from(u8::from(m & 4 == 0)),
                )
            })
            .collect();
        let diag = fem.rest_diagonal_blocks();
        let scale = nodes
            .iter()
            .map(|&i| {
                let k = diag[i as usize];
                (k.x_axis.x + k.y_axis.y + k.z_axis.z) / 3.0
            })
            .collect();
        let count = nodes.len();
        Ok(Self {
            fem,
            sys,
            nodes,
            free,
            scale,
            active: vec![false; count],
            lambda: vec![0.0; count],
            centre: DVec3::ZERO,
            radius: points.radius_m,
            points,
        })
    }

    fn geometry(&self, k: usize, x: &[DVec3]) -> NodeGeometry {
        let d = x[self.nodes[k] as usize] - self.centre;
        let rho = d.length();
        let n = if rho > 0.0 { d / rho } else { DVec3::Z };
        let cn = n * self.free[k];
        let len = cn.length();
        // A node that can hardly move along the normal (a roller plane nearly tangent to
        // the sphere) is not constrained: its other nodes' constraints hold it.
        let (m, mn) = if len > 0.1 {
            (cn / len, len)
        } else {
            (DVec3::ZERO, 0.0)
        };
        NodeGeometry {
            g: self.radius - rho,
            rho,
            n,
            m,
            mn,
        }
    }

    /// `f_int(x) + f_points(x)`, N per node.
    fn residual(&self, x: &[DVec3], r: &mut Vec<DVec3>) {
        r.clear();
        r.resize(x.len(), DVec3::ZERO);
        self.fem.add_internal_forces(x, None, r);
        self.points.add_forces(x, r);
    }

    /// Force of the body on the sphere, N: minus the active nodes' contact forces and the
    /// points' multipliers (after Uzawa's update, the forces the positions are in equilibrium
    /// with).
    pub fn force_on_sphere_n(&self, x: &[DVec3]) -> DVec3 {
        let mut f = self.points.multiplier_force_n(x);
        for k in 0..self.nodes.len() {
            if self.active[k] {
                f -= self.geometry(k, x).n * self.lambda[k];
            }
        }
        f
    }

    /// Largest penetration of a contact node, m.
    pub fn max_penetration_m(&self, x: &[DVec3]) -> f64 {
        (0..self.nodes.len())
            .map(|k| self.geometry(k, x).g)
            .fold(0.0, f64::max)
    }

    /// The norm of the projected residual, the merit, the magnitude of the nodes' resultant
    /// contact force (the force scale) and whether the
    /// gaps are within `gap_tol`, for the active set `active` (the reactions of its nodes are
    /// written to `self.lambda`).
    fn measure(
        &mut self,
        x: &[DVec3],
        r: &[DVec3],
        active: &[bool],
        gap_tol: f64,
    ) -> (f64, f64, f64, bool) {
        let masks = self.fem.constraints();
        // |P r|^2 node by node: the free components, minus the constrained direction at the
        // active nodes (per node, so that the reactions do not swamp the rest by
        // cancellation).
        let mut constrained = vec![DVec3::ZERO; r.len()];
        let (mut gap2, mut force, mut gaps_ok) = (0.0, DVec3::ZERO, true);
        for (k, &is_active) in active.iter().enumerate() {
            let geo = self.geometry(k, x);
            let i = self.nodes[k] as usize;
            if is_active {
                let along = geo.m.dot(r[i]);
                constrained[i] = geo.m;
                self.lambda[k] = -along / geo.mn;
                force += geo.n * self.lambda[k];
                gap2 += (self.scale[k] * geo.g).powi(2);
                gaps_ok &= geo.g.abs() <= gap_tol;
            } else {
                self.lambda[k] = 0.0;
                if geo.mn > 0.0 && geo.g > 0.0 {
                    gap2 += (self.scale[k] * geo.g).powi(2);
                    gaps_ok &= geo.g <= gap_tol;
                }
            }
        }
        let mut res2 = 0.0;
        for (i, ri) in r.iter().enumerate() {
            let m = masks[i];
            let mut v = *ri;
            for c in 0..3 {
                if m & (1 << c) != 0 {
                    v[c] = 0.0;
                }
            }
            v -= constrained[i] * constrained[i].dot(v);
            res2 += v.length_squared();
        }
        let res = res2.max(0.0).sqrt();
        (res, res * res + gap2, force.length(), gaps_ok)
    }

    /// Newton iterations from `x` to the equilibrium against the sphere at `self.centre`.
    /// Returns the iterations, or why it failed (no convergence within the settings'
    /// iterations, an iterate with inverted elements only, a failed factorisation).
    pub fn solve(&mut self, x: &mut [DVec3], s: &Settings) -> Result<Converged, String> {
        let fem = self.fem;
        let n_nodes = fem.node_count();
        let mut r = Vec::with_capacity(n_nodes);
        let mut trial = x.to_vec();
        let mut r_trial = Vec::with_capacity(n_nodes);
        let mut floor = 0.0f64;
        let mut last = (f64::INFINITY, 0.0);
        let points_scale = |p: &SphereContact, x: &[DVec3]| p.force_on_sphere_n(x).length();
        self.residual(x, &mut r);
        for it in 0..=s.max_iterations {
            // The active set this iterate implies (primal-dual rule with the reactions).
            let current = self.active.clone();
            self.measure(x, &r, &current, s.gap_tol_m);
            let mut next = current.clone();
            for (k, on) in next.iter_mut().enumerate() {
                let geo = self.geometry(k, x);
                *on = geo.mn > 0.0 && self.lambda[k] + self.scale[k] * geo.g > 0.0;
            }
            let (res, merit, force, gaps_ok) = self.measure(x, &r, &next, s.gap_tol_m);
            let scale = force + points_scale(&self.points, x);
            let tol = (s.rel_tol * scale).max(s.abs_tol_n).max(floor);
            last = (res, tol);
            let stable = next == current;
            self.active = next;
            if stable && res <= tol && gaps_ok {
                return Ok(Converged {
                    iterations: it,
                    residual_n: res,
                    tolerance_n: tol,
                });
            }
            if it == s.max_iterations {
                break;
            }
            let dx = self.step(x, &r, s, &mut floor).map_err(|e| e.to_string())?;
            // Backtracking on the merit (projected residual and gaps), refusing inverted
            // states; the best of the tried steps is taken.
            let mut best: Option<(f64, f64)> = None;
            let mut alpha = 1.0;
            for _ in 0..5 {
                for i in 0..n_nodes {
                    trial[i] = x[i] + dx[i] * alpha;
                }
                if fem.inverted_elements(&trial) == 0 {
                    self.residual(&trial, &mut r_trial);
                    let active = self.active.clone();
                    let (_, m, _, _) = self.measure(&trial, &r_trial, &active, s.gap_tol_m);
                    if m.is_finite() && best.is_none_or(|(_, b)| m < b) {
                        best = Some((alpha, m));
                    }
                    if m.is_finite() && m <= (1.0 - 1e-4 * alpha) * merit {
                        break;
                    }
                }
                alpha *= 0.5;
            }
            let Some((alpha, _)) = best else {
                return Err(format!(
                    "every step of Newton iteration {} inverts an element",
                    it + 1
                ));
            };
            for i in 0..n_nodes {
                x[i] += dx[i] * alpha;
            }
            self.residual(x, &mut r);
        }
        Err(format!(
            "Newton stopped after {} iterations with residual {:.3e} N (tolerance {:.3e} N)",
            s.max_iterations, last.0, last.1
        ))
    }

    /// The Newton step at `x` for the current active set (node space, m); updates the
    /// round-off floor of the residual from the assembled tangent.
    fn step(
        &mut self,
        x: &[DVec3],
        r: &[DVec3],
        s: &Settings,
        floor: &mut f64,
    ) -> Result<Vec<DVec3>, ModelError> {
        let fem = self.fem;
        self.sys.assemble_cells(fem, x);
        let mut extra: Vec<(u32, u32, DMat3)> = Vec::new();
        self.points
            .for_each_stiffness_block(x, &mut |i, j, k| extra.push((i, j, k)));
        for (i, j, k) in extra {
            self.sys.add_block(i, j, k)?;
        }
        let mut constraints = Vec::new();
        let mut y0 = vec![DVec3::ZERO; x.len()];
        for k in 0..self.nodes.len() {
            if !self.active[k] {
                continue;
            }
            let geo = self.geometry(k, x);
            let i = self.nodes[k];
            if s.curvature_stiffness {
                let t = DMat3::IDENTITY - outer(geo.n, geo.n);
                self.sys
                    .add_block(i, i, t * (-self.lambda[k] / geo.rho.max(1e-300)))?;
            }
            y0[i as usize] = geo.m * (geo.g / geo.mn);
            constraints.push(NodeConstraint {
                node: i,
                m: geo.m,
                diag: self.scale[k],
            });
        }
        // r - K y0 with the unprojected tangent (y0 lives on the active nodes only).
        let mut rhs_nodes = r.to_vec();
        for c in &constraints {
            let i = c.node;
            let yi = y0[i as usize];
            for j in self.sys.neighbours(i) {
                let b = self.sys.block_index(i, j).expect("a neighbour");
                // (K y0)_j += K_ji y0_i = K_ij^T y0_i.
                rhs_nodes[j as usize] -= self.sys.blocks[b].transpose() * yi;
            }
        }
        for c in &constraints {
            let v = &mut rhs_nodes[c.node as usize];
            *v -= c.m * c.m.dot(*v);
        }
        self.sys.project(&constraints);
        self.sys.fill_values();
        let dof = &self.sys.dof;
        let mut b = vec![0.0; self.sys.nfree];
        let mut u = vec![0.0; self.sys.nfree];
        for i in 0..x.len() {
            for c in 0..3 {
                let d = dof[3 * i + c];
                if d != usize::MAX {
                    b[d] = rhs_nodes[i][c];
                    u[d] = x[i][c] - fem.rest()[i][c];
                }
            }
        }
        *floor = ROUNDOFF_FACTOR * f64::EPSILON * self.sys.abs_product_norm(&u);
        let mut z = vec![0.0; self.sys.nfree];
        self.sys.solve(&b, &mut z, s.linear_rel_tol)?;
        // dx = y0 + P z: the constrained directions get exactly the prescribed move.
        let dof = &self.sys.dof;
        let mut pz = vec![DVec3::ZERO; x.len()];
        for (i, v) in pz.iter_mut().enumerate() {
            for c in 0..3 {
                let k = dof[3 * i + c];
                if k != usize::MAX {
                    v[c] = z[k];
                }
            }
        }
        for c in &constraints {
            let v = &mut pz[c.node as usize];
            *v -= c.m * c.m.dot(*v);
        }
        Ok(y0.iter().zip(&pz).map(|(a, b)| *a + *b).collect())
    }
}
