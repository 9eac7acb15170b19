//! Liveness, readiness and metrics.

use super::common::AppState;
use super::problem::{ApiError, Problem};
use crate::problem::Code;
use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(healthz)).routes(routes!(readyz)).routes(routes!(metrics))
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Health {
    pub status: String,
    pub version: String,
}

/// Liveness: the process answers.
#[utoipa::path(get, path = "/healthz", operation_id = "healthz", tag = "operations",
    responses((status = 200, description = "Alive", body = Health)))]
pub async fn healthz() -> Json<Health> {
    Json(Health { status: "ok".into(), version: env!("CARGO_PKG_VERSION").into() })
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Readiness {
    pub status: String,
    pub database: String,
    pub disk: String,
    /// Free space on the data directory's file system, and the floor kept (`min_free_disk_mb`),
    /// MiB.
    pub disk_free_mb: u64,
    pub disk_floor_mb: u64,
    pub queued: i64,
    pub running: i64,
    /// This process's role: `all`, `api` or `worker`.
    pub role: String,
    /// Where uploaded bundles are kept: `local <dir>` or `s3://bucket/prefix`.
    pub blobs: String,
    /// Where the records are kept: `sqlite:<file>` or `postgres://user:***@host:port/database`.
    pub records: String,
}

/// Readiness: the database answers and commits a write, the data directory takes writes and has
/// more free space than its floor; reports the free space and the queue depth.
#[utoipa::path(get, path = "/readyz", operation_id = "readyz", tag = "operations",
    responses(
        (status = 200, description = "Ready", body = Readiness),
        (status = 503, description = "Not ready (database unreachable or not taking writes, disk not writable, or free space under the floor)", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn readyz(State(state): State<AppState>) -> Result<Json<Readiness>, ApiError> {
    // A database that reads but cannot write (disk full, write lock held) is not ready.
    state.store.database_ready().await.map_err(|reason| ApiError::new(Code::NotReady, reason))?;
    let files = state.store.files.clone();
    let (room, free) = tokio::task::spawn_blocking(move || {
        files.check_writable()?;
        files.has_room(0)
    })
    .await
    .map_err(ApiError::internal)?
    .map_err(|e| ApiError::new(Code::NotReady, format!("data directory not writable: {e}")))?;
    match tokio::time::timeout(std::time::Duration::from_secs(5), state.store.blobs.check()).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => {
            return Err(ApiError::new(
                Code::NotReady,
                format!("blob store {} does not take writes: {e}", state.store.blobs.describe()),
            ));
        }
        Err(_) => {
            return Err(ApiError::new(
                Code::NotReady,
                format!("blob store {} does not take writes: no answer within 5 s", state.store.blobs.describe()),
            ));
        }
    }
    let floor_mb = state.store.files.free_floor_bytes() >> 20;
    if !room {
        return Err(ApiError::new(
            Code::NotReady,
            format!("disk: {} MiB free, under the {floor_mb} MiB floor (min_free_disk_mb)", free >> 20),
        ));
    }
    let (queued, running) = state.store.queue_depth().await?;
    Ok(Json(Readiness {
        status: "ready".into(),
        database: "ok".into(),
        disk: "ok".into(),
        disk_free_mb: free >> 20,
        disk_floor_mb: floor_mb,
        queued,
        running,
        role: state.settings.role.as_str().into(),
        blobs: state.store.blobs.describe(),
        records: state.store.database.describe(),
    }))
}

/// Prometheus metrics (text exposition format).
#[utoipa::path(get, path = "/metrics", operation_id = "metrics", tag = "operations",
    responses((status = 200, description = "Prometheus text format", body = String, content_type = "application/openmetrics-text; version=1.0.0; charset=utf-8")))]
pub async fn metrics(State(state): State<AppState>) -> Result<Response, ApiError> {
    let (queued, running) = state.store.queue_depth().await?;
    state.metrics.set_queue(queued, running);
    let mut response = state.metrics.render().into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/openmetrics-text; version=1.0.0; charset=utf-8"),
    );
    Ok(response)
}
