//! One error type for the whole HTTP surface, rendered as RFC 9457 `application/problem+json` with a
//! stable machine `code`. [`CODES`] is the single table from code to HTTP status; failed jobs carry
//! the same object.

use crate::bundle::BundleError;
use crate::store::StoreError;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};

pub const PROBLEM_JSON: &str = "application/problem+json";

/// code → HTTP status. Every problem this service emits has its code here.
pub const CODES: &[(&str, u16, &str)] = &[
    // Request shape.
    ("bad_request", 400, "Bad request"),
    ("invalid_json", 400, "Invalid JSON"),
    ("invalid_multipart", 400, "Invalid multipart body"),
    ("invalid_query", 400, "Invalid query parameter"),
    ("invalid_header", 400, "Invalid header"),
    ("invalid_id", 404, "No such inspection"),
    ("route_not_found", 404, "No such route"),
    ("not_found", 404, "Not found"),
    ("method_not_allowed", 405, "Method not allowed"),
    ("not_acceptable", 406, "Not acceptable"),
    ("request_timeout", 408, "Request timeout"),
    ("body_too_large", 413, "Body too large"),
    ("unsupported_media_type", 415, "Unsupported media type"),
    ("invalid_option", 422, "Invalid option"),
    ("invalid_cmm", 422, "Invalid CMM measurements"),
    ("idempotency_key_reused", 422, "Idempotency-Key reused"),
    ("inspection_not_succeeded", 409, "Inspection has no results"),
    ("inspection_finished", 409, "Inspection already finished"),
    ("cmm_not_found", 404, "No CMM measurements"),
    ("unknown_designation", 404, "Unknown connection designation"),
    // Bundle validation (codes from the bundle reader).
    ("unsupported_format_version", 422, "Unsupported bundle format"),
    ("invalid_manifest", 422, "Invalid manifest"),
    ("invalid_optics", 422, "Invalid optics"),
    ("unknown_connection", 422, "Unknown connection"),
    ("invalid_thread", 422, "Invalid thread"),
    ("too_few_frames", 422, "Too few frames"),
    ("invalid_offsets", 422, "Invalid focus offsets"),
    ("missing_file", 422, "Missing file"),
    ("unreadable_frame", 422, "Unreadable frame"),
    ("inconsistent_frames", 422, "Inconsistent frames"),
    ("unsafe_path", 422, "Unsafe path"),
    ("bundle_too_large", 413, "Bundle too large"),
    ("inspection_too_large", 422, "Inspection too large"),
    ("invalid_archive", 422, "Invalid archive"),
    // Job failures (in a failed inspection's `error`).
    ("no_depth", 422, "No depth recovered"),
    ("no_thread", 422, "No thread found"),
    ("mesh_failed", 422, "Mesh failed"),
    ("pipeline_panic", 500, "Pipeline crashed"),
    ("attempts_exhausted", 500, "Attempts exhausted"),
    ("upload_missing", 500, "Upload missing"),
    // Server side.
    ("io_error", 500, "I/O error"),
    ("internal_error", 500, "Internal error"),
    ("not_ready", 503, "Not ready"),
];

pub fn status_of(code: &str) -> u16 {
    CODES.iter().find(|c| c.0 == code).map_or(500, |c| c.1)
}

fn title_of(code: &str) -> &'static str {
    CODES.iter().find(|c| c.0 == code).map_or("Error", |c| c.2)
}

pub fn type_uri(code: &str) -> String {
    format!("tag:crestscan,2026:problem/{code}")
}

/// The RFC 9457 problem object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Problem {
    /// `tag:crestscan,2026:problem/{code}`.
    #[serde(rename = "type")]
    pub type_: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    /// Stable machine code; see the `code` table in the README.
    pub code: String,
    /// The request path (for HTTP errors).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// The field, file or parameter at fault, when one is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub culprit: Option<String>,
}

#[derive(Debug, Clone)]
pub struct ApiError {
    pub code: &'static str,
    pub detail: String,
    pub culprit: Option<String>,
}

impl ApiError {
    pub fn new(code: &'static str, detail: impl Into<String>) -> Self {
        debug_assert!(CODES.iter().any(|c| c.0 == code), "{code} missing from CODES");
        Self { code, detail: detail.into(), culprit: None }
    }

    pub fn with_culprit(mut self, culprit: impl Into<String>) -> Self {
        self.culprit = Some(culprit.into());
        self
    }

    pub fn status(&self) -> StatusCode {
        StatusCode::from_u16(status_of(self.code)).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR)
    }

    pub fn problem(&self, instance: Option<String>) -> Problem {
        Problem {
            type_: type_uri(self.code),
            title: title_of(self.code).into(),
            status: status_of(self.code),
            detail: self.detail.clone(),
            code: self.code.into(),
            instance,
            culprit: self.culprit.clone(),
        }
    }

    pub fn internal(e: impl std::fmt::Display) -> Self {
        tracing::error!(error = %e, "internal error");
        Self::new("internal_error", e.to_string())
    }

    pub fn not_found(id: &str) -> Self {
        Self::new("invalid_id", format!("no inspection {id}")).with_culprit("id")
    }
}

impl From<BundleError> for ApiError {
    fn from(e: BundleError) -> Self {
        let culprit = match &e {
            BundleError::FormatVersion { .. } => Some("manifest.json: format".to_string()),
            BundleError::Manifest { field, .. }
            | BundleError::TooFewFrames { field, .. }
            | BundleError::Offsets { field, .. } => Some(format!("manifest.json: {field}")),
            BundleError::Optics { field, .. } => Some(format!("manifest.json: optics.{field}")),
            BundleError::Thread { field, .. } => Some(format!("manifest.json: part.thread.{field}")),
            BundleError::InspectionTooLarge { field, .. } => Some(format!("manifest.json: {field}")),
            BundleError::UnknownConnection { .. } => Some("manifest.json: part.connection".into()),
            BundleError::MissingFile { path }
            | BundleError::UnreadableFrame { path, .. }
            | BundleError::InconsistentFrames { path, .. }
            | BundleError::UnsafePath { path, .. } => Some(path.clone()),
            BundleError::Limit { .. } | BundleError::Archive { .. } => None,
            // The server's own file; not the client's business.
            BundleError::Io { .. } => return Self::internal(e),
        };
        Self { code: e.code(), detail: e.to_string(), culprit }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::NotFound => Self::new("not_found", "not found"),
            StoreError::IdempotencyConflict { .. } => {
                Self::new("idempotency_key_reused", e.to_string()).with_culprit("Idempotency-Key")
            }
            other => Self::internal(other),
        }
    }
}

/// The request path, stashed by the middleware so errors can name their `instance`.
#[derive(Clone)]
pub struct RequestPath(pub String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        let mut response =
            (status, serde_json::to_vec(&self.problem(None)).expect("problem serialises")).into_response();
        response.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        // Lets the middleware fill `instance` without re-parsing.
        response.extensions_mut().insert(self);
        response
    }
}

/// Codes for responses the framework produced by itself (no ApiError attached).
pub fn code_for_status(status: StatusCode) -> &'static str {
    match status.as_u16() {
        400 => "bad_request",
        404 => "route_not_found",
        405 => "method_not_allowed",
        406 => "not_acceptable",
        408 => "request_timeout",
        413 => "body_too_large",
        415 => "unsupported_media_type",
        422 => "invalid_json",
        503 => "not_ready",
        _ => "internal_error",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_is_unique_and_every_bundle_code_is_in_the_table() {
        let mut codes: Vec<&str> = CODES.iter().map(|c| c.0).collect();
        codes.sort();
        let n = codes.len();
        codes.dedup();
        assert_eq!(codes.len(), n, "duplicate code");
        for e in [
            BundleError::FormatVersion { found: "x".into() },
            BundleError::Limit { message: "x".into() },
            BundleError::InspectionTooLarge { field: "views".into(), message: "x".into() },
            BundleError::Archive { message: "x".into() },
            BundleError::MissingFile { path: "views/0/a.png".into() },
        ] {
            let api = ApiError::from(e.clone());
            assert_eq!(api.code, e.code());
            assert!(api.status().is_client_error(), "{}", api.code);
        }
        assert_eq!(ApiError::from(BundleError::MissingFile { path: "a.png".into() }).culprit.as_deref(), Some("a.png"));
    }

    #[test]
    fn every_code_is_documented_in_the_readme_under_its_status() {
        let readme = include_str!("../../README.md");
        let errors = &readme[readme.find("### Errors").expect("README has an Errors section")..];
        for (code, status, _) in CODES {
            let row = errors
                .lines()
                .find(|l| l.contains(&format!("`{code}`")))
                .unwrap_or_else(|| panic!("{code} is not in the README's error table"));
            assert!(row.contains(&status.to_string()), "{code} listed under the wrong status: {row}");
        }
    }
}
