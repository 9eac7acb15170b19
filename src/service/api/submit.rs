//! `POST /v1/inspections`: a bundle received, validated in full and recorded before its 202.

use super::common::{AppState, Binary};
use super::ingest;
use super::problem::{ApiError, Problem};
use crate::bundle::{Bundle, FrameCheck, OpenOptions};
use crate::domain::rules::ArcRule;
use crate::pipeline::PipelineOptions;
use crate::problem::{Code, ErrorCode};
use crate::service::queue::JobOptions;
use crate::service::store::files::sha256_hex;
use crate::service::store::{Inserted, InspectionRow, NewInspection};
use crate::service::wire::Inspection;
use axum::extract::{Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

/// Submission options, as query parameters or as a multipart `options` part (JSON; it wins).
#[derive(Clone, Debug, Default, Serialize, Deserialize, IntoParams, ToSchema)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct SubmitOptions {
    /// Your correlation id (MES order, station run); filterable. 1–200 characters, no control
    /// characters.
    #[param(min_length = 1, max_length = 200, pattern = r"^[^\u0000-\u001F\u007F-\u009F]*$")]
    #[schema(min_length = 1, max_length = 200, pattern = r"^[^\u0000-\u001F\u007F-\u009F]*$")]
    pub client_reference: Option<String>,
    #[param(schema_with = arc_rule_values)]
    #[schema(schema_with = arc_rule_values)]
    pub arc_rule: Option<ArcRule>,
    /// Where to POST the inspection's terminal state (a webhook signed per Standard Webhooks;
    /// docs/service.md). Its origin must be among the server's `callback_origins`, else 422
    /// `callback_not_allowed`.
    #[param(max_length = 2048)]
    #[schema(max_length = 2048)]
    pub callback_url: Option<String>,
    /// The station the bundle was recorded at (`POST /v1/stations`), over the manifest's
    /// `station`: at a qualified station its correction and uncertainty are applied. An unknown
    /// station is refused (422 `unknown_station`).
    #[param(min_length = 1, max_length = 64, pattern = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")]
    #[schema(min_length = 1, max_length = 64, pattern = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")]
    pub station: Option<String>,
    /// Pipeline options to override (JSON object, same shape as the inspection's `options.pipeline`).
    /// Only in the multipart `options` part.
    #[serde(default)]
    #[param(ignore)]
    #[schema(schema_with = pipeline_options_schema)]
    pub pipeline: Option<serde_json::Value>,
}

/// The schema of `pipeline`, built from the options' defaults and their ranges
/// ([`crate::pipeline::options::RANGES`]), so the document states the bounds the server checks:
/// every key optional, unknown keys refused, each number with its minimum, maximum and default.
fn pipeline_options_schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
    use crate::pipeline::options::RANGES;
    use utoipa::openapi::schema::{AdditionalProperties, ObjectBuilder, Schema, SchemaType, Type};
    fn node(value: &serde_json::Value, path: &str) -> Schema {
        // Single-precision defaults widen to f64 with a tail (0.45 → 0.44999998807907104): six
        // significant digits state them as written.
        let shown = match value.as_f64() {
            Some(v) if value.is_f64() => serde_json::json!(format!("{v:.6e}").parse::<f64>().unwrap_or(v)),
            _ => value.clone(),
        };
        let builder = ObjectBuilder::new().default(Some(shown));
        let built = match value {
            serde_json::Value::Object(map) => {
                let mut object = ObjectBuilder::new()
                    .schema_type(SchemaType::new(Type::Object))
                    .additional_properties(Some(AdditionalProperties::FreeForm(false)));
                for (key, child) in map {
                    let child_path = if path.is_empty() { key.clone() } else { format!("{path}.{key}") };
                    object = object.property(key, node(child, &child_path));
                }
                object
            }
            serde_json::Value::Bool(_) => builder.schema_type(SchemaType::new(Type::Boolean)),
            serde_json::Value::Number(_) => {
                let range = RANGES.iter().find(|r| r.field == path).expect("every numeric option has a range");
                let kind = if range.integer { Type::Integer } else { Type::Number };
                builder.schema_type(SchemaType::new(kind)).minimum(Some(range.min)).maximum(Some(range.max))
            }
            serde_json::Value::String(_) if path == "arc_rule" => {
                builder.schema_type(SchemaType::new(Type::String)).enum_values(Some(ArcRule::NAMES))
            }
            serde_json::Value::String(_) if path == "profile.correction" => builder
                .schema_type(SchemaType::new(Type::String))
                .enum_values(Some(["off", "on", "auto"]))
                .description(Some(
                    "Correct each pitch of profile with the seed's MLP (needs ONNX Runtime); auto: where the \
                     model's card says it helps threads of the part's family at the station's object pixel",
                )),
            serde_json::Value::String(_) if path == "depth.method" => builder
                .schema_type(SchemaType::new(Type::String))
                .enum_values(Some(["classic", "cnn"]))
                .description(Some(
                    "Depth from focus by the classical focus measure, or by the seed's U-Nets (needs ONNX Runtime) \
                     at the pixels the classical measure trusts",
                )),
            serde_json::Value::Null if path == "depth.model" => builder
                .schema_type(SchemaType::from_iter([Type::String, Type::Null]))
                .pattern(Some("^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"))
                .description(Some("A shipped or installed depth model by name; null: the shipped one")),
            serde_json::Value::Null if path == "profile.correction_model" => builder
                .schema_type(SchemaType::from_iter([Type::String, Type::Null]))
                .pattern(Some("^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"))
                .description(Some("A shipped or installed correction model by name; null: the shipped one")),
            _ => builder,
        };
        Schema::Object(built.build())
    }
    let defaults = serde_json::to_value(PipelineOptions::default()).expect("options serialise");
    let Schema::Object(mut object) = node(&defaults, "") else { unreachable!("the options are an object") };
    object.description = Some(
        "Pipeline options to override (same shape as the inspection's `options.pipeline`; keys left out keep \
         their defaults). Only in the multipart `options` part."
            .into(),
    );
    utoipa::openapi::RefOr::T(Schema::Object(object))
}

/// The multipart form of an upload. Instead of `bundle`, a `manifest` part and one part per frame
/// (named by its manifest path) may be sent.
#[derive(ToSchema)]
#[allow(dead_code)]
pub struct BundleForm {
    /// The bundle as a zip or tar archive.
    #[schema(value_type = String, format = Binary)]
    bundle: Vec<u8>,
    /// Submission options (a JSON part): `client_reference`, `arc_rule`, `callback_url`, `pipeline`.
    options: Option<SubmitOptions>,
}

/// Idempotency-Key: 1–255 visible ASCII characters.
fn idempotency_key(headers: &HeaderMap) -> Result<Option<String>, ApiError> {
    let Some(v) = headers.get("idempotency-key") else { return Ok(None) };
    let bad = || {
        ApiError::new(Code::InvalidHeader, "Idempotency-Key must be 1–255 visible ASCII characters")
            .with_culprit("Idempotency-Key")
    };
    let s = v.to_str().map_err(|_| bad())?.trim();
    if s.is_empty() || s.len() > 255 || !s.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(bad());
    }
    Ok(Some(s.to_string()))
}

fn client_reference(value: Option<String>) -> Result<Option<String>, ApiError> {
    use crate::domain::text::{self, CLIENT_REFERENCE_CHARS};
    if let Some(r) = &value {
        text::check(r, CLIENT_REFERENCE_CHARS).map_err(|e| {
            ApiError::new(
                Code::InvalidOption,
                format!("client_reference must be 1–200 characters without control characters: it {e}"),
            )
            .with_culprit("client_reference")
        })?;
    }
    Ok(value)
}

/// Deep-merges `patch` into `base`, refusing keys that `base` does not have (typos would
/// otherwise be ignored silently).
fn merge(base: &mut serde_json::Value, patch: &serde_json::Value, path: &str) -> Result<(), ApiError> {
    match (base, patch) {
        (serde_json::Value::Object(b), serde_json::Value::Object(p)) => {
            for (k, v) in p {
                let here = format!("{path}.{k}");
                let slot = b.get_mut(k).ok_or_else(|| {
                    ApiError::new(Code::InvalidOption, format!("{here}: unknown option")).with_culprit(here.clone())
                })?;
                merge(slot, v, &here)?;
            }
            Ok(())
        }
        (b, p) => {
            *b = p.clone();
            Ok(())
        }
    }
}

pub fn resolve_options(
    query: SubmitOptions,
    part: Option<&[u8]>,
    settings: &crate::service::config::Settings,
) -> Result<(Option<String>, Option<String>, JobOptions), ApiError> {
    let part: SubmitOptions = match part {
        Some(bytes) => {
            let de = &mut serde_json::Deserializer::from_slice(bytes);
            serde_path_to_error::deserialize(de).map_err(|e| {
                let field = format!("options.{}", e.path());
                ApiError::new(Code::InvalidOption, format!("{field}: {}", e.inner())).with_culprit(field)
            })?
        }
        None => SubmitOptions::default(),
    };
    let reference = client_reference(part.client_reference.or(query.client_reference))?;
    let station = part.station.or(query.station);
    if let Some(name) = &station {
        crate::domain::text::check_station_name(name)
            .map_err(|e| ApiError::new(Code::InvalidOption, format!("station: {e}")).with_culprit("station"))?;
    }
    let mut pipeline = serde_json::to_value(PipelineOptions::default()).expect("options serialise");
    if let Some(patch) = part.pipeline.as_ref() {
        if !patch.is_object() {
            return Err(ApiError::new(Code::InvalidOption, "pipeline: must be a JSON object").with_culprit("pipeline"));
        }
        merge(&mut pipeline, patch, "pipeline")?;
    }
    let mut pipeline: PipelineOptions = serde_path_to_error::deserialize(pipeline).map_err(|e| {
        let field = format!("pipeline.{}", e.path());
        ApiError::new(Code::InvalidOption, format!("{field}: {}", e.inner())).with_culprit(field)
    })?;
    if let Some(rule) = part.arc_rule.or(query.arc_rule) {
        pipeline.arc_rule = rule;
    }
    pipeline.check_ranges().map_err(|e| ApiError::of(&e))?;
    pipeline.check_model_names().map_err(|e| {
        let culprit = e.culprit().map(|c| format!("pipeline.{c}"));
        ApiError::of(&e).with_culprit(culprit.as_deref().unwrap_or("pipeline"))
    })?;
    let callback_url = part.callback_url.or(query.callback_url);
    if let Some(url) = &callback_url {
        crate::service::webhooks::callback_allowed(settings, url)
            .map_err(|e| ApiError::new(Code::CallbackNotAllowed, e).with_culprit("callback_url"))?;
    }
    Ok((reference, station, JobOptions { pipeline, callback_url }))
}

fn accepted(row: InspectionRow, replayed: bool) -> Response {
    let location = format!("/v1/inspections/{}", row.id);
    let mut response = (StatusCode::ACCEPTED, super::common::Rounded(Inspection::from(row))).into_response();
    let headers = response.headers_mut();
    headers.insert(header::LOCATION, HeaderValue::from_str(&location).expect("ids are ASCII"));
    if replayed {
        headers.insert("idempotent-replayed", HeaderValue::from_static("true"));
    }
    response
}

/// Submit a bundle for inspection.
///
/// The body is the bundle: a raw zip or tar (`application/zip`, `application/x-tar`,
/// `application/octet-stream`; a gzipped tar as `application/gzip`), or `multipart/form-data` with
/// one `bundle` part (zip/tar/tar.gz), or a
/// `manifest` part plus one part per frame named by its manifest path; an optional `options` part
/// (JSON) carries the submission options. The whole bundle is validated before the answer: a bad
/// one is a 4xx naming the field or file, and nothing is stored.
#[utoipa::path(
    post,
    path = "/v1/inspections",
    operation_id = "create_inspection",
    tag = "inspections",
    params(
        SubmitOptions,
        ("Idempotency-Key" = Option<String>, Header, pattern = "^[!-~]{1,255}$", description = "Retry-safe submission: the same key and body return the same inspection; the same key with another body is 422. 1–255 visible ASCII characters."),
    ),
    request_body(
        content(
            (Binary = "application/octet-stream"),
            (Binary = "application/zip"),
            (Binary = "application/x-tar"),
            (Binary = "application/gzip"),
            (BundleForm = "multipart/form-data"),
        ),
        description = "The bundle (docs/bundle.md)."
    ),
    responses(
        (status = 202, description = "Accepted and queued (or replayed for the same Idempotency-Key).", body = Inspection,
            headers(("Location" = String, description = "The inspection's URL"))),
        (status = 400, description = "Malformed request or multipart body", body = Problem, content_type = "application/problem+json"),
        (status = 413, description = "Body or bundle too large", body = Problem, content_type = "application/problem+json"),
        (status = 414, description = "Query string too long (the server's URI limit)", body = Problem, content_type = "application/problem+json"),
        (status = 415, description = "Unsupported Content-Type", body = Problem, content_type = "application/problem+json"),
        (status = 408, description = "The upload stalled or came too slowly (upload_idle_seconds, min_upload_kib_per_s)", body = Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid bundle, option (out of its range), callback_url not allowed, over the worker's memory budget, or Idempotency-Key reused with another body", body = Problem, content_type = "application/problem+json"),
        (status = 429, description = "Too many uploads from this client at once", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = String, description = "Seconds to wait"))),
        (status = 500, description = "Server error", body = Problem, content_type = "application/problem+json"),
        (status = 503, description = "Too many uploads at once", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = String, description = "Seconds to wait"))),
        (status = 507, description = "The server's disk cannot take the upload", body = Problem, content_type = "application/problem+json",
            headers(("Retry-After" = String, description = "Seconds to wait"))),
    )
)]
pub async fn create_inspection(
    State(state): State<AppState>,
    axum::extract::ConnectInfo(peer): axum::extract::ConnectInfo<std::net::SocketAddr>,
    query: Result<Query<SubmitOptions>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    request: Request,
) -> Result<Response, ApiError> {
    let early = query.map_err(ApiError::from).and_then(|q| Ok((q.0, idempotency_key(&headers)?)));
    let (query, key) = match early {
        Ok(ok) => ok,
        Err(e) => {
            ingest::drain(request.into_body()).await;
            return Err(e);
        }
    };
    let pass = match state.uploads.enter(peer.ip()) {
        Ok(pass) => pass,
        Err(e) => {
            ingest::drain(request.into_body()).await;
            return Err(e);
        }
    };
    let received =
        ingest::receive(request, &state.store.files, ingest::UploadRules::of(&state.settings), pass.slot()).await;
    drop(pass);
    let received = received?;
    let (reference, submitted_station, options) =
        resolve_options(query, received.options_part.as_deref(), &state.settings)?;
    // A learned part that cannot run is refused now, not found out by the worker (loading ONNX
    // Runtime the first time reads a 29 MB library: off the async threads).
    let (models, pipeline) = (state.models.clone(), options.pipeline.clone());
    tokio::task::spawn_blocking(move || pipeline.check_learned(&models))
        .await
        .map_err(|e| ApiError::new(Code::InternalError, format!("checking the learned models: {e}")))?
        .map_err(|e| match e.code() {
            // The server's own failure: its paths and library messages go to the log.
            Code::ModelUnavailable => {
                tracing::error!(error = %e, "a learned model was asked for and cannot run");
                ApiError::new(
                    Code::ModelUnavailable,
                    "this server cannot run the learned models now (ONNX Runtime or the model could not be \
                     loaded; its log says which); with pipeline.profile.correction \"off\" and \
                     pipeline.depth.method \"classic\" the classical pipeline runs",
                )
            }
            _ => {
                let culprit = e.culprit().map(|c| format!("pipeline.{c}"));
                ApiError::of(&e).with_culprit(culprit.as_deref().unwrap_or("pipeline"))
            }
        })?;
    let options_json = serde_json::to_string(&options).expect("options serialise");
    let request_sha256 = sha256_hex(
        format!(
            "{}\n{}\n{}{}",
            received.sha256,
            options_json,
            reference.as_deref().unwrap_or(""),
            submitted_station.as_deref().map(|s| format!("\nstation {s}")).unwrap_or_default()
        )
        .as_bytes(),
    );
    if let Some(key) = &key
        && let Some(existing) = state.store.by_idempotency_key(key).await?
    {
        return if existing.request_sha256 == request_sha256 {
            Ok(accepted(existing, true))
        } else {
            Err(ApiError::new(
                Code::IdempotencyKeyReused,
                format!("Idempotency-Key {key:?} was used for inspection {} with another body or options", existing.id),
            )
            .with_culprit("Idempotency-Key"))
        };
    }

    // Validate the whole bundle (manifest, optics, part, every frame's header) before accepting.
    let table = state.table.clone();
    let limits = state.settings.bundle_limits();
    let files = state.store.files.clone();
    let ingest::Received { file, sha256, size_bytes, .. } = received;
    let settings = state.settings.clone();
    let pipeline_options = options.pipeline.clone();
    let (upload, serial, connection, manifest_station, file) = tokio::task::spawn_blocking(move || {
        let bundle = Bundle::open(
            file.path(),
            &table,
            OpenOptions { limits, frame_check: FrameCheck::Headers, name: Some("the upload") },
        )?;
        crate::service::queue::check_memory(&bundle, &pipeline_options, &settings).map_err(|e| ApiError::of(&e))?;
        if !bundle.unread_fields.is_empty() {
            tracing::info!(fields = %bundle.unread_fields.join(", "), "manifest fields not read (accepted)");
        }
        let serial = bundle.manifest.part.serial.clone();
        let connection = bundle.manifest.part.connection.clone();
        let manifest_station = bundle.manifest.station.clone();
        let summary = crate::service::store::UploadInfo {
            sha256: sha256.clone(),
            size_bytes,
            views: bundle.views.len(),
            frames: bundle.frame_count(),
        };
        drop(bundle);
        // Durable now; placed under its hash inside the database transaction.
        files.prepare(&file).map_err(|e| ingest::write_failed(&e))?;
        Ok::<_, ApiError>((summary, serial, connection, manifest_station, file))
    })
    .await
    .map_err(ApiError::internal)??;

    let station = submitted_station.or(manifest_station);
    if let Some(name) = &station
        && state.store.station(name).await.is_err()
    {
        return Err(ApiError::new(
            Code::UnknownStation,
            format!("station {name:?} does not exist: create it first (POST /v1/stations)"),
        )
        .with_culprit("station"));
    }
    let new = NewInspection {
        id: uuid::Uuid::now_v7().to_string(),
        station,
        upload,
        serial,
        connection,
        client_reference: reference,
        options_json,
        idempotency_key: key,
        request_sha256,
        max_attempts: state.settings.max_attempts,
    };
    let response = match state.store.insert_inspection(&new, file).await? {
        Inserted::Created(row) => {
            tracing::info!(inspection = %row.id, bytes = new.upload.size_bytes, "accepted");
            state.wake.notify_one();
            accepted(row, false)
        }
        Inserted::Replayed(row) => accepted(row, true),
    };
    Ok(response)
}

fn arc_rule_values() -> utoipa::openapi::schema::Object {
    super::common::one_of(
        ArcRule::NAMES,
        "How the buttress 25% limit applies: per thread (default) or over the threads combined.",
    )
}
