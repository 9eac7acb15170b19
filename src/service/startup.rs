//! Building and running the service: open the store (migrations), bind, spawn the workers, the
//! webhook dispatcher and the retention sweep, serve until a shutdown signal, then drain.

use crate::domain::thread::ConnectionTable;
use crate::service::api::{self, AppState};
use crate::service::config::Settings;
use crate::service::store::{Store, StoreError, now_ms};
use crate::service::telemetry::Metrics;
use crate::service::worker::{self, WorkerContext};
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::{Notify, watch};

#[derive(Debug, thiserror::Error)]
pub enum StartupError {
    #[error(transparent)]
    Config(#[from] crate::service::config::ConfigError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("cannot listen on {addr}: {source}")]
    Bind { addr: SocketAddr, source: std::io::Error },
    #[error("webhooks: no HTTP client ({0})")]
    Webhooks(String),
    #[error("{0}")]
    OpcUa(String),
}

pub struct Application {
    listener: TcpListener,
    state: AppState,
    stop: watch::Sender<bool>,
    worker: WorkerContext,
    address: SocketAddr,
    webhooks: reqwest::Client,
    opcua: Option<crate::service::opcua::OpcUaServer>,
}

impl Application {
    pub async fn build(mut settings: Settings) -> Result<Self, StartupError> {
        settings.validate()?;
        if !settings.role.runs_jobs() {
            settings.workers = 0;
        }
        let webhooks =
            crate::service::webhooks::client(&settings).map_err(|e| StartupError::Webhooks(e.to_string()))?;
        let mut store = Store::connect(&settings.database(), &settings.uploads_dir(), &settings.tmp_dir()).await?;
        store.files = store.files.with_free_floor(settings.min_free_disk_mb.saturating_mul(1 << 20));
        store.max_interruptions = settings.max_interruptions as i64;
        if let Some(url) = &settings.object_store {
            use crate::service::store::blobs::{BlobStore, S3Blobs};
            let blobs = S3Blobs::open_url(url, &settings.s3(), &settings.tmp_dir()).map_err(StoreError::Io)?;
            // Refuse to start against a store that does not take a write, rather than accept
            // uploads that cannot be kept.
            blobs.check().await.map_err(|e| {
                StoreError::Io(std::io::Error::new(e.kind(), format!("object store {}: {e}", blobs.describe())))
            })?;
            tracing::info!(blobs = %blobs.describe(), "uploads, meshes and images are kept in the object store");
            let blobs = Arc::new(blobs);
            store.blobs = blobs.clone();
            store.artifact_objects = Some(blobs);
        }
        let cleared = store.files.clear_temporaries(Duration::from_secs(6 * 3600)).map_err(StoreError::Io)?;
        if cleared > 0 {
            tracing::info!(cleared, "removed temporaries of interrupted uploads");
        }
        let orphans = store.remove_orphan_uploads().await?;
        if orphans > 0 {
            tracing::info!(orphans, "removed upload files no inspection names (a submission that failed to commit)");
        }
        if settings.mqtt_url.is_some() {
            store.mqtt_start_cursor().await?;
        }
        let orphans = store.remove_orphan_artifacts(orphan_cutoff_ms(&settings)).await?;
        if orphans > 0 {
            tracing::info!(orphans, "removed artifact objects no inspection names (a completion that did not commit)");
        }
        let listener = TcpListener::bind(settings.bind)
            .await
            .map_err(|source| StartupError::Bind { addr: settings.bind, source })?;
        let address = listener.local_addr().map_err(|source| StartupError::Bind { addr: settings.bind, source })?;
        // Bound here, so that a taken port stops the start as the HTTP one does.
        let opcua = match (&settings.opcua_endpoint, settings.role.serves_api()) {
            (Some(url), true) => Some(
                crate::service::opcua::OpcUaServer::bind(&settings, &store, url).await.map_err(StartupError::OpcUa)?,
            ),
            _ => None,
        };
        let table = Arc::new(ConnectionTable::api5b());
        let metrics = Arc::new(Metrics::new());
        let wake = Arc::new(Notify::new());
        let settings = Arc::new(settings);
        let models = Arc::new(crate::learned::Models::new(Some(settings.models_dir())));
        let (stop, stopping) = watch::channel(false);
        let state = AppState {
            store: store.clone(),
            table: table.clone(),
            metrics: metrics.clone(),
            settings: settings.clone(),
            wake: wake.clone(),
            uploads: Arc::new(crate::service::api::ingest::UploadGate::new(
                settings.max_concurrent_uploads,
                settings.max_uploads_per_client,
                settings.min_upload_kib_per_s * 1024.0,
            )),
            browser: Arc::new(crate::service::api::origins::BrowserPolicy::new(
                &settings.allowed_hosts,
                &settings.allowed_origins,
            )),
            models: models.clone(),
            stopping,
            submissions: Default::default(),
        };
        let worker = WorkerContext {
            store,
            table,
            metrics,
            compute: worker::compute_pool(&settings),
            settings: (*settings).clone(),
            wake,
            owner: format!("{}-{}", std::process::id(), uuid::Uuid::now_v7()),
            models,
        };
        Ok(Self { listener, state, stop, worker, address, webhooks, opcua })
    }

    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// The OPC UA endpoint's URL with its port, where one is served.
    pub fn opcua_url(&self) -> Option<&str> {
        self.opcua.as_ref().map(|o| o.url())
    }

    /// Serves until `shutdown` resolves; then stops claiming, drains requests, and gives running
    /// jobs the grace period.
    pub async fn run_until(self, shutdown: impl Future<Output = ()> + Send + 'static) -> std::io::Result<()> {
        let (stop_tx, stop_rx) = (self.stop, self.state.stopping.clone());
        let workers = tokio::spawn(worker::run(self.worker.clone(), stop_rx.clone()));
        let sweeper = tokio::spawn(retention_sweep(self.state.clone(), stop_rx.clone()));
        // PostgreSQL: other processes' changes and queued uploads, by LISTEN/NOTIFY.
        let listener = {
            let store = self.state.store.clone();
            let (wake, stop) = (self.state.wake.clone(), stop_rx.clone());
            tokio::spawn(async move { store.listen(wake, stop).await })
        };
        let webhooks = tokio::spawn(crate::service::webhooks::run(
            self.state.store.clone(),
            self.webhooks,
            self.state.settings.clone(),
            stop_rx.clone(),
        ));
        let mqtt = tokio::spawn(crate::service::mqtt::run(
            self.state.store.clone(),
            self.state.settings.clone(),
            stop_rx.clone(),
        ));
        let opcua = self.opcua.map(|server| tokio::spawn(server.run(self.state.store.clone(), stop_rx.clone())));
        let header_timeout = Duration::from_secs_f64(self.state.settings.header_timeout_seconds);
        let app = if self.state.settings.role.serves_api() {
            api::router(self.state)
        } else {
            api::operations_router(self.state)
        };
        let mut http_stop = stop_rx.clone();
        let server = serve(self.listener, app, header_timeout, async move {
            let _ = http_stop.wait_for(|s| *s).await;
        });
        let signal = tokio::spawn(async move {
            shutdown.await;
            tracing::info!("shutdown requested");
            let _ = stop_tx.send(true);
        });
        server.await?;
        let _ = workers.await;
        // A delivery cut off here is attempted again by the next process (its lease lapses).
        webhooks.abort();
        // Given a moment to release its lease; an event cut off is published again (at least once).
        let _ = tokio::time::timeout(Duration::from_secs(2), mqtt).await;
        if let Some(opcua) = opcua {
            // It shows `Halted` to its subscribers, then closes its sessions.
            let _ = tokio::time::timeout(Duration::from_secs(5), opcua).await;
        }
        sweeper.abort();
        listener.abort();
        signal.abort();
        tracing::info!("stopped");
        Ok(())
    }
}

/// Serves HTTP/1.1 on `listener` until `stop` resolves, then lets open requests finish. Each
/// connection must send a request's whole head within `header_timeout` (the timer also runs while
/// a kept-alive connection waits for its next request, so idle connections close after it); the
/// HTTP layer's own head limits sit far above the router's (`api::MAX_HEADER_BYTES`, …), which
/// answer with problem+json. Each request carries the peer's address (`ConnectInfo`).
async fn serve(
    listener: TcpListener,
    app: axum::Router,
    header_timeout: Duration,
    stop: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    use hyper_util::rt::{TokioIo, TokioTimer};
    use tower::ServiceExt;
    let (closing_tx, closing_rx) = watch::channel(false);
    let mut connections = tokio::task::JoinSet::new();
    tokio::pin!(stop);
    loop {
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // Out of descriptors and the like: back off instead of spinning.
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut stop => break,
        };
        let service = app.clone().map_request(move |mut request: axum::http::Request<hyper::body::Incoming>| {
            request.extensions_mut().insert(axum::extract::ConnectInfo(peer));
            request.map(axum::body::Body::new)
        });
        let service = hyper_util::service::TowerToHyperService::new(service);
        let mut closing = closing_rx.clone();
        connections.spawn(async move {
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(header_timeout)
                .max_buf_size(1 << 20)
                .max_headers(1000)
                .serve_connection(TokioIo::new(stream), service);
            tokio::pin!(connection);
            tokio::select! {
                result = connection.as_mut() => {
                    if let Err(e) = result { tracing::debug!(error = %e, "connection ended"); }
                }
                _ = async { let _ = closing.wait_for(|c| *c).await; } => {
                    connection.as_mut().graceful_shutdown();
                    let _ = connection.as_mut().await;
                }
            }
        });
        // Reap finished connections so the set stays small.
        while connections.try_join_next().is_some() {}
    }
    drop(listener);
    let _ = closing_tx.send(true);
    while connections.join_next().await.is_some() {}
    Ok(())
}

/// Hourly: deletes the uploads, and the meshes and images, of inspections finished longer ago than
/// their retention periods (`upload_retention_days`, `artifact_retention_days`; 0 keeps them), and
/// upload files that no inspection names (a submission whose commit failed).
async fn retention_sweep(state: AppState, mut stop: watch::Receiver<bool>) {
    let (days, artifact_days) = (state.settings.upload_retention_days, state.settings.artifact_retention_days);
    loop {
        if days > 0.0 {
            let cutoff = now_ms() - (days * 86_400_000.0) as i64;
            match state.store.purge_uploads(cutoff).await {
                Ok(0) => {}
                Ok(n) => tracing::info!(purged = n, "retention: deleted old uploads"),
                Err(e) => tracing::warn!(error = %e, "retention sweep failed"),
            }
        }
        if artifact_days > 0.0 {
            let cutoff = now_ms() - (artifact_days * 86_400_000.0) as i64;
            match state.store.purge_artifacts(cutoff).await {
                Ok(0) => {}
                Ok(n) => tracing::info!(inspections = n, "retention: deleted old meshes and images"),
                Err(e) => tracing::warn!(error = %e, "artifact retention sweep failed"),
            }
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(3600)) => {}
            _ = stop.changed() => return,
        }
        // After the wait: `Application::build` removed them at start-up just before.
        match state.store.remove_orphan_uploads().await {
            Ok(0) => {}
            Ok(n) => tracing::info!(removed = n, "retention: deleted upload files no inspection names"),
            Err(e) => tracing::warn!(error = %e, "orphan upload sweep failed"),
        }
        // Status events a month old are history (the MQTT publisher's undelivered ones stay).
        if let Err(e) = state.store.purge_events(now_ms() - 30 * 86_400_000).await {
            tracing::warn!(error = %e, "event retention failed");
        }
        match state.store.remove_orphan_artifacts(orphan_cutoff_ms(&state.settings)).await {
            Ok(0) => {}
            Ok(n) => tracing::info!(removed = n, "retention: deleted artifact objects no inspection names"),
            Err(e) => tracing::warn!(error = %e, "orphan artifact sweep failed"),
        }
    }
}

/// Artifact objects no record names and written before this are orphans (`orphan_grace_seconds`).
fn orphan_cutoff_ms(settings: &Settings) -> i64 {
    now_ms() - (settings.orphan_grace_seconds * 1000.0) as i64
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = terminate => {}
    }
}
