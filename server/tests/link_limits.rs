//! `DeviceLink.Connect` answers with the scene's limits in its response headers, which the
//! bridge's guard applies (issue 15): `haptics-max-force-n` is the scene's `probe.max_force_n`
//! and `haptics-max-force-rate-n-per-s` its coupling stiffness times 1 m/s
//! (`LinkLimits::of_scene`). The server runs in process on 127.0.0.1:0; one scene's limits are
//! below every device's defaults (the sim device's 10 N and 1000 N/s, the HapticMaster's 100 N
//! and 5000 N/s), so a bridge that honours them is the one they bind.

use std::time::Duration;

use haptic_server::ServerConfig;
use haptic_server::service::{HEADER_MAX_FORCE, HEADER_MAX_FORCE_RATE, HEADER_SERVER_INSTANCE};
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::{DeviceSample, StartSessionRequest, StopSessionRequest};
use tokio_stream::wrappers::ReceiverStream;

const TIMEOUT: Duration = Duration::from_secs(30);

/// Starts a session (built-in `scene`, or `scene_toml` when not empty), connects a device
/// stream to it and returns the response headers.
async fn connect_headers(
    url: &str,
    scene: &str,
    scene_toml: String,
) -> (String, tonic::metadata::MetadataMap) {
    let channel = tonic::transport::Endpoint::from_shared(url.to_owned())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut control = SessionControlClient::new(channel.clone());
    let id = control
        .start_session(StartSessionRequest {
            scene: scene.to_owned(),
            scene_toml,
        })
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let mut link = DeviceLinkClient::new(channel);
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    // Far from the body: no contact, just a stream that names its session.
    tx.send(DeviceSample {
        session_id: id.clone(),
        seq: 1,
        device_time_us: 1,
        position_m: Some([0.1, 0.1, 0.1].into()),
        velocity_m_per_s: Some([0.0; 3].into()),
        capabilities: None,
        tool_id: String::new(),
    })
    .await
    .unwrap();
    let response = tokio::time::timeout(TIMEOUT, link.connect(ReceiverStream::new(rx)))
        .await
        .expect("Connect answers in time")
        .unwrap();
    let headers = response.metadata().clone();
    drop(tx);
    drop(response);
    control
        .stop_session(StopSessionRequest {
            session_id: id.clone(),
        })
        .await
        .unwrap();
    (id, headers)
}

fn header_f64(headers: &tonic::metadata::MetadataMap, name: &str) -> f64 {
    let v = headers
        .get(name)
        .unwrap_or_else(|| panic!("no {name} header in {headers:?}"));
    v.to_str()
        .unwrap()
        .parse()
        .unwrap_or_else(|e| panic!("{name}: {v:?}: {e}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connect_sends_the_scenes_force_and_force_rate_limits() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(haptic_server::run(
        listener,
        ServerConfig::default(),
        async move {
            let _ = stopped.await;
        },
    ));

    // The built-in LV: 10 N, 300 N/m x 1 m/s.
    let (_, lv) = connect_headers(&url, "lv", String::new()).await;
    assert_eq!(header_f64(&lv, HEADER_MAX_FORCE), 10.0, "{lv:?}");
    assert_eq!(header_f64(&lv, HEADER_MAX_FORCE_RATE), 300.0, "{lv:?}");
    let instance = lv.get(HEADER_SERVER_INSTANCE).expect("instance header");
    assert!(!instance.is_empty());

    // The same LV with limits below every device's: 2.5 N, 150 N/m x 1 m/s.
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/scenes/lv.toml");
    let toml = std::fs::read_to_string(path).unwrap();
    for line in [
        "\nmax_force_n = 10.0\n",
        "\ncoupling_stiffness_n_per_m = 300.0\n",
    ] {
        assert!(toml.contains(line), "{path} no longer has {line:?}");
    }
    let toml = toml
        .replace("\nmax_force_n = 10.0\n", "\nmax_force_n = 2.5\n")
        .replace(
            "\ncoupling_stiffness_n_per_m = 300.0\n",
            "\ncoupling_stiffness_n_per_m = 150.0\n",
        );
    let (_, low) = connect_headers(&url, "", toml).await;
    assert_eq!(header_f64(&low, HEADER_MAX_FORCE), 2.5, "{low:?}");
    assert_eq!(header_f64(&low, HEADER_MAX_FORCE_RATE), 150.0, "{low:?}");
    assert_eq!(low.get(HEADER_SERVER_INSTANCE), Some(instance));

    let _ = stop.send(());
    tokio::time::timeout(TIMEOUT, server)
        .await
        .expect("the server stops")
        .unwrap()
        .unwrap();
}
