//! The server's integration tests, one module per file of this folder, in one test binary
//! (`docs/decisions.md`, "The integration tests in a few binaries"). Run one file's tests with
//! `cargo test -p haptic-server --test server <file>::`. In their own binaries: the tests that
//! count allocations (`server_alloc.rs`) and `overrun.rs` (it measures loop rates against a
//! session alone, so it runs beside no other test file).

mod common;

mod builds;
mod cli_help;
mod config;
mod confine;
mod cores;
mod device_capabilities;
mod follow_session;
mod hybrid_session;
mod link_limits;
mod metrics;
mod servo_loop;
mod solve;
mod streams;
mod tools;

/// Every file of this folder is a module of one of the binaries or a binary's root: with
/// `autotests = false` an undeclared file would never run.
#[test]
fn every_test_file_is_declared() {
    const ROOTS: [&str; 3] = ["server.rs", "server_alloc.rs", "overrun.rs"];
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests");
    let roots = ROOTS.map(|r| std::fs::read_to_string(dir.join(r)).expect("a root file"));
    for entry in std::fs::read_dir(&dir).expect("the tests folder") {
        let name = entry.expect("an entry").file_name();
        let name = name.to_str().expect("a UTF-8 name");
        let Some(module) = name.strip_suffix(".rs") else {
            continue;
        };
        let declaration = format!("\nmod {module};\n");
        assert!(
            ROOTS.contains(&name) || roots.iter().any(|r| r.contains(&declaration)),
            "tests/{name} is declared in none of {ROOTS:?} (overrun.rs is its own [[test]])"
        );
    }
}
