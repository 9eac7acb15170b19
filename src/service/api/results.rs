//! Results of a succeeded inspection: report, per-thread table, mesh, images; immutable, with
//! strong ETags.

use super::common::{AppState, Binary, stored_artifact, succeeded};
use super::http::{if_none_match, immutable, negotiate};
use super::problem::{ApiError, Problem};
use crate::problem::Code;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, header};
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
}

/// The inspection report: verdict, reasons, per-thread heights and black crests, registration,
/// timings (the result shape of docs/bundle.md plus measures). With `Accept: text/html` or
/// `?format=html`, the same as one self-contained page for a person (plots, images and, once CMM
/// data is uploaded, crestscan against the CMM); it loads nothing from anywhere. With `Accept:
/// application/qif+xml` or `?format=qif`, the results as a QIF 3.0 document (ISO 23952) for CMM
/// software and quality databases (docs/interchange.md).
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/report",
    operation_id = "get_report",
    tag = "results",
    params(("id" = uuid::Uuid, Path, description = "Inspection id"), ReportFormatQuery),
    responses(
        (status = 200, description = "The report: JSON (with an ETag), an HTML page, or a QIF 3.0 document (with an ETag)", content(
            (crate::pipeline::report::Report = "application/json"),
            (String = "text/html"),
            (String = "application/qif+xml"),
        ), headers(("ETag" = String))),
        (status = 304, description = "Not modified"),
        (status = 400, description = "Malformed query (format given twice)", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 406, description = "Unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_report(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ReportFormatQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Query(q) = query?;
    let id = succeeded(&state, &id).await?;
    let (format, _) = negotiate(&headers, q.format.as_deref(), &REPORT_FORMATS)?;
    let (json, etag) = state.store.report(&id.0).await?;
    if format == "json" {
        return Ok(immutable(&headers, &etag, "application/json", json));
    }
    let report: crate::pipeline::report::Report = serde_json::from_str(&json).map_err(ApiError::internal)?;
    if format == "qif" {
        // What the document adds to the report (the station's name, the finishing time) is fixed
        // once the inspection succeeded: immutable like the report, with an ETag of its own.
        let row = state.store.inspection(&id.0).await?;
        let finished_at = row.finished_at.map(crate::service::wire::rfc3339);
        let inputs =
            crate::export::qif::QifInputs { station_name: row.station.as_deref(), finished_at: finished_at.as_deref() };
        let document = crate::export::qif::document(&report, &inputs);
        let etag = format!("{}-qif\"", etag.trim_end_matches('"'));
        return Ok(immutable(&headers, &etag, crate::export::qif::MEDIA_TYPE, document));
    }
    let cmm = super::cmm::comparison_if_uploaded(&state, &id, &report).await?;
    // Images the retention deleted are left out; the rest of the page stands.
    let image = |kind: &'static str| {
        let state = state.clone();
        let id = id.0.clone();
        async move { state.store.artifact(&id, kind).await.ok().map(|a| a.body) }
    };
    let (mosaic, height_map) = (image("all-in-focus.png").await, image("height-map.png").await);
    let artifacts_missing = match (&mosaic, &height_map) {
        (None, None) => state.store.artifacts_purged_at(&id.0).await?.map(|at| {
            format!(
                "The images and the mesh of this inspection were deleted on {} (artifact_retention_days); the \
                 report's figures above are kept.",
                crate::service::wire::rfc3339(at)
            )
        }),
        _ => None,
    };
    let inspection_id = id.0.clone();
    // Reducing the images decodes megabytes of PNG: off the async threads.
    let page = tokio::task::spawn_blocking(move || {
        use crate::export::{html, png};
        let preview =
            |png_bytes: Option<Vec<u8>>| png_bytes.and_then(|b| png::preview_png(&b, html::IMAGE_WIDTH_PX).ok());
        let (mosaic, height_map) = (preview(mosaic), preview(height_map));
        html::report_page(
            &report,
            &html::PageInputs {
                inspection_id: Some(&inspection_id),
                mosaic_png: mosaic.as_deref(),
                height_map_png: height_map.as_deref(),
                cmm,
                mesh: artifacts_missing
                    .is_none()
                    .then(|| html::MeshSource::Url(format!("/v1/inspections/{inspection_id}/mesh?format=glb"))),
                full_images: artifacts_missing.is_none().then(|| {
                    ["all-in-focus", "height-map"].map(|kind| format!("/v1/inspections/{inspection_id}/images/{kind}"))
                }),
                artifacts_missing,
            },
        )
    })
    .await
    .map_err(ApiError::internal)?;
    // The page changes when CMM data is uploaded: revalidated, not cached as immutable.
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("text/html; charset=utf-8")),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
            (header::VARY, HeaderValue::from_static("Accept")),
            (
                header::CONTENT_SECURITY_POLICY,
                HeaderValue::from_str(crate::export::html::content_security_policy()).map_err(ApiError::internal)?,
            ),
        ],
        page,
    )
        .into_response())
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ReportFormatQuery {
    #[param(schema_with = report_formats)]
    pub format: Option<String>,
}

const REPORT_FORMATS: [(&str, &str); 3] =
    [("json", "application/json"), ("html", "text/html"), ("qif", crate::export::qif::MEDIA_TYPE)];

fn report_formats() -> utoipa::openapi::schema::Object {
    super::common::one_of(REPORT_FORMATS.map(|f| f.0), "Overrides `Accept`.")
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct AngleHeight {
    pub angle_deg: f64,
    /// null where no view covered the bin.
    pub height_mm: Option<f64>,
    /// The height's expanded uncertainty (k = 2); null where the height is (or for results
    /// stored before it was computed).
    pub uncertainty_mm: Option<f64>,
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
    /// The thread's height against nominal ± tolerance with its uncertainty: within, outside,
    /// indeterminate or not_judged (the report's `threads[].height_finding` has its figures).
    #[schema(value_type = Option<crate::pipeline::uncertainty::HeightFinding>)]
    pub height_finding: Option<String>,
    /// The expanded uncertainty (k = 2) of the mean the finding judged.
    pub mean_height_uncertainty_mm: Option<f64>,
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
    #[param(schema_with = table_formats)]
    pub format: Option<String>,
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct MeshFormatQuery {
    #[param(schema_with = mesh_formats)]
    pub format: Option<String>,
}

/// What each resource offers (format, media type), the first its default: negotiation picks from
/// these and the `format` parameter's schema lists them.
const TABLE_FORMATS: [(&str, &str); 2] = [("json", "application/json"), ("csv", "text/csv")];
const MESH_FORMATS: [(&str, &str); 3] =
    [("ply", "application/x-ply"), ("stl", "model/stl"), ("glb", "model/gltf-binary")];

fn table_formats() -> utoipa::openapi::schema::Object {
    super::common::one_of(TABLE_FORMATS.map(|f| f.0), "Overrides `Accept`.")
}
fn mesh_formats() -> utoipa::openapi::schema::Object {
    super::common::one_of(MESH_FORMATS.map(|f| f.0), "Overrides `Accept`.")
}

/// The per-thread height table: JSON, or CSV (`thread,angle_deg,height_mm,uncertainty_mm`: the
/// CMM upload's columns and each height's expanded uncertainty, k = 2) on `Accept: text/csv` or
/// `?format=csv`.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/threads",
    operation_id = "get_threads",
    tag = "results",
    params(("id" = uuid::Uuid, Path, description = "Inspection id"), FormatQuery),
    responses(
        (status = 200, description = "Per-thread table", content(
            (ThreadTable = "application/json"),
            (String = "text/csv"),
        )),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 400, description = "Malformed query (format given twice)", body = Problem, content_type = "application/problem+json"),
        (status = 406, description = "Unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_threads(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<FormatQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Query(q) = query?;
    let id = succeeded(&state, &id).await?;
    let (format, media) = negotiate(&headers, q.format.as_deref(), &TABLE_FORMATS)?;
    let (threads, heights) = state.store.threads(&id.0).await?;
    if format == "csv" {
        let mut out = String::from("thread,angle_deg,height_mm,uncertainty_mm\n");
        for h in &heights {
            out.push_str(&format!(
                "{},{},{},{}\n",
                h.thread_index,
                h.angle_deg,
                h.height_mm.map(|v| format!("{v:.6}")).unwrap_or_default(),
                h.uncertainty_mm.map(|v| format!("{v:.6}")).unwrap_or_default()
            ));
        }
        let etag = crate::service::store::etag_of(out.as_bytes());
        return Ok(immutable(&headers, &etag, "text/csv; charset=utf-8", out));
    }
    let mut by_thread: std::collections::BTreeMap<i64, Vec<AngleHeight>> = Default::default();
    for h in heights {
        by_thread.entry(h.thread_index).or_default().push(AngleHeight {
            angle_deg: h.angle_deg,
            height_mm: h.height_mm,
            uncertainty_mm: h.uncertainty_mm,
        });
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
                height_finding: t.height_finding,
                mean_height_uncertainty_mm: t.mean_height_uncertainty_mm,
                heights: by_thread.remove(&t.thread_index).unwrap_or_default(),
            })
            .collect(),
    };
    let body = crate::export::json::to_vec(&table).map_err(ApiError::internal)?;
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
    params(("id" = uuid::Uuid, Path, description = "Inspection id"), MeshFormatQuery),
    responses(
        (status = 200, description = "The mesh", content(
            (Binary = "application/x-ply"),
            (Binary = "model/stl"),
            (Binary = "model/gltf-binary"),
        ), headers(("ETag" = String))),
        (status = 304, description = "Not modified"),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 400, description = "Malformed query (format given twice)", body = Problem, content_type = "application/problem+json"),
        (status = 406, description = "Unsupported format", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Deleted by the result retention", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_mesh(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<MeshFormatQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let Query(q) = query?;
    let id = succeeded(&state, &id).await?;
    let (format, media) = negotiate(&headers, q.format.as_deref(), &MESH_FORMATS)?;
    let a = stored_artifact(&state, &id.0, if format == "stl" { "mesh.stl" } else { "mesh.ply" }).await?;
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
        ("id" = uuid::Uuid, Path, description = "Inspection id"),
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
    let a = stored_artifact(&state, &id.0, kind).await?;
    Ok(immutable(&headers, &a.etag, &a.content_type, a.body))
}
