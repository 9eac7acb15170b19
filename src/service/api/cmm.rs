//! CMM measurements of an inspection (JSON or CSV per the contract) and their comparison with
//! crestscan's heights.

use super::common::{AppState, InspectionId, succeeded};
use super::problem::{ApiError, Problem};
use crate::eval::cmm::{self, CmmMeasurements, CmmPoint, Comparison};
use crate::pipeline::report::Report;
use crate::problem::Code;
use crate::service::store::StoreError;
use crate::service::wire::rfc3339;
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, header};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(put_cmm, get_cmm))
        .routes(routes!(list_cmm_versions))
        .routes(routes!(get_cmm_comparison))
        .routes(routes!(get_training_pairs))
}

const MAX_CMM_BYTES: usize = 16 << 20;

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StoredCmm {
    pub inspection_id: String,
    /// This upload's number among the inspection's CMM uploads (1, 2, ...): each upload is kept.
    pub version: i64,
    /// Who uploaded it: the client's address (NULL for uploads stored before versions).
    pub uploaded_by: Option<String>,
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub uploaded_at: String,
    pub points: Vec<CmmPoint>,
}

/// Upload CMM measurements of an inspection, stored as its next version (earlier uploads are kept,
/// `GET …/cmm/versions`; the latest is the one compared): JSON
/// (`{"instrument", "measured_at", "points": [{"thread", "angle_deg", "height_mm"}]}`) or CSV
/// (`thread,angle_deg,height_mm`; an empty angle is the thread's mean). CSV as CMM software
/// exports it is read too: `;` or tab separators with decimal commas, heights in inches
/// (`height_in`, or a `unit` column of `mm`/`in`, converted), and `# instrument: …`,
/// `# measured_at: …` and `# units: mm|in` lines before the header. Or a QIF 3.0 results
/// document (`application/qif+xml`) as CMM software exports it: each
/// `HeightCharacteristicMeasurement` whose item names its thread (an attribute `thread`, or a
/// `Name` like `thread 3 height`), with an `angle_deg` attribute for a point (without one, the
/// thread's mean), in the file's primary linear unit, its `combinedUncertainty` × 2 as the
/// point's expanded uncertainty; any other measurement, or one whose item names no thread, is
/// refused with its id (docs/interchange.md).
#[utoipa::path(
    put,
    path = "/v1/inspections/{id}/cmm",
    operation_id = "put_cmm",
    tag = "cmm",
    params(("id" = uuid::Uuid, Path, description = "Inspection id")),
    request_body(content(
        (CmmMeasurements = "application/json"),
        (super::common::Binary = "text/csv"),
        (super::common::Binary = "application/qif+xml"),
    )),
    responses(
        (status = 200, description = "Stored", body = StoredCmm),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Neither JSON, CSV nor QIF", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid measurements (the field or CSV line is named)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn put_cmm(
    State(state): State<AppState>,
    axum::extract::ConnectInfo(peer): axum::extract::ConnectInfo<std::net::SocketAddr>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Result<super::common::Rounded<StoredCmm>, ApiError> {
    let id = succeeded(&state, &id).await?;
    let body: Bytes = axum::body::to_bytes(body, MAX_CMM_BYTES).await.map_err(|e| {
        if std::error::Error::source(&e).is_some_and(|s| s.is::<http_body_util::LengthLimitError>()) {
            ApiError::new(Code::BodyTooLarge, format!("CMM uploads are limited to {} MiB", MAX_CMM_BYTES >> 20))
        } else {
            ApiError::new(Code::BadRequest, format!("reading the body: {e}"))
        }
    })?;
    let parsed = match super::common::media_type(&headers).as_str() {
        "application/json" => CmmMeasurements::from_json(&body),
        "text/csv" => CmmMeasurements::from_csv(&body),
        "application/qif+xml" | "application/xml" | "text/xml" => CmmMeasurements::from_qif(&body),
        other => {
            return Err(ApiError::new(
                Code::UnsupportedMediaType,
                format!(
                    "Content-Type {other:?}: send application/json, text/csv or application/qif+xml (QIF 3.0 results)"
                ),
            )
            .with_culprit("Content-Type"));
        }
    }
    .map_err(|e| ApiError::new(Code::InvalidCmm, e.to_string()).with_culprit(e.field.clone()))?;
    let (json, _) = state.store.report(&id.0).await?;
    let report: Report = serde_json::from_str(&json).map_err(ApiError::internal)?;
    cmm::check_threads(&report, &parsed)
        .map_err(|e| ApiError::new(Code::InvalidCmm, e.to_string()).with_culprit(e.field.clone()))?;
    let version = state.store.put_cmm(&id.0, &parsed, Some(&peer.ip().to_string())).await?;
    tracing::info!(inspection = %id.0, version, by = %peer.ip(), points = parsed.points.len(), "CMM data stored");
    Ok(super::common::Rounded(stored_cmm(&state, id, Some(version)).await?))
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct CmmVersionQuery {
    /// A stored version (default: the latest).
    #[param(minimum = 1)]
    pub version: Option<i64>,
}

fn checked_version(version: Option<i64>) -> Result<Option<i64>, ApiError> {
    match version {
        Some(v) if v < 1 => {
            Err(ApiError::new(Code::InvalidQuery, format!("version: {v} must be 1 or more")).with_culprit("version"))
        }
        v => Ok(v),
    }
}

/// The stored CMM measurements.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/cmm",
    operation_id = "get_cmm",
    tag = "cmm",
    params(("id" = uuid::Uuid, Path, description = "Inspection id"), CmmVersionQuery),
    responses(
        (status = 200, description = "Stored measurements", body = StoredCmm),
        (status = 400, description = "Invalid version", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such inspection, no CMM data yet, or no such version", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_cmm(
    State(state): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<CmmVersionQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<super::common::Rounded<StoredCmm>, ApiError> {
    let Query(q) = query?;
    let version = checked_version(q.version)?;
    let id = InspectionId::parse(&id)?;
    state.store.inspection(&id.0).await.map_err(|e| super::common::missing_inspection(e, &id.0))?;
    Ok(super::common::Rounded(stored_cmm(&state, id, version).await?))
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CmmVersion {
    pub version: i64,
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub uploaded_at: String,
    pub uploaded_by: Option<String>,
    /// How many points the upload holds.
    pub points: i64,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CmmVersions {
    pub inspection_id: String,
    /// Oldest first; the last is the one compared.
    pub versions: Vec<CmmVersion>,
}

/// Every CMM upload of an inspection (who, when, how many points), oldest first; each is read with
/// `GET …/cmm?version=N`.
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/cmm/versions",
    operation_id = "list_cmm_versions",
    tag = "cmm",
    params(("id" = uuid::Uuid, Path, description = "Inspection id")),
    responses(
        (status = 200, description = "The uploads (empty when none)", body = CmmVersions),
        (status = 404, description = "No such inspection", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn list_cmm_versions(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<CmmVersions>, ApiError> {
    let id = InspectionId::parse(&id)?;
    state.store.inspection(&id.0).await.map_err(|e| super::common::missing_inspection(e, &id.0))?;
    let versions = state
        .store
        .cmm_versions(&id.0)
        .await?
        .into_iter()
        .map(|v| CmmVersion {
            version: v.version,
            instrument: v.instrument,
            measured_at: v.measured_at,
            uploaded_at: rfc3339(v.uploaded_at),
            uploaded_by: v.uploaded_by,
            points: v.points,
        })
        .collect();
    Ok(Json(CmmVersions { inspection_id: id.0, versions }))
}

/// The CMM measurements stored for an inspection known to exist: the latest, or `version`.
async fn stored_cmm(state: &AppState, id: InspectionId, version: Option<i64>) -> Result<StoredCmm, ApiError> {
    let row = state.store.cmm(&id.0, version).await.map_err(|e| match (e, version) {
        (StoreError::NotFound, None) => {
            ApiError::new(Code::CmmNotFound, format!("no CMM measurements for {}; PUT them first", id.0))
        }
        (StoreError::NotFound, Some(v)) => {
            ApiError::new(Code::CmmNotFound, format!("no CMM version {v} for {}", id.0)).with_culprit("version")
        }
        (other, _) => other.into(),
    })?;
    Ok(StoredCmm {
        inspection_id: id.0,
        version: row.version,
        uploaded_by: row.uploaded_by,
        instrument: row.instrument,
        measured_at: row.measured_at,
        uploaded_at: rfc3339(row.uploaded_at),
        points: serde_json::from_str(&row.points_json).map_err(ApiError::internal)?,
    })
}

/// The report page's CMM panel, where CMM data was uploaded for the inspection (at the default
/// agreement tolerance).
pub(super) async fn comparison_if_uploaded(
    state: &AppState,
    id: &InspectionId,
    report: &Report,
) -> Result<Option<crate::export::html::CmmPanel>, ApiError> {
    let stored = match stored_cmm(state, id.clone(), None).await {
        Ok(stored) => stored,
        Err(e) if e.code == Code::CmmNotFound => return Ok(None),
        Err(e) => return Err(e),
    };
    let measurements = CmmMeasurements {
        instrument: stored.instrument.clone(),
        measured_at: stored.measured_at,
        points: stored.points,
        uncertainty_mm: None,
    };
    let c = cmm::compare(report, &measurements, cmm::default_tolerance_mm(report));
    Ok(Some(crate::export::html::CmmPanel {
        instrument: stored.instrument,
        points: c.points.iter().filter_map(|p| Some((p.cmm_height_mm, p.crestscan_height_mm?))).collect(),
        unmatched: c.agreement.unmatched,
        bias_mm: c.agreement.bias_mm,
        rms_mm: c.agreement.rms_mm,
        limits_of_agreement_mm: c.agreement.limits_of_agreement_mm,
        tolerance_mm: c.agreement.tolerance_mm,
        within_tolerance: c.agreement.within_tolerance,
    }))
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ComparisonQuery {
    /// Agreement tolerance in mm (default: one tenth of the thread-height tolerance band).
    #[param(exclusive_minimum = 0.0)]
    pub tolerance_mm: Option<f64>,
    /// The CMM upload to compare with (default: the latest).
    #[param(minimum = 1)]
    pub version: Option<i64>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CmmComparison {
    pub inspection_id: String,
    /// The CMM upload compared with.
    pub cmm_version: i64,
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
    params(("id" = uuid::Uuid, Path, description = "Inspection id"), ComparisonQuery),
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
) -> Result<super::common::Rounded<CmmComparison>, ApiError> {
    let Query(q) = query?;
    if let Some(t) = q.tolerance_mm
        && !(t.is_finite() && t > 0.0)
    {
        return Err(ApiError::new(Code::InvalidQuery, format!("tolerance_mm: {t} must be a positive number"))
            .with_culprit("tolerance_mm"));
    }
    let version = checked_version(q.version)?;
    let id = succeeded(&state, &id).await?;
    let stored = stored_cmm(&state, id.clone(), version).await?;
    let (json, _) = state.store.report(&id.0).await?;
    let report: Report = serde_json::from_str(&json).map_err(ApiError::internal)?;
    let tolerance = q.tolerance_mm.unwrap_or_else(|| cmm::default_tolerance_mm(&report));
    let measurements = CmmMeasurements {
        instrument: stored.instrument.clone(),
        measured_at: stored.measured_at.clone(),
        points: stored.points,
        uncertainty_mm: None,
    };
    Ok(super::common::Rounded(CmmComparison {
        inspection_id: id.0,
        cmm_version: stored.version,
        instrument: stored.instrument,
        measured_at: stored.measured_at,
        height_tolerance_mm: report.height_tolerance_mm,
        comparison: cmm::compare(&report, &measurements, tolerance),
    }))
}

/// The profile-correction MLP's training pairs of this inspection: one JSON object per line
/// (`application/x-ndjson`), for each measured 1° bin that has a CMM point of its thread: the
/// bin's pitch of reconstructed profile (256 samples), its own height fit, and the CMM's height
/// (of the latest CMM upload).
/// training/profile_mlp.py refits the MLP from such files (docs/models.md, "Recalibration from
/// CMM data").
#[utoipa::path(
    get,
    path = "/v1/inspections/{id}/training-pairs",
    operation_id = "get_training_pairs",
    tag = "cmm",
    params(("id" = uuid::Uuid, Path, description = "Inspection id")),
    responses(
        (status = 200, description = "One pair per line", body = String, content_type = "application/x-ndjson"),
        (status = 404, description = "No such inspection, no CMM data yet, or no pitch profiles kept", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not succeeded (yet)", body = Problem, content_type = "application/problem+json"),
        (status = 410, description = "Pitch profiles deleted by retention", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_training_pairs(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::response::Response, ApiError> {
    use axum::response::IntoResponse;
    let id = succeeded(&state, &id).await?;
    let stored = stored_cmm(&state, id.clone(), None).await?;
    let kind = crate::service::store::PITCH_PROFILES;
    let artifact = match super::common::stored_artifact(&state, &id.0, kind).await {
        Err(e) if e.code == Code::InvalidId => {
            return Err(ApiError::new(
                Code::NotFound,
                "this inspection kept no pitch profiles (it finished before crestscan kept them): inspect the \
                 bundle again to pair it with CMM data",
            ));
        }
        other => other?,
    };
    let set = crate::eval::pairs::ProfileSet::decode(&artifact.body).map_err(ApiError::internal)?;
    let measurements = CmmMeasurements {
        instrument: stored.instrument,
        measured_at: stored.measured_at,
        points: stored.points,
        uncertainty_mm: None,
    };
    let mut body = Vec::new();
    for pair in set.with_cmm(&id.0, &measurements) {
        serde_json::to_writer(&mut body, &pair).map_err(ApiError::internal)?;
        body.push(b'\n');
    }
    Ok(([(header::CONTENT_TYPE, "application/x-ndjson")], body).into_response())
}
