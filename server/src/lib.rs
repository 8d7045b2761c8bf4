//! # haptic-server: the `hapticd` daemon as a library
//!
//! [`run`] serves the `haptics.v1` services (plus gRPC health and reflection) on a listener it
//! is given, until a shutdown future resolves; then it stops every session (each servo thread
//! commands zero force and is joined) and the streams end.
//!
//! Modules: [`config`] (layered configuration), [`error`] (the one mapping to `tonic::Status`),
//! [`servo`] (the 1 kHz loop), [`session`] (threads and handoffs per session), [`service`]
//! (gRPC handlers), [`stream`] (surface streams: shared frames, compact encoding, watchers),
//! [`solve`] (static solutions of scene files, behind `haptic-solve`), [`calibrate`]
//! (mass-spring calibration tables, behind `haptic-calibrate`).

pub mod builds;
pub mod calibrate;
pub mod config;
pub mod confine;
pub mod error;
pub mod metrics;
pub mod service;
pub mod servo;
pub mod session;
pub mod solve;
pub mod stream;
pub mod surface_mesh;

use std::future::Future;
use std::sync::Arc;

use haptics_proto::v1::device_link_server::DeviceLinkServer;
use haptics_proto::v1::session_control_server::SessionControlServer;
use haptics_proto::v1::surface_stream_server::SurfaceStreamServer;
use tokio::net::TcpListener;

pub use config::ServerConfig;
pub use error::ServerError;

/// Serves until `shutdown` resolves, then stops all sessions and returns.
///
/// # Errors
/// When the transport fails or the reflection service cannot be built.
pub async fn run(
    listener: TcpListener,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send,
) -> anyhow::Result<()> {
    let manager = Arc::new(session::SessionManager::new(config));
    // Sessions recorded by an earlier process come back (same ids) before anyone can connect.
    for line in manager.restore() {
        tracing::info!("{line}");
    }
    if let Some(addr) = manager.config().metrics_listen {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|e| anyhow::anyhow!("binding the metrics endpoint {addr}: {e}"))?;
        // Printed like the gRPC address, so scripts and tests can find a port-0 endpoint.
        println!("metrics on {}", listener.local_addr()?);
        tokio::spawn(metrics::serve(listener, manager.clone()));
    }
    let services = service::Services::new(manager.clone());
    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_serving::<SessionControlServer<service::Services>>()
        .await;
    health
        .set_serving::<DeviceLinkServer<service::Services>>()
        .await;
    health
        .set_serving::<SurfaceStreamServer<service::Services>>()
        .await;
    // Reflection in both versions: grpcurl and Evans speak `v1`, Python's `grpcio-reflection`
    // and Postman still speak `v1alpha`.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(haptics_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_v1 = reflection().build_v1()?;
    let reflection_v1alpha = reflection().build_v1alpha()?;
    let stop_manager = manager.clone();
    // `Server::tcp_nodelay` is ignored with a custom incoming stream; set it on the incoming,
    // or Nagle's algorithm holds each small ForceCommand for one device period.
    let incoming = tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true));
    let result = tonic::transport::Server::builder()
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(SessionControlServer::new(services.clone()))
        .add_service(DeviceLinkServer::new(services.clone()))
        .add_service(SurfaceStreamServer::new(services))
        .serve_with_incoming_shutdown(incoming, async move {
            shutdown.await;
            tracing::info!("shutting down: stopping sessions");
            let m = stop_manager.clone();
            let _ = tokio::task::spawn_blocking(move || m.stop_all()).await;
        })
        .await;
    manager.stop_all();
    result?;
    Ok(())
}
