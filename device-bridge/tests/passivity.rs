//! Issue 15, section 3: the bridge's force path stays passive under network delay. A probe
//! follows a closed trajectory (three 1 Hz pokes, 3 mm deep, into a 300 N/m wall: the LV
//! coupling stiffness) while a simulated server answers each pose with the wall force and its
//! stiffness, delivered `d` = 5, 20 or 50 ms later. The guard renders each command through the
//! watchdog gains, the local contact model and the passivity controller at 1 kHz, on explicit
//! times (no clock, no sleeping). The energy the rendered force puts into the hand over the
//! whole trajectory, `sum f . v T`, must not be positive: the environment gives back at most
//! what it was given. Without the controller the same runs generate energy (the contact onset
//! is seen `d` late on the way in, not on the way out), which shows the test has teeth.

use std::collections::VecDeque;
use std::f64::consts::PI;

use haptic_bridge::guard::{ForceGuard, GuardCommand, GuardParams};
use haptic_bridge::passivity::PassivityMode;
use haptic_bridge::{DeviceSpec, DeviceState};

const K_N_PER_M: f64 = 300.0;
const DEPTH_M: f64 = 0.003;
/// The probe starts 0.5 mm outside the wall (surface at x = 0, tissue at x < 0).
const START_M: f64 = 0.0005;

fn probe(t_s: f64) -> (f64, f64) {
    let w = 2.0 * PI;
    let a = DEPTH_M + START_M;
    let x = START_M - a * (1.0 - (w * t_s).cos()) / 2.0;
    let v = -a * w * (w * t_s).sin() / 2.0;
    (x, v)
}

/// Energy put into the hand over three closed pokes, J (positive: the environment was active).
fn generated_energy(delay_ms: u64, mode: PassivityMode) -> (f64, f64) {
    let spec = DeviceSpec::sim_default();
    let mut p = GuardParams::from_spec(&spec);
    p.passivity.mode = mode;
    let mut g = ForceGuard::new(p);
    let mut in_flight: VecDeque<(u64, GuardCommand)> = VecDeque::new();
    let mut latest: Option<GuardCommand> = None;
    let mut energy = 0.0;
    let mut peak: f64 = 0.0;
    let dt = 1e-3;
    // 0.3 s of rest first (the start-up ramp), then three 1 s pokes, then rest.
    for tick in 0..3_600u64 {
        let now_us = tick * 1_000;
        let t = tick as f64 * dt;
        let (x, v) = if !(0.3..=3.3).contains(&t) {
            (START_M, 0.0)
        } else {
            probe(t - 0.3)
        };
        // The server answers this pose; the answer arrives `delay_ms` later.
        let pen = (-x).max(0.0);
        let mut k = [0.0; 9];
        if pen > 0.0 {
            k[0] = -K_N_PER_M;
        }
        in_flight.push_back((
            now_us + delay_ms * 1_000,
            GuardCommand {
                generation: tick + 1,
                seq: tick + 1,
                force_n: [K_N_PER_M * pen, 0.0, 0.0],
                stiffness_n_per_m: k,
                position_m: [x, 0.0, 0.0],
                sample_time_us: now_us,
            },
        ));
        while in_flight.front().is_some_and(|(due, _)| *due <= now_us) {
            latest = in_flight.pop_front().map(|(_, c)| c);
        }
        let state = DeviceState {
            time_us: now_us,
            position_m: [x, 0.0, 0.0],
            velocity_m_per_s: [v, 0.0, 0.0],
            motor_temperature: None,
        };
        let f = g.filter(now_us, true, latest.as_ref(), &state, &spec);
        energy += f[0] * v * dt;
        peak = peak.max(f[0].abs());
    }
    (energy, peak)
}

#[test]
fn no_net_energy_is_generated_with_5_20_and_50_ms_of_delay() {
    for delay in [5, 20, 50] {
        let (e_on, peak_on) = generated_energy(delay, PassivityMode::Control);
        let (e_off, peak_off) = generated_energy(delay, PassivityMode::Off);
        println!(
            "delay {delay} ms: energy into the hand {e_on:.3e} J with the passivity controller \
             (peak {peak_on:.3} N), {e_off:.3e} J without (peak {peak_off:.3} N)"
        );
        assert!(e_on <= 1e-9, "delay {delay} ms: {e_on} J generated");
        assert!(peak_on > 0.05, "the wall was felt: {peak_on} N");
        if delay >= 20 {
            assert!(e_off > 1e-7, "delay {delay} ms without control: {e_off} J");
        }
    }
}
