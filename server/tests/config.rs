//! The shipped configuration parses and validates; layering and bad values are reported.

use std::path::Path;

use haptic_server::config::{ConfigFile, LogFormat, ServerConfig};

#[test]
fn deploy_config_parses_and_matches_the_defaults() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/hapticd.toml");
    let cfg = ConfigFile::load(&path).unwrap().into_config().unwrap();
    // The shipped file documents the defaults: parsing it must give exactly them.
    assert_eq!(cfg, ServerConfig::default());
    assert_eq!(cfg.log_format, LogFormat::Text);
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
