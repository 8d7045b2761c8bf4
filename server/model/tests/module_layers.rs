//! The crate's top-level modules form layers: each one imports only modules of lower layers
//! (lib.rs documents the order). A module that imports one that imports it back (a cycle) is
//! how a codebase stops being extensible, so this test reads every source file, collects its
//! `crate::<module>` paths (comments and doc links ignored) and checks every edge against the
//! order. The real-time path (`fem`, `integrate`, `contact`, `loads`, `element`) must not use
//! the static solver.

use std::collections::BTreeSet;
use std::path::Path;

/// Top-level modules, lowest layer first. `error` (the crate's one error type) may be used by
/// every module and uses none.
const LAYERS: &[&str] = &[
    "error",
    "check",
    "pool",
    "simd",
    "linalg",
    "mesh",
    "material",
    "meshfree",
    "element",
    "contact",
    "integrate",
    "loads",
    "body",
    "mass_spring",
    "hybrid",
    "scene",
    "fem",
    "statics",
    "indent",
    "press",
];

/// Modules on the servo's path, which must not import the static solver.
const REAL_TIME: &[&str] = &[
    "element",
    "contact",
    "integrate",
    "loads",
    "body",
    "mass_spring",
    "hybrid",
    "fem",
];

/// The source scanner the house tests share (`tests/src/source_scan.rs`: comments and strings
/// stripped, grouped imports read, test modules left out).
#[allow(dead_code)]
#[path = "../../../tests/src/source_scan.rs"]
mod source_scan;

/// `(from, to)` for every `crate::to` path in the code of top-level module `from`.
fn edges() -> BTreeSet<(String, String)> {
    source_scan::crate_edges(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"))
}

#[test]
fn every_import_goes_to_a_lower_layer() {
    let edges = edges();
    assert!(
        edges.len() > 20,
        "the scan found too few imports to be real: {edges:?}"
    );
    let rank = |m: &str| {
        LAYERS
            .iter()
            .position(|l| *l == m)
            .unwrap_or_else(|| panic!("module `{m}` is not in LAYERS: add it at its layer"))
    };
    let upward: Vec<String> = edges
        .iter()
        .filter(|(from, to)| rank(from) <= rank(to))
        .map(|(from, to)| format!("{from} -> {to}"))
        .collect();
    assert!(
        upward.is_empty(),
        "imports against the layer order (a cycle in the making): {upward:?}"
    );
}

#[test]
fn the_real_time_path_does_not_use_the_static_solvers() {
    let bad: Vec<String> = edges()
        .into_iter()
        .filter(|(from, to)| {
            REAL_TIME.contains(&from.as_str()) && (to == "statics" || to == "indent")
        })
        .map(|(from, to)| format!("{from} -> {to}"))
        .collect();
    assert!(bad.is_empty(), "{bad:?}");
}

#[test]
fn the_comment_stripper_keeps_code_and_drops_comments() {
    let code = source_scan::strip_comments_and_strings(
        "use crate::a; // crate::b\n/* crate::c */ let x = 1; /// crate::d\n",
    );
    assert!(code.contains("crate::a") && code.contains("let x = 1;"));
    assert!(!code.contains("crate::b") && !code.contains("crate::c") && !code.contains("crate::d"));
}

#[test]
fn architecture_lists_the_layers_in_this_order() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../ARCHITECTURE.md");
    let text = std::fs::read_to_string(&path).expect("ARCHITECTURE.md");
    let start = text
        .find("**Layers in the model, no import cycles.**")
        .expect("ARCHITECTURE.md has the layers bullet");
    let bullet = &text[start..];
    let bullet = &bullet[..bullet.find("\n- ").unwrap_or(bullet.len())];
    let chain: Vec<String> = bullet
        .split("**")
        .nth(2)
        .and_then(|rest| rest.split(';').next())
        .expect("a chain `a <- b <- ...;`")
        .split("<-")
        .map(|m| m.split_whitespace().collect::<String>())
        .collect();
    let on_top = &LAYERS[chain.len()..];
    assert_eq!(
        chain,
        LAYERS[..chain.len()],
        "ARCHITECTURE.md's layer chain differs from LAYERS"
    );
    for m in on_top {
        assert!(
            bullet.contains(m),
            "ARCHITECTURE.md's layers bullet does not name `{m}` (on top of the chain)"
        );
    }
}
