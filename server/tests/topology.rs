//! The soft-body seam with a surface whose connectivity changes at run time (as a subdivided
//! mass-spring surface or activated particles will): the servo rewrites the snapshot's
//! triangles only when the topology version changes and never allocates doing it, and a viewer
//! watching the session gets a new keyframe with the new triangles (full and compact streams).

use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use haptic_model::body::{
    BodyInfo, BodyStats, SoftBody, SurfaceCapacity, SurfaceTopology, TickInput, TickOutput,
};
use haptic_model::{DVec3, ModelError};
use haptic_server::ServerConfig;
use haptic_server::service::Services;
use haptic_server::servo::{self, Clock, Pose, ServoCore, ServoHandles, SessionShared};
use haptic_server::session::SessionManager;
use haptics_proto::v1::WatchRequest;
use haptics_proto::v1::surface_stream_server::SurfaceStream;
use tokio_stream::StreamExt;

use crate::counting_alloc;
use counting_alloc::counted;

/// A unit square of two triangles that, every `period` ticks, is split at its centre into four
/// (version 1, 5 vertices) and merged back (version 2, 4 vertices), and so on.
struct SplittingSquare {
    ticks: u64,
    period: u64,
    /// Both connectivities, preallocated.
    coarse: [[u32; 3]; 2],
    fine: [[u32; 3]; 4],
    vertices: [DVec3; 5],
}

impl SplittingSquare {
    fn new(period: u64) -> Self {
        Self {
            ticks: 0,
            period,
            coarse: [[0, 1, 2], [0, 2, 3]],
            fine: [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]],
            vertices: [
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(0.01, 0.0, 0.0),
                DVec3::new(0.01, 0.01, 0.0),
                DVec3::new(0.0, 0.01, 0.0),
                DVec3::new(0.005, 0.005, 0.0),
            ],
        }
    }

    fn version(&self) -> u64 {
        self.ticks / self.period
    }

    fn fine_now(&self) -> bool {
        self.version() % 2 == 1
    }

    fn vertex_count(&self) -> usize {
        if self.fine_now() { 5 } else { 4 }
    }
}

impl SoftBody for SplittingSquare {
    fn tick(&mut self, _: &TickInput) -> Result<TickOutput, ModelError> {
        self.ticks += 1;
        Ok(TickOutput {
            sim_time_s: self.ticks as f64 * 1e-3,
            ..TickOutput::default()
        })
    }

    fn add_point_load(&mut self, _: DVec3, _: DVec3, _: f64) -> Result<(), ModelError> {
        Ok(())
    }

    fn surface_topology(&self) -> SurfaceTopology<'_> {
        SurfaceTopology {
            version: self.version(),
            vertex_count: self.vertex_count(),
            triangles: if self.fine_now() {
                &self.fine
            } else {
                &self.coarse
            },
        }
    }

    fn surface_capacity(&self) -> SurfaceCapacity {
        SurfaceCapacity {
            vertices: 5,
            triangles: 4,
        }
    }

    fn write_surface_positions(&self, out: &mut [f32]) -> f64 {
        assert_eq!(out.len(), 3 * self.vertex_count());
        for (o, v) in out.chunks_exact_mut(3).zip(&self.vertices) {
            o.copy_from_slice(&[v.x as f32, v.y as f32, v.z as f32]);
        }
        0.0
    }

    fn write_surface_rest_positions(&self, out: &mut [f32]) {
        self.write_surface_positions(out);
    }

    fn stats(&self) -> BodyStats {
        BodyStats {
            nodes: 5,
            surface_vertices: self.vertex_count(),
            topology_version: self.version(),
            sim_time_s: self.ticks as f64 * 1e-3,
            ..BodyStats::default()
        }
    }

    fn info(&self) -> BodyInfo {
        BodyInfo {
            family: "test",
            scene: "splitting-square".into(),
            tick_s: 1e-3,
            substeps: 1,
            critical_dt_s: f64::INFINITY,
            probe_radius_m: 2e-3,
            point_loads: haptic_model::body::PointLoadZone::Anywhere,
        }
    }
}

struct ManualClock(Cell<u64>);
impl Clock for ManualClock {
    fn now_us(&self) -> u64 {
        let t = self.0.get();
        self.0.set(t + 5);
        t
    }
}

#[test]
fn snapshots_follow_the_topology_without_allocating() {
    let body: Box<dyn SoftBody> = Box::new(SplittingSquare::new(40));
    let shared = Arc::new(SessionShared::default());
    let (ends, handles) = servo::channels(body.as_ref());
    let ServoHandles {
        pose: mut pose_in,
        snapshot: mut snap_out,
        ..
    } = handles;
    let mut core = ServoCore::new(body, ends, shared.clone(), 1, 10);
    shared.watchers.store(1, Ordering::Relaxed);
    pose_in.write(Pose {
        connected: true,
        ..Pose::default()
    });
    let clock = ManualClock(Cell::new(0));
    let mut seen = Vec::new();
    let mut allocations = 0;
    for _ in 0..200 {
        let now = clock.now_us();
        allocations += counted(|| core.tick(now, &clock)).1;
        snap_out.update();
        let s = snap_out.output_buffer();
        let triangles = if s.topology_version % 2 == 1 { 4 } else { 2 };
        assert_eq!(
            s.triangles.len(),
            3 * triangles,
            "version {}",
            s.topology_version
        );
        assert_eq!(s.positions_m.len(), s.rest_positions_m.len());
        assert_eq!(s.positions_m.len(), 3 * (triangles / 2 + 3));
        if seen.last() != Some(&s.topology_version) {
            seen.push(s.topology_version);
        }
    }
    assert_eq!(allocations, 0, "a servo tick allocated");
    // 200 ticks of 40: versions 0 to 5, each seen by the snapshot.
    assert_eq!(seen, [0, 1, 2, 3, 4, 5]);
}

#[tokio::test]
async fn a_viewer_gets_a_keyframe_when_the_topology_changes() {
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let session = manager
        .start_body(Box::new(SplittingSquare::new(300)))
        .unwrap();
    let services = Services::new(manager.clone());
    let response = services
        .watch(tonic::Request::new(WatchRequest {
            session_id: session.id.clone(),
            max_rate_hz: 100.0,
            ..WatchRequest::default()
        }))
        .await
        .unwrap();
    let mut frames = response.into_inner();
    let mut keyframes = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while keyframes.len() < 3 && tokio::time::Instant::now() < deadline {
        let Ok(Some(frame)) = tokio::time::timeout(Duration::from_secs(5), frames.next()).await
        else {
            break;
        };
        let frame = frame.unwrap();
        let vertices = frame.positions_m.len() / 3;
        if frame.keyframe {
            assert_eq!(frame.rest_positions_m.len(), frame.positions_m.len());
            keyframes.push((vertices, frame.triangles.len() / 3));
        } else {
            assert!(frame.triangles.is_empty() && frame.rest_positions_m.is_empty());
            // Positions always match the connectivity of the last keyframe.
            assert_eq!(Some(&vertices), keyframes.last().map(|k| &k.0));
        }
    }
    manager.stop(&session.id).unwrap();
    // The first keyframe, then one per topology change: split (5 vertices, 4 triangles), merged.
    assert!(keyframes.len() >= 3, "keyframes {keyframes:?}");
    assert_eq!(&keyframes[..3], &[(4, 2), (5, 4), (4, 2)]);
}

#[tokio::test]
async fn a_compact_viewer_gets_a_keyframe_with_triangles_when_the_topology_changes() {
    use haptics_proto::delta::DeltaCodec;
    use haptics_proto::v1::SurfaceEncoding;
    let manager = Arc::new(SessionManager::new(ServerConfig::default()));
    let session = manager
        .start_body(Box::new(SplittingSquare::new(300)))
        .unwrap();
    let services = Services::new(manager.clone());
    let mut frames = services
        .watch(tonic::Request::new(WatchRequest {
            session_id: session.id.clone(),
            max_rate_hz: 100.0,
            encoding: SurfaceEncoding::Delta as i32,
            quantum_m: 0.0,
        }))
        .await
        .unwrap()
        .into_inner();
    // (topology version, vertices, triangles) of every keyframe that brought triangles.
    let mut keyframes = Vec::new();
    let mut state: Option<(u64, DeltaCodec, Vec<f32>)> = None;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while keyframes.len() < 3 && tokio::time::Instant::now() < deadline {
        let Ok(Some(frame)) = tokio::time::timeout(Duration::from_secs(5), frames.next()).await
        else {
            break;
        };
        let f = frame.unwrap();
        if f.keyframe && !f.triangles.is_empty() {
            let n = f.positions_m.len() / 3;
            keyframes.push((f.topology_version, n, f.triangles.len() / 3));
            state = Some((
                f.topology_version,
                DeltaCodec::new(n, &f.triangles).unwrap(),
                f.positions_m.clone(),
            ));
        } else if f.keyframe && !f.positions_m.is_empty() {
            let s = state.as_mut().expect("a topology first");
            s.2 = f.positions_m.clone();
        } else if f.keyframe {
            // Chained: the new reference is the old one plus the step.
            let s = state.as_mut().expect("a topology first");
            let mut p = vec![0.0; s.2.len()];
            s.1.decode(&s.2, &f.reference_delta, f.quantum_m, &mut p)
                .unwrap();
            s.2 = p;
        }
        // Every frame is of the topology the last keyframe brought, and decodes against it.
        let (version, codec, reference) = state.as_ref().expect("keyframe first");
        assert_eq!(
            f.topology_version, *version,
            "a new topology without triangles"
        );
        let mut p = vec![0.0; reference.len()];
        codec
            .decode(reference, &f.position_delta, f.quantum_m, &mut p)
            .unwrap();
    }
    manager.stop(&session.id).unwrap();
    assert!(keyframes.len() >= 3, "keyframes {keyframes:?}");
    let shapes: Vec<_> = keyframes[..3].iter().map(|k| (k.1, k.2)).collect();
    assert_eq!(shapes, [(4, 2), (5, 4), (4, 2)]);
}
