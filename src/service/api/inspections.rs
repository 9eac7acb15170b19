//! `/v1/inspections`: the router, get (with a long-poll) and cancel. Submitting is
//! [`super::submit`], the list [`super::list`], the event stream [`super::events`].

use super::common::{AppState, InspectionId};
use super::problem::{ApiError, Problem};
use crate::problem::Code;
use crate::service::store::Status;
pub use crate::service::wire::{BundleSummary, Inspection, Links, Progress};
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use utoipa::IntoParams;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::events::{__path_inspection_events, WAIT_POLL, finished, inspection_events, watched};
use super::list::{__path_list_inspections, list_inspections};
use super::submit::{__path_create_inspection, create_inspection};
pub use super::submit::{BundleForm, SubmitOptions};

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_inspection, list_inspections))
        .routes(routes!(get_inspection))
        .routes(routes!(inspection_events))
        .routes(routes!(cancel_inspection))
}

/// Get an inspection: status, progress, timestamps, verdict, and the error if it failed.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}",
    operation_id = "get_inspection",
    tag = "inspections",
    params(("id" = uuid::Uuid, Path, description = "Inspection id"), WaitQuery),
    responses(
        (status = 200, description = "The inspection", body = Inspection),
        (status = 400, description = "Malformed wait", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_inspection(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<WaitQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<super::common::Rounded<Inspection>, ApiError> {
    let Query(q) = query?;
    let wait = q.wait.as_deref().map(parse_wait).transpose()?.unwrap_or_default();
    let id = InspectionId::parse(&id)?;
    let fetch =
        || async { state.store.inspection(&id.0).await.map_err(|e| super::common::missing_inspection(e, &id.0)) };
    // Subscribed before the first read, so no change after it is missed.
    let mut changes = state.store.changes.subscribe();
    let mut row = fetch().await?;
    // Long-poll: woken by the change feed (this process's writes; every process's under
    // PostgreSQL, by NOTIFY), and re-reading the row every WAIT_POLL besides, for a worker in
    // another process on a shared SQLite file.
    let seen = watched(&row);
    let deadline = tokio::time::Instant::now() + wait;
    let mut stopping = state.stopping.clone();
    let mut poll = tokio::time::interval_at(tokio::time::Instant::now() + WAIT_POLL, WAIT_POLL);
    while !finished(&row) && tokio::time::Instant::now() < deadline && !*stopping.borrow() {
        tokio::select! {
            _ = poll.tick() => {}
            _ = tokio::time::sleep_until(deadline) => {}
            _ = stopping.changed() => {}
            change = changes.recv() => match change {
                Ok(changed) if changed.id != id.0 => continue,
                _ => {}
            },
        }
        row = fetch().await?;
        if watched(&row) != seen {
            break;
        }
    }
    Ok(super::common::Rounded(row.into()))
}

/// The longest a long-poll is held; a longer `wait` is cut to it.
pub const MAX_WAIT: std::time::Duration = std::time::Duration::from_secs(60);

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct WaitQuery {
    /// Long-poll: answer as soon as the status or the progress stage changes (at once if the
    /// inspection is finished), or when this much time has passed: `30s`, `500ms`, or seconds
    /// (`30`). At most 60 s; a longer wait is cut to 60 s.
    #[param(pattern = r"^[0-9]{1,6}(ms|s)?$")]
    pub wait: Option<String>,
}

fn parse_wait(text: &str) -> Result<std::time::Duration, ApiError> {
    let (digits, unit_ms) = match text.strip_suffix("ms") {
        Some(d) => (d, 1u64),
        None => (text.strip_suffix('s').unwrap_or(text), 1000u64),
    };
    let bad = || {
        ApiError::new(Code::InvalidQuery, format!("wait: {text:?} is not a duration like 30s, 500ms or 30"))
            .with_culprit("wait")
    };
    if digits.is_empty() || digits.len() > 6 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return Err(bad());
    }
    let ms = digits.parse::<u64>().map_err(|_| bad())?.saturating_mul(unit_ms);
    Ok(std::time::Duration::from_millis(ms).min(MAX_WAIT))
}

/// Cancel an inspection: a queued one at once (200), a running one at its next heartbeat (202).
#[utoipa::path(
    post,
    path = "/v1/inspections/{id}/cancel",
    operation_id = "cancel_inspection",
    tag = "inspections",
    params(("id" = uuid::Uuid, Path, description = "Inspection id")),
    responses(
        (status = 200, description = "Canceled", body = Inspection),
        (status = 202, description = "Cancel requested; the worker stops at its next heartbeat", body = Inspection),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Already succeeded or failed", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn cancel_inspection(State(state): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    let id = InspectionId::parse(&id)?;
    let before = state.store.inspection(&id.0).await.map_err(|e| super::common::missing_inspection(e, &id.0))?;
    if matches!(before.status(), Status::Succeeded | Status::Failed) {
        return Err(ApiError::new(Code::InspectionFinished, format!("inspection {} already {}", id.0, before.status)));
    }
    let row = state.store.request_cancel(&id.0).await?;
    let code = if row.status() == Status::Canceled { StatusCode::OK } else { StatusCode::ACCEPTED };
    Ok((code, super::common::Rounded(Inspection::from(row))).into_response())
}
