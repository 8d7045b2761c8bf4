//! How the force kernels cut one force evaluation into parts (issue 48 sections 1 and 3).
//!
//! Single precision, tetrahedra: the lanes of every batch in halves ([`Split::Lanes`]): lane l
//! of a batch comes from run l of the Morton curve (`super::locality_order` interleaves sixteen
//! runs), so lanes 0-7 are the first half of the curve and the halves are spatially compact
//! (contiguous batch ranges are not: each batch spans the whole body). Single precision,
//! smoothing domains (batched by node count, not by place): contiguous batch ranges of about
//! equal node slots ([`Split::Batches`]). Double precision, both layouts: the two halves of the
//! Morton curve batched apart (`super::Kernels::add_forces_parts`), cut with [`cut`] (lane
//! halves would run four-lane registers in double precision).
//!
//! Per part: the nodes it touches, as runs of consecutive node indices (single precision packs
//! them with the vectorised code of `super::single`). A node touched by one part only is
//! *owned* by it: that part adds its sum to the double-precision forces. The few nodes touched
//! by several parts (the cut) are *shared*: one thread adds their sums in part order after
//! every part is done. So the arithmetic depends only on the number of parts, never on which
//! thread ran which part; one part is the one-core path (every touched node owned, one batch
//! range).

use std::ops::Range;

/// The largest number of parts a force evaluation is cut into (the cuts of 1 to this many
/// parts are made with the kernel's batches).
pub const MAX_FORCE_PARTS: usize = 2;

/// How a layout is cut into parts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Split {
    /// Every batch, lanes `p * L / k .. (p + 1) * L / k` of the `L` lanes to part `p` (`k` must
    /// divide `L` into halves of the eight-lane build: one or two parts).
    Lanes,
    /// Batch ranges of about equal work, every lane.
    Batches,
}

/// One part of a cut: its batches and lanes and the nodes they touch, all indices ascending.
#[derive(Debug, Clone)]
pub(super) struct PartPlan {
    /// The batches this part runs.
    pub(super) batches: Range<usize>,
    /// The lanes of each batch this part runs (all of them, or one half).
    pub(super) lanes: Range<usize>,
    /// Runs of node indices the part's batches touch (padding lanes included): the part
    /// packs their displacements and velocities.
    pub(super) touched: Vec<Range<usize>>,
    /// Runs of the touched nodes no other part touches: the part adds their sums to the
    /// double-precision forces and clears them. Disjoint between the parts of a cut.
    pub(super) own: Vec<Range<usize>>,
}

/// The cut of one evaluation into `parts.len()` parts.
#[derive(Debug, Clone)]
pub(super) struct Cut {
    /// The parts, in order.
    pub(super) parts: Vec<PartPlan>,
    /// Nodes touched by more than one part, ascending: summed after the parts, in part order.
    pub(super) shared: Vec<u32>,
}

impl super::Kernels {
    /// Bytes of the batches and of the two-part evaluation's.
    pub(crate) fn heap_bytes(&self) -> usize {
        use super::{Batches, Layout};
        use crate::linalg::vec_bytes as b;
        let layout = match &self.layout {
            Layout::Linear(batches) => b(batches),
            Layout::Quadratic { batches, order } => b(batches) + b(order),
            Layout::Domains(d) => d.heap_bytes(),
        };
        let two = self.two.as_ref().map_or(0, |t| {
            t.cut.heap_bytes()
                + match &t.batches {
                    Batches::Tets(batches) => b(batches),
                    Batches::Domains(d) => d.heap_bytes(),
                }
        });
        layout + two
    }
}

impl Cut {
    /// Bytes of the arrays.
    pub(super) fn heap_bytes(&self) -> usize {
        use crate::linalg::vec_bytes as b;
        b(&self.parts)
            + b(&self.shared)
            + self
                .parts
                .iter()
                .map(|p| b(&p.touched) + b(&p.own))
                .sum::<usize>()
    }
}

/// The cuts into `1..=MAX_FORCE_PARTS` parts (`cuts[k - 1]` has `k` parts) of `work.len()`
/// batches of `lanes` lanes over `node_count` nodes: batch `b` costs `work[b]` (any unit) and
/// its lanes `l` touch the nodes `nodes(b, l)` yields (each below `node_count`, repeats
/// allowed).
pub(super) fn cuts<I: Iterator<Item = usize>>(
    node_count: usize,
    (work, lanes, split): (&[usize], usize, Split),
    nodes: impl Fn(usize, Range<usize>) -> I,
) -> Vec<Cut> {
    (1..=MAX_FORCE_PARTS)
        .map(|k| {
            let parts: Vec<(Range<usize>, Range<usize>)> = match split {
                Split::Lanes => (0..k)
                    .map(|p| (0..work.len(), p * lanes / k..(p + 1) * lanes / k))
                    .collect(),
                Split::Batches => batch_ranges(work, k)
                    .into_iter()
                    .map(|r| (r, 0..lanes))
                    .collect(),
            };
            cut(node_count, parts, &nodes)
        })
        .collect()
}

/// The double-precision forces the parts write to, each only at the nodes it owns
/// ([`PartPlan::own`], disjoint between the parts of a cut).
pub(super) struct OwnedForces {
    pub(super) ptr: *mut glam::DVec3,
    pub(super) len: usize,
}

// SAFETY: the parts write through the pointer only at the nodes they own, which are disjoint
// ([`cut`]), and only while the `&mut` slice it was made from is not otherwise used.
unsafe impl Sync for OwnedForces {}

/// No part touches the node yet.
const NONE: u32 = u32::MAX;
/// More than one part touches the node.
const SHARED: u32 = u32::MAX - 1;

/// The cut into the parts `parts` (batches, lanes) (see [`cuts`]).
pub(super) fn cut<I: Iterator<Item = usize>>(
    node_count: usize,
    parts: Vec<(Range<usize>, Range<usize>)>,
    nodes: &impl Fn(usize, Range<usize>) -> I,
) -> Cut {
    let mut owner = vec![NONE; node_count];
    let mut touched = Vec::with_capacity(parts.len());
    for (p, (r, lanes)) in parts.iter().enumerate() {
        let mut mine = vec![false; node_count];
        for b in r.clone() {
            for i in nodes(b, lanes.clone()) {
                mine[i] = true;
            }
        }
        for (o, _) in owner.iter_mut().zip(&mine).filter(|(_, m)| **m) {
            *o = match *o {
                NONE => p as u32,
                q if q == p as u32 => q,
                _ => SHARED,
            };
        }
        touched.push(mine);
    }
    let parts = parts
        .into_iter()
        .zip(&touched)
        .enumerate()
        .map(|(p, ((batches, lanes), mine))| PartPlan {
            batches,
            lanes,
            touched: runs(mine.iter().copied()),
            own: runs(mine.iter().zip(&owner).map(|(m, &o)| *m && o == p as u32)),
        })
        .collect();
    let shared = (0..node_count as u32)
        .filter(|&i| owner[i as usize] == SHARED)
        .collect();
    Cut { parts, shared }
}

/// `k` consecutive ranges covering the batches, the cumulative work of part `p` ending at the
/// first batch where it reaches `(p + 1) / k` of the total.
fn batch_ranges(work: &[usize], k: usize) -> Vec<Range<usize>> {
    let total: usize = work.iter().sum();
    let mut ends = Vec::with_capacity(k);
    let (mut done, mut b) = (0usize, 0usize);
    for p in 1..=k {
        let goal = total * p / k;
        while b < work.len() && (done < goal || p == k) {
            done += work[b];
            b += 1;
        }
        ends.push(b);
    }
    let mut start = 0;
    ends.into_iter()
        .map(|end| {
            let r = start..end;
            start = end;
            r
        })
        .collect()
}

/// The runs of consecutive indices where `flags` is true.
fn runs(flags: impl Iterator<Item = bool>) -> Vec<Range<usize>> {
    let mut out: Vec<Range<usize>> = Vec::new();
    for (i, on) in flags.enumerate() {
        match out.last_mut() {
            Some(r) if on && r.end == i => r.end = i + 1,
            _ if on => out.push(i..i + 1),
            _ => {}
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chain of batches, batch `b` touching nodes `b` and `b + 1`, with a padding repeat:
    /// every node touched once or twice; the cuts own, share and cover exactly that.
    #[test]
    fn a_cut_owns_every_touched_node_once_and_shares_the_seams() {
        let work = [1, 1, 1, 1, 1, 1, 1];
        let all = cuts(10, (&work, 2, Split::Batches), |b, _| {
            [b, b + 1, b].into_iter()
        });
        let one = &all[0];
        assert_eq!(one.parts.len(), 1);
        assert_eq!(one.parts[0].batches, 0..7);
        assert_eq!(one.parts[0].touched, vec![0..8]);
        assert_eq!(one.parts[0].own, vec![0..8]);
        assert!(one.shared.is_empty());
        let two = &all[1];
        assert_eq!(two.parts[0].batches, 0..3);
        assert_eq!(two.parts[1].batches, 3..7);
        assert_eq!(two.parts[0].touched, vec![0..4]);
        assert_eq!(two.parts[0].own, vec![0..3]);
        assert_eq!(two.parts[1].touched, vec![3..8]);
        assert_eq!(two.parts[1].own, vec![4..8]);
        assert_eq!(two.shared, vec![3]);
        for (k, c) in all.iter().enumerate() {
            assert_eq!(c.parts.len(), k + 1);
            let covered: usize = c.parts.iter().map(|p| p.batches.len()).sum();
            assert_eq!(covered, work.len(), "{k}");
            let owned: usize = c.parts.iter().flat_map(|p| &p.own).map(|r| r.len()).sum();
            assert_eq!(owned + c.shared.len(), 8, "{k}");
        }
    }

    /// Two lanes: lane 0 of batch `b` touches node `b`, lane 1 node `b + 4` and node 3: halves
    /// by lane share node 3 only.
    #[test]
    fn a_lane_cut_takes_every_batch_and_half_the_lanes() {
        let work = [1, 1, 1];
        let nodes = |b: usize, l: Range<usize>| l.flat_map(move |l| [[b, 3], [b + 4, 3]][l]);
        let two = &cuts(8, (&work, 2, Split::Lanes), nodes)[1];
        assert_eq!(
            (two.parts[0].batches.clone(), two.parts[0].lanes.clone()),
            (0..3, 0..1)
        );
        assert_eq!(
            (two.parts[1].batches.clone(), two.parts[1].lanes.clone()),
            (0..3, 1..2)
        );
        assert_eq!(two.parts[0].touched, vec![0..4]);
        assert_eq!(two.parts[0].own, vec![0..3]);
        assert_eq!(two.parts[1].touched, vec![3..7]);
        assert_eq!(two.parts[1].own, vec![4..7]);
        assert_eq!(two.shared, vec![3]);
    }

    #[test]
    fn batch_ranges_balance_the_work() {
        assert_eq!(batch_ranges(&[4, 1, 1, 1, 1], 2), vec![0..1, 1..5]);
        assert_eq!(batch_ranges(&[1, 1, 1, 1], 3), vec![0..1, 1..2, 2..4]);
        assert_eq!(batch_ranges(&[], 2), vec![0..0, 0..0]);
        assert_eq!(
            runs([false, true, true, false, true].into_iter()),
            [1..3, 4..5]
        );
    }
}
