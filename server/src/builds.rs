//! Who may build a scene, when, and for how long (issue 16, section 2). `StartSession` builds
//! its model on a blocking thread; this module bounds that work:
//!
//! - at most `max_concurrent_builds` builds run at once; later calls wait for a turn;
//! - one client address has at most `max_builds_per_client` calls waiting or building and
//!   `max_sessions_per_client` sessions running (counting its builds in flight), beyond which
//!   it gets `RESOURCE_EXHAUSTED` at once;
//! - the whole call has a deadline (`build_timeout`): past it the client gets
//!   `DEADLINE_EXCEEDED`. A model build cannot be interrupted, so a late build finishes on its
//!   thread, still holding its turn and its client's count (the bounds stay true), and its
//!   session is stopped as soon as it exists.
//!
//! Clients are told apart by their address (there is no authentication yet); calls without one
//! (in-process transports) share one anonymous client.
//!
//! Neighbours: [`crate::service`] runs `StartSession` through [`BuildGate::run`];
//! [`crate::session::SessionManager`] builds and stops sessions.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::sync::Semaphore;

use crate::error::ServerError;
use crate::session::{Session, SessionManager};

/// The limits of [`BuildGate`] (from [`crate::config::ServerConfig`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BuildLimits {
    /// Builds running at once.
    pub max_concurrent_builds: usize,
    /// Calls of one client waiting or building at once.
    pub max_builds_per_client: usize,
    /// Sessions of one client running, builds in flight included.
    pub max_sessions_per_client: usize,
    /// Deadline of a call.
    pub build_timeout: Duration,
}

#[derive(Debug, Default)]
struct Clients {
    /// Calls in flight (waiting or building) per client.
    in_flight: HashMap<Option<IpAddr>, usize>,
    /// The client that started each session (entries of stopped sessions are pruned).
    owners: HashMap<String, Option<IpAddr>>,
}

/// Bounds scene builds: a pool of turns, per-client counts, a deadline.
#[derive(Debug)]
pub struct BuildGate {
    limits: BuildLimits,
    turns: Arc<Semaphore>,
    clients: Arc<Mutex<Clients>>,
}

/// A client's call in flight; releases its count when dropped (on the build's thread when the
/// build outlives the call).
struct Ticket {
    client: Option<IpAddr>,
    clients: Arc<Mutex<Clients>>,
}

impl Drop for Ticket {
    fn drop(&mut self) {
        let mut c = lock(&self.clients);
        if let Some(n) = c.in_flight.get_mut(&self.client) {
            *n -= 1;
            if *n == 0 {
                c.in_flight.remove(&self.client);
            }
        }
    }
}

fn lock(m: &Mutex<Clients>) -> MutexGuard<'_, Clients> {
    // The counts stay consistent under a panic elsewhere (each update is one statement).
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// How a build and its call ended, decided once under a lock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Outcome {
    Running,
    Delivered,
    Abandoned,
}

impl BuildGate {
    /// A gate with `limits`.
    pub fn new(limits: BuildLimits) -> Self {
        Self {
            limits,
            turns: Arc::new(Semaphore::new(limits.max_concurrent_builds.max(1))),
            clients: Arc::new(Mutex::new(Clients::default())),
        }
    }

    /// Runs `build` (on a blocking thread) for `client` within the limits, and records the
    /// session it returns as the client's.
    ///
    /// # Errors
    /// [`ServerError::Exhausted`] when the client is over its limits (nothing was started);
    /// [`ServerError::DeadlineExceeded`] when no turn came or the build did not finish before
    /// the deadline (a session it makes later is stopped); `build`'s own error otherwise.
    pub async fn run<F>(
        &self,
        client: Option<IpAddr>,
        manager: &Arc<SessionManager>,
        build: F,
    ) -> Result<Arc<Session>, ServerError>
    where
        F: FnOnce() -> Result<Arc<Session>, ServerError> + Send + 'static,
    {
        let ticket = self.admit(client, manager)?;
        let deadline = tokio::time::Instant::now() + self.limits.build_timeout;
        let timeout_s = self.limits.build_timeout.as_secs_f64();
        let turn = tokio::time::timeout_at(deadline, self.turns.clone().acquire_owned())
            .await
            .map_err(|_| {
                ServerError::DeadlineExceeded(format!(
                    "no scene build turn within the {timeout_s} s deadline (build_timeout_s; \
                     {} builds run at once)",
                    self.limits.max_concurrent_builds
                ))
            })?
            .map_err(|_| ServerError::Internal("build pool closed".into()))?;
        let outcome = Arc::new(Mutex::new(Outcome::Running));
        let job = {
            let outcome = outcome.clone();
            let manager = manager.clone();
            let handle = tokio::runtime::Handle::current();
            tokio::task::spawn_blocking(move || {
                let _guard = handle.enter();
                let (_turn, _ticket) = (turn, ticket);
                let result = build();
                let mut o = outcome
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                if *o == Outcome::Abandoned {
                    if let Ok(session) = &result {
                        let _ = manager.stop(&session.id);
                    }
                } else {
                    *o = Outcome::Delivered;
                }
                result
            })
        };
        tokio::pin!(job);
        let result = match tokio::time::timeout_at(deadline, &mut job).await {
            Ok(joined) => joined,
            Err(_) => {
                let abandoned = {
                    let mut o = outcome
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner);
                    let running = *o == Outcome::Running;
                    if running {
                        *o = Outcome::Abandoned;
                    }
                    running
                };
                if abandoned {
                    return Err(ServerError::DeadlineExceeded(format!(
                        "the scene did not build within the {timeout_s} s deadline \
                         (build_timeout_s); its session will not run"
                    )));
                }
                // Finished as the deadline passed: it is the client's.
                job.await
            }
        }
        .map_err(|e| ServerError::Internal(format!("scene build: {e}")))??;
        lock(&self.clients).owners.insert(result.id.clone(), client);
        Ok(result)
    }

    /// Counts a call of `client` in, or refuses it over the client's limits.
    fn admit(
        &self,
        client: Option<IpAddr>,
        manager: &SessionManager,
    ) -> Result<Ticket, ServerError> {
        let live = manager.ids();
        let mut c = lock(&self.clients);
        c.owners.retain(|id, _| live.contains(id));
        let in_flight = c.in_flight.get(&client).copied().unwrap_or(0);
        if in_flight >= self.limits.max_builds_per_client {
            return Err(ServerError::Exhausted(format!(
                "{in_flight} scene builds of this client are already waiting or running \
                 (max_builds_per_client = {})",
                self.limits.max_builds_per_client
            )));
        }
        let running = c.owners.values().filter(|o| **o == client).count();
        if running + in_flight >= self.limits.max_sessions_per_client {
            return Err(ServerError::Exhausted(format!(
                "this client has {running} sessions running and {in_flight} starting \
                 (max_sessions_per_client = {}); stop one first",
                self.limits.max_sessions_per_client
            )));
        }
        *c.in_flight.entry(client).or_insert(0) += 1;
        Ok(Ticket {
            client,
            clients: self.clients.clone(),
        })
    }
}
