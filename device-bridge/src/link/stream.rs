//! One `DeviceLink.Connect` stream: connect, send the first sample (session id,
//! capabilities), wait for the response headers (limits, server instance), then exchange
//! samples and force commands until it ends.

use std::time::Duration;

use haptics_proto::v1::device_link_client::DeviceLinkClient;
use haptics_proto::v1::{DeviceSample, ForceCommand};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::Streaming;
use tonic::transport::{Channel, Endpoint};
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

/// One `DeviceLink.Connect` stream, from connecting to its end: the first sample carries the
/// session id and the capabilities, the response headers the scene's limits and the server
/// instance; then samples go out and force commands come in until the device finishes, the
/// shutdown signal fires or the link fails. The link is marked down on the way out.
pub(super) async fn run_stream(
    endpoint: &Endpoint,
    config: &BridgeConfig,
    first: OutSample,
    samples: &mut mpsc::Receiver<OutSample>,
    shutdown: &mut watch::Receiver<bool>,
    ctx: &mut NetCtx,
) -> StreamEnd {
    ctx.attempts += 1;
    let channel = match connect(endpoint, config, shutdown).await {
        Ok(c) => c,
        Err(end) => return end,
    };
    let mut client = DeviceLinkClient::with_interceptor(channel, ctx.token.clone());
    let (out_tx, request) = first_request(config, &first, ctx);
    let call = client.connect(request);
    let response = match await_headers(call, &out_tx, samples, shutdown, ctx).await {
        Ok(r) => r,
        Err(end) => return end,
    };
    let mut inbound = stream_opened(config, ctx, response);
    let end = exchange(&mut inbound, &out_tx, samples, shutdown, ctx).await;
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

/// Opens the transport (or gives up on shutdown).
async fn connect(
    endpoint: &Endpoint,
    config: &BridgeConfig,
    shutdown: &mut watch::Receiver<bool>,
) -> Result<Channel, StreamEnd> {
    tokio::select! {
        biased;
        _ = wait_shutdown(shutdown) => Err(StreamEnd::Shutdown),
        c = endpoint.connect() => c.map_err(|e| {
            StreamEnd::Failed(format!("connect to {}: {}", config.server_url, chain(&e)))
        }),
    }
}

/// The outbound queue with the stream's first sample in it (session id, capabilities), and the
/// request that streams the queue (with the deadband header when one is set).
fn first_request(
    config: &BridgeConfig,
    first: &OutSample,
    ctx: &mut NetCtx,
) -> (
    mpsc::Sender<DeviceSample>,
    tonic::Request<ReceiverStream<DeviceSample>>,
) {
    let (out_tx, out_rx) = mpsc::channel::<DeviceSample>(config.sample_queue);
    let mut first_msg = to_proto(first);
    first_msg.session_id.clone_from(&config.session_id);
    first_msg.capabilities.clone_from(&config.capabilities);
    first_msg.tool_id.clone_from(&config.tool_id);
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
    (out_tx, request)
}

/// Waits for the response headers of `call`, feeding samples meanwhile: a server may wait for
/// the first message (it carries the session id) before answering. NOT_FOUND ends as
/// [`StreamEnd::SessionGone`], UNAUTHENTICATED and PERMISSION_DENIED as [`StreamEnd::Refused`].
async fn await_headers(
    call: impl Future<Output = Result<tonic::Response<Streaming<ForceCommand>>, tonic::Status>>,
    out_tx: &mpsc::Sender<DeviceSample>,
    samples: &mut mpsc::Receiver<OutSample>,
    shutdown: &mut watch::Receiver<bool>,
    ctx: &mut NetCtx,
) -> Result<tonic::Response<Streaming<ForceCommand>>, StreamEnd> {
    tokio::pin!(call);
    loop {
        tokio::select! {
            biased;
            _ = wait_shutdown(shutdown) => return Err(StreamEnd::Shutdown),
            r = &mut call => match r {
                Ok(resp) => return Ok(resp),
                Err(status) if status.code() == tonic::Code::NotFound => {
                    return Err(StreamEnd::SessionGone(status.message().to_owned()));
                }
                Err(status) if matches!(
                    status.code(),
                    tonic::Code::Unauthenticated | tonic::Code::PermissionDenied
                ) => {
                    return Err(StreamEnd::Refused(format!("{:?}: {}", status.code(), status.message())));
                }
                Err(status) => return Err(StreamEnd::Failed(format!("Connect rejected: {status}"))),
            },
            s = samples.recv() => match s {
                Some(s) => ctx.forward(out_tx, to_proto(&s)),
                None => return Err(StreamEnd::Finished),
            },
        }
    }
}

/// Takes the opened stream's headers: counts the stream (and the reconnect), notices a
/// restarted daemon, hands the scene's limits to the device thread with the link up, and logs
/// it. Returns the inbound force commands.
fn stream_opened(
    config: &BridgeConfig,
    ctx: &mut NetCtx,
    response: tonic::Response<Streaming<ForceCommand>>,
) -> Streaming<ForceCommand> {
    let limits = header_limits(response.metadata());
    let instance = response
        .metadata()
        .get(HEADER_SERVER_INSTANCE)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned);
    let inbound = response.into_inner();
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
    inbound
}

/// Samples out, force commands in (through fault injection's delays) until the stream ends.
async fn exchange(
    inbound: &mut Streaming<ForceCommand>,
    out_tx: &mpsc::Sender<DeviceSample>,
    samples: &mut mpsc::Receiver<OutSample>,
    shutdown: &mut watch::Receiver<bool>,
    ctx: &mut NetCtx,
) -> StreamEnd {
    loop {
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
                Some(s) => ctx.forward(out_tx, to_proto(&s)),
                None => break StreamEnd::Finished,
            },
        }
    }
}
