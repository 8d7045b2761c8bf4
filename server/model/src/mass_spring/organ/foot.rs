//! Where the organ table is read at run time: the probe's *foot* on the coarse rest surface.
//!
//! The calibration ([`super::calibrate_organ`]) presses a site (a coarse node, an edge's
//! midpoint) along its inward rest normal, so the sphere's centre stays on the line through the site's
//! rest position. At run time the factor is read where that line meets the rest surface: the
//! line through the probe's proxy centre along its contact normal, intersected with the coarse
//! rest triangles (the hit nearest the centre's expected distance `r - s`, `r` the probe's
//! radius and `s` its sphere depth). A press along a site's normal therefore reads exactly that
//! site's row, as the calibration measured it, however the dent deepens: read on the deformed
//! surface (the probe's contact triangle), the point left the pressed node for its edges' sites
//! as the dent deepened, whose factors are about half a node's on `hemisphere-springs`
//! (docs/accuracy.md, "The spring surfaces, session 5"). The foot moves continuously as the
//! probe slides, and the factor over the coarse triangles is continuous, so a stroke stays
//! smooth. On the coarse surface the factor itself is read at the same kind of foot of the
//! kernel patch's centroid (`MassSpringBody::patch_foot`, since session 6; in subdivided areas
//! too in session 15), which on a node, an edge's midpoint and a symmetric patch is this one;
//! in a subdivided area at this foot (session 16: the table's sites at the corner Loop
//! children's centroids, pressed along their own normals, have their foot there); the depth
//! and the subdivided area the press keeps are this foot's.
//!
//! The organ table's depth is read there too ([`foot_depth_m`]): the sphere's depth below the
//! flat rest triangle along the line, to which the body adds the organ's height over the
//! triangle (the arcs over its edges; in subdivided areas since session 12, on the coarse
//! surface since session 13, organ table version 4: the kernel plane's travel, the coarse key
//! until then, ran 0.02 mm ahead of the sphere's depth between nodes at the LV's lv-probe
//! point, +10 % at 0.25 mm).
//!
//! History: the kernel plane's travel (the depth everywhere until session 5) depends on which
//! nodes the probe's patch holds: a subdivided patch's plane sits lower at rest than the
//! coarse one's (0.1 mm at the pole of the 8 mm `hemisphere-springs`), so the same press read
//! another row subdivided than coarse. Keyed by the flat depth alone (session 5, without the
//! organ's height) the never-subdivided `lv-surface-springs` read -22 to -46 % at 0.25 mm (the
//! flat triangle lies inside a curved organ by the chord's sag between nodes); keyed by the
//! depth below the arcs on the 8 mm hemisphere, where the coarse spring surface is touched
//! 0.16 mm late between nodes, the factors grow to 495 at 0.1 mm (measured again in session
//! 13, and the reason that scene's mesh is 4 mm since).
//!
//! Neighbours: [`crate::mass_spring::MassSpringBody`] (calls [`rest_foot`] every sub-step in
//! contact, around the last foot), [`super::OrganTable`].

use glam::DVec3;

use crate::mass_spring::surface::SpringSurface;

/// Barycentric slack of the ray-triangle test (a hit on a shared edge or corner belongs to
/// every triangle there; the first found is kept).
const BARY_SLACK: f64 = 1e-9;

/// The probe's foot on a coarse rest triangle: the triangle and the barycentric weights of its
/// corners.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RestFoot {
    /// Coarse triangle index.
    pub triangle: u32,
    /// Barycentric weights of its corners (each in [0, 1], summing to 1).
    pub bary: [f64; 3],
    /// Distance from the line's origin (the proxy's centre) to the flat rest triangle along
    /// `-normal`, m (negative once the centre is below it).
    pub distance_m: f64,
}

/// A foot found by [`rest_foot`] and how far its hit lies from the expected distance along
/// the line, m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FootHit {
    /// The foot.
    pub foot: RestFoot,
    /// `|t - expected|`, m.
    pub miss_m: f64,
}

/// Where the line `origin - t * normal` (the proxy's centre, the outward contact normal) meets
/// triangle `tri` of `rest`: `(t, bary)`, or `None` when it misses (or runs parallel).
fn hit(rest: &[DVec3], tri: [u32; 3], origin: DVec3, normal: DVec3) -> Option<(f64, [f64; 3])> {
    let (a, b, c) = (
        rest[tri[0] as usize],
        rest[tri[1] as usize],
        rest[tri[2] as usize],
    );
    // Moller-Trumbore with direction -normal.
    let dir = -normal;
    let (e1, e2) = (b - a, c - a);
    let p = dir.cross(e2);
    let det = e1.dot(p);
    if det.abs() < 1e-30 {
        return None;
    }
    let inv = 1.0 / det;
    let s = origin - a;
    let u = s.dot(p) * inv;
    let q = s.cross(e1);
    let v = dir.dot(q) * inv;
    let t = e2.dot(q) * inv;
    let w = 1.0 - u - v;
    let inside = u >= -BARY_SLACK && v >= -BARY_SLACK && w >= -BARY_SLACK;
    inside.then(|| {
        let (u, v, w) = (u.max(0.0), v.max(0.0), w.max(0.0));
        let sum = u + v + w;
        (t, [w / sum, u / sum, v / sum])
    })
}

/// The probe's foot on `surface`'s coarse rest triangles (module documentation): the line from
/// the proxy centre `origin_m` along `-normal` (the outward contact normal, unit), the hit
/// whose distance along the line is nearest `expected_m` (`r - s`: negative once the centre
/// has sunk below the rest surface). The triangles around `hint` (the last foot's) are tried
/// first: a hit there within `tolerance_m` of `expected_m` is taken without a search over the
/// surface. `None` when the line meets no triangle (off a rim); the caller judges the miss. O(triangles) at worst,
/// allocation-free.
pub fn rest_foot(
    surface: &SpringSurface,
    origin_m: DVec3,
    normal: DVec3,
    expected_m: f64,
    tolerance_m: f64,
    hint: Option<u32>,
) -> Option<FootHit> {
    let rest = surface.rest();
    let tris = surface.triangles();
    let mut best: Option<(f64, RestFoot)> = None;
    let consider = |best: &mut Option<(f64, RestFoot)>, t_index: u32| {
        if let Some((t, bary)) = hit(rest, tris[t_index as usize], origin_m, normal) {
            let miss = (t - expected_m).abs();
            if best.is_none_or(|(m, _)| miss < m) {
                *best = Some((
                    miss,
                    RestFoot {
                        triangle: t_index,
                        bary,
                        distance_m: t,
                    },
                ));
            }
        }
    };
    if let Some(h) = hint.filter(|&h| (h as usize) < tris.len()) {
        consider(&mut best, h);
        for &corner in &tris[h as usize] {
            for &t in surface.triangles_at(corner) {
                consider(&mut best, t);
            }
        }
        if best.is_some_and(|(m, _)| m <= tolerance_m) {
            return best.map(|(miss_m, foot)| FootHit { foot, miss_m });
        }
    }
    for t in 0..tris.len() as u32 {
        consider(&mut best, t);
    }
    best.map(|(miss_m, foot)| FootHit { foot, miss_m })
}

/// The sphere depth at `foot` (module documentation), m: `radius_m - distance`, the sphere's
/// depth below the flat rest triangle along the line.
pub fn foot_depth_m(foot: &RestFoot, radius_m: f64) -> f64 {
    radius_m - foot.distance_m
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a flat hexagonal patch, the line through a node along the normal finds that node
    /// (weight 1 at its corner), and a line through an edge's midpoint weights 1/2 on its ends;
    /// the hint gives the same answer as the full search.
    #[test]
    fn the_foot_of_a_line_through_a_node_or_an_edge_midpoint_is_that_site() {
        let surface = SpringSurface::regular_hexagon(1e-3, 3);
        let rest = surface.rest();
        let n = DVec3::Z;
        let normal = if surface.rest_normal(0).dot(n) > 0.0 {
            n
        } else {
            -n
        };
        let node = 0u32;
        let origin = rest[node as usize] + normal * 1.5e-3;
        let hit = rest_foot(&surface, origin, normal, 1.5e-3, 1e-6, None).expect("a foot");
        assert!(hit.miss_m < 1e-12, "{}", hit.miss_m);
        assert!((hit.foot.distance_m - 1.5e-3).abs() < 1e-12);
        let foot = hit.foot;
        let tri = surface.triangles()[foot.triangle as usize];
        let k = tri
            .iter()
            .position(|&s| s == node)
            .expect("node on the triangle");
        assert!((foot.bary[k] - 1.0).abs() < 1e-9, "{:?}", foot.bary);
        let with_hint =
            rest_foot(&surface, origin, normal, 1.5e-3, 1e-6, Some(foot.triangle)).expect("hit");
        assert_eq!(with_hint.foot, foot);
        let [a, b] = surface.edges()[0];
        let mid = 0.5 * (rest[a as usize] + rest[b as usize]);
        let foot = rest_foot(&surface, mid - normal * 0.5e-3, normal, -0.5e-3, 1e-6, None)
            .expect("a foot")
            .foot;
        let tri = surface.triangles()[foot.triangle as usize];
        for end in [a, b] {
            let k = tri.iter().position(|&s| s == end).expect("end on triangle");
            assert!((foot.bary[k] - 0.5).abs() < 1e-9, "{:?}", foot.bary);
        }
    }
}
