//! Static indentation by a rigid sphere: the reference the probe forces are measured against
//! and the solver behind `haptic-solve --indent`.
//!
//! A rigid frictionless sphere of radius `R` with centre `c` may not be penetrated by the
//! body's touchable surface. The surface is sampled by contact points
//! ([`contact_points`]): each touchable triangle is split into `L^2` equal sub-triangles and
//! carries a point at each sub-triangle's centroid, `x_q = sum_a b_qa x_a` over the triangle's
//! three nodes with barycentric weights `b_qa`, and `L` is chosen so that the points are at
//! most `R / 4` apart (so the sphere cannot slip between the nodes of a coarse mesh, as it does
//! with node-to-sphere contact on the built-in `lv`). The constraint is
//! `g_q = R - |x_q - c| <= 0` and enters the static equilibrium ([`crate::statics`]) by an
//! augmented Lagrangian: for multipliers `lambda_q >= 0` (N) and per-point penalties `kappa_q`
//! (N/m) the contact energy is
//!
//! `E_c(x) = sum_q (max(0, lambda_q + kappa_q g_q)^2 - lambda_q^2) / (2 kappa_q)`,
//!
//! its force on node `a` of point `q` is `b_qa p_q n_q` with the contact pressure force
//! `p_q = max(0, lambda_q + kappa_q g_q)` and the outward normal `n_q = (x_q - c) / |x_q - c|`,
//! and its stiffness block between nodes `a` and `b` is `b_qa b_qb (kappa_q n n^T - (p_q /
//! |x_q - c|) (I - n n^T))` (the second term is the sphere's curvature). Newton solves the
//! equilibrium with the multipliers frozen, then Uzawa's update `lambda_q <- p_q` follows,
//! until every point is outside the sphere or on it within the gap tolerance and no point in
//! contact pulls (see [`IndentParams`]). The penalty only sets how
//! fast this converges, not the answer: the converged forces are those of the exact
//! constraint. There is no silent iteration cap: a depth that does not converge is an error
//! that names it.
//!
//! Depths are measured from first contact along the indentation direction: the sphere centre
//! starts at `from` (clear of the body) and the depth-zero centre is where the sphere first
//! touches a node or a contact point of the rest configuration ([`first_contact_distance`];
//! exact on flat triangles, within the point spacing where the surface folds at an edge).
//!
//! Owns: the sphere contact term and the indentation driver. Uses: [`crate::statics`] (the
//! Newton solver), [`crate::element`], [`crate::material`] (principal stretches for error
//! messages). Not used by the real-time path.

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::element::FemModel;
use crate::material::corotational::symmetric_eigen;
use crate::statics::{StaticParams, StaticTerm, solve_static_with};

/// A point of a touchable triangle that the sphere may not pass: `x_q = sum_a bary[a]
/// x[nodes[a]]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactPoint {
    /// The triangle's nodes.
    pub nodes: [u32; 3],
    /// Barycentric weights (sum 1).
    pub bary: [f64; 3],
    /// Share of the triangle's area the point stands for (`1 / L^2`).
    pub area_fraction: f64,
}

impl ContactPoint {
    /// The point's position, m.
    pub fn position(&self, x: &[DVec3]) -> DVec3 {
        (0..3)
            .map(|a| x[self.nodes[a] as usize] * self.bary[a])
            .sum()
    }

    /// The area it stands for at positions `x`, m^2.
    pub fn area_m2(&self, x: &[DVec3]) -> f64 {
        let [a, b, c] = self.nodes.map(|i| x[i as usize]);
        0.5 * (b - a).cross(c - a).length() * self.area_fraction
    }
}

/// Largest number of contact points [`contact_points`] makes (about 200 MB of them).
pub const MAX_CONTACT_POINTS: usize = 4_000_000;

/// Contact points of a triangle surface (see the module documentation): each triangle split
/// into `L^2` sub-triangles, `L` the smallest integer with `longest edge / L <= spacing_m`
/// (at least 1, at most 16), a point at each sub-triangle's centroid.
///
/// # Errors
/// [`ModelError::InvalidInput`] when that makes more than [`MAX_CONTACT_POINTS`] points (a
/// sphere far smaller than the surface's triangles).
pub fn contact_points(
    triangles: &[[u32; 3]],
    x: &[DVec3],
    spacing_m: f64,
) -> Result<Vec<ContactPoint>, ModelError> {
    let split = |t: &[u32; 3]| {
        let [a, b, c] = t.map(|i| x[i as usize]);
        let longest = (b - a).length().max((c - b).length()).max((a - c).length());
        ((longest / spacing_m).ceil() as usize).clamp(1, 16)
    };
    let needed: usize = triangles.iter().map(|t| split(t).pow(2)).sum();
    if needed > MAX_CONTACT_POINTS {
        return Err(ModelError::InvalidInput(format!(
            "sampling {} touchable triangles at {spacing_m:.3e} m needs {needed} contact points \
             (at most {MAX_CONTACT_POINTS}): the sphere is far smaller than the triangles",
            triangles.len()
        )));
    }
    let mut out = Vec::with_capacity(needed);
    for &t in triangles {
        let l = split(&t);
        let lf = l as f64;
        let area_fraction = 1.0 / (lf * lf);
        // Sub-triangles of the lattice with steps (i, j): "up" ones with vertices (i, j),
        // (i + 1, j), (i, j + 1), and "down" ones with (i + 1, j), (i + 1, j + 1), (i, j + 1).
        for i in 0..l {
            for j in 0..l - i {
                let (fi, fj) = (i as f64, j as f64);
                let mut push = |u: f64, v: f64| {
                    out.push(ContactPoint {
                        nodes: t,
                        bary: [1.0 - u - v, u, v],
                        area_fraction,
                    });
                };
                push((fi + 1.0 / 3.0) / lf, (fj + 1.0 / 3.0) / lf);
                if i + j + 1 < l {
                    push((fi + 2.0 / 3.0) / lf, (fj + 2.0 / 3.0) / lf);
                }
            }
        }
    }
    Ok(out)
}

/// The augmented-Lagrangian contact term of a rigid sphere over contact points (see the
/// module documentation).
#[derive(Debug, Clone)]
pub struct SphereContact {
    /// Sphere centre, m.
    pub centre_m: DVec3,
    /// Sphere radius, m.
    pub radius_m: f64,
    /// Contact points of the touchable surface.
    pub points: Vec<ContactPoint>,
    /// Penalty per point, N/m.
    pub penalty_n_per_m: Vec<f64>,
    /// Multiplier per point (the contact force it carries), N.
    pub multiplier_n: Vec<f64>,
    /// Whether [`StaticTerm::for_each_stiffness_block`] includes the sphere's curvature term
    /// `-(p_q / |x_q - c|) (I - n n^T)` (the exact second derivative) or only the penalty's
    /// `kappa_q n n^T`. [`indent`] leaves it out by default
    /// ([`IndentParams::curvature_stiffness`]): under the deep penetrations of a new depth's
    /// first iterations it makes the tangent indefinite and Newton wanders (measured on the LV
    /// refined under the probe: 50 iterations without convergence at increments down to
    /// 0.015 mm), while at the solution it is `p / R` against `kappa`, under 1 % of the
    /// penalty's stiffness, so the iteration still converges fast, to the same state (the
    /// residual and the energy are exact either way).
    pub curvature_stiffness: bool,
}

impl SphereContact {
    /// Distance from the centre and outward normal of point `q` at positions `x`; the normal
    /// is the direction away from the centre (any unit vector when the point is at the
    /// centre).
    fn geometry(&self, q: usize, x: &[DVec3]) -> (f64, DVec3) {
        let d = self.points[q].position(x) - self.centre_m;
        let rho = d.length();
        let n = if rho > 0.0 { d / rho } else { DVec3::Z };
        (rho, n)
    }

    /// Contact force magnitude `p_q = max(0, lambda_q + kappa_q g_q)` of point `q`, N.
    fn pressure_force(&self, q: usize, rho: f64) -> f64 {
        (self.multiplier_n[q] + self.penalty_n_per_m[q] * (self.radius_m - rho)).max(0.0)
    }

    /// Force of the body on the sphere, `-sum p_q n_q` (N), at positions `x`.
    pub fn force_on_sphere_n(&self, x: &[DVec3]) -> DVec3 {
        let mut f = DVec3::ZERO;
        for q in 0..self.points.len() {
            let (rho, n) = self.geometry(q, x);
            f -= n * self.pressure_force(q, rho);
        }
        f
    }
}

impl StaticTerm for SphereContact {
    fn energy(&self, x: &[DVec3]) -> f64 {
        let mut e = 0.0;
        for q in 0..self.points.len() {
            let (rho, _) = self.geometry(q, x);
            let p = self.pressure_force(q, rho);
            let l = self.multiplier_n[q];
            e += (p * p - l * l) / (2.0 * self.penalty_n_per_m[q]);
        }
        e
    }

    fn add_forces(&self, x: &[DVec3], f: &mut [DVec3]) {
        for (q, pt) in self.points.iter().enumerate() {
            let (rho, n) = self.geometry(q, x);
            let p = self.pressure_force(q, rho);
            if p > 0.0 {
                for a in 0..3 {
                    f[pt.nodes[a] as usize] += n * (p * pt.bary[a]);
                }
            }
        }
    }

    fn for_each_stiffness_block(&self, x: &[DVec3], add: &mut dyn FnMut(u32, u32, DMat3)) {
        for (q, pt) in self.points.iter().enumerate() {
            let (rho, n) = self.geometry(q, x);
            let p = self.pressure_force(q, rho);
            if p > 0.0 {
                let nn = DMat3::from_cols(n * n.x, n * n.y, n * n.z);
                let mut k_point = nn * self.penalty_n_per_m[q];
                if self.curvature_stiffness {
                    k_point -= (DMat3::IDENTITY - nn) * (p / rho.max(1e-300));
                }
                for a in 0..3 {
                    for b in 0..3 {
                        add(
                            pt.nodes[a],
                            pt.nodes[b],
                            k_point * (pt.bary[a] * pt.bary[b]),
                        );
                    }
                }
            }
        }
    }
}

/// Settings of [`indent`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndentParams {
    /// Penalty per contact point as a multiple of `mu l_q`, with `mu` the material's shear
    /// modulus and `l_q` the square root of the point's rest area (default 100: the gap
    /// shrinks about a hundredfold per multiplier update). A multiplier update that shrinks
    /// the worst gap less than fourfold multiplies the penalties by 4, up to 16 times their
    /// start values (stiffer penalties make Newton cycle across the contact's kink).
    pub penalty_factor: f64,
    /// Largest spacing of the contact points as a fraction of the sphere radius (default
    /// 0.25; see [`contact_points`]).
    pub point_spacing: f64,
    /// Gap tolerance as a fraction of the depth: every point must be outside the sphere or
    /// within this of its surface, and a point carrying force within it of the surface
    /// (default 1e-4; the force error it allows is about 1.5 times this for a Hertzian
    /// contact). Never below `1e-7 R`.
    pub gap_tol: f64,
    /// Largest number of multiplier updates per depth (default 40).
    pub max_augmentations: usize,
    /// Largest number of halvings of a depth increment whose Newton solve fails (default 6).
    pub max_bisections: usize,
    /// Newton settings of each solve with frozen multipliers.
    pub newton: StaticParams,
    /// Whether Newton's tangent carries the sphere's curvature term (default false; see
    /// [`SphereContact::curvature_stiffness`]). The converged state is the same either way.
    pub curvature_stiffness: bool,
}

impl Default for IndentParams {
    fn default() -> Self {
        Self {
            penalty_factor: 100.0,
            point_spacing: 0.25,
            gap_tol: 1e-4,
            max_augmentations: 40,
            max_bisections: 6,
            curvature_stiffness: false,
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
    /// Area of the contact, m^2: the current areas of the contact points carrying force
    /// (resolution: one point's area).
    pub contact_area_m2: f64,
    /// Contact radius `sqrt(contact_area_m2 / pi)`, m (the radius of a full circular contact
    /// of that area; zero without contact).
    pub contact_radius_m: f64,
    /// Contact points carrying force.
    pub points_in_contact: usize,
    /// Largest penetration of a contact point into the sphere, m (at most the gap tolerance).
    pub max_penetration_m: f64,
    /// Multiplier updates at this depth (over its sub-increments).
    pub augmentations: usize,
    /// Newton iterations at this depth.
    pub newton_iterations: usize,
    /// Node positions, m.
    pub x_m: Vec<DVec3>,
}

/// Distance along `direction` (unit) from `from` at which a sphere of radius `radius_m` first
/// touches one of `points` (m), or `None` when the ray misses them all.
///
/// # Errors
/// [`ModelError::InvalidInput`] when the sphere at `from` already contains a point.
pub fn first_contact_distance(
    points: &[DVec3],
    from: DVec3,
    direction: DVec3,
    radius_m: f64,
) -> Result<Option<f64>, ModelError> {
    let mut best: Option<f64> = None;
    for &p in points {
        let w = p - from;
        let c = w.length_squared() - radius_m * radius_m;
        if c < 0.0 {
            return Err(ModelError::InvalidInput(format!(
                "the sphere at the start point {from} m already overlaps the body (the surface \
                 point {p} m is {:.4e} m from its centre, radius {radius_m:.4e} m): start \
                 farther out",
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

/// Distance from `indenter.from_m` along its direction at which the sphere first touches the
/// touchable surface `triangles` of the rest configuration of `fem` (its nodes and the
/// contact points of `params`): the sphere centre at depth zero of [`indent`] is `from_m +
/// distance * direction.normalize()`, m.
///
/// # Errors
/// As [`indent`] for a start point overlapping the body or a ray that misses it.
pub fn contact_distance(
    fem: &FemModel,
    triangles: &[[u32; 3]],
    indenter: &Indenter,
    params: &IndentParams,
) -> Result<f64, ModelError> {
    let r = indenter.radius_m;
    let points = contact_points(triangles, fem.rest(), params.point_spacing * r)?;
    let dir = indenter.direction.normalize_or_zero();
    contact_distance_of(triangles, &points, fem.rest(), indenter.from_m, dir, r)
}

fn contact_distance_of(
    triangles: &[[u32; 3]],
    points: &[ContactPoint],
    rest: &[DVec3],
    from: DVec3,
    dir: DVec3,
    r: f64,
) -> Result<f64, ModelError> {
    let probe_points: Vec<DVec3> = triangles
        .iter()
        .flatten()
        .map(|&i| rest[i as usize])
        .chain(points.iter().map(|p| p.position(rest)))
        .collect();
    first_contact_distance(&probe_points, from, dir, r)?.ok_or_else(|| {
        ModelError::InvalidInput(format!(
            "a sphere of radius {r:.4e} m moving from {from} m along {dir} misses the touchable \
             surface"
        ))
    })
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
/// (increasing, m below first contact), with `triangles` the touchable surface (sampled by
/// [`contact_points`]). `progress` is called after each depth. Each depth starts from the
/// previous one's solution; an increment whose Newton solve fails is halved up to
/// `params.max_bisections` times.
///
/// # Errors
/// [`ModelError::InvalidInput`] for a non-finite or non-increasing depth list, a zero
/// direction, a start point overlapping the body or a ray that misses it;
/// [`ModelError::NoConvergence`] naming the depth that failed, the last converged depth, why
/// (Newton's message, the multiplier updates' gap or an inverted element in the converged
/// state) and the smallest principal stretch of the
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
    let rest = fem.rest();
    let points = contact_points(triangles, rest, params.point_spacing * r)?;
    let t0 = contact_distance_of(triangles, &points, rest, indenter.from_m, dir, r)?;
    let mu = fem.material().mu_pa;
    let mut contact = SphereContact {
        centre_m: indenter.from_m + dir * t0,
        radius_m: r,
        penalty_n_per_m: points
            .iter()
            .map(|p| params.penalty_factor * mu * p.area_m2(rest).sqrt())
            .collect(),
        multiplier_n: vec![0.0; points.len()],
        points,
        curvature_stiffness: params.curvature_stiffness,
    };
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
        let point = measure(&contact, &x, depth, augmentations, newton_iterations);
        progress(&point);
        out.push(point);
    }
    Ok(out)
}

/// Multiplier updates with Newton solves until the gap criterion holds: returns the updates
/// and Newton iterations used, or why it failed (a state with an inverted element fails). On
/// success the multipliers are those the final positions are in equilibrium with.
fn augment(
    fem: &FemModel,
    contact: &mut SphereContact,
    x: &mut [DVec3],
    gap_tol: f64,
    params: &IndentParams,
) -> Result<(usize, usize), String> {
    let mut newton = 0;
    let mut worst = f64::INFINITY;
    let mut previous = f64::INFINITY;
    for a in 1..=params.max_augmentations {
        let rep = solve_static_with(fem, &[], Some(&*contact), x, &params.newton)
            .map_err(|e| format!("Newton with frozen contact multipliers: {e}"))?;
        newton += rep.iterations;
        // Gap criterion: no node inside the sphere beyond the tolerance; a node carrying force
        // is on the sphere within it (complementarity).
        worst = 0.0f64;
        for k in 0..contact.points.len() {
            let (rho, _) = contact.geometry(k, x);
            let g = contact.radius_m - rho;
            let p = contact.pressure_force(k, rho);
            let violation = if p > 0.0 { g.abs() } else { g.max(0.0) };
            worst = worst.max(violation);
        }
        // Uzawa's update. When the criterion holds this stores the forces the positions are
        // in equilibrium with (what is reported) and warm-starts the next depth.
        for k in 0..contact.points.len() {
            let (rho, _) = contact.geometry(k, x);
            contact.multiplier_n[k] = contact.pressure_force(k, rho);
        }
        if worst <= gap_tol {
            // St. Venant-Kirchhoff has zero-energy reflected states, so Newton can converge
            // to a crushed body; that is no equilibrium of tissue.
            let inverted = fem.inverted_elements(x);
            if inverted > 0 {
                return Err(format!(
                    "the converged state inverts {inverted} element(s): no physical equilibrium"
                ));
            }
            return Ok((a, newton));
        }
        // A gap that closes slowly (the active set changing at the rim of the contact on a
        // coarse surface) gets a stiffer penalty; the converged answer does not depend on it.
        if worst > 0.25 * previous {
            let mu = fem.material().mu_pa;
            for (kappa, pt) in contact.penalty_n_per_m.iter_mut().zip(&contact.points) {
                let start = params.penalty_factor * mu * pt.area_m2(fem.rest()).sqrt();
                *kappa = (*kappa * 4.0).min(start * MAX_PENALTY_GROWTH);
            }
        }
        previous = worst;
    }
    Err(format!(
        "the contact gap did not close in {} multiplier updates (worst {worst:.3e} m, tolerance \
         {gap_tol:.3e} m)",
        params.max_augmentations
    ))
}

/// How far [`augment`] may stiffen the penalties above their start values.
const MAX_PENALTY_GROWTH: f64 = 16.0;

/// The reported quantities at one converged depth.
fn measure(
    contact: &SphereContact,
    x: &[DVec3],
    depth_m: f64,
    augmentations: usize,
    newton_iterations: usize,
) -> IndentPoint {
    let mut in_contact = 0;
    let mut area = 0.0;
    let mut max_pen = 0.0f64;
    let mut force = DVec3::ZERO;
    for (q, pt) in contact.points.iter().enumerate() {
        let (rho, n) = contact.geometry(q, x);
        max_pen = max_pen.max(contact.radius_m - rho);
        let p = contact.multiplier_n[q];
        if p > 0.0 {
            in_contact += 1;
            area += pt.area_m2(x);
        }
        force -= n * p;
    }
    IndentPoint {
        depth_m,
        centre_m: contact.centre_m,
        force_on_sphere_n: force,
        contact_area_m2: area,
        contact_radius_m: (area / std::f64::consts::PI).sqrt(),
        points_in_contact: in_contact,
        max_penetration_m: max_pen.max(0.0),
        augmentations,
        newton_iterations,
        x_m: x.to_vec(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two triangles folded along an edge, and a sphere pressing into both.
    fn fixture() -> (Vec<[u32; 3]>, Vec<DVec3>, SphereContact) {
        let x = vec![
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1e-3, 0.0, 0.0),
            DVec3::new(0.0, 1e-3, 0.1e-3),
            DVec3::new(1e-3, 1e-3, -0.2e-3),
        ];
        let tris = vec![[0, 1, 2], [1, 3, 2]];
        let points = contact_points(&tris, &x, 0.3e-3).unwrap();
        let n = points.len();
        let contact = SphereContact {
            centre_m: DVec3::new(0.45e-3, 0.5e-3, 1.9e-3),
            radius_m: 2e-3,
            penalty_n_per_m: (0..n).map(|q| 50.0 + q as f64).collect(),
            multiplier_n: (0..n).map(|q| 1e-4 * (q % 3) as f64).collect(),
            points,
            curvature_stiffness: true,
        };
        (tris, x, contact)
    }

    #[test]
    fn contact_points_tile_each_triangle_evenly() {
        let (tris, x, contact) = fixture();
        // Edges of about 1.0-1.4 mm at a spacing of 0.3 mm: L = 5, 25 points per triangle.
        assert_eq!(contact.points.len(), 2 * 25);
        for t in &tris {
            let pts: Vec<&ContactPoint> = contact.points.iter().filter(|p| p.nodes == *t).collect();
            let total: f64 = pts.iter().map(|p| p.area_fraction).sum();
            assert!((total - 1.0).abs() < 1e-12);
            // The points' centroid is the triangle's (the lattice is symmetric).
            let c: DVec3 = pts.iter().map(|p| p.position(&x)).sum::<DVec3>() / pts.len() as f64;
            let centroid = t.iter().map(|&i| x[i as usize]).sum::<DVec3>() / 3.0;
            assert!((c - centroid).length() < 1e-15, "{c} vs {centroid}");
            for p in pts {
                assert!(
                    p.bary.iter().all(|&b| b > 0.0)
                        && (p.bary.iter().sum::<f64>() - 1.0).abs() < 1e-12
                );
            }
        }
    }

    /// A sphere far smaller than the triangles is refused before any point is made.
    #[test]
    fn too_many_contact_points_are_refused() {
        let (tris, x, _) = fixture();
        let many = vec![tris[0]; 16_000]; // 16 000 x 16^2 = 4.1 million points
        let err = contact_points(&many, &x, 1e-6).unwrap_err().to_string();
        assert!(err.contains("4096000 contact points"), "{err}");
        assert_eq!(
            contact_points(&many[..100], &x, 1e-6).unwrap().len(),
            100 * 256
        );
    }

    /// Forces are minus the gradient of the energy and the stiffness blocks the derivative of
    /// the forces, by central differences.
    #[test]
    fn forces_and_stiffness_match_finite_differences() {
        let (_, x, contact) = fixture();
        let n = x.len();
        let mut f = vec![DVec3::ZERO; n];
        contact.add_forces(&x, &mut f);
        assert!(
            f.iter().any(|v| v.length() > 1e-6),
            "the fixture must be in contact"
        );
        let mut k = vec![DMat3::ZERO; n * n];
        contact.for_each_stiffness_block(&x, &mut |i, j, b| k[i as usize * n + j as usize] += b);
        let h = 1e-9;
        for j in 0..n {
            for c in 0..3 {
                let mut xp = x.clone();
                let mut xm = x.clone();
                xp[j][c] += h;
                xm[j][c] -= h;
                let de = (contact.energy(&xp) - contact.energy(&xm)) / (2.0 * h);
                assert!(
                    (de + f[j][c]).abs() < 1e-6 * f[j].length().max(1e-3),
                    "dE/dx {j} {c}"
                );
                let (mut fp, mut fm) = (vec![DVec3::ZERO; n], vec![DVec3::ZERO; n]);
                contact.add_forces(&xp, &mut fp);
                contact.add_forces(&xm, &mut fm);
                for i in 0..n {
                    let df = (fp[i] - fm[i]) / (2.0 * h);
                    // K = d^2E/dx^2 = -df/dx.
                    let col = k[i * n + j].col(c);
                    assert!(
                        (col + df).length() < 1e-5 * df.length().max(1.0),
                        "K[{i}][{j}] column {c}: {col} vs {}",
                        -df
                    );
                }
            }
        }
    }
}
