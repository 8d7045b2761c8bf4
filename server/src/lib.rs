//! # haptic-server: the `hapticd` daemon as a library
//!
//! [`run`] serves the `haptics.v1` services (plus gRPC health and reflection) on a listener it
//! is given, until a shutdown future resolves; then it stops every session (each servo thread
//! commands zero force and is joined) and the streams end.
//!
//! Modules: [`auth`] (tokens, roles, failed attempts), [`config`] (layered configuration), [`error`] (the one mapping to `tonic::Status`),
//! [`servo`] (the 1 kHz loop), [`session`] (threads and handoffs per session), [`service`]
//! (gRPC handlers), [`stream`] (surface streams: shared frames, compact encoding, watchers),
//! [`solve`] (static solutions of scene files, behind `haptic-solve`), [`calibrate`]
//! (mass-spring calibration tables, behind `haptic-calibrate`).

pub mod auth;
pub mod builds;
pub mod calibrate;
pub mod config;
pub mod confine;
pub mod cores;
pub mod deadband;
pub mod device;
pub mod error;
pub mod frame;
pub mod metrics;
pub mod regions;
pub mod service;
pub mod servo;
pub mod session;
pub mod solve;
pub mod stream;
pub mod surface_mesh;
pub mod tool;

use std::future::Future;
use std::sync::Arc;

use haptics_proto::v1::device_link_server::DeviceLinkServer;
use haptics_proto::v1::session_control_server::SessionControlServer;
use haptics_proto::v1::surface_stream_server::SurfaceStreamServer;
use tokio::net::TcpListener;

pub use config::ServerConfig;
pub use error::ServerError;

/// Serves until `shutdown` resolves, then stops all sessions and returns. Prints
/// `listening on ADDR` on stdout once access control (tokens, TLS) is set up.
///
/// # Errors
/// A bad directory, tokens file or TLS file ([`ServerError::Config`], [`ServerError::Tls`],
/// ...), a metrics address that cannot be bound ([`ServerError::Bind`]), or a failing
/// transport or reflection service ([`ServerError::Transport`], [`ServerError::Reflection`]).
pub async fn run(
    listener: TcpListener,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServerError> {
    let mut config = config;
    // What clients may read is checked before anything listens (issue 47).
    config.check_directories()?;
    let manager = Arc::new(session::SessionManager::new(config));
    // Region caches to fill ahead of sessions: their scene files are checked here (a bad
    // one stops the start), the fill runs beside the daemon and stops with it.
    let _fill = match &manager.config().region_cache {
        Some(cache) => regions::spawn_background_fill(
            &manager.config().prepare_regions,
            cache,
            manager.config().prepare_regions_priority,
            manager.running_sessions(),
        )?,
        None => None,
    };
    // Sessions recorded by an earlier process come back (same ids) before anyone can connect.
    for line in manager.restore() {
        tracing::info!("{line}");
    }
    if let Some(addr) = manager.config().metrics_listen {
        let listener = TcpListener::bind(addr)
            .await
            .map_err(|reason| ServerError::Bind {
                what: "metrics endpoint",
                addr,
                reason,
            })?;
        // Printed like the gRPC address, so scripts and tests can find a port-0 endpoint.
        println!("metrics on {}", listener.local_addr()?);
        tokio::spawn(metrics::serve(listener, manager.clone()));
    }
    let auth = Arc::new(auth::Auth::from_config(
        manager.config().tokens_file.as_deref(),
        manager.config().auth_limits,
    )?);
    let tls = manager.config().tls.as_ref().map(tls_config).transpose()?;
    let services = service::Services::with_auth(manager.clone(), auth.clone());
    let guard = auth::AuthInterceptor(auth);
    // Printed once the tokens exist and TLS is loaded, so that a script that waits for this
    // line can read the token files; a bad tokens file or certificate fails before it.
    println!("listening on {}", listener.local_addr()?);
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
    let mut builder = tonic::transport::Server::builder();
    if let Some(tls) = tls {
        builder = builder.tls_config(tls)?;
        tracing::info!("TLS on");
    }
    // Health and reflection answer without a token (they reveal only the public contract);
    // the three haptics services authenticate every call.
    let result = builder
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(SessionControlServer::with_interceptor(
            services.clone(),
            guard.clone(),
        ))
        .add_service(DeviceLinkServer::with_interceptor(
            services.clone(),
            guard.clone(),
        ))
        .add_service(SurfaceStreamServer::with_interceptor(services, guard))
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

/// The server's TLS configuration from its PEM files (each at most 1 MiB).
fn tls_config(files: &config::TlsFiles) -> Result<tonic::transport::ServerTlsConfig, ServerError> {
    use tonic::transport::{Certificate, Identity, ServerTlsConfig};
    let fail = |p: &std::path::Path, reason: String| ServerError::Tls {
        path: p.to_path_buf(),
        reason,
    };
    let read = |p: &std::path::Path| -> Result<Vec<u8>, ServerError> {
        let meta = std::fs::metadata(p).map_err(|e| fail(p, e.to_string()))?;
        if !meta.is_file() || meta.len() > 1 << 20 {
            return Err(fail(p, "not a regular file of at most 1 MiB".into()));
        }
        std::fs::read(p).map_err(|e| fail(p, e.to_string()))
    };
    let mut tls = ServerTlsConfig::new().identity(Identity::from_pem(
        read(&files.cert_file)?,
        read(&files.key_file)?,
    ));
    if let Some(ca) = &files.client_ca_file {
        tls = tls.client_ca_root(Certificate::from_pem(read(ca)?));
    }
    Ok(tls)
}
