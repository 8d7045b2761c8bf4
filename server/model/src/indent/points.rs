//! Contact points inside the touchable triangles that are coarser than the sphere, with an
//! augmented-Lagrangian contact term ([`SphereContact`]).
//!
//! On a surface whose triangles are larger than about a quarter of the sphere's radius the
//! sphere could pass between the nodes, which are the exact constraints of
//! [`super::newton`]: such a triangle is split into `L^2` equal sub-triangles and carries a
//! point at each sub-triangle's centroid, `x_q = sum_a b_qa x_a` over the triangle's three
//! nodes with barycentric weights `b_qa`. The constraint `g_q = R - |x_q - c| <= 0` enters
//! the equilibrium by an augmented Lagrangian: for multipliers `lambda_q >= 0` (N) and
//! per-point penalties `kappa_q` (N/m) the contact energy is
//!
//! `E_c(x) = sum_q (max(0, lambda_q + kappa_q g_q)^2 - lambda_q^2) / (2 kappa_q)`,
//!
//! its force on node `a` of point `q` is `b_qa p_q n_q` with the contact pressure force
//! `p_q = max(0, lambda_q + kappa_q g_q)` and the outward normal `n_q = (x_q - c) / |x_q -
//! c|`, and its stiffness block between nodes `a` and `b` is `b_qa b_qb (kappa_q n n^T - (p_q
//! / |x_q - c|) (I - n n^T))` (the second term is the sphere's curvature). Newton solves the
//! equilibrium with the multipliers frozen, then Uzawa's update `lambda_q <- p_q` follows
//! ([`super::Indentation`]); the converged forces are those of the exact constraint, not of
//! the penalty.
//!
//! Owns: the points and their term. Uses: [`crate::statics::StaticTerm`].

use glam::{DMat3, DVec3};

use crate::ModelError;
use crate::statics::StaticTerm;

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
    /// `kappa_q n n^T`. [`super::indent`] leaves it out by default
    /// ([`super::IndentParams::curvature_stiffness`]): under the deep penetrations of a new depth's
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
    pub(super) fn geometry(&self, q: usize, x: &[DVec3]) -> (f64, DVec3) {
        let d = self.points[q].position(x) - self.centre_m;
        let rho = d.length();
        let n = if rho > 0.0 { d / rho } else { DVec3::Z };
        (rho, n)
    }

    /// Contact force magnitude `p_q = max(0, lambda_q + kappa_q g_q)` of point `q`, N.
    pub(super) fn pressure_force(&self, q: usize, rho: f64) -> f64 {
        (self.multiplier_n[q] + self.penalty_n_per_m[q] * (self.radius_m - rho)).max(0.0)
    }

    /// Force of the body on the sphere carried by the multipliers alone, `-sum lambda_q n_q`
    /// (N), at positions `x`: after Uzawa's update (`lambda_q` set to the pressure forces the
    /// positions were solved with) it is the force the body is in equilibrium with, which
    /// [`Self::force_on_sphere_n`] would overstate by the updated multipliers' `kappa_q g_q`.
    pub fn multiplier_force_n(&self, x: &[DVec3]) -> DVec3 {
        let mut f = DVec3::ZERO;
        for q in 0..self.points.len() {
            let (_, n) = self.geometry(q, x);
            f -= n * self.multiplier_n[q];
        }
        f
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
