//! The dashboard at `/` (issue 30): recent inspections with the list's filters, a link to each
//! report page, and a form that uploads a bundle and follows it to its end. One page, its style and
//! script inline, using the public API as any client does.

use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use std::sync::OnceLock;

const PAGE: &str = include_str!("dashboard/page.html");
const SCRIPT: &str = include_str!("dashboard/dashboard.js");

/// The page with its script in place, and the policy that allows that script by its hash and the
/// page's requests to its own origin only.
fn page() -> &'static (String, HeaderValue) {
    static PAGE_AND_POLICY: OnceLock<(String, HeaderValue)> = OnceLock::new();
    PAGE_AND_POLICY.get_or_init(|| {
        let policy = format!(
            "default-src 'none'; style-src 'unsafe-inline'; script-src {}; connect-src 'self'; \
             frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
            crate::export::html::script_hash(SCRIPT)
        );
        (PAGE.replace("/*SCRIPT*/", SCRIPT), HeaderValue::from_str(&policy).expect("ASCII"))
    })
}

pub async fn dashboard() -> Response {
    let (html, policy) = page();
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("text/html; charset=utf-8")),
            (header::CONTENT_SECURITY_POLICY, policy.clone()),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        html.as_str(),
    )
        .into_response()
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_script_is_in_the_page_once_and_allowed_by_its_hash() {
        let (html, policy) = super::page();
        assert_eq!(html.matches(super::SCRIPT).count(), 1);
        assert!(!html.contains("/*SCRIPT*/"));
        let policy = policy.to_str().unwrap();
        let script_src = policy.split(';').map(str::trim).find(|d| d.starts_with("script-src")).unwrap();
        assert!(script_src.starts_with("script-src 'sha256-") && !script_src.contains("unsafe"), "{policy}");
        assert!(!policy.contains("http"));
    }
}
