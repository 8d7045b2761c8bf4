//! A mock `hapticd` for the client tests: canned `SurfaceStream` and `SessionControl` services
//! on a real loopback port (127.0.0.1:0), stopped by a oneshot.
//!
//! Sessions known to `Watch`:
//! - `ok`: a keyframe (icosahedron, radius 30 mm), then 5 frames pushing vertex 0 outwards by
//!   1..5 mm with the probe on it, then the stream ends (as when the server stops the session);
//! - `bad`: keyframe, a frame with too few positions, a keyframe whose triangles reference a
//!   missing vertex, then 2 good frames, then the end;
//! - `forever`: a keyframe, then a frame every 5 ms until the client goes away;
//! - `fail`: keyframe, one frame, then an `INTERNAL` error;
//! - anything else: `NOT_FOUND`.
#![allow(dead_code)]

use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use haptics_proto::v1::session_control_server::{SessionControl, SessionControlServer};
use haptics_proto::v1::surface_stream_server::{SurfaceStream, SurfaceStreamServer};
use haptics_proto::v1::*;
use tokio::sync::{mpsc, oneshot};
use tokio_stream::Stream;
use tokio_stream::wrappers::{ReceiverStream, TcpListenerStream};
use tonic::{Request, Response, Status};

/// Requests the mock received, for assertions.
#[derive(Debug, Default)]
pub struct Recorded {
    pub forces: Vec<ApplyForceRequest>,
    pub starts: Vec<StartSessionRequest>,
    pub stops: Vec<String>,
}

#[derive(Clone, Default)]
pub struct Mock {
    pub recorded: Arc<Mutex<Recorded>>,
}

pub const ICO_RADIUS_M: f32 = 0.03;

/// A regular icosahedron of radius `ICO_RADIUS_M` around the origin: 12 vertices, 20 triangles.
pub fn icosahedron() -> (Vec<f32>, Vec<u32>) {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let raw = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    let mut pos = Vec::new();
    for v in raw {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        pos.extend(v.iter().map(|c| c / n * ICO_RADIUS_M));
    }
    let tris = vec![
        0, 11, 5, 0, 5, 1, 0, 1, 7, 0, 7, 10, 0, 10, 11, 1, 5, 9, 5, 11, 4, 11, 10, 2, 10, 7, 6, 7,
        1, 8, 3, 9, 4, 3, 4, 2, 3, 2, 6, 3, 6, 8, 3, 8, 9, 4, 9, 5, 2, 4, 11, 6, 2, 10, 8, 6, 7, 9,
        8, 1,
    ];
    (pos, tris)
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_micros() as u64
}

/// Frame `k` of the `ok` session: vertex 0 pushed outwards by `k` mm, the probe on it.
pub fn pushed_frame(k: u64, keyframe: bool) -> SurfaceFrame {
    let (mut pos, tris) = icosahedron();
    let d = k as f32 * 1e-3;
    let v0 = [pos[0], pos[1], pos[2]];
    let n = ICO_RADIUS_M;
    for c in 0..3 {
        pos[c] += v0[c] / n * d;
    }
    let probe = [
        (v0[0] / n * (n + d + 0.004)) as f64,
        (v0[1] / n * (n + d + 0.004)) as f64,
        (v0[2] / n * (n + d + 0.004)) as f64,
    ];
    SurfaceFrame {
        frame: k,
        sim_time_s: k as f64 * 0.01,
        keyframe,
        positions_m: pos,
        triangles: if keyframe { tris } else { Vec::new() },
        probe_position_m: Some(Vec3::new(probe[0], probe[1], probe[2])),
        contact_force_n: Some(Vec3::new(
            probe[0] / 0.034 * k as f64 * 0.4,
            probe[1] / 0.034 * k as f64 * 0.4,
            probe[2] / 0.034 * k as f64 * 0.4,
        )),
        in_contact: k > 0,
        probe_radius_m: 0.004,
        server_time_us: now_us(),
        max_displacement_m: d as f64,
        rest_positions_m: Vec::new(),
        ..SurfaceFrame::default()
    }
}

type FrameStream = Pin<Box<dyn Stream<Item = Result<SurfaceFrame, Status>> + Send>>;

#[tonic::async_trait]
impl SurfaceStream for Mock {
    type WatchStream = FrameStream;

    async fn request_keyframe(
        &self,
        _: Request<KeyframeRequest>,
    ) -> Result<Response<KeyframeResponse>, Status> {
        Err(Status::unimplemented("the mock has no compact streams"))
    }

    async fn watch(
        &self,
        request: Request<WatchRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        let id = request.into_inner().session_id;
        let (tx, rx) = mpsc::channel(16);
        match id.as_str() {
            "ok" => {
                tokio::spawn(async move {
                    for k in 0..=5 {
                        if tx.send(Ok(pushed_frame(k, k == 0))).await.is_err() {
                            return;
                        }
                    }
                });
            }
            "bad" => {
                tokio::spawn(async move {
                    let mut short = pushed_frame(1, false);
                    short.positions_m.truncate(6);
                    let mut missing = pushed_frame(2, true);
                    missing.triangles[5] = 99;
                    let frames = [
                        pushed_frame(0, true),
                        short,
                        missing,
                        pushed_frame(3, false),
                        pushed_frame(4, false),
                    ];
                    for f in frames {
                        if tx.send(Ok(f)).await.is_err() {
                            return;
                        }
                    }
                });
            }
            "forever" => {
                tokio::spawn(async move {
                    let mut k = 0;
                    loop {
                        if tx.send(Ok(pushed_frame(k % 5, k == 0))).await.is_err() {
                            return; // the viewer went away
                        }
                        k += 1;
                        tokio::time::sleep(Duration::from_millis(5)).await;
                    }
                });
            }
            "fail" => {
                tokio::spawn(async move {
                    let _ = tx.send(Ok(pushed_frame(0, true))).await;
                    let _ = tx.send(Ok(pushed_frame(1, false))).await;
                    let _ = tx.send(Err(Status::internal("boom"))).await;
                });
            }
            other => return Err(Status::not_found(format!("no session '{other}'"))),
        }
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// A Phantom Touch as it introduces itself (its published ratings; scene frame = device frame).
pub fn touch() -> DeviceCapabilities {
    DeviceCapabilities {
        name: "touch".into(),
        sensed_degrees_of_freedom: 6,
        actuated_degrees_of_freedom: 3,
        workspace_min_m: Some(Vec3::from([-0.08, -0.06, -0.035])),
        workspace_max_m: Some(Vec3::from([0.08, 0.06, 0.035])),
        max_force_n: 3.3,
        max_continuous_force_n: 0.88,
        max_stiffness_n_per_m: 1260.0,
        native_rate_hz: 1000.0,
    }
}

/// Statistics with every field set to a distinct non-default value.
pub fn canned_stats(id: &str) -> SessionStats {
    SessionStats {
        session_id: id.to_string(),
        loop_rate_hz: 999.7,
        step_p50_us: 123.4,
        step_p99_us: 456.7,
        step_max_us: 890.1,
        overruns: 3,
        steps: 100_000,
        pose_to_force_p50_us: 55.5,
        pose_to_force_p99_us: 333.3,
        rejected_samples: 2,
        sim_time_s: 100.0,
        substeps: 4,
        in_contact: true,
        peak_force_n: 2.5,
        max_displacement_m: 0.004_25,
        faulted: true,
        fault: "NaN in node 17".into(),
        device_samples: 99_000,
        scene: "lv".into(),
        nodes: 412,
        tetrahedra: 1352,
        model_family: "fem".into(),
        active_elements: 1200,
        total_particles: 27_988,
        active_particles: 600,
        surface_vertices: 321,
        topology_version: 7,
        out_of_order_samples: 6,
        device_silent: true,
        device_silences: 8,
        overrunning: true,
        demoted: false,
        watchers: 3,
        watcher_frames_sent: 1234,
        watcher_frames_dropped: 5,
        watcher_bytes_sent: 987_654,
        watcher_queued_bytes: 4321,
        watcher_queue_limit_bytes: 65_536,
        region_swaps: 12,
        region_preparation_s: 1.234,
        region_tiles: 69,
        region_tiles_ready: 12,
        region_tiles_loaded: 10,
        region_tiles_refused: 1,
        region_tile_memory_bytes: 123_456_789,
        region_tiles_dropped: 3,
        region_tiles_reloaded: 2,
        region_tile_misses: 1,
        region_unmapped_swaps: 0,
        region_cache_error: "/var/cache/hapticd/regions/0a1b-00003.tile: damaged".into(),
        contact_ticks: 5_000,
        companion_ticks: 40,
        device: Some(touch()),
        out_of_workspace_samples: 9,
        threads: 2,
        pool_wait_us_max: 35,
        max_tools: 2,
        tools: vec![
            ToolStats {
                tool_id: "left".into(),
                slot: 0,
                connected: true,
                in_contact: true,
                force_n: 0.125,
                peak_force_n: 0.5,
                pose_to_force_p50_us: 44.4,
                pose_to_force_p99_us: 222.2,
                device_samples: 60_000,
                rejected_samples: 1,
                out_of_order_samples: 2,
                out_of_workspace_samples: 3,
                device_silent: false,
                contact_ticks: 4_000,
                device: Some(touch()),
            },
            ToolStats {
                tool_id: "right".into(),
                slot: 1,
                force_n: 0.25,
                device_samples: 39_000,
                ..ToolStats::default()
            },
        ],
    }
}

#[tonic::async_trait]
impl SessionControl for Mock {
    async fn list_scenes(
        &self,
        _: Request<ListScenesRequest>,
    ) -> Result<Response<ListScenesResponse>, Status> {
        Ok(Response::new(ListScenesResponse {
            scenes: vec![
                SceneInfo {
                    name: "ellipsoid".into(),
                    description: "ellipsoid shell".into(),
                    nodes: 120,
                    tetrahedra: 188,
                },
                SceneInfo {
                    name: "lv".into(),
                    description: "left ventricle".into(),
                    nodes: 412,
                    tetrahedra: 1352,
                },
            ],
        }))
    }

    async fn start_session(
        &self,
        request: Request<StartSessionRequest>,
    ) -> Result<Response<StartSessionResponse>, Status> {
        let r = request.into_inner();
        self.recorded.lock().unwrap().starts.push(r.clone());
        let id = if !r.scene_toml.is_empty() {
            "s-toml"
        } else if r.scene == "lv" {
            "s-1"
        } else {
            return Err(Status::not_found(format!("no scene '{}'", r.scene)));
        };
        Ok(Response::new(StartSessionResponse {
            session_id: id.into(),
            nodes: 412,
            tetrahedra: 1352,
            substeps: 4,
            critical_dt_s: 2.5e-4,
        }))
    }

    async fn stop_session(
        &self,
        request: Request<StopSessionRequest>,
    ) -> Result<Response<StopSessionResponse>, Status> {
        let id = request.into_inner().session_id;
        if id != "s-1" {
            return Err(Status::not_found(format!("no session '{id}'")));
        }
        self.recorded.lock().unwrap().stops.push(id);
        Ok(Response::new(StopSessionResponse {}))
    }

    async fn apply_force(
        &self,
        request: Request<ApplyForceRequest>,
    ) -> Result<Response<ApplyForceResponse>, Status> {
        let r = request.into_inner();
        if r.session_id != "s-1" {
            return Err(Status::not_found(format!("no session '{}'", r.session_id)));
        }
        self.recorded.lock().unwrap().forces.push(r);
        Ok(Response::new(ApplyForceResponse {}))
    }

    async fn get_stats(
        &self,
        request: Request<GetStatsRequest>,
    ) -> Result<Response<SessionStats>, Status> {
        let id = request.into_inner().session_id;
        if id != "s-1" {
            return Err(Status::not_found(format!("no session '{id}'")));
        }
        Ok(Response::new(canned_stats(&id)))
    }

    async fn list_sessions(
        &self,
        _: Request<ListSessionsRequest>,
    ) -> Result<Response<ListSessionsResponse>, Status> {
        Ok(Response::new(ListSessionsResponse {
            session_ids: vec!["s-1".into(), "s-2".into()],
            sessions: vec![
                SessionSummary {
                    session_id: "s-1".into(),
                    scene: "lv".into(),
                    model_family: "fem".into(),
                    device_connected: true,
                    device: Some(touch()),
                    max_tools: 2,
                    tools: vec![ToolSummary {
                        tool_id: "left".into(),
                        slot: 0,
                        device: Some(touch()),
                    }],
                },
                SessionSummary {
                    session_id: "s-2".into(),
                    scene: "lv-hybrid".into(),
                    model_family: "hybrid".into(),
                    device_connected: false,
                    device: None,
                    max_tools: 1,
                    tools: Vec::new(),
                },
            ],
        }))
    }
}

/// A running mock server; dropping it stops the server.
pub struct MockServer {
    pub url: String,
    pub mock: Mock,
    _stop: oneshot::Sender<()>,
}

/// Serves the mock on 127.0.0.1:0.
pub async fn serve() -> MockServer {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let mock = Mock::default();
    let (stop, stopped) = oneshot::channel::<()>();
    let svc = mock.clone();
    tokio::spawn(async move {
        tonic::transport::Server::builder()
            .add_service(SurfaceStreamServer::new(svc.clone()))
            .add_service(SessionControlServer::new(svc))
            .serve_with_incoming_shutdown(TcpListenerStream::new(listener), async {
                let _ = stopped.await;
            })
            .await
            .unwrap();
    });
    MockServer {
        url,
        mock,
        _stop: stop,
    }
}

/// A fresh, empty output directory under the cargo target tmp dir (kept for inspection).
pub fn out_dir(name: &str) -> std::path::PathBuf {
    let d = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("haptic-client")
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    d
}
