//! Several tools on the mass-spring surface (issue 50 section 1: "mass-spring: subdivision
//! under each tool"), on the built-in `hemisphere-springs` and `lv-surface-springs` (organ
//! tables, calibrated subdivision):
//!
//! - two tools pressing 1 mm at two distant points hold steady (the force JND, 7 % per tick)
//!   and the surface is subdivided under each; each tool's force is that tool's alone at its
//!   point;
//! - two tools at one point are one tool of twice the coupling (stiffness and damping): the
//!   couplings are completed together, so the surface is counted once;
//! - one tool leaving mid-hold leaves the other's force continuous;
//! - a two-tool tick allocates nothing, also when it subdivides;
//! - one tool in two slots is the one-tool tick bit for bit;
//! - named tools take their own force limit; hostile slot counts and inputs are refused.

use crate::counting_alloc;
use crate::tool_press;

use glam::DVec3;
use haptic_model::body::{SoftBody, TickInput, TickOutput};
use haptic_model::build_mass_spring_body;
use haptic_model::mass_spring::MassSpringBody;
use haptic_model::press::{LV_PROBE_Z_M, PressLine, lv_epicardium_point};
use haptic_model::scene::{Scene, builtin_scene_toml, load_builtin, parse_scene_toml};

use counting_alloc::counted;
use tool_press::{RAMP_S, hold_stats, ramp_input, run};

/// The force JND: the largest tick-to-tick change of a held force, as a fraction of it.
const JND: f64 = 0.07;

/// Ramp to the depth (a C1 smoothstep), then hold, s.
const HOLD_S: f64 = 0.6;

/// Device depth past first contact, m.
const DEPTH_M: f64 = 1e-3;

const SCENES: [&str; 2] = ["hemisphere-springs", "lv-surface-springs"];

fn ticks(s: f64) -> usize {
    (s / 1e-3).round() as usize
}

/// The press line of scene `name` at `u` in `[0, 1]` along a path on its surface between two
/// distant points (on the hemisphere from 45 degrees on one side of the pole over it to 45
/// degrees on the other, 70 mm apart; on the LV epicardium half way round at the probe's
/// height), along the inward normal, for a probe of radius `r` (m).
fn line_at(name: &str, body: &dyn SoftBody, r: f64, u: f64) -> PressLine {
    let line = |p: DVec3, n: DVec3| {
        PressLine::from_rest_surface(body, p - n * 0.02, n, r).expect("press line")
    };
    if name == "hemisphere-springs" {
        let a = DVec3::new(1.0, 0.2, 1.0).normalize();
        let b = DVec3::new(-1.0, -0.2, 1.0).normalize();
        let d = a.lerp(b, u).normalize();
        line(d * 0.05, -d)
    } else {
        let (p, n) = lv_epicardium_point(LV_PROBE_Z_M, std::f64::consts::PI * u);
        line(p, n)
    }
}

/// The press lines at both ends of [`line_at`]'s path.
fn distant_lines(name: &str, body: &dyn SoftBody, r: f64) -> [PressLine; 2] {
    [line_at(name, body, r, 0.0), line_at(name, body, r, 1.0)]
}

/// The input of slot `slot` at tick `k` of a ramp to [`DEPTH_M`] on `line`.
fn ramp_at(line: &PressLine, k: usize) -> TickInput {
    ramp_input(line, DEPTH_M, (k + 1) as f64 * 1e-3)
}

fn body_of(scene: &Scene) -> MassSpringBody {
    build_mass_spring_body(scene).expect("mass-spring body")
}

/// Whether a subdivided area's centre lies within 1.5 coarse edges (at rest) of tool `slot`'s
/// contact point.
fn subdivided_under(body: &MassSpringBody, slot: usize) -> bool {
    let probe = body.tool_probe(slot).expect("slot");
    let point = probe.state.proxy_m - probe.state.normal * probe.params.radius_m;
    let rest = body.surface().rest();
    body.area_home_constants().any(|(c, _)| {
        let l = body.surface().element_size_m(c);
        rest[c as usize].distance(point) < 1.5 * l
    })
}

/// Two tools 1 mm deep at distant points hold steady (largest tick change below 7 % of the
/// hold force), the surface is subdivided under each (a centre near each contact point, more
/// nodes than the coarse surface), and each tool's force is that tool's alone at its point
/// (the same slot, the other empty): measured within 3.3e-8 relative on both scenes (bound
/// 1e-6; the other tool's press reaches the first only through the surface's springs, and
/// each slot's springs take their nearest tool's organ factor).
#[test]
fn two_distant_tools_hold_steady_are_subdivided_under_each_and_feel_as_alone() {
    for name in SCENES {
        let scene = load_builtin(name).unwrap();
        assert_eq!(scene.tools.max_tools, 2);
        let mut body = body_of(&scene);
        assert_eq!(SoftBody::max_tools(&body), 2);
        let coarse_nodes = body.surface().node_count();
        let lines = distant_lines(name, &body, scene.probe.radius_m);
        let n = ticks(RAMP_S + HOLD_S);
        let hold = ticks(RAMP_S + 0.2)..n;
        let trace = run(&mut body, n, |k| {
            [ramp_at(&lines[0], k), ramp_at(&lines[1], k)]
        });
        let last = trace[n - 1];
        assert!(last[0].in_contact && last[1].in_contact, "{name}");
        let stats = body.stats();
        eprintln!(
            "{name}: {} nodes ({coarse_nodes} coarse), {} centres, events {:?}",
            stats.nodes,
            body.area_home_constants().count(),
            body.event_stats()
        );
        assert!(stats.nodes > coarse_nodes, "{name}: not subdivided");
        for slot in 0..2 {
            assert!(subdivided_under(&body, slot), "{name}: slot {slot}");
            let (f, change) = hold_stats(&trace, slot, hold.clone());
            // Alone: the same slot, the other empty.
            let mut alone = body_of(&scene);
            let one = run(&mut alone, n, |k| {
                let mut i = [TickInput::default(); 2];
                i[slot] = ramp_at(&lines[slot], k);
                i
            });
            let (f_alone, _) = hold_stats(&one, slot, hold.clone());
            let rel = (f - f_alone).length() / f_alone.length();
            eprintln!(
                "{name} slot {slot}: F {f} (|F| {:.4} N, largest change {:.2e} of it), alone {f_alone}, rel. difference {:.2e}",
                f.length(),
                change / f.length(),
                rel
            );
            assert!(f.dot(-lines[slot].direction) > 0.0, "{name}: {f}");
            assert!(
                change < JND * f.length(),
                "{name} slot {slot}: {change} vs {f}"
            );
            assert!(rel < 1e-6, "{name} slot {slot}: {f} vs alone {f_alone}");
        }
    }
}

/// Two tools at one device position count the surface once: with the couplings completed
/// together (Woodbury over the two rank-one terms) they are one tool of twice the coupling
/// stiffness and damping, whose summed force must equal that tool's to round-off (the proxy
/// of the patch contact is a function of the device position and the surface alone). Each
/// hold is steady (no chatter between the two).
#[test]
fn two_tools_at_one_point_are_one_tool_of_twice_the_coupling() {
    for name in SCENES {
        let scene = load_builtin(name).unwrap();
        let mut double = scene.clone();
        double.probe.coupling_stiffness_n_per_m *= 2.0;
        double.probe.coupling_damping_n_s_per_m *= 2.0;
        let probe = body_of(&scene);
        let [a, _] = distant_lines(name, &probe, scene.probe.radius_m);
        let n = ticks(RAMP_S + HOLD_S);
        let hold = ticks(RAMP_S + 0.2)..n;
        let mut single = body_of(&double);
        let one = run(&mut single, n, |k| [ramp_at(&a, k), TickInput::default()]);
        let (f_one, _) = hold_stats(&one, 0, hold.clone());
        let mut body = body_of(&scene);
        let both = run(&mut body, n, |k| [ramp_at(&a, k); 2]);
        let (f0, c0) = hold_stats(&both, 0, hold.clone());
        let (f1, c1) = hold_stats(&both, 1, hold.clone());
        let total = f0 + f1;
        // Tick by tick, over the whole press.
        let worst = one
            .iter()
            .zip(&both)
            .map(|(o, b)| {
                (b[0].force_on_device_n + b[1].force_on_device_n - o[0].force_on_device_n).length()
            })
            .fold(0.0, f64::max);
        eprintln!(
            "{name}: one tool 2k {f_one}, two tools {f0} + {f1} = {total}; rel. difference of the hold {:.2e}, worst tick {:.2e} N; changes {:.2e} {:.2e} N",
            (total - f_one).length() / f_one.length(),
            worst,
            c0,
            c1
        );
        assert!(
            (total - f_one).length() < 1e-6 * f_one.length(),
            "{name}: {total} vs {f_one}"
        );
        assert!(worst < 1e-6 * f_one.length(), "{name}: worst tick {worst}");
        assert!(c0 < JND * f0.length() && c1 < JND * f1.length(), "{name}");
        assert_eq!(body.stats().nodes, single.stats().nodes, "{name}");
    }
}

/// Tool 1 leaves mid-hold (its stream ends: no device): tool 0's force changes by less than
/// the JND per tick, and tool 1's slot reports no contact and no force; with tool 1 far away,
/// and about 4 mm away (0.05 of the path: the two patches share nodes, and the springs under
/// tool 1 take tool 0's factor when it leaves). Near, the leaving tool is withdrawn over
/// `WITHDRAW_S` (released at once, tool 0's force rose by 19 % in a tick): measured 3.8 %
/// (hemisphere) and 3.7 % (LV) near, below 1e-8 % far.
#[test]
fn one_tool_leaving_mid_hold_leaves_the_others_force_continuous() {
    for (name, gap) in SCENES.into_iter().flat_map(|n| [(n, 1.0), (n, 0.05)]) {
        let scene = load_builtin(name).unwrap();
        let mut body = body_of(&scene);
        let r = scene.probe.radius_m;
        let lines = [line_at(name, &body, r, 0.0), line_at(name, &body, r, gap)];
        let leave = ticks(RAMP_S + 0.3);
        let n = leave + ticks(0.3);
        let trace = run(&mut body, n, |k| {
            let second = if k < leave {
                ramp_at(&lines[1], k)
            } else {
                TickInput::default()
            };
            [ramp_at(&lines[0], k), second]
        });
        let (held, _) = hold_stats(&trace, 0, leave - 100..leave);
        let (_, change) = hold_stats(&trace, 0, leave - 1..n);
        let (after, _) = hold_stats(&trace, 0, n - 50..n);
        eprintln!(
            "{name}, gap {gap}: tool 0 held {held}, largest change after tool 1 left {change:.3e} N ({:.3} %), settled {after}",
            100.0 * change / held.length()
        );
        assert!(change < JND * held.length(), "{name}: {change} vs {held}");
        assert!(!trace[leave][1].in_contact && trace[leave - 1][1].in_contact);
        assert_eq!(trace[leave][1].force_on_device_n, DVec3::ZERO);
        assert!(trace[n - 1][0].in_contact);
    }
}

/// Every two-tool tick of a press from first touch to the hold allocates nothing, the ticks
/// that subdivide under each tool included (checked: the press ran events).
#[test]
fn two_tool_ticks_allocate_nothing_also_when_they_subdivide() {
    for name in SCENES {
        let scene = load_builtin(name).unwrap();
        let mut body = body_of(&scene);
        let lines = distant_lines(name, &body, scene.probe.radius_m);
        let mut out = [TickOutput::default(); 2];
        for k in 0..ticks(RAMP_S) + 20 {
            let inputs = [ramp_at(&lines[0], k), ramp_at(&lines[1], k)];
            let (r, allocations) = counted(|| body.tick_tools(&inputs, &mut out));
            r.unwrap();
            assert_eq!(allocations, 0, "{name}: tick {k}");
        }
        assert!(out[0].in_contact && out[1].in_contact);
        assert!(body.event_stats().subdivisions >= 2, "{name}");
        // Through the trait, and slot 0 alone (the other released).
        let inputs = [ramp_at(&lines[0], 300), ramp_at(&lines[1], 300)];
        let (r, allocations) = counted(|| SoftBody::tick_tools(&mut body, &inputs, &mut out));
        r.unwrap();
        assert_eq!(allocations, 0);
        let (r, allocations) = counted(|| body.tick(&inputs[0]));
        r.unwrap();
        assert_eq!(allocations, 0);
    }
}

/// One tool through [`SoftBody::tick_tools`] with the other slot empty is [`SoftBody::tick`]
/// bit for bit over a press that slides (subdivision events) and leaves: the servo ticks every
/// body with all its slots.
#[test]
fn one_tool_in_two_slots_is_the_one_tool_tick_bit_for_bit() {
    for name in SCENES {
        let scene = load_builtin(name).unwrap();
        let mut one = body_of(&scene);
        let mut two = body_of(&scene);
        // Press, slide 0.3 of the path (new areas; 0.15 until session 15, when an area began
        // to stay while the probe's rest foot is in it: 0.15 stayed in the LV's first area),
        // leave.
        let r = scene.probe.radius_m;
        let start = line_at(name, &one, r, 0.0);
        let inputs: Vec<TickInput> = (0..900)
            .map(|k| {
                let s = ((k as f64 - 200.0) / 400.0).clamp(0.0, 1.0);
                match k {
                    0..200 => ramp_at(&start, k),
                    200..800 => TickInput {
                        device_position_m: Some(line_at(name, &one, r, 0.3 * s).device_at(DEPTH_M)),
                        device_velocity_m_per_s: DVec3::ZERO,
                    },
                    _ => TickInput::default(),
                }
            })
            .collect();
        let input = |k: usize| inputs[k];
        for k in 0..900 {
            let o = one.tick(&input(k)).unwrap();
            let mut out = [TickOutput::default(); 2];
            two.tick_tools(&[input(k), TickInput::default()], &mut out)
                .unwrap();
            assert_eq!(o, out[0], "{name}: tick {k}");
            assert!(!out[1].in_contact);
        }
        assert_eq!(one.positions(), two.positions(), "{name}");
        assert_eq!(one.event_stats(), two.event_stats(), "{name}");
        assert!(
            one.event_stats().events >= 2,
            "{name}: {:?}",
            one.event_stats()
        );
    }
}

/// Named tools take their own probe: `[[probe.tool]]` with a force limit in slot 1 clamps that
/// tool's force and not the other's; `tool_slot` names the slot. Three slots for two tools,
/// mismatched lengths and a non-finite input in any slot are refused with the state untouched.
#[test]
fn named_tools_take_their_own_limits_and_hostile_slots_are_refused() {
    let name = "lv-surface-springs";
    let text = format!(
        "{}\nmax_tools = 2\n[[probe.tool]]\nid = \"grasper\"\n[[probe.tool]]\nid = \"needle\"\nmax_force_n = 0.004\n",
        builtin_scene_toml(name).unwrap()
    );
    let deploy = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes");
    let scene = parse_scene_toml(&text, &deploy).expect("scene with named tools");
    let mut body = body_of(&scene);
    assert_eq!(SoftBody::tool_slot(&body, "needle"), Some(1));
    assert_eq!(SoftBody::tool_slot(&body, "grasper"), Some(0));
    assert_eq!(SoftBody::tool_slot(&body, "scalpel"), None);
    let lines = distant_lines(name, &body, scene.probe.radius_m);
    let n = ticks(RAMP_S + 0.2);
    let trace = run(&mut body, n, |k| {
        [ramp_at(&lines[0], k), ramp_at(&lines[1], k)]
    });
    let (f0, f1) = (
        trace[n - 1][0].force_on_device_n.length(),
        trace[n - 1][1].force_on_device_n.length(),
    );
    eprintln!("named: grasper {f0:.4} N, needle {f1:.4} N (limit 0.004 N)");
    assert!(f0 > 0.004, "{f0}");
    assert!((f1 - 0.004).abs() < 1e-12, "{f1}");
    // Hostile slot counts and inputs: nothing changes.
    let before = body.positions().to_vec();
    let time = body.stats().sim_time_s;
    let good = ramp_at(&lines[0], n);
    let bad = TickInput {
        device_position_m: Some(DVec3::new(f64::NAN, 0.0, 0.0)),
        ..good
    };
    let mut out3 = [TickOutput::default(); 3];
    assert!(body.tick_tools(&[good; 3], &mut out3).is_err());
    let mut out2 = [TickOutput::default(); 2];
    assert!(body.tick_tools(&[good; 3], &mut out2).is_err());
    assert!(body.tick_tools(&[], &mut []).is_err());
    assert!(body.tick_tools(&[good, bad], &mut out2).is_err());
    assert!(body.tick_tools(&[bad, good], &mut out2).is_err());
    assert_eq!(body.positions(), &before[..]);
    assert_eq!(body.stats().sim_time_s, time);
    body.tick_tools(&[good, good], &mut out2)
        .expect("a good tick after");
}
