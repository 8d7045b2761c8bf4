//! Times reading a region cache back (issue 48 s2): every tile file of `--scene`'s cache in
//! `--region-cache` (written by `hapticd --prepare-regions` or a session) is read into one
//! buffer (`read_tile_file`) and rebuilt with `CondensedSolver::from_image`, as a session's
//! region worker does for a tile it dropped, and the file read and the rebuild are reported
//! (p50, min, max).
//!
//! `cargo run --release -p haptic-model --example tile_read -- --scene deploy/scenes/lv_h1_condensed.toml --region-cache DIR`

use std::time::Instant;

use clap::Parser;
use haptic_model::integrate::condensed::{ActiveRegion, CondensedSolver, TileMode};
use haptic_model::integrate::follow::{cache_key, read_tile_file, tile_centres, tile_file_name};
use haptic_model::integrate::{critical_time_step, plan_steps};
use haptic_model::scene::load_scene_file;

#[derive(Parser)]
struct Args {
    /// Scene file with `[active_region] tiles = "background"`.
    #[arg(long)]
    scene: std::path::PathBuf,
    /// The region cache directory holding the scene's tiles.
    #[arg(long)]
    region_cache: std::path::PathBuf,
    /// Read at most this many tiles (in the cache's order, nearest the region's centre first).
    #[arg(long, default_value_t = usize::MAX)]
    max_tiles: usize,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let scene = load_scene_file(&args.scene)?;
    let fem = scene.fem_model()?;
    let mut nodes: Vec<u32> = scene.touchable.iter().flatten().copied().collect();
    nodes.sort_unstable();
    nodes.dedup();
    let mut region = scene
        .active_region
        .ok_or_else(|| anyhow::anyhow!("{} has no [active_region]", args.scene.display()))?;
    region.follow = true;
    let TileMode::Background { cover_m } = region.tiles else {
        anyhow::bail!(
            "{} has no tiles (active_region.tiles)",
            args.scene.display()
        );
    };
    // The regions' step, as the body plans it.
    let p = scene.integrator;
    let dt_s = plan_steps(&p, critical_time_step(&fem, p.kind))?.sub_dt_s;
    let key = cache_key(&fem, &scene.mesh, &region, dt_s, &nodes);
    let centres = tile_centres(fem.rest(), &nodes, region.centre_m, cover_m);
    let (mut read_ms, mut rebuild_ms, mut bytes) = (Vec::new(), Vec::new(), 0usize);
    // One buffer for every file, as the session's worker reads them.
    let mut image = Vec::new();
    for (k, &centre_m) in centres.iter().enumerate().take(args.max_tiles) {
        let path = args.region_cache.join(tile_file_name(&key, k));
        let t = Instant::now();
        if read_tile_file(&path, &mut image, u64::MAX).is_err() {
            continue;
        }
        read_ms.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let tile = ActiveRegion { centre_m, ..region };
        let back = CondensedSolver::from_image(&fem, &scene.mesh, tile, dt_s, &key, &image)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        rebuild_ms.push(t.elapsed().as_secs_f64() * 1e3);
        bytes += image.len();
        drop(back);
    }
    if read_ms.is_empty() {
        anyhow::bail!(
            "no tile of this scene in {} ({} centres, first file {})",
            args.region_cache.display(),
            centres.len(),
            tile_file_name(&key, 0)
        );
    }
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[0], v[v.len() - 1])
    };
    let (n, mb) = (read_ms.len(), bytes as f64 / 1e6);
    let (r50, rmin, rmax) = stats(&mut read_ms);
    let (b50, bmin, bmax) = stats(&mut rebuild_ms);
    println!(
        "{n} of {} tiles read ({mb:.0} MB, {:.1} MB a tile): file read p50 {r50:.1} ms (min {rmin:.1}, max {rmax:.1}); rebuild p50 {b50:.1} ms (min {bmin:.1}, max {bmax:.1})",
        centres.len(),
        mb / n as f64
    );
    Ok(())
}
