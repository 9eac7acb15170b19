//! `/v1/connections`: the API 5B connection table the rule engine uses.

use super::common::AppState;
use super::problem::{ApiError, Problem};
use crate::domain::thread::Connection;
use crate::problem::Code;
use axum::Json;
use axum::extract::{Path, Query, State};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(list_connections)).routes(routes!(get_connection))
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ConnectionQuery {
    #[param(schema_with = kind_values)]
    pub kind: Option<String>,
}

/// The `kind` filter's values: the schema states them and the handler checks them.
const KINDS: [&str; 3] = ["BC", "LC", "STC"];

fn kind_values() -> utoipa::openapi::schema::Object {
    super::common::one_of(KINDS, "BC (buttress), LC (long round) or STC (short round).")
}

#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct ConnectionList {
    #[schema(value_type = Vec<Object>)]
    pub items: Vec<Connection>,
}

/// List the API 5B casing connections (designation, family, pitch, taper, thread height and
/// tolerance, Lc, gauge plane).
#[utoipa::path(
    get,
    path = "/v1/connections",
    operation_id = "list_connections",
    tag = "connections",
    params(ConnectionQuery),
    responses(
        (status = 200, description = "The table", body = ConnectionList),
        (status = 400, description = "Unknown kind", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn list_connections(
    State(state): State<AppState>,
    query: Result<Query<ConnectionQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<ConnectionList>, ApiError> {
    let Query(q) = query?;
    let kind = q.kind;
    if let Some(k) = kind.as_deref()
        && !KINDS.contains(&k)
    {
        return Err(ApiError::new(Code::InvalidQuery, format!("kind: {k:?} is not BC, LC or STC")).with_culprit("kind"));
    }
    let items =
        state.table.all().iter().filter(|c| kind.as_deref().is_none_or(|k| c.kind.prefix() == k)).cloned().collect();
    Ok(Json(ConnectionList { items }))
}

/// One connection by designation (`BC 4-1/2`, `LC 7`, `STC 9-5/8`; URL-encode the space and slash:
/// `BC%204-1%2F2`). `BTC`/`LTC` are accepted.
#[utoipa::path(
    get,
    path = "/v1/connections/{designation}",
    operation_id = "get_connection",
    tag = "connections",
    params(("designation" = String, Path, description = "Designation, URL-encoded")),
    responses(
        (status = 200, description = "The connection", body = Object),
        (status = 404, description = "Unknown designation", body = Problem, content_type = "application/problem+json"),
    )
)]
pub async fn get_connection(
    State(state): State<AppState>,
    Path(designation): Path<String>,
) -> Result<Json<Connection>, ApiError> {
    state.table.get(&designation).cloned().map(Json).ok_or_else(|| {
        ApiError::new(
            Code::UnknownDesignation,
            format!("no connection {designation:?}; GET /v1/connections lists them"),
        )
        .with_culprit("designation")
    })
}
