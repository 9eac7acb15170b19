//! HTTP representation helpers: immutable results with strong ETags (If-None-Match, 304) and
//! content negotiation by Accept or ?format=.

use super::problem::ApiError;
use crate::problem::Code;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

/// 200 with a strong ETag, or 304 when the client already has it (If-None-Match compares weakly,
/// as RFC 9110 asks). Representations chosen by `Accept` say so in `Vary`.
/// Whether the request's If-None-Match names `etag` (or `*`).
pub(super) fn if_none_match(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').map(|t| t.trim().trim_start_matches("W/")).any(|t| t == etag || t == "*"))
}

pub(super) fn immutable(
    headers: &HeaderMap,
    etag: &str,
    content_type: &str,
    body: impl Into<axum::body::Body>,
) -> Response {
    let matches = if_none_match(headers, etag);
    let etag_value = HeaderValue::from_str(etag).expect("etags are hex");
    let cache = HeaderValue::from_static("private, max-age=31536000, immutable");
    let vary = HeaderValue::from_static("Accept");
    if matches {
        return (
            StatusCode::NOT_MODIFIED,
            [(header::ETAG, etag_value), (header::CACHE_CONTROL, cache), (header::VARY, vary)],
        )
            .into_response();
    }
    (
        StatusCode::OK,
        [
            (header::ETAG, etag_value),
            (header::CONTENT_TYPE, HeaderValue::from_str(content_type).expect("static types")),
            (header::CACHE_CONTROL, cache),
            (header::VARY, vary),
        ],
        body.into(),
    )
        .into_response()
}

/// An `Accept` header's media ranges, lower-cased, most preferred first (RFC 9110 §12.5.1: by
/// weight `q`, 1 when absent; equal weights keep the client's order); ranges with `q=0` are
/// refused and left out, and so is a range whose weight is not a number from 0 to 1.
pub(super) fn media_ranges_by_preference(accept: &str) -> Vec<String> {
    let mut ranges: Vec<(f32, String)> = accept
        .split(',')
        .filter_map(|range| {
            let mut parts = range.split(';');
            let media = parts.next().unwrap_or("").trim().to_ascii_lowercase();
            let mut q = 1f32;
            for p in parts {
                if let Some((name, value)) = p.split_once('=')
                    && name.trim().eq_ignore_ascii_case("q")
                {
                    q = value.trim().parse().ok().filter(|q: &f32| (0.0..=1.0).contains(q))?;
                }
            }
            (q > 0.0).then_some((q, media))
        })
        .collect();
    ranges.sort_by(|a, b| b.0.total_cmp(&a.0)); // stable: ties keep the client's order
    ranges.into_iter().map(|(_, media)| media).collect()
}

/// The representation asked for by `?format=` or `Accept`, among `offered` (format, media type);
/// the first is the default.
pub(super) fn negotiate(
    headers: &HeaderMap,
    format: Option<&str>,
    offered: &[(&'static str, &'static str)],
) -> Result<(&'static str, &'static str), ApiError> {
    if let Some(f) = format {
        return offered.iter().find(|o| o.0 == f).copied().ok_or_else(|| {
            let names: Vec<&str> = offered.iter().map(|o| o.0).collect();
            ApiError::new(Code::NotAcceptable, format!("format {f:?}: offered {}", names.join(", ")))
                .with_culprit("format")
        });
    }
    let accept = headers.get(header::ACCEPT).and_then(|v| v.to_str().ok()).unwrap_or("*/*");
    for wanted in media_ranges_by_preference(accept) {
        if wanted == "*/*" || wanted.is_empty() {
            return Ok(offered[0]);
        }
        if let Some(o) = offered
            .iter()
            .find(|o| o.1 == wanted || wanted.ends_with("/*") && o.1.starts_with(wanted.trim_end_matches('*')))
        {
            return Ok(*o);
        }
    }
    let types: Vec<&str> = offered.iter().map(|o| o.1).collect();
    Err(ApiError::new(Code::NotAcceptable, format!("Accept {accept:?}: offered {}", types.join(", ")))
        .with_culprit("Accept"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn media_ranges_follow_their_weights_and_q_zero_refuses() {
        assert_eq!(media_ranges_by_preference("text/csv;q=0.5, application/json"), ["application/json", "text/csv"]);
        assert_eq!(media_ranges_by_preference("model/stl, text/csv ; q=0 , */*;q=0.1"), ["model/stl", "*/*"]);
        assert_eq!(media_ranges_by_preference("A/B;Q=0.000"), Vec::<String>::new());
        assert_eq!(media_ranges_by_preference("a/b;q=2, c/d;q=x, e/f;level=1"), ["e/f"]);
        assert_eq!(media_ranges_by_preference("a/b, c/d;q=1.0"), ["a/b", "c/d"]);
    }
}
