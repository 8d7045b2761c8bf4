//! The sweep cut at a fork of the elimination tree (issue 48): [`TreeSplit`] and how it is
//! found ([`tree_split`]), for [`super::SupernodalSolve::solve_in_place_in`] on two threads.

/// The supernodes cut into two groups of whole subtrees, `a = 0..b_start` and
/// `b = b_start..top_start`, below their common ancestors `top_start..` (issue 48): the rows
/// of a supernode of `a` lie in the columns of `a` or of the top only, so the two groups'
/// sweeps touch disjoint parts of the right-hand side except the top's rows, which the second
/// group's forward sweep adds into its own copy.
#[derive(Debug, Clone)]
pub(super) struct TreeSplit {
    pub(super) b_start: usize,
    pub(super) top_start: usize,
    /// First column of `b` and of the top.
    pub(super) col_b: usize,
    pub(super) col_top: usize,
    /// The second group's right-hand side (its columns and the top's rows) and column block.
    pub(super) xb: Vec<f32>,
    pub(super) yb: Vec<f32>,
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
    let ns = nodes.len();
    let cols = nodes.last().map(|n| (n[0] + n[1]) as usize)?;
    let mut node_of_col = vec![0_usize; cols];
    for (k, n) in nodes.iter().enumerate() {
        node_of_col[n[0] as usize..(n[0] + n[1]) as usize].fill(k);
    }
    let pattern = |k: usize| &rows[nodes[k][2] as usize..][..nodes[k][3] as usize];
    let values = |k: usize| {
        let end = nodes.get(k + 1).map_or(len_val, |n| n[4] as usize);
        end - nodes[k][4] as usize
    };
    let mut children = vec![Vec::new(); ns];
    let mut roots = Vec::new();
    let mut subtree: Vec<usize> = (0..ns).map(values).collect();
    for k in 0..ns {
        match pattern(k).iter().min() {
            Some(&r) if node_of_col[r as usize] > k => {
                let p = node_of_col[r as usize];
                children[p].push(k);
                subtree[p] += subtree[k];
            }
            Some(_) => return None,
            None => roots.push(k),
        }
    }
    let mut fork = *roots.iter().max_by_key(|&&k| subtree[k])?;
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
        prefix[k + 1] = prefix[k] + values(k);
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
    let a_stays = (0..b_start).all(|k| pattern(k).iter().all(|&r| r < col_b || r >= col_top));
    let top_stays = (fork..ns).all(|k| pattern(k).iter().all(|&r| r >= col_top));
    (a_stays && top_stays).then_some((b_start, fork))
}
