//! Static indentation by a rigid sphere: the reference the probe forces are measured against
//! and the solver behind `haptic-solve --indent`.
//!
//! A rigid frictionless sphere of radius `R` with centre `c` may not be penetrated by the
//! body's touchable surface. Every node of the touchable triangles (corner and mid-edge nodes
//! on quadratic meshes) is constrained exactly, `|x_i - c| >= R`, by an active set updated
//! within Newton's iteration (`newton.rs`: semismooth Newton, the contact forces are the
//! reactions, no penalty in the answer). A triangle coarser than the sphere (longest edge
//! above `point_spacing R`) also carries contact points inside it (`points.rs`: augmented
//! Lagrangian, Uzawa updates between Newton solves), so that the sphere cannot slip between
//! the nodes of a coarse mesh (as it does with nodes alone on the built-in `lv`, whose
//! facets are 2-4 mm).
//!
//! The contact discretisation converges with the mesh: one constraint per node makes the
//! contact forces unique (the contact points at `R/4` it replaces on fine surfaces
//! constrained about twice as many points as a quadratic surface has nodes, so half of them
//! carried no force and the contact area counted over the points carrying force read 37-39 %
//! under Hertz's on a quadratic Hertz block). The contact area is the sum of the nodal areas
//! (a third of each adjacent touchable triangle, current configuration) of the nodes carrying
//! force, and of the points' areas on coarse triangles.
//!
//! Depths are measured from first contact along the indentation direction (the sphere centre
//! starts at `from`, clear of the body, and the depth-zero centre is where the sphere first
//! touches a node or a contact point of the rest configuration, [`first_contact_distance`]),
//! or from a given distance along it ([`IndentParams::zero_distance_m`], for example where the
//! sphere touches an analytic surface). Each depth starts from the previous one's solution
//! extrapolated linearly in depth; a depth whose solve fails is approached by halved
//! increments. There is no silent iteration cap: a depth that does not converge is an error
//! that names it.
//!
//! Owns: the sphere contact and the indentation driver. Uses: [`crate::element`],
//! [`crate::statics`] (free-equation numbering, [`StaticTerm`](crate::statics::StaticTerm)),
//! [`crate::linalg::ordering`], [`crate::material`] (principal stretches for error messages). Not used
//! by the real-time path.

mod linear;
mod newton;
mod points;

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::element::FemModel;
use crate::material::corotational::symmetric_eigen;
use crate::statics::StaticParams;

pub use linear::LinearStats;
pub use points::{ContactPoint, MAX_CONTACT_POINTS, SphereContact, contact_points};

/// Settings of [`indent`] and [`Indentation`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndentParams {
    /// Penalty per contact point (coarse triangles only) as a multiple of `mu l_q`, with `mu`
    /// the material's shear modulus and `l_q` the square root of the point's rest area
    /// (default 100). A multiplier update that shrinks the worst gap less than fourfold
    /// multiplies the penalties by 4, up to 16 times their start values.
    pub penalty_factor: f64,
    /// Largest spacing of the contact constraints as a fraction of the sphere radius (default
    /// 0.25): a touchable triangle whose longest edge exceeds it carries contact points
    /// inside ([`contact_points`]).
    pub point_spacing: f64,
    /// Gap tolerance as a fraction of the depth: every node and point must be outside the
    /// sphere or within this of its surface, and one carrying force within it of the surface
    /// (default 1e-4). Never below `1e-7 R`.
    pub gap_tol: f64,
    /// Largest number of multiplier updates of the contact points per depth (default 40).
    pub max_augmentations: usize,
    /// Largest number of halvings of a depth increment whose solve fails (default 6).
    pub max_bisections: usize,
    /// Newton settings of each solve: the projected residual must be below `rel_tol` times
    /// the contact forces' norm (or `abs_tol_n`, or the round-off floor of the assembled
    /// forces, whichever is largest) within `max_iterations` iterations.
    pub newton: StaticParams,
    /// Whether Newton's tangent carries the sphere's curvature term `-(lambda / |x - c|) (I -
    /// n n^T)` at the nodes and points in contact (default false: under the deep penetrations
    /// of a new depth's first iterations it can make the tangent indefinite; at the solution
    /// it is `lambda / R`, under 1 % of the stiffness, so the iteration converges as fast).
    /// The converged state is the same either way.
    pub curvature_stiffness: bool,
    /// Relative residual of the linear solves inside Newton (default 1e-3; the last
    /// iterations' steps are small, so this does not limit the final accuracy).
    pub linear_rel_tol: f64,
    /// Distance from the start centre along the direction at which the depth is zero, m
    /// (default `None`: where the sphere first touches the rest surface).
    pub zero_distance_m: Option<f64>,
}

impl Default for IndentParams {
    fn default() -> Self {
        Self {
            penalty_factor: 100.0,
            point_spacing: 0.25,
            gap_tol: 1e-4,
            max_augmentations: 40,
            max_bisections: 6,
            curvature_stiffness: true,
            linear_rel_tol: 1e-3,
            zero_distance_m: None,
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
    /// Depth, m.
    pub depth_m: f64,
    /// Sphere centre, m.
    pub centre_m: DVec3,
    /// Force of the body on the sphere (what a probe there feels), N.
    pub force_on_sphere_n: DVec3,
    /// Area of the contact, m^2: the nodal areas of the nodes carrying force and the areas
    /// of the contact points carrying force (current configuration; resolution: one node's
    /// area).
    pub contact_area_m2: f64,
    /// Contact radius `sqrt(contact_area_m2 / pi)`, m (the radius of a full circular contact
    /// of that area; zero without contact).
    pub contact_radius_m: f64,
    /// Nodes carrying force.
    pub nodes_in_contact: usize,
    /// Contact points (inside coarse triangles) carrying force.
    pub points_in_contact: usize,
    /// Largest penetration of a node or contact point into the sphere, m (at most the gap
    /// tolerance).
    pub max_penetration_m: f64,
    /// Multiplier updates of the contact points at this depth (one solve without points).
    pub augmentations: usize,
    /// Newton iterations at this depth.
    pub newton_iterations: usize,
    /// Linear-solver counters accumulated up to this depth.
    pub linear: LinearStats,
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

/// The touchable triangles coarser than the point spacing (which carry contact points), and
/// the others.
fn split_by_size(
    triangles: &[[u32; 3]],
    x: &[DVec3],
    spacing_m: f64,
) -> (Vec<[u32; 3]>, Vec<[u32; 3]>) {
    triangles.iter().partition(|t| {
        let [a, b, c] = t.map(|i| x[i as usize]);
        (b - a).length().max((c - b).length()).max((a - c).length()) > spacing_m
    })
}

/// Distance from `indenter.from_m` along its direction at which the sphere first touches the
/// touchable surface `triangles` of the rest configuration of `fem` (its nodes and the
/// contact points of its coarse triangles): the sphere centre at depth zero of [`indent`] is
/// `from_m + distance * direction.normalize()`, m.
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
    let spacing = params.point_spacing * r;
    let (coarse, _) = split_by_size(triangles, fem.rest(), spacing);
    let points = contact_points(&coarse, fem.rest(), spacing)?;
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

/// A static indentation in progress: the body's state against the sphere at the last
/// converged depth, from which [`Indentation::solve`] goes to any other depth (deeper or
/// shallower).
pub struct Indentation<'a> {
    fem: &'a FemModel,
    newton: newton::Newton<'a>,
    params: IndentParams,
    from: DVec3,
    dir: DVec3,
    /// Distance from `from` to the depth-zero centre, m.
    zero: f64,
    /// The touchable triangles without contact points (their nodes' areas).
    fine: Vec<[u32; 3]>,
    /// Positions at the current depth, m.
    x: Vec<DVec3>,
    /// The current depth, m.
    reached: f64,
    /// The previous converged state (depth, positions), for the extrapolated start.
    previous: Option<(f64, Vec<DVec3>)>,
}

/// Contact multipliers and the active set: what a failed attempt restores.
type ContactState = (Vec<bool>, Vec<f64>, Vec<f64>, Vec<f64>);

/// Everything [`Indentation::solve`] carries from one depth to the next, so that a long
/// reference solve can stop after any depth and continue in another process
/// ([`Indentation::checkpoint`], [`Indentation::resume`]). Lengths: `positions_m` and the
/// previous state's positions one per node; `active` and `lambda` one per touchable node;
/// `multiplier_n` and `penalty_n_per_m` one per contact point.
#[derive(Debug, Clone, PartialEq)]
pub struct IndentCheckpoint {
    /// The last converged depth, m.
    pub reached_m: f64,
    /// Positions at that depth, m.
    pub positions_m: Vec<DVec3>,
    /// The converged state before it (depth, positions), for the extrapolated start.
    pub previous: Option<(f64, Vec<DVec3>)>,
    /// Node contact: the active set.
    pub active: Vec<bool>,
    /// Node contact: the multipliers, N.
    pub lambda: Vec<f64>,
    /// Contact points: the augmented-Lagrangian multipliers, N.
    pub multiplier_n: Vec<f64>,
    /// Contact points: the penalties, N/m.
    pub penalty_n_per_m: Vec<f64>,
}

impl<'a> Indentation<'a> {
    /// The body `fem` at rest with the sphere `indenter` at depth zero, touchable surface
    /// `triangles`.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for a zero or non-finite direction, a bad radius or start
    /// point, a start point overlapping the body, a ray that misses it, or too many contact
    /// points.
    pub fn new(
        fem: &'a FemModel,
        triangles: &[[u32; 3]],
        indenter: &Indenter,
        params: &IndentParams,
    ) -> Result<Self, ModelError> {
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
        let rest = fem.rest();
        let spacing = params.point_spacing * r;
        let (coarse, fine) = split_by_size(triangles, rest, spacing);
        let pts = contact_points(&coarse, rest, spacing)?;
        let first = contact_distance_of(triangles, &pts, rest, indenter.from_m, dir, r)?;
        let zero = params.zero_distance_m.unwrap_or(first);
        let mu = fem.material().mu_pa;
        let points = SphereContact {
            centre_m: indenter.from_m + dir * zero,
            radius_m: r,
            penalty_n_per_m: pts
                .iter()
                .map(|p| params.penalty_factor * mu * p.area_m2(rest).sqrt())
                .collect(),
            multiplier_n: vec![0.0; pts.len()],
            points: pts,
            curvature_stiffness: params.curvature_stiffness,
        };
        let mut newton = newton::Newton::new(fem, triangles, points)?;
        newton.sys.set_threads(params.newton.threads);
        newton.centre = indenter.from_m + dir * zero;
        Ok(Self {
            fem,
            newton,
            params: *params,
            from: indenter.from_m,
            dir,
            zero,
            fine,
            x: rest.to_vec(),
            reached: 0.0,
            previous: None,
        })
    }

    /// Distance from the start centre to the depth-zero centre along the direction, m.
    pub fn zero_distance_m(&self) -> f64 {
        self.zero
    }

    /// The current positions, m.
    pub fn positions(&self) -> &[DVec3] {
        &self.x
    }

    /// The state at the last converged depth (see [`IndentCheckpoint`]).
    pub fn checkpoint(&self) -> IndentCheckpoint {
        let (active, lambda, multiplier_n, penalty_n_per_m) = self.contact_state();
        IndentCheckpoint {
            reached_m: self.reached,
            positions_m: self.x.clone(),
            previous: self.previous.clone(),
            active,
            lambda,
            multiplier_n,
            penalty_n_per_m,
        }
    }

    /// Continues from `c`, a checkpoint of an indentation of the same body, surface, sphere
    /// and parameters: the next [`Indentation::solve`] starts where `c`'s run stopped (its
    /// linear solver refactors first, so the iterates agree with an uninterrupted run to the
    /// solver's tolerances, not bit for bit).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] when a length does not match this indentation's (another
    /// mesh, surface or contact-point set) or a value is not finite; nothing is changed then.
    pub fn resume(&mut self, c: IndentCheckpoint) -> Result<(), ModelError> {
        let nodes = self.x.len();
        let lengths = [
            ("positions", c.positions_m.len(), nodes),
            (
                "previous positions",
                c.previous.as_ref().map_or(nodes, |p| p.1.len()),
                nodes,
            ),
            ("active set", c.active.len(), self.newton.active.len()),
            ("node multipliers", c.lambda.len(), self.newton.lambda.len()),
            (
                "point multipliers",
                c.multiplier_n.len(),
                self.newton.points.multiplier_n.len(),
            ),
            (
                "point penalties",
                c.penalty_n_per_m.len(),
                self.newton.points.penalty_n_per_m.len(),
            ),
        ];
        for (what, got, want) in lengths {
            if got != want {
                return Err(ModelError::InvalidInput(format!(
                    "the checkpoint's {what} has {got} entries where this indentation has \
                     {want}: it belongs to another mesh, surface or sphere"
                )));
            }
        }
        let finite = c.reached_m.is_finite()
            && c.reached_m >= 0.0
            && c.positions_m.iter().all(|p| p.is_finite())
            && c.previous
                .as_ref()
                .is_none_or(|(d, x)| d.is_finite() && x.iter().all(|p| p.is_finite()))
            && c.lambda
                .iter()
                .chain(&c.multiplier_n)
                .chain(&c.penalty_n_per_m)
                .all(|v| v.is_finite());
        if !finite {
            return Err(ModelError::InvalidInput(
                "the checkpoint holds a negative depth or a non-finite value".into(),
            ));
        }
        self.reached = c.reached_m;
        self.x = c.positions_m;
        self.previous = c.previous;
        self.restore((c.active, c.lambda, c.multiplier_n, c.penalty_n_per_m));
        let centre = self.centre(self.reached);
        self.newton.centre = centre;
        self.newton.points.centre_m = centre;
        self.newton.sys.forget_factor();
        Ok(())
    }

    fn contact_state(&self) -> ContactState {
        (
            self.newton.active.clone(),
            self.newton.lambda.clone(),
            self.newton.points.multiplier_n.clone(),
            self.newton.points.penalty_n_per_m.clone(),
        )
    }

    fn restore(&mut self, s: ContactState) {
        (
            self.newton.active,
            self.newton.lambda,
            self.newton.points.multiplier_n,
            self.newton.points.penalty_n_per_m,
        ) = s;
    }

    /// The static equilibrium at `depth_m` (m, any non-negative depth), from the current
    /// state: increments that fail are halved up to `max_bisections` times.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for a negative or non-finite depth;
    /// [`ModelError::NoConvergence`] naming the depth, the last converged depth, why (Newton's
    /// message, the contact points' gap or an inverted element in the converged state) and
    /// the smallest principal stretch of the last converged state (St. Venant-Kirchhoff
    /// loses stability below `1/sqrt(3)`). The state stays at the last converged depth.
    pub fn solve(&mut self, depth_m: f64) -> Result<IndentPoint, ModelError> {
        if !depth_m.is_finite() || depth_m < 0.0 {
            return Err(ModelError::InvalidInput(format!(
                "depths must be finite and non-negative: got {depth_m} m"
            )));
        }
        let (mut augmentations, mut newton_iterations) = (0, 0);
        let mut halvings: usize = 0;
        let mut first = true;
        while first || self.reached != depth_m {
            first = false;
            let step = (depth_m - self.reached) * 0.5f64.powi(halvings as i32);
            let target = if halvings == 0 {
                depth_m
            } else {
                self.reached + step
            };
            let backup = (self.x.clone(), self.contact_state());
            self.start_at(target);
            match self.augment(target) {
                Ok((a, n)) => {
                    augmentations += a;
                    newton_iterations += n;
                    if target != self.reached {
                        self.previous = Some((self.reached, backup.0));
                    }
                    self.reached = target;
                    halvings = halvings.saturating_sub(1);
                }
                Err(why) => {
                    self.x = backup.0;
                    self.restore(backup.1);
                    self.newton.centre = self.centre(self.reached);
                    self.newton.sys.forget_factor();
                    if halvings < self.params.max_bisections {
                        halvings += 1;
                        continue;
                    }
                    return Err(ModelError::NoConvergence(format!(
                        "indentation depth {depth_m:.4e} m failed at {target:.4e} m after \
                         halving the increment {halvings} times (last converged depth \
                         {:.4e} m, smallest principal stretch there {:.3}): {why}",
                        self.reached,
                        min_principal_stretch(self.fem, &self.x)
                    )));
                }
            }
        }
        Ok(self.measure(augmentations, newton_iterations))
    }

    fn centre(&self, depth: f64) -> DVec3 {
        self.from + self.dir * (self.zero + depth)
    }

    /// Moves the sphere to `depth` and the positions to the linear extrapolation of the last
    /// two converged states (kept when that inverts an element).
    fn start_at(&mut self, depth: f64) {
        let c = self.centre(depth);
        self.newton.centre = c;
        self.newton.points.centre_m = c;
        if let Some((d0, x0)) = &self.previous {
            let span = self.reached - d0;
            if span != 0.0 {
                let t = ((depth - self.reached) / span).clamp(-3.0, 3.0);
                let guess: Vec<DVec3> = self
                    .x
                    .iter()
                    .zip(x0)
                    .map(|(a, b)| *a + (*a - *b) * t)
                    .collect();
                if self.fem.inverted_elements(&guess) == 0 {
                    self.x = guess;
                }
            }
        }
    }

    /// Newton solves with the points' multipliers updated between them until every gap is
    /// within tolerance: returns the updates and Newton iterations, or why it failed (a state
    /// with an inverted element fails).
    fn augment(&mut self, depth: f64) -> Result<(usize, usize), String> {
        let p = &self.params;
        let r = self.newton.radius;
        let gap_tol = (p.gap_tol * depth).max(1e-7 * r);
        let settings = newton::Settings {
            rel_tol: p.newton.rel_tol,
            abs_tol_n: p.newton.abs_tol_n,
            max_iterations: p.newton.max_iterations,
            gap_tol_m: gap_tol,
            linear_rel_tol: p.linear_rel_tol,
            curvature_stiffness: p.curvature_stiffness,
        };
        let mut newton_its = 0;
        let mut worst = f64::INFINITY;
        let mut previous = f64::INFINITY;
        for a in 1..=p.max_augmentations {
            let rep = self.newton.solve(&mut self.x, &settings)?;
            newton_its += rep.iterations;
            let pts = &mut self.newton.points;
            worst = 0.0f64;
            for k in 0..pts.points.len() {
                let (rho, _) = pts.geometry(k, &self.x);
                let g = pts.radius_m - rho;
                let pk = pts.pressure_force(k, rho);
                let violation = if pk > 0.0 { g.abs() } else { g.max(0.0) };
                worst = worst.max(violation);
            }
            // Uzawa's update: the forces the positions are in equilibrium with.
            for k in 0..pts.points.len() {
                let (rho, _) = pts.geometry(k, &self.x);
                pts.multiplier_n[k] = pts.pressure_force(k, rho);
            }
            if worst <= gap_tol {
                // St. Venant-Kirchhoff has zero-energy reflected states, so Newton can converge
                // to a crushed body; that is no equilibrium of tissue.
                let inverted = self.fem.inverted_elements(&self.x);
                if inverted > 0 {
                    return Err(format!(
                        "the converged state inverts {inverted} element(s): no physical \
                         equilibrium"
                    ));
                }
                return Ok((a, newton_its));
            }
            if worst > 0.25 * previous {
                let mu = self.fem.material().mu_pa;
                for (kappa, pt) in pts.penalty_n_per_m.iter_mut().zip(&pts.points) {
                    let start = p.penalty_factor * mu * pt.area_m2(self.fem.rest()).sqrt();
                    *kappa = (*kappa * 4.0).min(start * MAX_PENALTY_GROWTH);
                }
            }
            previous = worst;
        }
        Err(format!(
            "the contact points' gap did not close in {} multiplier updates (worst {worst:.3e} \
             m, tolerance {gap_tol:.3e} m)",
            p.max_augmentations
        ))
    }

    /// The reported quantities at the current (converged) depth.
    fn measure(&self, augmentations: usize, newton_iterations: usize) -> IndentPoint {
        let x = &self.x;
        let nw = &self.newton;
        let mut area = 0.0;
        let mut nodes_in_contact = 0;
        let mut node_area = vec![0.0; x.len()];
        for t in &self.fine {
            let [a, b, c] = t.map(|i| x[i as usize]);
            let third = (b - a).cross(c - a).length() / 6.0;
            for &i in t {
                node_area[i as usize] += third;
            }
        }
        for (k, &i) in nw.nodes.iter().enumerate() {
            if nw.active[k] && nw.lambda[k] > 0.0 {
                nodes_in_contact += 1;
                area += node_area[i as usize];
            }
        }
        let pts = &nw.points;
        let mut points_in_contact = 0;
        let mut max_pen = nw.max_penetration_m(x);
        for (q, pt) in pts.points.iter().enumerate() {
            let (rho, _) = pts.geometry(q, x);
            max_pen = max_pen.max(pts.radius_m - rho);
            if pts.multiplier_n[q] > 0.0 {
                points_in_contact += 1;
                area += pt.area_m2(x);
            }
        }
        IndentPoint {
            depth_m: self.reached,
            centre_m: nw.centre,
            force_on_sphere_n: nw.force_on_sphere_n(x),
            contact_area_m2: area,
            contact_radius_m: (area / std::f64::consts::PI).sqrt(),
            nodes_in_contact,
            points_in_contact,
            max_penetration_m: max_pen.max(0.0),
            augmentations,
            newton_iterations,
            linear: nw.sys.stats,
            x_m: x.clone(),
        }
    }
}

/// How far the contact points' penalties may grow above their start values.
const MAX_PENALTY_GROWTH: f64 = 16.0;

/// The static indentation of `fem` by a rigid frictionless sphere at each of `depths_m`
/// (increasing, m), with `triangles` the touchable surface ([`Indentation`]). `progress` is
/// called after each depth.
///
/// # Errors
/// [`ModelError::InvalidInput`] for a non-finite or non-increasing depth list, and as
/// [`Indentation::new`]; [`ModelError::NoConvergence`] as [`Indentation::solve`], naming the
/// depth that failed.
pub fn indent(
    fem: &FemModel,
    triangles: &[[u32; 3]],
    indenter: &Indenter,
    depths_m: &[f64],
    params: &IndentParams,
    progress: &mut dyn FnMut(&IndentPoint),
) -> Result<Vec<IndentPoint>, ModelError> {
    let mut prev = 0.0;
    for &d in depths_m {
        if !d.is_finite() || d < prev {
            return Err(ModelError::InvalidInput(format!(
                "depths must be finite, non-negative and increasing: got {depths_m:?} m"
            )));
        }
        prev = d;
    }
    let mut run = Indentation::new(fem, triangles, indenter, params)?;
    let mut out = Vec::with_capacity(depths_m.len());
    for &depth in depths_m {
        let point = run.solve(depth)?;
        progress(&point);
        out.push(point);
    }
    Ok(out)
}
