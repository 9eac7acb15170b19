//! What the API's handlers share: the application state, the inspection id, answers rounded to
//! their resolution, schema helpers, and the checks that an inspection exists and has results. The
//! routers (`mod.rs`) import the handlers, and the handlers import this, never the routers.

use super::ingest;
use super::limiter::SubmissionLimiter;
use super::origins::BrowserPolicy;
use super::problem::ApiError;
use crate::domain::thread::ConnectionTable;
use crate::problem::Code;
use crate::service::config::Settings;
use crate::service::store::{Status, Store};
use crate::service::telemetry::Metrics;
use axum::extract::Request;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use std::sync::Arc;
use tokio::sync::Notify;

#[derive(Clone)]
pub struct AppState {
    pub store: Store,
    pub table: Arc<ConnectionTable>,
    pub metrics: Arc<Metrics>,
    pub settings: Arc<Settings>,
    /// Wakes idle workers when an inspection is queued.
    pub wake: Arc<Notify>,
    /// Uploads received at once.
    pub uploads: Arc<ingest::UploadGate>,
    /// The hosts and origins browsers may reach the service by.
    pub browser: Arc<BrowserPolicy>,
    /// The learned models: shipped, and installed in `<data_dir>/models`.
    pub models: Arc<crate::learned::Models>,
    /// Turns true when the service is stopping: long-polls and event streams end then, so that
    /// the drain does not wait on them.
    pub stopping: tokio::sync::watch::Receiver<bool>,
    /// Submissions per API key in the last minute.
    pub submissions: Arc<SubmissionLimiter>,
}

/// An inspection id: a UUID, rendered in its canonical lowercase form.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct InspectionId(pub String);

impl InspectionId {
    pub fn parse(s: &str) -> Result<Self, ApiError> {
        // Only the hyphenated form the ids are written in (the document's `format: uuid`);
        // uuid also reads braced, URN and unhyphenated forms.
        Some(s)
            .filter(|s| s.len() == 36)
            .and_then(|s| uuid::Uuid::parse_str(s).ok())
            .map(|u| Self(u.to_string()))
            .ok_or(())
            .map_err(|_| ApiError::new(Code::InvalidId, format!("{s:?} is not an inspection id")).with_culprit("id"))
    }
}

/// 404 for an unknown inspection; any other store failure stays a 500.
pub fn missing_inspection(e: crate::service::store::StoreError, id: &str) -> ApiError {
    match e {
        crate::service::store::StoreError::NotFound => ApiError::not_found(id),
        other => other.into(),
    }
}

/// A page's `limit` parameter: `default` when absent, else within 1 to `max` (400 `invalid_query`).
pub fn page_limit(limit: Option<i64>, default: i64, max: i64) -> Result<i64, ApiError> {
    let limit = limit.unwrap_or(default);
    if !(1..=max).contains(&limit) {
        return Err(
            ApiError::new(Code::InvalidQuery, format!("limit: {limit} is not within 1–{max}")).with_culprit("limit")
        );
    }
    Ok(limit)
}

/// A JSON answer whose numbers are rounded to their resolution ([`crate::export::json`]).
pub struct Rounded<T>(pub T);

impl<T: serde::Serialize> IntoResponse for Rounded<T> {
    fn into_response(self) -> Response {
        match crate::export::json::to_vec(&self.0) {
            Ok(body) => ([(header::CONTENT_TYPE, HeaderValue::from_static("application/json"))], body).into_response(),
            Err(e) => ApiError::internal(e).into_response(),
        }
    }
}

/// A string parameter's schema: exactly one of `values` (what the server takes, case and all).
/// The description lives here because `schema_with` replaces the field's doc comment.
pub fn one_of<'a>(values: impl IntoIterator<Item = &'a str>, description: &str) -> utoipa::openapi::schema::Object {
    use utoipa::openapi::schema::{ObjectBuilder, Type};
    ObjectBuilder::new().schema_type(Type::String).enum_values(Some(values)).description(Some(description)).build()
}

/// Raw bytes (a bundle archive, a mesh, a PNG) in the OpenAPI document.
pub struct Binary;

impl utoipa::PartialSchema for Binary {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        use utoipa::openapi::schema::{KnownFormat, ObjectBuilder, SchemaFormat, Type};
        ObjectBuilder::new()
            .schema_type(Type::String)
            .format(Some(SchemaFormat::KnownFormat(KnownFormat::Binary)))
            .into()
    }
}

impl utoipa::ToSchema for Binary {}
/// Answers a request refused before its handler once its body is read (for a bounded time, as
/// the upload's own refusals do), so that a client still sending an upload gets the answer, not a
/// broken pipe.
pub async fn refuse(request: Request, response: Response) -> Response {
    ingest::drain(request.into_body()).await;
    response
}

/// 404 for an unknown id, 409 while it has no results.
pub async fn succeeded(state: &AppState, id: &str) -> Result<InspectionId, ApiError> {
    let id = InspectionId::parse(id)?;
    let row = state.store.inspection(&id.0).await.map_err(|e| missing_inspection(e, &id.0))?;
    if row.status() != Status::Succeeded {
        return Err(ApiError::new(
            Code::InspectionNotSucceeded,
            format!("inspection {} is {}; results exist once it succeeded", id.0, row.status),
        ));
    }
    Ok(id)
}

/// A stored mesh or image, or 410 when the retention deleted it.
pub async fn stored_artifact(
    state: &AppState,
    id: &str,
    kind: &str,
) -> Result<crate::service::store::StoredArtifact, ApiError> {
    match state.store.artifact(id, kind).await {
        Err(crate::service::store::StoreError::NotFound) => match state.store.artifacts_purged_at(id).await? {
            Some(at) => Err(ApiError::new(
                Code::ResultExpired,
                format!(
                    "the {kind} of this inspection was deleted on {} (artifact_retention_days); its report and thread \
                     table are kept",
                    crate::service::wire::rfc3339(at)
                ),
            )),
            None => Err(ApiError::not_found(id)),
        },
        other => Ok(other?),
    }
}

/// A body in the CMM formats: JSON or CSV.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JsonOrCsv {
    Json,
    Csv,
}

/// The body's media type by its `Content-Type`, lowercase, parameters dropped ("" without one).
pub fn media_type(headers: &axum::http::HeaderMap) -> String {
    let content_type = headers.get(axum::http::header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    content_type.split(';').next().unwrap_or("").trim().to_ascii_lowercase()
}

/// The body's format by its `Content-Type` (parameters ignored), or 415 naming the header.
pub fn json_or_csv(headers: &axum::http::HeaderMap) -> Result<JsonOrCsv, ApiError> {
    match media_type(headers).as_str() {
        "application/json" => Ok(JsonOrCsv::Json),
        "text/csv" => Ok(JsonOrCsv::Csv),
        other => Err(ApiError::new(
            Code::UnsupportedMediaType,
            format!("Content-Type {other:?}: send application/json or text/csv"),
        )
        .with_culprit("Content-Type")),
    }
}
