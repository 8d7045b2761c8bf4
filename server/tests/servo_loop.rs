//! Loop logic with a manual clock: absolute deadlines, overrun counting, no catch-up bursts;
//! the stop path sends a final zero force; a diverging model quarantines the session (zero
//! force, fault reported) instead of panicking.

use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use haptic_model::DVec3;
use haptic_model::body::SoftBody;
use haptic_model::fem::FemBody;
use haptic_model::scene::load_builtin;
use haptic_server::servo::{
    self, Clock, Flow, ForceOut, Pacer, Pose, ServoCore, ServoHandles, SessionShared, StatsSnapshot,
};

#[test]
fn pacer_keeps_absolute_deadlines() {
    let mut p = Pacer::new(0, 1000);
    assert_eq!(p.deadline_us(), 1000);
    // Ticks that start on time and take 300 µs keep the grid 1000, 2000, 3000 ...
    for k in 1..=5u64 {
        let start = p.deadline_us();
        p.finish(start, start + 300);
        assert_eq!(p.deadline_us(), (k + 1) * 1000);
    }
    // Small wake-up jitter does not shift the grid.
    let d = p.deadline_us();
    p.finish(d + 150, d + 500);
    assert_eq!(p.deadline_us(), d + 1000);
    assert_eq!(p.overruns, 0);
}

#[test]
fn pacer_counts_overruns_and_never_bursts() {
    let mut p = Pacer::new(0, 1000);
    // A tick that runs 3.5 ms past its start overruns: the next deadline is "now", not a burst
    // of three ticks at 2000, 3000, 4000 µs.
    let start = p.deadline_us(); // 1000
    p.finish(start, start + 3500);
    assert_eq!(p.overruns, 1);
    assert_eq!(p.deadline_us(), 4500);
    // Then the rhythm resumes from there.
    p.finish(4500, 4800);
    assert_eq!(p.deadline_us(), 5500);
    // A wake-up a whole period late is an overrun too.
    p.finish(5500 + 1000, 5500 + 1100);
    assert_eq!(p.overruns, 2);
    assert_eq!(p.deadline_us(), 6600);
    // Finishing exactly at the next deadline is on time.
    p.finish(6600, 7600);
    assert_eq!(p.overruns, 2);
    assert_eq!(p.deadline_us(), 7600);
}

struct ManualClock(Cell<u64>);
impl Clock for ManualClock {
    fn now_us(&self) -> u64 {
        self.0.get()
    }
}

struct Rig {
    core: ServoCore,
    shared: Arc<SessionShared>,
    pose_in: triple_buffer::Input<Pose>,
    forces: rtrb::Consumer<ForceOut>,
    stats: triple_buffer::Output<StatsSnapshot>,
}

fn rig(body: Box<dyn SoftBody>) -> Rig {
    let shared = Arc::new(SessionShared::default());
    let (ends, handles) = servo::channels(body.as_ref());
    let ServoHandles {
        pose: pose_in,
        forces,
        stats,
        ..
    } = handles;
    let core = ServoCore::new(body, ends, shared.clone(), 16, 10);
    Rig {
        core,
        shared,
        pose_in,
        forces,
        stats,
    }
}

#[test]
fn each_fresh_pose_gets_one_force_and_stop_sends_zero() {
    let mut r = rig(Box::new(
        FemBody::new(&load_builtin("lv").unwrap()).unwrap(),
    ));
    let clock = ManualClock(Cell::new(0));
    let mut answered = Vec::new();
    for k in 0..40u64 {
        clock.0.set(k * 1000);
        // A new pose only every other tick: stale poses are not answered twice.
        if k % 2 == 0 {
            r.pose_in.write(Pose {
                seq: k,
                position_m: DVec3::new(0.0112, 0.0, -0.005), // touching the epicardium
                received_us: k * 1000,
                connected: true,
                ..Pose::default()
            });
        }
        assert_eq!(r.core.tick(k * 1000, &clock), Flow::Continue);
        while let Ok(f) = r.forces.pop() {
            answered.push(f);
        }
    }
    let seqs: Vec<u64> = answered.iter().map(|f| f.seq).collect();
    assert_eq!(seqs, (0..40).step_by(2).collect::<Vec<_>>());
    assert!(answered.last().unwrap().in_contact && answered.last().unwrap().force_n.x > 0.0);
    let stats = *r.stats.read();
    assert_eq!(stats.steps, 40);
    assert_eq!(stats.device_samples, 20);
    // 40 ticks in 39 ms of manual time, published at tick 40: 10 ticks over 9 ms -> ~1 kHz.
    assert!(
        stats.loop_rate_hz > 900.0 && stats.loop_rate_hz < 1200.0,
        "{stats:?}"
    );
    r.shared.stop.store(true, Ordering::Release);
    assert_eq!(r.core.tick(41_000, &clock), Flow::Stop);
    let last = r.forces.pop().unwrap();
    assert_eq!(last.force_n, DVec3::ZERO);
    assert_eq!(last.seq, 38);
    assert!(r.shared.finished.load(Ordering::Acquire));
}

#[test]
fn a_diverging_model_is_quarantined_with_zero_force() {
    let mut sim = FemBody::new(&load_builtin("lv").unwrap()).unwrap();
    // Corrupt the state: a NaN velocity on a free node makes the next step diverge.
    let free = (0..sim.fem().node_count())
        .find(|&i| sim.fem().constraints()[i] == 0)
        .unwrap();
    sim.state_mut().v[free] = DVec3::NAN;
    let mut r = rig(Box::new(sim));
    let clock = ManualClock(Cell::new(0));
    for k in 0..20u64 {
        r.pose_in.write(Pose {
            seq: k,
            position_m: DVec3::new(0.0112, 0.0, -0.005),
            received_us: k * 1000,
            connected: true,
            ..Pose::default()
        });
        assert_eq!(r.core.tick(k * 1000, &clock), Flow::Continue);
    }
    assert!(r.core.fault().is_some());
    let mut answered = 0;
    while let Ok(f) = r.forces.pop() {
        answered += 1;
        assert_eq!(f.force_n, DVec3::ZERO);
    }
    // Every sample was still answered (with zero force): the device is told, not left hanging.
    assert_eq!(answered, 20);
    let stats = *r.stats.read();
    assert!(stats.fault.unwrap().contains("quarantined"), "{stats:?}");
}
