//! What the stations' and the checks' routes both read: a station's study and its chart.

use super::common::AppState;
use super::problem::ApiError;
use crate::domain::control::{ChartPoint, ControlLimits, Violation};
use crate::domain::qualification::Qualification;
use crate::eval::qualify::Certificate;
use crate::pipeline::report::Report;
use crate::problem::Code;
use crate::service::store::{CheckRow, InspectionRow, MasterRow, StationRow, Status, StoreError, StudyRow};
use crate::service::wire::rfc3339;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

pub fn station_not_found(e: StoreError, name: &str) -> ApiError {
    match e {
        StoreError::NotFound => {
            ApiError::new(Code::StationNotFound, format!("no station {name:?} (POST /v1/stations creates one)"))
        }
        e => ApiError::from(e),
    }
}

pub fn study_qualification(row: &StudyRow) -> Result<Qualification, ApiError> {
    serde_json::from_str(&row.qualification_json).map_err(ApiError::internal)
}

/// A master's certificate as stored with it.
pub fn certificate_of(m: &MasterRow) -> Result<Certificate, ApiError> {
    Ok(Certificate {
        points: crate::eval::cmm::CmmMeasurements {
            instrument: Some(m.instrument.clone()),
            measured_at: Some(m.calibrated_at.clone()),
            points: serde_json::from_str(&m.certificate_json).map_err(ApiError::internal)?,
            uncertainty_mm: None,
        },
        instrument: m.instrument.clone(),
        calibrated_at: m.calibrated_at.clone(),
        expanded_uncertainty_mm: m.uncertainty_mm,
    })
}

/// Inspection `id` as a run a study or a check (`taker`) reads at station `name`: it exists, it
/// succeeded, and it was recorded there; otherwise `refuse` with why.
pub async fn run_at_station(
    state: &AppState,
    name: &str,
    id: &str,
    taker: &str,
    refuse: impl Fn(String) -> ApiError,
) -> Result<InspectionRow, ApiError> {
    let row = state.store.inspection(id).await.map_err(|e| match e {
        StoreError::NotFound => refuse(format!("no inspection {id}")),
        e => ApiError::from(e),
    })?;
    if row.status() != Status::Succeeded {
        return Err(refuse(format!("inspection {id} is {}; a {taker} takes succeeded inspections", row.status)));
    }
    if row.station.as_deref() != Some(name) {
        return Err(refuse(format!(
            "inspection {id} was recorded at {}, not at station {name:?}",
            row.station.as_deref().map_or("no station".to_string(), |s| format!("station {s:?}"))
        )));
    }
    Ok(row)
}

/// Inspection `id`'s stored report.
pub async fn stored_report(state: &AppState, id: &str) -> Result<Report, ApiError> {
    let (json, _) = state.store.report(id).await?;
    serde_json::from_str(&json).map_err(ApiError::internal)
}

/// A check run as charted.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Check {
    /// Its place on the study's chart: 1, 2, …
    pub seq: i64,
    /// The study whose limits it was judged against.
    pub study: String,
    pub inspection: String,
    /// The master it measured.
    pub master: String,
    /// Each statistic's value and its distance from the centre line.
    pub points: Vec<ChartPoint>,
    /// The rule it broke; null in control.
    pub violation: Option<Violation>,
    pub created_at: String,
}

pub fn check_out(row: &CheckRow) -> Result<Check, ApiError> {
    Ok(Check {
        seq: row.seq,
        study: row.study_id.clone(),
        inspection: row.inspection_id.clone(),
        master: row.master.clone(),
        points: serde_json::from_str(&row.points_json).map_err(ApiError::internal)?,
        violation: row.violation_json.as_deref().map(serde_json::from_str).transpose().map_err(ApiError::internal)?,
        created_at: rfc3339(row.created_at),
    })
}

/// The study in force's limits and checks; empty before the first study.
pub async fn chart(state: &AppState, station: &StationRow) -> Result<(Vec<ControlLimits>, Vec<Check>), ApiError> {
    let Some(study_id) = &station.study_id else { return Ok((Vec::new(), Vec::new())) };
    let q = study_qualification(&state.store.study(&station.name, study_id).await?)?;
    Ok((q.control, checks_of(state, station).await?))
}

/// The checks charted under the study in force, oldest first; none before the first study.
pub async fn checks_of(state: &AppState, station: &StationRow) -> Result<Vec<Check>, ApiError> {
    let Some(study_id) = &station.study_id else { return Ok(Vec::new()) };
    state.store.checks(&station.name, study_id).await?.iter().map(check_out).collect()
}
