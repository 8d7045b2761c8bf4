//! The server's error type and its one mapping to `tonic::Status`.

use haptic_model::ModelError;
use thiserror::Error;
use tonic::Status;

/// Everything a request or the daemon can fail with.
#[derive(Debug, Error)]
pub enum ServerError {
    /// The configuration file or flags are wrong.
    #[error("configuration: {0}")]
    Config(String),
    /// A request names a session that does not exist.
    #[error("no session `{0}`")]
    UnknownSession(String),
    /// A `RequestKeyframe` names a watch stream that is not open on the session.
    #[error("no watch stream {0} on this session")]
    UnknownWatch(u64),
    /// A request carries a bad value (NaN, out of range, missing field).
    #[error("{0}")]
    InvalidArgument(String),
    /// A request asks for something the daemon's rules forbid (a file outside the allowed
    /// directories); the message names the rule, never what lies outside.
    #[error("{0}")]
    PermissionDenied(String),
    /// The scene could not be loaded or simulated.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// A limit was reached (sessions, queued commands).
    #[error("{0}")]
    Exhausted(String),
    /// The session cannot take this request in its current state (faulted, device already
    /// connected).
    #[error("{0}")]
    FailedPrecondition(String),
    /// A call's deadline passed (a scene build that did not finish in time).
    #[error("{0}")]
    DeadlineExceeded(String),
    /// Unexpected internal failure.
    #[error("internal: {0}")]
    Internal(String),
    /// The daemon could not bind one of its listeners ([`crate::run`]).
    #[error("binding the {what} {addr}: {reason}")]
    Bind {
        /// Which listener (`"metrics endpoint"`).
        what: &'static str,
        /// The address asked for.
        addr: std::net::SocketAddr,
        /// The operating system's error.
        reason: std::io::Error,
    },
    /// A TLS file cannot be used ([`crate::run`]): unreadable, not a regular file, or larger
    /// than 1 MiB.
    #[error("TLS file {}: {reason}", path.display())]
    Tls {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        reason: String,
    },
    /// An input/output error of the daemon's listeners ([`crate::run`]).
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The gRPC transport failed ([`crate::run`]: TLS set-up, serving).
    #[error(transparent)]
    Transport(#[from] tonic::transport::Error),
    /// The reflection service could not be built ([`crate::run`]).
    #[error(transparent)]
    Reflection(#[from] tonic_reflection::server::Error),
}

/// Longest status message sent to a client, bytes: a parse error quoting a huge line of the
/// client's own text is cut here (with a note), never sent whole.
pub const MAX_STATUS_MESSAGE_BYTES: usize = 1024;

/// `msg` cut to [`MAX_STATUS_MESSAGE_BYTES`] at a character boundary.
pub fn bounded_message(msg: String) -> String {
    if msg.len() <= MAX_STATUS_MESSAGE_BYTES {
        return msg;
    }
    let mut end = MAX_STATUS_MESSAGE_BYTES - 40;
    while !msg.is_char_boundary(end) {
        end -= 1;
    }
    format!("{} ... [{} bytes cut]", &msg[..end], msg.len() - end)
}

impl From<ServerError> for Status {
    fn from(e: ServerError) -> Self {
        let msg = bounded_message(e.to_string());
        match e {
            ServerError::PermissionDenied(_) => Status::permission_denied(msg),
            ServerError::UnknownSession(_) | ServerError::UnknownWatch(_) => Status::not_found(msg),
            ServerError::InvalidArgument(_) | ServerError::Config(_) => {
                Status::invalid_argument(msg)
            }
            ServerError::Model(ModelError::NoConvergence(_)) => Status::internal(msg),
            ServerError::Model(ModelError::Io { .. }) => Status::invalid_argument(msg),
            ServerError::Model(_) => Status::invalid_argument(msg),
            ServerError::Exhausted(_) => Status::resource_exhausted(msg),
            ServerError::FailedPrecondition(_) => Status::failed_precondition(msg),
            ServerError::DeadlineExceeded(_) => Status::deadline_exceeded(msg),
            ServerError::Internal(_)
            | ServerError::Bind { .. }
            | ServerError::Tls { .. }
            | ServerError::Io(_)
            | ServerError::Transport(_)
            | ServerError::Reflection(_) => Status::internal(msg),
        }
    }
}
