//! `/v1/stations`: stations a plant qualifies (ISO 15530-3). A station is created by name; its
//! masters' certificates are uploaded; a study over the masters' inspections measures its
//! correction and uncertainty and qualifies it; inspections naming it are then decided with them.

use super::common::{AppState, InspectionId};
use super::problem::{ApiError, Problem};
use super::station_reads::{certificate_of, run_at_station, station_not_found, stored_report, study_qualification};
use crate::domain::qualification::Qualification;
use crate::eval::qualify::{self, Certificate, MasterRuns};
use crate::pipeline::report::Report;
use crate::problem::Code;
use crate::service::store::{StationRow, StoreError, StudyRow, now_ms};
use crate::service::wire::rfc3339;
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(create_station, list_stations))
        .routes(routes!(get_station))
        .routes(routes!(put_master))
        .routes(routes!(create_study))
        .routes(routes!(get_study))
}

const MAX_CERTIFICATE_BYTES: usize = 16 << 20;
/// The most inspections one study takes.
const MAX_STUDY_RUNS: usize = 500;

#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewStation {
    /// What bundles (`station` in the manifest) and submissions name it by, and its URL: 1–64 of
    /// `A–Z a–z 0–9 . _ -`, starting with a letter or digit.
    #[schema(min_length = 1, max_length = 64, pattern = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")]
    pub name: String,
    /// What the station is (line, camera, lens): 1–200 characters.
    #[schema(min_length = 1, max_length = 200)]
    pub description: Option<String>,
}

/// A station and where its qualification stands.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StationRecord {
    pub name: String,
    pub description: Option<String>,
    /// `unqualified` (inspections are decided as at any station), `qualified` (its study's
    /// correction and uncertainty are applied), `suspended` (a check broke its control chart, or
    /// the qualification expired: no decision until requalified).
    #[schema(pattern = "^(unqualified|qualified|suspended)$")]
    pub status: String,
    /// Why it is suspended.
    pub status_reason: Option<String>,
    /// The study in force; null before the first.
    pub study: Option<String>,
    /// The fingerprint the study bound the station to (object pixel, depth of field, frame step,
    /// views, rows, overlap); null before the first study.
    pub fingerprint: Option<crate::domain::qualification::Fingerprint>,
    /// The station's expanded uncertainty of a corrected height (k = 2), µm, from the study.
    pub expanded_uncertainty_um: Option<f64>,
    /// Until when the qualification holds (RFC 3339); null: until requalified.
    pub qualified_until: Option<String>,
    /// The masters' serials, certificates' instruments and uncertainties.
    pub masters: Vec<Master>,
    pub created_at: String,
    pub updated_at: String,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Master {
    pub serial: String,
    pub instrument: String,
    /// The certificate's date.
    pub calibrated_at: String,
    /// The largest expanded uncertainty (k = 2) its certificate states, µm.
    pub certificate_uncertainty_um: f64,
    /// Certified heights.
    pub points: usize,
    pub uploaded_at: String,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StationList {
    pub items: Vec<StationRecord>,
}

#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewStudy {
    /// The masters' succeeded inspections at this station (at least 10 per master; 25 is usual),
    /// each of a part whose serial is one of the station's masters.
    #[schema(min_items = 1, max_items = 500)]
    pub inspections: Vec<uuid::Uuid>,
    /// Until when the qualification holds (RFC 3339), if it expires.
    #[schema(format = DateTime, max_length = 64)]
    pub valid_until: Option<String>,
}

/// A study and what it found.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Study {
    pub id: String,
    pub station: String,
    /// The inspections it was run over.
    pub inspections: Vec<String>,
    pub created_at: String,
    /// The correction, the uncertainty components and the gauge figures.
    pub qualification: Qualification,
}

/// A station's masters and the qualification of the study in force (none before the first).
async fn masters_and_study(
    state: &AppState,
    row: &StationRow,
) -> Result<(Vec<crate::service::store::MasterRow>, Option<Qualification>), ApiError> {
    let masters = state.store.masters(&row.name).await?;
    let qualification = match &row.study_id {
        Some(id) => Some(study_qualification(&state.store.study(&row.name, id).await?)?),
        None => None,
    };
    Ok((masters, qualification))
}

/// The station's status and reason as they stand now: a qualification past its `valid_until`
/// reads `suspended` (the worker refuses it) though nothing was written.
fn status_now(row: &StationRow, qualification: Option<&Qualification>) -> (String, Option<String>) {
    if row.status == "qualified"
        && let Some(reason) =
            qualification.and_then(|q| crate::service::wire::qualification_expired(&row.name, q, now_ms()))
    {
        return ("suspended".into(), Some(reason));
    }
    (row.status.clone(), row.status_reason.clone())
}

async fn station_out(state: &AppState, row: StationRow) -> Result<StationRecord, ApiError> {
    let (masters, qualification) = masters_and_study(state, &row).await?;
    let (status, status_reason) = status_now(&row, qualification.as_ref());
    Ok(StationRecord {
        masters: masters
            .into_iter()
            .map(|m| Master {
                points: serde_json::from_str::<Vec<serde_json::Value>>(&m.certificate_json).map_or(0, |v| v.len()),
                serial: m.serial,
                instrument: m.instrument,
                calibrated_at: m.calibrated_at,
                certificate_uncertainty_um: 1e3 * m.uncertainty_mm,
                uploaded_at: rfc3339(m.uploaded_at),
            })
            .collect(),
        fingerprint: qualification.as_ref().map(|q| q.fingerprint.clone()),
        expanded_uncertainty_um: qualification.as_ref().map(|q| q.uncertainty.expanded_um),
        qualified_until: qualification.and_then(|q| q.valid_until),
        name: row.name,
        description: row.description,
        status,
        status_reason,
        study: row.study_id,
        created_at: rfc3339(row.created_at),
        updated_at: rfc3339(row.updated_at),
    })
}

/// Create a station (unqualified).
#[utoipa::path(
    post,
    path = "/v1/stations",
    operation_id = "create_station",
    tag = "stations",
    request_body = NewStation,
    responses(
        (status = 201, description = "Created", body = StationRecord),
        (status = 409, description = "A station of this name exists", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid name or description", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create_station(
    State(state): State<AppState>,
    body: Result<Json<NewStation>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(new) = body?;
    crate::domain::text::check_station_name(&new.name)
        .map_err(|e| ApiError::new(Code::InvalidOption, format!("name: {e}")).with_culprit("name"))?;
    if let Some(d) = &new.description {
        crate::domain::text::check(d, 200)
            .map_err(|e| ApiError::new(Code::InvalidOption, format!("description {e}")).with_culprit("description"))?;
    }
    let Some(row) = state.store.create_station(&new.name, new.description.as_deref()).await? else {
        return Err(ApiError::new(Code::StationExists, format!("station {:?} exists", new.name)).with_culprit("name"));
    };
    let location = format!("/v1/stations/{}", row.name);
    let station = station_out(&state, row).await?;
    Ok((StatusCode::CREATED, [(axum::http::header::LOCATION, location)], super::common::Rounded(station))
        .into_response())
}

/// The stations, by name.
#[utoipa::path(
    get,
    path = "/v1/stations",
    operation_id = "list_stations",
    tag = "stations",
    responses((status = 200, description = "The stations", body = StationList))
)]
pub async fn list_stations(State(state): State<AppState>) -> Result<super::common::Rounded<StationList>, ApiError> {
    let mut items = Vec::new();
    for row in state.store.stations().await? {
        items.push(station_out(&state, row).await?);
    }
    Ok(super::common::Rounded(StationList { items }))
}

/// A station: status, the study in force, its fingerprint and U, its masters; or its page.
#[utoipa::path(
    get,
    path = "/v1/stations/{name}",
    operation_id = "get_station",
    tag = "stations",
    params(("name" = String, Path, description = "Station name"), StationFormatQuery),
    responses(
        (status = 200, description = "The station; with `?format=html` or `Accept: text/html`, its page \
            (fingerprint, uncertainty, the bias per thread before and after the correction, the gauge figures, \
            the control charts of its check runs)",
            content((StationRecord = "application/json"), (String = "text/html"))),
        (status = 404, description = "No such station", body = Problem, content_type = "application/problem+json"),
        (status = 406, description = "Neither JSON nor HTML acceptable (`format` or `Accept`)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_station(
    State(state): State<AppState>,
    Path(name): Path<String>,
    headers: axum::http::HeaderMap,
    query: Result<axum::extract::Query<StationFormatQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let axum::extract::Query(q) = query?;
    let row = state.store.station(&name).await.map_err(|e| station_not_found(e, &name))?;
    let (format, _) = super::http::negotiate(&headers, q.format.as_deref(), &STATION_FORMATS)?;
    if format == "json" {
        return Ok(super::common::Rounded(station_out(&state, row).await?).into_response());
    }
    let (masters, qualification) = masters_and_study(&state, &row).await?;
    // The study is read once, above: only its checks here.
    let checks = super::station_reads::checks_of(&state, &row).await?;
    let (status, status_reason) = status_now(&row, qualification.as_ref());
    let page = crate::export::html::station::station_page(&crate::export::html::station::StationPage {
        name: &row.name,
        description: row.description.as_deref(),
        status: &status,
        status_reason: status_reason.as_deref(),
        masters: masters
            .iter()
            .map(|m| (m.serial.clone(), m.instrument.clone(), m.calibrated_at.clone(), 1e3 * m.uncertainty_mm))
            .collect(),
        qualification: qualification.as_ref(),
        checks: checks
            .iter()
            .map(|c| crate::export::html::station::CheckLine {
                seq: c.seq,
                master: &c.master,
                inspection: &c.inspection,
                points: &c.points,
                violation: c.violation.as_ref(),
            })
            .collect(),
    });
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (axum::http::header::CACHE_CONTROL, "no-cache"),
            (axum::http::header::VARY, "Accept"),
            (axum::http::header::CONTENT_SECURITY_POLICY, crate::export::html::content_security_policy()),
        ],
        page,
    )
        .into_response())
}

#[derive(Clone, Debug, Default, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct StationFormatQuery {
    #[param(schema_with = station_formats)]
    pub format: Option<String>,
}

const STATION_FORMATS: [(&str, &str); 2] = [("json", "application/json"), ("html", "text/html")];

fn station_formats() -> utoipa::openapi::schema::Object {
    super::common::one_of(STATION_FORMATS.map(|f| f.0), "`html` for the station's page; overrides `Accept`.")
}

/// Upload a master's calibration certificate: its certified thread heights in the CMM formats
/// `PUT /v1/inspections/{id}/cmm` takes (JSON or CSV), stating `instrument`, `measured_at` (the
/// calibration date) and `uncertainty_mm` (k = 2) for every height. A master's certificate is
/// not replaced: a recalibrated master is uploaded under a new serial.
#[utoipa::path(
    put,
    path = "/v1/stations/{name}/masters/{serial}",
    operation_id = "put_master",
    tag = "stations",
    params(
        ("name" = String, Path, description = "Station name"),
        ("serial" = String, Path, description = "The master's serial (its bundles' `part.serial`)"),
    ),
    request_body(content(
        (crate::eval::cmm::CmmMeasurements = "application/json"),
        (super::common::Binary = "text/csv"),
    )),
    responses(
        (status = 201, description = "Stored", body = Master),
        (status = 404, description = "No such station", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "This master's certificate is stored already", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Neither JSON nor CSV", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Not a certificate (the field is named)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn put_master(
    State(state): State<AppState>,
    Path((name, serial)): Path<(String, String)>,
    headers: axum::http::HeaderMap,
    body: axum::body::Body,
) -> Result<Response, ApiError> {
    state.store.station(&name).await.map_err(|e| station_not_found(e, &name))?;
    crate::domain::text::check(&serial, crate::domain::text::SERIAL_CHARS)
        .map_err(|e| ApiError::new(Code::InvalidOption, format!("serial {e}")).with_culprit("serial"))?;
    let body: Bytes = axum::body::to_bytes(body, MAX_CERTIFICATE_BYTES)
        .await
        .map_err(|e| ApiError::new(Code::BodyTooLarge, format!("certificates are limited to 16 MiB ({e})")))?;
    let certificate = match super::common::json_or_csv(&headers)? {
        super::common::JsonOrCsv::Json => Certificate::from_json(&body),
        super::common::JsonOrCsv::Csv => Certificate::from_csv(&body),
    }
    .map_err(|e| ApiError::new(Code::InvalidCertificate, e.to_string()).with_culprit(e.field.clone()))?;
    let points = serde_json::to_string(&certificate.points.points).expect("points serialise");
    let stored = state
        .store
        .put_master(
            &name,
            &serial,
            &points,
            &certificate.instrument,
            &certificate.calibrated_at,
            certificate.expanded_uncertainty_mm,
        )
        .await?;
    if !stored {
        return Err(ApiError::new(
            Code::MasterExists,
            format!(
                "station {name:?} has master {serial:?} already; a recalibrated master is uploaded under a new serial"
            ),
        )
        .with_culprit("serial"));
    }
    let master = Master {
        serial,
        instrument: certificate.instrument,
        calibrated_at: certificate.calibrated_at,
        certificate_uncertainty_um: 1e3 * certificate.expanded_uncertainty_mm,
        points: certificate.points.points.len(),
        uploaded_at: rfc3339(now_ms()),
    };
    Ok((StatusCode::CREATED, super::common::Rounded(master)).into_response())
}

/// Run a qualification study (ISO 15530-3) over the masters' inspections at this station: the
/// heights against each master's certificate, the correction model chosen by its held-out error,
/// the station's uncertainty (u_cal, u_p, u_b, u_w) and the gauge figures (Cg, Cgk, %GRR, ndc).
/// The station is qualified under it at once: later inspections naming the station are corrected
/// and decided with its uncertainty.
#[utoipa::path(
    post,
    path = "/v1/stations/{name}/studies",
    operation_id = "create_study",
    tag = "stations",
    params(("name" = String, Path, description = "Station name")),
    request_body = NewStudy,
    responses(
        (status = 201, description = "The study; the station is qualified under it", body = Study),
        (status = 404, description = "No such station", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "The study cannot be run (the culprit names the inspection or master)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create_study(
    State(state): State<AppState>,
    Path(name): Path<String>,
    body: Result<Json<NewStudy>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(new) = body?;
    state.store.station(&name).await.map_err(|e| station_not_found(e, &name))?;
    if new.inspections.is_empty() || new.inspections.len() > MAX_STUDY_RUNS {
        return Err(ApiError::new(
            Code::StudyRefused,
            format!("inspections: {} given; a study takes 1–{MAX_STUDY_RUNS}", new.inspections.len()),
        )
        .with_culprit("inspections"));
    }
    if let Some(until) = &new.valid_until {
        let t = crate::service::wire::parse_rfc3339(until)
            .map_err(|e| ApiError::new(Code::StudyRefused, format!("valid_until: {e}")).with_culprit("valid_until"))?;
        if t <= now_ms() {
            return Err(ApiError::new(Code::StudyRefused, format!("valid_until: {until} has passed"))
                .with_culprit("valid_until"));
        }
    }
    let refuse = |i: usize, message: String| {
        ApiError::new(Code::StudyRefused, message).with_culprit(format!("inspections[{i}]"))
    };
    let masters = state.store.masters(&name).await?;
    if masters.is_empty() {
        return Err(ApiError::new(
            Code::StudyRefused,
            format!("station {name:?} has no master: upload a certificate first (PUT /v1/stations/{name}/masters/{{serial}})"),
        )
        .with_culprit("masters"));
    }
    let certificates = masters.iter().map(certificate_of).collect::<Result<Vec<_>, _>>()?;
    let mut runs: Vec<Vec<(String, Report)>> = vec![Vec::new(); masters.len()];
    let mut seen = std::collections::BTreeSet::new();
    for (i, id) in new.inspections.iter().enumerate() {
        let id = InspectionId::parse(&id.to_string())?.0;
        if !seen.insert(id.clone()) {
            return Err(refuse(i, format!("inspection {id} is named twice")));
        }
        let row = run_at_station(&state, &name, &id, "study", |m| refuse(i, m)).await?;
        let Some(m) = masters.iter().position(|m| row.serial.as_deref() == Some(m.serial.as_str())) else {
            let serials: Vec<&str> = masters.iter().map(|m| m.serial.as_str()).collect();
            return Err(refuse(
                i,
                format!(
                    "inspection {id} measured part {:?}, not one of the station's masters ({})",
                    row.serial.as_deref().unwrap_or("without a serial"),
                    serials.join(", ")
                ),
            ));
        };
        let report = stored_report(&state, &id).await?;
        runs[m].push((id, report));
    }
    let study_id = uuid::Uuid::now_v7().to_string();
    let (station, sid, valid_until) = (name.clone(), study_id.clone(), new.valid_until.clone());
    let serials: Vec<String> = masters.iter().map(|m| m.serial.clone()).collect();
    let qualification = tokio::task::spawn_blocking(move || {
        // Masters without runs in this study are left out of it.
        let inputs: Vec<MasterRuns> = serials
            .iter()
            .zip(&certificates)
            .zip(&runs)
            .filter(|(_, r)| !r.is_empty())
            .map(|((serial, certificate), r)| MasterRuns {
                serial: serial.clone(),
                certificate,
                runs: r.iter().map(|(id, report)| (id.clone(), report)).collect(),
            })
            .collect();
        qualify::study(&station, &sid, &inputs, 2.0, valid_until)
    })
    .await
    .map_err(ApiError::internal)?
    .map_err(|e| ApiError::new(Code::StudyRefused, e.to_string()).with_culprit(e.culprit()))?;
    let row = StudyRow {
        id: study_id,
        station: name.clone(),
        inspections_json: serde_json::to_string(&new.inspections).expect("ids serialise"),
        qualification_json: serde_json::to_string(&qualification).expect("qualification serialises"),
        created_at: now_ms(),
    };
    state.store.put_study(&row).await?;
    tracing::info!(station = %name, study = %row.id, u_um = qualification.uncertainty.expanded_um, "station qualified");
    let location = format!("/v1/stations/{name}/studies/{}", row.id);
    Ok((StatusCode::CREATED, [(axum::http::header::LOCATION, location)], super::common::Rounded(study_out(&row)?))
        .into_response())
}

fn study_out(row: &StudyRow) -> Result<Study, ApiError> {
    Ok(Study {
        id: row.id.clone(),
        station: row.station.clone(),
        inspections: serde_json::from_str(&row.inspections_json).map_err(ApiError::internal)?,
        created_at: rfc3339(row.created_at),
        qualification: study_qualification(row)?,
    })
}

/// A study and its findings.
#[utoipa::path(
    get,
    path = "/v1/stations/{name}/studies/{study}",
    operation_id = "get_study",
    tag = "stations",
    params(
        ("name" = String, Path, description = "Station name"),
        ("study" = String, Path, description = "Study id"),
    ),
    responses(
        (status = 200, description = "The study", body = Study),
        (status = 404, description = "No such station or study", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_study(
    State(state): State<AppState>,
    Path((name, study)): Path<(String, String)>,
) -> Result<super::common::Rounded<Study>, ApiError> {
    state.store.station(&name).await.map_err(|e| station_not_found(e, &name))?;
    let row = state.store.study(&name, &study).await.map_err(|e| match e {
        StoreError::NotFound => ApiError::new(Code::NotFound, format!("station {name:?} has no study {study:?}")),
        e => ApiError::from(e),
    })?;
    Ok(super::common::Rounded(study_out(&row)?))
}
