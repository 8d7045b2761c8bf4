//! A global allocator that counts allocations (and reallocations): the "no allocation in the
//! tick" tests of the model and of the server, and the bytes they hold. Three modes:
//!
//! - [`counted`]: what the calling thread allocates while `f` runs;
//! - [`counted_registered`]: what every *registered* thread allocates while `f` runs: the calling
//!   thread, and every thread that called [`count_this_thread`] (a tick pool's workers call it from
//!   their start hook), so work moved to pool threads cannot escape the count while the test
//!   harness's other threads are never counted;
//! - [`net_bytes`]: the bytes the calling thread allocates and keeps while `f` runs.
//!
//! A test file includes it with `#[path = "common/counting_alloc.rs"] mod counting_alloc;` (from
//! `server/tests`: `"../model/tests/common/counting_alloc.rs"`); it installs the allocator of
//! that test binary.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard};

struct Counting;
thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
    static REGISTERED: Cell<bool> = const { Cell::new(false) };
    static COUNTING_BYTES: Cell<bool> = const { Cell::new(false) };
    static NET_BYTES: Cell<isize> = const { Cell::new(0) };
}
/// Counting of the registered threads is on.
static REGISTERED_ON: AtomicBool = AtomicBool::new(false);
/// Allocations by registered threads while [`REGISTERED_ON`].
static REGISTERED_ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

/// Counts one allocation of this thread in the modes that are on.
fn note_allocation() {
    // `try_with`: a thread being torn down has no thread-locals left and is not counted.
    if COUNTING.try_with(|c| c.get()).unwrap_or(false) {
        let _ = ALLOCATIONS.try_with(|a| a.set(a.get() + 1));
    }
    if REGISTERED_ON.load(Ordering::Relaxed) && REGISTERED.try_with(|r| r.get()).unwrap_or(false) {
        REGISTERED_ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
    }
}

/// Adds `bytes` to this thread's net bytes while [`net_bytes`] counts them.
fn note_bytes(bytes: isize) {
    if COUNTING_BYTES.try_with(|c| c.get()).unwrap_or(false) {
        let _ = NET_BYTES.try_with(|n| n.set(n.get() + bytes));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note_allocation();
        note_bytes(layout.size() as isize);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        note_bytes(-(layout.size() as isize));
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note_allocation();
        note_bytes(new_size as isize - layout.size() as isize);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Runs `f` and returns its result with the number of allocations this thread made during it.
pub fn counted<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let before = ALLOCATIONS.with(|a| a.get());
    COUNTING.with(|c| c.set(true));
    let out = f();
    COUNTING.with(|c| c.set(false));
    (out, ALLOCATIONS.with(|a| a.get()) - before)
}

/// Runs `f` and returns its result with the bytes this thread allocated during it less those
/// it freed: what `f`'s result holds on the heap when `f` allocates on this thread only.
#[allow(dead_code)]
pub fn net_bytes<T>(f: impl FnOnce() -> T) -> (T, isize) {
    let before = NET_BYTES.with(|n| n.get());
    COUNTING_BYTES.with(|c| c.set(true));
    let out = f();
    COUNTING_BYTES.with(|c| c.set(false));
    (out, NET_BYTES.with(|n| n.get()) - before)
}

/// Registers the calling thread for [`counted_registered`] (for the rest of its life).
#[allow(dead_code)]
pub fn count_this_thread() {
    REGISTERED.with(|r| r.set(true));
}

/// Runs `f` on this thread (registered by the call) and returns its result with the number of
/// allocations every registered thread made meanwhile. Runs of it must not overlap, and no other
/// test's registered thread may allocate during one: every test that registers threads (or
/// calls this) holds [`one_at_a_time`] for its whole body.
#[allow(dead_code)]
pub fn counted_registered<T>(f: impl FnOnce() -> T) -> (T, usize) {
    count_this_thread();
    let before = REGISTERED_ALLOCATIONS.load(Ordering::SeqCst);
    REGISTERED_ON.store(true, Ordering::SeqCst);
    let out = f();
    REGISTERED_ON.store(false, Ordering::SeqCst);
    (out, REGISTERED_ALLOCATIONS.load(Ordering::SeqCst) - before)
}

/// The tests that register threads (a pool whose start hook calls [`count_this_thread`]) or call
/// [`counted_registered`] run one at a time: each holds this guard for its whole body, so no
/// other test's registered thread allocates inside its count (the binary's other tests run
/// beside it: [`counted`] counts only its own thread).
#[allow(dead_code)]
pub fn one_at_a_time() -> MutexGuard<'static, ()> {
    static REGISTERED_TESTS: Mutex<()> = Mutex::new(());
    REGISTERED_TESTS.lock().unwrap_or_else(|e| e.into_inner())
}
