//! `GET /v1/inspections/{id}/events`: the inspection's changes as server-sent events, and what
//! a waiter (this stream, the long-poll of `get`) counts as news.

use super::common::{AppState, InspectionId};
use super::problem::{ApiError, Problem};
use crate::service::store::{InspectionRow, Status};
use crate::service::wire::Inspection;
use axum::extract::{Path, State};
use axum::response::{IntoResponse, Response};

/// How often a waiter (a long-poll, a stream between changes) re-reads its inspection.
pub(super) const WAIT_POLL: std::time::Duration = std::time::Duration::from_millis(200);

/// What a waiter watches of an inspection (the long-poll, the event stream): its status and
/// progress stage; a change of either is news.
pub(super) fn watched(row: &InspectionRow) -> (String, Option<String>) {
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
pub(super) fn finished(row: &InspectionRow) -> bool {
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
