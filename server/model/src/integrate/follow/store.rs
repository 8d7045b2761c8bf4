//! The region cache on disk (issue 48 s2): a following region's tiles written to a directory
//! the host names ([`RegionCacheDir`]) as they are built, and read back by the next session
//! of the same body instead of being prepared again.
//!
//! A tile is one file, `<key>-<index>.tile`: the key (BLAKE3, [`cache_key`]) covers everything
//! a tile depends on (the body's mesh, masses, constraints, material and fibres; the
//! region's radius, margin and cover; the step; the touchable nodes; the image format and
//! the crate version), so a changed scene looks for other files. A file at the right name
//! that does not hold the tile asked for (another key inside, another format, a damaged or
//! truncated file, another centre) is refused with the reason
//! ([`CondensedSolver::from_image`]), counted, and replaced by a fresh build. Files are
//! written to a temporary name and renamed, so a reader never sees half a file. The
//! directory's `.tile` files are kept under [`RegionCacheDir::max_bytes`]: a write that would
//! exceed it first removes the least recently used files of other keys (a changed scene's, a
//! former version's; reading a file marks it used), and when that is not enough the tile stays
//! in memory only.
//!
//! Owns: the key, the file names, reading and writing. May use:
//! [`super::super::condensed`].

use std::io::Write;
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::super::condensed::{
    ActiveRegion, CondensedSolver, TILE_IMAGE_FORMAT, TILE_IMAGE_HEADER_BYTES,
};
use crate::element::FemModel;
use crate::mesh::TetMesh;

/// Where following regions keep their tiles between sessions: a directory the host (the
/// daemon's operator) chooses, never a scene (a client's file must not name host paths).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RegionCacheDir {
    /// The directory; created on the first write.
    pub dir: PathBuf,
    /// Largest total size of the directory's `.tile` files, bytes; a tile that would exceed it
    /// is not written (it stays in the session's memory).
    pub max_bytes: u64,
    /// Largest total size of the tiles one session keeps in memory, bytes
    /// ([`CondensedSolver::heap_bytes`]; default [`DEFAULT_REGION_CACHE_MEMORY_BYTES`]):
    /// beyond it the tiles farthest from the probe are dropped from memory (their files
    /// stay) and read back as it comes near them. Tiles without a file (the directory full)
    /// go last, and are prepared again when needed; once the directory refuses a tile,
    /// background builds stop at this limit. A session without a directory keeps
    /// [`DEFAULT_REGION_CACHE_MEMORY_BYTES`] of tiles at most.
    pub memory_bytes: u64,
}

/// Where a following region reports its region cache's complaints as they happen: a file
/// refused (damaged, truncated, of another format, key or centre), a write that failed or
/// did not fit under [`RegionCacheDir::max_bytes`]. Called on the region worker's thread,
/// never the servo's, with one line that names the file and the reason; the host logs it (the
/// daemon: a warning naming the session). Two reports are equal when they share the sink.
#[derive(Clone)]
pub struct RegionCacheReport(pub std::sync::Arc<dyn Fn(&str) + Send + Sync>);

impl RegionCacheReport {
    /// Reports `line`.
    pub fn report(&self, line: &str) {
        (self.0)(line);
    }
}

impl std::fmt::Debug for RegionCacheReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("RegionCacheReport(..)")
    }
}

impl PartialEq for RegionCacheReport {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.0, &other.0)
    }
}

impl Eq for RegionCacheReport {}

/// Default [`RegionCacheDir::max_bytes`]: 8 GiB (`lv_h1_condensed.toml`'s 69 tiles take
/// about 0.85 GB).
pub const DEFAULT_REGION_CACHE_MAX_BYTES: u64 = 8 << 30;

/// Default [`RegionCacheDir::memory_bytes`]: 2 GiB (`lv_h1_condensed.toml`'s 69 tiles,
/// about 1.25 GB, stay whole; of the 100 000-tet LV's 678 tiles of about 40 MB at its
/// default cover, the 50 or so nearest the probe).
pub const DEFAULT_REGION_CACHE_MEMORY_BYTES: u64 = 2 << 30;

/// The key's first 16 bytes in hexadecimal: the prefix of its tiles' files.
fn file_prefix(key: &[u8; 32]) -> String {
    key[..16].iter().map(|b| format!("{b:02x}")).collect()
}

fn name_of(prefix: &str, k: usize) -> String {
    format!("{prefix}-{k:05}.tile")
}

/// The name of tile `k`'s file in a region cache directory for the key `key` ([`cache_key`]),
/// as a session writes and reads it.
pub fn tile_file_name(key: &[u8; 32], k: usize) -> String {
    name_of(&file_prefix(key), k)
}

/// Reads the file at `path` into `image` (its contents replaced), reusing `image`'s memory:
/// a region worker reads every tile file into one buffer, whose pages are then already
/// mapped (a fresh 30 MB buffer a read cost 10-50 ms of page faults on the 100 000-tet LV's
/// tiles, docs/benchmarks.md, "A tile file read into one buffer").
///
/// # Errors
/// The file's error (`NotFound` when there is none); `InvalidData` when it is longer than
/// `max_bytes` (no tile is: the directory's size limit, [`RegionCacheDir::max_bytes`]);
/// `OutOfMemory` when its length cannot be reserved.
pub fn read_tile_file(path: &Path, image: &mut Vec<u8>, max_bytes: u64) -> std::io::Result<()> {
    use std::io::Read;
    let mut file = std::fs::File::open(path)?;
    let len = file.metadata()?.len();
    if len > max_bytes {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{len} bytes, more than the region cache's limit of {max_bytes}"),
        ));
    }
    image.clear();
    image
        .try_reserve_exact(usize::try_from(len).unwrap_or(usize::MAX))
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::OutOfMemory, e.to_string()))?;
    file.read_to_end(image)?;
    Ok(())
}

/// The key of a following region's tiles over `body` (mesh `mesh`): the region's radius,
/// margin and tile cover (`region`, its centre excluded: each file holds its own), the step
/// `dt_s`, the touchable `nodes`, [`TILE_IMAGE_FORMAT`] and this crate's version (BLAKE3).
pub fn cache_key(
    body: &FemModel,
    mesh: &TetMesh,
    region: &ActiveRegion,
    dt_s: f64,
    nodes: &[u32],
) -> [u8; 32] {
    let mut h = blake3::Hasher::new();
    let mut text = |s: &str| {
        h.update(&(s.len() as u64).to_le_bytes());
        h.update(s.as_bytes());
    };
    text("haptic-model region tile");
    text(env!("CARGO_PKG_VERSION"));
    text(&TILE_IMAGE_FORMAT.to_string());
    text(&format!("{:?}", body.material()));
    text(&format!("{:?}", body.strain_smoothing()));
    text(&format!("{:?}", body.fibres()));
    text(&format!(
        "single {} radius {:?} margin {:?} tiles {:?} dt {:?}",
        body.single_precision(),
        region.radius_m.to_bits(),
        region.stiffness_margin.to_bits(),
        region.tiles,
        dt_s.to_bits()
    ));
    let mut words = |values: &mut dyn Iterator<Item = u64>| {
        let mut count = 0u64;
        for v in values {
            h.update(&v.to_le_bytes());
            count += 1;
        }
        h.update(&count.to_le_bytes());
    };
    words(
        &mut body
            .rest()
            .iter()
            .flat_map(|p| p.to_array().map(f64::to_bits)),
    );
    words(&mut mesh.tets.iter().flatten().map(|&i| u64::from(i)));
    words(&mut mesh.tet_edge_nodes.iter().flatten().map(|&i| u64::from(i)));
    words(&mut body.lumped_mass_kg().iter().map(|m| m.to_bits()));
    words(&mut body.constraints().iter().map(|&c| u64::from(c)));
    words(&mut nodes.iter().map(|&i| u64::from(i)));
    *h.finalize().as_bytes()
}

/// The tiles of one body and region in a [`RegionCacheDir`].
pub(super) struct TileStore {
    dir: PathBuf,
    max_bytes: u64,
    key: [u8; 32],
    /// The key's first 16 bytes in hexadecimal: the files' prefix.
    prefix: String,
    /// The buffer every file is read into ([`read_tile_file`]): the largest file read so
    /// far stays allocated (13 MB on `lv_h1_condensed`, 30 MB on the 100 000-tet LV).
    image: std::cell::RefCell<Vec<u8>>,
}

impl TileStore {
    pub(super) fn new(cache: &RegionCacheDir, key: [u8; 32]) -> Self {
        let prefix = file_prefix(&key);
        Self {
            dir: cache.dir.clone(),
            max_bytes: cache.max_bytes,
            key,
            prefix,
            image: std::cell::RefCell::new(Vec::new()),
        }
    }

    /// The file of tile `k`.
    pub(super) fn path(&self, k: usize) -> PathBuf {
        self.dir.join(name_of(&self.prefix, k))
    }

    /// Tile `k` centred at `centre_m` from its file: `Ok(None)` when there is no file,
    /// `Err` with the reason when the file cannot be read or is refused
    /// ([`CondensedSolver::from_image`]).
    pub(super) fn load(
        &self,
        k: usize,
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        centre_m: DVec3,
        dt_s: f64,
    ) -> Result<Option<CondensedSolver>, String> {
        let path = self.path(k);
        let Ok(mut bytes) = self.image.try_borrow_mut() else {
            return Err(format!("{}: a read already in progress", path.display()));
        };
        match read_tile_file(&path, &mut bytes, self.max_bytes) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(format!("{}: {e}", path.display())),
        }
        // Used now: the last to be removed to make room (best effort).
        if let Ok(f) = std::fs::File::options().append(true).open(&path) {
            let _ = f.set_modified(std::time::SystemTime::now());
        }
        let region = ActiveRegion { centre_m, ..region };
        CondensedSolver::from_image(body, mesh, region, dt_s, &self.key, &bytes)
            .map(Some)
            .map_err(|e| format!("{}: {e}", path.display()))
    }

    /// Whether tile `k`'s file is there and begins with the header of an image of tile `k`
    /// (centre `centre_m`, step `dt_s`; [`CondensedSolver::check_image_header`]), without
    /// reading the rest: `Ok(false)` when there is no file, `Err` with the reason when it
    /// cannot be read or its header is refused. A file found is marked used.
    pub(super) fn present(&self, k: usize, centre_m: DVec3, dt_s: f64) -> Result<bool, String> {
        use std::io::Read;
        let path = self.path(k);
        let in_file = |e: String| format!("{}: {e}", path.display());
        let mut file = match std::fs::File::open(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(false),
            Err(e) => return Err(in_file(e.to_string())),
        };
        let mut head = [0u8; TILE_IMAGE_HEADER_BYTES];
        file.read_exact(&mut head).map_err(|e| match e.kind() {
            std::io::ErrorKind::UnexpectedEof => in_file("region image is truncated".into()),
            _ => in_file(e.to_string()),
        })?;
        CondensedSolver::check_image_header(&head, &self.key, centre_m, dt_s)
            .map_err(|e| in_file(e.to_string()))?;
        if let Ok(f) = std::fs::File::options().append(true).open(&path) {
            let _ = f.set_modified(std::time::SystemTime::now());
        }
        Ok(true)
    }

    /// Writes tile `k` (`solver`, a trimmed tile): `Ok(false)` when the directory's tiles
    /// would exceed the size limit, `Err` with the reason when it cannot be written.
    pub(super) fn save(&self, k: usize, solver: &CondensedSolver) -> Result<bool, String> {
        let bytes = solver.to_image(&self.key).map_err(|e| e.to_string())?;
        let path = self.path(k);
        let in_dir = |e: std::io::Error| format!("{}: {e}", self.dir.display());
        std::fs::create_dir_all(&self.dir).map_err(in_dir)?;
        if !self.make_room(&path, bytes.len() as u64).map_err(in_dir)? {
            return Ok(false);
        }
        // A name no other writer uses, in this process (two sessions of one scene build the
        // same tiles) or another.
        static WRITES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = WRITES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = path.with_extension(format!("tmp{}-{n}", std::process::id()));
        let write = || -> std::io::Result<()> {
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(&bytes)?;
            f.sync_all()?;
            std::fs::rename(&tmp, &path)
        };
        write().map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            format!("{}: {e}", path.display())
        })?;
        Ok(true)
    }
}

impl TileStore {
    /// Whether `bytes` more fit under the limit beside the directory's other `.tile` files
    /// (`replaced`, about to be overwritten, not counted), after removing the least recently
    /// used files of other keys as needed.
    fn make_room(&self, replaced: &Path, bytes: u64) -> std::io::Result<bool> {
        let mut files = Vec::new();
        for entry in std::fs::read_dir(&self.dir)? {
            let entry = entry?;
            let path = entry.path();
            if path.extension().is_some_and(|e| e == "tile") && path != replaced {
                let meta = entry.metadata()?;
                let modified = meta.modified().unwrap_or(std::time::UNIX_EPOCH);
                files.push((modified, meta.len(), path));
            }
        }
        let mut used: u64 = files.iter().map(|f| f.1).sum();
        files.sort();
        let ours = |p: &Path| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&self.prefix))
        };
        for (_, len, path) in files.iter().filter(|f| !ours(&f.2)) {
            if used.saturating_add(bytes) <= self.max_bytes {
                break;
            }
            if std::fs::remove_file(path).is_ok() {
                used = used.saturating_sub(*len);
            }
        }
        Ok(used.saturating_add(bytes) <= self.max_bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `read_tile_file` replaces the buffer's contents (a shorter file after a longer one
    /// leaves nothing of the first), keeps its memory, and refuses a file over the limit and
    /// a missing one with their kinds.
    #[test]
    fn a_tile_file_is_read_into_the_same_buffer() {
        let dir = std::env::temp_dir().join(format!("haptic-read-tile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let (long, short) = (dir.join("long.tile"), dir.join("short.tile"));
        let long_bytes: Vec<u8> = (0..100_000u32).map(|i| (i % 251) as u8).collect();
        std::fs::write(&long, &long_bytes).expect("write");
        std::fs::write(&short, b"tile").expect("write");
        let mut image = Vec::new();
        read_tile_file(&long, &mut image, 1 << 20).expect("long");
        assert_eq!(image, long_bytes);
        let (capacity, at) = (image.capacity(), image.as_ptr());
        read_tile_file(&short, &mut image, 1 << 20).expect("short");
        assert_eq!(image, b"tile");
        assert_eq!((image.capacity(), image.as_ptr()), (capacity, at));
        let over = read_tile_file(&long, &mut image, 99_999).expect_err("over the limit");
        assert_eq!(over.kind(), std::io::ErrorKind::InvalidData, "{over}");
        assert!(over.to_string().contains("100000 bytes"), "{over}");
        let missing =
            read_tile_file(&dir.join("none.tile"), &mut image, 1 << 20).expect_err("missing");
        assert_eq!(missing.kind(), std::io::ErrorKind::NotFound);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
