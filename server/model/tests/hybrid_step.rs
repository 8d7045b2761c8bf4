//! The explicit step of the hybrid body under a deep press with many regions active (issue 13,
//! section 4): the sub-step count the body chooses stays bounded in the worst case we know.
//!
//! The body steps with `ceil(tick / (safety_factor * bound))` sub-steps, the bound being the
//! assembled Gershgorin bound of the particles at rest plus the probe penalty
//! (`meshfree::critical_time_step`, `HybridBody::critical_step_bound_s`). On `lv-hybrid` it
//! gives one sub-step per 1 ms tick for the seed variant (before issue 13's tighter bound:
//! two) and two for the corrected one; the power-iteration estimate of the true limit is
//! about 1.5 times the bound (docs/benchmarks.md). The worst case: the probe pressed 2 mm deep
//! (twice the benchmark's depth) and slid 6 mm across the wall with every region it passes
//! held active (up to the scene's 2 000 particles), then released; the body must not diverge
//! and must come to rest.

use crate::common;
use crate::counting_alloc;

use glam::DVec3;
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::hybrid::{CoreMassScale, CoreStep, HybridBody, HybridParams, ScaledMotion};
use haptic_model::meshfree::{KernelKind, MeshfreeVariant};

#[test]
fn default_substeps_stay_bounded_pressed_deep_with_many_regions_active() {
    // The scene: deviation mass and the implicit core, one sub-step for both variants.
    for variant in [MeshfreeVariant::Seed, MeshfreeVariant::Corrected] {
        worst_case(variant, None, 1);
    }
}

#[test]
fn explicit_substeps_stay_bounded_pressed_deep_with_many_regions_active() {
    // The scene before the implicit core: everything explicit, mass_scale = 1000 and the
    // core's scale chosen by the body; one sub-step for the seed variant, two for the
    // corrected one.
    for (variant, substeps) in [(MeshfreeVariant::Seed, 1), (MeshfreeVariant::Corrected, 2)] {
        worst_case(variant, Some((1000.0, CoreMassScale::Auto)), substeps);
    }
}

#[test]
fn a_real_inertia_core_stays_stable_pressed_deep_with_many_regions_active() {
    // core_mass_scale = 1 (the body's real inertia), particles at mass_scale = 300: the
    // sub-steps come from the core's critical step and the coupling margin (11 per tick).
    worst_case(
        MeshfreeVariant::Corrected,
        Some((300.0, CoreMassScale::Fixed(1.0))),
        11,
    );
}

/// Steps everything explicitly (`scaled_motion = "absolute"`, `core_step = "explicit"`) at
/// `mass_scale` and `core`.
fn explicit(p: &mut HybridParams, mass_scale: f64, core: CoreMassScale) {
    p.scaled_motion = ScaledMotion::Absolute;
    p.core_step = CoreStep::Explicit;
    p.mass_scale = mass_scale;
    p.core_mass_scale = core;
}

/// The lv-hybrid body with `variant` (and its kernel), stepped explicitly at `scales`
/// (`(mass_scale, core_mass_scale)`, [`explicit`]) or as the scene says; with its scene.
fn lv_body(
    variant: MeshfreeVariant,
    scales: Option<(f64, CoreMassScale)>,
) -> (HybridBody, haptic_model::scene::Scene) {
    let edit = |p: &mut HybridParams| {
        p.meshfree.variant = variant;
        p.meshfree.kernel = KernelKind::default_for(variant);
        if let Some((m, c)) = scales {
            explicit(p, m, c);
        }
    };
    // The explicit configurations are those of the seed's layer (the scene until 2026-11-26).
    let (model, clamped, scene) = if scales.is_some() {
        common::lv_hybrid_tied_model(edit)
    } else {
        common::lv_hybrid_model(edit)
    };
    let body = HybridBody::new(
        model,
        &clamped,
        scene.probe,
        scene.integrator.tick_s,
        &scene.name,
    )
    .expect("body");
    (body, scene)
}

/// `scales`: `(mass_scale, core_mass_scale)` stepped explicitly, or the scene's.
fn worst_case(variant: MeshfreeVariant, scales: Option<(f64, CoreMassScale)>, substeps: u32) {
    let (mut body, scene) = lv_body(variant, scales);
    let bound = body.critical_step_bound_s();
    assert_eq!(
        body.substeps().0,
        substeps,
        "{variant:?}: bound {bound:.3e} s"
    );
    body.hold_regions(true);
    let m = body.model();
    let v = (0..m.outer_rest_m.len())
        .max_by(|&a, &b| m.outer_rest_m[a].x.total_cmp(&m.outer_rest_m[b].x))
        .expect("vertices");
    let surf = m.outer_rest_m[v];
    let normal = (surf - m.centre_m).normalize();
    let tangent = normal.cross(DVec3::Z).normalize();
    let radius = scene.probe.radius_m;
    let depth_m = 2e-3;
    let mut max_speed_proxy: f64 = 0.0;
    let mut max_active = 0;
    let mut max_force: f64 = 0.0;
    // Press 2 mm in 100 ms, hold 100 ms, slide 6 mm in 600 ms, hold 200 ms.
    let ticks = 1000;
    for t in 0..ticks {
        let ramp = (t as f64 / 100.0).min(1.0);
        let slide = ((t as f64 - 200.0) / 600.0).clamp(0.0, 1.0);
        let device = surf + normal * (radius - depth_m * ramp) + tangent * (6e-3 * slide);
        let out = body
            .tick(&TickInput {
                device_position_m: Some(device),
                device_velocity_m_per_s: DVec3::ZERO,
            })
            .unwrap_or_else(|e| panic!("{variant:?}, tick {t}: {e}"));
        max_force = max_force.max(out.force_on_device_n.length());
        max_active = max_active.max(body.active_particles().len());
        let (kinetic, _) = body.energy();
        max_speed_proxy = max_speed_proxy.max(kinetic);
    }
    assert!(
        max_active >= 1500,
        "{variant:?}: {max_active} active particles"
    );
    assert!(max_force > 0.01, "force {max_force} N");
    // Release and let it settle (the regions stay held: the whole set keeps being stepped).
    let mut last = f64::INFINITY;
    for t in 0..3000 {
        body.tick(&TickInput::default())
            .unwrap_or_else(|e| panic!("{variant:?}, free tick {t}: {e}"));
        if t % 500 == 499 {
            let (kinetic, _) = body.energy();
            eprintln!("{variant:?}, free {} ms: kinetic {kinetic:.3e} J", t + 1);
            last = kinetic;
        }
    }
    eprintln!(
        "{variant:?}, {substeps} sub-steps (bound {bound:.3e} s): {max_active} active, force up to {max_force:.4} N, kinetic energy up to {max_speed_proxy:.3e} J, {last:.3e} J after 3 s free"
    );
    assert!(
        last < 1e-3 * max_speed_proxy,
        "{variant:?}: the body did not come to rest: {last:e} J of {max_speed_proxy:e} J"
    );
}

#[test]
fn the_scene_presses_and_slides_with_no_force_jump_at_activation_and_release() {
    // lv-hybrid at its own scales (corrected variant, the core's mass scale chosen by the
    // body): the probe approaches the lv-probe point (the epicardium at z = -5 mm, radius 9.682 mm,
    // on the +x axis) along -x at 10 mm/s, presses 1 mm, holds 200 ms, slides 0.4 rad (3.9 mm of arc) around
    // the axis, holds 200 ms and retracts. The slide fills the 1 600 particles the test
    // allows, so it goes on by releasing the regions the probe left (farther than the new
    // region by half the release band, settled or not). At every tick where the active set
    // changes the force moves by at most the 7 % JND of the larger of the two forces (issue 13,
    // section 3), the force under the probe stays within 25 % of the hold's while it slides
    // (before regions were released for room it fell to 0.4 mN, then spiked to 20-170 mN),
    // and after retracting every region is released. The seed variant fails here: one-tick
    // jumps up to 56 % (6.2 -> 13.1 mN) at activations during the slide (docs/accuracy.md).
    let mm = 1e-3;
    let variant = MeshfreeVariant::Corrected;
    // The scene allows 6 000 active particles, which this slide does not fill: 1 600 (the 1 mm
    // press activates about 1 450 at the scene's 0.35 mm lattice) make it release regions for
    // room.
    let (model, clamped, scene) = common::lv_hybrid_model(|p| p.max_active_particles = 1600);
    let mut body = HybridBody::new(
        model,
        &clamped,
        scene.probe,
        scene.integrator.tick_s,
        &scene.name,
    )
    .expect("body");
    let surface = 9.682 * mm + scene.probe.radius_m;
    let at = |r: f64, a: f64| DVec3::new(r * a.cos(), r * a.sin(), -5.0 * mm);
    let step = 10.0 * mm * 1e-3;
    let mut path = Vec::new();
    let mut r = surface + 5.0 * mm;
    while r > surface - 1.0 * mm {
        path.push(at(r, 0.0));
        r -= step;
    }
    let pressed = surface - 1.0 * mm;
    path.extend(std::iter::repeat_n(at(pressed, 0.0), 200));
    let hold_end = path.len();
    let mut a = 0.0;
    while a < 0.4 {
        path.push(at(pressed, a));
        a += step / pressed;
    }
    path.extend(std::iter::repeat_n(at(pressed, 0.4), 200));
    let slide_end = path.len();
    let mut r = pressed;
    while r < surface + 8.0 * mm {
        path.push(at(r, 0.4));
        r += step;
    }
    // The slide (from the end of the press's hold to the end of the second hold) counts
    // the heap allocations of the ticks: none, releases for room included.
    let mut allocations = 0;
    let (mut prev, mut prev_active) = (DVec3::ZERO, 0usize);
    let (mut changes, mut worst_jump, mut max_force) = (0, 0.0f64, 0.0f64);
    let (mut hold_force, mut slide_range) = (0.0, (f64::INFINITY, 0.0f64));
    for (t, c) in path.iter().enumerate() {
        let input = TickInput {
            device_position_m: Some(*c),
            device_velocity_m_per_s: DVec3::ZERO,
        };
        let (out, n) = if (hold_end..slide_end).contains(&t) {
            counting_alloc::counted(|| body.tick(&input))
        } else {
            (body.tick(&input), 0)
        };
        allocations += n;
        let f = out
            .unwrap_or_else(|e| panic!("{variant:?}, tick {t}: {e}"))
            .force_on_device_n;
        max_force = max_force.max(f.length());
        if (hold_end - 50..hold_end).contains(&t) {
            hold_force += f.length() / 50.0;
        } else if (hold_end..slide_end).contains(&t) {
            slide_range = (slide_range.0.min(f.length()), slide_range.1.max(f.length()));
        }
        let active = body.active_particles().len();
        if active != prev_active {
            changes += 1;
            let scale = f.length().max(prev.length());
            if scale > 1e-4 {
                worst_jump = worst_jump.max((f - prev).length() / scale);
            }
        }
        prev = f;
        prev_active = active;
    }
    for _ in 0..2000 {
        body.tick(&TickInput::default()).expect("free tick");
    }
    eprintln!(
        "{variant:?}: core_mass_scale {:.1}, {} sub-steps, {changes} activation/release ticks ({} implicit-core refactorings, {} regions released for room), largest relative force jump there {:.2} %, hold {:.2} mN, slide {:.2}-{:.2} mN, force up to {:.2} mN, {} particles active 2 s after retracting",
        body.core_mass_scale(),
        body.substeps().0,
        body.implicit_refactors(),
        body.released_for_room(),
        100.0 * worst_jump,
        hold_force * 1e3,
        slide_range.0 * 1e3,
        slide_range.1 * 1e3,
        max_force * 1e3,
        body.active_particles().len()
    );
    common::assert_active_set_changes_without_jump(
        &format!("{variant:?} slide"),
        changes,
        4,
        max_force,
        5e-3,
        worst_jump,
    );
    assert!(
        body.released_for_room() > 0,
        "the slide released no region for room"
    );
    assert_eq!(allocations, 0, "allocations in the slide's ticks");
    // With the elements under the layer the implicit FEM's matrix is the whole wall's: the
    // active set never refactors it (the tied layer's is refactored when an active region was
    // not in it).
    assert_eq!(
        body.implicit_refactors(),
        0,
        "refactorings of the FEM's matrix"
    );
    assert!(
        slide_range.0 > 0.75 * hold_force && slide_range.1 < 1.25 * hold_force,
        "slide {slide_range:?} N against the hold's {hold_force} N"
    );
    assert!(
        body.active_particles().is_empty(),
        "{variant:?}: regions not released"
    );
}

/// The body of `lv-hybrid` with a core of `core_tets` wanted tetrahedra and at most
/// `max_active` active particles, its regions held around the outer vertex at the largest x
/// (the free wall) up to that cap, and the probe 1 mm into it at once (`hybrid_bench`'s
/// press); stepped explicitly at the scene's former scales ([`explicit`], `mass_scale =
/// 1000`, `"auto"`) when `explicit_step`, else as the scene says; `substeps` overrides the
/// body's own count. Returns the sub-steps used and the outcome of 100 ticks.
fn instant_press(
    core_tets: usize,
    max_active: usize,
    explicit_step: bool,
    substeps: Option<u32>,
) -> (u32, Result<(), haptic_model::ModelError>) {
    let mut scene = haptic_model::scene::load_builtin("lv-hybrid").expect("lv-hybrid");
    let h = scene.hybrid.as_mut().expect("hybrid");
    h.core_target_tets = core_tets;
    if explicit_step {
        // The seed's layer, material and lattice (0.26 mm until 2026-11-27), as the scene had
        // them when it stepped explicitly.
        common::seed_layer(&mut h.params);
        h.params.meshfree.spacing_m = 0.26e-3;
        explicit(&mut h.params, 1000.0, CoreMassScale::Auto);
        scene.material.model = haptic_model::material::MaterialModel::StVenantKirchhoff;
    }
    h.params.max_active_particles = max_active;
    let mut body = haptic_model::build_hybrid_body(&scene, &mut |_, _| {}).expect("body");
    if let Some(n) = substeps {
        body.override_substeps(n).expect("sub-steps");
    }
    let m = body.model();
    let v = (0..m.outer_rest_m.len())
        .max_by(|&a, &b| m.outer_rest_m[a].x.total_cmp(&m.outer_rest_m[b].x))
        .expect("vertices");
    let surface = m.outer_rest_m[v];
    let normal = (surface - m.centre_m).normalize();
    body.hold_regions(true);
    let mut r = 0.5e-3;
    while body.active_particles().len() < max_active && r < 0.05 {
        body.activate_near(surface, r);
        r += 0.1e-3;
    }
    let device = surface + normal * (scene.probe.radius_m - 1e-3);
    let outcome = (0..100).try_for_each(|_| {
        body.tick(&TickInput {
            device_position_m: Some(device),
            device_velocity_m_per_s: DVec3::ZERO,
        })
        .map(|_| ())
    });
    (body.substeps().0, outcome)
}

#[test]
fn a_finer_core_takes_the_sub_steps_of_its_coupled_limit() {
    // Stepped explicitly: the core's share of the coupled step (0.65 of its own) was measured
    // on lv-hybrid's 519-tetrahedron core. With 999 tetrahedra the coupled limit is shorter
    // than the step it gives (two sub-steps: an instant 1 mm press with 600 active particles
    // diverged within a few ticks while the probe pressed the particles directly; through the
    // proxy's coupling, since 2026-11-26, it no longer does); the set-up check (power
    // iteration at six outer vertices) gives the body three.
    let (substeps, outcome) = instant_press(1000, 600, true, None);
    assert!(substeps >= 3, "{substeps} sub-steps");
    outcome.expect("the press with the checked sub-steps");
    // The scene's own core keeps its two.
    let (scene_substeps, scene_outcome) = instant_press(500, 600, true, None);
    assert_eq!(scene_substeps, 2);
    scene_outcome.expect("the scene's press");
}

#[test]
fn the_implicit_core_holds_an_instant_press_with_the_largest_active_set() {
    // The scene (deviation mass, implicit core, stiffness margin 4): the instant 1 mm press
    // with the 2 000 active particles the scene allows holds at one sub-step, on the scene's
    // core and a finer one (999 tetrahedra). With the margin at 1 it diverged within 2 ms at
    // mass_scale 1000 (docs/accuracy.md).
    for core_tets in [500, 1000] {
        let (substeps, outcome) = instant_press(core_tets, 2000, false, None);
        assert_eq!(substeps, 1, "{core_tets} tets");
        outcome.unwrap_or_else(|e| panic!("{core_tets} tets: {e}"));
    }
}
