//! One tool through `SoftBody::tick_tools` with the other slots empty is `SoftBody::tick`
//! bit for bit (issue 50: the servo ticks every body with all its slots), on the FEM (`lv`)
//! and hybrid (`lv-hybrid`) bodies.
//!
//! Alone in its own test binary: run beside the other tests of `tools.rs` (two test threads
//! building and ticking bodies at once), the two `lv-hybrid` bodies of this test differed by
//! 1.2e-5 of the force at the first contact in 1 of 7 runs (2026-11-27, session 11; built
//! and ticked one after the other on one thread, in any number of runs here and by two
//! threads of a small program, they agree bit for bit). Not understood; `valgrind` finds no
//! read of uninitialised memory on the AVX2 path.

#[path = "common/tool_press.rs"]
mod tool_press;

use haptic_model::body::{TickInput, TickOutput};
use haptic_model::press::{LV_PROBE_Z_M, PressLine, lv_epicardium_point};
use haptic_model::scene::load_builtin;
use tool_press::{RAMP_S, ramp_input};

#[test]
fn one_tool_in_two_slots_is_the_one_tool_tick_bit_for_bit() {
    for name in ["lv", "lv-hybrid"] {
        let scene = load_builtin(name).unwrap();
        let build = || haptic_model::build_body(&scene).unwrap();
        let (mut one, mut two) = (build(), build());
        assert_eq!(two.max_tools(), 2, "{name}");
        let (p, n) = lv_epicardium_point(LV_PROBE_Z_M, 0.0);
        let a = PressLine::at_surface_point(p, n, scene.probe.radius_m);
        for k in 0..((RAMP_S + 0.1) / 1e-3).round() as usize {
            let input = ramp_input(&a, 1e-3, (k + 1) as f64 * 1e-3);
            let expected = one.tick(&input).unwrap();
            let mut out = [TickOutput::default(); 2];
            two.tick_tools(&[input, TickInput::default()], &mut out)
                .unwrap();
            assert_eq!(out[0], expected, "{name} tick {k}");
            assert!(!out[1].in_contact);
        }
    }
}
