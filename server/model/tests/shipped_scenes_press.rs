//! Every scene a user can start (the built-ins and every `deploy/scenes/*.toml`) pressed as the
//! demo presses (issue 46, section 5): the probe driven through [`SoftBody::tick`] at 10 mm/s
//! to 3.7 mm past first contact, then held 1 s ([`press::constant_speed_press`]). Each must
//! build, never fault, push back harder the deeper it is pressed (the force at every 0.25 mm of
//! the press above the one before), and hold steady: no tick-to-tick change of the force above
//! 7 % (the force JND) of the held force, the probe in contact throughout the hold. A scene that
//! is not meant for the haptic loop (`[model] realtime = false`) must be refused by
//! [`build_body`] naming that key.
//!
//! Each scene is its own test so that they share the machine's cores; the deploy copies of the
//! built-ins are pressed as built-ins (`scene_parse.rs` checks they are identical), and a test
//! fails when a shipped scene has no press here.

use std::path::PathBuf;

use haptic_model::body::SoftBody;
use haptic_model::press::{self, PressLine};
use haptic_model::scene::{Scene, builtin_scene_names, load_builtin, load_scene_file};
use haptic_model::{DVec3, ModelError, build_body};

/// The demo's press: 10 mm/s to 3.7 mm, a 1 s hold.
const SPEED_M_PER_S: f64 = 0.010;
const DEPTH_M: f64 = 3.7e-3;
const HOLD_S: f64 = 1.0;
/// The force just-noticeable difference: the largest tick-to-tick change allowed in a hold.
const JND: f64 = 0.07;

/// How each shipped scene is pressed: its press line, or `None` for a static benchmark the
/// haptic loop must refuse.
fn press_line(name: &str, body: &dyn SoftBody) -> Option<PressLine> {
    let r = body.info().probe_radius_m;
    let rest = |from_mm: [f64; 3], dir: [f64; 3]| {
        PressLine::from_rest_surface(body, DVec3::from(from_mm) * 1e-3, DVec3::from(dir), r)
            .unwrap_or_else(|e| panic!("{name}: {e}"))
    };
    Some(match name {
        // The seed's ellipsoidal shell (outer semi-axes 10, 10, 16 mm): its equator on +x.
        "ellipsoids" | "ellipsoids-hybrid" => rest([15.0, 0.0, 0.0], [-1.0, 0.0, 0.0]),
        // The 50 mm dome, rim clamped: its top.
        "hemisphere-springs" => rest([0.0, 0.0, 70.0], [0.0, 0.0, -1.0]),
        // Every left ventricle: the lv-probe line (the analytic epicardium's depth zero).
        _ => PressLine::lv_probe(r),
    })
}

fn deploy_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../deploy/scenes")
}

/// Shipped scene files that are not copies of built-ins, with whether the haptic loop runs them.
const DEPLOY_FILES: &[(&str, bool)] = &[
    ("lv_h1", true),
    ("lv_h1_condensed", true),
    ("lv_h1_es", true),
    ("lv_h2", true),
    ("lv_h3", true),
    ("lv_h3_v41", true),
    ("lv_100k_condensed", true),
    ("lv_h2_inflation", true),
    ("lv_guccione_inflation", false),
    ("lv_h2_guccione_inflation", false),
];

fn press_scene(scene: &Scene) {
    let name = scene.name.clone();
    let mut body = build_body(scene).unwrap_or_else(|e| panic!("{name}: {e}"));
    let line = press_line(&name, body.as_ref()).expect("a press line");
    let tick = body.info().tick_s;
    let (hold, trace) =
        press::constant_speed_press(body.as_mut(), &line, DEPTH_M, SPEED_M_PER_S, HOLD_S, tick)
            .unwrap_or_else(|e| panic!("{name}: the press faulted: {e}"));
    // Monotone: the force at each 0.25 mm of the press exceeds the one before.
    let mut last = (0.0, 0.0);
    let mut depth = 0.25e-3;
    for (k, f) in trace.force_n.iter().enumerate() {
        if line.depth_of(trace.device_m[k]) + 1e-12 >= depth && depth <= DEPTH_M {
            let f = f.length();
            assert!(
                f > last.1,
                "{name}: {:.4} mN at {:.2} mm, not above {:.4} mN at {:.2} mm",
                f * 1e3,
                depth * 1e3,
                last.1 * 1e3,
                last.0 * 1e3
            );
            last = (depth, f);
            depth += 0.25e-3;
        }
    }
    assert!(depth > DEPTH_M, "{name}: the press stopped at {depth} m");
    assert_eq!(
        hold.contact_ticks, hold.hold_ticks,
        "{name}: the probe left the surface during the hold"
    );
    assert!(
        hold.steadiness() <= JND,
        "{name}: the hold at 3.7 mm is not steady: {:.3} mN mean, {:.3}..{:.3} mN, a tick-to-tick \
         change of {:.3} mN ({:.1} % > 7 %)",
        hold.force_n * 1e3,
        hold.force_min_n * 1e3,
        hold.force_max_n * 1e3,
        hold.max_tick_change_n * 1e3,
        100.0 * hold.steadiness()
    );
    eprintln!(
        "{name}: {:.3} mN held at 3.7 mm (sphere depth {:.3} mm), largest tick change {:.2} %, \
         tick p50 {:.0} us",
        hold.force_n * 1e3,
        hold.sphere_depth_m * 1e3,
        100.0 * hold.steadiness(),
        trace.tick_quantile_s(0.5) * 1e6
    );
}

fn press_builtin(name: &str) {
    press_scene(&load_builtin(name).unwrap_or_else(|e| panic!("{name}: {e}")));
}

fn press_file(stem: &str) {
    let scene = load_scene_file(&deploy_dir().join(format!("{stem}.toml")))
        .unwrap_or_else(|e| panic!("{stem}.toml: {e}"));
    press_scene(&scene);
}

macro_rules! press_tests {
    ($($test:ident => $how:ident($name:literal);)*) => {
        $(#[test]
        fn $test() {
            $how($name);
        })*
        /// The scenes this file presses, by built-in name or deploy file stem.
        const PRESSED: &[&str] = &[$($name),*];
    };
}

press_tests! {
    builtin_lv => press_builtin("lv");
    builtin_ellipsoids => press_builtin("ellipsoids");
    builtin_hemisphere_springs => press_builtin("hemisphere-springs");
    builtin_lv_surface_springs => press_builtin("lv-surface-springs");
    builtin_lv_hybrid => press_builtin("lv-hybrid");
    builtin_ellipsoids_hybrid => press_builtin("ellipsoids-hybrid");
    file_lv_h1 => press_file("lv_h1");
    file_lv_h1_condensed => press_file("lv_h1_condensed");
    file_lv_h1_es => press_file("lv_h1_es");
    file_lv_h2 => press_file("lv_h2");
    file_lv_h3 => press_file("lv_h3");
    file_lv_h3_v41 => press_file("lv_h3_v41");
    file_lv_100k_condensed => press_file("lv_100k_condensed");
    file_lv_h2_inflation => press_file("lv_h2_inflation");
}

#[test]
fn static_benchmarks_are_refused_by_the_haptic_loop() {
    for (stem, realtime) in DEPLOY_FILES {
        if *realtime {
            continue;
        }
        let scene = load_scene_file(&deploy_dir().join(format!("{stem}.toml")))
            .unwrap_or_else(|e| panic!("{stem}.toml: {e}"));
        assert!(!scene.realtime, "{stem}");
        match build_body(&scene) {
            Err(ModelError::SceneField { field, message }) => {
                assert_eq!(field, "model.realtime", "{stem}: {message}");
                assert!(message.contains("haptic-solve"), "{stem}: {message}");
            }
            Err(e) => panic!("{stem}: expected the model.realtime refusal, got {e}"),
            Ok(_) => panic!("{stem}: a static benchmark was built for the haptic loop"),
        }
    }
}

#[test]
fn every_shipped_scene_is_pressed_here() {
    for (name, _) in builtin_scene_names() {
        assert!(PRESSED.contains(name), "built-in {name} is not pressed");
    }
    let mut files: Vec<String> = std::fs::read_dir(deploy_dir())
        .unwrap()
        .filter_map(|e| {
            let p = e.unwrap().path();
            (p.extension()? == "toml").then(|| p.file_stem()?.to_str().map(str::to_string))?
        })
        .collect();
    files.sort();
    for stem in files {
        let builtin = builtin_scene_names().iter().any(|(n, _)| *n == stem);
        let listed = DEPLOY_FILES.iter().find(|(s, _)| *s == stem);
        match listed {
            _ if builtin => {}
            Some((_, true)) => assert!(PRESSED.contains(&stem.as_str()), "{stem} not pressed"),
            Some((_, false)) => {}
            None => {
                panic!("deploy/scenes/{stem}.toml is shipped but neither pressed nor refused here")
            }
        }
    }
}
