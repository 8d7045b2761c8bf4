//! The shipped configuration parses and validates; layering and bad values are reported.

use std::path::{Path, PathBuf};

use haptic_server::config::{ConfigFile, LogFormat, ServerConfig};

#[test]
fn deploy_config_parses_and_matches_the_defaults() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/hapticd.toml");
    let mut cfg = ConfigFile::load(&path).unwrap().into_config().unwrap();
    // The shipped file names the installed directories (issue 47), absolute, so they do not
    // depend on where the file lies ...
    assert_eq!(
        cfg.scene_dir.take(),
        Some(PathBuf::from("/var/lib/hapticd/scenes"))
    );
    assert_eq!(
        std::mem::take(&mut cfg.data_dirs),
        [PathBuf::from("/usr/local/share/hapticd/meshes")]
    );
    // ... and documents the defaults for everything else: parsing it must give exactly them.
    assert_eq!(cfg, ServerConfig::default());
    assert_eq!(cfg.log_format, LogFormat::Text);
}

#[test]
fn relative_paths_in_the_file_resolve_against_its_directory() {
    let dir = std::env::temp_dir().join(format!("config-relative-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("hapticd.toml");
    std::fs::write(
        &path,
        "scene_dir = \"scenes\"\ndata_dirs = [\"../meshes\", \"/abs/meshes\"]\n\
         state_dir = \"state\"\nregion_cache_dir = \"cache\"\n\
         prepare_regions = [\"scenes/tiled.toml\"]\nprepare_regions_priority = \"normal\"\n[auth]\ntokens_file = \"state/tokens.toml\"\n\
         [tls]\ncert_file = \"tls/s.pem\"\nkey_file = \"tls/s.key\"\n",
    )
    .unwrap();
    // Whatever the working directory: the daemon as installed runs in `/`.
    let cfg = ConfigFile::load(&path).unwrap().into_config().unwrap();
    assert_eq!(cfg.scene_dir, Some(dir.join("scenes")));
    assert_eq!(
        cfg.data_dirs,
        [dir.join("../meshes"), PathBuf::from("/abs/meshes")]
    );
    assert_eq!(cfg.state_dir, Some(dir.join("state")));
    assert_eq!(
        cfg.region_cache,
        Some(haptic_model::integrate::follow::RegionCacheDir {
            dir: dir.join("cache"),
            max_bytes: haptic_model::integrate::follow::DEFAULT_REGION_CACHE_MAX_BYTES,
            memory_bytes: haptic_model::integrate::follow::DEFAULT_REGION_CACHE_MEMORY_BYTES,
        })
    );
    assert_eq!(cfg.prepare_regions, [dir.join("scenes/tiled.toml")]);
    assert_eq!(
        cfg.prepare_regions_priority,
        haptic_server::config::FillPriority::Normal
    );
    // Regions to prepare need a cache to prepare them into; a priority is idle or normal.
    for (text, field) in [
        ("prepare_regions = [\"a.toml\"]", "region_cache_dir"),
        (
            "region_cache_dir = \"c\"\nprepare_regions_priority = \"high\"",
            "expected `idle` or `normal`",
        ),
    ] {
        let e = ConfigFile::parse(text)
            .and_then(ConfigFile::into_config)
            .unwrap_err();
        assert!(e.to_string().contains(field), "{text}: {e}");
    }
    // A cache of no bytes is a mistake, not a way to turn it off (leave the directory unset).
    for key in ["region_cache_max_bytes", "region_cache_memory_bytes"] {
        let zero = ConfigFile::parse(&format!("region_cache_dir = \"c\"\n{key} = 0"))
            .unwrap()
            .into_config()
            .unwrap_err();
        assert!(zero.to_string().contains(key), "{zero}");
        // A limit without the cache it bounds is refused, not ignored.
        let alone = ConfigFile::parse(&format!("{key} = 4096"))
            .unwrap()
            .into_config()
            .unwrap_err();
        assert!(
            alone.to_string().contains(key) && alone.to_string().contains("region_cache_dir"),
            "{alone}"
        );
    }
    let limits = ConfigFile::parse(
        "region_cache_dir = \"c\"\nregion_cache_max_bytes = 3000\nregion_cache_memory_bytes = 2000",
    )
    .unwrap()
    .into_config()
    .unwrap()
    .region_cache
    .unwrap();
    assert_eq!((limits.max_bytes, limits.memory_bytes), (3000, 2000));
    assert_eq!(cfg.tokens_file, Some(dir.join("state/tokens.toml")));
    let tls = cfg.tls.unwrap();
    assert_eq!(
        (tls.cert_file, tls.key_file),
        (dir.join("tls/s.pem"), dir.join("tls/s.key"))
    );
    // Text without a file (and flags) keeps its paths as given: relative to the working
    // directory, like any command-line path.
    let cfg = ConfigFile::parse("scene_dir = \"scenes\"")
        .unwrap()
        .into_config()
        .unwrap();
    assert_eq!(cfg.scene_dir, Some(PathBuf::from("scenes")));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn system_directories_never_serve_client_scenes() {
    let dir = std::env::temp_dir().join(format!("config-system-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("scenes")).unwrap();
    std::os::unix::fs::symlink("/proc/self", dir.join("proc-link")).unwrap();
    let check = |scene: &Path, data: &[&Path]| {
        let mut c = ServerConfig {
            scene_dir: Some(scene.to_path_buf()),
            data_dirs: data.iter().map(|d| d.to_path_buf()).collect(),
            ..ServerConfig::default()
        };
        c.check_directories().map(|()| c).map_err(|e| e.to_string())
    };
    let ok = dir.join("scenes");
    for bad in [
        "/",
        "/etc",
        "/proc",
        "/sys",
        "/dev",
        "/usr",
        "/usr/share",
        "/bin",
        "/boot",
        "/root",
        "/home",
        "/var",
        "/var/lib",
        "/run",
        "/tmp",
        "/etc/ssl",
        "/proc/self",
        "/sys/kernel",
    ] {
        if !Path::new(bad).is_dir() {
            continue; // not on this machine
        }
        let e = check(Path::new(bad), &[]).unwrap_err();
        assert!(e.contains("scene_dir") && e.contains(bad), "{bad}: {e}");
        let e = check(&ok, &[Path::new(bad)]).unwrap_err();
        assert!(e.contains("data_dirs"), "{bad}: {e}");
    }
    // Through a symlink: the resolved directory counts.
    let e = check(&dir.join("proc-link"), &[]).unwrap_err();
    assert!(e.contains("system tree"), "{e}");
    let e = check(&dir.join("missing"), &[]).unwrap_err();
    assert!(e.contains("cannot be resolved"), "{e}");
    // A directory of its own passes, made canonical.
    let c = check(&dir.join("scenes/../scenes"), &[]).unwrap();
    assert_eq!(c.scene_dir, Some(std::fs::canonicalize(&ok).unwrap()));
    // The tokens file (even before it exists), the TLS key and the state directory stay out
    // of what clients may read.
    let mut c = ServerConfig {
        scene_dir: Some(dir.clone()),
        tokens_file: Some(dir.join("scenes/tokens.toml")),
        ..ServerConfig::default()
    };
    let e = c.check_directories().unwrap_err().to_string();
    assert!(
        e.contains("tokens_file") && e.contains("move it out"),
        "{e}"
    );
    let mut c = ServerConfig {
        scene_dir: Some(ok.clone()),
        state_dir: Some(dir.clone()),
        tokens_file: Some(dir.join("tokens.toml")),
        ..ServerConfig::default()
    };
    assert!(c.check_directories().is_ok());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_configuration_is_reported_by_field() {
    let unknown = ConfigFile::parse("listen = \"127.0.0.1:1\"\nlisten_port = 3\n")
        .unwrap_err()
        .to_string();
    assert!(unknown.contains("listen_port"), "{unknown}");
    let bad_addr = ConfigFile::parse("listen = \"nowhere\"")
        .unwrap()
        .into_config()
        .unwrap_err()
        .to_string();
    assert!(bad_addr.contains("listen"), "{bad_addr}");
    let prio = ConfigFile::parse("[servo]\npriority = 0")
        .unwrap()
        .into_config()
        .unwrap_err()
        .to_string();
    assert!(prio.contains("servo.priority"), "{prio}");
    let fmt = ConfigFile::parse("log_format = \"xml\"")
        .unwrap()
        .into_config()
        .unwrap_err()
        .to_string();
    assert!(fmt.contains("log_format"), "{fmt}");
}

#[test]
fn file_values_override_defaults() {
    let cfg = ConfigFile::parse(
        "listen = \"127.0.0.1:0\"\nmax_sessions = 2\n[servo]\ncpu = 1\nrealtime = true",
    )
    .unwrap()
    .into_config()
    .unwrap();
    assert_eq!(cfg.listen.port(), 0);
    assert_eq!(cfg.max_sessions, 2);
    assert_eq!(cfg.servo.cpu, Some(1));
    assert!(cfg.servo.realtime);
}

#[test]
fn build_limits_are_read_and_checked() {
    let cfg = ConfigFile::parse(
        "max_concurrent_builds = 1\nmax_builds_per_client = 3\nmax_sessions_per_client = 5\nbuild_timeout_s = 2.5",
    )
    .unwrap()
    .into_config()
    .unwrap();
    assert_eq!(
        (
            cfg.max_concurrent_builds,
            cfg.max_builds_per_client,
            cfg.max_sessions_per_client
        ),
        (1, 3, 5)
    );
    assert_eq!(cfg.build_timeout, std::time::Duration::from_millis(2500));
    for (text, field) in [
        ("max_concurrent_builds = 0", "max_concurrent_builds"),
        ("max_builds_per_client = 0", "max_builds_per_client"),
        ("max_sessions_per_client = 0", "max_sessions_per_client"),
        ("build_timeout_s = -1.0", "build_timeout_s"),
        ("build_timeout_s = nan", "build_timeout_s"),
    ] {
        let e = ConfigFile::parse(text)
            .unwrap()
            .into_config()
            .unwrap_err()
            .to_string();
        assert!(e.contains(field), "{text}: {e}");
    }
}

#[test]
fn listening_beyond_loopback_needs_tls_and_tokens_or_an_explicit_override() {
    let config = |text: &str| ConfigFile::parse(text).unwrap().into_config();
    let tls = "[tls]\ncert_file = \"c.pem\"\nkey_file = \"k.pem\"\n";
    let tokens = "[auth]\ntokens_file = \"tokens.toml\"\n";
    for text in [
        "listen = \"0.0.0.0:50051\"\n".to_owned(),
        format!("listen = \"0.0.0.0:50051\"\n{tls}"),
        format!("listen = \"[::]:50051\"\n{tokens}"),
    ] {
        let e = config(&text).unwrap_err().to_string();
        assert!(
            e.contains("refusing to listen") && e.contains("allow_insecure_remote"),
            "{e}"
        );
    }
    let both = config(&format!("listen = \"0.0.0.0:50051\"\n{tokens}{tls}")).unwrap();
    assert_eq!(both.tokens_file.as_deref(), Some(Path::new("tokens.toml")));
    assert!(both.tls.is_some());
    let overridden = config("listen = \"0.0.0.0:50051\"\nallow_insecure_remote = true\n").unwrap();
    assert!(overridden.allow_insecure_remote && overridden.tls.is_none());
    // Loopback needs neither.
    assert!(config("listen = \"127.0.0.1:50051\"\n").is_ok());
    let e = config("[auth]\nmax_failures = 0\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("auth.max_failures"), "{e}");
    let e = config("[auth]\nfailure_window_s = -1\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("auth.failure_window_s"), "{e}");
}

#[test]
fn servo_threads_and_cpus_are_read_and_checked() {
    use haptic_server::config::ServoThreads;
    let cfg = ConfigFile::parse("").unwrap().into_config().unwrap();
    assert_eq!(cfg.servo.threads, ServoThreads::Auto);
    assert!(cfg.servo.pinned_cpus().is_empty());
    let cfg = ConfigFile::parse("[servo]\nthreads = 2\ncpus = [2, 3]")
        .unwrap()
        .into_config()
        .unwrap();
    assert_eq!(cfg.servo.threads, ServoThreads::Fixed(2));
    assert_eq!(cfg.servo.pinned_cpus(), [2, 3]);
    let cfg = ConfigFile::parse("[servo]\nthreads = \"auto\"\ncpu = 1")
        .unwrap()
        .into_config()
        .unwrap();
    assert_eq!(cfg.servo.threads, ServoThreads::Auto);
    assert_eq!(
        cfg.servo.pinned_cpus(),
        [1],
        "cpu = N is a one-element list"
    );
    let sixteen = ConfigFile::parse("[servo]\nthreads = 16").unwrap();
    assert_eq!(sixteen.servo.threads, ServoThreads::Fixed(16));
    // Refused at parsing (the TOML error names the key and says what is expected).
    for text in [
        "[servo]\nthreads = 0",
        "[servo]\nthreads = 17",
        "[servo]\nthreads = -1",
        "[servo]\nthreads = \"many\"",
    ] {
        let e = ConfigFile::parse(text).unwrap_err().to_string();
        assert!(
            e.contains("servo.threads") && e.contains("1..=16"),
            "{text}: {e}"
        );
    }
    // Refused at validation.
    for (text, named) in [
        ("[servo]\ncpu = 1\ncpus = [0, 1]", "servo.cpus"),
        ("[servo]\ncpus = [1, 1]", "servo.cpus"),
    ] {
        let e = ConfigFile::parse(text)
            .unwrap()
            .into_config()
            .unwrap_err()
            .to_string();
        assert!(e.contains(named), "{text}: {e}");
    }
    // A value built in code is checked too.
    let mut file = ConfigFile::default();
    file.servo.threads = ServoThreads::Fixed(0);
    let e = file.into_config().unwrap_err().to_string();
    assert!(e.contains("servo.threads = 0"), "{e}");
    // The flag's parser is the key's.
    assert_eq!("auto".parse::<ServoThreads>(), Ok(ServoThreads::Auto));
    assert_eq!("3".parse::<ServoThreads>(), Ok(ServoThreads::Fixed(3)));
    assert!("0".parse::<ServoThreads>().is_err());
}

#[test]
fn the_servo_threads_flag_refuses_what_the_key_refuses() {
    for bad in ["0", "17", "many"] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_hapticd"))
            .args(["--servo-threads", bad, "--listen", "127.0.0.1:0"])
            .output()
            .expect("hapticd runs");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: {err}");
        assert!(
            err.contains("--servo-threads") && err.contains("1..=16"),
            "{bad}: {err}"
        );
    }
}
