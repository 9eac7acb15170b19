//! Browsers cannot be turned against the service (issue 29): a page the operator opens must not
//! reach it by DNS rebinding (the `Host` check), change anything by a cross-site form or fetch
//! (the `Origin` check on state-changing requests), frame it or sniff its answers (the security
//! headers on every answer). Cross-origin reads need CORS, and crestscan sends none unless
//! `allowed_origins` names the origin.

use super::AppState;
use super::problem::ApiError;
use crate::problem::Code;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// The host names (beyond IP literals and `localhost`) and the cross-origin origins a service
/// accepts, from the `allowed_hosts` and `allowed_origins` settings, lowercased.
#[derive(Clone, Debug, Default)]
pub struct BrowserPolicy {
    hosts: Vec<String>,
    origins: Vec<String>,
}

impl BrowserPolicy {
    pub fn new(hosts: &[String], origins: &[String]) -> Self {
        let lower = |v: &[String]| v.iter().map(|s| s.trim().trim_end_matches('/').to_ascii_lowercase()).collect();
        Self { hosts: lower(hosts), origins: lower(origins) }
    }

    /// Whether a `Host` value names this service. An IP literal cannot be rebound (the browser
    /// connected to that address for that origin), nor can `localhost`; any other name must be
    /// listed, since a name is what an attacker's DNS points at 127.0.0.1.
    pub fn host_allowed(&self, host: &str) -> bool {
        let name = host_name(host).to_ascii_lowercase();
        name.parse::<std::net::IpAddr>().is_ok()
            || name == "localhost"
            || self.hosts.iter().any(|h| h == "*" || *h == name)
    }

    /// Whether a request carrying `origin` may change state: the same origin as the `Host` it
    /// was sent to, or a listed one. `null` (sandboxed frames, file: pages) never is. The service
    /// speaks plain HTTP, so the same origin is `http://` and the Host; behind a TLS proxy the
    /// `https://` origin is listed in `allowed_origins`.
    pub fn origin_allowed(&self, origin: &str, host: Option<&str>) -> bool {
        let origin = origin.trim().to_ascii_lowercase();
        if origin == "null" {
            return false;
        }
        let same = origin
            .strip_prefix("http://")
            .is_some_and(|authority| host.is_some_and(|h| h.eq_ignore_ascii_case(authority)));
        same || self.origins.iter().any(|o| *o == origin)
    }
}

/// The host part of a `Host` value: `[::1]:8080` → `::1`, `name:8080` → `name`.
fn host_name(host: &str) -> &str {
    if let Some(rest) = host.strip_prefix('[') {
        return rest.split(']').next().unwrap_or(rest);
    }
    host.rsplit_once(':').filter(|(_, port)| port.bytes().all(|b| b.is_ascii_digit())).map_or(host, |(n, _)| n)
}

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

/// Answers `error` as [`super::refuse`] does, with the security headers (this guard adds them to
/// every other answer on its way out).
async fn refuse(request: Request, error: ApiError) -> Response {
    secured(super::refuse(request, error.into_response()).await, "")
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_are_ip_literals_localhost_or_listed() {
        let none = BrowserPolicy::default();
        for ok in ["127.0.0.1:8080", "127.0.0.1", "[::1]:8080", "localhost:8080", "LOCALHOST", "10.0.0.5:80"] {
            assert!(none.host_allowed(ok), "{ok}");
        }
        for bad in ["evil.example:8080", "evil.example", "127.0.0.1.evil.example", "localhost.evil.example"] {
            assert!(!none.host_allowed(bad), "{bad}");
        }
        let listed = BrowserPolicy::new(&["CrestScan.Plant.Local".into()], &[]);
        assert!(listed.host_allowed("crestscan.plant.local:8080"));
        assert!(!listed.host_allowed("other.plant.local"));
    }

    #[test]
    fn origins_are_the_same_one_or_listed_and_never_null() {
        let policy = BrowserPolicy::new(&[], &["https://mes.plant.local/".into()]);
        assert!(policy.origin_allowed("http://127.0.0.1:8080", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("http://127.0.0.1:9999", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("http://evil.example", Some("127.0.0.1:8080")));
        assert!(policy.origin_allowed("https://mes.plant.local", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("null", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("http://127.0.0.1:8080", None));
        // The service is plain HTTP: an https origin with the same authority is another origin.
        assert!(!policy.origin_allowed("https://127.0.0.1:8080", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("ftp://127.0.0.1:8080", Some("127.0.0.1:8080")));
    }
}
