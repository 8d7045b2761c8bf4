//! The model's "no allocation in the tick" tests and the files that share them, in one test
//! binary whose global allocator counts allocations (`common/counting_alloc.rs`, declared once
//! here; each file uses `crate::counting_alloc`). `counted` counts the calling thread only, so
//! the tests running beside it cannot disturb it; the tests that count registered threads
//! (`counted_registered`, pool workers) take `counting_alloc::one_at_a_time()` for their whole
//! body. Run one file's tests with `cargo test -p haptic-model --test model_alloc <file>::`.

mod common;
#[path = "common/counting_alloc.rs"]
mod counting_alloc;
#[path = "common/tool_press.rs"]
mod tool_press;

mod companion_threads;
mod condensed;
mod hybrid;
mod hybrid_step;
mod hybrid_threads;
mod implicit;
mod mass_spring;
mod mass_spring_organ;
mod parallel_forces;
mod pool;
mod tools;
mod tools_mass_spring;
