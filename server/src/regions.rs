//! Region caches filled ahead of sessions (issue 48 s2): `hapticd --prepare-regions SCENE`
//! (in the foreground, then exits) and the `prepare_regions` configuration key (in the
//! background from the daemon's start; by default only while no session runs, at the lowest
//! scheduling priority, since a fill beside a running session adds to its overruns:
//! `docs/deploy.md`, "The region cache"). Both build the scene file's body
//! with a fill-only region worker ([`haptic_model::BodyOptions::region_cache_fill_only`]):
//! regions whose files are there are left unread, missing ones are built and written, none is
//! kept in memory. A session of the scene that starts meanwhile reads what is written and
//! builds what is not yet.
//!
//! Owns: the fill's wait and its reports. May use: [`crate::config`], the model.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use haptic_model::fem::FemBody;
use haptic_model::integrate::condensed::TileMode;
use haptic_model::integrate::follow::{FollowStats, RegionCacheDir, RegionCacheReport};
use haptic_model::scene::Scene;

use crate::config::FillPriority;
use crate::error::ServerError;

/// Loads the scene file `path` and checks that its region has a cache to fill
/// (`[active_region] follow = true`, `tiles = "background"`).
///
/// # Errors
/// [`ServerError::Config`] naming the file: it cannot be loaded, or has no region cache.
pub fn tiled_scene(path: &Path) -> Result<Scene, ServerError> {
    let scene = haptic_model::scene::load_scene_file(path)
        .map_err(|e| ServerError::Config(format!("loading {}: {e}", path.display())))?;
    let tiled = scene
        .active_region
        .is_some_and(|r| r.follow && matches!(r.tiles, TileMode::Background { .. }));
    if !tiled {
        return Err(ServerError::Config(format!(
            "{}: no region cache to prepare (it needs [active_region] follow = true and tiles = \"background\")",
            path.display()
        )));
    }
    Ok(scene)
}

/// Fills `cache` with every region of `scene` (a [`tiled_scene`]) and waits until each is
/// there (found, written, or failed), calling `progress` with the worker's counters and the
/// seconds since the start whenever a region is done, and `report` with each complaint of the
/// cache (a file refused, a write that failed), preparing each region with `threads` threads
/// (bit for bit the same regions at any count). `paused` is asked every 200 ms: while it says
/// so, no region is started (the one in progress finishes). Returns the last counters, or
/// `None` when `stop` was raised first (the body is dropped: its worker stops after the
/// region it is building).
///
/// # Errors
/// [`ServerError::Model`] when the body cannot be built.
pub fn fill_region_cache(
    scene: &Scene,
    cache: &RegionCacheDir,
    report: RegionCacheReport,
    progress: &mut dyn FnMut(&FollowStats, f64),
    paused: &mut dyn FnMut() -> bool,
    threads: usize,
    stop: &AtomicBool,
) -> Result<Option<FollowStats>, ServerError> {
    let options = haptic_model::BodyOptions {
        region_cache: Some(cache.clone()),
        region_cache_report: Some(report),
        region_cache_fill_only: true,
    };
    let start = Instant::now();
    let body = FemBody::new_with_options(scene, &options, &mut |_, _| {})?;
    body.set_region_preparation_threads(threads);
    let mut last = u64::MAX;
    loop {
        if stop.load(Ordering::Relaxed) {
            return Ok(None);
        }
        body.set_region_preparation_paused(paused());
        let s = body.follow_stats().unwrap_or_default();
        if s.tiles_ready() != last {
            progress(&s, start.elapsed().as_secs_f64());
            last = s.tiles_ready();
        }
        if s.tiles_ready() >= s.tiles {
            return Ok(Some(s));
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Threads for a fill that has the machine to itself: its cores (at most
/// [`haptic_model::integrate::condensed::MAX_PREPARATION_THREADS`]).
pub fn preparation_threads() -> usize {
    std::thread::available_parallelism().map_or(1, usize::from)
}

/// The one-line summary of a fill's counters `s` for the scene `name`.
pub fn summary(name: &str, s: &FollowStats) -> String {
    format!(
        "{} regions of {name} ready ({} already there, {} written, {} refused, {} failed)",
        s.tiles_ready(),
        s.tiles_present,
        s.tiles_stored,
        s.tiles_refused,
        s.tiles_failed
    )
}

/// The background fill of the configuration's `prepare_regions`: stops (after the region
/// being built) when dropped.
pub struct BackgroundFill {
    stop: Arc<AtomicBool>,
}

impl Drop for BackgroundFill {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Checks every scene file of `scenes` ([`tiled_scene`]) and starts one thread that fills
/// `cache` with their regions in turn: with [`FillPriority::Idle`] only while `running`
/// (the daemon's session count) is zero, at the lowest scheduling priority (`SCHED_IDLE`,
/// else nice 19) and on every core ([`preparation_threads`]), with [`FillPriority::Normal`]
/// always, at the daemon's own, on one core. Logs the start,
/// each quarter, each pause and the end of every scene, and each complaint as a warning.
/// `None` when `scenes` is empty.
///
/// # Errors
/// [`ServerError::Config`] when a scene file cannot be loaded or has no region cache, or
/// when the thread cannot start.
pub fn spawn_background_fill(
    scenes: &[PathBuf],
    cache: &RegionCacheDir,
    priority: FillPriority,
    running: Arc<AtomicUsize>,
) -> Result<Option<BackgroundFill>, ServerError> {
    if scenes.is_empty() {
        return Ok(None);
    }
    let loaded = scenes
        .iter()
        .map(|p| tiled_scene(p))
        .collect::<Result<Vec<_>, _>>()?;
    let stop = Arc::new(AtomicBool::new(false));
    let (cache, flag) = (cache.clone(), Arc::clone(&stop));
    std::thread::Builder::new()
        .name("region-fill".into())
        .spawn(move || {
            if priority == FillPriority::Idle {
                crate::servo::lowest_priority();
            }
            let busy = || priority == FillPriority::Idle && running.load(Ordering::Relaxed) > 0;
            let threads = match priority {
                FillPriority::Idle => preparation_threads(),
                FillPriority::Normal => 1,
            };
            for scene in &loaded {
                fill_in_background(scene, &cache, (&busy, threads), &flag);
            }
        })
        .map_err(|e| ServerError::Config(format!("prepare_regions: cannot start: {e}")))?;
    Ok(Some(BackgroundFill { stop }))
}

/// One scene of [`spawn_background_fill`], logged.
fn fill_in_background(
    scene: &Scene,
    cache: &RegionCacheDir,
    (busy, threads): (&dyn Fn() -> bool, usize),
    stop: &AtomicBool,
) {
    let name = scene.name.clone();
    tracing::info!(scene = %name, dir = %cache.dir.display(), "filling the region cache");
    let report = {
        let name = name.clone();
        RegionCacheReport(Arc::new(move |e: &str| {
            tracing::warn!(scene = %name, "region cache: {e}");
        }))
    };
    let mut quarter = 0;
    let mut progress = |s: &FollowStats, t: f64| {
        let q = (4 * s.tiles_ready()).checked_div(s.tiles).unwrap_or(4);
        if q > quarter && q < 4 {
            quarter = q;
            tracing::info!(scene = %name, "region cache: {}/{} after {t:.0} s", s.tiles_ready(), s.tiles);
        }
    };
    let mut was_paused = false;
    let mut paused = || {
        let now = busy();
        if now != was_paused {
            was_paused = now;
            let what = if now {
                "paused while sessions run"
            } else {
                "resumed"
            };
            tracing::info!(scene = %name, "region cache: fill {what}");
        }
        now
    };
    let start = Instant::now();
    match fill_region_cache(
        scene,
        cache,
        report,
        &mut progress,
        &mut paused,
        threads,
        stop,
    ) {
        Ok(Some(s)) => tracing::info!(
            "region cache: {} in {:.1} s",
            summary(&name, &s),
            start.elapsed().as_secs_f64()
        ),
        Ok(None) => {}
        Err(e) => tracing::warn!(scene = %name, "region cache not filled: {e}"),
    }
}
