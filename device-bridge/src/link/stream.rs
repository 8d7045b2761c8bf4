//! One `DeviceLink.Connect` stream: connect, send the first sample (session id,
//! capabilities), wait for the response headers (limits, server instance), then exchange
//! samples and force commands until it ends.

use std::time::Duration;

use haptics_proto::v1::DeviceSample;
use haptics_proto::v1::device_link_client::DeviceLinkClient;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Endpoint;
use tracing::{info, warn};

use crate::guard::Limits;

use super::net::{NetCtx, to_proto};
use super::shared::OutSample;
use super::{
    BridgeConfig, HEADER_FORCE_DEADBAND, HEADER_MAX_FORCE, HEADER_MAX_FORCE_RATE,
    HEADER_SERVER_INSTANCE,
};

/// How long to wait for the server to close its side after we close ours.
const CLOSE_GRACE: Duration = Duration::from_millis(200);

/// How one stream ended.
pub(super) enum StreamEnd {
    /// The device finished (its sample queue closed).
    Finished,
    /// The shutdown signal fired.
    Shutdown,
    /// Connecting or streaming failed; retry.
    Failed(String),
    /// The server does not know the session (NOT_FOUND): retrying cannot help.
    SessionGone(String),
    /// The server refused the credentials (UNAUTHENTICATED, PERMISSION_DENIED): retrying
    /// cannot help either.
    Refused(String),
}

/// `error: cause: cause ...`, since tonic's transport errors hide the useful part in sources.
fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

/// Resolves once `true` is sent on `shutdown`; never if the sender is gone without sending it.
pub(super) async fn wait_shutdown(shutdown: &mut watch::Receiver<bool>) {
    loop {
        if *shutdown.borrow_and_update() {
            return;
        }
        if shutdown.changed().await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

/// Sleeps for `d`, or forever when `None`.
async fn sleep_or_pending(d: Option<Duration>) {
    match d {
        Some(d) => tokio::time::sleep(d).await,
        None => std::future::pending::<()>().await,
    }
}

/// The scene's limits from the response headers (`None` when absent or malformed).
fn header_limits(md: &tonic::metadata::MetadataMap) -> Option<Limits> {
    let num = |k: &str| -> Option<f64> { md.get(k)?.to_str().ok()?.trim().parse().ok() };
    let l = Limits {
        max_force_n: num(HEADER_MAX_FORCE)?,
        max_rate_n_per_s: num(HEADER_MAX_FORCE_RATE)?,
    };
    l.is_valid().then_some(l)
}

pub(super) async fn run_stream(
    endpoint: &Endpoint,
    config: &BridgeConfig,
    first: OutSample,
    samples: &mut mpsc::Receiver<OutSample>,
    shutdown: &mut watch::Receiver<bool>,
    ctx: &mut NetCtx,
) -> StreamEnd {
    ctx.attempts += 1;
    let channel = tokio::select! {
        biased;
        _ = wait_shutdown(shutdown) => return StreamEnd::Shutdown,
        c = endpoint.connect() => match c {
            Ok(c) => c,
            Err(e) => {
                return StreamEnd::Failed(format!("connect to {}: {}", config.server_url, chain(&e)));
            }
        },
    };
    let mut client = DeviceLinkClient::with_interceptor(channel, ctx.token.clone());
    let (out_tx, out_rx) = mpsc::channel::<DeviceSample>(config.sample_queue);
    let mut first_msg = to_proto(&first);
    first_msg.session_id.clone_from(&config.session_id);
    first_msg.capabilities.clone_from(&config.capabilities);
    // The first sample carries the session id: never drop it by injection.
    let fault = ctx.fault.take();
    ctx.forward(&out_tx, first_msg);
    ctx.fault = fault;
    let mut request = tonic::Request::new(ReceiverStream::new(out_rx));
    if let Some(k) = config.deadband
        && let Ok(v) = k.to_string().parse()
    {
        // The same deadband on the force stream, applied by the server.
        request.metadata_mut().insert(HEADER_FORCE_DEADBAND, v);
    }
    let call = client.connect(request);
    tokio::pin!(call);
    // Keep feeding samples while waiting for response headers: a server may wait for the first
    // message (it carries the session id) before answering.
    let response = loop {
        tokio::select! {
            biased;
            _ = wait_shutdown(shutdown) => return StreamEnd::Shutdown,
            r = &mut call => match r {
                Ok(resp) => break resp,
                Err(status) if status.code() == tonic::Code::NotFound => {
                    return StreamEnd::SessionGone(status.message().to_owned());
                }
                Err(status) if matches!(
                    status.code(),
                    tonic::Code::Unauthenticated | tonic::Code::PermissionDenied
                ) => {
                    return StreamEnd::Refused(format!("{:?}: {}", status.code(), status.message()));
                }
                Err(status) => return StreamEnd::Failed(format!("Connect rejected: {status}")),
            },
            s = samples.recv() => match s {
                Some(s) => ctx.forward(&out_tx, to_proto(&s)),
                None => return StreamEnd::Finished,
            },
        }
    };
    let limits = header_limits(response.metadata());
    let instance = response
        .metadata()
        .get(HEADER_SERVER_INSTANCE)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned);
    let mut inbound = response.into_inner();
    ctx.streams_opened += 1;
    if ctx.attempts > 1 {
        ctx.reconnects += 1;
    }
    if let (Some(old), Some(new)) = (&ctx.server_instance, &instance)
        && old != new
    {
        ctx.server_restarts += 1;
        warn!(
            session = %config.session_id,
            "hapticd restarted (instance {old} -> {new}) and restored session {}: re-attached; \
             forces stay off until the link is healthy and they are re-armed",
            config.session_id
        );
    }
    if instance.is_some() {
        ctx.server_instance = instance;
    }
    ctx.shared.set_link(true, limits);
    match limits {
        Some(l) => info!(
            url = %config.server_url, session = %config.session_id,
            scene_max_force_n = l.max_force_n, scene_max_rate_n_per_s = l.max_rate_n_per_s,
            "DeviceLink stream open"
        ),
        None => info!(url = %config.server_url, session = %config.session_id,
            "DeviceLink stream open (the server sent no scene limits: device limits only)"),
    }
    let end = loop {
        // Deliver what is due first: a timer is only checked when the runtime turns, and a
        // stream of samples every millisecond would keep a zero-length sleep from firing.
        ctx.release_delayed();
        let release = ctx.next_release();
        tokio::select! {
            biased;
            _ = wait_shutdown(shutdown) => break StreamEnd::Shutdown,
            _ = sleep_or_pending(release) => ctx.release_delayed(),
            m = inbound.message() => match m {
                Ok(Some(cmd)) => ctx.receive(cmd),
                Ok(None) => break StreamEnd::Failed("server closed the stream".to_owned()),
                Err(status) => break StreamEnd::Failed(format!("stream error: {status}")),
            },
            s = samples.recv() => match s {
                Some(s) => ctx.forward(&out_tx, to_proto(&s)),
                None => break StreamEnd::Finished,
            },
        }
    };
    ctx.shared.set_link(false, None);
    ctx.delayed.clear();
    if matches!(end, StreamEnd::Finished | StreamEnd::Shutdown) {
        // Close our half and collect the answers still in flight, briefly.
        drop(out_tx);
        let _ = tokio::time::timeout(CLOSE_GRACE, async {
            while let Ok(Some(cmd)) = inbound.message().await {
                ctx.on_force(&cmd);
            }
        })
        .await;
    }
    end
}
