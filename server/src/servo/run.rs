//! The servo loops: fixed-rate ([`run_loop`]) and device-paced ([`run_loop_device_paced`]).

use super::{Clock, DevicePacer, Flow, MonotonicClock, Pacer, ServoCore, Wake, Yielding};

/// Runs the servo loop until stopped, device-paced ([`DevicePacer`]): a tick as soon as a
/// device sample arrives (the stream task unparks this thread after publishing it), a tick per
/// `period_us` slot otherwise. Wakes `forwarder` after each tick.
pub fn run_loop_device_paced(
    mut core: ServoCore,
    clock: MonotonicClock,
    period_us: u64,
    forwarder: std::thread::Thread,
    mut yielding: Yielding,
) {
    let mut pacer = DevicePacer::new(clock.now_us(), period_us);
    loop {
        let now = clock.now_us();
        let wake = pacer.decide(now, core.sample_pending(), core.device_connected());
        if let Wake::SleepUntil(t) = wake {
            // A sample's arrival unparks us early; spurious wake-ups just decide again.
            std::thread::park_timeout(std::time::Duration::from_micros(t.saturating_sub(now)));
            continue;
        }
        let started = clock.now_us();
        let flow = core.tick(started, &clock);
        forwarder.unpark();
        if flow == Flow::Stop {
            break;
        }
        pacer.finish(clock.now_us());
        core.set_overruns(pacer.overruns);
        yielding.after_tick(&mut core);
    }
}

/// Runs the servo loop until stopped: paces ticks at `period_us` with absolute deadlines and
/// wakes `forwarder` after each tick that produced a force.
pub fn run_loop(
    mut core: ServoCore,
    clock: MonotonicClock,
    period_us: u64,
    forwarder: std::thread::Thread,
    mut yielding: Yielding,
) {
    let sleeper = spin_sleep::SpinSleeper::default();
    let mut pacer = Pacer::new(clock.now_us(), period_us);
    loop {
        let deadline = clock.epoch() + std::time::Duration::from_micros(pacer.deadline_us());
        sleeper.sleep_until(deadline);
        let started = clock.now_us();
        let flow = core.tick(started, &clock);
        forwarder.unpark();
        if flow == Flow::Stop {
            break;
        }
        pacer.finish(started, clock.now_us());
        core.set_overruns(pacer.overruns);
        yielding.after_tick(&mut core);
    }
}
