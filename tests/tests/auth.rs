//! Who may do what (issue 16, section 3), over loopback against the server library: tokens
//! with roles, ownership of sessions, the tokens file made at first start, the limit on failed
//! attempts, and TLS with and without client certificates. The clients use the same
//! credentials code as the binaries (`haptic_cli::credentials`).

use crate::common;

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use common::InProcess;
use haptic_cli::credentials::{AuthChannel, ClientCredentials};
use haptic_server::ServerConfig;
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use haptics_proto::v1::*;
use tonic::Code;

/// A fresh directory under the target's temporary space.
fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("haptic-auth-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// Writes `text` with mode 0600.
fn write_private(path: &Path, text: &str) {
    std::fs::write(path, text).expect("write");
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
}

/// Tokens of the hand-written file: `(name, role, token)`.
const TOKENS: [(&str, &str, &str); 5] = [
    ("root", "admin", "admin-0123456789abcdef"),
    ("alice", "control", "alice-0123456789abcdef"),
    ("bob", "control", "bob-0123456789abcdef"),
    ("screen", "viewer", "viewer-0123456789abcdef"),
    ("arm", "device", "device-0123456789abcdef"),
];

/// The tokens file and one token file per entry, in `dir`.
fn write_tokens(dir: &Path) -> PathBuf {
    let mut text = String::new();
    for (name, role, token) in TOKENS {
        text.push_str(&format!(
            "[[token]]\nname = \"{name}\"\nrole = \"{role}\"\ntoken = \"{token}\"\n"
        ));
        write_private(&dir.join(format!("{name}.token")), &format!("{token}\n"));
    }
    let path = dir.join("tokens.toml");
    write_private(&path, &text);
    path
}

/// A channel to `url` with `credentials`, the binaries' way.
async fn channel(url: &str, credentials: &ClientCredentials) -> Result<AuthChannel> {
    let token = credentials.interceptor()?;
    let channel = credentials
        .endpoint(url)?
        .connect_timeout(Duration::from_secs(5))
        .connect()
        .await
        .with_context(|| format!("connecting to {url}"))?;
    Ok(token.wrap(channel))
}

fn with_token_file(path: PathBuf) -> ClientCredentials {
    ClientCredentials {
        token_file: Some(path),
        ..Default::default()
    }
}

async fn control(url: &str, token_file: Option<PathBuf>) -> SessionControlClient<AuthChannel> {
    let creds = token_file.map(with_token_file).unwrap_or_default();
    SessionControlClient::new(channel(url, &creds).await.expect("channel"))
}

fn code<T: std::fmt::Debug>(r: Result<tonic::Response<T>, tonic::Status>) -> Code {
    match r {
        Ok(_) => Code::Ok,
        Err(s) => s.code(),
    }
}

fn stats(id: &str) -> GetStatsRequest {
    GetStatsRequest {
        session_id: id.into(),
    }
}

fn stop(id: &str) -> StopSessionRequest {
    StopSessionRequest {
        session_id: id.into(),
    }
}

fn push(id: &str) -> ApplyForceRequest {
    ApplyForceRequest {
        session_id: id.into(),
        point_m: Some(Vec3::new(0.0, 0.0, 0.02)),
        force_n: Some(Vec3::new(0.0, 0.0, -0.01)),
        duration_s: 0.05,
    }
}

fn watch(id: &str) -> WatchRequest {
    WatchRequest {
        session_id: id.into(),
        max_rate_hz: 30.0,
        ..Default::default()
    }
}

/// Opens a device stream whose first sample names `id`.
async fn device_link(url: &str, token_file: PathBuf, id: &str) -> Code {
    let ch = channel(url, &with_token_file(token_file))
        .await
        .expect("channel");
    let first = DeviceSample {
        session_id: id.into(),
        seq: 1,
        position_m: Some(Vec3::new(0.0, 0.0, 0.2)),
        ..Default::default()
    };
    code(
        DeviceLinkClient::new(ch)
            .connect(tokio_stream::iter([first]))
            .await,
    )
}

#[tokio::test]
async fn roles_and_session_ownership() -> Result<()> {
    let _serial = haptic_e2e::serial().await;
    let dir = temp_dir("roles");
    let server = InProcess::start_with(ServerConfig {
        tokens_file: Some(write_tokens(&dir)),
        ..Default::default()
    })
    .await?;
    let url = server.url.as_str();
    let tf = |name: &str| Some(dir.join(format!("{name}.token")));

    // No token, a wrong token: UNAUTHENTICATED, before anything else is looked at.
    let e = control(url, None)
        .await
        .list_scenes(ListScenesRequest {})
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");
    assert!(e.message().contains("no token"), "{e:?}");
    write_private(&dir.join("wrong.token"), "wrong-0123456789abcdef\n");
    let e = control(url, tf("wrong"))
        .await
        .list_sessions(ListSessionsRequest {})
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");
    assert!(e.message().contains("unknown token"), "{e:?}");
    // Health answers without a token (load balancers and systemd probes have none).
    let mut health = tonic_health::pb::health_client::HealthClient::new(
        channel(url, &ClientCredentials::default()).await?,
    );
    let h = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "haptics.v1.SessionControl".into(),
        })
        .await?;
    assert_eq!(h.into_inner().status, 1, "SERVING");

    let (mut alice, mut bob) = (
        control(url, tf("alice")).await,
        control(url, tf("bob")).await,
    );
    let (mut viewer, mut device) = (
        control(url, tf("screen")).await,
        control(url, tf("arm")).await,
    );
    let mut admin = control(url, tf("root")).await;
    let start = || StartSessionRequest {
        scene: "hemisphere-springs".into(),
        scene_toml: String::new(),
    };
    // Only control and admin start sessions.
    assert_eq!(
        code(viewer.start_session(start()).await),
        Code::PermissionDenied
    );
    assert_eq!(
        code(device.start_session(start()).await),
        Code::PermissionDenied
    );
    let id = alice.start_session(start()).await?.into_inner().session_id;

    // Every role lists the scenes.
    for c in [&mut alice, &mut bob, &mut viewer, &mut device] {
        assert_eq!(code(c.list_scenes(ListScenesRequest {}).await), Code::Ok);
    }
    // The owner does everything with its session; the viewer watches and reads; another
    // control token sees nothing of it; the device only connects.
    assert_eq!(code(alice.get_stats(stats(&id)).await), Code::Ok);
    assert_eq!(code(alice.apply_force(push(&id)).await), Code::Ok);
    let listed = |c: &mut SessionControlClient<AuthChannel>| {
        let mut c = c.clone();
        async move {
            c.list_sessions(ListSessionsRequest {})
                .await
                .map(|r| r.into_inner().session_ids)
        }
    };
    assert_eq!(listed(&mut alice).await?, vec![id.clone()]);
    assert_eq!(listed(&mut viewer).await?, vec![id.clone()]);
    assert!(
        listed(&mut bob).await?.is_empty(),
        "bob sees alice's session"
    );
    assert_eq!(code(viewer.get_stats(stats(&id)).await), Code::Ok);
    assert_eq!(
        code(viewer.apply_force(push(&id)).await),
        Code::PermissionDenied
    );
    assert_eq!(
        code(viewer.stop_session(stop(&id)).await),
        Code::PermissionDenied
    );
    for r in [
        code(bob.get_stats(stats(&id)).await),
        code(bob.apply_force(push(&id)).await),
        code(bob.stop_session(stop(&id)).await),
    ] {
        assert_eq!(r, Code::PermissionDenied);
    }
    assert_eq!(
        code(device.get_stats(stats(&id)).await),
        Code::PermissionDenied
    );
    assert_eq!(
        code(device.list_sessions(ListSessionsRequest {}).await),
        Code::PermissionDenied
    );

    // Surface streams: the viewer and the owner, not another control token or the device.
    let watch_code = |name: &'static str| {
        let (url, path, id) = (
            url.to_owned(),
            dir.join(format!("{name}.token")),
            id.clone(),
        );
        async move {
            let ch = channel(&url, &with_token_file(path))
                .await
                .expect("channel");
            code(SurfaceStreamClient::new(ch).watch(watch(&id)).await)
        }
    };
    assert_eq!(watch_code("screen").await, Code::Ok);
    assert_eq!(watch_code("alice").await, Code::Ok);
    assert_eq!(watch_code("bob").await, Code::PermissionDenied);
    assert_eq!(watch_code("arm").await, Code::PermissionDenied);

    // Device streams: the device role (and admin), nobody else.
    assert_eq!(device_link(url, dir.join("arm.token"), &id).await, Code::Ok);
    assert_eq!(
        device_link(url, dir.join("screen.token"), &id).await,
        Code::PermissionDenied
    );
    assert_eq!(
        device_link(url, dir.join("alice.token"), &id).await,
        Code::PermissionDenied
    );

    // Admin stops anyone's session; the owner's rights end with it.
    assert_eq!(code(admin.stop_session(stop(&id)).await), Code::Ok);
    assert_eq!(
        code(alice.get_stats(stats(&id)).await),
        Code::PermissionDenied
    );
    server.shutdown().await
}

#[tokio::test]
async fn tokens_file_is_created_at_first_start_and_guarded() -> Result<()> {
    let _serial = haptic_e2e::serial().await;
    let dir = temp_dir("first-start");
    let tokens = dir.join("tokens.toml");
    let server = InProcess::start_with(ServerConfig {
        tokens_file: Some(tokens.clone()),
        ..Default::default()
    })
    .await?;
    let url = server.url.as_str();
    // The server writes its files before it answers; wait for the first answer.
    let mut admin = None;
    for _ in 0..100 {
        if dir.join("viewer.token").exists() {
            admin = Some(control(url, Some(dir.join("admin.token"))).await);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut admin = admin.context("the role token files were not written")?;
    let mut seen = std::collections::HashSet::new();
    for f in [
        "tokens.toml",
        "admin.token",
        "control.token",
        "device.token",
        "viewer.token",
    ] {
        let meta = std::fs::metadata(dir.join(f))?;
        assert_eq!(meta.permissions().mode() & 0o777, 0o600, "{f}");
        if f.ends_with(".token") {
            let t = std::fs::read_to_string(dir.join(f))?.trim().to_owned();
            assert_eq!(t.len(), 64, "{f}: 256 bits as hex");
            assert!(t.bytes().all(|b| b.is_ascii_hexdigit()), "{f}");
            assert!(seen.insert(t), "{f}: a token repeats");
        }
    }
    assert_eq!(
        code(admin.list_sessions(ListSessionsRequest {}).await),
        Code::Ok
    );
    let mut viewer = control(url, Some(dir.join("viewer.token"))).await;
    let start = StartSessionRequest {
        scene: "hemisphere-springs".into(),
        scene_toml: String::new(),
    };
    assert_eq!(
        code(viewer.start_session(start.clone()).await),
        Code::PermissionDenied
    );
    let mut ctl = control(url, Some(dir.join("control.token"))).await;
    let id = ctl.start_session(start).await?.into_inner().session_id;
    assert_eq!(code(ctl.stop_session(stop(&id)).await), Code::Ok);
    server.shutdown().await?;

    // A tokens file others can read is refused, with the rule and without its contents.
    std::fs::set_permissions(&tokens, std::fs::Permissions::from_mode(0o644))?;
    let e = haptic_server::auth::TokenStore::load(&tokens)
        .unwrap_err()
        .to_string();
    assert!(e.contains("chmod 600"), "{e}");
    Ok(())
}

#[tokio::test]
async fn failed_attempts_are_limited_per_address_and_never_lock_out_valid_tokens() -> Result<()> {
    let _serial = haptic_e2e::serial().await;
    let dir = temp_dir("failures");
    let window = Duration::from_millis(1500);
    let server = InProcess::start_with(ServerConfig {
        tokens_file: Some(write_tokens(&dir)),
        auth_limits: haptic_server::auth::FailureLimits {
            max_failures: 3,
            window,
        },
        ..Default::default()
    })
    .await?;
    let url = server.url.as_str();
    write_private(&dir.join("guess.token"), "guess-0123456789abcdef\n");
    let mut guesser = control(url, Some(dir.join("guess.token"))).await;
    let mut viewer = control(url, Some(dir.join("screen.token"))).await;
    for _ in 0..3 {
        let e = guesser
            .list_sessions(ListSessionsRequest {})
            .await
            .unwrap_err();
        assert!(e.message().contains("unknown token"), "{e:?}");
    }
    // Past the limit the guesser's failures say so; a right token from the same address still
    // passes (issue 47: every local client shares 127.0.0.1).
    let e = guesser
        .list_sessions(ListSessionsRequest {})
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    assert!(e.message().contains("too many failed attempts"), "{e:?}");
    assert_eq!(
        code(viewer.list_sessions(ListSessionsRequest {}).await),
        Code::Ok
    );
    let mut anonymous = control(url, None).await;
    let e = anonymous
        .list_sessions(ListSessionsRequest {})
        .await
        .unwrap_err();
    assert!(
        e.message().contains("no token") && e.message().contains("too many"),
        "{e:?}"
    );
    assert_eq!(
        code(viewer.list_sessions(ListSessionsRequest {}).await),
        Code::Ok
    );
    // The window ends: failures are counted (and logged) afresh.
    tokio::time::sleep(window + Duration::from_millis(100)).await;
    let e = guesser
        .list_sessions(ListSessionsRequest {})
        .await
        .unwrap_err();
    assert!(!e.message().contains("too many"), "{e:?}");
    server.shutdown().await
}

/// A CA, a daemon certificate for `localhost` and a client certificate, as PEM files in `dir`:
/// `ca.pem`, `server.pem`, `server.key`, `client.pem`, `client.key`.
fn make_certificates(dir: &Path) -> Result<()> {
    use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
    let mut ca_params = CertificateParams::new(Vec::<String>::new())?;
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca = CertifiedIssuer::self_signed(ca_params, KeyPair::generate()?)?;
    std::fs::write(dir.join("ca.pem"), ca.pem())?;
    for (name, san) in [("server", "localhost"), ("client", "lab-bridge")] {
        let key = KeyPair::generate()?;
        let cert = CertificateParams::new(vec![san.to_owned()])?.signed_by(&key, &ca)?;
        std::fs::write(dir.join(format!("{name}.pem")), cert.pem())?;
        write_private(&dir.join(format!("{name}.key")), &key.serialize_pem());
    }
    Ok(())
}

#[tokio::test]
async fn tls_with_and_without_client_certificates() -> Result<()> {
    let _serial = haptic_e2e::serial().await;
    let dir = temp_dir("tls");
    make_certificates(&dir)?;
    let files = |client_ca: bool| haptic_server::config::TlsFiles {
        cert_file: dir.join("server.pem"),
        key_file: dir.join("server.key"),
        client_ca_file: client_ca.then(|| dir.join("ca.pem")),
    };
    let ca_only = ClientCredentials {
        tls_ca: Some(dir.join("ca.pem")),
        ..Default::default()
    };
    let with_cert = ClientCredentials {
        tls_cert: Some(dir.join("client.pem")),
        tls_key: Some(dir.join("client.key")),
        ..ca_only.clone()
    };
    let list = |url: String, creds: ClientCredentials| async move {
        let ch = channel(&url, &creds).await?;
        SessionControlClient::new(ch)
            .list_scenes(ListScenesRequest {})
            .await
            .map_err(anyhow::Error::from)
    };

    // Server certificate only: a client that trusts the CA gets in; plain HTTP/2 does not.
    let server = InProcess::start_with(ServerConfig {
        tls: Some(files(false)),
        ..Default::default()
    })
    .await?;
    assert!(list(server.url.clone(), ca_only.clone()).await.is_ok());
    let plain = server.url.replace("https://localhost", "http://127.0.0.1");
    assert!(list(plain, ClientCredentials::default()).await.is_err());
    server.shutdown().await?;

    // Client certificates required: the CA-signed client gets in, the one without is refused.
    let server = InProcess::start_with(ServerConfig {
        tls: Some(files(true)),
        ..Default::default()
    })
    .await?;
    assert!(list(server.url.clone(), with_cert).await.is_ok());
    assert!(list(server.url.clone(), ca_only).await.is_err());
    server.shutdown().await
}
