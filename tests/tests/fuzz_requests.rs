//! Property-based fuzzing of every request decoder and handler (issue 16, section 4): each RPC
//! of the contract gets bytes mutated from a valid request of its type (so many decode and
//! reach the handler's checks) or arbitrary bytes, over loopback against the server library.
//! Every answer must be a status the contract names for bad input (never INTERNAL or UNKNOWN,
//! never a panic or a hang), and a session running beside the traffic keeps stepping.
//! 24 cases per RPC in the test command; `PROPTEST_CASES=N` for a longer run.

use std::time::Duration;

use anyhow::{Context, Result};
use haptic_e2e::{STEP_TIMEOUT, channel, serial, session_control};
use haptics_proto::v1::{
    ApplyForceRequest, DeviceSample, GetStatsRequest, KeyframeRequest, ListScenesRequest,
    ListSessionsRequest, StartSessionRequest, StopSessionRequest, Vec3, WatchRequest,
};
use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use prost::Message;
use prost::bytes::BufMut;
use tonic::codec::{Codec, EncodeBuf, Encoder};
use tonic::codegen::http::uri::PathAndQuery;
use tonic::{Code, Request, Status};

use crate::common;
use common::InProcess;

/// Sends request bodies as given bytes; answers are decoded as `()` (every field skipped), with
/// the contract's decoder and its statuses.
#[derive(Debug, Default, Clone, Copy)]
struct RawCodec;

#[derive(Debug)]
struct RawEncoder;

impl Encoder for RawEncoder {
    type Item = Vec<u8>;
    type Error = Status;

    fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put_slice(&item);
        Ok(())
    }
}

impl Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = ();
    type Encoder = RawEncoder;
    type Decoder = haptics_proto::codec::ProtoDecoder<()>;

    fn encoder(&mut self) -> RawEncoder {
        RawEncoder
    }

    fn decoder(&mut self) -> Self::Decoder {
        haptics_proto::codec::ProtoCodec::<(), ()>::default().decoder()
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Unary,
    ServerStreaming,
    Bidi,
}

/// Each RPC of the contract with a valid request of its type (against `target`).
fn rpcs(target: &str) -> Vec<(&'static str, Kind, Vec<u8>)> {
    let v = |x: f64, y: f64, z: f64| Some(Vec3::new(x, y, z));
    vec![
        (
            "/haptics.v1.SessionControl/ListScenes",
            Kind::Unary,
            ListScenesRequest {}.encode_to_vec(),
        ),
        (
            "/haptics.v1.SessionControl/StartSession",
            Kind::Unary,
            StartSessionRequest {
                scene: "no-such-scene".into(),
                scene_toml: String::new(),
            }
            .encode_to_vec(),
        ),
        (
            "/haptics.v1.SessionControl/StopSession",
            Kind::Unary,
            StopSessionRequest {
                session_id: "0000deadbeef".into(),
            }
            .encode_to_vec(),
        ),
        (
            "/haptics.v1.SessionControl/ApplyForce",
            Kind::Unary,
            ApplyForceRequest {
                session_id: target.into(),
                point_m: v(0.0, 0.0, 0.01),
                force_n: v(0.0, 0.0, -0.01),
                duration_s: 0.01,
            }
            .encode_to_vec(),
        ),
        (
            "/haptics.v1.SessionControl/GetStats",
            Kind::Unary,
            GetStatsRequest {
                session_id: target.into(),
            }
            .encode_to_vec(),
        ),
        (
            "/haptics.v1.SessionControl/ListSessions",
            Kind::Unary,
            ListSessionsRequest {}.encode_to_vec(),
        ),
        (
            "/haptics.v1.SurfaceStream/RequestKeyframe",
            Kind::Unary,
            KeyframeRequest {
                session_id: target.into(),
                watch_id: 1,
            }
            .encode_to_vec(),
        ),
        (
            "/haptics.v1.SurfaceStream/Watch",
            Kind::ServerStreaming,
            WatchRequest {
                session_id: target.into(),
                max_rate_hz: 30.0,
                encoding: 1,
                quantum_m: 1e-6,
            }
            .encode_to_vec(),
        ),
        (
            "/haptics.v1.DeviceLink/Connect",
            Kind::Bidi,
            DeviceSample {
                session_id: target.into(),
                seq: 1,
                device_time_us: 1,
                position_m: v(0.0, 0.0, 0.05),
                velocity_m_per_s: v(0.0, 0.0, 0.0),
                capabilities: None,
                tool_id: String::new(),
            }
            .encode_to_vec(),
        ),
    ]
}

/// `base` with one to eight byte edits (overwrite, insert or remove), or arbitrary bytes.
fn mutated(base: Vec<u8>) -> impl Strategy<Value = Vec<u8>> {
    let edits = proptest::collection::vec((any::<Index>(), any::<u8>(), 0u8..3), 1..8).prop_map(
        move |edits| {
            let mut b = base.clone();
            for (i, value, op) in edits {
                match op {
                    0 if !b.is_empty() => {
                        let k = i.index(b.len());
                        b[k] = value;
                    }
                    1 => b.insert(i.index(b.len() + 1), value),
                    _ if !b.is_empty() => {
                        b.remove(i.index(b.len()));
                    }
                    _ => {}
                }
            }
            b
        },
    );
    prop_oneof![3 => edits, 1 => proptest::collection::vec(any::<u8>(), 0..200)]
}

/// The status of a stream's first answer, or OK when the stream stays open for 200 ms.
async fn first_answer(mut s: tonic::Streaming<()>) -> Code {
    tokio::time::timeout(Duration::from_millis(200), s.message())
        .await
        .map_or(Code::Ok, |r| r.map_or_else(|s| s.code(), |_| Code::Ok))
}

/// The status of one call with `body` (a stream answer: of its first message, or OK when the
/// stream stays open for 200 ms).
async fn call(url: &str, path: &'static str, kind: Kind, body: Vec<u8>) -> Result<Code> {
    let mut grpc = tonic::client::Grpc::new(channel(url).await?);
    grpc.ready().await?;
    let path = PathAndQuery::from_static(path);
    let code = match kind {
        Kind::Unary => match grpc.unary(Request::new(body), path, RawCodec).await {
            Ok(_) => Code::Ok,
            Err(s) => s.code(),
        },
        Kind::ServerStreaming => {
            match grpc
                .server_streaming(Request::new(body), path, RawCodec)
                .await
            {
                Ok(r) => first_answer(r.into_inner()).await,
                Err(s) => s.code(),
            }
        }
        Kind::Bidi => {
            let out = tokio_stream::iter(vec![body.clone(), body]);
            match grpc.streaming(Request::new(out), path, RawCodec).await {
                Ok(r) => first_answer(r.into_inner()).await,
                Err(s) => s.code(),
            }
        }
    };
    Ok(code)
}

#[test]
fn every_rpc_answers_mutated_and_arbitrary_requests_with_a_clear_status() -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let _serial = rt.block_on(serial());
    let server = rt.block_on(InProcess::start())?;
    let url = server.url.clone();
    let mut ctl = rt.block_on(session_control(&url))?;
    let start = |ctl: &mut haptics_proto::v1::session_control_client::SessionControlClient<_>| {
        rt.block_on(ctl.start_session(StartSessionRequest {
            scene: "hemisphere-springs".into(),
            scene_toml: String::new(),
        }))
        .map(|r| r.into_inner().session_id)
    };
    // The traffic's target, and a bystander nobody addresses.
    let target = start(&mut ctl)?;
    let bystander = start(&mut ctl)?;
    let stats = |ctl: &mut haptics_proto::v1::session_control_client::SessionControlClient<_>| {
        rt.block_on(ctl.get_stats(GetStatsRequest {
            session_id: bystander.clone(),
        }))
        .map(|r| r.into_inner())
    };
    let before = stats(&mut ctl)?;

    let cases = std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|c| c.parse().ok())
        .unwrap_or(24);
    let mut runner = TestRunner::new(Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    });
    for (path, kind, base) in rpcs(&target) {
        runner
            .run(&mutated(base), |body| {
                let code = rt
                    .block_on(async {
                        tokio::time::timeout(STEP_TIMEOUT, call(&url, path, kind, body.clone()))
                            .await
                    })
                    .map_err(|_| TestCaseError::fail(format!("{path}: no answer")))?
                    .map_err(|e| TestCaseError::fail(format!("{path}: {e:#}")))?;
                prop_assert!(
                    !matches!(
                        code,
                        Code::Internal | Code::Unknown | Code::Unavailable | Code::DataLoss
                    ),
                    "{path}: {code:?} for {body:?}"
                );
                Ok(())
            })
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }

    // The daemon still answers, and the bystander kept stepping, unharmed. (Its statistics
    // are published periodically: when the traffic took less than a publication period, as
    // in a CI run where all of it took 0.2 s, wait for the next one, up to 5 s.)
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    let after = loop {
        let after = stats(&mut ctl)?;
        if after.steps > before.steps || std::time::Instant::now() > deadline {
            break after;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    anyhow::ensure!(
        after.steps > before.steps && !after.faulted,
        "bystander: {before:?} -> {after:?}"
    );
    // Stop whatever the traffic managed to start.
    let sessions = rt
        .block_on(ctl.list_sessions(ListSessionsRequest {}))?
        .into_inner()
        .session_ids;
    for id in sessions {
        rt.block_on(ctl.stop_session(StopSessionRequest { session_id: id }))
            .context("stop")?;
    }
    rt.block_on(server.shutdown())
}
