//! The model's integration tests, one module per file of this folder, in one test binary
//! (`docs/decisions.md`, "The integration tests in a few binaries": each binary compiles at
//! opt-level 3 and links the whole dependency graph on its own). Run one file's tests with
//! `cargo test -p haptic-model --test model <file>::`. The tests that count allocations are in
//! `model_alloc.rs` (their counting allocator is that binary's global allocator).

mod common;

mod cantilever_elastica;
mod contact;
mod fem_contracts;
mod fuzz_inputs;
mod guccione;
mod hertz;
mod hybrid_contact;
mod hybrid_feel;
mod incompressible;
mod lame_convergence;
mod lame_sphere;
mod loads;
mod lv_probe_reference;
mod macneal_harder_patch;
mod mass_spring_force;
mod mass_spring_hemisphere_organ;
mod mass_spring_scenes;
mod material_models;
mod mesh_gmsh;
mod mesh_mesher;
mod meshfree;
mod module_layers;
mod ordering_threads;
mod quadratic_tets;
mod readme_tables;
mod scene_parse;
mod scene_runs;
mod shipped_scenes_press;
mod sim_lv;
mod stability;
mod strain_smoothing;
mod uniaxial_compression;

/// Every file of this folder is a module of one of the binaries or a binary's root: with
/// `autotests = false` an undeclared file would never run.
#[test]
fn every_test_file_is_declared() {
    const ROOTS: [&str; 2] = ["model.rs", "model_alloc.rs"];
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
            "tests/{name} is declared in none of {ROOTS:?}"
        );
    }
}
