//! Browsers cannot be turned against the service (issue 29): a page the operator opens must not
//! reach it by DNS rebinding (the `Host` check), change anything by a cross-site form or fetch
//! (the `Origin` check on state-changing requests), frame it or sniff its answers (the security
//! headers on every answer). Cross-origin reads need CORS, and crestscan sends none unless
//! `allowed_origins` names the origin.

use super::common::AppState;
use super::problem::ApiError;
use crate::problem::Code;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

fn changes_state(method: &Method) -> bool {
    !matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS | Method::TRACE)
}

/// Checks `Host` on every request and `Origin` on state-changing ones (or, from a browser that
/// sent no `Origin`, `Sec-Fetch-Site: cross-site`); adds the security headers to every answer.
pub async fn guard(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let policy = &state.browser;
    let headers = request.headers();
    // A Host that is not text names nothing here: refused like a foreign name.
    let host = headers.get(header::HOST).map(|v| v.to_str().unwrap_or("(not text)").to_string());
    if let Some(h) = host.as_deref()
        && !policy.host_allowed(h)
    {
        let detail = format!(
            "Host {h:?} does not name this service: IP addresses and localhost are taken, other names must be \
             listed in allowed_hosts"
        );
        return refuse(request, ApiError::new(Code::HostNotAllowed, detail).with_culprit("Host")).await;
    }
    if changes_state(request.method()) {
        let origin = headers.get(header::ORIGIN).map(|v| v.to_str().unwrap_or("null").to_string());
        let cross_site = headers.get("sec-fetch-site").is_some_and(|v| v.as_bytes() == b"cross-site");
        let refused = match origin.as_deref() {
            Some(o) => !policy.origin_allowed(o, host.as_deref()),
            None => cross_site,
        };
        if refused {
            let detail = format!(
                "a {} from origin {} may not change anything here: only the service's own origin and those in \
                 allowed_origins may",
                request.method(),
                origin.as_deref().unwrap_or("(cross-site, none sent)")
            );
            return refuse(request, ApiError::new(Code::OriginNotAllowed, detail).with_culprit("Origin")).await;
        }
    }
    let path = request.uri().path().to_string();
    secured(next.run(request).await, &path)
}

/// Answers `error` as [`super::common::refuse`] does, with the security headers (this guard adds them to
/// every other answer on its way out).
async fn refuse(request: Request, error: ApiError) -> Response {
    secured(super::common::refuse(request, error.into_response()).await, "")
}

/// The API browser (Swagger UI) runs its own scripts and styles, some inline; every other answer
/// is data and may load nothing.
const DOCS_CSP: &str = "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; \
                        img-src 'self' data:; frame-ancestors 'none'; base-uri 'none'; form-action 'self'";
const DATA_CSP: &str = "default-src 'none'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'";

fn secured(mut response: Response, path: &str) -> Response {
    let csp = if path == "/docs" || path.starts_with("/docs/") { DOCS_CSP } else { DATA_CSP };
    let headers: &mut HeaderMap = response.headers_mut();
    for (name, value) in [
        (header::CONTENT_SECURITY_POLICY, csp),
        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        (header::X_FRAME_OPTIONS, "DENY"),
        (header::REFERRER_POLICY, "no-referrer"),
        (header::HeaderName::from_static("cross-origin-resource-policy"), "same-origin"),
    ] {
        headers.entry(name).or_insert(HeaderValue::from_static(value));
    }
    response
}
