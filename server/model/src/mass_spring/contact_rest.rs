//! Where the probe meets a mass-spring surface at rest: the *contact positions* the probe's
//! kernel patch sees, offset from the nodes so that the patch's plane passes through the surface
//! the nodes sample.
//!
//! The kernel patch ([`crate::contact`]) puts its plane through the weighted centroid of the nodes
//! within `2 r` of the device. On a convex surface that centroid lies inside the surface, by
//! about `sum w_i rho_i^2 kappa / 2` (0.1 mm at the lv-probe point of the left ventricle, 0.2-0.3
//! mm near its apex, with a 2 mm probe): the probe would touch 0.1-0.3 mm late, which at a
//! 0.25 mm press is most of the depth. And Loop's edge rule puts the new nodes of a subdivided
//! area inside a convex surface (0.05-0.1 mm on the LV surface, 0.2-0.4 mm on the hemisphere):
//! there the subdivided surface would be touched later still. So every slot gets a contact
//! position at rest:
//!
//! - a coarse node `i`: `rest_i + delta_i n_i` (`n_i` its rest normal), with `delta_i` such that
//!   the probe's plane, for the device `r` above node `i` along `n_i`, passes through node `i`:
//!   Jacobi iterations over the nodes of [`PLANE_SAG_ITERATIONS`], each moving `delta_i` by the
//!   plane's remaining sag at node `i` (its neighbours' offsets lift the plane too);
//! - a coarse edge's slot (the type-2 node of subdivision): the point over the edge's midpoint on
//!   the circular arc through its ends with their rest normals (`(c / 2) tan(theta / 4)` beyond
//!   the chord's midpoint, `c` the chord, `theta` the angle between the normals), raised by the
//!   mean `delta` of its ends, so that a subdivided area is touched where the coarse one is.
//!
//! At run time a slot's contact position is its position plus `contact_rest - rest`; the
//! springs, masses and the viewer keep the nodes' own positions. Used by the body and by the
//! calibration patches (the same probe sees the same surface in both).
//!
//! Neighbours: [`super::surface`] (the coarse surface), [`crate::contact::Probe`] (the plane).

use glam::DVec3;

use super::surface::SpringSurface;
use crate::contact::{ContactModel, ContactSurface, PATCH_RADIUS_FACTOR, ProbeParams};

/// Jacobi sweeps of the plane-sag offsets (the remaining sag shrinks by about a factor 3-5 per
/// sweep on the shipped surfaces; [`contact_rest_positions`] reports what is left).
pub const PLANE_SAG_ITERATIONS: usize = 12;

/// The contact positions of a surface's slots at rest (module documentation) and the largest
/// plane sag left at a free node after the iterations (m; 0 when the probe's contact is not
/// the kernel patch, which gets no offsets: the sphere contact meets the triangles themselves).
#[derive(Debug, Clone)]
pub struct ContactRest {
    /// Per slot (the coarse nodes, then one per coarse edge), m.
    pub positions: Vec<DVec3>,
    /// Per coarse node, the offset `delta_i` along its rest normal, m.
    pub node_offset_m: Vec<f64>,
    /// The largest remaining plane sag at a free node, m.
    pub residual_m: f64,
}

/// Whether the probe `params` meets the surface through the kernel patch (the contact the
/// offsets correct).
pub fn uses_patch(params: &ProbeParams) -> bool {
    matches!(
        params.contact,
        ContactModel::Auto | ContactModel::Patch | ContactModel::PatchHertz
    )
}

/// The point over the middle of the chord `a b` on the circular arc through `a` and `b` with
/// unit normals `na`, `nb` there (m), and that arc's normal; the chord's midpoint and the mean
/// normal when the normals agree.
pub fn arc_midpoint(a: DVec3, b: DVec3, na: DVec3, nb: DVec3) -> (DVec3, DVec3) {
    let mid = 0.5 * (a + b);
    let n = (na + nb).normalize_or_zero();
    let theta = na.dot(nb).clamp(-1.0, 1.0).acos();
    if n == DVec3::ZERO || !(theta > 1e-12) {
        return (mid, n);
    }
    // Diverging normals along the chord: a convex arc, bulging outward.
    let sign = if (nb - na).dot(b - a) >= 0.0 {
        1.0
    } else {
        -1.0
    };
    let h = 0.5 * (b - a).length() * (0.25 * theta).tan();
    (mid + n * (sign * h), n)
}

/// The contact positions at rest of `surface` for the probe `params` (module documentation).
pub fn contact_rest_positions(surface: &SpringSurface, params: ProbeParams) -> ContactRest {
    let nc = surface.node_count();
    let rest = surface.rest();
    let mut delta = vec![0.0; nc];
    let mut residual: f64 = 0.0;
    if uses_patch(&params) {
        // The probe's plane for the device `r` above node `i` along `n_i` (where the sphere
        // touches the node): the kernel patch of the nodes within `2 r` of the device and its
        // weighted normal, exactly as `Probe::update` builds it.
        let surf = ContactSurface::new(surface.triangles().to_vec(), nc);
        let r = params.radius_m;
        let (mut nodes, mut weights) = (Vec::new(), Vec::new());
        let mut cx = rest.to_vec();
        let mut sag = vec![0.0; nc];
        for _ in 0..PLANE_SAG_ITERATIONS {
            residual = 0.0;
            for i in 0..nc {
                let n = surface.rest_normal(i as u32);
                let device = rest[i] + n * r;
                let seed = surface.triangles_at(i as u32)[0];
                surf.gather_kernel_patch(
                    &cx,
                    device,
                    seed,
                    PATCH_RADIUS_FACTOR * r,
                    &mut nodes,
                    &mut weights,
                );
                let (mut centre, mut normal) = (DVec3::ZERO, DVec3::ZERO);
                for (&j, &w) in nodes.iter().zip(&weights) {
                    centre += cx[j as usize] * w;
                    normal += surf.vertex_normal(j, &cx) * w;
                }
                let m = normal.normalize_or_zero();
                // The plane lies `sag` below the node where the probe would touch it.
                sag[i] = if m == DVec3::ZERO {
                    0.0
                } else {
                    (device - centre).dot(m) - r
                };
                if !surface.is_fixed(i as u32) {
                    residual = residual.max(sag[i].abs());
                }
            }
            for i in 0..nc {
                delta[i] += sag[i];
                cx[i] = rest[i] + surface.rest_normal(i as u32) * delta[i];
            }
        }
    }
    let mut positions: Vec<DVec3> = (0..nc)
        .map(|i| rest[i] + surface.rest_normal(i as u32) * delta[i])
        .collect();
    for &[a, b] in surface.edges() {
        let (na, nb) = (surface.rest_normal(a), surface.rest_normal(b));
        let (arc, n) = arc_midpoint(rest[a as usize], rest[b as usize], na, nb);
        let d = if uses_patch(&params) {
            0.5 * (delta[a as usize] + delta[b as usize])
        } else {
            0.0
        };
        positions.push(arc + n * d);
    }
    ContactRest {
        positions,
        node_offset_m: delta,
        residual_m: residual,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_arc_midpoint_lies_on_the_circle() {
        let r = 0.01;
        let (ta, tb) = (0.3_f64, 0.7_f64);
        let a = DVec3::new(ta.cos(), ta.sin(), 0.0) * r;
        let b = DVec3::new(tb.cos(), tb.sin(), 0.0) * r;
        let (p, n) = arc_midpoint(a, b, a / r, b / r);
        assert!((p.length() - r).abs() < 1e-15, "{}", p.length() - r);
        assert!((n - p / r).length() < 1e-12);
        // Concave side: the arc of a hole bulges the other way.
        let (q, _) = arc_midpoint(a, b, -a / r, -b / r);
        assert!((q.length() - r).abs() < 1e-15);
    }
}
