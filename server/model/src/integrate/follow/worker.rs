//! The region worker's side of [`super::RegionFollower`]: it answers the servo's requests
//! (a tile, a region prepared on demand, or nothing to do) and, while it has none, builds,
//! reads back and drops tiles (module documentation of [`super`], "Tiles").

use std::cell::{Cell, RefCell};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use glam::DVec3;

use super::store::TileStore;
use super::tiles::{Tile, TileCache};
use super::{
    MERGE_RADII, Prepared, RECENTRE_RADII, RegionCacheReport, Request, Shared, TILE_HYSTERESIS_M,
};
use crate::element::FemModel;
use crate::integrate::condensed::{
    ActiveRegion, CondensedSolver, MAX_PREPARATION_THREADS, RegionBalls,
};
use crate::mesh::TetMesh;
/// The worker thread's state.
pub(super) struct Worker {
    /// The tiles ([`crate::integrate::condensed::TileMode::Background`]), or `None`.
    pub(super) cache: Option<TileCache>,
    /// Their files on disk ([`super::RegionFollower::spawn_with_cache`]), or `None`.
    pub(super) store: Option<TileStore>,
    /// Where the store's complaints go as they happen, or `None`.
    pub(super) report: Option<RegionCacheReport>,
    /// Fill the store only ([`super::RegionFollower::spawn_with_cache`]).
    pub(super) fill_only: bool,
    /// Bytes of tiles kept in memory at most ([`super::RegionCacheDir::memory_bytes`]; without a
    /// store [`super::DEFAULT_REGION_CACHE_MEMORY_BYTES`]).
    pub(super) memory_limit: u64,
    /// The store refused a tile (full, or a write failed): later tiles are not written
    /// either, so background builds stop at the memory limit ([`Self::build_next_tile`]).
    pub(super) store_full: Cell<bool>,
    /// The last requested point, m: background builds start nearest it.
    pub(super) last_point_m: Cell<DVec3>,
    pub(super) body: FemModel,
    pub(super) mesh: TetMesh,
    pub(super) nodes: Vec<u32>,
    pub(super) region: ActiveRegion,
    pub(super) dt_s: f64,
    /// The rings from and to the servo, behind cells: a request is also answered while a
    /// tile is being built ([`Self::answer_waiting`]).
    pub(super) requests: RefCell<rtrb::Consumer<Request>>,
    pub(super) results: RefCell<rtrb::Producer<Prepared>>,
    pub(super) returns: RefCell<rtrb::Consumer<Box<CondensedSolver>>>,
    /// Tiles read from disk for requests while a tile was being built
    /// ([`Self::read_while_building`]), kept ([`Self::keep`]) once the worker is free, and
    /// the tile whose read was tried during the build in progress (`usize::MAX`: none).
    pub(super) read_meanwhile: RefCell<Vec<(usize, Arc<CondensedSolver>)>>,
    pub(super) tried_meanwhile: Cell<usize>,
    pub(super) shared: Arc<Shared>,
}

impl Worker {
    pub(super) fn run(mut self) {
        loop {
            self.drop_returned();
            for (k, tile) in std::mem::take(self.read_meanwhile.get_mut()) {
                self.keep(k, Some(&tile), true);
            }
            if self.shared.stop.load(Ordering::Acquire) {
                return;
            }
            let request = self.requests.get_mut().pop();
            match request {
                Ok(request) => {
                    let answer = self.answer(request);
                    self.send(answer);
                }
                Err(_) => {
                    if let Some(p) = self.shared.focus_m.lock().ok().and_then(|mut f| f.take()) {
                        self.last_point_m.set(p);
                    }
                    if self.shared.paused.load(Ordering::Relaxed) || !self.build_next_tile() {
                        std::thread::park_timeout(Duration::from_millis(50));
                    }
                }
            }
        }
    }

    /// Frees the regions the servo gave back.
    fn drop_returned(&self) {
        if let Ok(mut returns) = self.returns.try_borrow_mut() {
            while let Ok(old) = returns.pop() {
                drop(old);
            }
        }
    }

    /// Sends `answer` to the servo, a region cut for its tick pool first.
    fn send(&self, mut answer: Prepared) {
        if let Prepared::Region { solver, .. } = &mut answer {
            let parts = self.shared.parts.load(Ordering::Relaxed);
            solver.set_parts(usize::try_from(parts).unwrap_or(1));
        }
        // The servo sends one request at a time and reads the answer before the next, so the
        // ring has room.
        if let Ok(mut results) = self.results.try_borrow_mut() {
            let _ = results.push(answer);
        }
    }

    /// Called while a tile is being built ([`Self::build_tile`]): answers the servo's waiting
    /// request when that needs no preparation ([`Self::ready_answer`]: nothing to do, or a
    /// copy of a tile in memory) or only a read ([`Self::read_while_building`]: its tile's
    /// file), so that the probe sliding onto a built tile does not wait for another tile's
    /// build (10-15 s on the 100 000-tet LV); else (its tile to be built, or a union) the
    /// request waits in its ring for the build to end. Frees the regions given back
    /// meanwhile.
    fn answer_waiting(&self) {
        self.drop_returned();
        let Ok(mut requests) = self.requests.try_borrow_mut() else {
            return;
        };
        let Ok(&request) = requests.peek() else {
            return;
        };
        let answer = match self.ready_answer(&request) {
            Ok(answer) => Some(answer),
            Err(Pending::Tile(k)) => self.read_while_building(k),
            Err(Pending::Union(_)) => None,
        };
        if let Some(answer) = answer {
            let _ = requests.pop();
            drop(requests);
            self.shared
                .answered_while_building
                .fetch_add(1, Ordering::Relaxed);
            self.send(answer);
        }
    }

    /// A request's tile `k`, not in memory, read from its file while another tile is being
    /// built (tried once per build: a missing file or a refused one waits for the build, then
    /// [`Self::miss`]); counted as [`Self::obtain`] counts a read, and kept later.
    fn read_while_building(&self, k: usize) -> Option<Prepared> {
        let cache = self.cache.as_ref()?;
        if self.tried_meanwhile.replace(k) == k {
            return None;
        }
        let start = Instant::now();
        let tile = self.load_tile(k, cache.centres[k])?;
        self.shared.tile_misses.fetch_add(1, Ordering::Relaxed);
        self.shared
            .read_while_building
            .fetch_add(1, Ordering::Relaxed);
        self.count_obtained(matches!(cache.tiles[k], Tile::Dropped), true, start);
        let answer = self.copy_of(&tile, cache.centres[k], start, false);
        self.read_meanwhile.borrow_mut().push((k, tile));
        Some(answer)
    }

    /// Threads of a preparation's column solves: the session's tick threads
    /// ([`super::RegionFollower::set_parts`]; at least 1, at most [`MAX_PREPARATION_THREADS`]), so
    /// a session prepares regions with the cores it was given. At normal priority they take
    /// what the real-time servo and its workers leave.
    fn threads(&self) -> usize {
        let parts = self.shared.parts.load(Ordering::Relaxed);
        usize::try_from(parts)
            .unwrap_or(1)
            .clamp(1, MAX_PREPARATION_THREADS)
    }

    /// The touchable node nearest `p`, and its distance, m.
    fn nearest(&self, p: DVec3) -> (DVec3, f64) {
        let rest = self.body.rest();
        self.nodes
            .iter()
            .map(|&i| rest[i as usize])
            .map(|q| (q, q.distance(p)))
            .fold((p, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a })
    }

    /// The balls for `points` (module documentation, "Several tools"), and the first point
    /// that got one (the one-ball request's point).
    fn balls_for(&self, points: &RegionBalls) -> (RegionBalls, DVec3) {
        let radius = self.region.radius_m;
        let mut balls = RegionBalls::EMPTY;
        let mut lead = DVec3::NAN;
        for &p in points.centres() {
            let (centre, d) = self.nearest(p);
            if d > radius || balls.distance(centre) <= MERGE_RADII * radius {
                continue;
            }
            if balls.centres().is_empty() {
                lead = p;
            }
            balls.push(centre);
        }
        (balls, lead)
    }

    /// The answer to `request`: one ball as before (a tile, or [`Self::prepare`]), several
    /// prepared on demand.
    fn answer(&mut self, request: Request) -> Prepared {
        match self.ready_answer(&request) {
            Ok(answer) => answer,
            Err(Pending::Tile(k)) => self.miss(k),
            Err(Pending::Union(balls)) => self.prepare(balls),
        }
    }

    /// The answer to `request` when it needs no preparation: nothing to do, or a copy of the
    /// tile in memory it chooses ([`Self::tile_ready`]); else what it needs.
    fn ready_answer(&self, request: &Request) -> Result<Prepared, Pending> {
        let (balls, point_m) = self.balls_for(&request.points_m);
        let current = request.current.centres();
        match balls.centres() {
            [] => {
                // The device above the surface, farther than a radius: the tiles follow the
                // surface point under it, ready when it comes down.
                if let (Some(_), Some(&p)) = (&self.cache, request.points_m.centres().first()) {
                    self.last_point_m.set(self.nearest(p).0);
                }
                Ok(Prepared::Nothing)
            }
            [_] if current.len() == 1 && self.cache.is_some() => {
                self.tile_ready(point_m, current[0])
            }
            // From a union back to one ball: the nearest tile, whatever the hysteresis.
            [_] if self.cache.is_some() => self.tile_ready(point_m, DVec3::NAN),
            _ => {
                // The region of `balls` unless it is `current` to [`RECENTRE_RADII`] radii
                // (same number of balls, each that near one of `current`).
                let radius = self.region.radius_m;
                let close = |c: &DVec3| {
                    current
                        .iter()
                        .any(|k| c.distance(*k) < RECENTRE_RADII * radius)
                };
                if balls.centres().len() == current.len() && balls.centres().iter().all(close) {
                    Ok(Prepared::Nothing)
                } else {
                    Err(Pending::Union(balls))
                }
            }
        }
    }

    /// The region of `balls`, prepared on demand.
    fn prepare(&self, balls: RegionBalls) -> Prepared {
        let start = Instant::now();
        match CondensedSolver::new_in_threads(
            &self.body,
            &self.mesh,
            self.region,
            balls,
            self.dt_s,
            self.threads(),
            &mut |_, _| {},
        ) {
            Ok(mut solver) => {
                solver.prepare_contact(&self.nodes);
                self.shared
                    .record_prepare_s(start.elapsed().as_secs_f64(), true);
                self.shared.prepared.fetch_add(1, Ordering::Relaxed);
                Prepared::Region {
                    solver: Box::new(solver),
                    balls,
                }
            }
            Err(_) => {
                self.shared.failed.fetch_add(1, Ordering::Relaxed);
                Prepared::Nothing
            }
        }
    }

    /// A region centred at `centre_m`, prepared as [`Self::prepare`] does and trimmed for the
    /// cache ([`CondensedSolver::trim_for_tiles`]); `None` when the preparation failed.
    ///
    /// The build runs on a thread of its own (`region-tile`; on this one if it cannot be
    /// started) while this one answers the servo's requests that need no preparation
    /// ([`Self::answer_waiting`]), so that a build of 10-15 s (the 100 000-tet LV) does not
    /// hold them up.
    fn build_tile(&self, centre_m: DVec3) -> Option<Arc<CondensedSolver>> {
        let region = ActiveRegion {
            centre_m,
            ..self.region
        };
        let (body, mesh, nodes) = (&self.body, &self.mesh, self.nodes.as_slice());
        let (dt_s, threads) = (self.dt_s, self.threads());
        let build = move || {
            let mut solver = CondensedSolver::new_in_threads(
                body,
                mesh,
                region,
                RegionBalls::one(centre_m),
                dt_s,
                threads,
                &mut |_, _| {},
            )
            .ok()?;
            solver.prepare_contact(nodes);
            solver.trim_for_tiles();
            Some(Arc::new(solver))
        };
        let me = std::thread::current();
        self.tried_meanwhile.set(usize::MAX);
        std::thread::scope(|scope| {
            let builder = std::thread::Builder::new()
                .name("region-tile".into())
                .spawn_scoped(scope, move || {
                    let built = build();
                    me.unpark();
                    built
                });
            let Ok(builder) = builder else {
                return build();
            };
            while !builder.is_finished() {
                self.answer_waiting();
                std::thread::park_timeout(Duration::from_millis(50));
            }
            builder.join().ok().flatten()
        })
    }

    /// Tile `k` from its file on disk, or `None` (no store, no file, or a file refused:
    /// counted, the reason kept).
    fn load_tile(&self, k: usize, centre_m: DVec3) -> Option<Arc<CondensedSolver>> {
        let store = self.store.as_ref()?;
        match store.load(k, &self.body, &self.mesh, self.region, centre_m, self.dt_s) {
            Ok(Some(t)) => {
                self.shared.tiles_loaded.fetch_add(1, Ordering::Relaxed);
                Some(Arc::new(t))
            }
            Ok(None) => None,
            Err(e) => {
                self.shared.tiles_refused.fetch_add(1, Ordering::Relaxed);
                self.cache_error(e);
                None
            }
        }
    }

    /// Writes the built tile `k` to its file on disk when there is a store.
    /// Whether it was written.
    fn store_tile(&self, k: usize, tile: &CondensedSolver) -> bool {
        let Some(store) = self.store.as_ref() else {
            return false;
        };
        match store.save(k, tile) {
            Ok(true) => {
                self.shared.tiles_stored.fetch_add(1, Ordering::Relaxed);
                return true;
            }
            Ok(false) => self.cache_error(format!(
                "{}: the region cache is full (its size limit); tile {k} kept in memory only",
                store.path(k).display()
            )),
            Err(e) => self.cache_error(e),
        }
        self.store_full.set(true);
        false
    }

    fn cache_error(&self, e: String) {
        if let Some(r) = &self.report {
            r.report(&e);
        }
        if let Ok(mut last) = self.shared.cache_error.lock() {
            *last = Some(e);
        }
    }

    /// Builds tile `k` (or reads it from disk) and keeps it; counts it (or the failure).
    fn build_and_keep(&mut self, k: usize) -> Option<Arc<CondensedSolver>> {
        let (tile, stored) = self.obtain(k, true);
        self.keep(k, tile.as_ref(), stored);
        tile
    }

    /// Tile `k` read from disk (when `read`) or built and written, and whether its file
    /// holds it (read or written); counts it (or the failure; a dropped tile read back as
    /// reloaded) and its time.
    fn obtain(&mut self, k: usize, read: bool) -> (Option<Arc<CondensedSolver>>, bool) {
        let Some(cache) = self.cache.as_ref() else {
            return (None, false);
        };
        let centre_m = cache.centres[k];
        let reload = matches!(cache.tiles[k], Tile::Dropped);
        let start = Instant::now();
        let loaded = if read {
            self.load_tile(k, centre_m)
        } else {
            None
        };
        let mut stored = loaded.is_some();
        let tile = loaded.or_else(|| {
            let built = self.build_tile(centre_m);
            if let Some(t) = &built {
                stored = self.store_tile(k, t);
            }
            built
        });
        self.count_obtained(reload, tile.is_some(), start);
        (tile, stored)
    }

    /// Counts a tile obtained since `start` (`got`: read or built; `reload`: a dropped one
    /// read back) or its failure, and its time.
    fn count_obtained(&self, reload: bool, got: bool, start: Instant) {
        let s = start.elapsed().as_secs_f64();
        let total = f64::from_bits(self.shared.tile_build_s.load(Ordering::Relaxed));
        self.shared
            .tile_build_s
            .store((total + s).to_bits(), Ordering::Relaxed);
        let counter = match (got, reload) {
            (true, true) => &self.shared.tiles_reloaded,
            (true, false) => &self.shared.tiles_built,
            (false, _) => {
                self.shared.failed.fetch_add(1, Ordering::Relaxed);
                &self.shared.tiles_failed
            }
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Keeps tile `k` in memory ([`Tile::Built`]; `stored`: its file holds it), or marks it
    /// [`Tile::Failed`]; then drops the tiles farthest from the last requested point while
    /// the cache is over its memory limit.
    fn keep(&mut self, k: usize, tile: Option<&Arc<CondensedSolver>>, stored: bool) {
        let Some(cache) = self.cache.as_mut() else {
            return;
        };
        cache.stored[k] |= stored;
        cache.tiles[k] = match tile {
            Some(t) => {
                self.shared
                    .tile_cache_bytes
                    .fetch_add(t.heap_bytes() as u64, Ordering::Relaxed);
                Tile::Built(Arc::clone(t))
            }
            None => Tile::Failed,
        };
        let p = self.last_point_m.get();
        while self.shared.tile_cache_bytes.load(Ordering::Relaxed) > self.memory_limit {
            // Those with a file first (read back in a fraction of a second), then the others
            // (prepared again if the probe comes back).
            let Some((j, _)) = cache
                .farthest_in_memory(p, k, true)
                .or_else(|| cache.farthest_in_memory(p, k, false))
            else {
                return;
            };
            let to = if cache.stored[j] {
                Tile::Dropped
            } else {
                Tile::Missing
            };
            if let Tile::Built(t) = std::mem::replace(&mut cache.tiles[j], to) {
                self.shared
                    .tile_cache_bytes
                    .fetch_sub(t.heap_bytes() as u64, Ordering::Relaxed);
                self.shared.tiles_dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Builds the missing tile nearest the last requested point (idle work), or else reads
    /// back a dropped one ([`Self::reload_nearer`]); `false` when there is nothing to do (or
    /// no cache). Without a file to write it to (no store, or a store that refused one), a
    /// missing tile is built only when it belongs in memory ([`Self::belongs_in_memory`]):
    /// the background work then stops at the memory limit instead of holding every tile.
    fn build_next_tile(&mut self) -> bool {
        let Some(k) = self
            .cache
            .as_ref()
            .and_then(|c| c.next_missing(self.last_point_m.get()))
        else {
            return !self.fill_only && self.reload_nearer();
        };
        if self.fill_only {
            self.fill(k);
        } else if (self.store.is_some() && !self.store_full.get()) || self.belongs_in_memory(k) {
            self.build_and_keep(k);
        } else {
            return self.reload_nearer();
        }
        true
    }

    /// Whether tile `k`, not in memory, belongs there: it fits under the memory limit, or it
    /// lies [`TILE_HYSTERESIS_M`] nearer the last requested point than a tile in memory
    /// (which [`Self::keep`] then drops), so that the tiles in memory follow the probe.
    fn belongs_in_memory(&self, k: usize) -> bool {
        let Some(cache) = self.cache.as_ref() else {
            return false;
        };
        let p = self.last_point_m.get();
        let d_k = cache.centres[k].distance(p);
        let bytes = self.shared.tile_cache_bytes.load(Ordering::Relaxed);
        let fits = cache
            .mean_built_bytes()
            .is_none_or(|b| bytes.saturating_add(b) <= self.memory_limit);
        let nearer = [true, false].into_iter().any(|with_file| {
            cache
                .farthest_in_memory(p, k, with_file)
                .is_some_and(|(_, d_j)| d_k + TILE_HYSTERESIS_M < d_j)
        });
        fits || nearer
    }

    /// Reads back the dropped tile nearest the last requested point when it belongs in
    /// memory ([`Self::belongs_in_memory`]). `false` when there is none to read.
    fn reload_nearer(&mut self) -> bool {
        let Some((k, _)) = self
            .cache
            .as_ref()
            .and_then(|c| c.nearest_dropped(self.last_point_m.get()))
        else {
            return false;
        };
        if !self.belongs_in_memory(k) {
            return false;
        }
        self.build_and_keep(k);
        true
    }

    /// Fill-only idle work on the missing tile `k`: [`Tile::OnDisk`] when its file is there
    /// (header checked, not read), else built and written (and dropped once written).
    fn fill(&mut self, k: usize) {
        let (Some(cache), Some(store)) = (self.cache.as_ref(), self.store.as_ref()) else {
            return;
        };
        let centre_m = cache.centres[k];
        match store.present(k, centre_m, self.dt_s) {
            Ok(true) => {
                self.shared.tiles_present.fetch_add(1, Ordering::Relaxed);
                if let Some(cache) = self.cache.as_mut() {
                    cache.tiles[k] = Tile::OnDisk;
                }
                return;
            }
            Ok(false) => {}
            Err(e) => {
                self.shared.tiles_refused.fetch_add(1, Ordering::Relaxed);
                self.cache_error(e);
            }
        }
        // Never read: the file is missing or its header was refused.
        match self.obtain(k, false) {
            (Some(_), true) => {
                if let Some(cache) = self.cache.as_mut() {
                    cache.tiles[k] = Tile::OnDisk;
                }
            }
            (Some(_), false) => self.stop_fill(k),
            (None, _) => self.keep(k, None, false),
        }
    }

    /// A fill-only worker that could not write tile `k` (the cache full, or a write error,
    /// reported) stops: it serves no session, so a tile it cannot write would only grow its
    /// memory, and once the cache is full the others would not fit either. Tile `k` and every
    /// missing one are marked failed (the missing ones counted), and the reason is kept.
    fn stop_fill(&mut self, k: usize) {
        let Some(cache) = self.cache.as_mut() else {
            return;
        };
        cache.tiles[k] = Tile::Failed;
        let mut left = 0;
        for t in cache
            .tiles
            .iter_mut()
            .filter(|t| matches!(t, Tile::Missing))
        {
            *t = Tile::Failed;
            left += 1;
        }
        self.shared.tiles_failed.fetch_add(left, Ordering::Relaxed);
        self.shared.failed.fetch_add(left, Ordering::Relaxed);
        self.cache_error(format!(
            "the region cache could not take tile {k}: the fill stops with {left} tiles not \
             prepared (raise region_cache_max_bytes, or free the disk)"
        ));
    }

    /// A one-ball request with tiles for `point_m` while the region in use is centred at
    /// `centre_m` (NaN: a union, which no tile is): nothing to do, or a copy of the tile the
    /// cache chooses when it is in memory (a hit); else that tile's index (a miss,
    /// [`Self::miss`]).
    fn tile_ready(&self, point_m: DVec3, centre_m: DVec3) -> Result<Prepared, Pending> {
        self.last_point_m.set(point_m);
        let start = Instant::now();
        let Some(cache) = self.cache.as_ref() else {
            return Ok(Prepared::Nothing);
        };
        let Some(k) = cache.choose(point_m, centre_m) else {
            return Ok(Prepared::Nothing);
        };
        let meanwhile = self.read_meanwhile.borrow();
        let read = meanwhile.iter().find(|(j, _)| *j == k).map(|(_, t)| t);
        match (&cache.tiles[k], read) {
            (Tile::Built(t), _) | (_, Some(t)) => {
                self.shared.tile_hits.fetch_add(1, Ordering::Relaxed);
                Ok(self.copy_of(t, cache.centres[k], start, true))
            }
            (Tile::Failed, None) => Ok(Prepared::Nothing),
            (Tile::Missing | Tile::OnDisk | Tile::Dropped, None) => Err(Pending::Tile(k)),
        }
    }

    /// A request's tile `k`, not in memory: read back or built, kept, and copied.
    fn miss(&mut self, k: usize) -> Prepared {
        let start = Instant::now();
        self.shared.tile_misses.fetch_add(1, Ordering::Relaxed);
        let Some(centre_m) = self.cache.as_ref().map(|c| c.centres[k]) else {
            return Prepared::Nothing;
        };
        match self.build_and_keep(k) {
            Some(t) => self.copy_of(&t, centre_m, start, false),
            None => Prepared::Nothing,
        }
    }

    /// The answer with a copy of `tile` (centred at `centre_m`), looked up since `start`
    /// (`hit`: found in memory; requests lead by those times).
    fn copy_of(
        &self,
        tile: &CondensedSolver,
        centre_m: DVec3,
        start: Instant,
        hit: bool,
    ) -> Prepared {
        // A copy shares the tile's arrays (the tick never writes them); they are read here
        // once so that the servo's first tick with the region does not wait for them.
        let solver = Box::new(tile.clone());
        std::hint::black_box(solver.touch());
        self.shared
            .record_prepare_s(start.elapsed().as_secs_f64(), hit);
        self.shared.prepared.fetch_add(1, Ordering::Relaxed);
        Prepared::Region {
            solver,
            balls: RegionBalls::one(centre_m),
        }
    }
}

/// What a request needs besides an answer ready now ([`Worker::ready_answer`]).
enum Pending {
    /// Tile `k`, not in memory.
    Tile(usize),
    /// The region of these balls, prepared on demand.
    Union(RegionBalls),
}
