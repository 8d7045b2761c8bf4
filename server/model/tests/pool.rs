//! The threaded tick pool (`haptic_model::pool`, issue 48 section 1): every part runs exactly
//! once, `join` runs and returns both closures, the threaded results equal the serial pool's, a
//! worker that never starts leaves every job to the caller, panics do not wedge the pool, and
//! neither the caller nor the workers allocate. Each test well under a second (debug profile).

use crate::counting_alloc;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use haptic_model::pool::{StartHook, TickPool};

fn no_hook() -> StartHook {
    Arc::new(|_| {})
}

/// `counted_registered` runs must not overlap, and the other tests' workers must not allocate
/// inside one: every test takes this lock (the one of every such test of the binary).
fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    counting_alloc::one_at_a_time()
}

#[test]
fn every_part_runs_exactly_once_for_1_to_8_threads_and_0_to_1000_parts() {
    let _one = one_at_a_time();
    for threads in 1..=8 {
        let pool = TickPool::new(threads - 1, no_hook()).unwrap();
        assert_eq!(pool.threads(), threads);
        for n in [0, 1, 2, 3, 7, 8, 9, 64, 1000] {
            let mut runs: Vec<AtomicU32> = (0..n).map(|_| AtomicU32::new(0)).collect();
            for job in 0..20_u32 {
                pool.for_each_mut(&mut runs, &|p, r| {
                    // Each part sees its own index and increments only its own counter.
                    assert_eq!(r.load(Ordering::Relaxed), job, "part {p} of job {job}");
                    r.fetch_add(1, Ordering::Relaxed);
                });
            }
            assert!(
                runs.iter().all(|r| r.load(Ordering::Relaxed) == 20),
                "{threads} threads, {n} parts: a part ran other than once per job"
            );
        }
        let s = pool.stats();
        let parts = 20 * (1 + 2 + 3 + 7 + 8 + 9 + 64 + 1000);
        assert_eq!(s.parts_on_caller + s.parts_on_workers, parts);
        assert_eq!(s.jobs, 20 * 9);
        if threads == 1 {
            assert_eq!(s.parts_on_workers, 0);
        }
    }
}

#[test]
fn join_runs_both_and_returns_both() {
    let _one = one_at_a_time();
    for threads in 1..=4 {
        let pool = TickPool::new(threads - 1, no_hook()).unwrap();
        for k in 0..200_u64 {
            let (mut left, mut right) = (vec![0_u64; 50], vec![0_u64; 70]);
            let (a, b) = pool.join(
                || {
                    left.iter_mut()
                        .enumerate()
                        .for_each(|(i, x)| *x = i as u64 * k);
                    left.iter().sum::<u64>()
                },
                || {
                    right
                        .iter_mut()
                        .enumerate()
                        .for_each(|(i, x)| *x = i as u64 + k);
                    right.iter().sum::<u64>() + 1
                },
            );
            assert_eq!(a, k * 49 * 50 / 2);
            assert_eq!(b, 69 * 70 / 2 + 70 * k + 1);
            assert_eq!(left[49], 49 * k);
            assert_eq!(right[69], 69 + k);
        }
        let s = pool.stats();
        assert_eq!(s.parts_on_caller + s.parts_on_workers, 400);
    }
}

/// A job whose arithmetic is cut into parts: part `p` sums a fixed series over its own range.
fn partial_sums(pool: &TickPool, parts: usize) -> Vec<f64> {
    let mut sums = vec![0.0; parts];
    pool.for_each_mut(&mut sums, &|p, s| {
        let (lo, hi) = (p * 10_000 / parts, (p + 1) * 10_000 / parts);
        *s = (lo..hi)
            .map(|i| (i as f64 * 0.37).sin() / (1.0 + i as f64))
            .sum();
    });
    sums
}

#[test]
fn a_two_thread_pool_gives_the_serial_pools_results_bit_for_bit() {
    let _one = one_at_a_time();
    let serial = TickPool::serial();
    let two = TickPool::new(1, no_hook()).unwrap();
    for parts in [2, 3, 16] {
        for _ in 0..20 {
            let a = partial_sums(&serial, parts);
            let b = partial_sums(&two, parts);
            assert_eq!(
                a.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                b.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
            );
            let (j1, j2) = two.join(
                || partial_sums(&two, parts),
                || partial_sums(&serial, parts),
            );
            assert_eq!(j1, a);
            assert_eq!(j2, a);
        }
    }
}

#[test]
fn a_pool_whose_worker_is_held_completes_every_job_on_the_caller() {
    let _one = one_at_a_time();
    let release = Arc::new(AtomicBool::new(false));
    let hold = Arc::clone(&release);
    let hook: StartHook = Arc::new(move |_| {
        while !hold.load(Ordering::Acquire) {
            std::thread::yield_now();
        }
    });
    let pool = TickPool::new(1, hook).unwrap();
    for _ in 0..100 {
        let mut runs = vec![0_u32; 9];
        pool.for_each_mut(&mut runs, &|_, r| *r += 1);
        assert_eq!(runs, [1; 9]);
        assert_eq!(pool.join(|| 1, || 2), (1, 2));
    }
    let s = pool.stats();
    assert_eq!(s.parts_on_workers, 0, "the held worker ran something");
    assert_eq!(s.parts_on_caller, 100 * (9 + 2));
    release.store(true, Ordering::Release); // so that dropping the pool can join its worker
}

#[test]
fn a_panicking_part_or_task_panics_the_caller_and_leaves_the_pool_usable() {
    let _one = one_at_a_time();
    let pool = TickPool::new(1, no_hook()).unwrap();
    let mut items = vec![0_u32; 16];
    for _ in 0..20 {
        let out = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.for_each_mut(&mut items, &|p, _| assert!(p != 5, "part five"));
        }));
        assert!(
            out.is_err(),
            "a part panicked and the job returned normally"
        );
        let out = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.join(|| 1, || -> u32 { panic!("task") })
        }));
        assert!(out.is_err(), "the task panicked and join returned normally");
    }
    items.iter_mut().for_each(|x| *x = 0);
    pool.for_each_mut(&mut items, &|_, x| *x += 1);
    assert_eq!(items, [1; 16]);
    assert_eq!(pool.join(|| 3, || 4), (3, 4));
}

#[test]
fn neither_the_caller_nor_the_workers_allocate() {
    let _one = one_at_a_time();
    let hook: StartHook = Arc::new(|_| counting_alloc::count_this_thread());
    let pool = TickPool::new(3, hook).unwrap();
    let mut items = vec![0_u64; 64];
    pool.for_each_mut(&mut items, &|p, x| *x = p as u64); // the workers are running
    let ((), allocations) = counting_alloc::counted_registered(|| {
        for k in 0..500 {
            pool.for_each_mut(&mut items, &|p, x| {
                // About a microsecond a part, so that the workers take some.
                *x = (0..300_u64).fold(*x ^ (p as u64 * k), |s, i| s ^ (s << 1).wrapping_add(i));
            });
            let (a, b) = pool.join(
                || pool.for_each_mut(&mut items[..8], &|_, x| *x = x.wrapping_add(1)),
                || (0..100_u64).sum::<u64>(),
            );
            assert_eq!((a, b), ((), 4950));
        }
    });
    assert_eq!(allocations, 0, "the pool allocated in its jobs");
    let stats = crate::common::until_a_worker_ran(&pool, || {
        pool.for_each_mut(&mut items, &|p, x| {
            *x = (0..300_u64).fold(*x ^ p as u64, |s, i| s ^ (s << 1).wrapping_add(i));
        });
    });
    assert!(stats.parts_on_workers > 0, "no worker ran a part");
}
