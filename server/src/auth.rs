//! Who may do what (issue 16, section 3): bearer tokens with roles, checked on every call of
//! the `haptics.v1` services.
//!
//! - **Tokens** live in a TOML file the operator names (`[auth] tokens_file`, `--tokens-file`
//!   or `HAPTICD_TOKENS_FILE`; never a token on the command line). Each entry has a `name`, a
//!   `role` and the `token` (16-1024 printable ASCII characters). The file must not be
//!   readable by group or others. At first start, when the file does not exist, the daemon
//!   creates it with one fresh 256-bit token per role and writes each token also to
//!   `<role>.token` beside it (all mode 0600), for the clients on the same machine.
//! - **Roles** ([`Role`]): `device` connects a `DeviceLink` to any session; `control` starts
//!   sessions and stops, pushes, reads the statistics of and watches **the sessions it
//!   started**; `viewer` lists sessions, watches and reads statistics; `admin` does everything.
//!   `ListScenes` is open to every role.
//! - **Answers**: no token or an unknown one is `UNAUTHENTICATED`; a role without the right is
//!   `PERMISSION_DENIED`. Failed attempts are counted per client address and logged, the first
//!   of a window and the one that reaches `max_failures` at `warn`, the rest at `debug`; past
//!   the limit an address's failures are no longer counted until `failure_window` ends. A known
//!   token is never refused because of failures from its address (issue 47: local clients all
//!   share 127.0.0.1); guessing is answered by the tokens' 256 bits, not by the limit.
//! - Tokens are compared by their SHA-256 digests (a hash-map lookup), so the time of a check
//!   does not depend on how much of a guess is right.
//!
//! Without a tokens file every call is allowed (an anonymous `admin`): the daemon then refuses
//! to listen beyond loopback unless the operator says so
//! ([`crate::config::ServerConfig::allow_insecure_remote`]).
//!
//! Neighbours: [`crate::service`] calls [`Auth::authorize`] first in every handler;
//! [`crate::run`] puts [`AuthInterceptor`] in front of the services; clients attach tokens with
//! `haptic_cli::credentials`.

use std::collections::HashMap;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::Deserialize;
use tonic::{Request, Status};

use crate::error::ServerError;

/// What a token may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Watch and read statistics of any session, list sessions.
    Viewer,
    /// Connect a device stream to any session.
    Device,
    /// Start sessions; stop, push, watch and read the statistics of its own.
    Control,
    /// Everything.
    Admin,
}

impl Role {
    /// Every role, in the order the generated tokens file lists them.
    pub const ALL: [Role; 4] = [Role::Admin, Role::Control, Role::Device, Role::Viewer];

    /// The role's name in the tokens file.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Device => "device",
            Role::Control => "control",
            Role::Admin => "admin",
        }
    }
}

/// An RPC, as far as permissions go.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    /// `SessionControl.ListScenes`.
    ListScenes,
    /// `SessionControl.ListSessions`.
    ListSessions,
    /// `SessionControl.StartSession`.
    StartSession,
    /// `SessionControl.StopSession`.
    StopSession,
    /// `SessionControl.ApplyForce`.
    ApplyForce,
    /// `SessionControl.GetStats`.
    GetStats,
    /// `DeviceLink.Connect`.
    DeviceLink,
    /// `SurfaceStream.Watch` and `RequestKeyframe`.
    Watch,
}

/// What `role` may do with `action`: `Some(true)` on any session, `Some(false)` only on the
/// sessions the caller started, `None` not at all.
fn permission(role: Role, action: Action) -> Option<bool> {
    use Action::*;
    match (role, action) {
        (Role::Admin, _) | (_, ListScenes) => Some(true),
        (Role::Viewer, ListSessions | GetStats | Watch) => Some(true),
        (Role::Device, DeviceLink) => Some(true),
        (Role::Control, StartSession) => Some(true),
        (Role::Control, ListSessions | StopSession | ApplyForce | GetStats | Watch) => Some(false),
        _ => None,
    }
}

/// The authenticated caller of a request (in its extensions once [`AuthInterceptor`] passed it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Caller {
    /// The token's name in the tokens file (`anonymous` without tokens).
    pub name: Arc<str>,
    /// Its role.
    pub role: Role,
}

type Digest = [u8; 32];

fn digest(token: &str) -> Digest {
    let d = ring::digest::digest(&ring::digest::SHA256, token.as_bytes());
    let mut out = [0; 32];
    out.copy_from_slice(d.as_ref());
    out
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TokensFile {
    #[serde(default)]
    token: Vec<TokenEntry>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TokenEntry {
    name: String,
    role: Role,
    token: String,
}

/// Largest tokens file read, bytes.
pub const MAX_TOKENS_FILE_BYTES: u64 = 1 << 20;

/// The tokens the daemon accepts, by digest.
#[derive(Debug, Default)]
pub struct TokenStore {
    by_digest: HashMap<Digest, Caller>,
}

impl TokenStore {
    /// Parses tokens-file text (`[[token]]` entries with `name`, `role`, `token`).
    ///
    /// # Errors
    /// [`ServerError::Config`] for a TOML error, an empty file, a malformed token (16-1024
    /// printable ASCII characters), a repeated name or a repeated token. Messages give the
    /// line or the entry's number and what was expected, never the file's text (issue 47).
    pub fn parse(text: &str) -> Result<Self, ServerError> {
        let file: TokensFile = toml::from_str(text).map_err(|e| {
            ServerError::Config(format!(
                "tokens file: {}",
                haptic_model::scene::describe_toml_error(text, &e)
            ))
        })?;
        if file.token.is_empty() {
            return Err(ServerError::Config(
                "tokens file has no [[token]] entry".into(),
            ));
        }
        let mut store = TokenStore::default();
        let mut names = std::collections::HashSet::new();
        for (i, e) in file.token.into_iter().enumerate() {
            let entry = i + 1;
            if e.name.is_empty() || e.name.len() > 64 || !names.insert(e.name.clone()) {
                return Err(ServerError::Config(format!(
                    "tokens file, [[token]] entry {entry}: expected a name of 1-64 characters \
                     that no other entry has"
                )));
            }
            if !(16..=1024).contains(&e.token.len())
                || !e.token.bytes().all(|b| b.is_ascii_graphic())
            {
                return Err(ServerError::Config(format!(
                    "tokens file, [[token]] entry {entry}: the token must be 16-1024 printable \
                     ASCII characters without spaces"
                )));
            }
            let caller = Caller {
                name: e.name.as_str().into(),
                role: e.role,
            };
            if store.by_digest.insert(digest(&e.token), caller).is_some() {
                return Err(ServerError::Config(format!(
                    "tokens file, [[token]] entry {entry}: its token is used by an earlier entry"
                )));
            }
        }
        Ok(store)
    }

    /// Reads the tokens file at `path`.
    ///
    /// # Errors
    /// [`ServerError::Config`] when it cannot be read, is not a regular file, is larger than
    /// 1 MiB, is readable by group or others, or does not parse ([`Self::parse`]).
    pub fn load(path: &Path) -> Result<Self, ServerError> {
        use std::io::Read;
        use std::os::unix::fs::PermissionsExt;
        let err = |m: String| ServerError::Config(format!("tokens file {}: {m}", path.display()));
        let file = std::fs::File::open(path).map_err(|e| err(e.to_string()))?;
        let meta = file.metadata().map_err(|e| err(e.to_string()))?;
        if !meta.is_file() {
            return Err(err("not a regular file".into()));
        }
        let mode = meta.permissions().mode() & 0o777;
        if mode & 0o077 != 0 {
            return Err(err(format!(
                "readable by group or others (mode {mode:04o}); run chmod 600 on it"
            )));
        }
        let mut text = String::new();
        file.take(MAX_TOKENS_FILE_BYTES + 1)
            .read_to_string(&mut text)
            .map_err(|e| err(e.to_string()))?;
        if text.len() as u64 > MAX_TOKENS_FILE_BYTES {
            return Err(err(format!("larger than {MAX_TOKENS_FILE_BYTES} bytes")));
        }
        Self::parse(&text).map_err(|e| err(e.to_string()))
    }

    /// Creates the tokens file at `path` with one fresh token per role (named after the role)
    /// and writes each token to `<role>.token` in the same directory; every file mode 0600,
    /// created only if absent. Returns the store and the token files written.
    ///
    /// # Errors
    /// [`ServerError::Config`] when a file exists already or cannot be written, or the system
    /// random source fails.
    pub fn create(path: &Path) -> Result<(Self, Vec<PathBuf>), ServerError> {
        let err =
            |p: &Path, m: String| ServerError::Config(format!("writing {}: {m}", p.display()));
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut text = String::from(
            "# hapticd tokens: one [[token]] per client (name, role: admin, control, device or\n\
             # viewer, token). Keep this file mode 0600. See docs/security.md.\n",
        );
        let mut role_files = Vec::new();
        for role in Role::ALL {
            let token = random_token()?;
            text.push_str(&format!(
                "\n[[token]]\nname = \"{0}\"\nrole = \"{0}\"\ntoken = \"{token}\"\n",
                role.as_str()
            ));
            role_files.push((dir.join(format!("{}.token", role.as_str())), token));
        }
        write_private(path, &text).map_err(|e| err(path, e.to_string()))?;
        let mut written = vec![path.to_owned()];
        for (p, token) in role_files {
            write_private(&p, &format!("{token}\n")).map_err(|e| err(&p, e.to_string()))?;
            written.push(p);
        }
        Ok((Self::parse(&text)?, written))
    }

    /// How many tokens the store holds.
    pub fn len(&self) -> usize {
        self.by_digest.len()
    }

    /// True when the store holds no token.
    pub fn is_empty(&self) -> bool {
        self.by_digest.is_empty()
    }

    fn caller(&self, token: &str) -> Option<&Caller> {
        self.by_digest.get(&digest(token))
    }
}

/// 32 random bytes from the system source, as 64 hexadecimal digits.
fn random_token() -> Result<String, ServerError> {
    use ring::rand::SecureRandom;
    let mut bytes = [0u8; 32];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .map_err(|_| ServerError::Config("the system random source failed".into()))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Writes a new file readable by its owner only (fails if it exists).
fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)?;
    f.write_all(text.as_bytes())?;
    f.sync_all()
}

/// Limits on failed attempts (from [`crate::config::ServerConfig`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FailureLimits {
    /// Failed calls one address may make per window before it is refused outright.
    pub max_failures: u32,
    /// The window, and how long an address stays refused.
    pub window: Duration,
}

impl Default for FailureLimits {
    fn default() -> Self {
        Self {
            max_failures: 10,
            window: Duration::from_secs(10),
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct FailureWindow {
    start: Instant,
    count: u32,
}

/// Addresses whose failures are tracked at most (older windows are pruned first; beyond
/// this, new addresses are not tracked so memory stays bounded).
const MAX_TRACKED_ADDRESSES: usize = 10_000;

/// Token checks, failure counting and session ownership; shared by every handler.
#[derive(Debug)]
pub struct Auth {
    store: Option<TokenStore>,
    limits: FailureLimits,
    failures: Mutex<HashMap<Option<IpAddr>, FailureWindow>>,
    owners: Mutex<HashMap<String, Arc<str>>>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl Auth {
    /// Every call allowed (no tokens file).
    pub fn open() -> Self {
        Self::new(None, FailureLimits::default())
    }

    /// Checks calls against `store` (`None`: every call allowed, as an anonymous admin).
    pub fn new(store: Option<TokenStore>, limits: FailureLimits) -> Self {
        Self {
            store,
            limits,
            failures: Mutex::new(HashMap::new()),
            owners: Mutex::new(HashMap::new()),
        }
    }

    /// The daemon's access control from its configuration: the tokens file is read, or
    /// created with one token per role when it does not exist (logged with the files written).
    ///
    /// # Errors
    /// As [`TokenStore::load`] and [`TokenStore::create`].
    pub fn from_config(
        tokens_file: Option<&Path>,
        limits: FailureLimits,
    ) -> Result<Self, ServerError> {
        let store = match tokens_file {
            None => None,
            Some(p) if p.exists() => Some(TokenStore::load(p)?),
            Some(p) => {
                let (store, written) = TokenStore::create(p)?;
                let files: Vec<_> = written.iter().map(|p| p.display().to_string()).collect();
                tracing::info!(
                    "created tokens for roles admin, control, device, viewer (mode 0600): {}",
                    files.join(", ")
                );
                Some(store)
            }
        };
        if let Some(s) = &store {
            tracing::info!(tokens = s.len(), "token authentication on");
        }
        Ok(Self::new(store, limits))
    }

    /// True when calls must carry a known token.
    pub fn required(&self) -> bool {
        self.store.is_some()
    }

    /// Authenticates one call: puts its [`Caller`] in the request's extensions. A known token
    /// is always accepted, whatever other clients from the same address did (issue 47: on a
    /// lab machine every local client shares 127.0.0.1, and one misconfigured bridge must not
    /// lock the others out; the tokens are 256-bit, so guessing is not the threat the limit
    /// answers). Failures are what is limited: past `max_failures` in a window, an address's
    /// further failures are answered at once, not counted and logged only at `debug`, until
    /// the window ends.
    ///
    /// # Errors
    /// `UNAUTHENTICATED` for no token or an unknown token (saying so, and past the limit that
    /// the address failed too often).
    pub fn authenticate(&self, req: &mut Request<()>) -> Result<(), Status> {
        let Some(store) = &self.store else {
            return Ok(());
        };
        let address = req.remote_addr().map(|a| a.ip());
        let now = Instant::now();
        let token = req
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| {
                let (scheme, rest) = v.split_once(' ')?;
                scheme.eq_ignore_ascii_case("bearer").then(|| rest.trim())
            });
        let caller = match token {
            None => Err("no token (send `authorization: Bearer <token>`; see docs/security.md)"),
            Some(t) => store.caller(t).ok_or("unknown token"),
        };
        match caller {
            Ok(c) => {
                req.extensions_mut().insert(c.clone());
                Ok(())
            }
            Err(why) => {
                if let Some(retry) = self.refused_for(address, now) {
                    tracing::debug!(?address, "authentication failed: {why} (over the limit)");
                    return Err(Status::unauthenticated(format!(
                        "{why}; too many failed attempts from this address (the next {} s are \
                         not logged)",
                        retry.as_secs().max(1)
                    )));
                }
                self.count_failure(address, now, why);
                Err(Status::unauthenticated(why))
            }
        }
    }

    /// How long `address` stays refused, if it is over its failure limit.
    fn refused_for(&self, address: Option<IpAddr>, now: Instant) -> Option<Duration> {
        let failures = lock(&self.failures);
        let w = failures.get(&address)?;
        let elapsed = now.duration_since(w.start);
        (w.count >= self.limits.max_failures && elapsed < self.limits.window)
            .then(|| self.limits.window - elapsed)
    }

    fn count_failure(&self, address: Option<IpAddr>, now: Instant, why: &str) {
        let mut failures = lock(&self.failures);
        let window = self.limits.window;
        if failures.len() >= MAX_TRACKED_ADDRESSES && !failures.contains_key(&address) {
            failures.retain(|_, w| now.duration_since(w.start) < window);
            if failures.len() >= MAX_TRACKED_ADDRESSES {
                tracing::warn!(
                    ?address,
                    "authentication failed: {why} (address not tracked: table full)"
                );
                return;
            }
        }
        let w = failures.entry(address).or_insert(FailureWindow {
            start: now,
            count: 0,
        });
        if now.duration_since(w.start) >= window {
            *w = FailureWindow {
                start: now,
                count: 0,
            };
        }
        w.count += 1;
        if w.count == 1 {
            tracing::warn!(?address, "authentication failed: {why}");
        } else if w.count == self.limits.max_failures {
            tracing::warn!(
                ?address,
                failures = w.count,
                "authentication failed: {why}; further failures from this address are not \
                 logged for {} s (its valid tokens still pass)",
                window.as_secs_f64()
            );
        } else {
            tracing::debug!(?address, failures = w.count, "authentication failed: {why}");
        }
    }

    /// The caller of `req` if its role may do `action` (on `session`, for per-session
    /// actions).
    ///
    /// # Errors
    /// `PERMISSION_DENIED` naming the role and the rule; `UNAUTHENTICATED` when tokens are
    /// required and the request was not authenticated (not passed through the interceptor).
    pub fn authorize<T>(
        &self,
        req: &Request<T>,
        action: Action,
        session: Option<&str>,
    ) -> Result<Caller, Status> {
        if self.store.is_none() {
            return Ok(Caller {
                name: "anonymous".into(),
                role: Role::Admin,
            });
        }
        let caller = req
            .extensions()
            .get::<Caller>()
            .cloned()
            .ok_or_else(|| Status::unauthenticated("no token"))?;
        match permission(caller.role, action) {
            Some(true) => Ok(caller),
            Some(false) => match session {
                Some(id) if lock(&self.owners).get(id) == Some(&caller.name) => Ok(caller),
                Some(_) => Err(Status::permission_denied(format!(
                    "role {} acts only on sessions its token started, and this is not one",
                    caller.role.as_str()
                ))),
                // Listing: filtered by the handler with [`Auth::visible`].
                None => Ok(caller),
            },
            None => Err(Status::permission_denied(format!(
                "role {} may not call {action:?}",
                caller.role.as_str()
            ))),
        }
    }

    /// Records that `caller` started session `id`.
    pub fn set_owner(&self, id: &str, caller: &Caller) {
        lock(&self.owners).insert(id.to_owned(), caller.name.clone());
    }

    /// Forgets the owner of a stopped session.
    pub fn forget(&self, id: &str) {
        lock(&self.owners).remove(id);
    }

    /// The sessions of `ids` that `caller` may see in a listing.
    pub fn visible(&self, caller: &Caller, ids: Vec<String>) -> Vec<String> {
        if permission(caller.role, Action::ListSessions) == Some(true) || self.store.is_none() {
            return ids;
        }
        let owners = lock(&self.owners);
        ids.into_iter()
            .filter(|id| owners.get(id) == Some(&caller.name))
            .collect()
    }
}

/// Puts [`Auth::authenticate`] in front of a service.
#[derive(Debug, Clone)]
pub struct AuthInterceptor(pub Arc<Auth>);

impl tonic::service::Interceptor for AuthInterceptor {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        self.0.authenticate(&mut req)?;
        Ok(req)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn permission_table() {
        use Action::*;
        let all = [
            ListScenes,
            ListSessions,
            StartSession,
            StopSession,
            ApplyForce,
            GetStats,
            DeviceLink,
            Watch,
        ];
        for a in all {
            assert_eq!(permission(Role::Admin, a), Some(true), "{a:?}");
        }
        let allowed = |r: Role| -> Vec<Action> {
            all.into_iter()
                .filter(|a| permission(r, *a).is_some())
                .collect()
        };
        assert_eq!(
            allowed(Role::Viewer),
            vec![ListScenes, ListSessions, GetStats, Watch]
        );
        assert_eq!(allowed(Role::Device), vec![ListScenes, DeviceLink]);
        assert_eq!(
            allowed(Role::Control),
            vec![
                ListScenes,
                ListSessions,
                StartSession,
                StopSession,
                ApplyForce,
                GetStats,
                Watch
            ]
        );
        assert_eq!(permission(Role::Control, StopSession), Some(false));
    }

    /// Issue 47: a client failing from an address never locks out the valid tokens of others
    /// from the same address; only the failures are limited.
    #[test]
    fn failures_never_lock_out_a_valid_token_from_the_same_address() {
        let text = "[[token]]\nname = \"arm\"\nrole = \"device\"\ntoken = \"0123456789abcdef\"\n";
        let auth = Auth::new(
            Some(TokenStore::parse(text).unwrap()),
            FailureLimits {
                max_failures: 3,
                window: Duration::from_secs(3600),
            },
        );
        // Requests without a transport share one address (`None`), as local clients share
        // 127.0.0.1.
        let call = |token: Option<&str>| {
            let mut req = Request::new(());
            if let Some(t) = token {
                req.metadata_mut()
                    .insert("authorization", format!("Bearer {t}").parse().unwrap());
            }
            auth.authenticate(&mut req)
                .map(|()| req.extensions().get::<Caller>().map(|c| c.name.to_string()))
        };
        for _ in 0..3 {
            let e = call(None).unwrap_err();
            assert_eq!(e.code(), tonic::Code::Unauthenticated);
            assert!(!e.message().contains("too many"), "{e:?}");
        }
        for _ in 0..20 {
            // Past the limit: failures say so, and are no longer counted ...
            let e = call(Some("wrong-0123456789abcdef")).unwrap_err();
            assert!(
                e.message().contains("unknown token") && e.message().contains("too many"),
                "{e:?}"
            );
            // ... and the valid token still passes, every time.
            assert_eq!(call(Some("0123456789abcdef")).unwrap(), Some("arm".into()));
        }
        assert_eq!(lock(&auth.failures)[&None].count, 3);
    }

    #[test]
    fn tokens_file_rules_never_quote_a_token() {
        let ok = "[[token]]\nname = \"a\"\nrole = \"viewer\"\ntoken = \"0123456789abcdef\"\n";
        assert_eq!(TokenStore::parse(ok).unwrap().len(), 1);
        let secret = "s3cr3t-0123456789-abcdef";
        for (text, rule) in [
            (String::new(), "no [[token]]"),
            (
                format!("[[token]]\nname = \"a\"\nrole = \"{secret}\"\ntoken = \"{secret}\"\n"),
                "line 3, column 8: unknown value; expected one of",
            ),
            (
                format!("[[token]]\nname = \"a\"\nrole = \"admin\"\ntoken = {secret}\n"),
                "line 4",
            ),
            (
                "[[token]]\nname = \"a\"\nrole = \"admin\"\ntoken = \"short\"\n".into(),
                "16-1024",
            ),
            (
                format!(
                    "[[token]]\nname = \"a\"\nrole = \"admin\"\ntoken = \"{secret}\"\n\
                     [[token]]\nname = \"b\"\nrole = \"viewer\"\ntoken = \"{secret}\"\n"
                ),
                "used by an earlier entry",
            ),
            (
                format!("{ok}[[token]]\nname = \"a\"\nrole = \"admin\"\ntoken = \"{secret}\"\n"),
                "entry 2: expected a name",
            ),
        ] {
            let e = TokenStore::parse(&text).unwrap_err().to_string();
            assert!(e.contains(rule), "{rule}: {e}");
            assert!(!e.contains(secret), "the message quotes a token: {e}");
        }
    }
}
