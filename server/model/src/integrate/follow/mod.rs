//! The contact-local region follows the probe (issue 20): a worker thread prepares the next
//! [`CondensedSolver`] around the touchable surface near the device while the servo ticks with
//! the current one, and the servo swaps it in at a tick boundary.
//!
//! **Protocol.** Every [`POLL_TICKS`] ticks without a request in flight, the servo sends the
//! device point (led by its velocity over the shortest of the last three preparation times,
//! with tiles of the hits, plus the poll interval, at most [`FOLLOW_LEAD_RADII`] radii) and the
//! current centre through a wait-free ring and unparks the worker. The worker picks the
//! touchable node nearest that point (rest configuration) as the new centre, and answers
//! "nothing to do" when the device is farther than a radius from every touchable node or the
//! centre would move less than [`RECENTRE_RADII`] radii; otherwise it condenses and
//! factorises the new region ([`CondensedSolver::new`], then
//! [`CondensedSolver::prepare_contact`]) and sends it back. At the next tick boundary the servo
//! swaps it in when it is closer to the device than the current one (or within
//! [`FOLLOW_NEAR_RADII`] radii of it) and holds at least as many nodes of the contact patch,
//! handing the state over ([`CondensedSolver::hand_over`]: the nodes it newly simulates start
//! from the old far field's static response); the region it replaces, or
//! a rejected one, goes back to the worker to be freed. The servo side allocates nothing, takes
//! no lock and never waits (except in [`RegionFollower::set_blocking`] mode, for tests and
//! studies).
//!
//! **Until a region is ready** the current one answers: the probe's touchable surface is the
//! whole body's, so a touch outside the region meets the far surface as the far field moves it
//! (its nodes are not simulated: it does not yield to the probe, which rests on it instead of
//! passing through). How fast the probe may slide is set by the preparation time: the probe
//! must stay well inside a region (its contact patch reaches two probe radii) until the next
//! one is ready (`docs/benchmarks.md`). A scene with a coarse whole-body companion
//! (`active_region.fallback_target_tets`) lets the companion answer meanwhile
//! ([`crate::fem::FemBody`], "The coarse companion").
//!
//! **Several tools** (issue 50). A request carries every connected tool's led point. The worker
//! gives each point farther than [`MERGE_RADII`] radii from the balls so far a ball at the
//! touchable node nearest it (a point farther than a radius from every touchable node gets
//! none), so a region is the union of up to [`MAX_REGION_BALLS`] balls of the scene's radius
//! ([`CondensedSolver::new_union`]). One ball is the one-tool protocol above, unchanged
//! (tiles included). Several balls are prepared on demand (tiles are single balls), when
//! their number changes or one of them would move [`RECENTRE_RADII`] radii; meanwhile the
//! current region (and the companion) answers. The swap rule holds for each tool: the new
//! region is near every device (one farther than a radius from both regions does not count
//! when there are several) and holds at least as many nodes of every tool's contact patch.
//!
//! **Tiles** ([`TileMode::Background`], issue 48 s2): the worker keeps regions prepared ahead
//! at centres covering the touchable surface ([`tile_centres`]) and builds them while it has
//! no request, the tile nearest the last requested point first. A request then takes the tile
//! nearest the point ([`TILE_HYSTERESIS_M`] replaces [`RECENTRE_RADII`]) and sends a copy
//! (the tile itself is never stepped), or prepares the tile on demand when it is not built
//! yet and keeps it. A request that needs no preparation (a tile in memory, or nothing to
//! do) or only a read (its tile's file) is answered while a tile is being built (on a
//! thread of its own); one whose tile must be built waits for that build (at most one)
//! before its own. The servo's side
//! is unchanged. The tiles in memory are bounded ([`RegionCacheDir::memory_bytes`], or
//! [`DEFAULT_REGION_CACHE_MEMORY_BYTES`] without a region cache on disk): the farthest from
//! the last requested point are dropped, read back from their files (or prepared again
//! without one) as the probe nears them; without files to write, background builds stop at
//! the limit. A device above the surface moves that point to the surface under it, and
//! [`RegionFollower::focus_tiles`] anywhere the host says. A tile maps only the far
//! components its neighbours can take over (its ring), and the far field beyond is at rest.
//!
//! Owns: the worker thread, the hand-off rings, the re-centring rule and the tile cache
//! (`tiles`). May use: [`super::condensed`], [`crate::element`], [`crate::mesh`].

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::Thread;
use std::time::{Duration, Instant};

use glam::DVec3;

use super::condensed::{
    CondensedSolver, FOLLOW_LEAD_RADII, FOLLOW_NEAR_RADII, MAX_REGION_BALLS, RegionBalls, TileMode,
};
use crate::ModelError;
use crate::element::FemModel;
use crate::mesh::TetMesh;
use crate::pool::TickPool;

mod store;
mod tiles;
mod worker;

use store::TileStore;
pub use store::{
    DEFAULT_REGION_CACHE_MAX_BYTES, DEFAULT_REGION_CACHE_MEMORY_BYTES, RegionCacheDir,
    RegionCacheReport, cache_key, read_tile_file, tile_file_name,
};
use tiles::TileCache;
pub use tiles::{TILE_HYSTERESIS_M, tile_centres};
use worker::Worker;

/// Servo ticks between two requests when none is in flight.
pub const POLL_TICKS: u64 = 20;

/// Preparations the lead is the shortest of (`Shared::lead_prepare_s`).
const LEAD_SAMPLES: usize = 3;

/// The worker re-centres only when the centre would move at least this many radii.
pub const RECENTRE_RADII: f64 = 0.25;

/// A tool's point within this many radii of an earlier tool's ball shares that ball (module
/// documentation, "Several tools").
pub const MERGE_RADII: f64 = 0.5;

/// A request from the servo: where the devices are heading and where the region is.
#[derive(Debug, Clone, Copy)]
struct Request {
    /// Every connected tool's led device point, m (slot order; the list type is reused).
    points_m: RegionBalls,
    /// The balls of the region in use.
    current: RegionBalls,
}

/// The worker's answer.
enum Prepared {
    /// A new region, the union of `balls`.
    Region {
        solver: Box<CondensedSolver>,
        balls: RegionBalls,
    },
    /// No re-centring needed (or the preparation failed: counted in [`Shared`]).
    Nothing,
}

/// What the worker and the servo share: atomics, and the region cache's last error behind a
/// lock the servo never takes ([`RegionFollower::cache_error`]).
#[derive(Debug, Default)]
struct Shared {
    stop: AtomicBool,
    prepared: AtomicU64,
    failed: AtomicU64,
    /// Last and largest preparation time, s, as `f64` bits.
    last_prepare_s: AtomicU64,
    max_prepare_s: AtomicU64,
    /// The preparation time requests lead the device by, s, as `f64` bits: the shortest of
    /// the last [`LEAD_SAMPLES`] preparations on demand or tile hits (a tile read from disk
    /// or built on a miss does not count: the next request is most likely a hit again; one
    /// slow hit, the host busy for a moment, does not put the next regions ahead either).
    lead_prepare_s: AtomicU64,
    /// Those preparation times, s, as `f64` bits (written by the worker only), and how many
    /// were recorded.
    lead_samples: [AtomicU64; LEAD_SAMPLES],
    lead_recorded: AtomicU64,
    tile_hits: AtomicU64,
    tile_misses: AtomicU64,
    tiles_built: AtomicU64,
    tiles_failed: AtomicU64,
    tiles: AtomicU64,
    tile_cache_bytes: AtomicU64,
    tile_build_s: AtomicU64,
    tiles_loaded: AtomicU64,
    tiles_refused: AtomicU64,
    tiles_stored: AtomicU64,
    tiles_present: AtomicU64,
    tiles_dropped: AtomicU64,
    tiles_reloaded: AtomicU64,
    answered_while_building: AtomicU64,
    read_while_building: AtomicU64,
    /// The worker builds no tile in the background ([`RegionFollower::set_paused`]).
    paused: AtomicBool,
    cache_error: std::sync::Mutex<Option<String>>,
    /// Where the background tile work moves to ([`RegionFollower::focus_tiles`]), until the
    /// worker takes it.
    focus_m: std::sync::Mutex<Option<DVec3>>,
    /// The tick pool's thread count the regions are cut for
    /// ([`CondensedSolver::set_parts`]; 0 or 1: uncut).
    parts: AtomicU64,
}

impl Shared {
    /// Records one preparation (or tile lookup) of `s` seconds; `lead`: requests lead by it.
    fn record_prepare_s(&self, s: f64, lead: bool) {
        self.last_prepare_s.store(s.to_bits(), Ordering::Relaxed);
        if lead {
            let n = self.lead_recorded.fetch_add(1, Ordering::Relaxed) + 1;
            self.lead_samples[(n - 1) as usize % LEAD_SAMPLES]
                .store(s.to_bits(), Ordering::Relaxed);
            let shortest = self.lead_samples[..(n as usize).min(LEAD_SAMPLES)]
                .iter()
                .map(|a| f64::from_bits(a.load(Ordering::Relaxed)))
                .fold(f64::INFINITY, f64::min);
            self.lead_prepare_s
                .store(shortest.to_bits(), Ordering::Relaxed);
        }
        let max = f64::from_bits(self.max_prepare_s.load(Ordering::Relaxed));
        self.max_prepare_s
            .store(max.max(s).to_bits(), Ordering::Relaxed);
    }
}

/// Counters of a following region, for reports.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FollowStats {
    /// Regions the worker sent (with tiles: tile copies included).
    pub prepared: u64,
    /// Preparations that failed (a factorisation error; the current region stays).
    pub failed: u64,
    /// Regions swapped in.
    pub swaps: u64,
    /// Prepared regions not swapped in (the device had moved back, the contact patch left
    /// the region).
    pub rejected: u64,
    /// Last preparation time, s (with tiles: of the lookup and copy, or of the on-demand
    /// preparation of a tile not built yet).
    pub last_prepare_s: f64,
    /// Largest preparation time, s.
    pub max_prepare_s: f64,
    /// Centre of the region in use, m (rest configuration; of a union, its first ball).
    pub centre_m: DVec3,
    /// Balls of the region in use (1, or one per tool apart from the others).
    pub balls: usize,
    /// Bytes held by the region in use ([`CondensedSolver::memory_bytes`]).
    pub region_bytes: usize,
    /// Time the last swap spent handing the state over, s ([`CondensedSolver::hand_over`], on
    /// the servo's thread; 0 before the first swap).
    pub last_hand_over_s: f64,
    /// Largest of those, s.
    pub max_hand_over_s: f64,
    /// Swaps that started some taken-over component at rest because the region in use had
    /// no far-map row for it (a tile's successor beyond its ring:
    /// [`CondensedSolver::hand_over`]); 0 while every swap goes to a neighbouring tile.
    pub unmapped_swaps: u64,
    /// Requests answered by a built tile ([`TileMode::Background`]).
    pub tile_hits: u64,
    /// Requests whose tile was not built yet (prepared on demand, then kept).
    pub tile_misses: u64,
    /// Tiles built (on demand or in the background) or read from the region cache on disk.
    pub tiles_built: u64,
    /// Tiles whose preparation failed (not tried again; also counted in `failed`).
    pub tiles_failed: u64,
    /// Tile centres (0 without tiles).
    pub tiles: u64,
    /// Bytes held by the built tiles ([`CondensedSolver::heap_bytes`] after
    /// [`CondensedSolver::trim_for_tiles`]).
    pub tile_cache_bytes: u64,
    /// Seconds the worker spent building tiles (and reading them from disk).
    pub tile_build_s: f64,
    /// Tiles read from the region cache on disk ([`RegionCacheDir`]; also in `tiles_built`).
    pub tiles_loaded: u64,
    /// Tile files refused (damaged, of another format, key or centre: built again and
    /// replaced; [`RegionFollower::cache_error`] says why).
    pub tiles_refused: u64,
    /// Tiles written to the region cache on disk.
    pub tiles_stored: u64,
    /// Tiles a fill-only worker found in the region cache and left unread (not in
    /// `tiles_built`; [`RegionFollower::spawn_with_cache`]).
    pub tiles_present: u64,
    /// Tiles dropped from memory to keep the cache under
    /// [`RegionCacheDir::memory_bytes`] (their files stay).
    pub tiles_dropped: u64,
    /// Dropped tiles read back from their files (on request, or while idle as the probe
    /// came near them; in `tiles_loaded`, not in `tiles_built`).
    pub tiles_reloaded: u64,
    /// Requests answered while a tile was being built (nothing to do, a copy of a tile in
    /// memory, or a tile read from its file) instead of after the build (module
    /// documentation, "Tiles").
    pub answered_while_building: u64,
    /// Of those, the requests whose tile was read from its file (also in `tile_misses`).
    pub read_while_building: u64,
}

impl FollowStats {
    /// Tiles done: built or read, failed, or (a fill-only worker's) found on disk. Every
    /// tile is done once this reaches [`Self::tiles`].
    pub fn tiles_ready(&self) -> u64 {
        self.tiles_built + self.tiles_failed + self.tiles_present
    }
}

/// The servo's side of a following region (module documentation).
pub struct RegionFollower {
    requests: rtrb::Producer<Request>,
    results: rtrb::Consumer<Prepared>,
    returns: rtrb::Producer<Box<CondensedSolver>>,
    /// A region waiting to go back to the worker (the return ring was full).
    pending_return: Option<Box<CondensedSolver>>,
    worker: Thread,
    shared: Arc<Shared>,
    radius_m: f64,
    balls: RegionBalls,
    in_flight: bool,
    ticks: u64,
    next_request_tick: u64,
    blocking: bool,
    swaps: u64,
    rejected: u64,
    region_bytes: usize,
    last_hand_over_s: f64,
    max_hand_over_s: f64,
    unmapped_swaps: u64,
    /// The servo's tick, s ([`Self::set_tick_s`]; the region's step until set).
    tick_s: f64,
}

impl std::fmt::Debug for RegionFollower {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RegionFollower")
            .field("stats", &self.stats())
            .finish()
    }
}

impl RegionFollower {
    /// Starts the worker for regions like `first` (its radius and margin) over `body` and
    /// `mesh`, re-centred on `touchable_nodes` (rest positions of `body`), with tick `dt_s`.
    ///
    /// # Errors
    /// [`ModelError::SceneField`] (`active_region.follow`) when there is no touchable node or
    /// the worker thread cannot be started.
    pub fn spawn(
        body: &FemModel,
        mesh: &TetMesh,
        touchable_nodes: &[u32],
        first: &CondensedSolver,
    ) -> Result<Self, ModelError> {
        Self::spawn_with_cache(body, mesh, touchable_nodes, first, None, None, false)
    }

    /// [`Self::spawn`] with the tiles ([`TileMode::Background`]) read from and written to
    /// `cache` ([`RegionCacheDir`], module `store`): a tile whose file holds it is read
    /// instead of built, and a tile built is written for the next session. Each file refused
    /// and each write that failed or did not fit goes to `report` as it happens (besides
    /// [`Self::cache_error`] and the counts of [`FollowStats`]).
    ///
    /// `fill_only` (with a cache): the worker only fills the cache, for a host that prepares
    /// it ahead of sessions. A tile whose file is there with the right header
    /// ([`CondensedSolver::check_image_header`]) is counted in
    /// [`FollowStats::tiles_present`] and left unread; a missing one (or one whose header is
    /// refused) is built, written and dropped. The first tile that cannot be written (the
    /// cache full) stops the fill: it and every missing tile count as failed, and
    /// [`Self::cache_error`] says why. A request still gets its tile, read from disk then.
    ///
    /// # Errors
    /// As [`Self::spawn`].
    pub fn spawn_with_cache(
        body: &FemModel,
        mesh: &TetMesh,
        touchable_nodes: &[u32],
        first: &CondensedSolver,
        cache: Option<&RegionCacheDir>,
        report: Option<RegionCacheReport>,
        fill_only: bool,
    ) -> Result<Self, ModelError> {
        let mut nodes = touchable_nodes.to_vec();
        nodes.sort_unstable();
        nodes.dedup();
        if nodes.is_empty() {
            return Err(ModelError::field(
                "active_region.follow",
                "needs a touchable surface",
            ));
        }
        let region = first.region();
        let (requests, worker_requests) = rtrb::RingBuffer::new(1);
        let (worker_results, results) = rtrb::RingBuffer::new(1);
        let (returns, worker_returns) = rtrb::RingBuffer::new(4);
        let shared = Arc::new(Shared::default());
        let memory_limit = cache.map_or(DEFAULT_REGION_CACHE_MEMORY_BYTES, |d| d.memory_bytes);
        let store = match (region.tiles, cache) {
            (TileMode::Background { .. }, Some(dir)) if region.follow => Some(TileStore::new(
                dir,
                cache_key(body, mesh, &region, first.dt_s(), &nodes),
            )),
            _ => None,
        };
        let cache = match region.tiles {
            TileMode::Background { cover_m } if region.follow => {
                let centres = tile_centres(body.rest(), &nodes, region.centre_m, cover_m);
                shared.tiles.store(centres.len() as u64, Ordering::Relaxed);
                Some(TileCache::new(centres, cover_m))
            }
            _ => None,
        };
        let job = Worker {
            fill_only: fill_only && store.is_some(),
            memory_limit,
            store_full: std::cell::Cell::new(false),
            cache,
            store,
            report,
            last_point_m: std::cell::Cell::new(region.centre_m),
            body: body.clone(),
            mesh: mesh.clone(),
            nodes,
            region,
            dt_s: first.dt_s(),
            requests: std::cell::RefCell::new(worker_requests),
            results: std::cell::RefCell::new(worker_results),
            returns: std::cell::RefCell::new(worker_returns),
            read_meanwhile: std::cell::RefCell::new(Vec::new()),
            tried_meanwhile: std::cell::Cell::new(usize::MAX),
            shared: Arc::clone(&shared),
        };
        let handle = std::thread::Builder::new()
            .name("region-prep".into())
            .spawn(move || job.run())
            .map_err(|e| {
                ModelError::field(
                    "active_region.follow",
                    format!("cannot start the preparation thread: {e}"),
                )
            })?;
        Ok(Self {
            requests,
            results,
            returns,
            pending_return: None,
            worker: handle.thread().clone(),
            shared,
            radius_m: region.radius_m,
            balls: first.balls(),
            in_flight: false,
            ticks: 0,
            next_request_tick: 0,
            blocking: false,
            swaps: 0,
            rejected: 0,
            region_bytes: first.memory_bytes(),
            last_hand_over_s: 0.0,
            max_hand_over_s: 0.0,
            unmapped_swaps: 0,
            tick_s: first.dt_s(),
        })
    }

    /// Cuts every region the worker sends from now on for a tick pool of `parts` threads
    /// ([`CondensedSolver::set_parts`], on the worker: the servo thread never allocates), and
    /// prepares them with as many threads ([`CondensedSolver::new_in_threads`]).
    pub fn set_parts(&self, parts: usize) {
        self.shared.parts.store(parts as u64, Ordering::Relaxed);
    }

    /// The servo's tick, s (a region's step may be a sub-step of it): requests lead the
    /// device by one poll interval, [`POLL_TICKS`] ticks, besides one preparation. Ignored
    /// unless positive and finite.
    pub fn set_tick_s(&mut self, tick_s: f64) {
        if tick_s > 0.0 && tick_s.is_finite() {
            self.tick_s = tick_s;
        }
    }

    /// In blocking mode a tick that sends a request waits for the answer (and swaps at once):
    /// deterministic, for tests and studies; never for a servo.
    pub fn set_blocking(&mut self, on: bool) {
        self.blocking = on;
    }

    /// Pauses (or resumes) the worker's background builds of tiles, after the one in
    /// progress; requests are still answered (a missing tile built on demand). For a host
    /// that fills the region cache only while nothing else wants the machine.
    pub fn set_paused(&self, on: bool) {
        if self.shared.paused.swap(on, Ordering::Relaxed) && !on {
            self.worker.unpark();
        }
    }

    /// Centres the worker's background tile work on `point_m` (m, the body's rest frame)
    /// until the next request moves it: the missing tiles nearest it are built first, the
    /// dropped ones nearest it read back, and those farthest from it dropped for the memory
    /// limit ([`RegionCacheDir::memory_bytes`]). For a host that knows where the probe is
    /// going (a planned stroke, the device above the surface before contact). Ignored
    /// unless `point_m` is finite; no effect without tiles.
    pub fn focus_tiles(&self, point_m: DVec3) {
        if !point_m.is_finite() {
            return;
        }
        if let Ok(mut focus) = self.shared.focus_m.lock() {
            *focus = Some(point_m);
        }
        self.worker.unpark();
    }

    /// Regions swapped in so far (as in [`Self::stats`], without reading the worker's
    /// counters).
    pub fn swaps(&self) -> u64 {
        self.swaps
    }

    /// Counters.
    pub fn stats(&self) -> FollowStats {
        let f = |a: &AtomicU64| f64::from_bits(a.load(Ordering::Relaxed));
        FollowStats {
            prepared: self.shared.prepared.load(Ordering::Relaxed),
            failed: self.shared.failed.load(Ordering::Relaxed),
            swaps: self.swaps,
            rejected: self.rejected,
            last_prepare_s: f(&self.shared.last_prepare_s),
            max_prepare_s: f(&self.shared.max_prepare_s),
            centre_m: self.balls.centres().first().copied().unwrap_or(DVec3::NAN),
            balls: self.balls.centres().len(),
            region_bytes: self.region_bytes,
            last_hand_over_s: self.last_hand_over_s,
            max_hand_over_s: self.max_hand_over_s,
            unmapped_swaps: self.unmapped_swaps,
            tile_hits: self.shared.tile_hits.load(Ordering::Relaxed),
            tile_misses: self.shared.tile_misses.load(Ordering::Relaxed),
            tiles_built: self.shared.tiles_built.load(Ordering::Relaxed),
            tiles_failed: self.shared.tiles_failed.load(Ordering::Relaxed),
            tiles: self.shared.tiles.load(Ordering::Relaxed),
            tile_cache_bytes: self.shared.tile_cache_bytes.load(Ordering::Relaxed),
            tile_build_s: f(&self.shared.tile_build_s),
            tiles_loaded: self.shared.tiles_loaded.load(Ordering::Relaxed),
            tiles_refused: self.shared.tiles_refused.load(Ordering::Relaxed),
            tiles_stored: self.shared.tiles_stored.load(Ordering::Relaxed),
            tiles_present: self.shared.tiles_present.load(Ordering::Relaxed),
            tiles_dropped: self.shared.tiles_dropped.load(Ordering::Relaxed),
            tiles_reloaded: self.shared.tiles_reloaded.load(Ordering::Relaxed),
            answered_while_building: self.shared.answered_while_building.load(Ordering::Relaxed),
            read_while_building: self.shared.read_while_building.load(Ordering::Relaxed),
        }
    }

    /// The region cache's last error (a tile file refused, or one that could not be
    /// written), for the host's log. Takes a lock the worker takes: not for the tick.
    pub fn cache_error(&self) -> Option<String> {
        self.shared.cache_error.lock().ok().and_then(|e| e.clone())
    }

    /// Called by the body at the start of every tick, before any sub-step: swaps in a prepared
    /// region (handing over `x`, `v`) and sends the next request. `devices[k]` is tool slot
    /// `k`'s device point and velocity (m, m/s) when it has one, `patches[k]` the nodes of its
    /// contact patch (at most [`MAX_REGION_BALLS`] slots are read). A swap hands the state
    /// over on `pool` when there is one ([`CondensedSolver::hand_over_in`]). Allocation-free,
    /// lock-free, never waits (unless blocking).
    pub fn before_tick(
        &mut self,
        solver: &mut Box<CondensedSolver>,
        pool: Option<&TickPool>,
        devices: &[Option<(DVec3, DVec3)>],
        patches: &[&[u32]],
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) {
        let devices = &devices[..devices.len().min(MAX_REGION_BALLS)];
        self.ticks += 1;
        if let Some(old) = self.pending_return.take() {
            self.give_back(old);
        }
        self.take_result(solver, pool, devices, patches, x, v);
        if devices.iter().all(Option::is_none) {
            return;
        }
        if self.in_flight || self.ticks < self.next_request_tick {
            return;
        }
        // Lead each device by its travel until the region asked for now can be swapped in
        // and until the next request's can: one preparation and one poll interval (none when
        // the tick waits). Leading by the preparation alone let a tile (prepared in 5-15 ms)
        // arrive when the device had already slid up to a poll interval past its cover. With
        // tiles the preparation is a hit's: one tile read from disk (0.2-0.4 s on the
        // 100 000-tet LV before image format 3) put every later region a radius ahead of the
        // device.
        let lead_s = if self.blocking {
            0.0
        } else {
            f64::from_bits(self.shared.lead_prepare_s.load(Ordering::Relaxed))
                + POLL_TICKS as f64 * self.tick_s
        };
        let mut points_m = RegionBalls::EMPTY;
        for &(point, velocity) in devices.iter().flatten() {
            let lead = (velocity * lead_s).clamp_length_max(FOLLOW_LEAD_RADII * self.radius_m);
            points_m.push(point + if lead.is_finite() { lead } else { DVec3::ZERO });
        }
        let request = Request {
            points_m,
            current: self.balls,
        };
        if self.requests.push(request).is_ok() {
            self.in_flight = true;
            self.next_request_tick = self.ticks + POLL_TICKS;
            self.worker.unpark();
            if self.blocking {
                while self.results.is_empty() {
                    std::thread::sleep(Duration::from_micros(100));
                }
                self.take_result(solver, pool, devices, patches, x, v);
            }
        }
    }

    fn take_result(
        &mut self,
        solver: &mut Box<CondensedSolver>,
        pool: Option<&TickPool>,
        devices: &[Option<(DVec3, DVec3)>],
        patches: &[&[u32]],
        x: &mut [DVec3],
        v: &mut [DVec3],
    ) {
        let Ok(prepared) = self.results.pop() else {
            return;
        };
        self.in_flight = false;
        let Prepared::Region {
            solver: mut next,
            balls,
        } = prepared
        else {
            return;
        };
        let (r, several) = (self.radius_m, devices.iter().flatten().count() > 1);
        // Near enough for every device: closer to it than the current region, or (a region
        // prepared ahead of a sliding probe) within the largest shift of it; with several
        // tools, one farther than a radius from both regions does not count.
        let near = devices.iter().flatten().all(|&(p, _)| {
            let (d, d_cur) = (balls.distance(p), self.balls.distance(p));
            d < d_cur || d <= FOLLOW_NEAR_RADII * r || (several && d.min(d_cur) > r)
        });
        // Every contact patch must be held at least as well as by the current region (a
        // region outrun by the probe is replaced by one that holds more of its patch).
        let held = |c: &CondensedSolver, patch: &[u32]| {
            patch.iter().filter(|&&i| c.is_active_node(i)).count()
        };
        let holds_patch = patches
            .iter()
            .take(MAX_REGION_BALLS)
            .all(|p| held(&next, p) >= held(solver, p));
        let start = Instant::now();
        // The hand-over's rows cut in two on the tick pool when the session has one (the swap
        // tick is the servo's longest).
        let handed = near
            && holds_patch
            && match pool {
                Some(pool) => solver.hand_over_in(pool, &mut next, x, v),
                None => solver.hand_over(&next, x, v),
            };
        if handed {
            self.last_hand_over_s = start.elapsed().as_secs_f64();
            self.max_hand_over_s = self.max_hand_over_s.max(self.last_hand_over_s);
            self.unmapped_swaps += u64::from(solver.unmapped_hand_over() > 0);
            let old = std::mem::replace(solver, next);
            self.balls = balls;
            self.region_bytes = solver.memory_bytes();
            self.swaps += 1;
            self.give_back(old);
            // Ask again at once: the probe may have moved on while this one was prepared.
            self.next_request_tick = self.ticks;
        } else {
            self.rejected += 1;
            self.give_back(next);
        }
    }

    /// Sends a region back to the worker to be freed there (never on the servo thread).
    fn give_back(&mut self, region: Box<CondensedSolver>) {
        match self.returns.push(region) {
            Ok(()) => self.worker.unpark(),
            Err(rtrb::PushError::Full(region)) => self.pending_return = Some(region),
        }
    }
}

impl Drop for RegionFollower {
    fn drop(&mut self) {
        // The worker exits after its current preparation; it is not joined (a drop on the
        // servo's thread must not wait for a factorisation).
        self.shared.stop.store(true, Ordering::Release);
        self.worker.unpark();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lead is the shortest of the last three leading preparations: one slow tile hit
    /// does not move it, three do, and a miss (not leading) never does.
    #[test]
    fn the_lead_is_the_shortest_of_the_last_three_preparations() {
        let shared = Shared::default();
        let lead = |s: &Shared| f64::from_bits(s.lead_prepare_s.load(Ordering::Relaxed));
        assert_eq!(lead(&shared), 0.0);
        shared.record_prepare_s(0.005, true);
        assert_eq!(lead(&shared), 0.005);
        shared.record_prepare_s(0.107, true);
        assert_eq!(lead(&shared), 0.005);
        shared.record_prepare_s(0.37, false);
        assert_eq!(lead(&shared), 0.005);
        shared.record_prepare_s(0.006, true);
        shared.record_prepare_s(0.2, true);
        assert_eq!(lead(&shared), 0.006);
        shared.record_prepare_s(0.3, true);
        shared.record_prepare_s(0.25, true);
        assert_eq!(lead(&shared), 0.2);
        assert_eq!(
            f64::from_bits(shared.max_prepare_s.load(Ordering::Relaxed)),
            0.37
        );
    }
}
