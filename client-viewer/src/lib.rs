//! `haptic-client`: the viewer library and scripted client of the haptic server.
//!
//! Three concepts, each in its own module, glued by two thin binaries:
//!
//! - [`raster`]: a small deterministic software rasterizer (z-buffer, Lambert shading) that turns
//!   a deformed surface, the probe and its contact force into an RGB picture and a PNG file,
//!   without a GPU or a display.
//! - [`viewer`]: subscribes to `SurfaceStream.Watch`, keeps the keyframe topology, applies the
//!   position frames, measures rate and frame age, and writes pictures with [`raster`]
//!   (binary `haptic-viewer`).
//! - [`compact`]: the client side of compact streams (quantized deltas against a reference
//!   keyframe), turning each frame into its full form.
//! - [`ctl`]: calls `SessionControl` (scenes, start, stop, sessions, force, stats) and formats
//!   the answers as tables or JSON (binary `hapticctl`).
//! - [`web`]: the browser viewer (`haptic-viewer --web ADDR`), a relay that subscribes once
//!   per session and fans the compact stream out to browsers over WebSocket, with the page
//!   and three.js compiled into the binary.
//!
//! Neighbours: the wire contract is `haptics_proto::v1`; the server (`haptic-server`) implements
//! it. This crate never depends on the physics model: everything it knows about a session comes
//! over gRPC.

pub mod compact;
pub mod ctl;
pub mod error;
pub mod raster;
pub mod record;
pub mod viewer;
pub mod web;

pub use error::ClientError;

pub use haptics_proto::client::{AuthChannel, ClientCredentials};

/// Default server address when neither `--server` nor `HAPTICD_ADDR` is given.
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:50051";

/// Opens a gRPC channel to `url` (`http://host:port` or `https://host:port`; a bare
/// `host:port` gets `http://`) whose every call carries the token of `credentials`, over TLS
/// for `https://` ([`haptics_proto::client`]).
///
/// The connection attempt gives up after 5 s, so a wrong address fails quickly in scripts.
///
/// # Errors
/// [`ClientError::Credentials`] for an unreadable token or TLS file;
/// [`ClientError::Connect`] when the URL is malformed or nothing answers at the address.
pub async fn connect(
    url: &str,
    credentials: &ClientCredentials,
) -> Result<AuthChannel, ClientError> {
    let url = normalize_url(url);
    let token = credentials.interceptor()?;
    let endpoint = credentials
        .endpoint(&url)?
        .connect_timeout(std::time::Duration::from_secs(5));
    let channel = endpoint
        .connect()
        .await
        .map_err(|source| ClientError::Connect { url, source })?;
    Ok(token.wrap(channel))
}

/// Adds the `http://` scheme to a bare `host:port` address; other strings pass unchanged.
pub fn normalize_url(url: &str) -> String {
    if url.contains("://") {
        url.to_string()
    } else {
        format!("http://{url}")
    }
}
