//! Shared by the end-to-end tests that run the server library in process.

use anyhow::{Context, Result};
use haptic_e2e::STEP_TIMEOUT;
use tokio::sync::oneshot;

/// The server library on 127.0.0.1:0; dropping the guard stops it.
pub struct InProcess {
    /// `http://127.0.0.1:PORT`.
    pub url: String,
    stop: Option<oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<Result<(), haptic_server::ServerError>>>,
}

impl InProcess {
    /// Starts the server on a port-0 listener.
    #[allow(dead_code)] // not every test binary starts with the defaults
    pub async fn start() -> Result<Self> {
        Self::start_with(haptic_server::ServerConfig::default()).await
    }

    /// Starts the server with `config` on a port-0 listener (its `listen` is replaced; the
    /// URL is `https://localhost:PORT` when `config.tls` is set).
    pub async fn start_with(config: haptic_server::ServerConfig) -> Result<Self> {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let url = match config.tls {
            Some(_) => format!("https://localhost:{}", addr.port()),
            None => format!("http://{addr}"),
        };
        let (tx, rx) = oneshot::channel::<()>();
        let config = haptic_server::ServerConfig {
            listen: addr,
            ..config
        };
        let task = tokio::spawn(haptic_server::run(listener, config, async move {
            let _ = rx.await;
        }));
        Ok(Self {
            url,
            stop: Some(tx),
            task: Some(task),
        })
    }

    /// Stops the server and waits for it.
    pub async fn shutdown(mut self) -> Result<()> {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(task) = self.task.take() {
            tokio::time::timeout(STEP_TIMEOUT, task)
                .await
                .context("the in-process server did not stop")???;
        }
        Ok(())
    }
}

impl Drop for InProcess {
    fn drop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
    }
}
