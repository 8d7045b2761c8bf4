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
