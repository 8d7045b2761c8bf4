//! The sweep cut at a fork of the elimination tree (issue 48): [`TreeSplit`] and how it is
//! found ([`tree_split`], [`phases`]), for [`super::SupernodalSolve::solve_in_place_in`] on
//! two threads.

use std::ops::Range;

/// The supernodes cut into two groups of whole subtrees, `a = 0..b_start` and
/// `b = b_start..top_start`, below their common ancestors `top_start..` (issue 48): the rows
/// of a supernode of `a` lie in the columns of `a` or of the top only, so the two groups'
/// sweeps touch disjoint parts of the right-hand side except the top's rows, which the second
/// group's forward sweep adds into its own copy.
#[derive(Debug, Clone)]
pub(super) struct TreeSplit {
    pub(super) top_start: usize,
    /// First column of the top.
    pub(super) col_top: usize,
    /// The second group's right-hand side (its columns and the top's rows) and column block.
    pub(super) xb: Vec<f32>,
    pub(super) yb: Vec<f32>,
    /// Who sweeps what ([`Phases`]; [`Phases::plain`] for the cut alone).
    pub(super) phases: Phases,
}

/// The cut of [`TreeSplit`] for supernodes `nodes` (parents after their children, as faer
/// stores them in postorder) with pattern `rows` and `len_val` factor values:
/// `(b_start, top_start)`, or `None` when no fork balances (each side at least a quarter of
/// the values, the rest at most a third) or the check below fails. The parent of a supernode
/// is the one holding its smallest pattern row. From the heaviest root (clamped equations
/// are roots of their own) down through every child holding more than two thirds of its
/// parent's subtree to the first balanced fork; its child subtrees are cut where the two
/// sides' values balance best, everything before them joins the first side, the fork and
/// everything after it is the top. Checked directly, so the sweeps may rely on it: every
/// pattern row of a supernode before `b_start` lies before the second side's first column
/// or in the top's columns, and every top supernode's rows lie in the top's columns.
pub(super) fn tree_split(
    nodes: &[[u32; 5]],
    rows: &[u32],
    len_val: usize,
) -> Option<(usize, usize)> {
    let tree = Tree::new(nodes, rows, len_val)?;
    let Tree {
        children, subtree, ..
    } = &tree;
    let roots = (0..nodes.len()).filter(|&k| tree.parent[k] == usize::MAX);
    let mut fork = roots.max_by_key(|&k| subtree[k])?;
    let heaviest = |k: usize| children[k].iter().copied().max_by_key(|&c| subtree[c]);
    while let Some(c) = heaviest(fork).filter(|&c| 3 * subtree[c] > 2 * subtree[fork]) {
        fork = c;
    }
    let kids = &children[fork];
    if kids.len() < 2 {
        return None;
    }
    let mut prefix = vec![0_usize; fork + 1];
    for k in 0..fork {
        prefix[k + 1] = prefix[k] + tree.values(k);
    }
    let below = prefix[fork];
    let b_start = kids[..kids.len() - 1]
        .iter()
        .map(|&c| c + 1)
        .min_by_key(|&j| prefix[j].abs_diff(below - prefix[j]))?;
    let (a, b, top) = (prefix[b_start], below - prefix[b_start], len_val - below);
    if 4 * a.min(b) < len_val || 3 * top > len_val {
        return None;
    }
    let (col_b, col_top) = (nodes[b_start][0], nodes[fork][0]);
    let pattern = |k: usize| tree.pattern(k);
    let a_stays = (0..b_start).all(|k| pattern(k).iter().all(|&r| r < col_b || r >= col_top));
    let top_stays = (fork..nodes.len()).all(|k| pattern(k).iter().all(|&r| r >= col_top));
    (a_stays && top_stays).then_some((b_start, fork))
}

/// The elimination tree of supernodes `nodes` (postorder) with pattern `rows`: the parent of
/// a supernode is the one holding its smallest pattern row (`usize::MAX` for a root).
struct Tree<'a> {
    nodes: &'a [[u32; 5]],
    rows: &'a [u32],
    len_val: usize,
    node_of_col: Vec<usize>,
    parent: Vec<usize>,
    children: Vec<Vec<usize>>,
    /// Values and supernodes of each subtree.
    subtree: Vec<usize>,
    count: Vec<usize>,
}

impl<'a> Tree<'a> {
    /// `None` when a supernode's rows reach back to an earlier one (not a postorder).
    fn new(nodes: &'a [[u32; 5]], rows: &'a [u32], len_val: usize) -> Option<Self> {
        let ns = nodes.len();
        let cols = nodes.last().map(|n| (n[0] + n[1]) as usize)?;
        let mut tree = Tree {
            nodes,
            rows,
            len_val,
            node_of_col: vec![0_usize; cols],
            parent: vec![usize::MAX; ns],
            children: vec![Vec::new(); ns],
            subtree: Vec::new(),
            count: vec![1; ns],
        };
        for (k, n) in nodes.iter().enumerate() {
            tree.node_of_col[n[0] as usize..(n[0] + n[1]) as usize].fill(k);
        }
        tree.subtree = (0..ns).map(|k| tree.values(k)).collect();
        for k in 0..ns {
            let Some(&r) = tree.pattern(k).iter().min() else {
                continue;
            };
            let p = tree.node_of_col[r as usize];
            if p <= k {
                return None;
            }
            tree.parent[k] = p;
            tree.children[p].push(k);
            tree.subtree[p] += tree.subtree[k];
            tree.count[p] += tree.count[k];
        }
        Some(tree)
    }

    fn pattern(&self, k: usize) -> &'a [u32] {
        &self.rows[self.nodes[k][2] as usize..][..self.nodes[k][3] as usize]
    }

    /// Factor values of supernode `k`.
    fn values(&self, k: usize) -> usize {
        let end = self
            .nodes
            .get(k + 1)
            .map_or(self.len_val, |n| n[4] as usize);
        end - self.nodes[k][4] as usize
    }

    /// The supernodes of `group` above the `roots` (ascending).
    fn above(&self, roots: &[usize], group: &Range<usize>) -> Vec<usize> {
        let mut w: Vec<usize> = Vec::new();
        for &s in roots {
            let mut p = self.parent[s];
            while group.contains(&p) && !w.contains(&p) {
                w.push(p);
                p = self.parent[p];
            }
        }
        w.sort_unstable();
        w
    }
}

/// The cut's two phases (issue 48), when they balance the two threads better than the cut
/// alone: the first thread sweeps the lighter group but the top of its heaviest subtree
/// (`held`, kept for a second phase) and up to two subtrees of the heavier group (`stolen`);
/// the second thread the heavier group but `stolen` and the supernodes above them
/// (`waiting`), which wait for them, in the second phase beside `held`.
/// Forward: phase one (the first group without `held`, and `stolen` | the second group
/// without `stolen` and `waiting`), then `stolen`'s sums into `waiting`'s columns are handed
/// to the second group's copy, then phase two (`held` | `waiting`); backward the other way
/// round. Node and column ranges ascending.
#[derive(Debug, Clone, Default)]
pub(super) struct Phases {
    /// Phase one's supernode ranges on the first (calling) thread and on the second.
    pub(super) one: [Vec<Range<usize>>; 2],
    /// Phase two's.
    pub(super) two: [Vec<Range<usize>>; 2],
    /// Columns of `waiting`, of the group the second thread sweeps (`lent`) and of that group
    /// without `stolen`.
    pub(super) waiting_cols: Vec<Range<usize>>,
    pub(super) lent_cols: Range<usize>,
    pub(super) second_cols: Vec<Range<usize>>,
}

impl Phases {
    /// The cut alone: the first group `0..b_start` | the second `b_start..top_start` (columns
    /// `col_b..col_top`), no second phase.
    // One range each, not the range's elements.
    #[allow(clippy::single_range_in_vec_init)]
    pub(super) fn plain(b_start: usize, top_start: usize, col_b: usize, col_top: usize) -> Self {
        Self {
            one: [vec![0..b_start], vec![b_start..top_start]],
            two: [Vec::new(), Vec::new()],
            waiting_cols: Vec::new(),
            lent_cols: col_b..col_top,
            second_cols: vec![col_b..col_top],
        }
    }
}

/// Who sweeps a supernode in [`Phases`].
#[derive(Clone, Copy, PartialEq, Eq)]
enum Part {
    First,
    Held,
    Stolen,
    Second,
    Waiting,
    Top,
}

/// The [`Phases`] of the cut `(b_start, top_start)` of [`tree_split`], or `None` when none
/// saves at least 2 % of the factor's values on the longer thread or the check fails. Cost of
/// a supernode: its values. Searched: `stolen` one or two disjoint subtrees of the second
/// group holding 1-20 % of the values each, `held` the heaviest-child chain (0-8 supernodes)
/// from the root of the first group's heaviest subtree. Checked directly, so the sweeps may
/// rely on it: every pattern row of a supernode lies in the columns its phase allows
/// (`held`: itself or the top; `stolen`: itself, `waiting` or the top; ...).
pub(super) fn phases(
    nodes: &[[u32; 5]],
    rows: &[u32],
    len_val: usize,
    b_start: usize,
    top_start: usize,
) -> Option<Phases> {
    let tree = Tree::new(nodes, rows, len_val)?;
    let a_total = (0..b_start).map(|k| tree.values(k)).sum::<usize>();
    let b_total = (b_start..top_start).map(|k| tree.values(k)).sum::<usize>();
    // The lighter group `x` on the first thread; the heavier `y` lends it subtrees.
    let (x, y) = match a_total <= b_total {
        true => (0..b_start, b_start..top_start),
        false => (b_start..top_start, 0..b_start),
    };
    let (wall, stolen, held) =
        best_loan(&tree, &x, &y, a_total.min(b_total), a_total.max(b_total))?;
    if 50 * (a_total.max(b_total) - wall) < len_val {
        return None;
    }
    let waiting = tree.above(&stolen, &y);
    let mut part = vec![Part::Top; nodes.len()];
    part[x.clone()].fill(Part::First);
    part[y.clone()].fill(Part::Second);
    for &k in &held {
        part[k] = Part::Held;
    }
    for &s in &stolen {
        part[s + 1 - tree.count[s]..=s].fill(Part::Stolen);
    }
    for &k in &waiting {
        part[k] = Part::Waiting;
    }
    let allowed = |p: Part, q: Part| {
        q == Part::Top
            || q == p
            || matches!(
                (p, q),
                (Part::First, Part::Held) | (Part::Stolen | Part::Second, Part::Waiting)
            )
    };
    let checked = (0..nodes.len()).all(|k| {
        let owner = |r: &u32| part[tree.node_of_col[*r as usize]];
        tree.pattern(k).iter().all(|r| allowed(part[k], owner(r)))
    });
    if !checked {
        return None;
    }
    let node_ranges = |want: &[Part]| runs(&part, |p| want.contains(&p));
    let col_ranges = |want: &[Part]| {
        let first = |k: usize| nodes[k][0] as usize;
        let run = |r: Range<usize>| first(r.start)..first(r.end - 1) + nodes[r.end - 1][1] as usize;
        node_ranges(want).into_iter().map(run).collect::<Vec<_>>()
    };
    Some(Phases {
        one: [
            node_ranges(&[Part::First, Part::Stolen]),
            node_ranges(&[Part::Second]),
        ],
        two: [node_ranges(&[Part::Held]), node_ranges(&[Part::Waiting])],
        waiting_cols: col_ranges(&[Part::Waiting]),
        lent_cols: nodes[y.start][0] as usize..nodes[y.end][0] as usize,
        second_cols: col_ranges(&[Part::Second, Part::Waiting]),
    })
}

/// The best loan for [`phases`]: `(wall, stolen, held)`, the longer thread's values over
/// both phases, the roots of the stolen subtrees and the held supernodes, for the lighter
/// group `x` (`x_total` values) and the heavier `y`; `wall` is `y_total` when nothing helps.
fn best_loan(
    tree: &Tree<'_>,
    x: &Range<usize>,
    y: &Range<usize>,
    x_total: usize,
    y_total: usize,
) -> Option<(usize, Vec<usize>, Vec<usize>)> {
    let (parent, subtree, count) = (&tree.parent, &tree.subtree, &tree.count);
    let x_root = x
        .clone()
        .filter(|&k| !x.contains(&parent[k]))
        .max_by_key(|&k| subtree[k])?;
    let mut chain = vec![x_root];
    while chain.len() < 8 {
        let kids = &tree.children[chain[chain.len() - 1]];
        match kids.iter().copied().max_by_key(|&c| subtree[c]) {
            Some(c) => chain.push(c),
            None => break,
        }
    }
    let len_val = tree.len_val;
    let candidates: Vec<usize> = y
        .clone()
        .filter(|&k| y.contains(&parent[k]))
        .filter(|&k| 100 * subtree[k] >= len_val && 5 * subtree[k] <= len_val)
        .collect();
    let disjoint = |s: usize, t: usize| s + count[t] <= t || t + count[s] <= s;
    let mut best = (y_total, Vec::new(), 0);
    for (i, &s) in candidates.iter().enumerate() {
        let pairs = candidates[i + 1..].iter().filter(|&&t| disjoint(s, t));
        for stolen in std::iter::once(vec![s]).chain(pairs.map(|&t| vec![s, t])) {
            let stolen_cost: usize = stolen.iter().map(|&k| subtree[k]).sum();
            let waiting = tree.above(&stolen, y);
            let waiting_cost: usize = waiting.iter().map(|&k| tree.values(k)).sum();
            let mut held_cost = 0;
            for held in 0..=chain.len() {
                if held > 0 {
                    held_cost += tree.values(chain[held - 1]);
                }
                let one =
                    (x_total - held_cost + stolen_cost).max(y_total - stolen_cost - waiting_cost);
                let wall = one + held_cost.max(waiting_cost);
                if wall < best.0 {
                    best = (wall, stolen.clone(), held);
                }
            }
        }
    }
    let (wall, stolen, held) = best;
    Some((wall, stolen, chain[..held].to_vec()))
}

/// The maximal runs of indices of `part` whose part `keep` accepts.
fn runs(part: &[Part], keep: impl Fn(Part) -> bool) -> Vec<Range<usize>> {
    let mut out: Vec<Range<usize>> = Vec::new();
    for (k, &p) in part.iter().enumerate() {
        if !keep(p) {
            continue;
        }
        match out.last_mut() {
            Some(r) if r.end == k => r.end = k + 1,
            _ => out.push(k..k + 1),
        }
    }
    out
}
