//! The haptic probe's contact models ([`haptic_model::contact`]) on their own: kernel patches
//! are partitions of unity, the sphere's proxy penetrates no triangle and its load sits on the
//! faces it touches, the coupling conserves linear momentum exactly, the proxy stays outside the
//! surface, and the contact force changes continuously while the probe slides over a curved
//! surface (no jump when nodes or faces enter or leave the contact).

use haptic_model::DVec3;
use haptic_model::contact::{ContactModel, ContactSurface, Probe, ProbeParams};
use haptic_model::mesh::TetMesh;
use haptic_model::mesh::generate::{box_mesh, sphere_shell};

/// A 20 x 20 x 5 mm block with 1 mm cells and its top face (z = 5 mm).
fn block() -> (TetMesh, Vec<[u32; 3]>) {
    let mesh = box_mesh(DVec3::new(0.02, 0.02, 0.005), [20, 20, 5]);
    let top = mesh.surface("ZMAX").expect("top face").triangles.clone();
    (mesh, top)
}

fn params(contact: ContactModel) -> ProbeParams {
    ProbeParams {
        contact,
        radius_m: 2e-3,
        coupling_stiffness_n_per_m: 300.0,
        coupling_damping_n_s_per_m: 0.05,
        max_force_n: 10.0,
        friction_coefficient: 0.0,
        hertz_modulus_pa: 0.0,
    }
}

#[test]
fn kernel_patch_weights_are_a_partition_of_unity() {
    let (mesh, top) = block();
    let x = &mesh.nodes;
    let surface = ContactSurface::new(top, x.len());
    let (mut nodes, mut weights) = (Vec::new(), Vec::new());
    for q in [
        DVec3::new(0.010, 0.010, 0.0055),
        DVec3::new(0.0103, 0.0071, 0.0062),
        DVec3::new(0.0005, 0.0195, 0.0051), // near a corner: a truncated patch
    ] {
        let seed = surface.closest_global(x, q).unwrap().triangle;
        let reach = 4e-3;
        surface.gather_kernel_patch(x, q, seed, reach, &mut nodes, &mut weights);
        assert!(nodes.len() >= 3, "{q}: {} nodes", nodes.len());
        let sum: f64 = weights.iter().sum();
        assert!((sum - 1.0).abs() < 1e-12, "{q}: weights sum to {sum}");
        assert!(weights.iter().all(|w| *w > 0.0));
        // Each weight is the kernel (1 - d^2/R^2)^2 times one normalising constant.
        let scale = weights[0] / kernel(x[nodes[0] as usize], q, reach);
        for (&i, w) in nodes.iter().zip(&weights) {
            let d = (x[i as usize] - q).length();
            assert!(d < reach, "node {i} at {d} m is outside the patch");
            let ratio = w / kernel(x[i as usize], q, reach);
            assert!(
                (ratio - scale).abs() < 1e-9 * scale,
                "node {i}: {ratio} against {scale}"
            );
        }
        let mut sorted = nodes.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), nodes.len(), "a node appears twice");
    }
    // Nothing within reach: an empty patch, not a division by zero.
    let far = DVec3::new(0.010, 0.010, 0.02);
    surface.gather_kernel_patch(x, far, 0, 4e-3, &mut nodes, &mut weights);
    assert!(nodes.is_empty() && weights.is_empty());
}

fn kernel(p: DVec3, q: DVec3, reach: f64) -> f64 {
    let u = 1.0 - (p - q).length_squared() / (reach * reach);
    u * u
}

/// On a flat face the smoothed plane is the face itself: the proxy sits exactly one probe
/// radius above it, the force is `k (r - s)` along the outward normal.
#[test]
fn the_proxy_stays_outside_a_flat_surface() {
    for contact in [ContactModel::Patch, ContactModel::Sphere] {
        proxy_on_a_flat_surface(contact);
    }
}

/// On a flat face both models put the proxy exactly one radius above the face; the sphere's
/// load sits on the faces within its contact band (gap below the coupling's stretch `t`), whose
/// nodes lie within `sqrt(2 r t + t^2)` of the axis plus one cell.
fn proxy_on_a_flat_surface(contact: ContactModel) {
    let (mesh, top) = block();
    let x = &mesh.nodes;
    let p = params(contact);
    let mut probe = Probe::new(p, top, x);
    for (depth, dx) in [(0.2e-3, 0.0), (1.0e-3, 0.3e-3), (2.5e-3, -0.7e-3)] {
        // Device centre `depth` below the position where the sphere touches the face.
        let device = DVec3::new(0.01 + dx, 0.01, 0.005 + p.radius_m - depth);
        let c = probe.update(x, device, DVec3::ZERO);
        assert!(c.in_contact, "depth {depth}");
        assert!((c.normal - DVec3::Z).length() < 1e-12, "{}", c.normal);
        assert!(
            (c.proxy_m.z - (0.005 + p.radius_m)).abs() < 1e-12,
            "proxy {} is not one radius above the face",
            c.proxy_m
        );
        assert!((c.proxy_m.truncate() - device.truncate()).length() < 1e-12);
        let expected = p.coupling_stiffness_n_per_m * depth;
        assert!(
            (c.force_on_device_n - DVec3::Z * expected).length() < 1e-12,
            "{} against {expected}",
            c.force_on_device_n
        );
        if contact == ContactModel::Sphere {
            let (nodes, weights) = probe.patch();
            let t = depth;
            let footprint = (2.0 * p.radius_m * t + t * t).sqrt() + 1e-3 * 2f64.sqrt();
            for &i in nodes {
                let lateral = (x[i as usize] - device).truncate().length();
                assert!(lateral < footprint, "depth {depth}: node at {lateral} m");
            }
            assert!((weights.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!(!nodes.is_empty());
        }
    }
    // Above the face: no contact, the proxy is the device point.
    let device = DVec3::new(0.01, 0.01, 0.005 + p.radius_m + 1e-4);
    let c = probe.update(x, device, DVec3::ZERO);
    assert!(!c.in_contact && c.proxy_m == device && c.force_on_device_n == DVec3::ZERO);
}

/// The patch with the Hertz compliance in series on a rigid flat face: for the device `D`
/// below the touching position, the force `F` satisfies the series law written the other way
/// round, `D = F / k + (F / K)^(2/3)` with `K = 4/3 E* r^(1/2)` (Johnson 1985, eq. 4.23), the
/// proxy sinks `(F / K)^(2/3)` into the face, and the stiffness the implicit coupling uses
/// (from `coupling_gamma`) is the slope of `F(D)` by central differences.
#[test]
fn the_hertz_patch_puts_a_hertz_spring_in_series_with_the_coupling() {
    let (mesh, top) = block();
    let x = &mesh.nodes;
    let e_star = 14_500.0 / (1.0 - 0.45 * 0.45);
    let p = ProbeParams {
        hertz_modulus_pa: e_star,
        ..params(ContactModel::PatchHertz)
    };
    let (k, r) = (p.coupling_stiffness_n_per_m, p.radius_m);
    let hertz_k = 4.0 / 3.0 * e_star * r.sqrt();
    let mut probe = Probe::new(p, top, x);
    let mut force_at = |depth: f64| {
        let device = DVec3::new(0.01, 0.01, 0.005 + r - depth);
        let c = probe.update(x, device, DVec3::ZERO);
        assert!(c.in_contact, "depth {depth}");
        (c, probe.coupling_gamma(1e-3))
    };
    for depth in [1e-6, 0.1e-3, 0.5e-3, 1e-3, 3e-3] {
        let (c, gamma) = force_at(depth);
        let f = c.force_on_device_n.z;
        assert!((c.force_on_device_n - DVec3::Z * f).length() < 1e-15 && f > 0.0);
        let delta = (f / hertz_k).powf(2.0 / 3.0);
        let back = f / k + delta;
        assert!(
            (back - depth).abs() < 1e-9 * depth,
            "depth {depth}: the force {f} N gives back {back} m"
        );
        let sink = 0.005 + r - c.proxy_m.z;
        assert!(
            (sink - delta).abs() < 1e-9 * depth,
            "{sink} against {delta}"
        );
        // The coupling's stiffness in the implicit term: gamma = dt (k_s dt + b).
        let k_series = (gamma / 1e-3 - p.coupling_damping_n_s_per_m) / 1e-3;
        let h = 1e-3 * depth;
        let slope = (force_at(depth + h).0.force_on_device_n.z
            - force_at(depth - h).0.force_on_device_n.z)
            / (2.0 * h);
        assert!(
            (k_series - slope).abs() < 1e-5 * slope,
            "depth {depth}: series stiffness {k_series} against the slope {slope} N/m"
        );
        assert!(k_series < k);
    }
    // Far softer tissue than the coupling: nearly all the depth is Hertz indentation; a
    // stiff one: nearly all of it is the coupling's stretch.
    for (e, share) in [(1.0, 0.99), (1e9, 0.01)] {
        let mut probe = Probe::new(
            ProbeParams {
                hertz_modulus_pa: e,
                ..p
            },
            mesh.surface("ZMAX").unwrap().triangles.clone(),
            x,
        );
        let c = probe.update(x, DVec3::new(0.01, 0.01, 0.005 + r - 1e-3), DVec3::ZERO);
        let sink = 0.005 + r - c.proxy_m.z;
        if share > 0.5 {
            assert!(sink > share * 1e-3, "E* = {e}: sink {sink}");
        } else {
            assert!(sink < share * 1e-3, "E* = {e}: sink {sink}");
        }
    }
}

/// The coupling's force on the body is minus the device force over the same patch: after a
/// step completed implicitly (here with a lumped mass per node), the body's momentum change is
/// exactly `-dt F_device`.
#[test]
fn the_coupling_reaction_conserves_linear_momentum() {
    for contact in [
        ContactModel::Patch,
        ContactModel::Sphere,
        ContactModel::PatchHertz,
    ] {
        for friction_coefficient in [0.0, 0.4] {
            momentum_is_conserved(ProbeParams {
                friction_coefficient,
                hertz_modulus_pa: 18_000.0,
                ..params(contact)
            });
        }
    }
}

fn momentum_is_conserved(p: ProbeParams) {
    let (mesh, top) = block();
    let x0 = mesh.nodes.clone();
    let n = x0.len();
    let mass_kg = 2e-4;
    let dt = 1e-4;
    let mut probe = Probe::new(p, top, &x0);
    for (device, velocity) in [
        (DVec3::new(0.01, 0.01, 0.0062), DVec3::ZERO),
        (
            DVec3::new(0.0123, 0.0081, 0.0058),
            DVec3::new(0.01, -0.02, -0.05),
        ),
    ] {
        let mut x = x0.clone();
        let c = probe.update(&x, device, velocity);
        assert!(c.in_contact);
        // Explicit part: the reaction on the patch, then a symplectic Euler velocity.
        let mut f = vec![DVec3::ZERO; n];
        probe.add_reaction(&mut f);
        let explicit_total: DVec3 = f.iter().sum();
        assert!((explicit_total + c.force_on_device_n).length() < 1e-14);
        let mut v: Vec<DVec3> = f.iter().map(|fi| *fi * (dt / mass_kg)).collect();
        // Implicit completion of the coupling.
        probe.finish_implicit(dt, &mut x, &mut v, |_, w| w / mass_kg);
        let device_force = probe.state.force_on_device_n;
        let momentum: DVec3 = v.iter().map(|vi| *vi * mass_kg).sum();
        let expected = -device_force * dt;
        assert!(
            (momentum - expected).length() <= 1e-12 * expected.length(),
            "body momentum {momentum} against -dt F_device {expected}"
        );
        // Only the patch moved.
        let (patch, _) = probe.patch();
        for (i, vi) in v.iter().enumerate() {
            if !patch.contains(&(i as u32)) {
                assert_eq!(*vi, DVec3::ZERO);
            }
        }
    }
}

/// Sliding over a sphere at constant depth: the force is the same everywhere up to the
/// faceting of the mesh, and changes continuously from one position to the next (nodes enter
/// and leave the patch with zero weight), where a plain closest-point contact jumps at every
/// triangle edge.
#[test]
fn the_patch_force_is_continuous_while_sliding() {
    let (ri, ro) = (0.006, 0.010);
    let mesh = sphere_shell(ri, ro, 3000);
    let outer = mesh.surface("OUTER").expect("outer").triangles.clone();
    let x = &mesh.nodes;
    let p = params(ContactModel::Patch);
    let surface = ContactSurface::new(outer.clone(), x.len());
    let mut probe = Probe::new(p, outer, x);
    // The proxy is one radius outside the smoothed plane through the patch's weighted centre,
    // which on a convex surface lies below the surface by at most the sagitta of the patch
    // (radius 2 r) on a sphere of radius R: (2 r)^2 / (2 R).
    let sagitta = (2.0 * p.radius_m).powi(2) / (2.0 * ro);
    let depth = 0.5e-3;
    let centre_distance = ro + p.radius_m - depth;
    let steps = 400;
    let mut forces = Vec::with_capacity(steps);
    for k in 0..steps {
        // A quarter of a great circle in the x-z plane, 0.04 mm per step.
        let a = 0.1 + 1.2 * k as f64 / steps as f64;
        let device = DVec3::new(a.cos(), 0.0, a.sin()) * centre_distance;
        let c = probe.update(x, device, DVec3::ZERO);
        assert!(c.in_contact, "step {k}");
        // Proxy outside the body, about one radius from its (faceted) surface.
        let dist = surface.closest_global(x, c.proxy_m).unwrap().dist2.sqrt();
        assert!(
            c.proxy_m.length() > ro && dist > p.radius_m - sagitta,
            "step {k}: proxy {dist} m from the surface"
        );
        forces.push(c.force_on_device_n);
    }
    let mean = forces.iter().map(|f| f.length()).sum::<f64>() / steps as f64;
    // The force points away from the centre, within the faceting.
    for (k, f) in forces.iter().enumerate() {
        let a = 0.1 + 1.2 * k as f64 / steps as f64;
        let radial = DVec3::new(a.cos(), 0.0, a.sin());
        assert!(f.normalize().dot(radial) > 0.99, "step {k}: {f}");
        assert!(
            (f.length() - mean).abs() < 0.25 * mean,
            "step {k}: {f} against {mean}"
        );
    }
    let largest_jump: f64 = forces
        .windows(2)
        .map(|w| (w[1] - w[0]).length())
        .fold(0.0, f64::max);
    println!("mean {mean:.4e} N, largest jump {largest_jump:.3e} N");
    assert!(
        largest_jump < 0.02 * mean,
        "force jumped by {largest_jump:.3e} N between neighbouring positions (mean {mean:.3e} N)"
    );
}

/// The sphere slid over a faceted sphere at constant depth: its proxy penetrates no triangle
/// (every triangle at least `r` away, to round-off) and touches at least one (within the
/// contact band), the force points away from the centre and changes continuously from one
/// position to the next (faces enter and leave the band with zero weight).
#[test]
fn the_sphere_force_is_continuous_while_sliding_and_never_penetrates() {
    let (ri, ro) = (0.006, 0.010);
    let mesh = sphere_shell(ri, ro, 3000);
    let outer = mesh.surface("OUTER").expect("outer").triangles.clone();
    let x = &mesh.nodes;
    let p = params(ContactModel::Sphere);
    let surface = ContactSurface::new(outer.clone(), x.len());
    let mut probe = Probe::new(p, outer, x);
    let depth = 0.5e-3;
    let centre_distance = ro + p.radius_m - depth;
    let steps = 400;
    let mut forces = Vec::with_capacity(steps);
    for k in 0..steps {
        let a = 0.1 + 1.2 * k as f64 / steps as f64;
        let device = DVec3::new(a.cos(), 0.0, a.sin()) * centre_distance;
        let c = probe.update(x, device, DVec3::ZERO);
        assert!(c.in_contact, "step {k}");
        let gap = surface.closest_global(x, c.proxy_m).unwrap().dist2.sqrt() - p.radius_m;
        let stretch = (c.proxy_m - device).length();
        assert!(
            gap > -1e-12 && gap < 0.01 * p.radius_m,
            "step {k}: the proxy sphere is {gap:e} m from the surface"
        );
        assert!(
            (c.force_on_device_n.length() - p.coupling_stiffness_n_per_m * stretch).abs() < 1e-12
        );
        forces.push(c.force_on_device_n);
    }
    let mean = forces.iter().map(|f| f.length()).sum::<f64>() / steps as f64;
    for (k, f) in forces.iter().enumerate() {
        let a = 0.1 + 1.2 * k as f64 / steps as f64;
        let radial = DVec3::new(a.cos(), 0.0, a.sin());
        assert!(f.normalize().dot(radial) > 0.99, "step {k}: {f}");
        assert!(
            (f.length() - mean).abs() < 0.25 * mean,
            "step {k}: {f} against {mean}"
        );
    }
    let largest_jump: f64 = forces
        .windows(2)
        .map(|w| (w[1] - w[0]).length())
        .fold(0.0, f64::max);
    println!("mean {mean:.4e} N, largest jump {largest_jump:.3e} N");
    assert!(
        largest_jump < 0.02 * mean,
        "force jumped by {largest_jump:.3e} N between neighbouring positions (mean {mean:.3e} N)"
    );
}

/// Coulomb friction on a flat face (the surface held fixed): the proxy sticks where it touched,
/// so a small tangential move of the device gives the tangential force `k delta` against it;
/// a larger one slides the proxy at the cone's edge (`|F_t| = mu F_n`, the proxy trailing the
/// device by `mu F_n / k`); moving back sticks again. Frictionless, no tangential force at all.
#[test]
fn friction_sticks_within_the_cone_and_slides_at_its_edge() {
    let (mesh, top) = block();
    let x = &mesh.nodes;
    for contact in [ContactModel::Patch, ContactModel::Sphere] {
        let mu = 0.5;
        let p = ProbeParams {
            friction_coefficient: mu,
            ..params(contact)
        };
        let k = p.coupling_stiffness_n_per_m;
        let mut probe = Probe::new(p, top.clone(), x);
        let depth = 1e-3;
        let device = |dx: f64| DVec3::new(0.01 + dx, 0.01, 0.005 + p.radius_m - depth);
        let normal_n = k * depth;
        let c = probe.update(x, device(0.0), DVec3::ZERO);
        assert!((c.force_on_device_n - DVec3::Z * normal_n).length() < 1e-12);
        // (device travel along x, expected tangential force along x).
        for (dx, expected) in [
            (0.1e-3, -k * 0.1e-3),                 // stick
            (1.2e-3, -mu * normal_n),              // slide: trailing by mu F_n / k = 0.5 mm
            (1.0e-3, -mu * normal_n + k * 0.2e-3), // back 0.2 mm: stick again
        ] {
            let c = probe.update(x, device(dx), DVec3::ZERO);
            let f = c.force_on_device_n;
            assert!((f.z - normal_n).abs() < 1e-12, "{contact:?} {dx}: {f}");
            assert!(
                (f.x - expected).abs() < 1e-9 && f.y.abs() < 1e-12,
                "{contact:?} travel {dx}: tangential {f} against {expected}"
            );
            assert!(f.x.abs() <= mu * f.z + 1e-12, "outside the cone: {f}");
            assert!(((c.proxy_m - device(dx)).x * k - f.x).abs() < 1e-9);
        }
        let mut frictionless = Probe::new(params(contact), top.clone(), x);
        frictionless.update(x, device(0.0), DVec3::ZERO);
        let f = frictionless
            .update(x, device(1e-3), DVec3::ZERO)
            .force_on_device_n;
        assert!(f.x.abs() < 1e-12 && f.y.abs() < 1e-12, "{f}");
    }
}

/// The implicit sphere of backward Euler ([`Probe::use_implicit_sphere`]): the body's contact
/// force, explicit part plus the implicit term `-h A^T C A v'` evaluated at any end-of-step
/// velocities, is exactly minus the device force (linear momentum conserved), and on a flat
/// face at rest the force is the coupling's `k` times the device's depth below the proxy's
/// rest position (a sphere resting on the face), along the face normal, with the proxy outside
/// the face up to the penalty's penetration (half its onset band plus the force over its
/// stiffness, [`haptic_model::contact::probe::PENALTY_FACTOR`] k).
#[test]
fn the_implicit_sphere_conserves_momentum_and_rests_on_a_flat_face() {
    let (mesh, top) = block();
    let x = mesh.nodes.clone();
    let dt = 1e-3;
    let p = params(ContactModel::Sphere);
    let mut probe = Probe::new(p, top, &x);
    probe.use_implicit_sphere(dt);
    let depth = 0.4e-3;
    // First touch casts the sphere out of the face; the coupling then pulls it onto the face.
    let device = DVec3::new(0.0103, 0.0097, 0.005 + p.radius_m - depth);
    let mut force = DVec3::ZERO;
    for step in 0..3 {
        let st = probe.update(&x, device, DVec3::ZERO);
        assert!(st.in_contact, "step {step}");
        let mut f = vec![DVec3::ZERO; x.len()];
        probe.add_reaction(&mut f);
        let explicit: DVec3 = f.iter().sum();
        // Arbitrary end-of-step velocities of the contact nodes.
        let v: Vec<DVec3> = (0..x.len())
            .map(|i| {
                DVec3::new(
                    (i % 7) as f64 - 3.0,
                    (i % 5) as f64 - 2.0,
                    (i % 3) as f64 - 1.0,
                ) * 1e-3
            })
            .collect();
        let mut g = vec![DVec3::ZERO; x.len()];
        {
            let c = probe.coupling(dt).expect("in contact");
            let mut y = vec![0.0; c.rows()];
            c.a_times(&v, &mut y);
            c.apply_c(&mut y);
            c.add_at(&y, -dt, &mut g);
        }
        let implicit: DVec3 = g.iter().sum();
        probe.finish_solved(dt, &v);
        let device_force = probe.state.force_on_device_n;
        assert!(
            (explicit + implicit + device_force).length() <= 1e-12 * device_force.length(),
            "body {} against -F_device {}",
            explicit + implicit,
            -device_force
        );
        // At rest (v = 0) on the next pass.
        let rest = vec![DVec3::ZERO; x.len()];
        let st = probe.update(&x, device, DVec3::ZERO);
        assert!(st.in_contact);
        probe.finish_solved(dt, &rest);
        force = probe.state.force_on_device_n;
    }
    // The faces under the sphere sink in by at most the penalty's onset band's half plus the
    // force over the penalty stiffness (one face carrying it all).
    let k = p.coupling_stiffness_n_per_m;
    let k_p = haptic_model::contact::probe::PENALTY_FACTOR * k;
    let band = haptic_model::contact::probe::PENALTY_BAND * p.radius_m;
    let sink = 0.5 * band + k * depth / k_p;
    assert!(force.x.abs() < 1e-9 && force.y.abs() < 1e-9, "{force}");
    assert!(
        force.z <= k * depth && force.z >= k * (depth - sink),
        "{} N against k d = {} N (the faces may take {sink} m)",
        force.z,
        k * depth
    );
    let proxy = probe.state.proxy_m;
    assert!(proxy.z - p.radius_m > 0.005 - sink, "proxy {proxy}");
}

/// Friction on the implicit sphere: pressed onto the flat face and then moved along it, the
/// tangential force opposes the motion, stays within `mu` times the normal force (sticking
/// first, then on the cone's edge), and the body's contact force, friction included, is
/// minus the device force.
#[test]
fn the_implicit_sphere_carries_the_friction_cone() {
    let (mesh, top) = block();
    let x = mesh.nodes.clone();
    let dt = 1e-3;
    let mu = 0.4;
    let p = ProbeParams {
        friction_coefficient: mu,
        ..params(ContactModel::Sphere)
    };
    let mut probe = Probe::new(p, top, &x);
    probe.use_implicit_sphere(dt);
    let rest = vec![DVec3::ZERO; x.len()];
    let (mut stuck, mut slid) = (false, false);
    for step in 0..40 {
        // Pressed 0.4 mm, then moved along +x by 20 um per step.
        let shift = (step as f64 - 4.0).max(0.0) * 2e-5;
        let device = DVec3::new(0.0103 + shift, 0.0097, 0.005 + p.radius_m - 0.4e-3);
        assert!(probe.update(&x, device, DVec3::ZERO).in_contact);
        let mut f = vec![DVec3::ZERO; x.len()];
        probe.add_reaction(&mut f);
        probe.finish_solved(dt, &rest);
        let force = probe.state.force_on_device_n;
        let body: DVec3 = f.iter().sum();
        assert!(
            (body + force).length() <= 1e-12 * force.length(),
            "step {step}: body {body} against -F_device {}",
            -force
        );
        // In the contact's frame (its normal leans a little where faces' edges touch).
        let n = probe.state.normal;
        let f_n = force.dot(n);
        let f_t = force - n * f_n;
        assert!(
            f_t.length() <= mu * f_n * (1.0 + 1e-9),
            "step {step}: {force}"
        );
        if shift > 0.0 {
            assert!(
                f_t.x < 0.0,
                "step {step}: friction {f_t} does not oppose +x"
            );
            stuck |= f_t.length() < 0.99 * mu * f_n;
            slid |= f_t.length() > 0.99 * mu * f_n;
        }
    }
    assert!(stuck && slid, "stuck {stuck}, slid {slid}");
}
