//! `/v1/stations/{name}/checks`: drift control. A check run is an inspection of one of the
//! station's masters, charted against the limits the study in force set from that master's runs
//! and judged by the Western Electric rules; a violation suspends the station (no decision until
//! it is requalified) and is told to the webhook endpoints as `station.suspended`.

use super::common::{AppState, InspectionId, Rounded};
use super::problem::{ApiError, Problem};
use super::station_reads::{
    Check, certificate_of, chart, check_out, run_at_station, station_not_found, stored_report, study_qualification,
};
use crate::domain::control::{ChartPoint, ControlLimits, Violation, judge};
use crate::eval::qualify;
use crate::problem::Code;
use crate::service::store::{CheckJudgement, CheckRecorded};
use axum::Json;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(create_check, list_checks))
}

#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewCheck {
    /// A succeeded inspection of one of the study's masters at this station, not one of the
    /// study's own runs.
    pub inspection: uuid::Uuid,
}

/// A check and where it left the station.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CheckOutcome {
    pub check: Check,
    /// Whether this check suspended the station.
    pub suspended: bool,
    /// The station's status after it: `qualified` or `suspended`.
    #[schema(pattern = "^(unqualified|qualified|suspended)$")]
    pub station_status: String,
    /// Why the station is suspended, if it is.
    pub status_reason: Option<String>,
}

/// The control chart of the study in force: its limits and the checks made under it.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct ControlChart {
    pub station: String,
    /// The study in force; null before the first.
    pub study: Option<String>,
    #[schema(pattern = "^(unqualified|qualified|suspended)$")]
    pub station_status: String,
    /// Per master and statistic: the centre line and σ the study set.
    pub limits: Vec<ControlLimits>,
    /// The checks, oldest first.
    pub items: Vec<Check>,
}

/// What the `station.suspended` event says.
#[derive(Serialize)]
struct Suspension<'a> {
    station: &'a str,
    status: &'a str,
    status_reason: &'a str,
    study: &'a str,
    inspection: &'a str,
    master: &'a str,
    violation: &'a Violation,
}

fn refused(message: String, culprit: &str) -> ApiError {
    ApiError::new(Code::CheckRefused, message).with_culprit(culprit)
}

/// Chart a check run of a master: its height bias against the certificate (after the station's
/// correction) and its crest-cone radius, against the limits the study in force set from that
/// master's runs. A point that breaks a Western Electric rule (one beyond 3σ; two of three beyond
/// 2σ; four of five beyond 1σ; eight on one side) suspends the station, in the same transaction,
/// and tells the webhook endpoints (`station.suspended`); a new study lifts the suspension.
#[utoipa::path(
    post,
    path = "/v1/stations/{name}/checks",
    operation_id = "create_check",
    tag = "stations",
    params(("name" = String, Path, description = "Station name")),
    request_body = NewCheck,
    responses(
        (status = 201, description = "Charted; `suspended` says whether it suspended the station", body = CheckOutcome),
        (status = 404, description = "No such station", body = Problem, content_type = "application/problem+json"),
        (status = 409, description = "This inspection is charted already", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Not a check run of this station's study (the culprit names why)", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create_check(
    State(state): State<AppState>,
    Path(name): Path<String>,
    body: Result<Json<NewCheck>, axum::extract::rejection::JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(new) = body?;
    let station = state.store.station(&name).await.map_err(|e| station_not_found(e, &name))?;
    let Some(study_id) = station.study_id.clone() else {
        return Err(refused(
            format!("station {name:?} has no study: a check is judged against one (POST /v1/stations/{name}/studies)"),
            "station",
        ));
    };
    let study = state.store.study(&name, &study_id).await?;
    let q = study_qualification(&study)?;
    let id = InspectionId::parse(&new.inspection.to_string())?.0;
    let row = run_at_station(&state, &name, &id, "check", |m| refused(m, "inspection")).await?;
    let study_runs: Vec<String> = serde_json::from_str(&study.inspections_json).map_err(ApiError::internal)?;
    if study_runs.contains(&id) {
        return Err(refused(
            format!("inspection {id} is one of study {study_id}'s own runs; a check is a later run"),
            "inspection",
        ));
    }
    let serial = row.serial.clone().unwrap_or_default();
    let Some(master) = state.store.masters(&name).await?.into_iter().find(|m| m.serial == serial) else {
        let serials: Vec<&str> = q.masters.iter().map(|m| m.serial.as_str()).collect();
        return Err(refused(
            format!(
                "inspection {id} measured part {:?}, not one of study {study_id}'s masters ({})",
                row.serial.as_deref().unwrap_or("without a serial"),
                serials.join(", ")
            ),
            "inspection",
        ));
    };
    let certificate = certificate_of(&master)?;
    let report = stored_report(&state, &id).await?;
    let points =
        qualify::check(&q, &serial, &certificate, &id, &report).map_err(|e| refused(e.to_string(), "inspection"))?;

    let violation: std::sync::OnceLock<Violation> = std::sync::OnceLock::new();
    let settings = state.settings.clone();
    let recorded = state
        .store
        .add_check(
            &name,
            &study_id,
            &id,
            &serial,
            |earlier| {
                let seq = earlier.last().map_or(1, |c| c.seq + 1);
                // Written by this route from the same type: it reads back.
                let earlier: Vec<Vec<ChartPoint>> = earlier
                    .iter()
                    .filter(|c| c.master == serial)
                    .map(|c| serde_json::from_str(&c.points_json).unwrap_or_default())
                    .collect();
                let history: Vec<&[ChartPoint]> = earlier.iter().map(Vec::as_slice).collect();
                let broken = judge(&q.control, &serial, &history, &points);
                CheckJudgement {
                    points_json: serde_json::to_string(&points).expect("points serialise"),
                    violation: broken.map(|v| {
                        let judged = (
                            serde_json::to_string(&v).expect("a violation serialises"),
                            format!(
                                "Drift: check {seq} (inspection {id}) broke {}. Requalify the station (a new study) to lift the suspension.",
                                v.description
                            ),
                        );
                        let _ = violation.set(v);
                        judged
                    }),
                }
            },
            |reason| match violation.get() {
                Some(v) => crate::service::webhooks::station_deliveries(
                    &settings,
                    &Suspension {
                        station: &name,
                        status: "suspended",
                        status_reason: reason,
                        study: &study_id,
                        inspection: &id,
                        master: &serial,
                        violation: v,
                    },
                ),
                None => Vec::new(),
            },
        )
        .await?;
    let (row, suspended) = match recorded {
        CheckRecorded::Charted { row, suspended } => (row, suspended),
        CheckRecorded::Exists => {
            return Err(ApiError::new(
                Code::CheckExists,
                format!("inspection {id} is charted under study {study_id} already"),
            )
            .with_culprit("inspection"));
        }
        CheckRecorded::StudyChanged => {
            return Err(refused(
                format!("station {name:?} was requalified while this check was judged: post it again"),
                "station",
            ));
        }
    };
    if suspended {
        tracing::warn!(station = %name, study = %study_id, inspection = %id, "station suspended by its drift control");
    }
    let after = state.store.station(&name).await?;
    let outcome = CheckOutcome {
        check: check_out(&row)?,
        suspended,
        station_status: after.status,
        status_reason: after.status_reason,
    };
    Ok((StatusCode::CREATED, Rounded(outcome)).into_response())
}

/// The control chart of the study in force: its limits and the checks charted under it.
#[utoipa::path(
    get,
    path = "/v1/stations/{name}/checks",
    operation_id = "list_checks",
    tag = "stations",
    params(("name" = String, Path, description = "Station name")),
    responses(
        (status = 200, description = "The chart", body = ControlChart),
        (status = 404, description = "No such station", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn list_checks(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Rounded<ControlChart>, ApiError> {
    let station = state.store.station(&name).await.map_err(|e| station_not_found(e, &name))?;
    let (limits, items) = chart(&state, &station).await?;
    Ok(Rounded(ControlChart {
        station: station.name,
        study: station.study_id,
        station_status: station.status,
        limits,
        items,
    }))
}
