//! [`SurfaceSampler`]: a displacement field of a triangulated surface read at fixed rest points,
//! so that bodies with different surfaces (meshes of different sizes, the hybrid model's outer
//! surface, a reference solve) can be compared at the same material points.

use glam::DVec3;

use super::closest_point_on_triangle;

/// Sample points located on a rest surface: for each point, the triangle holding its closest
/// point on the surface and the barycentric weights there.
#[derive(Debug, Clone)]
pub struct SurfaceSampler {
    located: Vec<([u32; 3], [f64; 3])>,
    /// Distance from each sample point to the surface at rest, m.
    distance_m: Vec<f64>,
}

impl SurfaceSampler {
    /// Locates `points` (m) on the surface of `triangles` over the rest vertices `rest` (m),
    /// each at its closest point (brute force over the triangles: meant for tens of points).
    ///
    /// # Panics
    /// If `triangles` is empty or names a vertex outside `rest`.
    pub fn new(rest: &[DVec3], triangles: &[[u32; 3]], points: &[DVec3]) -> Self {
        assert!(!triangles.is_empty(), "a surface to sample");
        let mut located = Vec::with_capacity(points.len());
        let mut distance_m = Vec::with_capacity(points.len());
        for &p in points {
            let mut best = (f64::INFINITY, [0u32; 3], [0.0; 3]);
            for t in triangles {
                let [a, b, c] = t.map(|i| rest[i as usize]);
                let (q, w) = closest_point_on_triangle(p, a, b, c);
                let d2 = (q - p).length_squared();
                if d2 < best.0 {
                    best = (d2, *t, w);
                }
            }
            located.push((best.1, best.2));
            distance_m.push(best.0.sqrt());
        }
        Self {
            located,
            distance_m,
        }
    }

    /// Distance from each sample point to the rest surface, m.
    pub fn distance_m(&self) -> &[f64] {
        &self.distance_m
    }

    /// The displacement (`x - rest`, m) at each sample point, interpolated linearly over its
    /// triangle; `x` and `rest` indexed like the vertices the sampler was built on.
    pub fn displacements(&self, rest: &[DVec3], x: &[DVec3]) -> Vec<DVec3> {
        self.located
            .iter()
            .map(|(t, w)| {
                t.iter()
                    .zip(w)
                    .map(|(&i, &w)| (x[i as usize] - rest[i as usize]) * w)
                    .sum()
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_affine_field_is_read_exactly_at_points_off_the_vertices() {
        // A unit sphere's octahedron subdivided once; an affine displacement u = A x + b is
        // linear over every triangle, so the interpolation at any point is exact.
        let rest = vec![
            DVec3::X,
            DVec3::Y,
            DVec3::Z,
            -DVec3::X,
            -DVec3::Y,
            -DVec3::Z,
        ];
        let triangles = [
            [0, 1, 2],
            [1, 3, 2],
            [3, 4, 2],
            [4, 0, 2],
            [1, 0, 5],
            [3, 1, 5],
            [4, 3, 5],
            [0, 4, 5],
        ];
        let a = glam::DMat3::from_cols(
            DVec3::new(0.01, -0.02, 0.03),
            DVec3::new(0.005, 0.0, -0.01),
            DVec3::new(-0.02, 0.04, 0.01),
        );
        let b = DVec3::new(1e-3, -2e-3, 5e-4);
        let x: Vec<DVec3> = rest.iter().map(|p| *p + a * *p + b).collect();
        // Points inside faces, on an edge and off the surface (projected onto it).
        let points = [
            DVec3::new(0.3, 0.3, 0.4),
            DVec3::new(-0.2, 0.5, -0.3),
            DVec3::new(0.5, 0.5, 0.0),
            DVec3::new(0.6, 0.6, 0.6),
        ];
        let s = SurfaceSampler::new(&rest, &triangles, &points);
        for (k, u) in s.displacements(&rest, &x).iter().enumerate() {
            // The located point: the closest point on the octahedron (x + y + z = 1 octant
            // face for points 0, 2, 3; the (-x, +y, -z) face for point 1).
            let p = points[k];
            let n = DVec3::new(p.x.signum(), p.y.signum(), p.z.signum()) / 3f64.sqrt();
            let q = p - n * (p.dot(n) - 1.0 / 3f64.sqrt());
            let exact = a * q + b;
            assert!((*u - exact).length() < 1e-14, "{k}: {u} vs {exact}");
        }
        assert!(s.distance_m()[0] < 1e-12 && s.distance_m()[3] > 0.1);
    }
}
