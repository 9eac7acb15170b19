//! Authentication and authorisation at the edge: the bearer-key guard every request passes
//! (scopes by route), per-key submission limits, the audit trail, and the admin routes for keys and
//! the audit log.

use super::common::AppState;
use super::problem::{ApiError, Problem};
use crate::problem::Code;
use crate::service::auth::{self, Scope};
use crate::service::config::AuthMode;
use crate::service::store::{AuditEntry, KeyRow, StoreError};
use crate::service::wire::rfc3339;
use axum::Json;
use axum::extract::{ConnectInfo, MatchedPath, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::time::Instant;
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(list_keys, create_key)).routes(routes!(revoke_key)).routes(routes!(get_audit))
}

/// Who made a request: a key (auth required), or nobody in particular (auth off).
#[derive(Clone, Debug, Default)]
pub struct Principal {
    pub key_id: Option<String>,
    pub key_name: Option<String>,
}

/// The scope a request needs; None for what anyone may call (`/healthz`, `/readyz`, CORS
/// preflights). Keys, the audit log and webhook deliveries need `admin`; every other read `read`; every other change
/// `submit`.
pub fn required_scope(method: &Method, path: &str) -> Option<Scope> {
    if method == Method::OPTIONS || matches!(path, "/healthz" | "/readyz") {
        return None;
    }
    if path == "/v1/keys" || path.starts_with("/v1/keys/") || path == "/v1/audit" || path.starts_with("/v1/webhooks") {
        return Some(Scope::Admin);
    }
    if method == Method::GET || method == Method::HEAD { Some(Scope::Read) } else { Some(Scope::Submit) }
}

fn unauthorized(code: Code, message: String) -> Response {
    let mut response = ApiError::new(code, message).with_culprit("Authorization").into_response();
    response.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"crestscan\""));
    response
}

/// The key a request presents, checked against the store.
async fn authenticate(state: &AppState, headers: &HeaderMap) -> Result<(KeyRow, Vec<Scope>), Response> {
    let Some(value) = headers.get(header::AUTHORIZATION) else {
        return Err(unauthorized(
            Code::Unauthorized,
            "this service needs an API key: send Authorization: Bearer csk_… (crestscan keys create)".into(),
        ));
    };
    // The scheme's name is case-insensitive (RFC 9110 §11.1): `bearer` and `BEARER` are Bearer.
    let token = value
        .to_str()
        .ok()
        .and_then(|v| v.split_once(' '))
        .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
        .map(|(_, token)| token.trim())
        .unwrap_or("");
    let row = match state.store.key_for_token(token).await {
        Ok(Some(row)) => row,
        Ok(None) => {
            return Err(unauthorized(
                Code::InvalidKey,
                "the API key is not valid (unknown, malformed or revoked)".into(),
            ));
        }
        Err(e) => return Err(ApiError::from(e).into_response()),
    };
    let scopes = row.scopes();
    Ok((row, scopes))
}

/// Checks the key (auth required), its scope and its submission rate, then records what the
/// audit keeps: every change, and every read of an inspection's results.
pub async fn guard(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let peer = request.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0.ip().to_string());
    let method = request.method().clone();
    let path = request.uri().path().to_string();
    let needed = required_scope(&method, &path);
    let mut principal = Principal::default();
    if state.settings.auth == AuthMode::Required
        && let Some(needed) = needed
    {
        let (row, scopes) = match authenticate(&state, request.headers()).await {
            Ok(found) => found,
            Err(response) => return super::common::refuse(request, response).await,
        };
        if !auth::allows(&scopes, needed) {
            let response = ApiError::new(
                Code::InsufficientScope,
                format!(
                    "the key {} ({}) has the scopes {}; {method} {path} needs {}",
                    row.id,
                    row.name,
                    auth::scopes_text(&scopes),
                    needed.as_str()
                ),
            )
            .with_culprit("Authorization")
            .into_response();
            return super::common::refuse(request, response).await;
        }
        let per_minute = state.settings.submissions_per_minute;
        if per_minute > 0
            && method == Method::POST
            && path == "/v1/inspections"
            && let Err(wait) = state.submissions.admit(&row.id, per_minute, Instant::now())
        {
            let mut response = ApiError::new(
                Code::TooManySubmissions,
                format!("the key {} submitted {per_minute} inspections in the last minute; retry in {wait} s", row.id),
            )
            .into_response();
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(wait));
            return super::common::refuse(request, response).await;
        }
        principal = Principal { key_id: Some(row.id), key_name: Some(row.name) };
    }
    let route = request.extensions().get::<MatchedPath>().map(|m| m.as_str().to_string());
    let response = next.run(request).await;
    if let Some(route) = route.filter(|r| audited(&method, r)) {
        let target = target_of(&path, &response);
        let entry = AuditEntry {
            key_id: principal.key_id,
            key_name: principal.key_name,
            client: peer.unwrap_or_else(|| "unknown".into()),
            action: format!("{method} {route}"),
            target,
            status: response.status().as_u16(),
        };
        // Written beside the answer, not before it: a read is not held up by the audit's write.
        let store = state.store.clone();
        tokio::spawn(async move {
            if let Err(e) = store.audit(&entry).await {
                tracing::warn!(error = %e, action = entry.action, "audit entry not written");
            }
        });
    }
    response
}

/// What the audit keeps: every change (POST, PUT, DELETE) and reads of an inspection's results;
/// not status polls, lists, event streams, health or metrics.
fn audited(method: &Method, route: &str) -> bool {
    if method != Method::GET && method != Method::HEAD {
        return route.starts_with("/v1/");
    }
    route.starts_with("/v1/inspections/{id}/") && route != "/v1/inspections/{id}/events"
}

/// The inspection or key a request was about: the path's id, or the created inspection's.
fn target_of(path: &str, response: &Response) -> Option<String> {
    let parts: Vec<&str> = path.trim_start_matches('/').split('/').collect();
    match parts.as_slice() {
        ["v1", "inspections" | "keys", id, ..] => Some((*id).to_string()),
        ["v1", "inspections"] => response
            .headers()
            .get(header::LOCATION)
            .and_then(|l| l.to_str().ok())
            .and_then(|l| l.rsplit('/').next())
            .map(str::to_string),
        _ => None,
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct ApiKey {
    /// The key's public part (`csk_<id>_…`).
    pub id: String,
    pub name: String,
    pub scopes: Vec<Scope>,
    pub created_at: String,
    pub revoked_at: Option<String>,
}

impl From<KeyRow> for ApiKey {
    fn from(row: KeyRow) -> Self {
        ApiKey {
            scopes: row.scopes(),
            id: row.id,
            name: row.name,
            created_at: rfc3339(row.created_at),
            revoked_at: row.revoked_at.map(rfc3339),
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct ApiKeys {
    pub keys: Vec<ApiKey>,
}

#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewApiKey {
    /// Who or what holds it (`mes-line-3`), 1–100 characters (surrounding spaces are trimmed).
    #[schema(min_length = 1, max_length = 100)]
    pub name: String,
    /// What it may do; at least one.
    #[schema(min_items = 1)]
    pub scopes: Vec<Scope>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CreatedApiKey {
    pub key: ApiKey,
    /// The bearer token: shown once, stored only as its hash.
    pub token: String,
}

/// The API keys (revoked ones too; never their secrets).
#[utoipa::path(get, path = "/v1/keys", operation_id = "list_keys", tag = "admin",
    responses((status = 200, description = "The keys", body = ApiKeys)))]
pub async fn list_keys(State(state): State<AppState>) -> Result<Json<ApiKeys>, ApiError> {
    Ok(Json(ApiKeys { keys: state.store.keys().await?.into_iter().map(ApiKey::from).collect() }))
}

/// Create an API key; the token is in the answer once and nowhere else.
#[utoipa::path(post, path = "/v1/keys", operation_id = "create_key", tag = "admin",
    request_body = NewApiKey,
    responses(
        (status = 201, description = "Created", body = CreatedApiKey),
        (status = 400, description = "Malformed JSON body", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not application/json", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid name or scopes", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn create_key(
    State(state): State<AppState>,
    body: Result<Json<NewApiKey>, axum::extract::rejection::JsonRejection>,
) -> Result<(StatusCode, Json<CreatedApiKey>), ApiError> {
    let Json(new) = body?;
    let name = auth::key_name(&new.name).map_err(|e| ApiError::new(Code::InvalidOption, e).with_culprit("name"))?;
    let scopes =
        auth::scope_set(new.scopes).map_err(|e| ApiError::new(Code::InvalidOption, e).with_culprit("scopes"))?;
    let (row, token) = state.store.create_key(name, &scopes).await?;
    tracing::info!(key = row.id, name = row.name, scopes = row.scopes, "API key created");
    Ok((StatusCode::CREATED, Json(CreatedApiKey { key: row.into(), token })))
}

/// Revoke an API key at once (it stays listed, with `revoked_at`).
#[utoipa::path(delete, path = "/v1/keys/{id}", operation_id = "revoke_key", tag = "admin",
    params(("id" = String, Path, description = "The key's id")),
    responses(
        (status = 200, description = "Revoked", body = ApiKey),
        (status = 404, description = "No such key", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn revoke_key(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<ApiKey>, ApiError> {
    let row = state.store.revoke_key(&id).await.map_err(|e| match e {
        StoreError::NotFound => ApiError::new(Code::NotFound, format!("no API key {id}")),
        other => other.into(),
    })?;
    tracing::info!(key = row.id, name = row.name, "API key revoked");
    Ok(Json(row.into()))
}

#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct AuditQuery {
    /// At most this many entries (1–1000, default 100).
    #[param(minimum = 1, maximum = 1000)]
    pub limit: Option<i64>,
    /// Entries before this sequence number (the previous page's `next_before`).
    pub before: Option<i64>,
    /// Only entries about this inspection or key.
    pub target: Option<String>,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct AuditRecord {
    pub seq: i64,
    pub at: String,
    pub key_id: Option<String>,
    pub key_name: Option<String>,
    /// The client's address.
    pub client: String,
    /// Method and route: `POST /v1/inspections`, `GET /v1/inspections/{id}/report`, ...
    pub action: String,
    pub target: Option<String>,
    pub status: i64,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct AuditPage {
    /// Newest first.
    pub entries: Vec<AuditRecord>,
    pub next_before: Option<i64>,
}

/// The audit log: who created, read, cancelled or uploaded CMM data for what, and when; key changes.
#[utoipa::path(get, path = "/v1/audit", operation_id = "get_audit", tag = "admin", params(AuditQuery),
    responses(
        (status = 200, description = "Newest first", body = AuditPage),
        (status = 400, description = "Invalid query", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn get_audit(
    State(state): State<AppState>,
    query: Result<Query<AuditQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<AuditPage>, ApiError> {
    let Query(q) = query?;
    let limit = super::common::page_limit(q.limit, 100, 1000)?;
    let rows = state.store.audit_log(limit, q.before, q.target.as_deref()).await?;
    let next_before = (rows.len() as i64 == limit).then(|| rows.last().map(|r| r.seq)).flatten();
    let entries = rows
        .into_iter()
        .map(|r| AuditRecord {
            seq: r.seq,
            at: rfc3339(r.at),
            key_id: r.key_id,
            key_name: r.key_name,
            client: r.client,
            action: r.action,
            target: r.target,
            status: r.status,
        })
        .collect();
    Ok(Json(AuditPage { entries, next_before }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::api::limiter::SubmissionLimiter;
    use std::time::Duration;

    #[test]
    fn the_limiter_admits_per_minute_per_key_and_says_how_long_to_wait() {
        let limiter = SubmissionLimiter::default();
        let t0 = Instant::now();
        assert!(limiter.admit("a", 2, t0).is_ok());
        assert!(limiter.admit("a", 2, t0 + Duration::from_secs(10)).is_ok());
        assert_eq!(limiter.admit("a", 2, t0 + Duration::from_secs(20)), Err(40));
        assert!(limiter.admit("b", 2, t0 + Duration::from_secs(20)).is_ok());
        assert!(limiter.admit("a", 2, t0 + Duration::from_secs(61)).is_ok());
    }

    #[test]
    fn scopes_by_route() {
        assert_eq!(required_scope(&Method::GET, "/healthz"), None);
        assert_eq!(required_scope(&Method::OPTIONS, "/v1/inspections"), None);
        assert_eq!(required_scope(&Method::GET, "/metrics"), Some(Scope::Read));
        assert_eq!(required_scope(&Method::POST, "/v1/inspections/x/cancel"), Some(Scope::Submit));
        assert_eq!(required_scope(&Method::GET, "/v1/keys"), Some(Scope::Admin));
        assert_eq!(required_scope(&Method::DELETE, "/v1/keys/abc"), Some(Scope::Admin));
        assert_eq!(required_scope(&Method::GET, "/v1/audit"), Some(Scope::Admin));
        assert_eq!(required_scope(&Method::GET, "/v1/webhooks/deliveries"), Some(Scope::Admin));
    }
}
