//! Contracts of the hybrid body (seed 000 sections 4-6, `haptic_model::hybrid`): the coupling
//! conserves linear momentum to round-off, a constant strain across the interface gives no
//! spurious force, press/hold/slide/release gives no force jump above 7 % at activation and
//! release and injects no energy, and the tick does not allocate.

mod common;

use common::Rng;
use glam::{DMat3, DVec3};
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::contact::probe::ProbeParams;
use haptic_model::hybrid::{HybridBody, HybridParams, ShellGeometry, prepare};
use haptic_model::material::MaterialParams;
use haptic_model::meshfree::{KernelKind, MeshfreeParams, MeshfreeVariant};

const MM: f64 = 1e-3;

fn geometry() -> ShellGeometry {
    ShellGeometry {
        inner_m: DVec3::new(6.0, 6.0, 12.0) * MM,
        outer_m: DVec3::new(10.0, 10.0, 16.0) * MM,
        z_cut_m: None,
    }
}

fn material(damping: bool) -> MaterialParams {
    // Seed 000 Table 1, Hybrid Model: lambda = 5.0, mu = 2.0 (read as kPa).
    let mut m = MaterialParams {
        lambda_pa: 5000.0,
        mu_pa: 2000.0,
        ..MaterialParams::from_youngs(1.0, 0.3, 1060.0)
    };
    if damping {
        m.phi_pa_s = 0.09;
        m.psi_pa_s = 0.09;
        m.mass_damping_per_s = 20.0;
    }
    m
}

fn params(variant: MeshfreeVariant) -> HybridParams {
    HybridParams {
        meshfree: MeshfreeParams {
            variant,
            kernel: KernelKind::default_for(variant),
            spacing_m: 0.8 * MM,
            ..MeshfreeParams::default()
        },
        surface_target_tets: 8000,
        max_active_particles: 3000,
        ..HybridParams::default()
    }
}

fn body(variant: MeshfreeVariant, damping: bool, clamp: bool) -> HybridBody {
    body_with(params(variant), damping, clamp)
}

fn body_with(params: HybridParams, damping: bool, clamp: bool) -> HybridBody {
    let model =
        prepare(geometry(), &params, &material(damping), 188, &mut |_, _| {}).expect("prepare");
    let clamped: Vec<u32> = if clamp {
        let zc = -0.8 * model.geometry.axes(model.params.core_fraction).z;
        (0..model.core_mesh.nodes.len() as u32)
            .filter(|&i| model.core_mesh.nodes[i as usize].z < zc)
            .collect()
    } else {
        Vec::new()
    };
    HybridBody::new(model, &clamped, ProbeParams::default(), 1e-3, "test").expect("body")
}

#[test]
fn coupling_conserves_linear_momentum() {
    for variant in [MeshfreeVariant::Seed, MeshfreeVariant::Corrected] {
        let mut b = body(variant, false, false);
        b.hold_regions(true);
        b.activate_near(DVec3::new(10.0, 0.0, 0.0) * MM, 4.0 * MM);
        let n_active = b.active_particles().len();
        assert!(n_active > 50, "{n_active} active");
        let active: Vec<u32> = b.active_particles().to_vec();
        let mut rng = Rng(11);
        {
            let (_, vc) = b.core_state_mut();
            vc.iter_mut().for_each(|v| *v = rng.vec() * 1e-3);
        }
        {
            let (_, vp) = b.particle_state_mut();
            for &p in &active {
                vp[p as usize] = rng.vec() * 1e-3;
            }
        }
        let p0 = b.linear_momentum();
        let scale: f64 = {
            let (_, vc) = b.core_state_mut();
            vc.iter().map(|v| v.length()).sum::<f64>()
        };
        b.run_free(20).expect("run");
        let p1 = b.linear_momentum();
        let (_, vc) = b.core_state_mut();
        let moved = vc.iter().map(|v| v.length()).sum::<f64>();
        assert!(moved > 0.0 && scale > 0.0);
        let mass = b.particle_mass_kg() * 1e4;
        eprintln!(
            "{variant:?}: {n_active} active, |dP| = {:e}",
            (p1 - p0).length()
        );
        assert!(
            (p1 - p0).length() < 1e-12 * mass * 1e-3,
            "{variant:?}: momentum changed by {}",
            p1 - p0
        );
    }
}

#[test]
fn constant_strain_across_the_interface_gives_no_spurious_force() {
    // Spacing 0.4 mm: particles within 0.8 mm of the core are two supports away from the
    // free outer surface, so only the interface can disturb them.
    let mut p = params(MeshfreeVariant::Corrected);
    p.meshfree.spacing_m = 0.4 * MM;
    p.max_active_particles = 20_000;
    let mut b = body_with(p, false, false);
    b.hold_regions(true);
    let a = DMat3::from_cols(
        DVec3::new(1.02, 0.01, 0.0),
        DVec3::new(0.01, 0.99, 0.005),
        DVec3::new(0.0, 0.005, 1.01),
    );
    {
        let rest = b.model().core_mesh.nodes.clone();
        let (xc, _) = b.core_state_mut();
        for (x, r) in xc.iter_mut().zip(&rest) {
            *x = a * *r;
        }
    }
    b.activate_near(DVec3::new(10.0, 0.0, 0.0) * MM, 5.0 * MM);
    let active: Vec<u32> = b.active_particles().to_vec();
    let rest = b.model().cloud.rest_m().to_vec();
    let geo = b.model().geometry;
    let support = b.model().params.meshfree.support_m();
    let thickness = 4.0 * MM;
    let t_inner_max = 1.0 - 2.0 * support / thickness;
    let (_, fp) = b.evaluate_forces();
    let mut typical = 0.0f64;
    let mut spurious = 0.0f64;
    let mut checked = 0;
    for &p in &active {
        let f = fp[p as usize].length();
        typical = typical.max(f);
        if geo.contains(rest[p as usize], 0.0, t_inner_max) {
            spurious = spurious.max(f);
            checked += 1;
        }
    }
    eprintln!(
        "{checked} interior particles (next to the core), largest force {spurious:e} N, typical (outer surface) {typical:e} N"
    );
    assert!(checked > 20 && typical > 0.0);
    assert!(spurious < 1e-10 * typical, "{spurious:e} vs {typical:e}");
}
