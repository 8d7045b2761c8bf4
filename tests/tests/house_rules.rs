//! Rules of the house that ARCHITECTURE.md states and this test keeps true, reading the
//! sources as text (`haptic_e2e::source_scan`; no binary is built or run):
//!
//! - every file that uses `unsafe` is in ARCHITECTURE's `unsafe` list (by its path or a folder
//!   above it), and every entry of that list still holds some `unsafe`;
//! - no crate's top-level modules import each other in a cycle (the model's stricter layer
//!   order is `server/model/tests/module_layers.rs`);
//! - ARCHITECTURE.md stays a map of at most 150 lines;
//! - no function outside the tests (libraries, binaries, examples, benchmarks) is longer than [`MAX_FUNCTION_LINES`] (issue 49: a function
//!   that long is cut at its stages into named functions).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use haptic_e2e::source_scan::{
    code_before_test_module, crate_edges, function_spans, rust_files, strip_comments_and_strings,
    uses_unsafe,
};

/// The repository's root (this crate is `tests/`).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the workspace root")
        .to_path_buf()
}

/// The workspace members' folders that hold Rust sources (the model is below `server/`).
const MEMBERS: &[&str] = &[
    "proto",
    "cli",
    "server",
    "client-viewer",
    "device-bridge",
    "tests",
];

/// The library source folders whose top-level modules must not form a cycle.
const LIBRARIES: &[&str] = &[
    "proto/src",
    "cli/src",
    "server/src",
    "server/model/src",
    "client-viewer/src",
    "device-bridge/src",
    "tests/src",
];

fn architecture() -> String {
    let path = root().join("ARCHITECTURE.md");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The backticked paths of ARCHITECTURE's `unsafe` bullet (files end in `.rs`, folders in `/`).
fn listed_unsafe_paths(architecture: &str) -> Vec<String> {
    let mut lines = architecture
        .lines()
        .skip_while(|l| !l.starts_with("- **`unsafe`**"));
    let first = lines
        .next()
        .expect("ARCHITECTURE.md has a bullet starting with - **`unsafe`**");
    let bullet: Vec<&str> = std::iter::once(first)
        .chain(lines.take_while(|l| l.starts_with("  ")))
        .collect();
    bullet
        .join(" ")
        .split('`')
        .skip(1)
        .step_by(2)
        .filter(|p| p.contains('/') && (p.ends_with(".rs") || p.ends_with('/')))
        .map(str::to_string)
        .collect()
}

/// Every Rust file of the workspace that uses `unsafe`, as a path relative to the root.
fn files_with_unsafe() -> Vec<String> {
    let root = root();
    let mut out = Vec::new();
    for member in MEMBERS {
        for file in rust_files(&root.join(member)) {
            let rel = file.strip_prefix(&root).expect("under the root");
            if rel.components().any(|c| c.as_os_str() == "target") {
                continue;
            }
            let text = std::fs::read_to_string(&file).expect("read a source file");
            if uses_unsafe(&strip_comments_and_strings(&text)) {
                out.push(rel.to_string_lossy().replace('\\', "/"));
            }
        }
    }
    out
}

#[test]
fn every_file_with_unsafe_is_listed_and_every_entry_has_unsafe() {
    let listed = listed_unsafe_paths(&architecture());
    let found = files_with_unsafe();
    assert!(
        found.len() >= 5,
        "the scan found too few files with unsafe to be real: {found:?}"
    );
    let covered = |file: &str, entry: &str| {
        if entry.ends_with('/') {
            file.starts_with(entry)
        } else {
            file == entry
        }
    };
    let unlisted: Vec<&String> = found
        .iter()
        .filter(|f| !listed.iter().any(|e| covered(f, e)))
        .collect();
    assert!(
        unlisted.is_empty(),
        "files using `unsafe` that ARCHITECTURE.md's `unsafe` bullet does not list (add the \
         file or its folder, with the reason): {unlisted:?}"
    );
    let stale: Vec<&String> = listed
        .iter()
        .filter(|e| !found.iter().any(|f| covered(f, e)))
        .collect();
    assert!(
        stale.is_empty(),
        "ARCHITECTURE.md's `unsafe` bullet lists paths with no `unsafe` (moved or cleaned up: \
         update the list): {stale:?}"
    );
}

/// A cycle through `from` in `edges`, if any: the modules on it in order.
fn cycle_from(from: &str, edges: &BTreeMap<String, Vec<String>>) -> Option<Vec<String>> {
    let mut stack = vec![(from.to_string(), vec![from.to_string()])];
    let mut seen = BTreeSet::new();
    while let Some((node, path)) = stack.pop() {
        for next in edges.get(&node).into_iter().flatten() {
            if next == from {
                return Some(path.iter().cloned().chain([from.to_string()]).collect());
            }
            if seen.insert(next.clone()) {
                let mut longer = path.clone();
                longer.push(next.clone());
                stack.push((next.clone(), longer));
            }
        }
    }
    None
}

#[test]
fn no_module_imports_one_that_imports_it_back() {
    let root = root();
    let mut cycles = Vec::new();
    let mut total = 0;
    for library in LIBRARIES {
        let mut edges: BTreeMap<String, Vec<String>> = BTreeMap::new();
        for (from, to) in crate_edges(&root.join(library)) {
            total += 1;
            edges.entry(from).or_default().push(to);
        }
        for module in edges.keys() {
            if let Some(cycle) = cycle_from(module, &edges) {
                cycles.push(format!("{library}: {}", cycle.join(" -> ")));
                break; // one cycle per crate is enough to name it
            }
        }
    }
    assert!(
        total > 50,
        "the scan found too few imports ({total}) to be real"
    );
    assert!(
        cycles.is_empty(),
        "top-level modules that import each other (move the shared part to a module both \
         import): {cycles:?}"
    );
}

#[test]
fn architecture_is_a_map_of_at_most_150_lines() {
    let lines = architecture().lines().count();
    assert!(
        lines <= 150,
        "ARCHITECTURE.md has {lines} lines: it is a map (data path, one paragraph per folder, \
         rules); measurements and history belong in docs/"
    );
}

#[test]
fn the_unsafe_list_is_read_from_the_bullet_only() {
    let text = "intro `a/b.rs`\n- **`unsafe`** in `x/y.rs` and `x/z/`\n  also `p/q.rs`, not `word`\n- next `m/n.rs`\n";
    assert_eq!(listed_unsafe_paths(text), ["x/y.rs", "x/z/", "p/q.rs"]);
}

/// The measurement programs (examples and benchmarks), held to the same function length as
/// the libraries and binaries.
const PROGRAMS: &[&str] = &[
    "server/model/examples",
    "server/model/benches",
    "server/examples",
    "server/benches",
    "client-viewer/examples",
    "device-bridge/examples",
    "tests/benches",
];

/// The longest a function outside the tests may be, in lines from its `fn` keyword to its
/// closing brace.
const MAX_FUNCTION_LINES: usize = 100;

#[test]
fn no_function_outside_the_tests_is_longer_than_the_limit() {
    let root = root();
    let mut long = Vec::new();
    let mut functions = 0;
    for src in LIBRARIES.iter().chain(PROGRAMS) {
        for file in rust_files(&root.join(src)) {
            let text = std::fs::read_to_string(&file).expect("read a source file");
            let spans = function_spans(&code_before_test_module(&text));
            functions += spans.len();
            for span in spans.into_iter().filter(|s| s.lines > MAX_FUNCTION_LINES) {
                let rel = file.strip_prefix(&root).expect("under the root");
                long.push(format!(
                    "{}:{} {} ({} lines)",
                    rel.display(),
                    span.line,
                    span.name,
                    span.lines
                ));
            }
        }
    }
    assert!(
        functions > 1000,
        "the scan found too few functions ({functions}) to be real"
    );
    assert!(
        long.is_empty(),
        "functions longer than {MAX_FUNCTION_LINES} lines: cut them at their stages into \
         named functions:\n{}",
        long.join("\n")
    );
}

/// The test folders whose crates set `autotests = false`, with their binaries' root files:
/// every file there must be a root or declared (`mod FILE;`) in one, or it would never run.
const TEST_ROOTS: &[(&str, &[&str])] = &[
    ("server/model/tests", &["model.rs", "model_alloc.rs"]),
    (
        "server/tests",
        &["server.rs", "server_alloc.rs", "overrun.rs"],
    ),
    ("tests/tests", &["e2e.rs"]),
];

#[test]
fn every_integration_test_file_is_declared_in_a_binary() {
    for (folder, roots) in TEST_ROOTS {
        let dir = root().join(folder);
        let texts: Vec<String> = roots
            .iter()
            .map(|r| std::fs::read_to_string(dir.join(r)).expect("a root file"))
            .collect();
        for entry in std::fs::read_dir(&dir).expect("the tests folder") {
            let name = entry.expect("an entry").file_name();
            let name = name.to_str().expect("a UTF-8 name").to_string();
            let Some(module) = name.strip_suffix(".rs") else {
                continue;
            };
            let declaration = format!("\nmod {module};\n");
            assert!(
                roots.contains(&name.as_str()) || texts.iter().any(|t| t.contains(&declaration)),
                "{folder}/{name} is declared in none of {roots:?}"
            );
        }
    }
}
