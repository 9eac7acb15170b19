//! The wire form of an inspection: what `GET /v1/inspections/{id}` answers, what the event stream
//! sends and what a webhook delivers, made from its stored row. A leaf of the service that the
//! API, the webhook dispatcher and the CLI share, so none of them imports another for it.

use crate::problem::Problem;
use crate::service::store::{InspectionRow, Status};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// Milliseconds since the epoch as RFC 3339 (UTC).
pub fn rfc3339(ms: i64) -> String {
    time::OffsetDateTime::from_unix_timestamp_nanos(ms as i128 * 1_000_000)
        .ok()
        .and_then(|t| t.format(&time::format_description::well_known::Rfc3339).ok())
        .unwrap_or_default()
}

/// Why station `name`'s qualification `q` no longer holds at `now_ms` (its `valid_until` has
/// passed); None while it holds. The worker refuses it then, and the station reads `suspended`.
pub fn qualification_expired(
    name: &str,
    q: &crate::domain::qualification::Qualification,
    now_ms: i64,
) -> Option<String> {
    let until = q.valid_until.as_deref()?;
    parse_rfc3339(until)
        .is_ok_and(|t| t < now_ms)
        .then(|| format!("Station {name}'s qualification {} expired at {until}: requalify it", q.study))
}

pub fn parse_rfc3339(s: &str) -> Result<i64, String> {
    time::OffsetDateTime::parse(s, &time::format_description::well_known::Rfc3339)
        .map(|t| (t.unix_timestamp_nanos() / 1_000_000) as i64)
        .map_err(|e| format!("{s:?} is not an RFC 3339 time ({e})"))
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Progress {
    /// depth, register, fuse, mesh, profile, crest_and_rules.
    pub stage: String,
    /// 0–1 within the stage.
    pub fraction: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct BundleSummary {
    pub sha256: String,
    pub size_bytes: i64,
    pub views: i64,
    pub frames: i64,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Links {
    #[serde(rename = "self")]
    pub self_: String,
    pub report: String,
    pub threads: String,
    pub mesh: String,
    pub height_map: String,
    pub all_in_focus: String,
    pub cmm: String,
    pub cmm_comparison: String,
    pub cancel: String,
}

/// An inspection job and, once it succeeded, where its results are.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Inspection {
    pub id: String,
    pub status: Status,
    /// While running: the pipeline stage and how far it is.
    pub progress: Option<Progress>,
    /// Once succeeded: the black-crest rules' verdict on the best estimates.
    #[schema(value_type = Option<crate::domain::rules::Verdict>)]
    pub verdict: Option<String>,
    /// Once succeeded: whether the result needs a person's review before its verdict is acted on
    /// (the report's `quality` says why). Null before, and for inspections that succeeded before
    /// quality was assessed.
    pub review_required: Option<bool>,
    /// Once succeeded: the decision per ISO 14253-1 (conforms, does_not_conform or
    /// indeterminate: whether the verdict holds with every measured value moved by its
    /// uncertainty). Null before, and for inspections that succeeded before it was made.
    #[schema(value_type = Option<crate::pipeline::uncertainty::Decision>)]
    pub decision: Option<String>,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    /// The station the bundle was recorded at, as the manifest or the submission named it.
    pub station: Option<String>,
    pub created_at: String,
    pub updated_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    /// Claims so far (a retry or a re-claim after a crash counts).
    pub attempts: i64,
    pub cancel_requested: bool,
    pub bundle: BundleSummary,
    /// The options the pipeline runs with (defaults filled in), under `pipeline`.
    #[schema(value_type = Object)]
    pub options: serde_json::Value,
    /// The origin (scheme, host, port) of the submission's `callback_url`, if it gave one. The URL
    /// itself is not shown: its query may hold the receiver's token, and every reader of the
    /// inspection (and every webhook endpoint) sees this resource.
    pub callback_origin: Option<String>,
    /// Why it failed: the same problem object HTTP errors use.
    pub error: Option<Problem>,
    pub links: Links,
}

impl From<InspectionRow> for Inspection {
    fn from(r: InspectionRow) -> Self {
        let status = r.status();
        let mut options: serde_json::Value = serde_json::from_str(&r.options_json).unwrap_or(serde_json::Value::Null);
        let callback_origin = options
            .as_object_mut()
            .and_then(|o| o.remove("callback_url"))
            .and_then(|url| url.as_str().and_then(|u| crate::service::webhook_settings::origin_of(u).ok()));
        let base = format!("/v1/inspections/{}", r.id);
        Self {
            progress: match (status, &r.progress_stage, r.progress_fraction) {
                (Status::Running, Some(stage), Some(fraction)) => Some(Progress { stage: stage.clone(), fraction }),
                _ => None,
            },
            status,
            verdict: r.verdict,
            review_required: r.review_required,
            decision: r.decision,
            serial: r.serial,
            connection: r.connection,
            client_reference: r.client_reference,
            station: r.station,
            created_at: rfc3339(r.created_at),
            updated_at: rfc3339(r.updated_at),
            started_at: r.started_at.map(rfc3339),
            finished_at: r.finished_at.map(rfc3339),
            attempts: r.attempts,
            cancel_requested: r.cancel_requested,
            bundle: BundleSummary {
                sha256: r.upload_sha256,
                size_bytes: r.size_bytes,
                views: r.views,
                frames: r.frames,
            },
            options,
            callback_origin,
            error: r.error_json.as_deref().and_then(|e| serde_json::from_str(e).ok()),
            links: Links {
                report: format!("{base}/report"),
                threads: format!("{base}/threads"),
                mesh: format!("{base}/mesh"),
                height_map: format!("{base}/images/height-map"),
                all_in_focus: format!("{base}/images/all-in-focus"),
                cmm: format!("{base}/cmm"),
                cmm_comparison: format!("{base}/cmm-comparison"),
                cancel: format!("{base}/cancel"),
                self_: base,
            },
            id: r.id,
        }
    }
}
