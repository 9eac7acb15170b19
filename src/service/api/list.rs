//! `GET /v1/inspections`: the list, with filters, a cursor, and pages cut at about a MiB.

use super::common::{AppState, InspectionId};
use super::problem::{ApiError, Problem};
use crate::domain::rules::Verdict;
use crate::problem::Code;
use crate::service::store::{ListFilter, Status};
use crate::service::wire::{Inspection, parse_rfc3339};
use axum::extract::{Query, State};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

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
    /// Only inspections recorded at this station.
    pub station: Option<String>,
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
        station: q.station,
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
