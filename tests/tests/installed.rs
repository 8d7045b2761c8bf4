//! The daemon as installed (issue 47, section 1): `deploy/install.sh` into a staging root, the
//! directories systemd makes for the unit (`StateDirectory=`), the shipped configuration and
//! the unit's `ExecStart=` run as the unit runs them: working directory `/`. Only what a test
//! must change is redirected, each explicitly: the staging root is prefixed to the unit's and
//! the configuration's absolute paths, the configuration's `scene_dir` is written relative to
//! the file (so the daemon finds it only if relative paths resolve against the configuration's
//! directory, not against `/`), and the port is 0.
//!
//! A client then names `/etc/passwd`, `/proc/self/environ`, `/etc/hostname`, a `..` escape,
//! symlinks out of the scene directory, and copies of those files inside it (where the Gmsh
//! reader and the calibration table reader parse them): each is refused, and no refusal
//! quotes a line of those files. A mesh inside the scene directory still runs. The daemon
//! refuses to start with `/` or a system directory as its scene directory, and its log (to a
//! pipe, as to the journal) has no colour codes.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, ensure};
use haptic_cli::credentials::ClientCredentials;
use haptic_e2e::{Daemon, HAPTICD, STEP_TIMEOUT, binary, serial, unique_temp_dir, wait_timeout};
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::{StartSessionRequest, StopSessionRequest};
use tonic::Code;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("repository root")
        .to_path_buf()
}

/// `value` of the unit's `key=` line.
fn unit_value<'a>(unit: &'a str, key: &str) -> Result<&'a str> {
    unit.lines()
        .find_map(|l| l.strip_prefix(&format!("{key}=")))
        .with_context(|| format!("the unit has no {key}="))
}

/// Runs `deploy/install.sh` into `root` with the harness's binaries; returns the unit text.
fn install(root: &Path) -> Result<String> {
    let bin_dir = binary(HAPTICD)?
        .parent()
        .context("binary directory")?
        .to_path_buf();
    let out = Command::new("bash")
        .arg(repo().join("deploy/install.sh"))
        .env("DESTDIR", root)
        .env("BIN_DIR", &bin_dir)
        .output()?;
    ensure!(
        out.status.success(),
        "install.sh failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    for f in [
        "usr/local/bin/hapticd",
        "usr/local/bin/hapticctl",
        "etc/hapticd/hapticd.toml",
        "etc/systemd/system/hapticd.service",
    ] {
        ensure!(root.join(f).is_file(), "install.sh did not install /{f}");
    }
    ensure!(root.join("usr/local/share/hapticd/meshes").is_dir());
    let unit = std::fs::read_to_string(root.join("etc/systemd/system/hapticd.service"))?;
    // The unit's documentation is installed.
    for doc in unit_value(&unit, "Documentation")?.split_whitespace() {
        let path = doc.strip_prefix("file://").context("a file:// URL")?;
        ensure!(
            root.join(path.trim_start_matches('/')).is_file(),
            "Documentation={doc} is not installed"
        );
    }
    // What systemd makes at start (StateDirectory= is relative to /var/lib).
    for dir in unit_value(&unit, "StateDirectory")?.split_whitespace() {
        std::fs::create_dir_all(root.join("var/lib").join(dir))?;
    }
    // CacheDirectory= is relative to /var/cache.
    for dir in unit_value(&unit, "CacheDirectory")?.split_whitespace() {
        std::fs::create_dir_all(root.join("var/cache").join(dir))?;
    }
    ensure!(unit_value(&unit, "WorkingDirectory")? == "/");
    Ok(unit)
}

/// The installed configuration with the staging root in front of its directories, and
/// `scene_dir` relative to the file's directory (`ROOT/etc/hapticd`).
fn redirect_config(root: &Path) -> Result<()> {
    let path = root.join("etc/hapticd/hapticd.toml");
    let text = std::fs::read_to_string(&path)?;
    let shipped_scene = "scene_dir = \"/var/lib/hapticd/scenes\"";
    let shipped_data = "data_dirs = [\"/usr/local/share/hapticd/meshes\"]";
    ensure!(
        text.matches(shipped_scene).count() == 1,
        "{shipped_scene} not shipped"
    );
    ensure!(
        text.matches(shipped_data).count() == 1,
        "{shipped_data} not shipped"
    );
    let text = text
        .replace(
            shipped_scene,
            "scene_dir = \"../../var/lib/hapticd/scenes\"",
        )
        .replace(
            shipped_data,
            &format!(
                "data_dirs = [\"{}\"]",
                root.join("usr/local/share/hapticd/meshes").display()
            ),
        );
    std::fs::write(&path, text)?;
    Ok(())
}

/// The unit's `ExecStart=` arguments with the staging root in front of absolute paths.
fn exec_start(unit: &str, root: &Path) -> Result<(PathBuf, Vec<String>)> {
    let mut words = unit_value(unit, "ExecStart")?.split_whitespace().map(|w| {
        if w.starts_with('/') {
            root.join(w.trim_start_matches('/')).display().to_string()
        } else {
            w.to_string()
        }
    });
    let exe = PathBuf::from(words.next().context("empty ExecStart=")?);
    Ok((exe, words.collect()))
}

fn mesh_scene(file: &str) -> String {
    format!(
        "[mesh]\nfile = {file:?}\nlength_unit = \"mm\"\n[material]\nyoungs_modulus_pa = 14500.0\n\
         poisson_ratio = 0.45\ndensity_kg_per_m3 = 1060.0\n[boundary]\nclamped = [\"BASE\"]\n\
         touchable = [\"EPI\"]\n"
    )
}

/// The shipped mass-spring scene reading its calibration table from `table`.
fn springs_scene(table: &str) -> Result<String> {
    let text = std::fs::read_to_string(repo().join("deploy/scenes/hemisphere-springs.toml"))?;
    let line = "calibration_file = \"hemisphere-springs.calibration.csv\"";
    ensure!(text.contains(line), "the shipped scene changed");
    // Without its organ keys: their files are not in the daemon's scene directory.
    let text: String = text
        .lines()
        .filter(|l| {
            !["reference_file", "reference_axis", "organ_file"]
                .iter()
                .any(|k| l.starts_with(k))
        })
        .map(|l| format!("{l}\n"))
        .collect();
    Ok(text.replace(line, &format!("calibration_file = {table:?}")))
}

/// The lines (NUL- or newline-separated) of a file worth looking for in a message.
fn lines_of(path: &Path) -> Vec<String> {
    std::fs::read(path)
        .map(|b| {
            String::from_utf8_lossy(&b)
                .split(['\n', '\0'])
                .map(str::trim)
                .filter(|l| l.len() >= 8)
                .map(str::to_string)
                .collect()
        })
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_installed_daemon_reads_and_quotes_no_host_file() -> Result<()> {
    let _serial = serial().await;
    let root = unique_temp_dir("haptic-installed")?;
    let unit = install(&root)?;
    redirect_config(&root)?;
    let (exe, args) = exec_start(&unit, &root)?;
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let daemon = Daemon::spawn_in(&exe, &args, Some(Path::new("/")))?;
    let scenes = root.join("var/lib/hapticd/scenes");

    // Files inside the scene directory: symlinks out, and copies of host files.
    let environ = PathBuf::from(format!("/proc/{}/environ", daemon.pid()));
    std::os::unix::fs::symlink("/etc/passwd", scenes.join("passwd-link.msh"))?;
    std::os::unix::fs::symlink(&environ, scenes.join("environ-link.msh"))?;
    std::os::unix::fs::symlink("/etc", scenes.join("etc"))?;
    for (from, to) in [
        (Path::new("/etc/passwd"), "passwd.msh"),
        (Path::new("/etc/hostname"), "hostname.msh"),
        (environ.as_path(), "environ.msh"),
        (Path::new("/etc/passwd"), "passwd.calibration.csv"),
    ] {
        if let Ok(bytes) = std::fs::read(from) {
            std::fs::write(scenes.join(to), bytes)?;
        }
    }
    let secrets: Vec<String> = [
        Path::new("/etc/passwd"),
        Path::new("/etc/hostname"),
        &environ,
    ]
    .iter()
    .flat_map(|p| lines_of(p))
    .collect();
    ensure!(!secrets.is_empty(), "nothing to look for");

    let control = root.join("var/lib/hapticd/control.token");
    let creds = ClientCredentials {
        token_file: Some(control),
        ..Default::default()
    };
    let channel = creds.endpoint(&daemon.url())?.connect().await?;
    let mut ctl = SessionControlClient::new(creds.interceptor()?.wrap(channel));
    let start = |scene_toml: String| {
        let mut ctl = ctl.clone();
        async move {
            ctl.start_session(StartSessionRequest {
                scene: String::new(),
                scene_toml,
            })
            .await
        }
    };

    // Outside: one message whether the file exists or not.
    let nowhere = start(mesh_scene("/no/such/file.msh")).await.unwrap_err();
    assert_eq!(nowhere.code(), Code::PermissionDenied, "{nowhere:?}");
    let mut refusals = Vec::new();
    for name in [
        "/etc/passwd",
        "/proc/self/environ",
        "/etc/hostname",
        "../../../../../../../../etc/passwd",
        "passwd-link.msh",
        "environ-link.msh",
        "etc/passwd",
        "etc/../etc/hostname",
    ] {
        let e = start(mesh_scene(name)).await.unwrap_err();
        assert_eq!(e.code(), Code::PermissionDenied, "{name}: {e:?}");
        assert_eq!(e.message(), nowhere.message(), "{name}");
        refusals.push((name.to_string(), e));
    }
    // Inside, but not meshes or tables: parse errors naming the file as written, the line and
    // what was expected.
    for name in ["passwd.msh", "hostname.msh", "environ.msh"] {
        if !scenes.join(name).exists() {
            continue;
        }
        let e = start(mesh_scene(name)).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{name}: {e:?}");
        assert!(
            e.message().starts_with(&format!("mesh {name}: ")) && e.message().contains("line"),
            "{name}: {e:?}"
        );
        refusals.push((name.to_string(), e));
    }
    if scenes.join("passwd.calibration.csv").exists() {
        let e = start(springs_scene("passwd.calibration.csv")?)
            .await
            .unwrap_err();
        assert!(
            e.message()
                .contains("calibration table passwd.calibration.csv"),
            "{e:?}"
        );
        refusals.push(("passwd.calibration.csv".into(), e));
    }
    for (name, e) in &refusals {
        for line in &secrets {
            assert!(
                !e.message().contains(line.as_str()),
                "{name}: the refusal quotes {line:?}: {}",
                e.message()
            );
        }
    }

    // A mesh in the scene directory runs, named relative to it.
    std::fs::copy(
        repo().join("../shared/data/lv/lv_h3.msh"),
        scenes.join("lv_h3.msh"),
    )?;
    let id = start(mesh_scene("lv_h3.msh"))
        .await
        .context("a mesh inside the scene directory")?
        .into_inner()
        .session_id;
    ctl.stop_session(StopSessionRequest { session_id: id })
        .await?;

    // The log went to a pipe, as to the journal: no colour codes.
    let log = daemon.log_tail();
    assert!(log.contains("listening") || log.contains("token"), "{log}");
    assert!(!log.contains('\u{1b}'), "ANSI codes in the log:\n{log}");
    drop(daemon);

    // The root or a system directory as scene directory: refused at start, saying why.
    for dir in ["/", "/etc", "/usr", "/var", "/home"] {
        if !Path::new(dir).is_dir() {
            continue;
        }
        let mut child = Command::new(&exe)
            .args([
                "--config",
                &root.join("etc/hapticd/hapticd.toml").display().to_string(),
            ])
            .args(["--listen", "127.0.0.1:0", "--scene-dir", dir])
            .current_dir("/")
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()?;
        let status = wait_timeout(&mut child, STEP_TIMEOUT)?.context("still running")?;
        let out = child.wait_with_output()?;
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!status.success(), "{dir} accepted");
        assert!(
            stderr.contains("scene_dir") && stderr.contains("system directory"),
            "{dir}: {stderr}"
        );
        assert!(
            !String::from_utf8_lossy(&out.stdout).contains("listening on"),
            "{dir}"
        );
    }
    let _ = std::fs::remove_dir_all(&root);
    Ok(())
}
