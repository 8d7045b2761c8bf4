//! METIS keeps its random-number state in C globals (GKlib's `random.c`): two orderings made at
//! once on two threads used to draw from one interleaved stream, so a body built while another
//! was being built (two sessions created at once, two test threads) could get another ordering,
//! another factor and forces that differ in the last digits, which a press amplifies (a
//! 1.2e-5 difference at first contact on `lv-hybrid`, session 11). `nested_dissection`
//! serialises its METIS calls; this test orders one graph on several threads at once and
//! requires the ordering of a lone call every time.

use haptic_model::linalg::ordering::nested_dissection;

/// The 7-point pattern (both triangles, with the diagonal) of an `m x m x m` grid, three
/// equations per node (grouped by node), in compressed columns.
fn grid_pattern(m: usize) -> (usize, Vec<usize>, Vec<usize>, Vec<usize>) {
    let nodes = m * m * m;
    let n = 3 * nodes;
    let (mut col_ptr, mut row_idx) = (vec![0usize], Vec::new());
    for a in 0..nodes {
        let (i, j, k) = (a / (m * m), (a / m) % m, a % m);
        let mut nbrs = vec![a];
        for (d, c) in [(0, i), (1, j), (2, k)] {
            let step = [m * m, m, 1][d];
            if c > 0 {
                nbrs.push(a - step);
            }
            if c + 1 < m {
                nbrs.push(a + step);
            }
        }
        nbrs.sort_unstable();
        for _ in 0..3 {
            for &b in &nbrs {
                row_idx.extend((0..3).map(|c| 3 * b + c));
            }
            col_ptr.push(row_idx.len());
        }
    }
    let group = (0..n).map(|e| e / 3).collect();
    (n, col_ptr, row_idx, group)
}

#[test]
fn orderings_made_on_several_threads_at_once_equal_a_lone_one() {
    let (n, col_ptr, row_idx, group) = grid_pattern(24);
    let lone = nested_dissection(n, &col_ptr, &row_idx, &group)
        .unwrap()
        .expect("a graph large enough for METIS");
    let differing = std::thread::scope(|s| {
        let workers: Vec<_> = (0..4)
            .map(|_| {
                s.spawn(|| {
                    (0..6)
                        .filter(|_| {
                            nested_dissection(n, &col_ptr, &row_idx, &group)
                                .unwrap()
                                .expect("ordered")
                                != lone
                        })
                        .count()
                })
            })
            .collect();
        workers
            .into_iter()
            .map(|w| w.join().unwrap())
            .sum::<usize>()
    });
    assert_eq!(
        differing, 0,
        "{differing} of 24 concurrent orderings differ from a lone one"
    );
}
