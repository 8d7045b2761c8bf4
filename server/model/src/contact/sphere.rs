//! Sphere-against-triangle geometry for the probe's sphere contact: how far a sphere moving
//! along a line must travel to leave a triangle (a sphere cast), exactly.
//!
//! The set of sphere centres that touch triangle `T` is the Minkowski sum `T ⊕ B(r)`: the
//! triangle's prism of half-thickness `r` along its normal and the three capsules of radius `r`
//! around its edges (the vertex spheres are the capsules' caps). Each piece is convex, so a line
//! `y(t) = o + t n` meets it in an interval; the sphere has left the triangle after the largest
//! upper end over the pieces ([`sphere_exit`]). Ericson, *Real-Time Collision Detection*
//! (2005), 5.3.7 (segment-cylinder) and 5.3.8 (segment-polyhedron clipping).
//!
//! Neighbours: used by [`super::probe`]; allocation-free.

use glam::DVec3;

/// The largest `t` (m) at which the sphere of radius `r_m` centred at `o + t n` still touches
/// the triangle `(a, b, c)` (a point of it lies within `r_m` of the centre), or `None` when no
/// centre on the line touches it. `n` is a unit vector; the result may be negative (the
/// triangle lies behind `o`). For a degenerate (zero-area) triangle only the edge capsules
/// count.
pub fn sphere_exit(o: DVec3, n: DVec3, r_m: f64, a: DVec3, b: DVec3, c: DVec3) -> Option<f64> {
    let mut best: Option<f64> = None;
    let mut take = |t: Option<f64>| {
        if let Some(t) = t {
            best = Some(best.map_or(t, |b: f64| b.max(t)));
        }
    };
    take(prism_exit(o, n, r_m, a, b, c));
    for (p, q) in [(a, b), (b, c), (c, a)] {
        take(cylinder_exit(o, n, r_m, p, q));
        take(ball_exit(o, n, r_m, p));
    }
    best
}

/// Upper root of `|o + t n - centre| = r` (`n` unit), if the line meets the ball.
fn ball_exit(o: DVec3, n: DVec3, r: f64, centre: DVec3) -> Option<f64> {
    let m = o - centre;
    let b = m.dot(n);
    let disc = b * b - (m.length_squared() - r * r);
    (disc >= 0.0).then(|| -b + disc.sqrt())
}

/// Upper end of the line's interval inside the finite cylinder of radius `r` around segment
/// `p q` when that end lies on the curved side (an end on a cap lies inside the cap's ball,
/// whose own exit is later, so it is not needed).
fn cylinder_exit(o: DVec3, n: DVec3, r: f64, p: DVec3, q: DVec3) -> Option<f64> {
    let e = q - p;
    let len2 = e.length_squared();
    if len2 <= 0.0 {
        return None;
    }
    let m = o - p;
    // Components perpendicular to the axis.
    let n_perp = n - e * (n.dot(e) / len2);
    let m_perp = m - e * (m.dot(e) / len2);
    let qa = n_perp.length_squared();
    if qa <= 1e-24 {
        return None; // parallel to the axis: the caps' balls decide
    }
    let qb = m_perp.dot(n_perp);
    let disc = qb * qb - qa * (m_perp.length_squared() - r * r);
    if disc < 0.0 {
        return None;
    }
    let t = (-qb + disc.sqrt()) / qa;
    let s = (m + n * t).dot(e) / len2;
    (0.0..=1.0).contains(&s).then_some(t)
}

/// Upper end of the line's interval inside the triangle's prism `{y : |(y - a) . n_T| <= r,
/// y projects into the triangle}` (Cyrus-Beck clipping against its five planes).
fn prism_exit(o: DVec3, n: DVec3, r: f64, a: DVec3, b: DVec3, c: DVec3) -> Option<f64> {
    let normal = (b - a).cross(c - a).normalize_or_zero();
    if normal == DVec3::ZERO {
        return None;
    }
    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
    // Half-space (y - p) . m >= -offset, for y = o + t n.
    let mut clip = |p: DVec3, m: DVec3, offset: f64| -> bool {
        let dist = (o - p).dot(m) + offset;
        let rate = n.dot(m);
        if rate.abs() < 1e-300 {
            return dist >= 0.0;
        }
        let t = -dist / rate;
        if rate > 0.0 {
            lo = lo.max(t);
        } else {
            hi = hi.min(t);
        }
        lo <= hi
    };
    let inside = clip(a, normal, r)
        && clip(a, -normal, r)
        && clip(a, normal.cross(b - a), 0.0)
        && clip(b, normal.cross(c - b), 0.0)
        && clip(c, normal.cross(a - c), 0.0);
    (inside && hi.is_finite()).then_some(hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contact::closest_point_on_triangle;

    fn dist(y: DVec3, a: DVec3, b: DVec3, c: DVec3) -> f64 {
        (y - closest_point_on_triangle(y, a, b, c).0).length()
    }

    /// Independent reference: the distance along the line is convex, so scan for its minimum
    /// and bisect `dist = r` beyond it.
    fn exit_by_bisection(o: DVec3, n: DVec3, r: f64, a: DVec3, b: DVec3, c: DVec3) -> Option<f64> {
        let f = |t: f64| dist(o + n * t, a, b, c) - r;
        let (mut lo, mut hi) = (-10.0, 10.0);
        // Golden-section search for the minimum of the convex f.
        let g = (5f64.sqrt() - 1.0) / 2.0;
        for _ in 0..200 {
            let (x1, x2) = (hi - g * (hi - lo), lo + g * (hi - lo));
            if f(x1) < f(x2) {
                hi = x2;
            } else {
                lo = x1;
            }
        }
        let t_min = 0.5 * (lo + hi);
        if f(t_min) > 0.0 {
            return None;
        }
        let (mut inside, mut outside) = (t_min, 10.0);
        for _ in 0..200 {
            let mid = 0.5 * (inside + outside);
            if f(mid) <= 0.0 {
                inside = mid;
            } else {
                outside = mid;
            }
        }
        Some(inside)
    }

    /// A small deterministic generator (no test dependency on a random crate's streams).
    struct Lcg(u64);
    impl Lcg {
        fn unit(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
        fn vec(&mut self) -> DVec3 {
            DVec3::new(self.unit(), self.unit(), self.unit()) * 2.0 - 1.0
        }
    }

    #[test]
    fn sphere_exit_matches_bisection_on_random_triangles_and_lines() {
        let mut rng = Lcg(7);
        let (mut hits, mut misses) = (0, 0);
        for _ in 0..4000 {
            let (a, b, c) = (rng.vec(), rng.vec(), rng.vec());
            let o = rng.vec() * 1.5;
            let n = rng.vec().normalize();
            let r = 0.05 + 0.5 * rng.unit();
            let got = sphere_exit(o, n, r, a, b, c);
            let want = exit_by_bisection(o, n, r, a, b, c);
            match (got, want) {
                (Some(g), Some(w)) => {
                    hits += 1;
                    assert!((g - w).abs() < 1e-7, "exit {g} vs bisection {w}");
                    assert!((dist(o + n * g, a, b, c) - r).abs() < 1e-7);
                }
                (None, None) => misses += 1,
                // A line grazing the Minkowski sum: both sides agree to round-off.
                (g, w) => {
                    let t = g.or(w).unwrap();
                    assert!(
                        (dist(o + n * t, a, b, c) - r).abs() < 1e-6,
                        "disagreement {g:?} vs {w:?} away from a tangency"
                    );
                }
            }
        }
        assert!(hits > 500 && misses > 500, "{hits} hits, {misses} misses");
    }

    #[test]
    fn a_sphere_pushed_off_a_flat_triangle_rests_on_it() {
        let (a, b, c) = (
            DVec3::new(-1.0, -1.0, 0.0),
            DVec3::new(2.0, -1.0, 0.0),
            DVec3::new(-1.0, 2.0, 0.0),
        );
        // Centre 0.3 below the face, pushed up along +z: it leaves at z = +r.
        let t = sphere_exit(DVec3::new(0.1, 0.2, -0.3), DVec3::Z, 0.5, a, b, c).unwrap();
        assert!((t - 0.8).abs() < 1e-12, "{t}");
        // Pushed sideways past the hypotenuse x + y = 1 (distance to it r).
        let t = sphere_exit(DVec3::ZERO, DVec3::X, 0.5, a, b, c).unwrap();
        assert!((t - (1.0 + 0.5 * 2f64.sqrt())).abs() < 1e-12, "{t}");
        // A line that passes above the face at height 2r never touches it.
        assert!(sphere_exit(DVec3::new(0.0, 0.0, 1.0), DVec3::X, 0.5, a, b, c).is_none());
    }
}
