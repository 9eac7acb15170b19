//! Results of a succeeded inspection (report, per-thread table, mesh, images; immutable, with
//! strong ETags) and the CMM comparison.

use super::problem::{ApiError, Problem};
use super::{AppState, Binary, InspectionId, rfc3339};
use crate::eval::cmm::{self, CmmMeasurements, CmmPoint, Comparison};
use crate::pipeline::report::Report;
use crate::problem::Code;
use crate::service::store::{Status, StoreError};
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(get_report))
        .routes(routes!(get_threads))
        .routes(routes!(get_mesh))
        .routes(routes!(get_image))
        .routes(routes!(put_cmm, get_cmm))
        .routes(routes!(get_cmm_comparison))
}

/// 404 for an unknown id, 409 while it has no results.
async fn succeeded(state: &AppState, id: &str) -> Result<InspectionId, ApiError> {
    let id = InspectionId::parse(id)?;
    let row = state.store.inspection(&id.0).await.map_err(|e| super::missing_inspection(e, &id.0))?;
    if row.status() != Status::Succeeded {
        return Err(ApiError::new(
            Code::InspectionNotSucceeded,
            format!("inspection {} is {}; results exist once it succeeded", id.0, row.status),
        ));
    }
    Ok(id)
}

/// 200 with a strong ETag, or 304 when the client already has it (If-None-Match compares weakly,
/// as RFC 9110 asks). Representations chosen by `Accept` say so in `Vary`.
/// Whether the request's If-None-Match names `etag` (or `*`).
fn if_none_match(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').map(|t| t.trim().trim_start_matches("W/")).any(|t| t == etag || t == "*"))
}

fn immutable(headers: &HeaderMap, etag: &str, content_type: &str, body: impl Into<axum::body::Body>) -> Response {
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

/// The inspection report: verdict, reasons, per-thread heights and black crests, registration,
/// timings (the result shape of docs/bundle.md plus measures).
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/report",
    operation_id = "get_report",
    tag = "results",
    params(("id" = String, Path, description = "Inspection id")),
    responses(
        (status = 200, description = "The report (JSON)", body = Object, headers(("ETag" = String))),
        (status = 304, description = "Not modified"),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_report(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let id = succeeded(&state, &id).await?;
    let (json, etag) = state.store.report(&id.0).await?;
    Ok(immutable(&headers, &etag, "application/json", json))
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct AngleHeight {
    pub angle_deg: f64,
    /// null where no view covered the bin.
    pub height_mm: Option<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct ThreadRow {
    /// Thread number (1 = nearest the pipe end).
    pub thread: i64,
    pub crest_z_mm: [f64; 2],
    pub min_height_mm: Option<f64>,
    pub mean_height_mm: Option<f64>,
    pub max_height_mm: Option<f64>,
    pub bins_measured: i64,
    pub black_crest_arcs_deg: Vec<[f64; 2]>,
    pub black_crest_length_mm: f64,
    pub heights: Vec<AngleHeight>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct ThreadTable {
    pub inspection_id: String,
    pub threads: Vec<ThreadRow>,
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct FormatQuery {
    /// Overrides `Accept`.
    pub format: Option<String>,
}

/// An `Accept` header's media ranges, lower-cased, most preferred first (RFC 9110 §12.5.1: by
/// weight `q`, 1 when absent; equal weights keep the client's order); ranges with `q=0` are
/// refused and left out, and so is a range whose weight is not a number from 0 to 1.
fn media_ranges_by_preference(accept: &str) -> Vec<String> {
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
fn negotiate(
    headers: &HeaderMap,
    format: Option<&str>,
    offered: &[(&'static str, &'static str)],
) -> Result<(&'static str, &'static str), ApiError> {
    if let Some(f) = format {
        return offered.iter().find(|o| o.0.eq_ignore_ascii_case(f)).copied().ok_or_else(|| {
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

/// The per-thread height table: JSON, or CSV (`thread,angle_deg,height_mm`, the CMM upload's
/// columns) on `Accept: text/csv` or `?format=csv`.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/threads",
    operation_id = "get_threads",
    tag = "results",
    params(("id" = String, Path, description = "Inspection id"), FormatQuery),
    responses(
        (status = 200, description = "Per-thread table", content(
            (ThreadTable = "application/json"),
            (String = "text/csv"),
        )),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 406, description = "Unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_threads(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<FormatQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let id = succeeded(&state, &id).await?;
    let (format, media) =
        negotiate(&headers, q.format.as_deref(), &[("json", "application/json"), ("csv", "text/csv")])?;
    let (threads, heights) = state.store.threads(&id.0).await?;
    if format == "csv" {
        let mut out = String::from("thread,angle_deg,height_mm\n");
        for h in &heights {
            out.push_str(&format!(
                "{},{},{}\n",
                h.thread_index,
                h.angle_deg,
                h.height_mm.map(|v| format!("{v:.6}")).unwrap_or_default()
            ));
        }
        let etag = crate::service::store::etag_of(out.as_bytes());
        return Ok(immutable(&headers, &etag, "text/csv; charset=utf-8", out));
    }
    let mut by_thread: std::collections::BTreeMap<i64, Vec<AngleHeight>> = Default::default();
    for h in heights {
        by_thread
            .entry(h.thread_index)
            .or_default()
            .push(AngleHeight { angle_deg: h.angle_deg, height_mm: h.height_mm });
    }
    let table = ThreadTable {
        inspection_id: id.0.clone(),
        threads: threads
            .into_iter()
            .map(|t| ThreadRow {
                thread: t.thread_index,
                crest_z_mm: [t.crest_z_start_mm, t.crest_z_end_mm],
                min_height_mm: t.min_height_mm,
                mean_height_mm: t.mean_height_mm,
                max_height_mm: t.max_height_mm,
                bins_measured: t.bins_measured,
                black_crest_arcs_deg: serde_json::from_str(&t.black_crest_arcs_json).unwrap_or_default(),
                black_crest_length_mm: t.black_crest_length_mm,
                heights: by_thread.remove(&t.thread_index).unwrap_or_default(),
            })
            .collect(),
    };
    let body = serde_json::to_vec(&table).map_err(ApiError::internal)?;
    let etag = crate::service::store::etag_of(&body);
    Ok(immutable(&headers, &etag, media, body))
}

/// The surface mesh: binary PLY (default; `application/x-ply`), binary STL (`model/stl`) or binary
/// glTF (`model/gltf-binary`; millimetres scaled to glTF's metres by its node), by
/// `?format=ply|stl|glb` or `Accept`.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/mesh",
    operation_id = "get_mesh",
    tag = "results",
    params(("id" = String, Path, description = "Inspection id"), FormatQuery),
    responses(
        (status = 200, description = "The mesh", content(
            (Binary = "application/x-ply"),
            (Binary = "model/stl"),
            (Binary = "model/gltf-binary"),
        ), headers(("ETag" = String))),
        (status = 304, description = "Not modified"),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 406, description = "Unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_mesh(
    State(state): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<FormatQuery>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let id = succeeded(&state, &id).await?;
    let offered = [("ply", "application/x-ply"), ("stl", "model/stl"), ("glb", "model/gltf-binary")];
    let (format, media) = negotiate(&headers, q.format.as_deref(), &offered)?;
    let a = state.store.artifact(&id.0, if format == "stl" { "mesh.stl" } else { "mesh.ply" }).await?;
    let mut response = if format == "glb" {
        // Made from the stored PLY on request (a third stored copy would add as much again per
        // result); its validator follows the PLY's, so a revalidation costs no conversion.
        let etag = crate::service::store::etag_of(format!("glb {}", a.etag).as_bytes());
        if if_none_match(&headers, &etag) {
            immutable(&headers, &etag, media, Vec::new())
        } else {
            let body = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
                let mesh = crate::export::ply::read(&a.body).map_err(ApiError::internal)?;
                let mut glb = Vec::new();
                crate::export::glb::write(&mesh, &mut glb).map_err(ApiError::internal)?;
                Ok(glb)
            })
            .await
            .map_err(ApiError::internal)??;
            immutable(&headers, &etag, media, body)
        }
    } else {
        immutable(&headers, &a.etag, &a.content_type, a.body)
    };
    let disposition = format!("attachment; filename=\"{}.{format}\"", id.0);
    response.headers_mut().insert(header::CONTENT_DISPOSITION, HeaderValue::from_str(&disposition).expect("ASCII"));
    Ok(response)
}

/// The unrolled height map (16-bit gray) or the all-in-focus mosaic (RGB), as PNG.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/images/{kind}",
    operation_id = "get_image",
    tag = "results",
    params(
        ("id" = String, Path, description = "Inspection id"),
        ("kind" = String, Path, description = "height-map or all-in-focus"),
    ),
    responses(
        (status = 200, description = "PNG", content((Binary = "image/png")), headers(("ETag" = String))),
        (status = 304, description = "Not modified"),
        (status = 404, description = "No such inspection or image", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_image(
    State(state): State<AppState>,
    Path((id, kind)): Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let kind = match kind.trim_end_matches(".png") {
        "height-map" => "height-map.png",
        "all-in-focus" => "all-in-focus.png",
        other => {
            return Err(ApiError::new(Code::NotFound, format!("no image {other:?}: height-map or all-in-focus"))
                .with_culprit("kind"));
        }
    };
    let id = succeeded(&state, &id).await?;
    let a = state.store.artifact(&id.0, kind).await?;
    Ok(immutable(&headers, &a.etag, &a.content_type, a.body))
}

const MAX_CMM_BYTES: usize = 16 << 20;

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StoredCmm {
    pub inspection_id: String,
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub uploaded_at: String,
    pub points: Vec<CmmPoint>,
}

/// Upload (or replace) the CMM measurements of an inspection: JSON
/// (`{"instrument", "measured_at", "points": [{"thread", "angle_deg", "height_mm"}]}`) or CSV
/// (`thread,angle_deg,height_mm`; an empty angle is the thread's mean).
#[utoipa::path(
    put,
    path = "/v1/inspections/{id}/cmm",
    operation_id = "put_cmm",
    tag = "cmm",
    params(("id" = String, Path, description = "Inspection id")),
    request_body(content(
        (CmmMeasurements = "application/json"),
        (String = "text/csv"),
    )),
    responses(
        (status = 200, description = "Stored", body = StoredCmm),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Neither JSON nor CSV", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid measurements (the field or CSV line is named)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn put_cmm(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Result<Json<StoredCmm>, ApiError> {
    let id = succeeded(&state, &id).await?;
    let body: Bytes = axum::body::to_bytes(body, MAX_CMM_BYTES).await.map_err(|e| {
        if std::error::Error::source(&e).is_some_and(|s| s.is::<http_body_util::LengthLimitError>()) {
            ApiError::new(Code::BodyTooLarge, format!("CMM uploads are limited to {} MiB", MAX_CMM_BYTES >> 20))
        } else {
            ApiError::new(Code::BadRequest, format!("reading the body: {e}"))
        }
    })?;
    let content_type =
        headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let essence = content_type.split(';').next().unwrap_or("").trim();
    let parsed = match essence {
        "application/json" => CmmMeasurements::from_json(&body),
        "text/csv" => CmmMeasurements::from_csv(&body),
        other => {
            return Err(ApiError::new(
                Code::UnsupportedMediaType,
                format!("Content-Type {other:?}: send application/json or text/csv"),
            )
            .with_culprit("Content-Type"));
        }
    }
    .map_err(|e| ApiError::new(Code::InvalidCmm, e.to_string()).with_culprit(e.field.clone()))?;
    state.store.put_cmm(&id.0, &parsed).await?;
    get_cmm(State(state), Path(id.0)).await
}

/// The stored CMM measurements.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/cmm",
    operation_id = "get_cmm",
    tag = "cmm",
    params(("id" = String, Path, description = "Inspection id")),
    responses(
        (status = 200, description = "Stored measurements", body = StoredCmm),
        (status = 404, description = "No such inspection, or no CMM data yet", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_cmm(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<StoredCmm>, ApiError> {
    let id = InspectionId::parse(&id)?;
    state.store.inspection(&id.0).await.map_err(|e| super::missing_inspection(e, &id.0))?;
    Ok(Json(stored_cmm(&state, id).await?))
}

/// The CMM measurements stored for an inspection known to exist.
async fn stored_cmm(state: &AppState, id: InspectionId) -> Result<StoredCmm, ApiError> {
    let row = state.store.cmm(&id.0).await.map_err(|e| match e {
        StoreError::NotFound => {
            ApiError::new(Code::CmmNotFound, format!("no CMM measurements for {}; PUT them first", id.0))
        }
        other => other.into(),
    })?;
    Ok(StoredCmm {
        inspection_id: id.0,
        instrument: row.instrument,
        measured_at: row.measured_at,
        uploaded_at: rfc3339(row.uploaded_at),
        points: serde_json::from_str(&row.points_json).map_err(ApiError::internal)?,
    })
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ComparisonQuery {
    /// Agreement tolerance in mm (default: one tenth of the thread-height tolerance band).
    pub tolerance_mm: Option<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CmmComparison {
    pub inspection_id: String,
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    /// The thread-height tolerance (±) of the part.
    pub height_tolerance_mm: f64,
    #[serde(flatten)]
    pub comparison: Comparison,
}

/// crestscan against the CMM: per point (thread, angle) both heights and the deviation; bias, RMS,
/// max |deviation|, Bland–Altman limits of agreement, and agreement within a tolerance.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/cmm-comparison",
    operation_id = "get_cmm_comparison",
    tag = "cmm",
    params(("id" = String, Path, description = "Inspection id"), ComparisonQuery),
    responses(
        (status = 200, description = "The comparison", body = CmmComparison),
        (status = 400, description = "Invalid tolerance", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such inspection, or no CMM data yet", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_cmm_comparison(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ComparisonQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<CmmComparison>, ApiError> {
    let Query(q) = query.map_err(|e| ApiError::new(Code::InvalidQuery, e.body_text()))?;
    if let Some(t) = q.tolerance_mm
        && !(t.is_finite() && t > 0.0)
    {
        return Err(ApiError::new(Code::InvalidQuery, format!("tolerance_mm: {t} must be a positive number"))
            .with_culprit("tolerance_mm"));
    }
    let id = succeeded(&state, &id).await?;
    let stored = stored_cmm(&state, id.clone()).await?;
    let (json, _) = state.store.report(&id.0).await?;
    let report: Report = serde_json::from_str(&json).map_err(ApiError::internal)?;
    let tolerance = q.tolerance_mm.unwrap_or_else(|| cmm::default_tolerance_mm(&report));
    let measurements = CmmMeasurements {
        instrument: stored.instrument.clone(),
        measured_at: stored.measured_at.clone(),
        points: stored.points,
    };
    Ok(Json(CmmComparison {
        inspection_id: id.0,
        instrument: stored.instrument,
        measured_at: stored.measured_at,
        height_tolerance_mm: report.height_tolerance_mm,
        comparison: cmm::compare(&report, &measurements, tolerance),
    }))
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
