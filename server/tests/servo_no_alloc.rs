//! The servo tick allocates nothing (STYLE.md habit 4): a counting global allocator, enabled only
//! on this thread and only inside `ServoCore::tick`, must see zero allocations over thousands of
//! ticks that exercise every path: device poses in and out of contact, point-load commands,
//! snapshots for a watcher, statistics publication, and a device disconnect. The second test
//! runs the same ticks with a two-thread tick pool set up as the daemon does
//! ([`servo::worker_start_hook`]), counting the servo thread and the pool's workers. The third
//! runs two tools (issue 50) on the wall test body: both pressing, one falling silent and
//! coming back, one disconnecting while the other goes on.

use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use haptic_model::DVec3;
use haptic_model::scene::load_builtin;
use haptic_server::servo::{self, Clock, Command, Pose, ServoCore, ServoHandles, SessionShared};

use crate::counting_alloc;
use counting_alloc::{count_this_thread, counted, counted_registered};
use haptic_model::pool::{StartHook, TickPool};
use haptic_server::servo::StatsSnapshot;

/// A clock the test advances by hand.
struct ManualClock(Cell<u64>);
impl Clock for ManualClock {
    fn now_us(&self) -> u64 {
        let t = self.0.get();
        self.0.set(t + 7);
        t
    }
}

#[test]
fn servo_tick_never_allocates() {
    let body = haptic_model::build_body(&load_builtin("lv").unwrap()).unwrap();
    let stats = press_and_count(body, None, 1, &mut |tick| counted(tick).1);
    assert_eq!(stats.threads, 1);
}

#[test]
fn servo_tick_with_a_two_thread_pool_never_allocates_on_any_of_its_threads() {
    // Registers pool workers: one such test at a time in this binary (`counting_alloc`).
    let _one = counting_alloc::one_at_a_time();
    let mut body = haptic_model::build_body(&load_builtin("lv").unwrap()).unwrap();
    let workers = Arc::new(servo::WorkerThreads::default());
    let daemon_hook = servo::worker_start_hook(
        &haptic_server::config::ServoConfig::default(),
        Vec::new(),
        workers.clone(),
        "test".into(),
    );
    let hook: StartHook = Arc::new(move |k| {
        count_this_thread();
        daemon_hook(k);
    });
    let pool = TickPool::new(1, hook).unwrap();
    body.set_tick_pool(pool.clone());
    let stats = press_and_count(body, Some(pool.clone()), 2, &mut |tick| {
        counted_registered(tick).1
    });
    // With the serial pool of issue 48's step 0 the count is the servo thread's alone; with
    // workers their allocations count too. Either way the session says it uses two threads.
    assert_eq!(stats.threads, 2, "{stats:?}");
    assert_eq!(stats.pool_wait_us_max, pool.stats().longest_wait_us);
    // A pool with workers ran its start hook on each: their thread ids were recorded.
    assert_eq!(workers.started().count(), pool.threads() - 1);
}

#[path = "common/tools.rs"]
mod wall;

#[test]
fn servo_tick_with_two_tools_never_allocates() {
    let body = Box::new(wall::Wall::new(2, &[]));
    let shared = Arc::new(SessionShared::default());
    let (ends, handles, mut more) = servo::tool_channels(body.as_ref());
    assert_eq!(more.len(), 1);
    let ServoHandles {
        pose: mut left,
        forces: mut left_forces,
        stats: mut stats_out,
        ..
    } = handles;
    let servo::ToolHandles {
        pose: mut right,
        forces: mut right_forces,
    } = more.remove(0);
    let mut core = ServoCore::new(body, ends, shared.clone(), 4, 50).with_device_silence_us(2_000);
    shared.watchers.store(1, Ordering::Relaxed);
    let clock = ManualClock(Cell::new(0));
    let (mut worst, mut answered) = (0, [0u64; 2]);
    for k in 1..=2000u64 {
        // Left presses 1 mm throughout but is silent for ticks 500..800 (its pose ages past the
        // 2 ms limit); right presses 2 mm and disconnects at tick 1500.
        let t = clock.0.get();
        if !(500..800).contains(&k) {
            left.write(Pose {
                seq: k,
                position_m: DVec3::new(-0.001, 0.0, 0.0),
                received_us: t,
                connected: true,
                ..Pose::default()
            });
        }
        right.write(Pose {
            seq: k,
            position_m: DVec3::new(-0.002, 0.0, 0.0),
            received_us: t,
            connected: k < 1500,
            ..Pose::default()
        });
        let now = clock.now_us();
        worst = worst.max(
            counted(|| {
                core.tick(now, &clock);
            })
            .1,
        );
        for (i, ring) in [&mut left_forces, &mut right_forces]
            .into_iter()
            .enumerate()
        {
            while let Ok(f) = ring.pop() {
                let want = wall::wall_force(i, Some(DVec3::new(-0.001 * (i + 1) as f64, 0.0, 0.0)));
                assert_eq!(f.force_n, want, "slot {i} tick {k}");
                answered[i] += 1;
            }
        }
    }
    assert_eq!(worst, 0, "a two-tool servo tick allocated");
    // Left answered all but its silent ticks; right until it left.
    assert_eq!(answered, [2000 - 300, 1499]);
    let stats = *stats_out.read();
    assert_eq!(stats.tool_count, 2);
    assert_eq!(stats.tools[0].device_silences, 1);
    assert!(stats.tools[0].connected && stats.tools[0].in_contact);
    assert!(!stats.tools[1].connected && !stats.tools[1].in_contact);
    assert_eq!(stats.device_samples, 1700 + 1499);
}

/// Runs 3 000 ticks of `body` (a 6 mm press and release, point loads, a watcher, a disconnect)
/// through a servo core with `pool` and `threads`, asserting that `count` (the allocations made
/// while the given tick runs) is zero for each tick; returns the last statistics.
fn press_and_count(
    body: Box<dyn haptic_model::body::SoftBody>,
    pool: Option<Arc<TickPool>>,
    threads: usize,
    count: &mut dyn FnMut(&mut dyn FnMut()) -> usize,
) -> StatsSnapshot {
    let shared = Arc::new(SessionShared::default());
    let (ends, handles) = servo::channels(body.as_ref());
    let ServoHandles {
        commands: mut cmd_tx,
        pose: mut pose_in,
        forces: mut force_rx,
        snapshot: mut snap_out,
        stats: mut stats_out,
    } = handles;
    let mut core = ServoCore::new(body, ends, shared.clone(), 4, 50)
        .with_tick_pool(pool, haptic_server::cores::ThreadShare::fixed(threads));
    shared.watchers.store(1, Ordering::Relaxed);
    let clock = ManualClock(Cell::new(0));
    let mut worst = 0;
    let mut contact_ticks = 0;
    let mut seen_loads = Vec::new();
    for k in 0..3000u64 {
        // Press 6 mm along -x over 1.5 s, then leave; disconnect for the last 300 ticks.
        let depth = 0.006 * (k as f64 / 1500.0).min(1.0);
        let connected = k < 2700;
        pose_in.write(Pose {
            seq: k,
            position_m: DVec3::new(0.014 - depth, 0.0, -0.005),
            velocity_m_per_s: DVec3::new(-0.004, 0.0, 0.0),
            received_us: clock.0.get(),
            connected,
        });
        if k % 500 == 100 {
            cmd_tx
                .push(Command::ApplyForce {
                    point_m: DVec3::new(0.0, 0.00968, -0.005),
                    force_n: DVec3::new(0.0, -0.02, 0.0),
                    duration_s: 0.05,
                })
                .unwrap();
        }
        let now = clock.now_us();
        let allocations = count(&mut || {
            core.tick(now, &clock);
        });
        worst = worst.max(allocations);
        while let Ok(f) = force_rx.pop() {
            if f.in_contact {
                contact_ticks += 1;
            }
        }
        snap_out.update();
        let snap = snap_out.output_buffer();
        for a in &snap.applied[..snap.applied_len] {
            // Listed while acting or in the first snapshot after it ended (every 4 ticks).
            assert!(
                snap.sim_time_s <= a.start_sim_time_s + a.duration_s + 0.004 + 1e-9,
                "load {a:?} still listed at {} s",
                snap.sim_time_s
            );
            if !seen_loads.contains(&a.index) {
                seen_loads.push(a.index);
            }
        }
    }
    assert_eq!(worst, 0, "a servo tick allocated");
    // The paths were really exercised.
    assert!(contact_ticks > 500, "contact ticks {contact_ticks}");
    let stats = *stats_out.read();
    assert_eq!(stats.steps, 3000);
    assert!(
        stats.peak_force_n > 0.01 && stats.fault.is_none(),
        "{stats:?}"
    );
    let snap = snap_out.output_buffer();
    assert!(snap.tick > 0);
    // The first snapshot carried the surface's connectivity.
    assert_eq!(snap.topology_version, 0);
    assert_eq!(
        snap.triangles.len(),
        3 * core.body().surface_topology().triangles.len()
    );
    assert_eq!(snap.positions_m.len(), 3 * stats.body.surface_vertices);
    // The ApplyForce commands reached the body (each acts 50 ms, 500 ticks apart).
    assert!(stats.body.active_point_loads <= 1);
    // And every one of them was listed by the snapshots, in order.
    assert_eq!(seen_loads, [1, 2, 3, 4, 5, 6]);
    assert_eq!(snap.applied_total, 6);
    stats
}
