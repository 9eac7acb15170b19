//! The bundle contract published with the service: the manifest's JSON Schema (draft 2020-12),
//! made from the same declarations the reader parses with, so it cannot drift from the code.

use super::common::AppState;
use super::problem::Problem;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(get_manifest_schema))
}

/// The manifest's schema as a standalone JSON Schema: `Manifest` with every schema it refers to
/// under `$defs`, from the same declarations the OpenAPI document's components come from (read
/// off the types, not the document, so that this module does not import the router).
pub fn manifest_schema() -> Value {
    use utoipa::{PartialSchema, ToSchema};
    let mut collected = Vec::new();
    <crate::bundle::Manifest as ToSchema>::schemas(&mut collected);
    let mut map = serde_json::Map::new();
    for (name, schema) in collected {
        map.insert(name, serde_json::to_value(schema).expect("a schema serialises"));
    }
    map.insert(
        "Manifest".into(),
        serde_json::to_value(<crate::bundle::Manifest as PartialSchema>::schema()).expect("a schema serialises"),
    );
    let components = &Value::Object(map);
    let mut defs = serde_json::Map::new();
    let mut pending = vec!["Manifest".to_string()];
    while let Some(name) = pending.pop() {
        if defs.contains_key(&name) {
            continue;
        }
        let mut schema = components[&name].clone();
        rewrite_refs(&mut schema, &mut pending);
        defs.insert(name, schema);
    }
    let root = defs.remove("Manifest").expect("Manifest is a component");
    let mut out = json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "tag:crestscan,2026:schema/manifest/1",
        "title": "crestscan focal-stack bundle manifest (crestscan.focal-stack/1)",
    });
    for (k, v) in root.as_object().expect("an object schema") {
        out[k] = v.clone();
    }
    out["$defs"] = Value::Object(defs);
    out
}

fn rewrite_refs(schema: &mut Value, found: &mut Vec<String>) {
    match schema {
        Value::Object(map) => {
            if let Some(Value::String(r)) = map.get_mut("$ref")
                && let Some(name) = r.strip_prefix("#/components/schemas/")
            {
                found.push(name.to_string());
                *r = format!("#/$defs/{name}");
            }
            map.values_mut().for_each(|v| rewrite_refs(v, found));
        }
        Value::Array(items) => items.iter_mut().for_each(|v| rewrite_refs(v, found)),
        _ => {}
    }
}

/// The JSON Schema of a bundle's manifest.json (draft 2020-12; docs/bundle.md has the contract in
/// words). Fields it does not name are accepted and ignored, as the contract lets new optional
/// fields appear.
#[utoipa::path(get, path = "/v1/schemas/manifest", operation_id = "get_manifest_schema", tag = "operations",
    responses(
        (status = 200, description = "The schema", body = Object, content_type = "application/schema+json"),
        (status = 406, description = "Unsupported format", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn get_manifest_schema() -> Response {
    static SCHEMA: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    let body = SCHEMA.get_or_init(|| serde_json::to_vec_pretty(&manifest_schema()).expect("a schema serialises"));
    ([(header::CONTENT_TYPE, HeaderValue::from_static("application/schema+json"))], body.clone()).into_response()
}
