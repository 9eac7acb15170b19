//! One error type for the whole HTTP surface, rendered as RFC 9457 `application/problem+json`. The
//! codes, their statuses and the problem object live in [`crate::problem`]; this module only
//! renders them (failed jobs carry the same object).

use crate::bundle::BundleError;
pub use crate::problem::Problem;
use crate::problem::{Code, ErrorCode};
use crate::service::store::StoreError;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

pub const PROBLEM_JSON: &str = "application/problem+json";

#[derive(Debug, Clone)]
pub struct ApiError {
    pub code: Code,
    pub detail: String,
    pub culprit: Option<String>,
}

impl ApiError {
    pub fn new(code: Code, detail: impl Into<String>) -> Self {
        Self { code, detail: detail.into(), culprit: None }
    }

    pub fn with_culprit(mut self, culprit: impl Into<String>) -> Self {
        self.culprit = Some(culprit.into());
        self
    }

    pub fn status(&self) -> StatusCode {
        StatusCode::from_u16(self.code.status()).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR)
    }

    pub fn problem(&self, instance: Option<String>) -> Problem {
        Problem { instance, ..Problem::new(self.code, self.detail.clone(), self.culprit.clone()) }
    }

    /// The error as its own type describes it.
    pub fn of(e: &impl ErrorCode) -> Self {
        Self { code: e.code(), detail: e.to_string(), culprit: e.culprit() }
    }

    /// A failure of the server's own: logged in full under a fresh reference, which is all the
    /// client sees (no paths, no library messages).
    pub fn internal(e: impl std::fmt::Display) -> Self {
        let reference = uuid::Uuid::now_v7();
        tracing::error!(error = %e, %reference, "internal error");
        Self::new(
            Code::InternalError,
            format!("the server failed on this request; its log has the cause under reference {reference}"),
        )
    }

    pub fn not_found(id: &str) -> Self {
        Self::new(Code::InvalidId, format!("no inspection {id}")).with_culprit("id")
    }
}

/// A query string that does not parse into its operation's parameters (a repeated or unknown
/// key, a number that is not one).
impl From<axum::extract::rejection::QueryRejection> for ApiError {
    fn from(e: axum::extract::rejection::QueryRejection) -> Self {
        let text = e.body_text();
        let culprit = query_culprit(&text);
        let error = Self::new(Code::InvalidQuery, text);
        match culprit {
            Some(name) => error.with_culprit(name),
            None => error,
        }
    }
}

/// The parameter a query's parse error is about: `arc_rule: unknown variant …` (the path serde
/// gives), or the one quoted in `unknown field `x`` / `duplicate field `x``.
fn query_culprit(text: &str) -> Option<String> {
    let detail = text.split_once(": ").map_or(text, |(_, rest)| rest);
    let is_name = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_');
    if let Some((path, _)) = detail.split_once(": ")
        && is_name(path)
    {
        return Some(path.to_string());
    }
    for marker in ["unknown field `", "duplicate field `"] {
        if let Some(rest) = detail.split(marker).nth(1)
            && let Some((name, _)) = rest.split_once('`')
            && is_name(name)
        {
            return Some(name.to_string());
        }
    }
    None
}

#[cfg(test)]
mod query_culprit_tests {
    #[test]
    fn the_parameter_at_fault_is_read_off_the_parse_error() {
        use super::query_culprit;
        assert_eq!(
            query_culprit("Failed to deserialize query string: arc_rule: unknown variant `x`, expected one of …")
                .as_deref(),
            Some("arc_rule")
        );
        assert_eq!(
            query_culprit("Failed to deserialize query string: duplicate field `format`").as_deref(),
            Some("format")
        );
        assert_eq!(
            query_culprit("Failed to deserialize query string: unknown field `limt`, expected …").as_deref(),
            Some("limt")
        );
        assert_eq!(query_culprit("Failed to deserialize query string: invalid type"), None);
    }
}

impl From<axum::extract::rejection::JsonRejection> for ApiError {
    fn from(r: axum::extract::rejection::JsonRejection) -> Self {
        let code = match r {
            axum::extract::rejection::JsonRejection::MissingJsonContentType(_) => Code::UnsupportedMediaType,
            _ => Code::InvalidJson,
        };
        ApiError::new(code, r.body_text())
    }
}

impl From<BundleError> for ApiError {
    fn from(e: BundleError) -> Self {
        match e.code() {
            // The server's own file; not the client's business.
            Code::IoError => Self::internal(e),
            _ => Self::of(&e),
        }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e.code() {
            // The database's and the file store's own failures are the operator's (logged).
            Code::InternalError => Self::internal(e),
            Code::InsufficientStorage => {
                tracing::warn!(error = %e, "storage full");
                Self::new(Code::InsufficientStorage, "the server's disk is full; retry later")
            }
            _ => Self::of(&e),
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
        // Refusals that pass with time say when to come back.
        let retry_after = match self.code {
            Code::TooManyUploads | Code::ServerBusy => Some("5"),
            Code::InsufficientStorage => Some("60"),
            _ => None,
        };
        if let Some(seconds) = retry_after {
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from_static(seconds));
        }
        // Lets the middleware fill `instance` without re-parsing.
        response.extensions_mut().insert(self);
        response
    }
}

/// Codes for responses the framework produced by itself (no ApiError attached).
pub fn code_for_status(status: StatusCode) -> Code {
    match status.as_u16() {
        400 => Code::BadRequest,
        404 => Code::RouteNotFound,
        405 => Code::MethodNotAllowed,
        406 => Code::NotAcceptable,
        408 => Code::RequestTimeout,
        413 => Code::BodyTooLarge,
        414 => Code::UriTooLong,
        415 => Code::UnsupportedMediaType,
        431 => Code::HeadersTooLarge,
        422 => Code::InvalidJson,
        503 => Code::NotReady,
        _ => Code::InternalError,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bundle_errors_are_client_errors_with_their_own_code_and_culprit() {
        for e in [
            BundleError::FormatVersion { found: "x".into() },
            BundleError::Limit { culprit: None, message: "x".into() },
            BundleError::InspectionTooLarge { field: "views".into(), message: "x".into() },
            BundleError::Archive { message: "x".into() },
            BundleError::MissingFile { path: "views/0/a.png".into() },
        ] {
            let api = ApiError::from(e.clone());
            assert_eq!(api.code, e.code());
            assert!(api.status().is_client_error(), "{}", api.code);
            assert_eq!(api.problem(None).status, e.code().status());
        }
        assert_eq!(ApiError::from(BundleError::MissingFile { path: "a.png".into() }).culprit.as_deref(), Some("a.png"));
        let io = ApiError::from(BundleError::Io { path: "uploads/ab".into(), message: "EIO".into() });
        assert_eq!((io.code, io.culprit), (Code::InternalError, None), "the server's own file is not named");
    }

    #[test]
    fn every_code_is_documented_in_the_service_doc_under_its_status() {
        let doc = include_str!("../../../docs/service.md");
        let errors = &doc[doc.find("## Errors").expect("docs/service.md has an Errors section")..];
        for code in Code::ALL {
            let status = code.status();
            let row = errors
                .lines()
                .find(|l| l.contains(&format!("`{code}`")))
                .unwrap_or_else(|| panic!("{code} is not in docs/service.md's error table"));
            assert!(row.contains(&status.to_string()), "{code} listed under the wrong status: {row}");
        }
    }
}
