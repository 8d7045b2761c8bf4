//! Bad input never corrupts a session (DESIGN.md section 4): every kind of malformed request
//! gets a precise status and the session keeps stepping. Runs the server in process
//! (`haptic_server::run` on a port-0 listener with a oneshot shutdown) and talks to it over
//! loopback gRPC, with a hand-written DeviceLink client for exact sample-by-sample checks.

use std::time::Duration;

use anyhow::{Context, Result};
use haptic_e2e::{STEP_TIMEOUT, device_link, serial, session_control, surface_stream};
use haptics_proto::v1::{
    ApplyForceRequest, DeviceSample, ForceCommand, GetStatsRequest, StartSessionRequest,
    StopSessionRequest, Vec3, WatchRequest,
};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use crate::common;
use common::InProcess;

/// `StartSessionRequest` with `scene_toml` as bytes: the same wire format, any bytes.
#[derive(Clone, PartialEq, prost::Message)]
struct RawStartSession {
    #[prost(string, tag = "1")]
    scene: String,
    #[prost(bytes = "vec", tag = "2")]
    scene_toml: Vec<u8>,
}

/// Sends `StartSession` with raw scene bytes; the status of the refusal.
async fn start_raw(url: &str, scene_toml: Vec<u8>) -> Result<tonic::Status> {
    let mut grpc = tonic::client::Grpc::new(haptic_e2e::channel(url).await?);
    grpc.ready().await?;
    let path = tonic::codegen::http::uri::PathAndQuery::from_static(
        "/haptics.v1.SessionControl/StartSession",
    );
    let answer: Result<tonic::Response<haptics_proto::v1::StartSessionResponse>, _> = grpc
        .unary(
            tonic::Request::new(RawStartSession {
                scene: String::new(),
                scene_toml,
            }),
            path,
            haptics_proto::codec::ProtoCodec::default(),
        )
        .await;
    match answer {
        Ok(r) => anyhow::bail!("accepted: {:?}", r.into_inner()),
        Err(status) => Ok(status),
    }
}

fn sample(session: &str, seq: u64, p: [f64; 3]) -> DeviceSample {
    DeviceSample {
        session_id: session.to_string(),
        seq,
        device_time_us: seq * 1000,
        position_m: Some(Vec3::from(p)),
        velocity_m_per_s: Some(Vec3::new(0.0, 0.0, 0.0)),
        capabilities: None,
        tool_id: String::new(),
    }
}

/// Waits (bounded) for a force answering `seq`; panics if one answers a rejected sequence.
async fn force_for(
    forces: &mut tonic::Streaming<ForceCommand>,
    seq: u64,
    rejected: &[u64],
) -> Result<ForceCommand> {
    let deadline = tokio::time::Instant::now() + STEP_TIMEOUT;
    loop {
        let f = tokio::time::timeout_at(deadline, forces.message())
            .await
            .with_context(|| format!("no ForceCommand with seq {seq}"))??
            .context("the force stream ended")?;
        assert!(
            !rejected.contains(&f.seq),
            "a rejected sample (seq {}) was answered: {f:?}",
            f.seq
        );
        if f.seq == seq {
            return Ok(f);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_inputs_get_statuses_and_session_keeps_running() -> Result<()> {
    let _serial = serial().await;
    let server = InProcess::start().await?;
    let url = server.url.clone();
    let mut ctl = session_control(&url).await?;
    let id = ctl
        .start_session(StartSessionRequest {
            scene: "lv".into(),
            scene_toml: String::new(),
        })
        .await?
        .into_inner()
        .session_id;

    // Scene text that is not UTF-8 (a client can put any bytes in a string field): the
    // message does not decode, which is the client's error, not the server's.
    let status = start_raw(&url, b"[mesh]\nbuiltin = \"lv\xff\xfe\"\n".to_vec()).await?;
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(
        status.message().contains("UTF-8") && status.message().len() <= 1024,
        "{status:?}"
    );
    // The same bytes as valid UTF-8 are read as a scene (and refused as one: no [material]).
    let status = start_raw(&url, b"[mesh]\nbuiltin = 3\n".to_vec()).await?;
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("scene"), "{status:?}");

    // ApplyForce with bad numbers.
    let point = [0.0, 0.00968, -0.005];
    let apply = |p: [f64; 3], f: [f64; 3], d: f64| ApplyForceRequest {
        session_id: id.clone(),
        point_m: Some(Vec3::from(p)),
        force_n: Some(Vec3::from(f)),
        duration_s: d,
    };
    for (what, req) in [
        (
            "NaN point",
            apply([f64::NAN, 0.0, 0.0], [0.0, -0.05, 0.0], 0.1),
        ),
        (
            "infinite force",
            apply(point, [0.0, f64::INFINITY, 0.0], 0.1),
        ),
        ("1e6 N force", apply(point, [0.0, -1e6, 0.0], 0.1)),
        ("negative duration", apply(point, [0.0, -0.05, 0.0], -1.0)),
    ] {
        let e = ctl.apply_force(req).await.expect_err(what);
        assert_eq!(e.code(), Code::InvalidArgument, "{what}: {e:?}");
        assert!(!e.message().is_empty(), "{what}: empty message");
    }

    // Unknown sessions.
    let nosuch = "0000nosuch00".to_string();
    let e = ctl
        .apply_force(ApplyForceRequest {
            session_id: nosuch.clone(),
            ..apply(point, [0.0, -0.05, 0.0], 0.1)
        })
        .await
        .expect_err("ApplyForce on an unknown session");
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    let e = ctl
        .get_stats(GetStatsRequest {
            session_id: nosuch.clone(),
        })
        .await
        .expect_err("GetStats on an unknown session");
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    let e = ctl
        .stop_session(StopSessionRequest {
            session_id: nosuch.clone(),
        })
        .await
        .expect_err("StopSession on an unknown session");
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    let e = surface_stream(&url)
        .await?
        .watch(WatchRequest {
            session_id: nosuch.clone(),
            max_rate_hz: 0.0,
            ..WatchRequest::default()
        })
        .await
        .expect_err("Watch on an unknown session");
    assert_eq!(e.code(), Code::NotFound, "{e:?}");

    // Malformed scenes.
    let start_toml = |toml: String| StartSessionRequest {
        scene: String::new(),
        scene_toml: toml,
    };
    let e = ctl
        .start_session(start_toml("[mesh\nbuiltin=".into()))
        .await
        .expect_err("malformed TOML");
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(!e.message().is_empty());
    let e = ctl
        .start_session(StartSessionRequest {
            scene: "no_such_scene".into(),
            scene_toml: String::new(),
        })
        .await
        .expect_err("unknown built-in");
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().contains("no_such_scene"), "{e:?}");
    let lv_path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/scenes/lv.toml");
    let lv = std::fs::read_to_string(lv_path).with_context(|| format!("reading {lv_path}"))?;
    assert!(lv.contains("poisson_ratio = 0.45"), "{lv_path} changed");
    let e = ctl
        .start_session(start_toml(
            lv.replace("poisson_ratio = 0.45", "poisson_ratio = 0.5"),
        ))
        .await
        .expect_err("incompressible material");
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().contains("material.poisson_ratio"), "{e:?}");

    // A device stream naming an unknown session.
    let mut link = device_link(&url).await?;
    let e = link
        .connect(tokio_stream::iter([sample(&nosuch, 1, [0.03, 0.0, 0.0])]))
        .await
        .expect_err("DeviceLink to an unknown session");
    assert_eq!(e.code(), Code::NotFound, "{e:?}");

    // A device stream with a NaN and an absurd sample among valid ones.
    let (tx, rx) = mpsc::channel::<DeviceSample>(16);
    let free = [0.03, 0.0, 0.0]; // well outside the body: no contact
    tx.send(sample(&id, 1, free)).await?;
    let mut forces = link.connect(ReceiverStream::new(rx)).await?.into_inner();
    force_for(&mut forces, 1, &[]).await?;
    tx.send(sample(&id, 2, [f64::NAN, 0.0, 0.0])).await?;
    tx.send(sample(&id, 3, [1e9, 0.0, 0.0])).await?;
    tx.send(sample(&id, 4, free)).await?;
    let f4 = force_for(&mut forces, 4, &[2, 3]).await?;
    tx.send(sample(&id, 5, [0.03, 0.001, 0.0])).await?;
    let f5 = force_for(&mut forces, 5, &[2, 3]).await?;
    for f in [&f4, &f5] {
        let v = f.force_n.unwrap_or_default();
        assert!(v.is_finite(), "{f:?}");
        assert!(!f.in_contact, "free-space sample in contact: {f:?}");
    }

    // The session is alive and well after all that.
    let s1 = ctl
        .get_stats(GetStatsRequest {
            session_id: id.clone(),
        })
        .await?
        .into_inner();
    assert_eq!(s1.rejected_samples, 2, "{s1:?}");
    assert!(!s1.faulted, "{s1:?}");
    let mut s2 = s1.clone();
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        s2 = ctl
            .get_stats(GetStatsRequest {
                session_id: id.clone(),
            })
            .await?
            .into_inner();
        if s2.steps > s1.steps {
            break;
        }
    }
    assert!(
        s2.steps > s1.steps,
        "steps stalled: {} -> {}",
        s1.steps,
        s2.steps
    );
    assert!(s2.loop_rate_hz > 100.0, "{s2:?}");
    assert_eq!(s2.rejected_samples, 2);
    drop(tx);
    drop(forces);
    server.shutdown().await
}

/// Issue 16, section 3: older or repeated `seq` are dropped and counted (never applied, never
/// answered), and a device silent for longer than the limit (50 ms) leaves the scene (no
/// contact) until its next sample, which brings it back cleanly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn device_seq_only_goes_up_and_a_silent_device_leaves_the_scene() -> Result<()> {
    let _serial = serial().await;
    let server = InProcess::start().await?;
    let url = server.url.clone();
    let id = haptic_e2e::start_session(&url, "lv").await?;
    let ctl = session_control(&url).await?;
    let stats = || {
        let (mut ctl, id) = (ctl.clone(), id.clone());
        async move {
            anyhow::Ok(
                ctl.get_stats(GetStatsRequest { session_id: id })
                    .await?
                    .into_inner(),
            )
        }
    };
    // 1 mm into the epicardium (9.68 mm from the axis at z = -5 mm; probe radius 2 mm).
    let pressed = [0.0107, 0.0, -0.005];
    let (tx, rx) = mpsc::channel::<DeviceSample>(16);
    let mut link = device_link(&url).await?;
    tx.send(sample(&id, 10, pressed)).await?;
    let mut forces = link.connect(ReceiverStream::new(rx)).await?.into_inner();
    force_for(&mut forces, 10, &[]).await?;
    // Older and repeated sequence numbers, the repeat with a new position: dropped.
    tx.send(sample(&id, 9, [0.03, 0.0, 0.0])).await?;
    tx.send(sample(&id, 10, [0.03, 0.0, 0.0])).await?;
    tx.send(sample(&id, 11, pressed)).await?;
    force_for(&mut forces, 11, &[9]).await?;
    // Keep pressing until the contact is established.
    let mut seq = 11;
    let deadline = tokio::time::Instant::now() + STEP_TIMEOUT;
    loop {
        seq += 1;
        tx.send(sample(&id, seq, pressed)).await?;
        let f = force_for(&mut forces, seq, &[]).await?;
        if f.in_contact {
            break;
        }
        anyhow::ensure!(tokio::time::Instant::now() < deadline, "no contact at 1 mm");
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let s = stats().await?;
    assert_eq!(s.out_of_order_samples, 2, "{s:?}");
    assert!(!s.device_silent);

    // Silence: the stream stays open, nothing is sent for 400 ms.
    tokio::time::sleep(Duration::from_millis(400)).await;
    let s = stats().await?;
    assert!(s.device_silent, "{s:?}");
    assert!(!s.in_contact, "a silent device still presses: {s:?}");
    assert_eq!(s.device_silences, 1);

    // The next sample brings it back.
    let back = seq + 1;
    tx.send(sample(&id, back, pressed)).await?;
    let f = force_for(&mut forces, back, &[]).await?;
    assert!(f.force_n.is_some());
    let mut s = stats().await?;
    for k in 0..50 {
        if !s.device_silent {
            break;
        }
        tx.send(sample(&id, back + 1 + k, pressed)).await?;
        tokio::time::sleep(Duration::from_millis(5)).await;
        s = stats().await?;
    }
    assert!(!s.device_silent, "{s:?}");
    drop(tx);
    server.shutdown().await
}
