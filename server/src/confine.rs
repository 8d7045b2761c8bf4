//! Which files a client-sent scene may make the daemon read (issue 16): only regular files
//! inside the scene directory or a data directory the operator configured, after resolving
//! `..` and symlinks, and no larger than a size limit.
//!
//! The check runs on the scene text before anything is opened: every field that names a file
//! (`mesh.file`, `mass_spring.calibration_file`, `reference_file` and `organ_file`, and the
//! tables a mass-spring scene reads by default, `NAME.calibration.csv` and, with a reference,
//! `NAME.organ.csv`) is resolved against the scene directory. A path
//! that is outside every allowed directory *lexically* (after `..` is applied, before the file
//! system is asked) is refused with PERMISSION_DENIED without touching the file system, so the
//! answer is the same whether such a file exists or not. A path inside is then canonicalized
//! as the OS resolves it when the model opens it (a symlink pointing out, or a symlinked
//! directory followed by `..`, is refused with the same message), and must be a regular file (not
//! a pipe, device or directory: those are refused before any open, so a FIFO cannot block a
//! thread and `/dev/zero` cannot be read whole) within the size limit. Messages name the field
//! and the rule, never file contents.
//!
//! Neighbours: [`crate::session::SessionManager::load_scene`] calls [`FileRoots::check_scene`]
//! before the model parses the text; the directories come from [`crate::config`].

use std::path::{Component, Path, PathBuf};

use crate::error::ServerError;

/// The allowed directories (canonical) and the size limit.
#[derive(Debug, Clone)]
pub struct FileRoots {
    scene_dir: Option<PathBuf>,
    roots: Vec<PathBuf>,
    max_bytes: u64,
}

/// `base.join(rel)` with `.` and `..` applied lexically (no file-system access); `..` above
/// the root stays at the root.
pub fn lexical_join(base: &Path, rel: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    let joined = if rel.is_absolute() {
        rel.to_path_buf()
    } else {
        base.join(rel)
    };
    for c in joined.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other.as_os_str()),
        }
    }
    out
}

/// Directories that may never be a scene or data directory: the root and the system's own
/// folders (a client's scene could make the daemon read any file below them).
pub const SYSTEM_DIRS: &[&str] = &[
    "/",
    "/bin",
    "/boot",
    "/dev",
    "/etc",
    "/home",
    "/lib",
    "/lib32",
    "/lib64",
    "/libx32",
    "/media",
    "/mnt",
    "/opt",
    "/proc",
    "/root",
    "/run",
    "/sbin",
    "/snap",
    "/srv",
    "/sys",
    "/tmp",
    "/usr",
    "/usr/bin",
    "/usr/include",
    "/usr/lib",
    "/usr/lib64",
    "/usr/libexec",
    "/usr/local",
    "/usr/local/bin",
    "/usr/local/etc",
    "/usr/local/lib",
    "/usr/local/sbin",
    "/usr/local/share",
    "/usr/sbin",
    "/usr/share",
    "/usr/src",
    "/var",
    "/var/cache",
    "/var/lib",
    "/var/lib/private",
    "/var/local",
    "/var/log",
    "/var/mail",
    "/var/opt",
    "/var/run",
    "/var/spool",
    "/var/tmp",
];

/// Trees no directory below may serve clients either: kernel interfaces, devices, the
/// system's configuration and secrets.
pub const SYSTEM_TREES: &[&str] = &["/boot", "/dev", "/etc", "/proc", "/root", "/run", "/sys"];

/// Why `canonical` (an absolute, symlink-free path) may not serve client scenes, if it may not:
/// one of [`SYSTEM_DIRS`], inside one of [`SYSTEM_TREES`], or a home directory (`/home/NAME`).
pub fn system_dir_rule(canonical: &Path) -> Option<&'static str> {
    if SYSTEM_DIRS.iter().any(|d| canonical == Path::new(d)) {
        return Some("is the root or a system directory");
    }
    if SYSTEM_TREES.iter().any(|d| canonical.starts_with(d)) {
        return Some("lies inside a system tree (/etc, /proc, /sys, /dev, /run, /boot, /root)");
    }
    if canonical.parent() == Some(Path::new("/home")) {
        return Some("is a home directory");
    }
    None
}

/// Checks a scene or data directory at start-up and returns it canonical: it must exist, be a
/// directory, and not be the root or a system directory ([`system_dir_rule`]). `field` names
/// the setting in the message.
///
/// # Errors
/// [`ServerError::Config`] naming the setting, the directory and the rule.
pub fn check_root(field: &str, dir: &Path) -> Result<PathBuf, ServerError> {
    let shown = dir.display();
    let canonical = std::fs::canonicalize(dir).map_err(|e| {
        ServerError::Config(format!(
            "{field} {shown}: cannot be resolved ({}); create it (deploy/install.sh makes the \
             installed ones) or change {field}",
            e.kind()
        ))
    })?;
    if !canonical.is_dir() {
        return Err(ServerError::Config(format!(
            "{field} {shown}: not a directory"
        )));
    }
    if let Some(rule) = system_dir_rule(&canonical) {
        return Err(ServerError::Config(format!(
            "{field} {shown} ({}) {rule}: a client's scene could make the daemon read any file \
             below it. Give the daemon a directory of its own, e.g. /var/lib/hapticd/scenes \
             (docs/security.md)",
            canonical.display()
        )));
    }
    Ok(canonical)
}

impl FileRoots {
    /// Roots from the scene directory (if any) and the data directories (each canonicalized;
    /// one that does not exist allows nothing), with `max_bytes` per file. Without a scene
    /// directory, relative paths are refused and absolute ones must lie in a data directory.
    pub fn new(scene_dir: Option<&Path>, data_dirs: &[PathBuf], max_bytes: u64) -> Self {
        let scene_dir = scene_dir.and_then(|d| std::fs::canonicalize(d).ok());
        let roots = scene_dir
            .iter()
            .cloned()
            .chain(
                data_dirs
                    .iter()
                    .filter_map(|d| std::fs::canonicalize(d).ok()),
            )
            .collect();
        Self {
            scene_dir,
            roots,
            max_bytes,
        }
    }

    fn denied(field: &str) -> ServerError {
        ServerError::PermissionDenied(format!(
            "`{field}`: a scene sent by a client may only name files inside the daemon's scene \
             directory or its data directories (scene_dir, data_dirs)"
        ))
    }

    /// Checks that `file` (a scene field's value) names an allowed regular file.
    ///
    /// # Errors
    /// [`ServerError::PermissionDenied`] outside the allowed directories (lexically or through
    /// a symlink); [`ServerError::InvalidArgument`] for a missing file inside them, a file that
    /// is not a regular file, or one above the size limit.
    pub fn check_file(&self, field: &str, file: &str) -> Result<PathBuf, ServerError> {
        self.resolve(field, file)?.ok_or_else(|| {
            ServerError::InvalidArgument(format!(
                "`{field}`: no such file in the allowed directories"
            ))
        })
    }

    /// [`FileRoots::check_file`] with a missing file inside the allowed directories as
    /// `Ok(None)`.
    fn resolve(&self, field: &str, file: &str) -> Result<Option<PathBuf>, ServerError> {
        if file.contains('\0') {
            return Err(ServerError::InvalidArgument(format!(
                "`{field}`: a path may not contain NUL"
            )));
        }
        // Without a scene directory only absolute paths (into a data directory) can be allowed.
        let root = Path::new("/");
        let scene_dir = match &self.scene_dir {
            Some(d) => d.as_path(),
            None if Path::new(file).is_absolute() => root,
            None => return Err(Self::denied(field)),
        };
        let path = lexical_join(scene_dir, Path::new(file));
        if !self.roots.iter().any(|r| path.starts_with(r)) {
            return Err(Self::denied(field));
        }
        // What the model will open is the plain join, resolved by the OS (a symlinked
        // directory followed by `..` goes elsewhere than the lexical path): check that one.
        let canonical = match std::fs::canonicalize(scene_dir.join(file)) {
            Ok(c) => c,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => {
                return Err(ServerError::InvalidArgument(format!(
                    "`{field}`: cannot be resolved ({})",
                    e.kind()
                )));
            }
        };
        if !self.roots.iter().any(|r| canonical.starts_with(r)) {
            return Err(Self::denied(field));
        }
        let meta = std::fs::metadata(&canonical).map_err(|e| {
            ServerError::InvalidArgument(format!("`{field}`: cannot be read ({})", e.kind()))
        })?;
        if !meta.is_file() {
            return Err(ServerError::InvalidArgument(format!(
                "`{field}`: not a regular file (pipes, devices and directories are refused)"
            )));
        }
        if meta.len() > self.max_bytes {
            return Err(ServerError::InvalidArgument(format!(
                "`{field}`: the file is {} bytes; the limit is {} (max_file_bytes)",
                meta.len(),
                self.max_bytes
            )));
        }
        Ok(Some(canonical))
    }

    /// Checks every file a scene text would make the model read (see the module docs). Text
    /// that is not valid TOML passes: the model's parser reports it.
    ///
    /// # Errors
    /// As [`FileRoots::check_file`], naming the field.
    pub fn check_scene(&self, text: &str) -> Result<(), ServerError> {
        let Ok(value) = text.parse::<toml::Table>() else {
            return Ok(());
        };
        let get = |section: &str, key: &str| -> Option<&toml::Value> {
            value.get(section)?.as_table()?.get(key)
        };
        let as_path = |field: &str, v: &toml::Value| -> Result<String, ServerError> {
            v.as_str().map(str::to_owned).ok_or_else(|| {
                ServerError::InvalidArgument(format!("`{field}` must be a string path"))
            })
        };
        if let Some(v) = get("mesh", "file") {
            self.check_file("mesh.file", &as_path("mesh.file", v)?)?;
        }
        let springs = value
            .get("model")
            .and_then(|m| m.get("family"))
            .and_then(toml::Value::as_str)
            == Some("mass-spring");
        match get("mass_spring", "calibration_file") {
            Some(v) => {
                let f = as_path("mass_spring.calibration_file", v)?;
                self.check_calibration("mass_spring.calibration_file", &f)?;
            }
            None if springs => {
                // The default table name follows the scene name.
                let name = value
                    .get("name")
                    .and_then(toml::Value::as_str)
                    .unwrap_or("custom");
                self.check_calibration("name", &format!("{name}.calibration.csv"))?;
            }
            None => {}
        }
        // The organ calibration's files (a reference, and its table by default after the
        // scene name).
        if let Some(v) = get("mass_spring", "reference_file") {
            let f = as_path("mass_spring.reference_file", v)?;
            self.check_calibration("mass_spring.reference_file", &f)?;
            match get("mass_spring", "organ_file") {
                Some(v) => {
                    let f = as_path("mass_spring.organ_file", v)?;
                    self.check_calibration("mass_spring.organ_file", &f)?;
                }
                None => {
                    let name = value
                        .get("name")
                        .and_then(toml::Value::as_str)
                        .unwrap_or("custom");
                    self.check_calibration("name", &format!("{name}.organ.csv"))?;
                }
            }
        }
        Ok(())
    }

    /// Refuses a generated mesh whose parameters promise far more than `max_elements`
    /// elements before it is generated (a box of `mesh.cells` makes 6 tetrahedra per cell; the
    /// LV generator lands within about 30 % of `mesh.target_tets`). The exact counts are
    /// checked again after the mesh is built ([`check_counts`]).
    ///
    /// # Errors
    /// [`ServerError::InvalidArgument`] naming the field and the limit.
    pub fn check_generated_size(text: &str, max_elements: usize) -> Result<(), ServerError> {
        let Ok(value) = text.parse::<toml::Table>() else {
            return Ok(());
        };
        let Some(mesh) = value.get("mesh").and_then(toml::Value::as_table) else {
            return Ok(());
        };
        let estimate = if let Some(cells) = mesh.get("cells").and_then(toml::Value::as_array) {
            Some((
                "mesh.cells",
                cells
                    .iter()
                    .map(|c| c.as_integer().unwrap_or(1).max(1) as u128)
                    .product::<u128>()
                    * 6,
            ))
        } else {
            mesh.get("target_tets")
                .and_then(toml::Value::as_integer)
                .map(|t| ("mesh.target_tets", t.max(0) as u128))
        };
        match estimate {
            Some((field, n)) if n > (max_elements as u128).saturating_mul(13) / 10 => {
                Err(ServerError::InvalidArgument(format!(
                    "`{field}` asks for about {n} elements; this daemon takes at most \
                     {max_elements} per client scene (max_elements)"
                )))
            }
            _ => Ok(()),
        }
    }

    /// A calibration table may be missing (the scene then explains how to compute it), but
    /// never outside the allowed directories or a special file.
    fn check_calibration(&self, field: &str, file: &str) -> Result<(), ServerError> {
        self.resolve(field, file).map(|_| ())
    }
}

/// Refuses a built scene above the element or node limit (before its simulation is built).
///
/// # Errors
/// [`ServerError::InvalidArgument`] with the counts and the limit.
pub fn check_counts(
    nodes: usize,
    elements: usize,
    max_nodes: usize,
    max_elements: usize,
) -> Result<(), ServerError> {
    if elements > max_elements || nodes > max_nodes {
        return Err(ServerError::InvalidArgument(format!(
            "the scene has {nodes} nodes and {elements} elements; this daemon takes at most \
             {max_nodes} nodes and {max_elements} elements per client scene (max_nodes, \
             max_elements)"
        )));
    }
    Ok(())
}

/// Refuses a hybrid scene whose particle layer would be too large, before it is sampled:
/// the estimate is `volume_m3 / spacing_m^3` (the mesh's whole volume, an upper bound of the
/// layer's), checked against `max_particles`.
///
/// # Errors
/// [`ServerError::InvalidArgument`] naming `hybrid.spacing_m`, the estimate and the limit.
pub fn check_particles(
    volume_m3: f64,
    spacing_m: f64,
    max_particles: usize,
) -> Result<(), ServerError> {
    let estimate = volume_m3 / spacing_m.powi(3);
    if estimate.is_nan() || estimate > max_particles as f64 {
        return Err(ServerError::InvalidArgument(format!(
            "`hybrid.spacing_m` = {spacing_m} m gives about {estimate:.0} particles in this \
             mesh's volume; this daemon takes at most {max_particles} per client scene \
             (max_particles)"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lexical_join_applies_dots_without_the_file_system() {
        let b = Path::new("/srv/scenes");
        assert_eq!(
            lexical_join(b, Path::new("a/../b.msh")),
            PathBuf::from("/srv/scenes/b.msh")
        );
        assert_eq!(
            lexical_join(b, Path::new("../../../etc/passwd")),
            PathBuf::from("/etc/passwd")
        );
        assert_eq!(
            lexical_join(b, Path::new("/etc/shadow")),
            PathBuf::from("/etc/shadow")
        );
        assert_eq!(
            lexical_join(b, Path::new("./x/./y")),
            PathBuf::from("/srv/scenes/x/y")
        );
    }
}
