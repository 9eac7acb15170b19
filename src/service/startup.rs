//! Building and running the service: open the store (migrations), bind, spawn the workers and the
//! retention sweep, serve until a shutdown signal, then drain.

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
}

pub struct Application {
    listener: TcpListener,
    state: AppState,
    worker: WorkerContext,
    address: SocketAddr,
}

impl Application {
    pub async fn build(settings: Settings) -> Result<Self, StartupError> {
        settings.validate()?;
        let mut store = Store::open(&settings.database_path(), &settings.uploads_dir(), &settings.tmp_dir()).await?;
        store.files = store.files.with_free_floor(settings.min_free_disk_mb.saturating_mul(1 << 20));
        let cleared = store.files.clear_temporaries(Duration::from_secs(6 * 3600)).map_err(StoreError::Io)?;
        if cleared > 0 {
            tracing::info!(cleared, "removed temporaries of interrupted uploads");
        }
        let listener = TcpListener::bind(settings.bind)
            .await
            .map_err(|source| StartupError::Bind { addr: settings.bind, source })?;
        let address = listener.local_addr().map_err(|source| StartupError::Bind { addr: settings.bind, source })?;
        let table = Arc::new(ConnectionTable::api5b());
        let metrics = Arc::new(Metrics::new());
        let wake = Arc::new(Notify::new());
        let settings = Arc::new(settings);
        let state = AppState {
            store: store.clone(),
            table: table.clone(),
            metrics: metrics.clone(),
            settings: settings.clone(),
            wake: wake.clone(),
            uploads: Arc::new(crate::service::api::ingest::UploadGate::new(
                settings.max_concurrent_uploads,
                settings.max_uploads_per_client,
            )),
        };
        let worker = WorkerContext {
            store,
            table,
            metrics,
            compute: worker::compute_pool(settings.compute_threads),
            settings: (*settings).clone(),
            wake,
            owner: format!("{}-{}", std::process::id(), uuid::Uuid::now_v7()),
        };
        Ok(Self { listener, state, worker, address })
    }

    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Serves until `shutdown` resolves; then stops claiming, drains requests, and gives running
    /// jobs the grace period.
    pub async fn run_until(self, shutdown: impl Future<Output = ()> + Send + 'static) -> std::io::Result<()> {
        let (stop_tx, stop_rx) = watch::channel(false);
        let workers = tokio::spawn(worker::run(self.worker.clone(), stop_rx.clone()));
        let sweeper = tokio::spawn(retention_sweep(self.state.clone(), stop_rx.clone()));
        let app = api::router(self.state);
        let mut http_stop = stop_rx.clone();
        let app = app.into_make_service_with_connect_info::<SocketAddr>();
        let server = axum::serve(self.listener, app).with_graceful_shutdown(async move {
            let _ = http_stop.wait_for(|s| *s).await;
        });
        let signal = tokio::spawn(async move {
            shutdown.await;
            tracing::info!("shutdown requested");
            let _ = stop_tx.send(true);
        });
        server.await?;
        let _ = workers.await;
        sweeper.abort();
        signal.abort();
        tracing::info!("stopped");
        Ok(())
    }
}

/// Deletes uploads of finished inspections older than the retention period, hourly.
async fn retention_sweep(state: AppState, mut stop: watch::Receiver<bool>) {
    let days = state.settings.upload_retention_days;
    if days <= 0.0 {
        return;
    }
    loop {
        let cutoff = now_ms() - (days * 86_400_000.0) as i64;
        match state.store.purge_uploads(cutoff).await {
            Ok(0) => {}
            Ok(n) => tracing::info!(purged = n, "retention: deleted old uploads"),
            Err(e) => tracing::warn!(error = %e, "retention sweep failed"),
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_secs(3600)) => {}
            _ = stop.changed() => return,
        }
    }
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
