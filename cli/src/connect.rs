//! Opening a channel to `hapticd`: the address forms every client accepts and the connection
//! attempt, with the credentials of [`crate::credentials`].
//!
//! Neighbours: `hapticctl` and `haptic-viewer` connect with [`connect`]; `haptic-bridge` builds
//! its own endpoint (it reconnects with backoff) from the same credentials.

use crate::credentials::{AuthChannel, ClientCredentials, CredentialsError};

/// Default server address when neither `--server` nor `HAPTICD_ADDR` is given.
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:50051";

/// Why [`connect`] failed.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The server URL is malformed or the connection could not be made.
    #[error("cannot connect to {url}: {}", error_chain(.source))]
    Connect {
        /// The URL that was tried.
        url: String,
        /// The transport error.
        #[source]
        source: tonic::transport::Error,
    },
    /// A token, certificate or key could not be read, or the TLS set-up is inconsistent.
    #[error("credentials: {0}")]
    Credentials(#[from] CredentialsError),
}

/// Opens a gRPC channel to `url` (`http://host:port` or `https://host:port`; a bare
/// `host:port` gets `http://`) whose every call carries the token of `credentials`, over TLS
/// for `https://` ([`crate::credentials`]).
///
/// The connection attempt gives up after 5 s, so a wrong address fails quickly in scripts.
///
/// # Errors
/// [`ConnectError::Credentials`] for an unreadable token or TLS file;
/// [`ConnectError::Connect`] when the URL is malformed or nothing answers at the address.
pub async fn connect(
    url: &str,
    credentials: &ClientCredentials,
) -> Result<AuthChannel, ConnectError> {
    let url = normalize_url(url);
    let token = credentials.interceptor()?;
    let endpoint = credentials
        .endpoint(&url)?
        .connect_timeout(std::time::Duration::from_secs(5));
    let channel = endpoint
        .connect()
        .await
        .map_err(|source| ConnectError::Connect { url, source })?;
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

/// `e` and its sources joined by `": "` (tonic's transport errors hide the cause in `source()`).
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    let mut last = s.clone();
    while let Some(c) = cur {
        let m = c.to_string();
        if m != last {
            s.push_str(": ");
            s.push_str(&m);
        }
        last = m;
        cur = c.source();
    }
    s
}
