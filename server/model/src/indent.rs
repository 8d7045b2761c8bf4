//! Static indentation by a rigid sphere: the reference the probe forces are measured against
//! and the solver behind `haptic-solve --indent`.
//!
//! A rigid frictionless sphere of radius `R` with centre `c` may not be penetrated by the
//! body's candidate surface nodes: `g_i = R - |x_i - c| <= 0` (node-to-sphere contact). The
//! constraint enters the static equilibrium ([`crate::statics`]) by an augmented Lagrangian:
//! for multipliers `lambda_i >= 0` (N) and per-node penalties `kappa_i` (N/m) the contact
//! energy is
//!
//! `E_c(x) = sum_i (max(0, lambda_i + kappa_i g_i)^2 - lambda_i^2) / (2 kappa_i)`,
//!
//! its force on node `i` is `p_i n_i` with the contact pressure force `p_i = max(0, lambda_i +
//! kappa_i g_i)` and the outward normal `n_i = (x_i - c) / |x_i - c|`, and its stiffness is
//! `kappa_i n n^T - (p_i / |x_i - c|) (I - n n^T)` (the second term is the sphere's curvature).
//! Newton solves the equilibrium with the multipliers frozen, then Uzawa's update
//! `lambda_i <- p_i` follows, until every node is outside the sphere or on it within the gap
//! tolerance and no node in contact pulls (see [`IndentParams`]). The penalty only sets how
//! fast this converges, not the answer: the converged forces are those of the exact
//! constraint. There is no silent iteration cap: a depth that does not converge is an error
//! that names it.
//!
//! Depths are measured from first contact along the indentation direction: the sphere centre
//! starts at `from` (clear of the body) and the depth-zero centre is where the sphere first
//! touches a candidate node of the rest configuration ([`first_contact_distance`]).
//!
//! Owns: the sphere contact term and the indentation driver. Uses: [`crate::statics`] (the
//! Newton solver), [`crate::element`], [`crate::material`] (principal stretches for error
//! messages). Not used by the real-time path.

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::element::FemModel;
use crate::material::corotational::symmetric_eigen;
use crate::statics::{StaticParams, StaticTerm, solve_static_with};

/// The augmented-Lagrangian contact term of a rigid sphere over candidate nodes (see the
/// module documentation).
#[derive(Debug, Clone)]
pub struct SphereContact {
    /// Sphere centre, m.
    pub centre_m: DVec3,
    /// Sphere radius, m.
    pub radius_m: f64,
    /// Candidate node indices (the touchable surface).
    pub nodes: Vec<u32>,
    /// Penalty per candidate, N/m.
    pub penalty_n_per_m: Vec<f64>,
    /// Multiplier per candidate (the contact force it carries), N.
    pub multiplier_n: Vec<f64>,
}

impl SphereContact {
    /// Distance from the centre and outward normal of node `x`; the normal is the direction
    /// away from the centre (any unit vector when `x` is at the centre).
    fn geometry(&self, x: DVec3) -> (f64, DVec3) {
        let d = x - self.centre_m;
        let rho = d.length();
        let n = if rho > 0.0 { d / rho } else { DVec3::Z };
        (rho, n)
    }

    /// Contact force magnitude `p_k = max(0, lambda_k + kappa_k g_k)` of candidate `k`, N.
    fn pressure_force(&self, k: usize, rho: f64) -> f64 {
        (self.multiplier_n[k] + self.penalty_n_per_m[k] * (self.radius_m - rho)).max(0.0)
    }

    /// Force of the body on the sphere, `-sum p_k n_k` (N), at positions `x`.
    pub fn force_on_sphere_n(&self, x: &[DVec3]) -> DVec3 {
        let mut f = DVec3::ZERO;
        for (k, &i) in self.nodes.iter().enumerate() {
            let (rho, n) = self.geometry(x[i as usize]);
            f -= n * self.pressure_force(k, rho);
        }
        f
    }
}

impl StaticTerm for SphereContact {
    fn energy(&self, x: &[DVec3]) -> f64 {
        let mut e = 0.0;
        for (k, &i) in self.nodes.iter().enumerate() {
            let (rho, _) = self.geometry(x[i as usize]);
            let p = self.pressure_force(k, rho);
            let l = self.multiplier_n[k];
            e += (p * p - l * l) / (2.0 * self.penalty_n_per_m[k]);
        }
        e
    }

    fn add_forces(&self, x: &[DVec3], f: &mut [DVec3]) {
        for (k, &i) in self.nodes.iter().enumerate() {
            let (rho, n) = self.geometry(x[i as usize]);
            f[i as usize] += n * self.pressure_force(k, rho);
        }
    }

    fn for_each_stiffness_block(&self, x: &[DVec3], add: &mut dyn FnMut(u32, u32, DMat3)) {
        for (k, &i) in self.nodes.iter().enumerate() {
            let (rho, n) = self.geometry(x[i as usize]);
            let p = self.pressure_force(k, rho);
            if p > 0.0 {
                let nn = DMat3::from_cols(n * n.x, n * n.y, n * n.z);
                let k_block =
                    nn * self.penalty_n_per_m[k] - (DMat3::IDENTITY - nn) * (p / rho.max(1e-300));
                add(i, i, k_block);
            }
        }
    }
}

/// Settings of [`indent`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndentParams {
    /// Penalty per candidate node as a multiple of `mu l_i`, with `mu` the material's shear
    /// modulus and `l_i` the square root of the node's tributary surface area (default 100:
    /// the gap shrinks about a hundredfold per multiplier update).
    pub penalty_factor: f64,
    /// Gap tolerance as a fraction of the depth: every candidate must be outside the sphere or
    /// within this of its surface, and a node carrying force within it of the surface
    /// (default 1e-4; the force error it allows is about 1.5 times this for a Hertzian
    /// contact). Never below `1e-7 R`.
    pub gap_tol: f64,
    /// Largest number of multiplier updates per depth (default 40).
    pub max_augmentations: usize,
    /// Largest number of halvings of a depth increment whose Newton solve fails (default 6).
    pub max_bisections: usize,
    /// Newton settings of each solve with frozen multipliers.
    pub newton: StaticParams,
}

impl Default for IndentParams {
    fn default() -> Self {
        Self {
            penalty_factor: 100.0,
            gap_tol: 1e-4,
            max_augmentations: 40,
            max_bisections: 6,
            newton: StaticParams {
                rel_tol: 1e-9,
                ..StaticParams::default()
            },
        }
    }
}

/// Where the sphere goes: its radius, a start centre clear of the body and a direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Indenter {
    /// Sphere radius, m.
    pub radius_m: f64,
    /// Start centre, m (the sphere there must not overlap the body).
    pub from_m: DVec3,
    /// Indentation direction (normalised by [`indent`]).
    pub direction: DVec3,
}

/// The solution at one depth.
#[derive(Debug, Clone, PartialEq)]
pub struct IndentPoint {
    /// Depth below first contact, m.
    pub depth_m: f64,
    /// Sphere centre, m.
    pub centre_m: DVec3,
    /// Force of the body on the sphere (what a probe there feels), N.
    pub force_on_sphere_n: DVec3,
    /// Contact radius, m: over the surface edges that leave the contact (one node carrying
    /// force, one not), the mean distance from the indentation axis of the edges' midpoints
    /// (resolution: about half an edge; zero without contact).
    pub contact_radius_m: f64,
    /// Candidate nodes carrying force.
    pub nodes_in_contact: usize,
    /// Largest penetration of a candidate into the sphere, m (at most the gap tolerance).
    pub max_penetration_m: f64,
    /// Multiplier updates at this depth (over its sub-increments).
    pub augmentations: usize,
    /// Newton iterations at this depth.
    pub newton_iterations: usize,
    /// Node positions, m.
    pub x_m: Vec<DVec3>,
}

/// Distance along `direction` (unit) from `from` at which a sphere of radius `radius_m` first
/// touches one of the points `nodes` of `x`, or `None` when the ray misses them all.
///
/// # Errors
/// [`ModelError::InvalidInput`] when the sphere at `from` already contains a node.
pub fn first_contact_distance(
    x: &[DVec3],
    nodes: &[u32],
    from: DVec3,
    direction: DVec3,
    radius_m: f64,
) -> Result<Option<f64>, ModelError> {
    let mut best: Option<f64> = None;
    for &i in nodes {
        let w = x[i as usize] - from;
        let c = w.length_squared() - radius_m * radius_m;
        if c < 0.0 {
            return Err(ModelError::InvalidInput(format!(
                "the sphere at the start point {from} m already overlaps the body (node {i} is \
                 {:.4e} m from its centre, radius {radius_m:.4e} m): start farther out",
                w.length()
            )));
        }
        let b = w.dot(direction);
        let disc = b * b - c;
        if b > 0.0 && disc >= 0.0 {
            let t = b - disc.sqrt();
            best = Some(best.map_or(t, |s: f64| s.min(t)));
        }
    }
    Ok(best)
}

/// Candidate nodes of a triangle surface and their tributary areas (a third of each adjacent
/// triangle's area), m^2, in the positions `x`.
pub fn surface_nodes_and_areas(triangles: &[[u32; 3]], x: &[DVec3]) -> (Vec<u32>, Vec<f64>) {
    let mut area = vec![0.0; x.len()];
    let mut used = vec![false; x.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| x[i as usize]);
        let third = (b - a).cross(c - a).length() / 6.0;
        for &i in t {
            area[i as usize] += third;
            used[i as usize] = true;
        }
    }
    let nodes: Vec<u32> = (0..x.len() as u32).filter(|&i| used[i as usize]).collect();
    let areas = nodes.iter().map(|&i| area[i as usize]).collect();
    (nodes, areas)
}

/// Smallest principal stretch over the integration points of `fem` at positions `x` (the
/// square root of the smallest eigenvalue of `C = F^T F`).
pub fn min_principal_stretch(fem: &FemModel, x: &[DVec3]) -> f64 {
    let u: Vec<DVec3> = x.iter().zip(fem.rest()).map(|(a, b)| *a - *b).collect();
    let mut min = f64::INFINITY;
    for q in 0..fem.integration_point_count() {
        let f = DMat3::IDENTITY + fem.ip_field_gradient(q, &u);
        let (_, values) = symmetric_eigen(&(f.transpose() * f));
        min = min.min(values.min_element().max(0.0).sqrt());
    }
    min
}

/// The static indentation of `fem` by a rigid frictionless sphere at each of `depths_m`
/// (increasing, m below first contact), with `triangles` the touchable surface (its nodes are
/// the contact candidates). `progress` is called after each depth. Each depth starts from the
/// previous one's solution; an increment whose Newton solve fails is halved up to
/// `params.max_bisections` times.
///
/// # Errors
/// [`ModelError::InvalidInput`] for a non-finite or non-increasing depth list, a zero
/// direction, a start point overlapping the body or a ray that misses it;
/// [`ModelError::NoConvergence`] naming the depth that failed, the last converged depth, why
/// (Newton's message or the multiplier updates' gap) and the smallest principal stretch of the
/// last converged state (St. Venant-Kirchhoff loses stability below `1/sqrt(3)`).
pub fn indent(
    fem: &FemModel,
    triangles: &[[u32; 3]],
    indenter: &Indenter,
    depths_m: &[f64],
    params: &IndentParams,
    progress: &mut dyn FnMut(&IndentPoint),
) -> Result<Vec<IndentPoint>, ModelError> {
    let dir = indenter.direction.normalize_or_zero();
    if dir == DVec3::ZERO || !dir.is_finite() {
        return Err(ModelError::InvalidInput(
            "the indentation direction must be a finite nonzero vector".into(),
        ));
    }
    let r = indenter.radius_m;
    if !(r > 0.0) || !r.is_finite() || !indenter.from_m.is_finite() {
        return Err(ModelError::InvalidInput(
            "the sphere radius must be positive and the start point finite".into(),
        ));
    }
    let mut prev = 0.0;
    for &d in depths_m {
        if !d.is_finite() || d < prev {
            return Err(ModelError::InvalidInput(format!(
                "depths must be finite, non-negative and increasing: got {depths_m:?} m"
            )));
        }
        prev = d;
    }
    let (nodes, areas) = surface_nodes_and_areas(triangles, fem.rest());
    let t0 =
        first_contact_distance(fem.rest(), &nodes, indenter.from_m, dir, r)?.ok_or_else(|| {
            ModelError::InvalidInput(format!(
                "a sphere of radius {r:.4e} m moving from {} m along {dir} misses the touchable \
                 surface",
                indenter.from_m
            ))
        })?;
    let mu = fem.material().mu_pa;
    let mut contact = SphereContact {
        centre_m: indenter.from_m + dir * t0,
        radius_m: r,
        penalty_n_per_m: areas
            .iter()
            .map(|a| params.penalty_factor * mu * a.sqrt())
            .collect(),
        multiplier_n: vec![0.0; nodes.len()],
        nodes,
    };
    let edges = surface_edges(triangles);
    let mut x = fem.rest().to_vec();
    let mut reached = 0.0;
    let mut out = Vec::with_capacity(depths_m.len());
    for &depth in depths_m {
        let (mut augmentations, mut newton_iterations) = (0, 0);
        let mut halvings: usize = 0;
        while reached < depth {
            let step = (depth - reached) * 0.5f64.powi(halvings as i32);
            let target = if halvings == 0 { depth } else { reached + step };
            let backup = (x.clone(), contact.multiplier_n.clone());
            contact.centre_m = indenter.from_m + dir * (t0 + target);
            let gap_tol = (params.gap_tol * target).max(1e-7 * r);
            match augment(fem, &mut contact, &mut x, gap_tol, params) {
                Ok((a, n)) => {
                    augmentations += a;
                    newton_iterations += n;
                    reached = target;
                    halvings = halvings.saturating_sub(1);
                }
                Err(_) if halvings < params.max_bisections => {
                    (x, contact.multiplier_n) = backup;
                    halvings += 1;
                }
                Err(why) => {
                    (x, contact.multiplier_n) = backup;
                    return Err(ModelError::NoConvergence(format!(
                        "indentation depth {depth:.4e} m failed at {target:.4e} m after halving \
                         the increment {halvings} times (last converged depth {reached:.4e} m, \
                         smallest principal stretch there {:.3}): {why}",
                        min_principal_stretch(fem, &x)
                    )));
                }
            }
        }
        // At depth zero (or a repeated depth) the loop did not run: solve in place.
        if augmentations == 0 {
            contact.centre_m = indenter.from_m + dir * (t0 + depth);
            let gap_tol = (params.gap_tol * depth).max(1e-7 * r);
            let (a, n) = augment(fem, &mut contact, &mut x, gap_tol, params).map_err(|why| {
                ModelError::NoConvergence(format!("indentation depth {depth:.4e} m: {why}"))
            })?;
            augmentations += a;
            newton_iterations += n;
        }
        let point = measure(
            &contact,
            &x,
            &edges,
            dir,
            depth,
            augmentations,
            newton_iterations,
        );
        progress(&point);
        out.push(point);
    }
    Ok(out)
}

/// Multiplier updates with Newton solves until the gap criterion holds: returns the updates
/// and Newton iterations used, or why it failed. On success the multipliers are those the
/// final positions are in equilibrium with.
fn augment(
    fem: &FemModel,
    contact: &mut SphereContact,
    x: &mut [DVec3],
    gap_tol: f64,
    params: &IndentParams,
) -> Result<(usize, usize), String> {
    let mut newton = 0;
    let mut worst = f64::INFINITY;
    for a in 1..=params.max_augmentations {
        let rep = solve_static_with(fem, &[], Some(&*contact), x, &params.newton)
            .map_err(|e| format!("Newton with frozen contact multipliers: {e}"))?;
        newton += rep.iterations;
        // Gap criterion: no node inside the sphere beyond the tolerance; a node carrying force
        // is on the sphere within it (complementarity).
        worst = 0.0f64;
        for (k, &i) in contact.nodes.iter().enumerate() {
            let (rho, _) = contact.geometry(x[i as usize]);
            let g = contact.radius_m - rho;
            let p = contact.pressure_force(k, rho);
            let violation = if p > 0.0 { g.abs() } else { g.max(0.0) };
            worst = worst.max(violation);
        }
        // Uzawa's update. When the criterion holds this stores the forces the positions are
        // in equilibrium with (what is reported) and warm-starts the next depth.
        for (k, &i) in contact.nodes.iter().enumerate() {
            let (rho, _) = contact.geometry(x[i as usize]);
            contact.multiplier_n[k] = contact.pressure_force(k, rho);
        }
        if worst <= gap_tol {
            return Ok((a, newton));
        }
    }
    Err(format!(
        "the contact gap did not close in {} multiplier updates (worst {worst:.3e} m, tolerance \
         {gap_tol:.3e} m)",
        params.max_augmentations
    ))
}

/// The unique undirected edges of a triangle surface.
fn surface_edges(triangles: &[[u32; 3]]) -> Vec<(u32, u32)> {
    let mut edges: Vec<(u32, u32)> = triangles
        .iter()
        .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    edges.sort_unstable();
    edges.dedup();
    edges
}

/// The reported quantities at one converged depth.
fn measure(
    contact: &SphereContact,
    x: &[DVec3],
    edges: &[(u32, u32)],
    dir: DVec3,
    depth_m: f64,
    augmentations: usize,
    newton_iterations: usize,
) -> IndentPoint {
    let n_nodes = x.len();
    let mut carries = vec![false; n_nodes];
    let mut in_contact = 0;
    let mut max_pen = 0.0f64;
    let mut force = DVec3::ZERO;
    for (k, &i) in contact.nodes.iter().enumerate() {
        let (rho, n) = contact.geometry(x[i as usize]);
        max_pen = max_pen.max(contact.radius_m - rho);
        let p = contact.multiplier_n[k];
        if p > 0.0 {
            carries[i as usize] = true;
            in_contact += 1;
        }
        force -= n * p;
    }
    let axis_dist = |i: u32| {
        let d = x[i as usize] - contact.centre_m;
        (d - dir * d.dot(dir)).length()
    };
    let (mut sum, mut crossing) = (0.0, 0usize);
    for &(a, b) in edges {
        if carries[a as usize] != carries[b as usize] {
            sum += 0.5 * (axis_dist(a) + axis_dist(b));
            crossing += 1;
        }
    }
    let contact_radius_m = if crossing == 0 {
        0.0
    } else {
        sum / crossing as f64
    };
    IndentPoint {
        depth_m,
        centre_m: contact.centre_m,
        force_on_sphere_n: force,
        contact_radius_m,
        nodes_in_contact: in_contact,
        max_penetration_m: max_pen.max(0.0),
        augmentations,
        newton_iterations,
        x_m: x.to_vec(),
    }
}
