//! The hybrid body's terms on two threads (issue 48 section 1, "the particle groups of the
//! hybrid"): `lv-hybrid` with a 2-thread tick pool cuts its stencil loop's groups into two
//! parts, each adding into its own force buffers. Pressed 1 mm at the lv-probe point and held,
//! it gives the same device force as without a pool to round-off (the parts only regroup the
//! sums of the particles on their border; the core's half-precision solve rounds in single
//! precision, so a last-bit change of its right-hand side may move the force by about 1e-8 of
//! itself: measured 1.2e-8, bound 1e-6), the worker runs parts, and neither the servo thread
//! nor the worker allocates. A one-part pool (a starved or one-core session) is the serial
//! tick bit for bit (the same test: see its first comment).

use crate::counting_alloc;

use std::sync::Arc;

use haptic_model::DVec3;
use haptic_model::body::{SoftBody, TickInput};
use haptic_model::pool::{StartHook, TickPool};
use haptic_model::press::PressLine;
use haptic_model::scene::load_builtin;

/// Ticks of the press: a 0.25 s ramp to 1 mm, then a 0.15 s hold.
const RAMP_TICKS: usize = 250;
const TICKS: usize = 400;

fn lv_hybrid() -> Box<dyn SoftBody> {
    let scene = load_builtin("lv-hybrid").expect("lv-hybrid");
    haptic_model::build_body(&scene).expect("body")
}

/// The device on the lv-probe line at tick `k` (depth ramped linearly to 1 mm, then held).
fn device(line: &PressLine, k: usize) -> TickInput {
    let depth_m = 1e-3 * (k.min(RAMP_TICKS) as f64 / RAMP_TICKS as f64);
    TickInput {
        device_position_m: Some(line.device_at(depth_m)),
        device_velocity_m_per_s: DVec3::ZERO,
    }
}

#[test]
fn two_threads_give_the_serial_force_to_round_off_and_allocate_nothing() {
    // Registers pool workers: one such test at a time in this binary (`counting_alloc`).
    let _one = counting_alloc::one_at_a_time();
    // Two `lv-hybrid` bodies built at the same time on two test threads once differed by
    // about 1e-7 of the force from their first tick: METIS ordered both core factors from one
    // C random stream (now serialised, `tests/ordering_threads.rs`).
    let mut serial = lv_hybrid();
    let mut threaded = lv_hybrid();
    let mut one_part = lv_hybrid();
    assert_eq!(threaded.wants_threads(), 2);
    let hook: StartHook = Arc::new(|_| counting_alloc::count_this_thread());
    let pool = TickPool::new(1, hook).expect("pool");
    threaded.set_tick_pool(Arc::clone(&pool));
    one_part.set_tick_pool(TickPool::serial());
    let line = PressLine::lv_probe(serial.info().probe_radius_m);
    let bits = |v: DVec3| v.to_array().map(f64::to_bits);
    let mut worst: f64 = 0.0;
    let mut peak: f64 = 0.0;
    let ((), allocations) = counting_alloc::counted_registered(|| {
        for k in 0..TICKS {
            let input = device(&line, k);
            let a = serial.tick(&input).expect("tick without a pool");
            let b = threaded.tick(&input).expect("tick with two threads");
            let c = one_part.tick(&input).expect("tick with a one-thread pool");
            assert_eq!(a.in_contact, b.in_contact, "tick {k}: contact differs");
            assert_eq!(
                bits(a.force_on_device_n),
                bits(c.force_on_device_n),
                "tick {k}: a one-thread pool is not the serial tick"
            );
            worst = worst.max((a.force_on_device_n - b.force_on_device_n).length());
            peak = peak.max(a.force_on_device_n.length());
        }
    });
    let active = serial.stats().active_particles;
    let held = device(&line, TICKS - 1);
    let stats = crate::common::until_a_worker_ran(&pool, || {
        threaded.tick(&held).expect("tick with two threads");
    });
    eprintln!(
        "peak {:.4} mN, largest difference {worst:.3e} N, {active} active particles, pool {stats:?}",
        peak * 1e3
    );
    assert!(peak > 5e-3, "the press did not load the body: {peak} N");
    assert!(active > 500, "only {active} active particles");
    assert!(
        worst <= 1e-6 * peak,
        "2 threads differ from 1 by {worst:e} N (peak {peak:e} N)"
    );
    assert!(
        stats.parts_on_workers > 0,
        "the worker ran no part: {stats:?}"
    );
    assert_eq!(allocations, 0, "the servo thread or the worker allocated");
}
