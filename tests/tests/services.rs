//! The daemon as a generic gRPC server (health, reflection) and the `hapticctl` CLI round trip,
//! against the real `hapticd` binary on 127.0.0.1:0.

use std::time::Duration;

use anyhow::{Context, Result, ensure};
use haptic_e2e::{CTL, Daemon, STEP_TIMEOUT, channel, run_bin, serial};
use tokio_stream::StreamExt;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
use tonic_reflection::pb::v1::{ServerReflectionRequest, ServerReflectionResponse};

async fn ctl(url: &str, args: &[&str]) -> Result<haptic_e2e::CmdOutput> {
    let mut all = vec!["--server", url];
    all.extend_from_slice(args);
    run_bin(CTL, &all, STEP_TIMEOUT).await
}

async fn reflect(url: &str, req: MessageRequest) -> Result<MessageResponse> {
    let mut client = ServerReflectionClient::new(channel(url).await?);
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(req),
    };
    let mut responses = client
        .server_reflection_info(tokio_stream::iter([request]))
        .await?
        .into_inner();
    let first: ServerReflectionResponse = tokio::time::timeout(STEP_TIMEOUT, responses.next())
        .await
        .context("reflection answer timed out")?
        .context("reflection stream ended without an answer")??;
    first
        .message_response
        .context("reflection answer without a message")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn daemon_prints_listening_and_serves_health_and_reflection() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    assert_eq!(daemon.addr.ip().to_string(), "127.0.0.1");
    assert_ne!(
        daemon.addr.port(),
        0,
        "port 0 must be resolved in the printed address"
    );
    let url = daemon.url();

    let mut health = HealthClient::new(channel(&url).await?);
    for service in [
        "",
        "haptics.v1.SessionControl",
        "haptics.v1.DeviceLink",
        "haptics.v1.SurfaceStream",
    ] {
        let r = health
            .check(HealthCheckRequest {
                service: service.to_string(),
            })
            .await
            .with_context(|| format!("health check {service:?}"))?
            .into_inner();
        assert_eq!(
            r.status,
            ServingStatus::Serving as i32,
            "health of {service:?}"
        );
    }
    let unknown = health
        .check(HealthCheckRequest {
            service: "no.such.Service".into(),
        })
        .await
        .expect_err("an unknown service has no health status");
    assert_eq!(unknown.code(), tonic::Code::NotFound);

    let MessageResponse::ListServicesResponse(list) =
        reflect(&url, MessageRequest::ListServices(String::new())).await?
    else {
        panic!("ListServices answered with another message");
    };
    let names: Vec<&str> = list.service.iter().map(|s| s.name.as_str()).collect();
    for want in [
        "haptics.v1.SessionControl",
        "haptics.v1.DeviceLink",
        "haptics.v1.SurfaceStream",
        "grpc.health.v1.Health",
    ] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }

    // A generic client can fetch the contract itself.
    let MessageResponse::FileDescriptorResponse(files) = reflect(
        &url,
        MessageRequest::FileContainingSymbol("haptics.v1.DeviceLink".into()),
    )
    .await?
    else {
        panic!("FileContainingSymbol answered with another message");
    };
    assert!(!files.file_descriptor_proto.is_empty());
    let raw = &files.file_descriptor_proto[0];
    let has = |s: &str| raw.windows(s.len()).any(|w| w == s.as_bytes());
    assert!(
        has("haptics.v1") && has("ForceCommand"),
        "descriptor lacks the package"
    );

    // The older `v1alpha` protocol (Python's grpcio-reflection, Postman) lists the same services.
    use tonic_reflection::pb::v1alpha as alpha;
    let mut client =
        alpha::server_reflection_client::ServerReflectionClient::new(channel(&url).await?);
    let request = alpha::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(
            alpha::server_reflection_request::MessageRequest::ListServices(String::new()),
        ),
    };
    let mut responses = client
        .server_reflection_info(tokio_stream::iter([request]))
        .await
        .context("v1alpha reflection")?
        .into_inner();
    let first = tokio::time::timeout(STEP_TIMEOUT, responses.next())
        .await
        .context("v1alpha reflection answer timed out")?
        .context("v1alpha reflection stream ended without an answer")??;
    let Some(alpha::server_reflection_response::MessageResponse::ListServicesResponse(list)) =
        first.message_response
    else {
        panic!("v1alpha ListServices answered with another message");
    };
    let alpha_names: Vec<&str> = list.service.iter().map(|s| s.name.as_str()).collect();
    for want in ["haptics.v1.SessionControl", "haptics.v1.DeviceLink"] {
        assert!(
            alpha_names.contains(&want),
            "{want} missing from v1alpha {alpha_names:?}"
        );
    }
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hapticctl_roundtrip() -> Result<()> {
    let _serial = serial().await;
    let daemon = Daemon::spawn(&[])?;
    let url = daemon.url();
    let scenes = ctl(&url, &["scenes"]).await?.success()?;
    for name in ["lv", "ellipsoids"] {
        let line = scenes
            .stdout
            .lines()
            .find(|l| l.split_whitespace().next() == Some(name))
            .with_context(|| format!("scene {name} not listed:\n{}", scenes.stdout))?;
        let cols: Vec<&str> = line.split_whitespace().collect();
        let nodes: u32 = cols[1].parse().context("node count")?;
        let tets: u32 = cols[2].parse().context("tet count")?;
        assert!(
            nodes > 10 && tets > 10,
            "{name}: {nodes} nodes, {tets} tets"
        );
    }

    let started = ctl(&url, &["start", "lv"]).await?.success()?;
    let id = started.stdout.trim().to_string();
    ensure!(
        !id.is_empty() && !id.contains(char::is_whitespace),
        "start printed more than an id: {:?}",
        started.stdout
    );

    let listed = ctl(&url, &["sessions"]).await?.success()?;
    assert!(listed.stdout.contains(&id), "sessions: {}", listed.stdout);

    // Wait (bounded) until the servo has stepped, then check the JSON statistics.
    let mut stats = serde_json::Value::Null;
    for _ in 0..100 {
        stats = ctl(&url, &["stats", &id, "--json"])
            .await?
            .success()?
            .json()?;
        if stats["steps"].as_u64().unwrap_or(0) > 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(stats["session_id"], id.as_str());
    assert_eq!(stats["scene"], "lv");
    assert!(stats["steps"].as_u64().unwrap_or(0) > 0, "{stats}");
    assert!(stats["nodes"].as_u64().unwrap_or(0) > 0, "{stats}");
    assert_eq!(stats["faulted"], false);

    ctl(&url, &["stop", &id]).await?.success()?;
    let gone = ctl(&url, &["stats", &id]).await?;
    assert_eq!(gone.status.code(), Some(2), "{gone:?}");
    assert!(
        gone.stderr.contains("error: NOT_FOUND"),
        "stderr: {}",
        gone.stderr
    );

    let big = ctl(
        &url,
        &[
            "force",
            "nosuch",
            "--point",
            "0,0.00968,-0.005",
            "--force",
            "0,-1000,0",
            "--duration-s",
            "0.1",
        ],
    )
    .await?;
    assert_eq!(big.status.code(), Some(2), "{big:?}");
    assert!(
        big.stderr.contains("error: INVALID_ARGUMENT") || big.stderr.contains("error: NOT_FOUND"),
        "stderr: {}",
        big.stderr
    );
    Ok(())
}

/// `hapticd --prepare-regions SCENE --region-cache-dir DIR` fills the region cache of a scene
/// file and exits: the first run writes every region, the second finds them all there; a
/// scene without a region cache, and a missing cache directory, are refused with what to do.
/// The configuration's `prepare_regions` fills it in the background of a serving daemon
/// (here a missing region), and a scene it cannot prepare stops the daemon's start.
#[test]
fn prepare_regions_fills_the_region_cache_and_exits() -> Result<()> {
    let dir = haptic_e2e::unique_temp_dir("hapticd-prepare-regions")?;
    let scene = "name = \"lv-tiles\"\n[mesh]\nbuiltin = \"lv\"\ntarget_tets = 2000\norder = 1\n\
        [material]\nyoungs_modulus_pa = 14500.0\npoisson_ratio = 0.45\n\
        density_kg_per_m3 = 1060.0\n[boundary]\nclamped = [\"BASE\"]\ntouchable = [\"EPI\"]\n\
        [integrator]\nkind = \"backward-euler\"\nsubsteps = 1\n[active_region]\n\
        centre_m = [0.00968, 0.0, -0.005]\nradius_m = 0.006\nfollow = true\n";
    let tiled = dir.join("tiled.toml");
    std::fs::write(
        &tiled,
        format!("{scene}tiles = \"background\"\ntile_cover_m = 0.005\n"),
    )?;
    let plain = dir.join("plain.toml");
    std::fs::write(&plain, scene)?;
    let cache = dir.join("cache");
    let hapticd = haptic_e2e::binary(haptic_e2e::HAPTICD)?;
    let run = |args: &[&std::ffi::OsStr]| -> Result<(bool, String, String)> {
        let out = std::process::Command::new(&hapticd).args(args).output()?;
        Ok((
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        ))
    };
    let prepare = [
        "--prepare-regions".as_ref(),
        tiled.as_os_str(),
        "--region-cache-dir".as_ref(),
        cache.as_os_str(),
    ];
    let (ok, first, err) = run(&prepare)?;
    ensure!(ok, "first run failed: {err}");
    let files = std::fs::read_dir(&cache)?.count();
    ensure!(
        files >= 5
            && first.contains(&format!(
                "prepared {files} regions of lv-tiles ready (0 already there, {files} written"
            )),
        "{files} files; {first}"
    );
    let (ok, second, err) = run(&prepare)?;
    ensure!(ok, "second run failed: {err}");
    ensure!(
        second.contains(&format!("({files} already there, 0 written")),
        "{second}"
    );
    ensure!(err.contains("ready"), "no progress on stderr: {err}");
    let (ok, _, err) = run(&[
        "--prepare-regions".as_ref(),
        plain.as_os_str(),
        "--region-cache-dir".as_ref(),
        cache.as_os_str(),
    ])?;
    ensure!(!ok && err.contains("no region cache"), "{err}");
    let (ok, _, err) = run(&["--prepare-regions".as_ref(), tiled.as_os_str()])?;
    ensure!(!ok && err.contains("--region-cache-dir"), "{err}");

    // The daemon's background fill: one region missing, written while it serves.
    let mut names: Vec<_> = std::fs::read_dir(&cache)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()?;
    names.sort();
    std::fs::remove_file(&names[1])?;
    let config = dir.join("hapticd.toml");
    std::fs::write(
        &config,
        "region_cache_dir = \"cache\"\nprepare_regions = [\"tiled.toml\"]\n\
         prepare_regions_priority = \"normal\"\n",
    )?;
    let mut daemon = Daemon::spawn(&["--config", &config.to_string_lossy()])?;
    let done = format!(
        "{files} regions of lv-tiles ready ({} already there, 1 written",
        files - 1
    );
    let waited = std::time::Instant::now();
    while !daemon.log_tail().contains(&done) {
        ensure!(
            waited.elapsed() < Duration::from_secs(120),
            "no `{done}` in the daemon's log:\n{}",
            daemon.log_tail()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    ensure!(names[1].exists(), "{} not written", names[1].display());
    daemon.terminate(Duration::from_secs(10))?;
    std::fs::write(
        &config,
        "region_cache_dir = \"cache\"\nprepare_regions = [\"plain.toml\"]\n",
    )?;
    let (ok, _, err) = run(&[
        "--config".as_ref(),
        config.as_os_str(),
        "--listen".as_ref(),
        "127.0.0.1:0".as_ref(),
    ])?;
    ensure!(!ok && err.contains("no region cache to prepare"), "{err}");
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}
