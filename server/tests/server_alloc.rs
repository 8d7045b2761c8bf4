//! The server's "no allocation in the tick" tests, in one test binary whose global allocator
//! counts allocations (the model's `tests/common/counting_alloc.rs`, declared once here; each
//! file uses `crate::counting_alloc`; the test that counts registered pool workers holds
//! `counting_alloc::one_at_a_time()`). Run one file's tests with
//! `cargo test -p haptic-server --test server_alloc <file>::`.

#[path = "../model/tests/common/counting_alloc.rs"]
mod counting_alloc;

mod mass_spring_session;
mod servo_no_alloc;
mod topology;
