//! The crate's top-level modules form layers: each one imports only modules of lower layers
//! (lib.rs documents the order). A module that imports one that imports it back (a cycle) is
//! how a codebase stops being extensible, so this test reads every source file, collects its
//! `crate::<module>` paths (comments and doc links ignored) and checks every edge against the
//! order. The real-time path (`fem`, `integrate`, `contact`, `loads`, `element`) must not use
//! the static solver.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Top-level modules, lowest layer first. `error` (the crate's one error type) may be used by
/// every module and uses none.
const LAYERS: &[&str] = &[
    "error",
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

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("read src") {
        let path = entry.expect("dir entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The code of a Rust file without comments (line comments, doc comments, block comments);
/// string contents are kept, which is harmless here.
fn strip_comments(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut depth = 0;
    for line in text.lines() {
        let mut rest = line;
        loop {
            if depth > 0 {
                match rest.find("*/") {
                    Some(i) => {
                        depth -= 1;
                        rest = &rest[i + 2..];
                    }
                    None => break,
                }
            } else {
                let line_comment = rest.find("//");
                let block = rest.find("/*");
                match (line_comment, block) {
                    (Some(l), Some(b)) if b < l => {
                        out.push_str(&rest[..b]);
                        depth += 1;
                        rest = &rest[b + 2..];
                    }
                    (None, Some(b)) => {
                        out.push_str(&rest[..b]);
                        depth += 1;
                        rest = &rest[b + 2..];
                    }
                    (Some(l), _) => {
                        out.push_str(&rest[..l]);
                        break;
                    }
                    (None, None) => {
                        out.push_str(rest);
                        break;
                    }
                }
            }
        }
        out.push('\n');
    }
    out
}

/// `(from, to)` for every `crate::to` path in the code of top-level module `from`.
fn edges() -> BTreeSet<(String, String)> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut edges = BTreeSet::new();
    for file in files {
        let rel = file.strip_prefix(&src).expect("under src");
        let first = rel.components().next().expect("component");
        let module = first
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if module == "lib" {
            continue; // the crate root declares and assembles the modules
        }
        let code = strip_comments(&std::fs::read_to_string(&file).expect("read file"));
        for (i, _) in code.match_indices("crate::") {
            let before = code[..i].chars().last();
            if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
                continue; // e.g. `haptic_model_crate::`
            }
            let after = &code[i + "crate::".len()..];
            assert!(
                !after.starts_with('{'),
                "{}: write one `use crate::module::...` per module (grouped `crate::{{..}}` imports \
                 hide edges from this check)",
                rel.display()
            );
            let target: String = after
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if !target.is_empty()
                && target != module
                && target.chars().next().is_some_and(|c| c.is_lowercase())
            {
                edges.insert((module.clone(), target));
            }
        }
    }
    edges
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
    let code =
        strip_comments("use crate::a; // crate::b\n/* crate::c */ let x = 1; /// crate::d\n");
    assert!(code.contains("crate::a") && code.contains("let x = 1;"));
    assert!(!code.contains("crate::b") && !code.contains("crate::c") && !code.contains("crate::d"));
}
