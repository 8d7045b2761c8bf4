//! Where the hybrid body's probe touches its particles ([`haptic_model::hybrid::proxy`]): the
//! outer surface's depth function against the exact distance, and the sphere's first contact
//! with the particles at rest against its first contact with the body's analytic surface,
//! whatever the lattice's spacing and alignment.

use glam::DVec3;
use haptic_model::hybrid::{HybridParams, ShellGeometry, prepare};
use haptic_model::material::MaterialParams;
use haptic_model::meshfree::{KernelKind, MeshfreeParams, MeshfreeVariant};

const MM: f64 = 1e-3;

fn ellipsoids() -> ShellGeometry {
    ShellGeometry {
        inner_m: DVec3::new(6.0, 6.0, 12.0) * MM,
        outer_m: DVec3::new(10.0, 10.0, 16.0) * MM,
        z_cut_m: None,
    }
}

/// The outer surface's point at polar angle `theta` and azimuth `phi` and its unit normal.
fn surface_point(g: &ShellGeometry, theta: f64, phi: f64) -> (DVec3, DVec3) {
    let a = g.outer_m;
    let p = DVec3::new(
        a.x * theta.sin() * phi.cos(),
        a.y * theta.sin() * phi.sin(),
        a.z * theta.cos(),
    );
    (p, (p / (a * a)).normalize())
}

#[test]
fn the_outer_depth_is_the_distance_along_the_normal() {
    // On a sphere exactly R - |x|.
    let sphere = ShellGeometry {
        inner_m: DVec3::splat(6.0 * MM),
        outer_m: DVec3::splat(10.0 * MM),
        z_cut_m: None,
    };
    for (theta, phi) in [(0.3, 0.1), (1.5, 2.0), (2.8, -1.0)] {
        let (p, n) = surface_point(&sphere, theta, phi);
        for d in [0.0, 0.05 * MM, 0.3 * MM, -0.1 * MM] {
            let got = sphere.outer_depth_m(p - n * d);
            assert!((got - d).abs() < 1e-12, "{got} against {d}");
        }
    }
    // On the ellipsoid the point `d` below a surface point along its normal is `d` deep (the
    // surface point is its nearest for `d` below the smallest radius of curvature, 3.9 mm):
    // within 0.5 % of `d`.
    let g = ellipsoids();
    for (theta, phi) in [(0.2, 0.0), (0.9, 0.7), (1.57, 1.2), (2.5, -2.0)] {
        let (p, n) = surface_point(&g, theta, phi);
        for d in [0.02 * MM, 0.13 * MM, 0.3 * MM] {
            let got = g.outer_depth_m(p - n * d);
            assert!((got / d - 1.0).abs() < 5e-3, "{got} against {d}");
        }
    }
}

/// The sphere's depth (m) past touching the analytic surface at `p` (normal `n`) at which it
/// first reaches a layer particle of `rest` (`layer` of them) with reach `r + skin[i]`.
fn first_contact_depth_m(
    rest: &[DVec3],
    layer: usize,
    skin: &[f64],
    r: f64,
    p: DVec3,
    n: DVec3,
) -> f64 {
    // Centre c(d) = p + n (r - d); |x - c(d)| = r + t  <=>  d^2 + 2 d (q . n) + |q|^2 - R^2 = 0
    // with q = x - p - n r, R = r + t; the first contact is the smaller root.
    let mut first = f64::INFINITY;
    for (i, &x) in rest[..layer].iter().enumerate() {
        if (x - p).length() > 2.0 * MM {
            continue;
        }
        let q = x - p - n * r;
        let reach = r + skin[i];
        let b = q.dot(n);
        let disc = b * b - q.length_squared() + reach * reach;
        if disc >= 0.0 {
            first = first.min(-b - disc.sqrt());
        }
    }
    first
}

#[test]
fn the_probe_touches_the_particles_where_it_touches_the_surface() {
    // A 2 mm sphere pressed along the normal at eight points of the ellipsoids' outer surface,
    // on lattices of 0.5, 0.45 and 0.4 mm: with each surface particle's skin (its rest depth)
    // the first contact is within 0.1 s of the analytic surface's (later by at most the sag
    // between particles, s^2 / 8 R); with a uniform skin of s / 2 it is off by up to s / 2.
    let r = 2.0 * MM;
    let material = MaterialParams::from_youngs(10e3, 0.45, 1060.0);
    for spacing in [0.5 * MM, 0.45 * MM, 0.4 * MM] {
        let params = HybridParams {
            meshfree: MeshfreeParams {
                variant: MeshfreeVariant::Corrected,
                kernel: KernelKind::default_for(MeshfreeVariant::Corrected),
                spacing_m: spacing,
                ..MeshfreeParams::default()
            },
            surface_target_tets: 2000,
            ..HybridParams::default()
        };
        let model =
            prepare(ellipsoids(), &params, &material, 100, &mut |_, _| {}).expect("prepare");
        let rest = model.cloud.rest_m();
        let skin = model.contact_skin_m();
        let uniform = vec![0.5 * spacing; rest.len()];
        let (mut worst_skin, mut worst_uniform): (f64, f64) = (0.0, 0.0);
        for k in 0..8 {
            let (theta, phi) = (0.4 + 0.3 * k as f64, 0.77 * k as f64);
            let (p, n) = surface_point(&model.geometry, theta, phi);
            let with_skin = first_contact_depth_m(rest, model.layer_count, &skin, r, p, n);
            let with_uniform = first_contact_depth_m(rest, model.layer_count, &uniform, r, p, n);
            eprintln!(
                "s {:.2} mm, point {k}: first contact {:+.4} mm with the skin, {:+.4} mm with s / 2",
                spacing / MM,
                with_skin / MM,
                with_uniform / MM
            );
            worst_skin = worst_skin.max(with_skin.abs());
            worst_uniform = worst_uniform.max(with_uniform.abs());
        }
        assert!(
            worst_skin <= 0.1 * spacing,
            "s {spacing}: {worst_skin} m off"
        );
        assert!(
            worst_uniform > 0.2 * spacing,
            "s {spacing}: the uniform skin is off by {worst_uniform} m only"
        );
    }
}
