//! The client side of the daemon's access control (issue 16, section 3), shared by every
//! binary that calls `hapticd` (`hapticctl`, `haptic-viewer`, `haptic-bridge`, the demo):
//!
//! - a **bearer token** on every call (`authorization: Bearer <token>`), read from a file
//!   (`--token-file`, or `HAPTICD_TOKEN_FILE`) or from the environment (`HAPTICD_TOKEN`), never
//!   from the command line, where other users of the machine could read it in `ps`;
//! - **TLS** for `https://` URLs: the CA certificate that signed the daemon's certificate
//!   (`--tls-ca`), and optionally this client's own certificate and key (`--tls-cert`,
//!   `--tls-key`) when the daemon asks for client certificates.
//!
//! `hapticd` writes one token file per role beside its tokens file at first start
//! (`admin.token`, `control.token`, `device.token`, `viewer.token`, mode 0600), so a client on
//! the daemon's machine passes e.g. `--token-file /var/lib/hapticd/device.token`.
//!
//! Environment variables follow one scheme, `HAPTICD_*` ([`ENV_ALIASES`] lists them with the
//! older `HAPTICS_*` names, still read when the new one is unset; docs/tools.md, "Environment
//! variables").
//!
//! Neighbours: the server side is `haptic_server::auth`; `docs/security.md` is the operator's
//! guide.

use std::path::{Path, PathBuf};

use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};

/// Environment variable holding a token itself (used when no token file is given).
pub const TOKEN_ENV: &str = "HAPTICD_TOKEN";

/// The clients' environment variables and the older names each still answers to (read only
/// when the new one is unset). The daemon's own are `HAPTICD_CONFIG` and `HAPTICD_TOKENS_FILE`.
pub const ENV_ALIASES: [(&str, &str); 5] = [
    (TOKEN_ENV, "HAPTICS_TOKEN"),
    ("HAPTICD_TOKEN_FILE", "HAPTICS_TOKEN_FILE"),
    ("HAPTICD_TLS_CA", "HAPTICS_TLS_CA"),
    ("HAPTICD_TLS_CERT", "HAPTICS_TLS_CERT"),
    ("HAPTICD_TLS_KEY", "HAPTICS_TLS_KEY"),
];

/// The value of the environment variable `name`, or of its older alias in [`ENV_ALIASES`]
/// when `name` is unset; with the name it came from.
pub fn env_var_or_alias(name: &str) -> Option<(&'static str, std::ffi::OsString)> {
    lookup_with_alias(name, |k| std::env::var_os(k))
}

/// [`env_var_or_alias`] over any lookup (tests pass a table instead of the environment).
fn lookup_with_alias(
    name: &str,
    get: impl Fn(&str) -> Option<std::ffi::OsString>,
) -> Option<(&'static str, std::ffi::OsString)> {
    let (new, old) = ENV_ALIASES.iter().find(|(new, _)| *new == name)?;
    get(new)
        .map(|v| (*new, v))
        .or_else(|| get(old).map(|v| (*old, v)))
}
/// Largest token file read, bytes (a token is 64 characters).
pub const MAX_TOKEN_FILE_BYTES: u64 = 4096;
/// Largest certificate or key file read, bytes.
pub const MAX_PEM_FILE_BYTES: u64 = 1 << 20;

/// A channel whose every call carries this client's token ([`BearerToken`]).
pub type AuthChannel = InterceptedService<Channel, BearerToken>;

/// What went wrong setting up a client's credentials. Messages name the file and the rule,
/// never a token's text.
#[derive(Debug, thiserror::Error)]
pub enum CredentialsError {
    /// A token, certificate or key file could not be read.
    #[error("reading {path}: {message}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// The token is empty or not printable ASCII.
    #[error("{origin}: the token must be 16-1024 printable ASCII characters without spaces")]
    BadToken {
        /// Where the token came from (a file's path or the environment variable's name).
        origin: String,
    },
    /// An `https://` URL without a CA certificate, or TLS files for an `http://` URL.
    #[error("{0}")]
    Tls(String),
    /// The URL is malformed or the TLS configuration was refused.
    #[error("{url}: {source}")]
    Endpoint {
        /// The URL.
        url: String,
        /// The transport's error.
        #[source]
        source: tonic::transport::Error,
    },
}

/// Credentials flags of a client binary (`#[command(flatten)]`).
#[derive(Debug, Clone, Default, PartialEq, Eq, clap::Args)]
pub struct ClientCredentials {
    /// File holding this client's token (first non-empty line that is not a `#` comment), e.g.
    /// the `device.token` hapticd writes beside its tokens file. Without it the token is read
    /// from HAPTICD_TOKEN; without either, calls carry no token (a daemon without tokens).
    /// (Older name of the variable: HAPTICS_TOKEN_FILE.)
    #[arg(long, global = true, env = "HAPTICD_TOKEN_FILE", value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// CA certificate (PEM) that signed the daemon's certificate; needed for https:// URLs.
    #[arg(long, global = true, env = "HAPTICD_TLS_CA", value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,
    /// This client's certificate (PEM), for a daemon that requires client certificates.
    #[arg(
        long,
        global = true,
        env = "HAPTICD_TLS_CERT",
        value_name = "PEM",
        requires = "tls_key"
    )]
    pub tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(
        long,
        global = true,
        env = "HAPTICD_TLS_KEY",
        value_name = "PEM",
        requires = "tls_cert"
    )]
    pub tls_key: Option<PathBuf>,
}

impl ClientCredentials {
    /// These credentials with every unset file taken from the older environment variables
    /// (`HAPTICS_TOKEN_FILE`, `HAPTICS_TLS_*`; the `HAPTICD_*` ones are read by the flags).
    pub fn with_env_aliases(&self) -> Self {
        let alias = |field: &Option<PathBuf>, name: &str| {
            field
                .clone()
                .or_else(|| env_var_or_alias(name).map(|(_, v)| PathBuf::from(v)))
        };
        Self {
            token_file: alias(&self.token_file, "HAPTICD_TOKEN_FILE"),
            tls_ca: alias(&self.tls_ca, "HAPTICD_TLS_CA"),
            tls_cert: alias(&self.tls_cert, "HAPTICD_TLS_CERT"),
            tls_key: alias(&self.tls_key, "HAPTICD_TLS_KEY"),
        }
    }

    /// The token: from [`Self::token_file`] (or `HAPTICD_TOKEN_FILE`), else from
    /// `HAPTICD_TOKEN`, else none; the older `HAPTICS_*` names where the new ones are unset.
    ///
    /// # Errors
    /// [`CredentialsError::Read`] for an unreadable file (or one over 4 KiB);
    /// [`CredentialsError::BadToken`] for an empty or malformed token.
    pub fn token(&self) -> Result<Option<String>, CredentialsError> {
        let this = self.with_env_aliases();
        if let Some(path) = &this.token_file {
            let text = read_bounded(path, MAX_TOKEN_FILE_BYTES)?;
            let text = String::from_utf8(text).map_err(|_| CredentialsError::BadToken {
                origin: path.display().to_string(),
            })?;
            let line = text
                .lines()
                .map(str::trim)
                .find(|l| !l.is_empty() && !l.starts_with('#'))
                .unwrap_or("");
            return check_token(line, &path.display().to_string()).map(Some);
        }
        match env_var_or_alias(TOKEN_ENV) {
            Some((name, t)) => match t.into_string() {
                Ok(t) => check_token(t.trim(), name).map(Some),
                Err(_) => Err(CredentialsError::BadToken {
                    origin: name.into(),
                }),
            },
            None => Ok(None),
        }
    }

    /// The interceptor that puts the token on every call (none: calls go out unchanged).
    ///
    /// # Errors
    /// As [`Self::token`].
    pub fn interceptor(&self) -> Result<BearerToken, CredentialsError> {
        let value = match self.token()? {
            Some(t) => {
                Some(
                    format!("Bearer {t}")
                        .parse()
                        .map_err(|_| CredentialsError::BadToken {
                            origin: "token".into(),
                        })?,
                )
            }
            None => None,
        };
        Ok(BearerToken(value))
    }

    /// An endpoint for `url` with TLS configured: `https://` needs `--tls-ca`; TLS files with
    /// an `http://` URL are refused rather than silently unused.
    ///
    /// # Errors
    /// [`CredentialsError::Endpoint`] for a malformed URL; [`CredentialsError::Tls`] and
    /// [`CredentialsError::Read`] for the TLS rules and files above.
    pub fn endpoint(&self, url: &str) -> Result<Endpoint, CredentialsError> {
        let this = self.with_env_aliases();
        if this.tls_cert.is_some() != this.tls_key.is_some() {
            return Err(CredentialsError::Tls(
                "--tls-cert and --tls-key (HAPTICD_TLS_CERT, HAPTICD_TLS_KEY) go together".into(),
            ));
        }
        let endpoint =
            Endpoint::from_shared(url.to_owned()).map_err(|source| CredentialsError::Endpoint {
                url: url.to_owned(),
                source,
            })?;
        let https = url.starts_with("https://");
        let any_tls = this.tls_ca.is_some() || this.tls_cert.is_some();
        if !https {
            if any_tls {
                return Err(CredentialsError::Tls(format!(
                    "{url}: TLS files were given but the URL is not https://"
                )));
            }
            return Ok(endpoint);
        }
        let ca = this.tls_ca.as_deref().ok_or_else(|| {
            CredentialsError::Tls(format!(
                "{url}: an https:// URL needs --tls-ca (or HAPTICD_TLS_CA): the CA certificate \
                 that signed the daemon's certificate"
            ))
        })?;
        let mut tls = ClientTlsConfig::new()
            .ca_certificate(Certificate::from_pem(read_bounded(ca, MAX_PEM_FILE_BYTES)?));
        if let (Some(cert), Some(key)) = (&this.tls_cert, &this.tls_key) {
            tls = tls.identity(Identity::from_pem(
                read_bounded(cert, MAX_PEM_FILE_BYTES)?,
                read_bounded(key, MAX_PEM_FILE_BYTES)?,
            ));
        }
        endpoint
            .tls_config(tls)
            .map_err(|source| CredentialsError::Endpoint {
                url: url.to_owned(),
                source,
            })
    }
}

/// Checks a token's form: 16 to 1024 printable ASCII characters, no spaces (the server's
/// tokens are 64 hexadecimal digits).
fn check_token(t: &str, origin: &str) -> Result<String, CredentialsError> {
    if (16..=1024).contains(&t.len()) && t.bytes().all(|b| b.is_ascii_graphic()) {
        Ok(t.to_owned())
    } else {
        Err(CredentialsError::BadToken {
            origin: origin.to_owned(),
        })
    }
}

/// Reads a regular file of at most `limit` bytes.
fn read_bounded(path: &Path, limit: u64) -> Result<Vec<u8>, CredentialsError> {
    use std::io::Read;
    let err = |message: String| CredentialsError::Read {
        path: path.to_owned(),
        message,
    };
    let file = std::fs::File::open(path).map_err(|e| err(e.to_string()))?;
    let meta = file.metadata().map_err(|e| err(e.to_string()))?;
    if !meta.is_file() {
        return Err(err("not a regular file".into()));
    }
    let mut buf = Vec::new();
    file.take(limit + 1)
        .read_to_end(&mut buf)
        .map_err(|e| err(e.to_string()))?;
    if buf.len() as u64 > limit {
        return Err(err(format!("larger than {limit} bytes")));
    }
    Ok(buf)
}

/// Adds `authorization: Bearer <token>` to every call (nothing when there is no token).
#[derive(Debug, Clone, Default)]
pub struct BearerToken(Option<MetadataValue<Ascii>>);

impl BearerToken {
    /// No token: calls go out unchanged (a daemon without tokens, on loopback).
    pub fn none() -> Self {
        Self(None)
    }

    /// Wraps `channel` so that every call carries this token.
    pub fn wrap(self, channel: Channel) -> AuthChannel {
        InterceptedService::new(channel, self)
    }
}

impl Interceptor for BearerToken {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_file(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("haptics-proto-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn token_file_first_line_and_rules() {
        let p = temp_file(
            "ok.token",
            "# viewer token\n\n  0123456789abcdef0123  \nnext\n",
        );
        let c = ClientCredentials {
            token_file: Some(p),
            ..Default::default()
        };
        assert_eq!(c.token().unwrap().as_deref(), Some("0123456789abcdef0123"));
        for bad in ["short", "has a space in it 0123456789", ""] {
            let p = temp_file("bad.token", bad);
            let c = ClientCredentials {
                token_file: Some(p.clone()),
                ..Default::default()
            };
            let e = c.token().unwrap_err().to_string();
            assert!(e.contains("printable ASCII"), "{e}");
            if !bad.is_empty() {
                assert!(!e.contains(bad), "the message quotes the token: {e}");
            }
        }
        let big = temp_file("big.token", &"a".repeat(5000));
        let c = ClientCredentials {
            token_file: Some(big),
            ..Default::default()
        };
        assert!(c.token().unwrap_err().to_string().contains("larger than"));
    }

    #[test]
    fn new_variable_names_win_and_the_old_ones_still_answer() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| std::ffi::OsString::from(v))
            }
        };
        let both = env(&[("HAPTICD_TOKEN_FILE", "new"), ("HAPTICS_TOKEN_FILE", "old")]);
        assert_eq!(
            lookup_with_alias("HAPTICD_TOKEN_FILE", both),
            Some(("HAPTICD_TOKEN_FILE", "new".into()))
        );
        let old = env(&[("HAPTICS_TLS_CA", "ca.pem")]);
        assert_eq!(
            lookup_with_alias("HAPTICD_TLS_CA", old),
            Some(("HAPTICS_TLS_CA", "ca.pem".into()))
        );
        assert_eq!(lookup_with_alias("HAPTICD_TOKEN", env(&[])), None);
        // Every client variable follows the scheme and has its alias.
        for (new, old) in ENV_ALIASES {
            assert!(new.starts_with("HAPTICD_") && old.starts_with("HAPTICS_"));
            assert_eq!(new["HAPTICD_".len()..], old["HAPTICS_".len()..]);
        }
    }

    #[test]
    fn tls_rules() {
        let c = ClientCredentials::default();
        let e = c.endpoint("https://localhost:1").unwrap_err().to_string();
        assert!(e.contains("--tls-ca"), "{e}");
        let c = ClientCredentials {
            tls_ca: Some("/nonexistent/ca.pem".into()),
            ..Default::default()
        };
        let e = c.endpoint("http://localhost:1").unwrap_err().to_string();
        assert!(e.contains("not https"), "{e}");
        assert!(
            ClientCredentials::default()
                .endpoint("http://localhost:1")
                .is_ok()
        );
    }
}
