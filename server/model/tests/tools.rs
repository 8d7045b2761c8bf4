//! Several tools in one body (issue 50 section 1, the model side): each tool slot has its own
//! probe (proxy, coupling, contact) and all of them act on the body in the same tick
//! ([`SoftBody::tick_tools`]). On the built-in `lv` (FEM, backward Euler on the whole-body rest
//! factor, the probes' terms joined in one Woodbury solve):
//!
//! - two tools pressing opposite sides hold steady, and the body is in equilibrium: the support
//!   force of the clamp (minus the internal forces at the clamped nodes) balances the sum of
//!   the two device forces;
//! - one tool leaving mid-hold leaves the other's force continuous (the force JND, 7 % per
//!   tick);
//! - two tools at the same point count the body once: with the plain patch contact, two tools
//!   at one device position are exactly one tool of twice the coupling stiffness;
//! - a two-tool tick allocates nothing;
//! - every FEM stepper (CG, symplectic Euler, the implicit sphere) and a fixed active region
//!   carry two tools; hostile slot counts and inputs are refused with nothing changed;
//! - one tool in two slots is the one-tool tick bit for bit (`lv`, `lv-hybrid`);
//! - the hybrid body (`lv-hybrid`) activates under each tool, holds steady, keeps the other's
//!   force continuous when one leaves, and counts two tools on one spot once.

use crate::counting_alloc;
use crate::tool_press;

use glam::DVec3;
use haptic_model::body::{SoftBody, TickInput, TickOutput};
use haptic_model::fem::FemBody;
use haptic_model::integrate::condensed::SEPARATE_BALLS_RADII;
use haptic_model::press::{LV_PROBE_Z_M, PressLine, lv_epicardium_point};
use haptic_model::scene::{Scene, load_builtin};

use counting_alloc::counted;
use tool_press::{RAMP_S, hold_stats, ramp_input, run};

/// The force JND: the largest tick-to-tick change of a held force, as a fraction of it.
const JND: f64 = 0.07;

/// Hold after the ramp ([`RAMP_S`], a C1 smoothstep), s.
const HOLD_S: f64 = 0.6;

/// The press line of a tool on the analytic epicardium at the probe's height and `azimuth`
/// (rad), along the inward normal.
fn line_at(azimuth: f64, radius_m: f64) -> PressLine {
    let (p, n) = lv_epicardium_point(LV_PROBE_Z_M, azimuth);
    PressLine::at_surface_point(p, n, radius_m)
}

/// The clamp's support force on the body, N: minus the internal (elastic and viscous) forces
/// at the clamped nodes.
fn clamp_support_n(body: &FemBody, scene: &Scene) -> DVec3 {
    let state = body.state();
    let mut f = vec![DVec3::ZERO; state.x.len()];
    body.fem()
        .add_internal_forces(&state.x, Some(&state.v), &mut f);
    -scene
        .clamped_nodes
        .iter()
        .map(|&i| f[i as usize])
        .sum::<DVec3>()
}

fn ticks(s: f64) -> usize {
    (s / 1e-3).round() as usize
}

#[test]
fn two_tools_on_opposite_sides_hold_steady_and_balance_at_the_clamp() {
    let scene = load_builtin("lv").unwrap();
    assert_eq!(scene.tools.max_tools, 2);
    let mut body = FemBody::new(&scene).unwrap();
    assert_eq!(SoftBody::max_tools(&body), 2);
    let r = scene.probe.radius_m;
    let (a, b) = (line_at(0.0, r), line_at(std::f64::consts::PI, r));
    let depth = 1.5e-3;
    let n = ticks(RAMP_S + HOLD_S);
    let trace = run(&mut body, n, |k| {
        let t = (k + 1) as f64 * 1e-3;
        [ramp_input(&a, depth, t), ramp_input(&b, depth, t)]
    });
    let hold = ticks(RAMP_S + 0.2)..n;
    let (f0, c0) = hold_stats(&trace, 0, hold.clone());
    let (f1, c1) = hold_stats(&trace, 1, hold);
    let last = trace[n - 1];
    eprintln!(
        "two tools: F0 {f0} (change {c0:.2e}), F1 {f1} (change {c1:.2e}), last {:?} {:?}",
        last[0].force_on_device_n, last[1].force_on_device_n
    );
    assert!(last[0].in_contact && last[1].in_contact);
    // Pressing the surface: each force points out of the body, along its line's outward way.
    assert!(f0.dot(-a.direction) > 0.005, "{f0}");
    assert!(f1.dot(-b.direction) > 0.005, "{f1}");
    assert!(c0 < JND * f0.length(), "tool 0 not steady: {c0} vs {f0}");
    assert!(c1 < JND * f1.length(), "tool 1 not steady: {c1} vs {f1}");
    // Equilibrium: the clamp's support balances the device forces (the body pushes each
    // device with F_k, so the devices push it with -F_k).
    let support = clamp_support_n(&body, &scene);
    let total = last[0].force_on_device_n + last[1].force_on_device_n;
    let scale = f0.length().max(f1.length());
    eprintln!(
        "support {support}, F0 + F1 {total}, residual {}",
        (support - total).length()
    );
    // Measured: 8e-11 N of 18 mN (the hold is settled: the largest tick change is 1e-9 N).
    assert!(
        (support - total).length() < 1e-4 * scale,
        "support {support} vs F0 + F1 {total}"
    );
    // The presses are mirror images across x = 0 (both lines lean the same way in z, along
    // the epicardium's normals): their x components cancel up to the mesh's asymmetry
    // (measured 1.8 %), and the clamp carries the z components.
    assert!(total.x.abs() < 0.05 * scale, "F0 + F1 = {total}");
    assert!(total.z < 0.0 && (total.z - f0.z - f1.z).abs() < 1e-3 * scale);
}

/// Tool 1 leaves mid-hold (its stream ends: no device): tool 0's force stays continuous, and
/// tool 1's slot reports no contact.
#[test]
fn one_tool_leaving_mid_hold_leaves_the_others_force_continuous() {
    let scene = load_builtin("lv").unwrap();
    let mut body = FemBody::new(&scene).unwrap();
    let r = scene.probe.radius_m;
    let (a, b) = (line_at(0.0, r), line_at(std::f64::consts::PI, r));
    let depth = 1.5e-3;
    let leave = ticks(RAMP_S + 0.3);
    let n = leave + ticks(0.3);
    let trace = run(&mut body, n, |k| {
        let t = (k + 1) as f64 * 1e-3;
        let second = if k < leave {
            ramp_input(&b, depth, t)
        } else {
            TickInput::default()
        };
        [ramp_input(&a, depth, t), second]
    });
    let (held, _) = hold_stats(&trace, 0, leave - 100..leave);
    let (_, change) = hold_stats(&trace, 0, leave - 1..n);
    let (after, _) = hold_stats(&trace, 0, n - 50..n);
    eprintln!(
        "tool 0 held {held}, largest change after tool 1 left {change:.3e} N ({:.2} %), settled {after}",
        100.0 * change / held.length()
    );
    assert!(change < JND * held.length(), "{change} vs {held}");
    assert!(!trace[leave][1].in_contact && trace[leave - 1][1].in_contact);
    assert_eq!(trace[leave][1].force_on_device_n, DVec3::ZERO);
    assert!(trace[n - 1][0].in_contact);
}

/// The built-in `lv` with the plain patch contact and the coupling stiffness `k` (N/m).
fn patch_lv(k: f64) -> Scene {
    let mut scene = load_builtin("lv").unwrap();
    scene.probe.contact = haptic_model::contact::ContactModel::Patch;
    scene.probe.coupling_stiffness_n_per_m = k;
    scene
}

/// Two tools on the same facets count the body once. With the patch contact (the proxy a
/// function of the device position alone), two tools at one device position are exactly one
/// tool of twice the coupling stiffness and damping: the same reaction on the same nodes, and
/// the joined implicit term (two identical rows of compliance `1/c` each) is the one row of
/// compliance `1/(2c)`. So their summed force must equal that tool's to round-off; 0.2 mm
/// apart, within the patch's change over 0.2 mm (measured below 1 %; bound 3 %). Each hold is
/// steady (no chatter between the two).
#[test]
fn two_tools_on_the_same_facets_count_the_body_once() {
    let k = 300.0;
    let scene = patch_lv(k);
    let r = scene.probe.radius_m;
    let a = line_at(0.0, r);
    let depth = 1.5e-3;
    let n = ticks(RAMP_S + HOLD_S);
    let hold = ticks(RAMP_S + 0.2)..n;
    // One tool of twice the coupling (stiffness and damping).
    let mut single_scene = patch_lv(2.0 * k);
    single_scene.probe.coupling_damping_n_s_per_m *= 2.0;
    let mut single = FemBody::new(&single_scene).unwrap();
    let one = run(&mut single, n, |k| {
        let t = (k + 1) as f64 * 1e-3;
        [ramp_input(&a, depth, t), TickInput::default()]
    });
    let (f_one, c_one) = hold_stats(&one, 0, hold.clone());
    // Two tools at one position.
    let mut body = FemBody::new(&scene).unwrap();
    let both = run(&mut body, n, |k| {
        let t = (k + 1) as f64 * 1e-3;
        let i = ramp_input(&a, depth, t);
        [i, i]
    });
    let (f0, c0) = hold_stats(&both, 0, hold.clone());
    let (f1, c1) = hold_stats(&both, 1, hold.clone());
    let total = f0 + f1;
    eprintln!(
        "same point: one tool 2k {f_one} (change {c_one:.1e}), two tools {f0} + {f1} = {total} (changes {c0:.1e} {c1:.1e}), rel. difference {:.2e}",
        (total - f_one).length() / f_one.length()
    );
    assert!(f0.is_finite() && f1.is_finite());
    assert!(
        (total - f_one).length() < 1e-6 * f_one.length(),
        "{total} vs {f_one}"
    );
    assert!(c0 < JND * f0.length() && c1 < JND * f1.length());
    // 0.2 mm apart across the line (tangent to the surface).
    let offset = DVec3::new(0.0, 0.1e-3, 0.0);
    let mut body = FemBody::new(&scene).unwrap();
    let near = run(&mut body, n, |k| {
        let t = (k + 1) as f64 * 1e-3;
        let i = ramp_input(&a, depth, t);
        let shifted = |d: DVec3| TickInput {
            device_position_m: i.device_position_m.map(|p| p + d),
            ..i
        };
        [shifted(offset), shifted(-offset)]
    });
    let (g0, d0) = hold_stats(&near, 0, hold.clone());
    let (g1, d1) = hold_stats(&near, 1, hold);
    let total = g0 + g1;
    let rel = (total - f_one).length() / f_one.length();
    eprintln!(
        "0.2 mm apart: {g0} + {g1} = {total}, rel. difference {rel:.2e}, changes {d0:.1e} {d1:.1e}"
    );
    assert!(rel < 0.03, "{total} vs {f_one}");
    assert!(d0 < JND * g0.length() && d1 < JND * g1.length());
}

/// A two-tool tick of the built-in `lv` with both tools in contact allocates nothing.
#[test]
fn a_two_tool_tick_allocates_nothing() {
    let scene = load_builtin("lv").unwrap();
    let mut body = FemBody::new(&scene).unwrap();
    let r = scene.probe.radius_m;
    let (a, b) = (line_at(0.0, r), line_at(std::f64::consts::PI, r));
    let n = ticks(RAMP_S) + 20;
    let input = |k: usize| {
        let t = (k + 1) as f64 * 1e-3;
        [ramp_input(&a, 1e-3, t), ramp_input(&b, 1e-3, t)]
    };
    run(&mut body, n, input);
    let mut out = [TickOutput::default(); 2];
    for k in n..n + 20 {
        let inputs = input(k);
        let (r, allocations) = counted(|| body.tick_tools(&inputs, &mut out));
        r.unwrap();
        assert_eq!(allocations, 0, "tick {k}");
        assert!(out[0].in_contact && out[1].in_contact);
    }
    // Through the trait too, and with one slot (the other probe released).
    let (r, allocations) = counted(|| SoftBody::tick_tools(&mut body, &input(n + 20), &mut out));
    r.unwrap();
    assert_eq!(allocations, 0);
    let (r, allocations) = counted(|| body.tick(&input(n + 21)[0]));
    r.unwrap();
    assert_eq!(allocations, 0);
}

/// A named change of the built-in `lv` scene.
type Variant = (&'static str, fn(&mut Scene));

/// Every FEM stepper carries two tools: backward Euler with conjugate gradients (the joined
/// term in its preconditioner and operator), the explicit symplectic Euler (the couplings
/// completed one after another) and the implicit sphere contact on the rest factor (one row
/// per face of each tool, joined): opposite presses hold steady and the clamp balances them.
#[test]
fn every_fem_stepper_carries_two_tools_in_equilibrium() {
    use haptic_model::contact::ContactModel;
    use haptic_model::integrate::{IntegratorKind, LinearSolver};
    let variants: [Variant; 3] = [
        ("backward Euler, CG", |s| {
            s.integrator.linear_solver = LinearSolver::Cg;
        }),
        ("symplectic Euler", |s| {
            s.integrator.kind = IntegratorKind::SymplecticEuler;
        }),
        ("implicit sphere", |s| {
            s.probe.contact = ContactModel::Sphere
        }),
    ];
    for (name, change) in variants {
        let mut scene = load_builtin("lv").unwrap();
        change(&mut scene);
        let mut body = FemBody::new(&scene).unwrap();
        let r = scene.probe.radius_m;
        let (a, b) = (line_at(0.0, r), line_at(std::f64::consts::PI, r));
        let n = ticks(RAMP_S + HOLD_S);
        let trace = run(&mut body, n, |k| {
            let t = (k + 1) as f64 * 1e-3;
            [ramp_input(&a, 1.5e-3, t), ramp_input(&b, 1.5e-3, t)]
        });
        let hold = ticks(RAMP_S + 0.2)..n;
        let (f0, c0) = hold_stats(&trace, 0, hold.clone());
        let (f1, c1) = hold_stats(&trace, 1, hold);
        let total = trace[n - 1][0].force_on_device_n + trace[n - 1][1].force_on_device_n;
        let support = clamp_support_n(&body, &scene);
        let scale = f0.length().max(f1.length());
        let residual = (support - total).length() / scale;
        eprintln!(
            "{name}: F0 {f0} F1 {f1}, changes {:.2e} {:.2e} of the hold, clamp residual {residual:.2e}",
            c0 / f0.length(),
            c1 / f1.length()
        );
        assert!(
            f0.dot(-a.direction) > 0.005 && f1.dot(-b.direction) > 0.005,
            "{name}"
        );
        assert!(c0 < JND * f0.length() && c1 < JND * f1.length(), "{name}");
        assert!(residual < 1e-3, "{name}: support {support} vs {total}");
    }
}

/// The hybrid body (`lv-hybrid`): two tools on opposite sides activate the particles under
/// each (the union; neither evicts the other's regions for room), hold steady, and one
/// leaving (withdrawn over `RELEASE_FADE_TICKS`) leaves the other's force continuous
/// (measured 2.2 % per tick at most); a two-tool tick allocates nothing.
#[test]
fn hybrid_two_tools_activate_under_each_hold_steady_and_release_continuously() {
    let scene = load_builtin("lv-hybrid").unwrap();
    assert_eq!(scene.tools.max_tools, 2);
    let mut body = haptic_model::build_body(&scene).unwrap();
    let r = scene.probe.radius_m;
    let (a, b) = (line_at(0.0, r), line_at(std::f64::consts::PI, r));
    let depth = 1.5e-3;
    let leave = ticks(RAMP_S + 0.4);
    let n = leave + ticks(0.2);
    let mut trace = Vec::with_capacity(n);
    let mut active_both = 0;
    for k in 0..n {
        let t = (k + 1) as f64 * 1e-3;
        let second = if k < leave {
            ramp_input(&b, depth, t)
        } else {
            TickInput::default()
        };
        let inputs = [ramp_input(&a, depth, t), second];
        let mut out = [TickOutput::default(); 2];
        let (r, allocations) = counted(|| body.tick_tools(&inputs, &mut out));
        r.unwrap();
        if k > ticks(RAMP_S) {
            assert_eq!(allocations, 0, "tick {k}");
        }
        if k == leave - 1 {
            active_both = body.stats().active_particles;
        }
        trace.push(out);
    }
    let hold = ticks(RAMP_S + 0.2)..leave;
    let (f0, c0) = hold_stats(&trace, 0, hold.clone());
    let (f1, c1) = hold_stats(&trace, 1, hold);
    let (_, after) = hold_stats(&trace, 0, leave - 1..n);
    eprintln!(
        "hybrid: F0 {f0} F1 {f1}, hold changes {:.2e} {:.2e}, after tool 1 left {:.2} %, active particles {active_both}",
        c0 / f0.length(),
        c1 / f1.length(),
        100.0 * after / f0.length()
    );
    assert!(f0.dot(-a.direction) > 0.005 && f1.dot(-b.direction) > 0.005);
    assert!(c0 < JND * f0.length() && c1 < JND * f1.length());
    assert!(after < JND * f0.length());
    assert!(!trace[n - 1][1].in_contact && trace[n - 1][0].in_contact);
}

/// A fixed active region (condensed far field) takes two tools inside it, each with its own
/// contact, holding steady; a tool outside the region touches nothing there (its triangles
/// are condensed: docs/scenes.md, "Several tools").
#[test]
fn a_fixed_region_takes_two_tools_inside_it() {
    let text = format!(
        "{}\n[active_region]\ncentre_m = [0.0097, 0.0, -0.005]\nradius_m = 0.008\n",
        haptic_model::scene::builtin_scene_toml("lv")
            .unwrap()
            .replace("linear_solver = \"rest-cholesky\"", "")
            .replace("stiffness_margin = 2.0", "")
    );
    let scene = haptic_model::scene::parse_scene_toml(&text, std::path::Path::new(".")).unwrap();
    assert_eq!(scene.tools.max_tools, 2);
    let mut body = FemBody::new(&scene).unwrap();
    assert!(body.condensed().is_some_and(|c| !c.is_whole_body()));
    let r = scene.probe.radius_m;
    let (a, b) = (line_at(0.25, r), line_at(-0.25, r));
    let n = ticks(RAMP_S + HOLD_S);
    let trace = run(&mut body, n, |k| {
        let t = (k + 1) as f64 * 1e-3;
        [ramp_input(&a, 1.5e-3, t), ramp_input(&b, 1.5e-3, t)]
    });
    let hold = ticks(RAMP_S + 0.2)..n;
    let (f0, c0) = hold_stats(&trace, 0, hold.clone());
    let (f1, c1) = hold_stats(&trace, 1, hold);
    eprintln!(
        "fixed region: F0 {f0} F1 {f1}, changes {:.2e} {:.2e} of the hold",
        c0 / f0.length(),
        c1 / f1.length()
    );
    assert!(trace[n - 1][0].in_contact && trace[n - 1][1].in_contact);
    assert!(f0.dot(-a.direction) > 0.005 && f1.dot(-b.direction) > 0.005);
    assert!(c0 < JND * f0.length() && c1 < JND * f1.length());
    // The far side is condensed: no contact there.
    let far = line_at(std::f64::consts::PI, r);
    let mut out = [TickOutput::default(); 2];
    body.tick_tools(
        &[ramp_input(&a, 1.5e-3, 1.0), ramp_input(&far, 1.5e-3, 1.0)],
        &mut out,
    )
    .unwrap();
    assert!(out[0].in_contact && !out[1].in_contact);
}

/// Hostile slot counts and inputs: refused with a clear error, the state untouched (the next
/// tick is the same as on an untouched body).
#[test]
fn bad_slot_counts_and_one_bad_input_refuse_the_tick_and_change_nothing() {
    let scene = load_builtin("lv").unwrap();
    let mut body = FemBody::new(&scene).unwrap();
    let mut twin = FemBody::new(&scene).unwrap();
    let a = line_at(0.0, scene.probe.radius_m);
    let good = ramp_input(&a, 1e-3, 0.1);
    let bad = TickInput {
        device_position_m: Some(DVec3::new(f64::NAN, 0.0, 0.0)),
        ..good
    };
    let mut out3 = [TickOutput::default(); 3];
    let mut out2 = [TickOutput::default(); 2];
    let mut out1 = [TickOutput::default(); 1];
    let refused = [
        body.tick_tools(&[good; 3], &mut out3).unwrap_err(),
        body.tick_tools(&[good; 2], &mut out1).unwrap_err(),
        body.tick_tools(&[], &mut []).unwrap_err(),
        body.tick_tools(&[good, bad], &mut out2).unwrap_err(),
    ];
    for e in &refused {
        eprintln!("refused: {e}");
        assert!(!e.to_string().is_empty());
    }
    assert_eq!(body.state().time_s, 0.0);
    body.tick_tools(&[good, good], &mut out2).unwrap();
    let mut expected = [TickOutput::default(); 2];
    twin.tick_tools(&[good, good], &mut expected).unwrap();
    assert_eq!(out2, expected);
}

/// Two tools pressing the same spot of the hybrid body (`lv-hybrid`), 0.2 mm apart: both
/// forces finite and steady (no chatter between the two proxies on the same particles), and
/// together they carry what one tool pressed to the same depth carries.
#[test]
fn hybrid_two_tools_on_the_same_spot_hold_steady() {
    let scene = load_builtin("lv-hybrid").unwrap();
    let mut body = haptic_model::build_body(&scene).unwrap();
    let a = line_at(0.0, scene.probe.radius_m);
    let offset = DVec3::new(0.0, 0.1e-3, 0.0);
    let n = ticks(RAMP_S + HOLD_S);
    let mut trace = Vec::with_capacity(n);
    for k in 0..n {
        let i = ramp_input(&a, 1.5e-3, (k + 1) as f64 * 1e-3);
        let shifted = |d: DVec3| TickInput {
            device_position_m: i.device_position_m.map(|p| p + d),
            ..i
        };
        let mut out = [TickOutput::default(); 2];
        body.tick_tools(&[shifted(offset), shifted(-offset)], &mut out)
            .unwrap();
        trace.push(out);
    }
    let hold = ticks(RAMP_S + 0.2)..n;
    let (f0, c0) = hold_stats(&trace, 0, hold.clone());
    let (f1, c1) = hold_stats(&trace, 1, hold);
    eprintln!(
        "hybrid same spot: F0 {f0} F1 {f1} (sum {}), changes {:.2e} {:.2e} of the hold",
        f0 + f1,
        c0 / f0.length(),
        c1 / f1.length()
    );
    // One tool on the same line, for the record.
    let mut single = haptic_model::build_body(&scene).unwrap();
    let mut last = TickOutput::default();
    for k in 0..n {
        last = single
            .tick(&ramp_input(&a, 1.5e-3, (k + 1) as f64 * 1e-3))
            .unwrap();
    }
    eprintln!("hybrid one tool: {}", last.force_on_device_n);
    // No double counting: the two tools carry what one does, a little more for their doubled
    // coupling in series with the soft wall (k = 300 N/m against about 10 N/m: a few %;
    // measured +4 %), not twice as much.
    let one = last.force_on_device_n;
    assert!(
        (f0 + f1 - one).length() < 0.1 * one.length(),
        "{} vs {one}",
        f0 + f1
    );
    assert!(f0.is_finite() && f1.is_finite());
    assert!(f0.dot(-a.direction) > 0.002 && f1.dot(-a.direction) > 0.002);
    assert!(c0 < JND * f0.length() && c1 < JND * f1.length());
}

/// Named tools (`[[probe.tool]]`) take the slot of their index with their own radius and force
/// limit: on the built-in `lv`, a 3 mm tool pushes harder than a 2 mm one pressed as deep (a
/// larger sphere), and a tool limited to 5 mN is held there.
#[test]
fn named_tools_take_their_slots_with_their_own_radius_and_force_limit() {
    let scene_with = |radius_m: f64| {
        let text = format!(
            "{}max_tools = 2\n[[probe.tool]]\nid = \"grasper\"\nradius_m = {radius_m}\n[[probe.tool]]\nid = \"needle\"\nmax_force_n = 0.005\n",
            haptic_model::scene::builtin_scene_toml("lv").unwrap()
        );
        haptic_model::scene::parse_scene_toml(&text, std::path::Path::new(".")).unwrap()
    };
    let press = |radius_m: f64| {
        let mut body = FemBody::new(&scene_with(radius_m)).unwrap();
        assert_eq!(SoftBody::tool_slot(&body, "grasper"), Some(0));
        assert_eq!(SoftBody::tool_slot(&body, "needle"), Some(1));
        assert_eq!(SoftBody::tool_slot(&body, "scalpel"), None);
        let (a, b) = (line_at(0.0, radius_m), line_at(std::f64::consts::PI, 0.002));
        let n = ticks(RAMP_S + 0.3);
        let trace = run(&mut body, n, |k| {
            let t = (k + 1) as f64 * 1e-3;
            [ramp_input(&a, 1.5e-3, t), ramp_input(&b, 1.5e-3, t)]
        });
        trace[n - 1]
    };
    let [big, needle] = press(0.003);
    let [small, _] = press(0.002);
    eprintln!(
        "grasper 3 mm {} N, 2 mm {} N, needle {} N",
        big.force_on_device_n, small.force_on_device_n, needle.force_on_device_n
    );
    assert!(big.in_contact && small.in_contact && needle.in_contact);
    assert!(big.force_on_device_n.length() > 1.05 * small.force_on_device_n.length());
    assert!((needle.force_on_device_n.length() - 0.005).abs() < 1e-12);
}

/// `lv_h1_condensed.toml` as shipped (a following region with its coarse companion), its
/// regions prepared on demand (tiles off: the union of several balls is prepared on demand
/// anyway, and a blocking request would otherwise also wait for the tile being built).
fn lv_h1_following() -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../deploy/scenes/lv_h1_condensed.toml");
    let mut scene = haptic_model::scene::load_scene_file(&path).expect("lv_h1_condensed.toml");
    let region = scene.active_region.as_mut().expect("region");
    assert!(region.follow && scene.fallback.is_some());
    region.tiles = haptic_model::integrate::condensed::TileMode::Off;
    scene
}

/// A body of `scene` whose ticks wait for each region they request (deterministic swaps).
fn blocking_body(scene: &Scene) -> FemBody {
    let mut body = FemBody::new(scene).expect("following body");
    body.set_blocking_region_preparation(true);
    body
}

/// Per tick of a two-slot run: the outputs, the companion's weights of the two slots and the
/// following region's balls (0 and 0 without).
type FollowTrace = Vec<([TickOutput; 2], [f64; 2], usize)>;

/// Runs `ticks` two-slot ticks of `body` with `input(tick)`; returns the trace and the
/// allocations the ticks made on this thread.
fn run_following(
    body: &mut FemBody,
    ticks: usize,
    mut input: impl FnMut(usize) -> [TickInput; 2],
) -> (FollowTrace, usize) {
    let mut trace = Vec::with_capacity(ticks);
    let mut allocations = 0;
    for k in 0..ticks {
        let mut out = [TickOutput::default(); 2];
        let inputs = input(k);
        let (ticked, a) = counted(|| body.tick_tools(&inputs, &mut out));
        ticked.expect("tick");
        allocations += a;
        let w = body.fallback_stats().map_or([0.0; 4], |f| f.weights);
        let balls = body.follow_stats().map_or(0, |f| f.balls);
        trace.push((out, [w[0], w[1]], balls));
    }
    (trace, allocations)
}

/// The shipped following region (`lv_h1_condensed`) takes two tools (its default): tool 0 at
/// azimuth 0 and tool 1 either on the opposite side (19 mm apart) or at 2.35 rad round (centres
/// 2.55 radii apart, just past `SEPARATE_BALLS_RADII`: the closest balls whose coupling the tick
/// matrix leaves out), both pressing 1 mm, get a region of two balls, one at each (prepared at
/// the first request, before contact), so the region answers both (the companion's weights stay
/// 0) and each hold is steady. Each force is within `FORCE_TOL` of the whole body's
/// (`lv_h1.toml`, nothing condensed) with the same two tools; and pressing the other side
/// changes tool 0's force as it changes the whole body's (two opposite presses cancel the
/// ventricle's bending: each force is 15-16 % above one tool's alone, on both models). Tool 1
/// leaving mid-hold leaves tool 0's force continuous (under the 7 % JND per tick) while the
/// region shrinks back to one ball. The two-tool ticks, swaps included, allocate nothing. The
/// two placements share their one-tool references (tool 0 alone on the region and on the whole
/// body), so they are one test.
#[test]
fn a_following_region_covers_two_tools_apart_and_lets_one_leave() {
    let scene = lv_h1_following();
    assert_eq!(scene.tools.max_tools, 2);
    let whole = {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes/lv_h1.toml");
        haptic_model::scene::load_scene_file(&path).expect("lv_h1.toml")
    };
    let r = scene.probe.radius_m;
    let a = line_at(0.0, r);
    let azimuths = [std::f64::consts::PI, 2.35];
    let (n, leave_for) = (ticks(RAMP_S + HOLD_S), ticks(0.3));
    let press = |scene: &Scene, second: Option<PressLine>| {
        let mut body = blocking_body(scene);
        run_following(&mut body, n, |k| {
            let none = TickInput::default();
            [
                two_tool_input(&a, k),
                second.as_ref().map_or(none, |b| two_tool_input(b, k)),
            ]
        })
        .0
    };
    std::thread::scope(|s| {
        let (scene, whole, press) = (&scene, &whole, &press);
        let alone = s.spawn(move || press(scene, None));
        let whole_alone = s.spawn(move || press(whole, None));
        let whole_two = azimuths.map(|az| s.spawn(move || press(whole, Some(line_at(az, r)))));
        let refs = TwoToolRefs {
            alone: alone.join().expect("region, tool 0 alone"),
            whole_alone: whole_alone.join().expect("whole body, tool 0 alone"),
        };
        for (azimuth, whole_two) in azimuths.into_iter().zip(whole_two) {
            let two = run_two_tools(scene, &a, &line_at(azimuth, r), n, leave_for);
            let whole_two = whole_two.join().expect("whole body, two tools");
            let lines = [a, line_at(azimuth, r)];
            check_two_tools_apart(lines, &two, &whole_two, &refs, n, leave_for);
        }
    });
}

/// Tool `line`'s input at tick `k` of the two-tool presses: a 1 mm ramp.
fn two_tool_input(line: &PressLine, k: usize) -> TickInput {
    ramp_input(line, 1e-3, (k + 1) as f64 * 1e-3)
}

/// The one-tool references of [`a_following_region_covers_two_tools_apart_and_lets_one_leave`]:
/// tool 0 alone on the following region and on the whole body.
struct TwoToolRefs {
    alone: FollowTrace,
    whole_alone: FollowTrace,
}

/// Tools 0 and 1 on `a` and `b` pressing the following region of `scene` for `n` ticks, then
/// tool 0 alone for `leave_for` ticks; checks the region's two balls apart and no allocation
/// on this thread. Returns the trace.
fn run_two_tools(
    scene: &Scene,
    a: &PressLine,
    b: &PressLine,
    n: usize,
    leave_for: usize,
) -> FollowTrace {
    let mut body = blocking_body(scene);
    let (mut two, mut allocations) = run_following(&mut body, n, |k| {
        [two_tool_input(a, k), two_tool_input(b, k)]
    });
    let balls = body.condensed().expect("region").balls();
    let gap = match balls.centres() {
        [p, q] => p.distance(*q) / scene.active_region.expect("region").radius_m,
        other => panic!("{other:?}"),
    };
    eprintln!("ball centres {gap:.3} radii apart");
    assert!(gap >= SEPARATE_BALLS_RADII);
    let (left, a_left) = run_following(&mut body, leave_for, |k| {
        [two_tool_input(a, n + k), TickInput::default()]
    });
    two.extend(left);
    allocations += a_left;
    let stats = body.follow_stats().expect("follows");
    eprintln!("two tools: {stats:?}");
    assert_eq!(stats.failed, 0);
    assert_eq!(allocations, 0, "the two-tool ticks allocated");
    two
}

/// The checks of [`a_following_region_covers_two_tools_apart_and_lets_one_leave`] with the
/// tools on `lines`: `two` the region's trace (`n` two-tool ticks, then `leave_for` with tool 0
/// alone), `whole_two` the whole body's with both tools.
fn check_two_tools_apart(
    [a, b]: [PressLine; 2],
    two: &FollowTrace,
    whole_two: &FollowTrace,
    refs: &TwoToolRefs,
    n: usize,
    leave_for: usize,
) {
    const FORCE_TOL: f64 = 0.03;
    let hold = ticks(RAMP_S + 0.2)..n;
    let outs = |t: &FollowTrace| t.iter().map(|e| e.0).collect::<Vec<_>>();
    let two_out = outs(two);
    let [alone, whole_two, whole_alone] = [&refs.alone, whole_two, &refs.whole_alone].map(outs);
    // The region covers both from before contact to the end of the hold.
    let first_contact = two_out
        .iter()
        .position(|o| o[0].in_contact || o[1].in_contact);
    let covered = two[first_contact.expect("contact")..n]
        .iter()
        .all(|(_, w, balls)| *balls == 2 && *w == [0.0, 0.0]);
    assert!(covered, "the companion answered or the region lost a ball");
    let mean = |t: &[[TickOutput; 2]], slot| hold_stats(t, slot, hold.clone()).0;
    for slot in 0..2 {
        let (f, change) = hold_stats(&two_out, slot, hold.clone());
        let f_whole = mean(&whole_two, slot);
        let rel = (f - f_whole).length() / f_whole.length();
        eprintln!("tool {slot}: {f} (change {change:.2e} N), whole body {f_whole}, rel. {rel:.4}");
        assert!(two_out[n - 1][slot].in_contact);
        assert!(change < JND * f.length(), "tool {slot} not steady");
        assert!(f.dot(-[a, b][slot].direction) > 0.005, "{f}");
        assert!(
            rel < FORCE_TOL,
            "tool {slot}: {f} vs {f_whole} on the whole body"
        );
    }
    // The second tool's effect on the first, on both models.
    let gain = |two: &[[TickOutput; 2]], one: &[[TickOutput; 2]]| {
        mean(two, 0).length() / mean(one, 0).length()
    };
    let (g_region, g_whole) = (gain(&two_out, &alone), gain(&whole_two, &whole_alone));
    eprintln!(
        "tool 0 with the other side pressed / alone: region {g_region:.4}, whole body {g_whole:.4}"
    );
    assert!((g_region - g_whole).abs() < FORCE_TOL * g_whole);
    // Tool 1 leaves: tool 0 continuous, the region back to one ball.
    let (held, _) = hold_stats(&two_out, 0, n - 100..n);
    let (_, change) = hold_stats(&two_out, 0, n - 1..n + leave_for);
    eprintln!(
        "tool 1 left: tool 0's largest change {:.2} % per tick",
        100.0 * change / held.length()
    );
    assert!(change < JND * held.length(), "{change} vs {held}");
    let shrunk = (n..n + leave_for)
        .find(|&k| two[k].2 == 1)
        .expect("one ball again");
    let step = |k: usize| {
        let f = |k: usize| two_out[k][0].force_on_device_n;
        100.0 * (f(k) - f(k - 1)).length() / held.length()
    };
    eprintln!(
        "tick by tick after tool 1 left (%): {:?}; one ball from tick {}",
        (n..n + 30)
            .map(step)
            .map(|c| (c * 100.0).round() / 100.0)
            .collect::<Vec<_>>(),
        shrunk - n
    );
    assert!(!two_out[n][1].in_contact && two_out[n + leave_for - 1][0].in_contact);
    assert_eq!(two.last().expect("ticks").2, 1);
}

/// On a following region (`lv_h1_condensed`) too, one tool in slot 0 of two is the one-tool
/// tick bit for bit (its swaps included): forces and state.
#[test]
fn one_tool_in_two_slots_of_a_following_region_is_the_one_tool_tick_bit_for_bit() {
    let scene = lv_h1_following();
    let (mut one, mut two) = (blocking_body(&scene), blocking_body(&scene));
    // Half a radian round from the region's first centre: the region moves to the tool.
    let a = line_at(0.5, scene.probe.radius_m);
    assert_slot_zero_is_the_tick(
        &mut one,
        &mut two,
        &a,
        ticks(RAMP_S + 0.05),
        "lv_h1_condensed",
    );
    assert!(one.follow_stats().expect("follows").swaps >= 1);
    assert_eq!(
        one.follow_stats().unwrap().swaps,
        two.follow_stats().unwrap().swaps
    );
    let bits = |b: &FemBody| -> Vec<[u64; 3]> {
        b.state()
            .x
            .iter()
            .map(|p| p.to_array().map(f64::to_bits))
            .collect()
    };
    assert!(bits(&one) == bits(&two), "the states differ");
}

/// Once run alone in its own binary: beside the other tests here the two `lv-hybrid` bodies
/// differed by 1.2e-5 of the force at first contact in 1 of 7 runs (session 11). The cause was
/// METIS ordering two bodies' core factors at once on two test threads from one C random
/// stream (now serialised: `tests/ordering_threads.rs`).
#[test]
fn one_tool_in_two_slots_is_the_one_tool_tick_bit_for_bit() {
    for name in ["lv", "lv-hybrid"] {
        let scene = load_builtin(name).unwrap();
        let build = || haptic_model::build_body(&scene).unwrap();
        let (mut one, mut two) = (build(), build());
        assert_eq!(two.max_tools(), 2, "{name}");
        let a = line_at(0.0, scene.probe.radius_m);
        assert_slot_zero_is_the_tick(&mut *one, &mut *two, &a, ticks(RAMP_S + 0.1), name);
    }
}

/// Presses `one` through `tick` and `two` through `tick_tools` with the same input in slot 0
/// and slot 1 empty, `n` ticks of a 1 mm ramp on `line`: the outputs equal bit for bit.
fn assert_slot_zero_is_the_tick(
    one: &mut dyn SoftBody,
    two: &mut dyn SoftBody,
    line: &PressLine,
    n: usize,
    name: &str,
) {
    for k in 0..n {
        let input = ramp_input(line, 1e-3, (k + 1) as f64 * 1e-3);
        let expected = one.tick(&input).unwrap();
        let mut out = [TickOutput::default(); 2];
        two.tick_tools(&[input, TickInput::default()], &mut out)
            .unwrap();
        assert_eq!(out[0], expected, "{name} tick {k}");
        assert!(!out[1].in_contact, "{name} tick {k}");
    }
}
