//! `ClientError`: the one error type of the client library (viewer, rasterizer, control client).
//!
//! Binaries turn it into messages and exit codes; [`ClientError::is_rpc`] lets `hapticctl` give
//! gRPC failures their own exit code.

use std::path::PathBuf;

use haptic_cli::connect::{ConnectError, error_chain};

/// Everything that can go wrong in the client library.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
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
    Credentials(#[from] haptic_cli::credentials::CredentialsError),
    /// The server answered with a non-OK gRPC status. Displayed as `CODE: message`,
    /// e.g. `NOT_FOUND: no session abc`.
    #[error("{}: {}", code_name(.0.code()), .0.message())]
    Rpc(Box<tonic::Status>),
    /// A `X,Y,Z` vector argument could not be parsed.
    #[error("invalid vector {input:?}: {source}")]
    InvalidVector {
        /// The text as given.
        input: String,
        /// What was wrong with it (which component, and why).
        #[source]
        source: haptic_cli::vec3::ParseVec3Error,
    },
    /// A configuration value is out of range (checked before anything is started).
    #[error("invalid configuration: {0}")]
    InvalidConfig(String),
    /// The web viewer's listen address did not resolve, or none of its addresses could be bound.
    #[error("cannot listen on {addr}: {reason}")]
    Listen {
        /// The address as given (`HOST:PORT`).
        addr: String,
        /// Why: the resolver's error, or the last address tried and its bind error.
        reason: String,
    },
    /// A surface frame does not match the current keyframe (wrong sizes, missing vertices,
    /// non-finite numbers, no keyframe yet).
    #[error("bad frame {frame}: {reason}")]
    BadFrame {
        /// `SurfaceFrame.frame` of the offending frame.
        frame: u64,
        /// What was wrong with it.
        reason: String,
    },
    /// A file could not be written or renamed.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The file involved.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// PNG encoding failed.
    #[error("PNG encoding failed: {0}")]
    Png(#[from] png::EncodingError),
    /// A background task (the picture writer) panicked or was cancelled.
    #[error("background task failed: {0}")]
    Task(String),
}

impl From<ConnectError> for ClientError {
    fn from(e: ConnectError) -> Self {
        match e {
            ConnectError::Connect { url, source } => ClientError::Connect { url, source },
            ConnectError::Credentials(e) => ClientError::Credentials(e),
        }
    }
}

impl From<tonic::Status> for ClientError {
    fn from(status: tonic::Status) -> Self {
        ClientError::Rpc(Box::new(status))
    }
}

impl ClientError {
    /// The gRPC status when this error came from the server, `None` otherwise.
    pub fn status(&self) -> Option<&tonic::Status> {
        match self {
            ClientError::Rpc(s) => Some(s),
            _ => None,
        }
    }

    /// True when the server answered with a gRPC error status.
    pub fn is_rpc(&self) -> bool {
        self.status().is_some()
    }
}

/// The canonical upper-case gRPC name of a status code (`NOT_FOUND`, `INVALID_ARGUMENT`, ...),
/// as other gRPC tools print it.
pub fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}
