//! Several tools in one session (issue 50, section 1), over real `DeviceLink` streams on
//! 127.0.0.1:0 against the wall test body (`common/tools.rs`: slot k's force is (k + 1) x 100 N/m
//! x depth, so a force routed to the wrong stream shows): two tools each get their own force
//! and press in the same ticks; a third tool beyond the limit gets RESOURCE_EXHAUSTED, a second
//! stream of a connected tool FAILED_PRECONDITION; a tool named by the scene takes its own slot;
//! one tool disconnecting leaves the other's force continuous; `GetStats` and `ListSessions`
//! report per tool.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use haptic_server::ServerConfig;
use haptic_server::service::Services;
use haptic_server::session::{Session, SessionManager};
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::device_link_server::DeviceLinkServer;
use haptics_proto::v1::session_control_client::SessionControlClient;
use haptics_proto::v1::session_control_server::SessionControlServer;
use haptics_proto::v1::{
    DeviceSample, ForceCommand, GetStatsRequest, ListSessionsRequest, SessionStats, Vec3,
};
use tokio::sync::mpsc;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

#[path = "common/tools.rs"]
mod wall;
use wall::{WALL_STIFFNESS_N_PER_M, Wall};

const TIMEOUT: Duration = Duration::from_secs(30);
/// Depth of every tool into the wall, m.
const DEPTH_M: f64 = 0.001;

/// A daemon's services over `manager` on 127.0.0.1:0; a channel to it.
async fn serve(manager: Arc<SessionManager>) -> Channel {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let services = Services::new(manager);
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(DeviceLinkServer::new(services.clone()))
            .add_service(SessionControlServer::new(services))
            .serve_with_incoming(tonic::transport::server::TcpIncoming::from(listener)),
    );
    tonic::transport::Endpoint::from_shared(url)
        .unwrap()
        .connect()
        .await
        .unwrap()
}

/// A tool's device stream: samples at `x` every millisecond until the returned task is
/// aborted (the stream then ends); the answer, or the refusal.
async fn press(
    ch: &Channel,
    session: &str,
    tool: &str,
    x: f64,
) -> (
    Result<tonic::Streaming<ForceCommand>, tonic::Status>,
    tokio::task::JoinHandle<()>,
) {
    let (tx, rx) = mpsc::channel(16);
    let (session, tool) = (session.to_owned(), tool.to_owned());
    let sender = tokio::spawn(async move {
        for seq in 1.. {
            let first = seq == 1;
            let s = DeviceSample {
                session_id: if first {
                    session.clone()
                } else {
                    String::new()
                },
                seq,
                device_time_us: seq * 1000,
                position_m: Some(Vec3::new(x, 0.0, 0.0)),
                velocity_m_per_s: Some(Vec3::new(0.0, 0.0, 0.0)),
                capabilities: None,
                tool_id: if first { tool.clone() } else { String::new() },
            };
            if tx.send(s).await.is_err() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    });
    let answer = tokio::time::timeout(
        TIMEOUT,
        DeviceLinkClient::new(ch.clone()).connect(ReceiverStream::new(rx)),
    )
    .await
    .expect("connect answers")
    .map(tonic::Response::into_inner);
    (answer, sender)
}

/// The force of the next `n` commands of `forces` (x component, N).
async fn next_forces(forces: &mut tonic::Streaming<ForceCommand>, n: usize) -> Vec<f64> {
    let mut out = Vec::new();
    while out.len() < n {
        let c = tokio::time::timeout(TIMEOUT, forces.next())
            .await
            .expect("a force command in time")
            .expect("the stream goes on")
            .expect("a command");
        out.push(c.force_n.unwrap().x);
    }
    out
}

async fn stats(ch: &Channel, id: &str) -> SessionStats {
    SessionControlClient::new(ch.clone())
        .get_stats(GetStatsRequest {
            session_id: id.into(),
        })
        .await
        .unwrap()
        .into_inner()
}

/// Polls the statistics until `done` holds (statistics are published every 100 ticks).
async fn stats_until(ch: &Channel, id: &str, done: impl Fn(&SessionStats) -> bool) -> SessionStats {
    let t0 = std::time::Instant::now();
    loop {
        let s = stats(ch, id).await;
        if done(&s) || t0.elapsed() > TIMEOUT {
            return s;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The force slot `k` renders at [`DEPTH_M`], N.
fn slot_force(k: usize) -> f64 {
    (k + 1) as f64 * WALL_STIFFNESS_N_PER_M * DEPTH_M
}

fn start(manager: &SessionManager, body: Wall, names: &[&str]) -> Arc<Session> {
    let names: Vec<_> = names
        .iter()
        .map(|n| haptic_server::tool::NamedTool::id(n))
        .collect();
    manager
        .start_body_with_tools(Box::new(body), &names)
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_tools_get_their_own_forces_a_third_is_refused_and_one_leaving_spares_the_other() {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let body = Wall::new(2, &[]);
    let together = body.ticks_with_several_contacts.clone();
    let session = start(&manager, body, &[]);
    let ch = serve(manager.clone()).await;
    let id = session.id.clone();

    // Left first (slot 0), then right (slot 1).
    let (left, left_task) = press(&ch, &id, "left", -DEPTH_M).await;
    let mut left = left.expect("left connects");
    next_forces(&mut left, 1).await;
    let (right, right_task) = press(&ch, &id, "right", -DEPTH_M).await;
    let mut right = right.expect("right connects");
    // Each stream renders its own slot's force (after any command answering a pose from
    // before the wall was reached, of which there are none: every pose is inside).
    for f in next_forces(&mut left, 50).await {
        assert!((f - slot_force(0)).abs() < 1e-12, "left got {f}");
    }
    for f in next_forces(&mut right, 50).await {
        assert!((f - slot_force(1)).abs() < 1e-12, "right got {f}");
    }
    // Both contacts acted in the same ticks.
    assert!(together.load(Ordering::Relaxed) > 10);

    // A third tool: beyond the limit of two. A second stream of "left": refused as before.
    let (third, third_task) = press(&ch, &id, "third", -DEPTH_M).await;
    let e = third.expect_err("a third tool is refused");
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e}");
    assert!(e.message().contains("at most 2 tools"), "{e}");
    third_task.abort();
    let (again, again_task) = press(&ch, &id, "left", -DEPTH_M).await;
    let e = again.expect_err("a second left is refused");
    assert_eq!(e.code(), tonic::Code::FailedPrecondition, "{e}");
    again_task.abort();

    // Per-tool statistics.
    let s = stats_until(&ch, &id, |s| {
        s.tools.len() == 2
            && s.tools
                .iter()
                .all(|t| t.in_contact && t.device_samples > 20)
    })
    .await;
    assert_eq!(s.max_tools, 2);
    let (l, r) = (&s.tools[0], &s.tools[1]);
    assert_eq!((l.tool_id.as_str(), l.slot, l.connected), ("left", 0, true));
    assert_eq!(
        (r.tool_id.as_str(), r.slot, r.connected),
        ("right", 1, true)
    );
    assert!((l.force_n - slot_force(0)).abs() < 1e-12, "{l:?}");
    assert!((r.force_n - slot_force(1)).abs() < 1e-12, "{r:?}");
    assert!(l.pose_to_force_p99_us > 0.0 && r.pose_to_force_p99_us > 0.0);
    eprintln!(
        "pose-to-force p50/p99: left {}/{} us, right {}/{} us; samples {} + {}",
        l.pose_to_force_p50_us,
        l.pose_to_force_p99_us,
        r.pose_to_force_p50_us,
        r.pose_to_force_p99_us,
        l.device_samples,
        r.device_samples
    );
    assert!(s.in_contact && (s.peak_force_n - slot_force(1)).abs() < 1e-12);
    assert_eq!(s.device_samples, l.device_samples + r.device_samples);
    // The same per tool in the metrics (labels tool and slot).
    let text =
        haptic_server::metrics::render(&haptic_server::metrics::registry(manager.clone())).unwrap();
    for (tool, slot) in [("left", 0), ("right", 1)] {
        let labels =
            format!(r#"session="{id}",scene="wall",family="wall",tool="{tool}",slot="{slot}""#);
        let value = |name: &str| {
            let key = format!("{name}{{{labels}}} ");
            text.lines()
                .find_map(|l| l.strip_prefix(key.as_str()))
                .and_then(|v| v.trim().parse::<f64>().ok())
                .unwrap_or_else(|| panic!("{key} in {text}"))
        };
        assert_eq!(value("hapticd_tool_connected"), 1.0);
        assert_eq!(value("hapticd_tool_in_contact"), 1.0);
        assert!(value("hapticd_tool_force_newtons") > 0.0);
        assert!(value("hapticd_tool_pose_to_force_seconds_count") > 10.0);
        assert_eq!(value("hapticd_tool_rejected_samples_total"), 0.0);
    }

    // Left leaves: its slot frees and its contact is released; right's force goes on unchanged.
    left_task.abort();
    let mut previous = slot_force(1);
    for f in next_forces(&mut right, 300).await {
        assert!((f - previous).abs() <= 0.07 * previous, "{previous} -> {f}");
        previous = f;
    }
    let s = stats_until(&ch, &id, |s| {
        !s.tools[0].connected && !s.tools[0].in_contact
    })
    .await;
    assert!(!s.tools[0].connected && !s.tools[0].in_contact, "{s:?}");
    assert!(s.tools[1].connected && s.tools[1].in_contact, "{s:?}");
    let listed = SessionControlClient::new(ch.clone())
        .list_sessions(ListSessionsRequest {})
        .await
        .unwrap()
        .into_inner();
    let summary = &listed.sessions[0];
    assert_eq!(summary.max_tools, 2);
    let tools: Vec<_> = summary
        .tools
        .iter()
        .map(|t| (t.tool_id.as_str(), t.slot))
        .collect();
    assert_eq!(tools, [("right", 1)]);
    // The freed slot takes a new tool.
    let (back, back_task) = press(&ch, &id, "left-again", -DEPTH_M).await;
    let mut back = back.expect("a freed slot takes a tool");
    let f = next_forces(&mut back, 5).await;
    assert!((f[4] - slot_force(0)).abs() < 1e-12, "{f:?}");
    back_task.abort();
    right_task.abort();
    manager.stop(&id).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_named_tool_takes_its_own_slot_and_unnamed_ones_skip_it() {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let session = start(&manager, Wall::new(2, &["", "right"]), &["", "right"]);
    let ch = serve(manager.clone()).await;
    let id = session.id.clone();
    // "right" first: slot 1 all the same.
    let (right, right_task) = press(&ch, &id, "right", -DEPTH_M).await;
    let f = next_forces(&mut right.expect("right"), 5).await;
    assert!((f[4] - slot_force(1)).abs() < 1e-12, "{f:?}");
    // Both slots are named: another tool has none.
    let (other, other_task) = press(&ch, &id, "other", -DEPTH_M).await;
    assert_eq!(
        other.expect_err("no slot").code(),
        tonic::Code::ResourceExhausted
    );
    other_task.abort();
    // The default tool ("") takes its slot 0.
    let (default, default_task) = press(&ch, &id, "", -DEPTH_M).await;
    let f = next_forces(&mut default.expect("default"), 5).await;
    assert!((f[4] - slot_force(0)).abs() < 1e-12, "{f:?}");
    // A bad tool id is refused before the session is touched.
    let (bad, bad_task) = press(&ch, &id, "a b", -DEPTH_M).await;
    assert_eq!(
        bad.expect_err("bad id").code(),
        tonic::Code::InvalidArgument
    );
    bad_task.abort();
    default_task.abort();
    right_task.abort();
    manager.stop(&id).unwrap();
}
