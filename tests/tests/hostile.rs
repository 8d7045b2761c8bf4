//! The hostile-client suite (issue 16, section 4): while a session runs, every class of hostile
//! request is sent to the daemon (over loopback, tokens on), each gets its clear status, and
//! the session's trajectory is **bit for bit** the one of a run without the traffic.
//!
//! The session is the default LV with a permanent point load on the epicardium from t = 0 (so
//! it moves: a damped dynamic response), with nothing else acting on it. Its surface frames
//! are published every 16 ticks, at simulated times that do not depend on the wall clock, so
//! two runs are compared frame by frame at equal simulated times.

use crate::common;

use std::collections::HashMap;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, ensure};
use common::InProcess;
use haptic_cli::credentials::{AuthChannel, ClientCredentials};
use haptic_server::ServerConfig;
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::surface_stream_client::SurfaceStreamClient;
use haptics_proto::v1::*;
use tokio_stream::StreamExt;
use tonic::Code;

/// Simulated time each run records, s.
const RECORD_S: f64 = 0.4;

/// The shipped LV scene with a 0.05 N point load on the epicardium from the start.
fn scene() -> String {
    let base = include_str!("../../deploy/scenes/lv.toml");
    format!(
        "{base}\n[loads]\n[[loads.point]]\npoint_m = [0.0, 0.00968, -0.005]\n\
         force_n = [0.0, -0.05, 0.0]\n"
    )
}

fn write_private(path: &Path, text: &str) {
    std::fs::write(path, text).expect("write");
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
}

/// A tokens file with an owner, another control client, a viewer and a device; token files
/// `<name>.token` beside it, and `wrong.token` that the daemon does not know.
fn tokens(dir: &Path) -> PathBuf {
    let mut text = String::new();
    for (name, role) in [
        ("owner", "control"),
        ("other", "control"),
        ("screen", "viewer"),
        ("arm", "device"),
    ] {
        let token = format!("{name}-token-0123456789abcdef");
        text.push_str(&format!(
            "[[token]]\nname = \"{name}\"\nrole = \"{role}\"\ntoken = \"{token}\"\n"
        ));
        write_private(&dir.join(format!("{name}.token")), &token);
    }
    write_private(&dir.join("wrong.token"), "wrong-token-0123456789abcdef");
    let path = dir.join("tokens.toml");
    write_private(&path, &text);
    path
}

async fn channel(url: &str, token_file: Option<PathBuf>) -> Result<AuthChannel> {
    let creds = ClientCredentials {
        token_file,
        ..Default::default()
    };
    let ch = creds.endpoint(url)?.connect().await?;
    Ok(creds.interceptor()?.wrap(ch))
}

/// The session's frames until `RECORD_S` of simulated time: positions by simulated time.
async fn record(ch: AuthChannel, id: &str) -> Result<HashMap<u64, Vec<f32>>> {
    let mut frames = SurfaceStreamClient::new(ch)
        .max_decoding_message_size(64 << 20)
        .watch(WatchRequest {
            session_id: id.into(),
            max_rate_hz: 120.0,
            ..Default::default()
        })
        .await?
        .into_inner();
    let mut out = HashMap::new();
    while let Some(f) = tokio::time::timeout(Duration::from_secs(20), frames.next())
        .await
        .context("no frame for 20 s")?
    {
        let f = f?;
        if f.sim_time_s > RECORD_S {
            break;
        }
        out.insert(f.sim_time_s.to_bits(), f.positions_m);
    }
    Ok(out)
}

/// One run: start the session as its owner and record its frames, with the hostile traffic
/// alongside (its statuses checked) or not. Returns the frames and how many hostile requests
/// were sent.
async fn run(url: &str, dir: &Path, hostile: bool) -> Result<(HashMap<u64, Vec<f32>>, usize)> {
    let owner_ch = channel(url, Some(dir.join("owner.token"))).await?;
    let mut owner = SessionControlClient::new(owner_ch.clone());
    let id = owner
        .start_session(StartSessionRequest {
            scene: String::new(),
            scene_toml: scene(),
        })
        .await?
        .into_inner()
        .session_id;
    let recording = {
        let id = id.clone();
        tokio::spawn(async move { record(owner_ch, &id).await })
    };
    let mut sent = 0;
    let mut rejected_samples = 0;
    if hostile {
        while !recording.is_finished() {
            let (n, samples) = hostile_round(url, dir, &id).await?;
            sent += n;
            rejected_samples += samples;
        }
    }
    let frames = recording.await??;
    let stats = owner.get_stats(stats(&id)).await?.into_inner();
    ensure!(
        stats.rejected_samples >= rejected_samples,
        "{} of {rejected_samples} bad device samples counted",
        stats.rejected_samples
    );
    ensure!(stats.device_samples == 0, "a hostile sample was used");
    owner
        .stop_session(StopSessionRequest { session_id: id })
        .await?;
    Ok((frames, sent))
}

fn stats(id: &str) -> GetStatsRequest {
    GetStatsRequest {
        session_id: id.into(),
    }
}

fn push(id: &str, force_n: Vec3, point_m: Vec3) -> ApplyForceRequest {
    ApplyForceRequest {
        session_id: id.into(),
        point_m: Some(point_m),
        force_n: Some(force_n),
        duration_s: 0.1,
    }
}

fn expect<T: std::fmt::Debug>(
    what: &str,
    r: Result<tonic::Response<T>, tonic::Status>,
    code: Code,
) -> Result<usize> {
    match r {
        Err(s) if s.code() == code => {
            ensure!(
                s.message().len() <= 1024,
                "{what}: a {} B message",
                s.message().len()
            );
            Ok(1)
        }
        other => anyhow::bail!("{what}: expected {code:?}, got {other:?}"),
    }
}

/// One round of every hostile class against session `id`. Returns the requests sent and the
/// bad device samples among them.
async fn hostile_round(url: &str, dir: &Path, id: &str) -> Result<(usize, u64)> {
    let token = |n: &str| Some(dir.join(format!("{n}.token")));
    let control = |n: Option<PathBuf>| async move {
        Ok::<_, anyhow::Error>(SessionControlClient::new(channel(url, n).await?))
    };
    let (mut anonymous, mut wrong) = (control(None).await?, control(token("wrong")).await?);
    let (mut other, mut screen) = (
        control(token("other")).await?,
        control(token("screen")).await?,
    );
    let mut owner = control(token("owner")).await?;
    let (ok_force, ok_point) = (Vec3::new(0.0, -0.05, 0.0), Vec3::new(0.0, 0.00968, -0.005));
    let mut n = 0;
    // Who may not: no token, a wrong token, another control client, a viewer.
    n += expect(
        "no token",
        anonymous.get_stats(stats(id)).await,
        Code::Unauthenticated,
    )?;
    n += expect(
        "no token, stop",
        anonymous
            .stop_session(StopSessionRequest {
                session_id: id.into(),
            })
            .await,
        Code::Unauthenticated,
    )?;
    n += expect(
        "wrong token",
        wrong.apply_force(push(id, ok_force, ok_point)).await,
        Code::Unauthenticated,
    )?;
    n += expect(
        "another client's push",
        other.apply_force(push(id, ok_force, ok_point)).await,
        Code::PermissionDenied,
    )?;
    n += expect(
        "another client's stop",
        other
            .stop_session(StopSessionRequest {
                session_id: id.into(),
            })
            .await,
        Code::PermissionDenied,
    )?;
    n += expect(
        "a viewer's push",
        screen.apply_force(push(id, ok_force, ok_point)).await,
        Code::PermissionDenied,
    )?;
    // Bad values, even from the owner.
    for (what, force, point) in [
        ("NaN force", Vec3::new(f64::NAN, 0.0, 0.0), ok_point),
        ("absurd force", Vec3::new(0.0, -1e12, 0.0), ok_point),
        ("absurd point", ok_force, Vec3::new(1e6, 0.0, 0.0)),
    ] {
        n += expect(
            what,
            owner.apply_force(push(id, force, point)).await,
            Code::InvalidArgument,
        )?;
    }
    n += expect(
        "unknown session",
        screen.get_stats(stats("no-such-session")).await,
        Code::NotFound,
    )?;
    // Scenes that read outside the allowed directories or are too large.
    let mesh = |m: &str| StartSessionRequest {
        scene: String::new(),
        scene_toml: format!(
            "{m}\n[material]\nyoungs_modulus_pa = 1e4\npoisson_ratio = 0.3\n\
             density_kg_per_m3 = 1000.0\n[boundary]\nclamped = [\"ZMIN\"]\ntouchable = [\"ZMAX\"]\n"
        ),
    };
    n += expect(
        "a scene reading /etc/passwd",
        owner
            .start_session(mesh("[mesh]\nfile = \"/etc/passwd\""))
            .await,
        Code::PermissionDenied,
    )?;
    n += expect(
        "a 600 000-tetrahedron scene",
        owner
            .start_session(mesh(
                "[mesh]\nbuiltin = \"box\"\nsize = [0.1, 0.1, 0.1]\ncells = [100, 100, 10]",
            ))
            .await,
        Code::InvalidArgument,
    )?;
    // Streams: an absurd rate, a keyframe for a stream that does not exist.
    let mut surface = SurfaceStreamClient::new(channel(url, token("screen")).await?);
    n += expect(
        "a 1e-300 Hz watch",
        surface
            .watch(WatchRequest {
                session_id: id.into(),
                max_rate_hz: 1e-300,
                ..Default::default()
            })
            .await,
        Code::InvalidArgument,
    )?;
    n += expect(
        "a keyframe for no stream",
        surface
            .request_keyframe(KeyframeRequest {
                session_id: id.into(),
                watch_id: u64::MAX,
            })
            .await,
        Code::NotFound,
    )?;
    // Device streams: no session, an unknown one, and samples the servo must never use.
    let mut device = DeviceLinkClient::new(channel(url, token("arm")).await?);
    let sample = |session: &str, seq: u64, x: f64| DeviceSample {
        session_id: session.into(),
        seq,
        position_m: Some(Vec3::new(x, 0.0, 0.0)),
        ..Default::default()
    };
    n += expect(
        "a device stream without a session",
        device
            .connect(tokio_stream::iter([sample("", 1, 0.0)]))
            .await,
        Code::InvalidArgument,
    )?;
    n += expect(
        "a device stream for an unknown session",
        device
            .connect(tokio_stream::iter([sample("no-such-session", 1, 0.0)]))
            .await,
        Code::NotFound,
    )?;
    let bad = [
        sample(id, 1, f64::NAN),
        sample(id, 2, f64::INFINITY),
        sample(id, 3, 1e9),
    ];
    let samples = bad.len() as u64;
    let mut answers = device
        .connect(tokio_stream::iter(bad))
        .await
        .context("a device stream with bad samples")?
        .into_inner();
    // The stream ends when ours does; nothing may be answered to unusable samples but the
    // end-of-link zero.
    while let Some(Ok(f)) = answers.next().await {
        let v = f.force_n.unwrap_or_default();
        ensure!(
            v.x == 0.0 && v.y == 0.0 && v.z == 0.0,
            "a force for a bad sample: {f:?}"
        );
    }
    n += 1;
    Ok((n, samples))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_traffic_gets_clear_statuses_and_leaves_a_running_session_unchanged() -> Result<()>
{
    let _serial = haptic_e2e::serial().await;
    let dir = std::env::temp_dir().join(format!("haptic-hostile-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    let server = InProcess::start_with(ServerConfig {
        tokens_file: Some(tokens(&dir)),
        // The failure limit is tested in auth.rs; here every hostile call must reach its rule.
        auth_limits: haptic_server::auth::FailureLimits {
            max_failures: u32::MAX,
            window: Duration::from_secs(1),
        },
        ..Default::default()
    })
    .await?;
    let (quiet, _) = run(&server.url, &dir, false).await?;
    let (noisy, sent) = run(&server.url, &dir, true).await?;
    let common: Vec<_> = quiet.keys().filter(|t| noisy.contains_key(t)).collect();
    println!(
        "{sent} hostile requests; {} and {} frames, {} at equal simulated times",
        quiet.len(),
        noisy.len(),
        common.len()
    );
    ensure!(sent >= 20, "only {sent} hostile requests during the run");
    ensure!(common.len() >= 5, "only {} frames to compare", common.len());
    let mut moved = 0.0f32;
    for t in common {
        let (a, b) = (&quiet[t], &noisy[t]);
        ensure!(
            a == b,
            "the trajectory differs at t = {} s",
            f64::from_bits(*t)
        );
        let first = &quiet[&quiet.keys().min().copied().unwrap_or(*t)];
        moved = moved.max(
            a.iter()
                .zip(first)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max),
        );
    }
    // The comparison means something only if the body moves.
    ensure!(moved > 1e-5, "the surface moved only {moved} m");
    server.shutdown().await
}
