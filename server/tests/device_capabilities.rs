//! Devices that introduce themselves (issue 50, section 2): a `DeviceLink` stream whose first
//! sample carries `DeviceCapabilities` gets the lower of the scene's and the device's force
//! limit in its headers and in every force command, contact stiffness within the device's
//! limit, its poses outside the declared workspace dropped and counted, and the device shown by
//! `GetStats` and `ListSessions` until it disconnects; capabilities that are absurd refuse the
//! stream with INVALID_ARGUMENT and leave the session free for the next device. The daemon runs
//! in process on 127.0.0.1:0 with the built-in LV; the probe presses 3 mm at the lv-probe point
//! (about 30 mN from the organ) against a device limited to 5 mN.

use std::time::Duration;

use haptic_server::ServerConfig;
use haptic_server::service::HEADER_MAX_FORCE;
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::{
    DeviceCapabilities, DeviceSample, GetStatsRequest, ListSessionsRequest, SessionStats,
    StartSessionRequest, StopSessionRequest, Vec3,
};
use tokio::sync::mpsc;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

const TIMEOUT: Duration = Duration::from_secs(30);
/// The lv-probe line: the sphere (2 mm) touches the epicardium with its centre at x = 11.68 mm.
const TOUCH_X_M: f64 = 0.011_682;
const DEVICE_FORCE_N: f64 = 0.005;
const DEVICE_STIFFNESS_N_PER_M: f64 = 50.0;

fn weak_arm() -> DeviceCapabilities {
    DeviceCapabilities {
        name: "weak-arm".into(),
        sensed_degrees_of_freedom: 3,
        actuated_degrees_of_freedom: 3,
        workspace_min_m: Some(Vec3::new(0.005, -0.01, -0.01)),
        workspace_max_m: Some(Vec3::new(0.02, 0.01, 0.0)),
        max_force_n: DEVICE_FORCE_N,
        max_continuous_force_n: 0.004,
        max_stiffness_n_per_m: DEVICE_STIFFNESS_N_PER_M,
        native_rate_hz: 1000.0,
    }
}

fn sample(session: &str, seq: u64, x: f64, caps: Option<DeviceCapabilities>) -> DeviceSample {
    DeviceSample {
        session_id: session.into(),
        seq,
        device_time_us: seq * 1000,
        position_m: Some(Vec3::new(x, 0.0, -0.005)),
        velocity_m_per_s: Some(Vec3::new(0.0, 0.0, 0.0)),
        capabilities: caps,
        tool_id: String::new(),
    }
}

async fn start_server() -> (String, tokio::sync::oneshot::Sender<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(haptic_server::run(
        listener,
        ServerConfig::default(),
        async move {
            let _ = stopped.await;
        },
    ));
    (url, stop)
}

async fn channel(url: &str) -> Channel {
    tonic::transport::Endpoint::from_shared(url.to_owned())
        .unwrap()
        .connect()
        .await
        .unwrap()
}

async fn stats(control: &mut SessionControlClient<Channel>, id: &str) -> SessionStats {
    control
        .get_stats(GetStatsRequest {
            session_id: id.into(),
        })
        .await
        .unwrap()
        .into_inner()
}

/// A daemon on 127.0.0.1:0 with a session of the built-in LV: (its stop switch, a channel to
/// it, a control client, the session id).
async fn lv_session() -> (
    tokio::sync::oneshot::Sender<()>,
    Channel,
    SessionControlClient<Channel>,
    String,
) {
    let (url, stop) = start_server().await;
    let ch = channel(&url).await;
    let mut control = SessionControlClient::new(ch.clone());
    let id = control
        .start_session(StartSessionRequest {
            scene: "lv".into(),
            scene_toml: String::new(),
        })
        .await
        .unwrap()
        .into_inner()
        .session_id;
    (stop, ch, control, id)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_that_introduces_itself_is_limited_checked_and_shown() {
    let (stop, ch, mut control, id) = lv_session().await;

    let mut link = DeviceLinkClient::new(ch.clone());
    let (tx, rx) = mpsc::channel(64);
    tx.send(sample(&id, 1, TOUCH_X_M + 0.002, Some(weak_arm())))
        .await
        .unwrap();
    let response = tokio::time::timeout(TIMEOUT, link.connect(ReceiverStream::new(rx)))
        .await
        .expect("Connect answers in time")
        .unwrap();
    // The lower of the scene's 10 N and the device's 5 mN.
    let header: f64 = response
        .metadata()
        .get(HEADER_MAX_FORCE)
        .unwrap()
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(header, DEVICE_FORCE_N);
    let mut forces = response.into_inner();

    // Press 3 mm over 0.3 s and hold 0.2 s (a sample every 2 ms), then five samples outside
    // the declared box (x = 30 mm), then one inside again.
    let mut seq = 1;
    let mut largest = 0.0f64;
    let mut answered_outside = 0;
    let press = |k: u64| TOUCH_X_M + 0.002 - 0.005 * (k as f64 / 150.0).min(1.0);
    for k in 1..=250u64 {
        seq += 1;
        tx.send(sample("", seq, press(k), None)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let outside: Vec<u64> = (0..5).map(|i| seq + 1 + i).collect();
    for &s in &outside {
        tx.send(sample("", s, 0.03, None)).await.unwrap();
    }
    seq += 6;
    tx.send(sample("", seq, press(250), None)).await.unwrap();
    let last_seq = seq;
    // Read until the last sample's answer.
    let deadline = tokio::time::Instant::now() + TIMEOUT;
    loop {
        let cmd = tokio::time::timeout_at(deadline, forces.next())
            .await
            .expect("the last sample is answered")
            .expect("stream open")
            .expect("a force command");
        let f = cmd.force_n.unwrap();
        let magnitude = (f.x * f.x + f.y * f.y + f.z * f.z).sqrt();
        assert!(magnitude <= DEVICE_FORCE_N * (1.0 + 1e-12), "{magnitude} N");
        largest = largest.max(magnitude);
        let k_norm = cmd
            .stiffness_n_per_m
            .iter()
            .map(|v| v * v)
            .sum::<f64>()
            .sqrt();
        assert!(
            k_norm <= DEVICE_STIFFNESS_N_PER_M * (1.0 + 1e-12),
            "{k_norm} N/m"
        );
        answered_outside += usize::from(outside.contains(&cmd.seq));
        if cmd.seq >= last_seq {
            break;
        }
    }
    // The organ pushes back with about 30 mN at 3 mm: the clamp was reached.
    assert!(largest > 0.99 * DEVICE_FORCE_N, "largest force {largest} N");
    assert_eq!(
        answered_outside, 0,
        "poses outside the workspace were answered"
    );

    let s = stats(&mut control, &id).await;
    assert_eq!(s.out_of_workspace_samples, 5, "{s:?}");
    assert_eq!(s.rejected_samples, 0, "{s:?}");
    assert_eq!(s.device.as_ref().map(|d| d.name.as_str()), Some("weak-arm"));
    let listed = control
        .list_sessions(ListSessionsRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(listed.session_ids, vec![id.clone()]);
    let summary = &listed.sessions[0];
    assert_eq!(
        (summary.session_id.as_str(), summary.scene.as_str()),
        (id.as_str(), "lv")
    );
    assert_eq!(summary.model_family, "fem");
    assert!(summary.device_connected);
    assert_eq!(summary.device.as_ref(), Some(&weak_arm()));

    // Gone: no device shown any more.
    drop(tx);
    drop(forces);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let listed = control
            .list_sessions(ListSessionsRequest {})
            .await
            .unwrap()
            .into_inner();
        let s = stats(&mut control, &id).await;
        if !listed.sessions[0].device_connected && s.device.is_none() {
            assert!(listed.sessions[0].device.is_none());
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the device never detached"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    control
        .stop_session(StopSessionRequest { session_id: id })
        .await
        .unwrap();
    let _ = stop.send(());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn absurd_capabilities_refuse_the_stream_and_leave_the_session_free() {
    let (stop, ch, mut control, id) = lv_session().await;
    let absurd = [
        DeviceCapabilities {
            max_force_n: f64::NAN,
            ..weak_arm()
        },
        DeviceCapabilities {
            workspace_min_m: Some(Vec3::new(0.03, 0.0, 0.0)),
            ..weak_arm()
        },
        DeviceCapabilities {
            name: "\u{1b}[2J".into(),
            ..weak_arm()
        },
    ];
    for (caps, field) in absurd
        .into_iter()
        .zip(["max_force_n", "workspace_min_m", "name"])
    {
        let mut link = DeviceLinkClient::new(ch.clone());
        let (tx, rx) = mpsc::channel(4);
        tx.send(sample(&id, 1, 0.03, Some(caps))).await.unwrap();
        let e = tokio::time::timeout(TIMEOUT, link.connect(ReceiverStream::new(rx)))
            .await
            .expect("Connect answers in time")
            .expect_err("refused");
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e:?}");
        assert!(e.message().contains(field), "{field}: {}", e.message());
    }
    // An older bridge (no capabilities) connects to the same session at once.
    let mut link = DeviceLinkClient::new(ch.clone());
    let (tx, rx) = mpsc::channel(4);
    tx.send(sample(&id, 1, 0.03, None)).await.unwrap();
    let response = tokio::time::timeout(TIMEOUT, link.connect(ReceiverStream::new(rx)))
        .await
        .expect("Connect answers in time")
        .expect("a plain device connects");
    assert_eq!(
        response
            .metadata()
            .get(HEADER_MAX_FORCE)
            .unwrap()
            .to_str()
            .unwrap(),
        "10",
        "the scene's limit alone"
    );
    let mut forces = response.into_inner();
    let first = tokio::time::timeout(TIMEOUT, forces.next())
        .await
        .expect("answered")
        .unwrap()
        .unwrap();
    assert_eq!(first.seq, 1);
    let s = stats(&mut control, &id).await;
    assert!(s.device.is_none() && s.fault.is_empty(), "{s:?}");
    assert_eq!(s.out_of_workspace_samples, 0);
    drop(tx);
    control
        .stop_session(StopSessionRequest { session_id: id })
        .await
        .unwrap();
    let _ = stop.send(());
}
