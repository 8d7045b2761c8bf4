//! Part runners for the element kernel's forces in parts ([`PartRunner`]) without the tick
//! pool: serial parts and a two-thread stand-in, shared by `tests/parallel_forces.rs` and
//! `examples/threads_bench.rs` (included with `#[path]`).

use haptic_model::element::{ForcePart, PartRunner};

/// The parts one after the other on the calling thread: `.0` parts of the cut.
pub struct Serial(pub usize);

impl PartRunner for Serial {
    fn threads(&self) -> usize {
        self.0
    }

    fn run_parts(&self, parts: &mut [ForcePart], f: &(dyn Fn(usize, &mut ForcePart) + Sync)) {
        for (p, part) in parts.iter_mut().enumerate() {
            f(p, part);
        }
    }
}

/// A stand-in for a two-thread pool: part 0 on the caller, the others on a scoped thread
/// spawned per call (so a measurement with it includes a thread's spawn).
pub struct Scoped;

impl PartRunner for Scoped {
    fn threads(&self) -> usize {
        2
    }

    fn run_parts(&self, parts: &mut [ForcePart], f: &(dyn Fn(usize, &mut ForcePart) + Sync)) {
        let (first, rest) = parts.split_at_mut(1);
        std::thread::scope(|s| {
            let worker = s.spawn(|| {
                for (p, part) in rest.iter_mut().enumerate() {
                    f(p + 1, part);
                }
            });
            f(0, &mut first[0]);
            worker.join().expect("the worker part");
        });
    }
}
