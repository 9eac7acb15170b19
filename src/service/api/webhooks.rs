//! The webhook deliveries' record, for admins: what was sent where, each attempt and its answer.

use super::common::AppState;
use super::problem::{ApiError, Problem};
use crate::problem::Code;
use crate::service::store::DeliveryFilter;
use crate::service::wire::rfc3339;
use axum::Json;
use axum::extract::{Query, State};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(list_deliveries))
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct DeliveryQuery {
    /// Only deliveries of this inspection.
    pub inspection_id: Option<String>,
    /// Only deliveries in this state.
    #[param(schema_with = delivery_status_values)]
    pub status: Option<String>,
    /// At most this many (1–1000, default 100), newest first.
    #[param(minimum = 1, maximum = 1000)]
    pub limit: Option<i64>,
}

const DELIVERY_STATUSES: [&str; 3] = ["pending", "delivered", "failed"];

fn delivery_status_values() -> utoipa::openapi::schema::Object {
    utoipa::openapi::schema::ObjectBuilder::new()
        .schema_type(utoipa::openapi::schema::Type::String)
        .enum_values(Some(DELIVERY_STATUSES))
        .build()
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum DeliveryStatus {
    /// Not delivered yet; attempted again at `next_attempt_at`.
    Pending,
    /// A 2xx answer came.
    Delivered,
    /// Given up: out of attempts, or its destination is no longer configured or allowed.
    Failed,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct DeliveryAttempt {
    pub attempt: i64,
    pub started_at: String,
    pub duration_ms: i64,
    /// The answer's status; null when none came (refused, timed out, not allowed).
    pub status_code: Option<i64>,
    /// Why it was not a delivery; null when it was.
    pub error: Option<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct WebhookDelivery {
    /// The `webhook-id` header, the same on every attempt.
    pub id: String,
    pub inspection_id: String,
    /// The configured endpoint's name, or `callback` (the submission's `callback_url`).
    pub endpoint: String,
    pub url: String,
    /// `inspection.succeeded`, `inspection.failed` or `inspection.canceled`.
    pub event_type: crate::service::webhooks::EventType,
    pub status: DeliveryStatus,
    pub attempts: i64,
    pub created_at: String,
    /// While pending: when it is attempted next.
    pub next_attempt_at: Option<String>,
    pub delivered_at: Option<String>,
    pub last_error: Option<String>,
    pub attempt_log: Vec<DeliveryAttempt>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct DeliveryPage {
    /// Newest first.
    pub deliveries: Vec<WebhookDelivery>,
}

/// Webhook deliveries and their attempts (admin): what was sent where, when, and what came back.
#[utoipa::path(get, path = "/v1/webhooks/deliveries", operation_id = "list_webhook_deliveries", tag = "admin",
    params(DeliveryQuery),
    responses(
        (status = 200, description = "Newest first", body = DeliveryPage),
        (status = 400, description = "Invalid query", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn list_deliveries(
    State(state): State<AppState>,
    query: Result<Query<DeliveryQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<DeliveryPage>, ApiError> {
    let Query(q) = query?;
    let limit = super::common::page_limit(q.limit, 100, 1000)?;
    if let Some(status) = q.status.as_deref().filter(|s| !DELIVERY_STATUSES.contains(s)) {
        return Err(ApiError::new(
            Code::InvalidQuery,
            format!("status: {status:?} is not one of {}", DELIVERY_STATUSES.join(", ")),
        )
        .with_culprit("status"));
    }
    let filter = DeliveryFilter { inspection_id: q.inspection_id, status: q.status, limit: limit as u32 };
    let rows = state.store.deliveries(&filter).await?;
    let deliveries = rows
        .into_iter()
        .map(|(d, attempts)| {
            let status = match d.status.as_str() {
                "delivered" => DeliveryStatus::Delivered,
                "failed" => DeliveryStatus::Failed,
                _ => DeliveryStatus::Pending,
            };
            WebhookDelivery {
                // Written by the dispatcher from EventType::as_str, so it always parses.
                event_type: crate::service::webhooks::EventType::parse(&d.event_type)
                    .unwrap_or(crate::service::webhooks::EventType::Failed),
                next_attempt_at: (status == DeliveryStatus::Pending).then(|| rfc3339(d.next_attempt_at)),
                status,
                id: d.id,
                inspection_id: d.inspection_id,
                endpoint: d.endpoint,
                url: d.url,
                attempts: d.attempts,
                created_at: rfc3339(d.created_at),
                delivered_at: d.delivered_at.map(rfc3339),
                last_error: d.last_error,
                attempt_log: attempts
                    .into_iter()
                    .map(|a| DeliveryAttempt {
                        attempt: a.attempt,
                        started_at: rfc3339(a.started_at),
                        duration_ms: a.duration_ms,
                        status_code: a.status_code,
                        error: a.error,
                    })
                    .collect(),
            }
        })
        .collect();
    Ok(Json(DeliveryPage { deliveries }))
}
