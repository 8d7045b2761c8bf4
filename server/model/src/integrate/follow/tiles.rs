//! The region cache of a following region ([`TileMode::Background`]; issue 48 s2): regions
//! ("tiles") prepared ahead at fixed centres covering the touchable surface, so that a request
//! is a lookup and a copy instead of a condensation.
//!
//! Owns: the tile centres (greedy farthest-point covering), the cache and its choice rule.
//! May use: [`super::super::condensed`].
//!
//! [`TileMode::Background`]: super::super::condensed::TileMode::Background

use std::sync::Arc;

use glam::DVec3;

use super::super::condensed::CondensedSolver;

/// A request moves to another tile only when that tile's centre is this much nearer the
/// device than the current one's (or the current one no longer covers the device), m.
pub const TILE_HYSTERESIS_M: f64 = 5e-4;

/// Centres covering `nodes` (indices into `rest`, m) within `cover_m`: greedy farthest-point
/// covering (Gonzalez, Theor. Comput. Sci. 38 (1985) 293) starting at `start_m` (the scene's
/// region centre), then adding the node farthest from every centre so far (ties: the lowest
/// index in `nodes`) until every node lies within `cover_m` of a centre. Deterministic; each
/// centre but the first is a node's rest position. Stops as well when every node is a centre
/// (a `cover_m` that is not positive). Costs `|nodes|` distances per centre.
pub fn tile_centres(rest: &[DVec3], nodes: &[u32], start_m: DVec3, cover_m: f64) -> Vec<DVec3> {
    let points: Vec<DVec3> = nodes
        .iter()
        .filter_map(|&i| rest.get(i as usize).copied())
        .collect();
    let mut nearest: Vec<f64> = points.iter().map(|p| p.distance(start_m)).collect();
    let mut centres = vec![start_m];
    loop {
        let (far, d) =
            nearest.iter().enumerate().fold(
                (usize::MAX, 0.0),
                |(k, d), (j, &e)| {
                    if e > d { (j, e) } else { (k, d) }
                },
            );
        if far == usize::MAX || d <= cover_m {
            return centres;
        }
        let c = points[far];
        centres.push(c);
        for (e, p) in nearest.iter_mut().zip(&points) {
            *e = e.min(p.distance(c));
        }
    }
}

/// One tile of the cache.
pub(super) enum Tile {
    /// Not prepared yet.
    Missing,
    /// Prepared, trimmed ([`CondensedSolver::trim_for_tiles`]) and never stepped.
    Built(Arc<CondensedSolver>),
    /// Its preparation failed (not tried again).
    Failed,
    /// Its file in the region cache holds it; not in memory (a fill-only worker's,
    /// [`super::RegionFollower::spawn_with_cache`]). A request reads it.
    OnDisk,
    /// Built or read, then dropped from memory to keep the cache under its memory limit
    /// ([`super::RegionCacheDir::memory_bytes`]); its file holds it. Read back when a request
    /// asks for it, or while idle once it is nearer the probe than a tile in memory.
    Dropped,
}

/// The worker's cache: the centres and their tiles.
pub(super) struct TileCache {
    pub(super) centres: Vec<DVec3>,
    pub(super) tiles: Vec<Tile>,
    /// Per tile: its file in the region cache holds it (read from it or written to it), so
    /// it may be dropped from memory.
    pub(super) stored: Vec<bool>,
    cover_m: f64,
}

impl TileCache {
    pub(super) fn new(centres: Vec<DVec3>, cover_m: f64) -> Self {
        let tiles = centres.iter().map(|_| Tile::Missing).collect();
        let stored = vec![false; centres.len()];
        Self {
            centres,
            tiles,
            stored,
            cover_m,
        }
    }

    /// The tile in memory farthest from `p` other than `except`, among those with a file
    /// (`with_file`) or those without, and its distance, m (ties: the lowest index).
    pub(super) fn farthest_in_memory(
        &self,
        p: DVec3,
        except: usize,
        with_file: bool,
    ) -> Option<(usize, f64)> {
        self.tiles
            .iter()
            .enumerate()
            .filter(|&(k, t)| {
                k != except && self.stored[k] == with_file && matches!(t, Tile::Built(_))
            })
            .map(|(k, _)| (k, self.centres[k].distance(p)))
            .fold(None, |a: Option<(usize, f64)>, b| match a {
                Some(a) if a.1 >= b.1 => Some(a),
                _ => Some(b),
            })
    }

    /// The dropped tile nearest `p` and its distance, m (ties: the lowest index).
    pub(super) fn nearest_dropped(&self, p: DVec3) -> Option<(usize, f64)> {
        self.tiles
            .iter()
            .enumerate()
            .filter(|(_, t)| matches!(t, Tile::Dropped))
            .map(|(k, _)| (k, self.centres[k].distance(p)))
            .fold(None, |a: Option<(usize, f64)>, b| match a {
                Some(a) if a.1 <= b.1 => Some(a),
                _ => Some(b),
            })
    }

    /// Mean bytes of the tiles in memory ([`CondensedSolver::heap_bytes`]), or `None`.
    pub(super) fn mean_built_bytes(&self) -> Option<u64> {
        let (n, sum) = self
            .tiles
            .iter()
            .filter_map(|t| match t {
                Tile::Built(s) => Some(s.heap_bytes() as u64),
                _ => None,
            })
            .fold((0u64, 0u64), |(n, sum), b| (n + 1, sum + b));
        (n > 0).then(|| sum / n)
    }

    /// The centre nearest `p` and its distance, m (ties: the lowest index).
    fn nearest(&self, p: DVec3) -> (usize, f64) {
        self.centres
            .iter()
            .enumerate()
            .map(|(k, c)| (k, c.distance(p)))
            .fold((0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a })
    }

    /// The tile a request for `point_m` gets while the region in use is centred at
    /// `current_m`: `None` to stay (the current region is a tile that still covers the point
    /// and no other centre is [`TILE_HYSTERESIS_M`] nearer), else the nearest centre.
    pub(super) fn choose(&self, point_m: DVec3, current_m: DVec3) -> Option<usize> {
        let (best, d_best) = self.nearest(point_m);
        let current = self.centres.iter().position(|&c| c == current_m);
        if let Some(cur) = current {
            let d_cur = point_m.distance(current_m);
            if cur == best || (d_cur <= self.cover_m && d_cur < d_best + TILE_HYSTERESIS_M) {
                return None;
            }
        }
        Some(best)
    }

    /// The missing tile whose centre is nearest `p`, if any.
    pub(super) fn next_missing(&self, p: DVec3) -> Option<usize> {
        self.centres
            .iter()
            .zip(&self.tiles)
            .enumerate()
            .filter(|(_, (_, t))| matches!(t, Tile::Missing))
            .map(|(k, (c, _))| (k, c.distance(p)))
            .fold(None, |a: Option<(usize, f64)>, b| match a {
                Some(a) if a.1 <= b.1 => Some(a),
                _ => Some(b),
            })
            .map(|(k, _)| k)
    }
}
