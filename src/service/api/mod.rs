//! The HTTP edge: per-resource routers (utoipa-axum, so routes and the OpenAPI document come from
//! the same declarations), merged here with the docs, the fallback and the middleware that turns
//! every error into problem+json and counts requests.

pub mod browser;
pub mod capabilities;
pub mod checks;
pub mod cmm;
pub mod common;
pub mod connections;
pub mod dashboard;
pub mod events;
pub mod health;
mod http;
pub mod ingest;
pub mod inspections;
pub mod keys;
pub mod limiter;
pub mod list;
pub mod origins;
pub mod problem;
pub mod results;
pub mod schemas;
pub mod station_reads;
pub mod stations;
pub mod submit;
pub mod webhooks;

use crate::problem::Code;
use axum::Router;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{HeaderValue, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use common::refuse;
use problem::{ApiError, PROBLEM_JSON};

pub use crate::service::wire::{parse_rfc3339, rfc3339};
pub use common::{AppState, Binary, InspectionId, Rounded, missing_inspection, one_of, page_limit};
use std::time::Instant;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_swagger_ui::SwaggerUi;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "crestscan",
        description = "Thread inspection from focal stacks: upload a bundle, poll the inspection, fetch the report, \
                       per-thread heights, mesh and images, and compare with CMM measurements. Errors are RFC 9457 \
                       problem+json with a stable `code`.",
        license(name = "MIT OR Apache-2.0"),
    ),
    tags(
        (name = "inspections", description = "Submit, list, poll and cancel inspections"),
        (name = "results", description = "Reports, per-thread tables, meshes and images of succeeded inspections"),
        (name = "cmm", description = "CMM measurements and the comparison with crestscan"),
        (name = "stations", description = "Stations, their masters and qualification studies (ISO 15530-3)"),
        (name = "connections", description = "The API 5B connection table"),
        (name = "operations", description = "Health, readiness, metrics, capabilities, the bundle manifest's schema"),
        (name = "admin", description = "API keys, the audit log and webhook deliveries (scope `admin`)"),
    ),
    modifiers(&BearerKeys),
    security(("api_key" = [])),
    components(schemas(problem::Problem, crate::bundle::Manifest))
)]
struct ApiDoc;

/// Every operation but the health probes may be refused by the key guard (with `auth =
/// required`): 401 and 403 are declared on each, so that a generated client parses them as problems.
fn document_key_refusals(doc: &mut utoipa::openapi::OpenApi) {
    use utoipa::openapi::{ContentBuilder, Ref, ResponseBuilder};
    let refusal = |description: &str| {
        ResponseBuilder::new()
            .description(description)
            .content(
                "application/problem+json",
                ContentBuilder::new().schema(Some(Ref::from_schema_name("Problem"))).build(),
            )
            .build()
    };
    for (path, item) in doc.paths.paths.iter_mut() {
        if matches!(path.as_str(), "/healthz" | "/readyz") {
            // Public: no key, and no security requirement.
            for op in [&mut item.get, &mut item.head].into_iter().flatten() {
                op.security = Some(Vec::new());
            }
            continue;
        }
        let operations =
            [&mut item.get, &mut item.post, &mut item.put, &mut item.delete, &mut item.patch, &mut item.head];
        for op in operations.into_iter().flatten() {
            let responses = &mut op.responses.responses;
            responses
                .entry("401".into())
                .or_insert_with(|| refusal("No API key, or an invalid or revoked one (`auth = required`)").into());
            responses
                .entry("403".into())
                .or_insert_with(|| refusal("The key lacks the route's scope, or the origin is not allowed").into());
        }
    }
}

/// The bearer-key scheme (`Authorization: Bearer csk_…`): with `auth = required` every route but
/// `/healthz` and `/readyz` needs a key (scopes: read, submit, admin).
struct BearerKeys;

impl utoipa::Modify for BearerKeys {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "api_key",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .description(Some(
                        "An API key (`crestscan keys create`, or `POST /v1/keys`): needed when the service runs with \
                         `auth = required`; scopes read, submit, admin",
                    ))
                    .build(),
            ),
        );
    }
}

fn api_routes() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .merge(inspections::router())
        .merge(results::router())
        .merge(cmm::router())
        .merge(connections::router())
        .merge(health::router())
        .merge(capabilities::router())
        .merge(keys::router())
        .merge(webhooks::router())
        .merge(schemas::router())
        .merge(stations::router())
        .merge(checks::router())
}

/// The OpenAPI document (what `/openapi.json` serves and `crestscan openapi` prints).
pub fn openapi() -> utoipa::openapi::OpenApi {
    let mut doc = api_routes().split_for_parts().1;
    doc.info.version = env!("CARGO_PKG_VERSION").into();
    document_key_refusals(&mut doc);
    doc
}

pub fn router(state: AppState) -> Router {
    let (routes, _) = api_routes().split_for_parts();
    routes
        .merge(SwaggerUi::new("/docs").url("/openapi.json", openapi()))
        .route("/", axum::routing::get(dashboard::dashboard))
        .fallback(route_not_found)
        // Uploads stream to disk under their own limit (max_upload_mb); small bodies are capped where read.
        .layer(DefaultBodyLimit::disable())
        .layer(tower_http::catch_panic::CatchPanicLayer::new())
        .layer(middleware::from_fn(request_head_limits))
        .layer(middleware::from_fn(unknown_query_parameters))
        .layer(middleware::from_fn_with_state(state.clone(), keys::guard))
        .layer(tower::util::option_layer(cors(&state.settings.allowed_origins)))
        .layer(middleware::from_fn_with_state(state.clone(), browser::guard))
        .layer(middleware::from_fn_with_state(state.clone(), observe))
        .with_state(state)
}

/// A worker process's routes (`role: worker`): liveness, readiness and metrics, for whatever runs
/// and scales it; every other path is a 404 that says where the API is.
pub fn operations_router(state: AppState) -> Router {
    let (routes, _) = OpenApiRouter::<AppState>::new().merge(health::router()).split_for_parts();
    routes
        .fallback(not_on_a_worker)
        .layer(tower_http::catch_panic::CatchPanicLayer::new())
        .layer(middleware::from_fn(request_head_limits))
        .layer(middleware::from_fn(unknown_query_parameters))
        .layer(middleware::from_fn_with_state(state.clone(), observe))
        .with_state(state)
}

async fn not_on_a_worker(request: Request) -> ApiError {
    ApiError::new(
        Code::RouteNotFound,
        format!(
            "no route {} {} on a worker process (role worker): it serves /healthz, /readyz and /metrics; the API is \
             served by the processes of role api or all",
            request.method(),
            request.uri().path()
        ),
    )
}

/// CORS for the `allowed_origins` setting only (none by default: a page elsewhere cannot read
/// an answer).
fn cors(origins: &[String]) -> Option<tower_http::cors::CorsLayer> {
    use tower_http::cors::{AllowOrigin, CorsLayer};
    let origins: Vec<HeaderValue> =
        origins.iter().filter_map(|o| HeaderValue::from_str(o.trim().trim_end_matches('/')).ok()).collect();
    (!origins.is_empty()).then(|| {
        CorsLayer::new()
            .allow_origin(AllowOrigin::list(origins))
            .allow_methods([axum::http::Method::GET, axum::http::Method::POST, axum::http::Method::PUT])
            .allow_headers([header::AUTHORIZATION, header::CONTENT_TYPE, header::ACCEPT])
            .expose_headers([header::LOCATION, header::ETAG, header::RETRY_AFTER])
    })
}

/// The longest URI, the most header fields and their bytes a request may carry. The HTTP layer's
/// own limits are set far above these (startup), so what passes them is refused here as
/// problem+json rather than with the HTTP layer's empty answers.
pub const MAX_URI_BYTES: usize = 8 << 10;
pub const MAX_HEADERS: usize = 100;
pub const MAX_HEADER_BYTES: usize = 64 << 10;

async fn request_head_limits(request: Request, next: Next) -> Response {
    let uri_bytes = request.uri().to_string().len();
    if uri_bytes > MAX_URI_BYTES {
        return ApiError::new(Code::UriTooLong, format!("the URI has {uri_bytes} bytes; at most {MAX_URI_BYTES}"))
            .into_response();
    }
    let headers = request.headers();
    let bytes: usize = headers.iter().map(|(name, value)| name.as_str().len() + value.len() + 4).sum();
    if headers.len() > MAX_HEADERS || bytes > MAX_HEADER_BYTES {
        return ApiError::new(
            Code::HeadersTooLarge,
            format!(
                "{} header fields of {bytes} bytes; at most {MAX_HEADERS} fields and {MAX_HEADER_BYTES} bytes",
                headers.len()
            ),
        )
        .into_response();
    }
    next.run(request).await
}

/// The query parameters each documented operation takes, by method and route, from the OpenAPI
/// document the router is built from.
fn declared_query_parameters() -> &'static std::collections::HashMap<(String, String), Vec<String>> {
    static DECLARED: std::sync::OnceLock<std::collections::HashMap<(String, String), Vec<String>>> =
        std::sync::OnceLock::new();
    DECLARED.get_or_init(|| {
        use utoipa::openapi::path::ParameterIn;
        let doc = openapi();
        let mut declared = std::collections::HashMap::new();
        for (path, item) in &doc.paths.paths {
            let operations = [
                ("GET", &item.get),
                ("POST", &item.post),
                ("PUT", &item.put),
                ("DELETE", &item.delete),
                ("PATCH", &item.patch),
                ("HEAD", &item.head),
            ];
            for (method, op) in operations {
                let Some(op) = op else { continue };
                let names = op
                    .parameters
                    .iter()
                    .flatten()
                    .filter(|p| matches!(p.parameter_in, ParameterIn::Query))
                    .map(|p| p.name.clone())
                    .collect();
                declared.insert((method.to_string(), path.clone()), names);
            }
        }
        declared
    })
}

/// Refuses a query parameter the route does not declare (400 `invalid_query` naming it), on every
/// documented route: a misspelt `?wiat=30s` would otherwise be silently ignored.
async fn unknown_query_parameters(request: Request, next: Next) -> Response {
    let Some(query) = request.uri().query().filter(|q| !q.is_empty()) else { return next.run(request).await };
    let Some(route) = request.extensions().get::<MatchedPath>().map(|m| m.as_str().to_string()) else {
        return next.run(request).await;
    };
    let method = if request.method() == axum::http::Method::HEAD { "GET" } else { request.method().as_str() };
    let Some(allowed) = declared_query_parameters().get(&(method.to_string(), route.clone())) else {
        return next.run(request).await;
    };
    let unknown = query
        .split('&')
        .map(|pair| pair.split_once('=').map_or(pair, |(k, _)| k))
        .find(|key| !key.is_empty() && !allowed.iter().any(|a| a == key))
        .map(str::to_string);
    match unknown {
        None => next.run(request).await,
        Some(key) => {
            let accepted = if allowed.is_empty() { "none".to_string() } else { allowed.join(", ") };
            let response = ApiError::new(
                Code::InvalidQuery,
                format!("unknown query parameter {key:?} for {method} {route}; it takes: {accepted}"),
            )
            .with_culprit(key)
            .into_response();
            refuse(request, response).await
        }
    }
}

async fn route_not_found(request: Request) -> ApiError {
    ApiError::new(Code::RouteNotFound, format!("no route {} {}", request.method(), request.uri().path()))
}

/// Counts the request by matched route and makes every error a problem+json with `instance`.
async fn observe(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = request.method().as_str().to_string();
    let route = request.extensions().get::<MatchedPath>().map_or("unmatched", |m| m.as_str()).to_string();
    let path = request.uri().path().to_string();
    // The request's span: what trace export (otlp_endpoint) sends, named by method and route.
    let span = tracing::info_span!(
        "request",
        otel.name = %format_args!("{method} {route}"),
        otel.kind = "server",
        http.response.status_code = tracing::field::Empty,
    );
    let response = tracing::Instrument::instrument(next.run(request), span.clone()).await;
    let response = if response.status().is_client_error() || response.status().is_server_error() {
        problem_response(response, path.clone()).await
    } else {
        response
    };
    let (status, seconds) = (response.status().as_u16(), started.elapsed().as_secs_f64());
    state.metrics.request(&method, &route, status, seconds);
    span.record("http.response.status_code", status);
    // The access log: one line a request (probes and scrapes only at debug, they come every
    // few seconds).
    if matches!(route.as_str(), "/healthz" | "/readyz" | "/metrics") {
        tracing::debug!(method, path, route, status, ms = 1e3 * seconds, "request");
    } else {
        tracing::info!(method, path, route, status, ms = 1e3 * seconds, "request");
    }
    response
}

async fn problem_response(response: Response, path: String) -> Response {
    let status = response.status();
    if let Some(error) = response.extensions().get::<ApiError>().cloned() {
        return with_problem(error.problem(Some(path)), response);
    }
    let is_problem =
        response.headers().get(header::CONTENT_TYPE).is_some_and(|v| v.as_bytes().starts_with(PROBLEM_JSON.as_bytes()));
    if is_problem {
        return response;
    }
    // The framework's own rejection (plain text): keep its text as the detail.
    let (parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, 64 << 10)
        .await
        .map(|b| String::from_utf8_lossy(&b).into_owned())
        .unwrap_or_default();
    let code = problem::code_for_status(status);
    let detail = if text.trim().is_empty() { status.canonical_reason().unwrap_or("error").to_string() } else { text };
    let mut problem = ApiError::new(code, detail).problem(Some(path));
    problem.status = status.as_u16();
    with_problem(problem, Response::from_parts(parts, axum::body::Body::empty()))
}

fn with_problem(problem: problem::Problem, response: Response) -> Response {
    let (mut parts, _) = response.into_parts();
    let body = serde_json::to_vec(&problem).expect("problem serialises");
    parts.headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    parts.headers.remove(header::CONTENT_LENGTH);
    let mut out = Response::from_parts(parts, axum::body::Body::from(body));
    *out.status_mut() = axum::http::StatusCode::from_u16(problem.status).unwrap_or(out.status());
    out.into_response()
}
