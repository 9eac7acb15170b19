//! `/v1/inspections`: the router, and list with filters and a cursor, get (with a long-poll), the
//! event stream, cancel. Submitting is [`super::submit`].

use super::common::{AppState, InspectionId};
use super::problem::{ApiError, Problem};
use crate::domain::rules::Verdict;
use crate::problem::Code;
use crate::service::store::{InspectionRow, ListFilter, Status};
use crate::service::wire::parse_rfc3339;
pub use crate::service::wire::{BundleSummary, Inspection, Links, Progress};
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::submit::{__path_create_inspection, create_inspection};
pub use super::submit::{BundleForm, SubmitOptions};

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_inspection, list_inspections))
        .routes(routes!(get_inspection))
        .routes(routes!(inspection_events))
        .routes(routes!(cancel_inspection))
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    #[param(schema_with = status_values)]
    pub status: Option<String>,
    #[param(schema_with = verdict_values)]
    pub verdict: Option<String>,
    #[param(schema_with = boolean_values)]
    pub review_required: Option<String>,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    /// RFC 3339; only inspections created after it.
    #[param(value_type = Option<String>, format = DateTime)]
    pub created_after: Option<String>,
    /// RFC 3339; only inspections created before it.
    #[param(value_type = Option<String>, format = DateTime)]
    pub created_before: Option<String>,
    /// RFC 3339; only inspections that finished (succeeded, failed, canceled) after it: an MES
    /// asks for what finished since its last look.
    #[param(value_type = Option<String>, format = DateTime)]
    pub finished_after: Option<String>,
    /// Page size, 1–200 (default 50).
    #[param(minimum = 1, maximum = 200)]
    pub limit: Option<u32>,
    /// `next_cursor` of the previous page.
    #[param(value_type = Option<uuid::Uuid>)]
    pub cursor: Option<String>,
}

fn status_values() -> utoipa::openapi::schema::Object {
    super::common::one_of(Status::ALL.map(Status::as_str), "Only inspections in this status.")
}
fn verdict_values() -> utoipa::openapi::schema::Object {
    super::common::one_of(Verdict::ALL.map(Verdict::as_str), "Only inspections with this verdict.")
}
fn boolean_values() -> utoipa::openapi::schema::Object {
    super::common::one_of(
        ["true", "false"],
        "Only succeeded inspections whose result does (true) or does not (false) need review.",
    )
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct InspectionPage {
    /// Newest first.
    pub items: Vec<Inspection>,
    /// Pass as `cursor` for the next page; absent on the last page.
    pub next_cursor: Option<String>,
}

/// List inspections, newest first, with filters and cursor pagination.
#[utoipa::path(
    get,
    path = "/v1/inspections",
    operation_id = "list_inspections",
    tag = "inspections",
    params(ListQuery),
    responses(
        (status = 200, description = "A page of inspections: at most `limit` of them, and fewer where their JSON would pass about 1 MiB (`next_cursor` then continues)", body = InspectionPage),
        (status = 400, description = "Invalid filter or cursor", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn list_inspections(
    State(state): State<AppState>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<super::common::Rounded<InspectionPage>, ApiError> {
    let Query(q) = query?;
    let invalid = |field: &str, message: String| {
        ApiError::new(Code::InvalidQuery, format!("{field}: {message}")).with_culprit(field)
    };
    let status = q.status.as_deref().map(str::parse::<Status>).transpose().map_err(|e| invalid("status", e))?;
    if let Some(v) = q.verdict.as_deref()
        && !Verdict::ALL.iter().any(|known| known.as_str() == v)
    {
        return Err(invalid("verdict", format!("{v:?} is neither accept nor reject")));
    }
    let review_required = match q.review_required.as_deref() {
        None => None,
        Some("true") => Some(true),
        Some("false") => Some(false),
        Some(v) => return Err(invalid("review_required", format!("{v:?} is neither true nor false"))),
    };
    let time = |field: &str, v: &Option<String>| {
        v.as_deref().map(|t| parse_rfc3339(t).map_err(|e| invalid(field, e))).transpose()
    };
    let limit = q.limit.unwrap_or(50);
    if !(1..=200).contains(&limit) {
        return Err(invalid("limit", format!("{limit} is outside 1–200")));
    }
    let before_id = match q.cursor.as_deref() {
        Some(c) => Some(InspectionId::parse(c).map_err(|_| invalid("cursor", "not a cursor from this list".into()))?.0),
        None => None,
    };
    let filter = ListFilter {
        status,
        verdict: q.verdict,
        review_required,
        serial: q.serial,
        connection: q.connection,
        client_reference: q.client_reference,
        created_after_ms: time("created_after", &q.created_after)?,
        created_before_ms: time("created_before", &q.created_before)?,
        finished_after_ms: time("finished_after", &q.finished_after)?,
        before_id,
        limit: limit + 1,
    };
    let mut rows = state.store.list(&filter).await?;
    let more = rows.len() > limit as usize;
    rows.truncate(limit as usize);
    let (items, cut) = within_page_bytes(rows.into_iter().map(Inspection::from), PAGE_BYTES);
    let next_cursor = if more || cut { items.last().map(|i| i.id.clone()) } else { None };
    Ok(super::common::Rounded(InspectionPage { items, next_cursor }))
}

/// About the most a page of the list holds, bytes of JSON: with every text capped a row is a few
/// KiB, but rows stored before the caps may be larger, and one answer must never be hundreds of MiB.
pub const PAGE_BYTES: usize = 1 << 20;

/// The leading items whose JSON together stays within `budget` bytes (always at least one), and
/// whether any were left out for it.
fn within_page_bytes<T: Serialize>(items: impl Iterator<Item = T>, budget: usize) -> (Vec<T>, bool) {
    let mut kept = Vec::new();
    let mut used = 0usize;
    for item in items {
        let size = serde_json::to_vec(&item).map(|b| b.len()).unwrap_or(usize::MAX);
        if !kept.is_empty() && used.saturating_add(size) > budget {
            return (kept, true);
        }
        used = used.saturating_add(size);
        kept.push(item);
    }
    (kept, false)
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
    let mut row = fetch().await?;
    // Long-poll by re-reading the row: the worker may be another process on the same database,
    // so an in-process notification would miss its changes.
    let seen = watched(&row);
    let deadline = tokio::time::Instant::now() + wait;
    let mut stopping = state.stopping.clone();
    while !finished(&row) && tokio::time::Instant::now() < deadline && !*stopping.borrow() {
        tokio::select! {
            _ = tokio::time::sleep(WAIT_POLL.min(deadline - tokio::time::Instant::now())) => {}
            _ = stopping.changed() => {}
        }
        row = fetch().await?;
        if watched(&row) != seen {
            break;
        }
    }
    Ok(super::common::Rounded(row.into()))
}

/// What a waiter watches of an inspection (the long-poll, the event stream): its status and
/// progress stage; a change of either is news.
fn watched(row: &InspectionRow) -> (String, Option<String>) {
    (row.status.clone(), row.progress_stage.clone())
}

/// Whether a row read or received may be shown after one of `read_at`: not an older snapshot (a
/// database read can overtake the feed, and stepping back would reorder the events), except that
/// a terminal row always is: writes wait for SQLite's lock and can land out of their clocks'
/// order, and the stream must end with the final state.
fn newer(row: &InspectionRow, read_at: i64) -> bool {
    row.updated_at >= read_at || finished(row)
}

/// Whether no more news will come: the status is terminal.
fn finished(row: &InspectionRow) -> bool {
    row.status.parse::<Status>().is_ok_and(Status::is_terminal)
}

/// A stream of the inspection's changes (server-sent events, `text/event-stream`): an event
/// `state` with the inspection now, then one at each change of its status or progress stage, in
/// order, with ids counting from 1; after a terminal status (succeeded, failed, canceled) the
/// stream ends. When the service stops it sends `event: shutdown` and ends: reconnect.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/events",
    operation_id = "inspection_events",
    tag = "inspections",
    params(("id" = uuid::Uuid, Path, description = "Inspection id")),
    responses(
        (status = 200, description = "Server-sent events: `event: state`, `data:` the inspection as JSON (the \
            `Inspection` schema), one per change; `event: shutdown` when the service stops",
            body = String, content_type = "text/event-stream"),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn inspection_events(State(state): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    use axum::response::sse::{Event, KeepAlive, Sse};
    let id = InspectionId::parse(&id)?;
    // Subscribed before the first read, so no change after it is missed.
    let changes = state.store.changes.subscribe();
    let first = state.store.inspection(&id.0).await.map_err(|e| super::common::missing_inspection(e, &id.0))?;
    struct Cursor {
        state: AppState,
        changes: tokio::sync::broadcast::Receiver<std::sync::Arc<InspectionRow>>,
        id: String,
        next: Option<InspectionRow>,
        seen: Option<(String, Option<String>)>,
        /// `updated_at` of the newest row taken.
        read_at: i64,
        poll: tokio::time::Interval,
        count: u64,
        done: bool,
    }
    let event = |count: u64, row: InspectionRow| {
        let inspection = Inspection::from(row);
        let json = crate::export::json::to_vec(&inspection).map(|j| String::from_utf8_lossy(&j).into_owned());
        json.map(|data| Event::default().id(count.to_string()).event("state").data(data))
    };
    // Takes every change this process writes from the store's feed, and re-reads the row as the
    // long-poll does (a worker in another process writes only to the database); yields an event
    // at each change. The cursor holds the row read but not yet sent.
    let read_at = first.updated_at;
    let mut poll = tokio::time::interval(WAIT_POLL);
    poll.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let cursor =
        Cursor { state, changes, id: id.0, next: Some(first), seen: None, read_at, poll, count: 0, done: false };
    let stream = futures_util::stream::unfold(cursor, move |mut c| async move {
        if c.done {
            return None;
        }
        loop {
            if let Some(row) = c.next.take() {
                let key = watched(&row);
                if c.seen.as_ref() != Some(&key) {
                    c.seen = Some(key);
                    c.count += 1;
                    c.done = finished(&row);
                    let e = event(c.count, row);
                    return Some((e.map_err(|e| std::io::Error::other(e.to_string())), c));
                }
            }
            let mut stopping = c.state.stopping.clone();
            if *stopping.borrow() {
                c.done = true;
                return Some((Ok(Event::default().event("shutdown").data("the service is stopping")), c));
            }
            tokio::select! {
                change = c.changes.recv() => match change {
                    Ok(row) if row.id == c.id => {
                        if newer(&row, c.read_at) {
                            c.read_at = c.read_at.max(row.updated_at);
                            c.next = Some((*row).clone());
                        }
                        continue;
                    }
                    Ok(_) => continue,
                    // Fell behind the feed: the database says where things are.
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => { c.poll.tick().await; }
                },
                // One interval for the whole stream (not a fresh sleep per message): a busy feed
                // about other inspections cannot put the database read off.
                _ = c.poll.tick() => {}
                _ = stopping.changed() => continue,
            }
            match c.state.store.inspection(&c.id).await {
                Ok(row) if newer(&row, c.read_at) => {
                    c.read_at = c.read_at.max(row.updated_at);
                    c.next = Some(row);
                }
                Ok(_) => {}
                Err(e) => {
                    tracing::warn!(inspection = %c.id, error = %e, "event stream: reading the inspection failed");
                    c.done = true;
                    return Some((Ok(Event::default().event("error").data("reading the inspection failed")), c));
                }
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()).into_response())
}

/// How often a long-poll re-reads its inspection.
const WAIT_POLL: std::time::Duration = std::time::Duration::from_millis(200);
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

#[cfg(test)]
mod page_tests {
    use super::within_page_bytes;

    #[test]
    fn a_page_stops_at_its_byte_budget_but_always_holds_one_item() {
        let items = vec!["a".repeat(400), "b".repeat(400), "c".repeat(400)];
        let (kept, cut) = within_page_bytes(items.clone().into_iter(), 1000);
        assert_eq!((kept.len(), cut), (2, true));
        let (kept, cut) = within_page_bytes(items.clone().into_iter(), 10);
        assert_eq!((kept.len(), cut), (1, true));
        let (kept, cut) = within_page_bytes(items.into_iter(), 1 << 20);
        assert_eq!((kept.len(), cut), (3, false));
    }
}
