//! The coarse companion ticks on a tick-pool worker beside the following region's solve
//! (issue 48 section 1), the region's element forces in two parts before it: a condensed,
//! following body with a companion (the set-up of `tests/condensed.rs`'s companion test on
//! its 2 000-tet LV, regions prepared blocking so that swaps come at the same ticks in every
//! run) gives the same outputs with a 2-thread pool as without one to round-off (the forces'
//! two parts sum in another order), and two 2-thread runs the same bits, tick by tick, through
//! a press where the companion answers and then hands the probe back; neither the servo
//! thread nor the worker allocates in the ticks.

use crate::counting_alloc;

use std::sync::Arc;

use haptic_model::DVec3;
use haptic_model::body::{SoftBody, TickOutput};
use haptic_model::contact::ContactModel;
use haptic_model::element::StrainSmoothing;
use haptic_model::fem::{FallbackStats, FemBody, TickInput};
use haptic_model::integrate::IntegratorKind;
use haptic_model::integrate::condensed::{ActiveRegion, DEFAULT_STIFFNESS_MARGIN, TileMode};
use haptic_model::mesh::generate;
use haptic_model::pool::{StartHook, TickPool};
use haptic_model::scene::{Scene, load_builtin};

/// Ticks of the run: the companion answers from the first contact at -x (about tick 34) until
/// the settling and blend ticks after the swap at tick 40 have passed (about tick 160).
const TICKS: usize = 220;

/// The built-in `lv` (material, probe, base clamped, epicardium touchable) on about 2 000
/// linear tets, backward Euler, a following 6 mm region starting at +x, and the built-in `lv`
/// (474 quadratic tets) as its coarse companion; patch contact as in `tests/condensed.rs`.
fn scene() -> Scene {
    let mut scene = load_builtin("lv").expect("lv");
    let mesh = generate::lv_shell(2000);
    scene.clamped_nodes = mesh
        .nodes_of_surfaces(&["BASE".to_string()], "clamped")
        .expect("base");
    scene.touchable = mesh.surface("EPI").expect("EPI").triangles.clone();
    scene.mesh = mesh;
    scene.strain_smoothing = StrainSmoothing::None;
    scene.integrator.kind = IntegratorKind::BackwardEuler;
    scene.integrator.safety_factor = 0.9;
    scene.integrator.max_substeps = 500;
    scene.active_region = Some(ActiveRegion {
        centre_m: DVec3::new(0.00968, 0.0, -0.005),
        radius_m: 0.006,
        stiffness_margin: DEFAULT_STIFFNESS_MARGIN,
        follow: true,
        tiles: TileMode::Off,
    });
    scene.probe.contact = ContactModel::Patch;
    let mut coarse = load_builtin("lv").expect("lv");
    coarse.probe.contact = ContactModel::Patch;
    scene.fallback = Some(Box::new(coarse));
    scene
}

/// The device: 2 mm above the epicardium at +x (the region's centre) for 21 ticks, then 1 mm
/// above it at -x, pressed in to 0.5 mm over 20 ticks (contact after about 13: before the
/// region's next poll at tick 40, so the companion answers), then held.
fn device(k: usize) -> TickInput {
    const RING_M: f64 = 0.00968 + 0.002; // epicardium + probe radius: first contact
    let position = if k < 21 {
        DVec3::new(RING_M + 0.002, 0.0, -0.005)
    } else {
        let s = ((k - 21) as f64 / 20.0).min(1.0);
        DVec3::new(-(RING_M + 0.001 - 0.0015 * s), 0.0, -0.005)
    };
    TickInput {
        device_position_m: Some(position),
        device_velocity_m_per_s: DVec3::ZERO,
    }
}

fn body(scene: &Scene) -> FemBody {
    let mut sim = FemBody::new(scene).expect("body with companion");
    sim.set_blocking_region_preparation(true);
    sim
}

/// Every output and companion value of one tick, as bits.
fn bits(o: &TickOutput, fb: &FallbackStats) -> [u64; 24] {
    let values = o
        .force_on_device_n
        .to_array()
        .into_iter()
        .chain(o.proxy_position_m.to_array())
        .chain(o.contact_stiffness_n_per_m)
        .chain([f64::from(u8::from(o.in_contact)), o.sim_time_s, fb.weight])
        .chain(fb.region_force_n.to_array())
        .chain(fb.companion_force_n.to_array());
    let mut out = [0; 24];
    for (b, v) in out.iter_mut().zip(values) {
        *b = v.to_bits();
    }
    out
}

#[test]
fn the_companion_beside_the_region_on_two_threads_keeps_the_outputs_and_allocates_nothing() {
    // Registers pool workers: one such test at a time in this binary (`counting_alloc`).
    let _one = counting_alloc::one_at_a_time();
    let scene = scene();
    let mut serial = body(&scene);
    let mut threaded = body(&scene);
    let mut again = body(&scene);
    assert_eq!(SoftBody::wants_threads(&threaded), 2);
    let hook: StartHook = Arc::new(|_| counting_alloc::count_this_thread());
    let pool = TickPool::new(1, Arc::clone(&hook)).expect("pool");
    let pool_again = TickPool::new(1, hook).expect("pool");
    SoftBody::set_tick_pool(&mut threaded, Arc::clone(&pool));
    SoftBody::set_tick_pool(&mut again, pool_again);

    let mut one = vec![TickOutput::default(); TICKS];
    let mut two = vec![TickOutput::default(); TICKS];
    let mut bits_two = vec![[0_u64; 24]; TICKS];
    let mut bits_again = vec![[0_u64; 24]; TICKS];
    let mut weights = vec![[0.0; 2]; TICKS];
    let ((), allocations) = counting_alloc::counted_registered(|| {
        for k in 0..TICKS {
            let input = device(k);
            one[k] = serial.tick(&input).expect("tick without a pool");
            two[k] = threaded.tick(&input).expect("tick with two threads");
            let c = again.tick(&input).expect("tick with two threads, again");
            let fa = serial.fallback_stats().expect("companion");
            let fb = threaded.fallback_stats().expect("companion");
            let fc = again.fallback_stats().expect("companion");
            bits_two[k] = bits(&two[k], &fb);
            bits_again[k] = bits(&c, &fc);
            weights[k] = [fa.weight, fb.weight];
        }
    });
    assert_eq!(allocations, 0, "the servo thread or the worker allocated");
    for k in 0..TICKS {
        assert_eq!(
            bits_two[k], bits_again[k],
            "tick {k}: two 2-thread runs differ"
        );
        assert_eq!(
            weights[k][0], weights[k][1],
            "tick {k}: companion weights differ"
        );
        let (a, b) = (one[k].force_on_device_n, two[k].force_on_device_n);
        assert!(
            (a - b).length() <= 1e-9 * a.length().max(1e-6),
            "tick {k}: 2-thread force {b} against {a}"
        );
        assert_eq!(
            one[k].in_contact, two[k].in_contact,
            "tick {k}: contact differs"
        );
    }
    // The run did what it is for: the companion answered, fully, and handed the probe back
    // after a swap; the worker ran some of the companion's ticks.
    let swaps = threaded.follow_stats().expect("follows").swaps;
    assert!(swaps >= 1, "no region swap");
    let peak = weights.iter().map(|w| w[0]).fold(0.0, f64::max);
    assert!(peak > 0.0, "the companion never answered");
    assert_eq!(
        weights[TICKS - 1][0],
        0.0,
        "the region did not take the probe back"
    );
    let stats = pool.stats();
    assert!(
        stats.jobs >= 2 * TICKS as u64,
        "a parts job (the forces) and a join (the companion) a tick: {stats:?}"
    );
    let last = device(TICKS - 1);
    let stats = crate::common::until_a_worker_ran(&pool, || {
        threaded.tick(&last).expect("tick with two threads");
    });
    assert!(
        stats.parts_on_workers > 0,
        "the worker ticked no companion: {stats:?}"
    );
    eprintln!("companion weight peak {peak}, {swaps} swap(s), pool {stats:?}");
}
