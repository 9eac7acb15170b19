//! The OpenAPI document: served, and the same as the committed file.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openapi_is_served_and_matches_the_committed_file() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let served: Value = app.get("/openapi.json").await.json().await.unwrap();
    let generated: Value = serde_json::from_str(&crestscan::service::api::openapi().to_pretty_json().unwrap()).unwrap();
    assert_eq!(served, generated);
    let committed: Value = serde_json::from_slice(
        &std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi/openapi.json"))
            .expect("openapi/openapi.json committed"),
    )
    .unwrap();
    assert!(committed == generated, "openapi/openapi.json is stale: run `cargo run -- openapi > openapi/openapi.json`");
    // Every operation has an operationId and documents its errors.
    for (path, item) in served["paths"].as_object().unwrap() {
        for (method, op) in item.as_object().unwrap() {
            assert!(op["operationId"].is_string(), "{method} {path}");
            let codes: Vec<&String> = op["responses"].as_object().unwrap().keys().collect();
            if !["/healthz", "/metrics"].contains(&path.as_str()) {
                assert!(
                    codes.iter().any(|c| c.starts_with('4') || c.starts_with('5')),
                    "{method} {path} documents no error"
                );
            }
        }
    }
    let docs = app.get("/docs/").await;
    assert_eq!(docs.status(), StatusCode::OK);
    let html = docs.text().await.unwrap();
    assert!(html.contains("swagger-ui"), "the API browser is served");
    assert!(!html.contains("https://"), "no CDN: the browser works offline");
    let ready: Value = app.get("/readyz").await.json().await.unwrap();
    assert_eq!(ready["status"], "ready");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn capabilities_state_the_envelope_the_figures_were_measured_in() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let response = app.get("/v1/capabilities").await;
    assert_eq!(response.status(), StatusCode::OK);
    let caps: Value = response.json().await.unwrap();
    let envelope = &caps["measured_envelope"];
    let pixel = &envelope["object_pixel"];
    assert_eq!(
        (pixel["min"].as_f64(), pixel["max"].as_f64(), pixel["unit"].as_str()),
        (Some(0.037), Some(0.045), Some("mm"))
    );
    for parameter in ["depth_of_field", "frame_step", "overlap"] {
        let (min, max) = (envelope[parameter]["min"].as_f64().unwrap(), envelope[parameter]["max"].as_f64().unwrap());
        assert!(min < max, "{parameter}: {envelope}");
    }
    assert_eq!(caps["coverage_factor"].as_f64(), Some(2.0));
    assert!(caps["decision_rule"].as_str().unwrap().starts_with("ISO 14253-1"), "{caps}");
    // The classes: standard (the measured envelope) first, then fine, medium and coarse tiling
    // the benchmarked object pixels, 0.12 mm pixels and 3° overlaps inside the coarse class.
    let classes = caps["station_classes"].as_array().unwrap();
    let names: Vec<&str> = classes.iter().map(|c| c["class"].as_str().unwrap()).collect();
    assert_eq!(names, ["standard", "fine", "medium", "coarse"]);
    assert_eq!(classes[0]["ranges"], caps["measured_envelope"]);
    let range = |c: &Value, p: &str| (c["ranges"][p]["min"].as_f64().unwrap(), c["ranges"][p]["max"].as_f64().unwrap());
    assert_eq!(range(&classes[1], "object_pixel").1, range(&classes[2], "object_pixel").0);
    assert_eq!(range(&classes[2], "object_pixel").1, range(&classes[3], "object_pixel").0);
    let (coarse_pixel, coarse_overlap) = (range(&classes[3], "object_pixel"), range(&classes[3], "overlap"));
    assert!(coarse_pixel.0 < 0.12 && 0.12 < coarse_pixel.1 && coarse_overlap.0 <= 3.0, "{caps}");
    assert!(classes[3]["results"].as_str().unwrap().contains("review_required"), "{caps}");
    let refused: Vec<&str> = caps["refused"].as_array().unwrap().iter().map(|r| r["field"].as_str().unwrap()).collect();
    assert_eq!(refused, ["optics.pixel_pitch_um", "views[i].frames"]);
    app.stop().await;
}

/// Where the document narrows a parameter (enums, bounds, formats), the server refuses what it
/// excludes, with the field named: the document is not looser than the server, nor the reverse
/// (scripts/schemathesis checks both ways at scale; these are the cases it first found).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_refuses_what_the_document_excludes() {
    let app = spawn_app().await;
    let response = app.submit(ci_tar(), "").await;
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&id, Duration::from_secs(300)).await["status"], "succeeded");
    let base = format!("/v1/inspections/{id}");

    for (path, status, code, culprit) in [
        ("/v1/connections?kind=bc", 400, "invalid_query", Some("kind")),
        ("/v1/inspections?status=", 400, "invalid_query", Some("status")),
        ("/v1/inspections?limit=0", 400, "invalid_query", Some("limit")),
        (&format!("{base}/threads?format=CSV"), 406, "not_acceptable", Some("format")),
        (&format!("{base}/mesh?format=ply&format=ply"), 400, "invalid_query", Some("format")),
        (&format!("{base}/report?format=json&format=json"), 400, "invalid_query", Some("format")),
        (&format!("{base}/cmm-comparison?tolerance_mm=0"), 400, "invalid_query", Some("tolerance_mm")),
        (&format!("/v1/inspections/{}", id.replace('-', "")), 404, "invalid_id", Some("id")),
        (&format!("/v1/inspections/{{{id}}}"), 404, "invalid_id", Some("id")),
    ] {
        let response = app.get(path).await;
        assert_eq!(response.status().as_u16(), status, "{path}");
        let v: Value = response.json().await.unwrap();
        assert_eq!(v["code"], code, "{path}: {v}");
        assert_eq!(v["culprit"].as_str(), culprit, "{path}: {v}");
    }
    // The exact forms the document gives are taken.
    for path in
        ["/v1/connections?kind=BC".to_string(), format!("{base}/threads?format=csv"), format!("{base}/mesh?format=glb")]
    {
        assert_eq!(app.get(&path).await.status(), StatusCode::OK, "{path}");
    }
    let cmm = |thread: u32| serde_json::json!({ "points": [{ "thread": thread, "height_mm": 1.5 }] });
    // 1001 is outside the document's range; 1000 inside it but no thread of this inspection (the
    // document says a point must name one, issue 49); 3 is one.
    for (thread, status) in
        [(1001, StatusCode::UNPROCESSABLE_ENTITY), (1000, StatusCode::UNPROCESSABLE_ENTITY), (3, StatusCode::OK)]
    {
        let response = app.client.put(app.url(&format!("{base}/cmm"))).json(&cmm(thread)).send().await.unwrap();
        assert_eq!(response.status(), status, "thread {thread}");
    }
    let response = app.client.put(app.url(&format!("{base}/cmm"))).json(&cmm(1001)).send().await.unwrap();
    let v: Value = response.json().await.unwrap();
    assert_eq!(v["culprit"], "points[0].thread", "{v}");
    app.stop().await;
}

/// Every documented operation refuses a query parameter it does not declare (400 `invalid_query`
/// naming it), and still takes the ones it declares: table-driven over the document, so a new
/// route is covered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_operation_refuses_unknown_query_parameters() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let mut checked = 0;
    for (method, path, concrete) in documented_operations() {
        let response = app
            .client
            .request(method.clone(), app.url(&format!("{concrete}?wiat=30s")))
            .header("content-type", "application/json")
            .body(if method == reqwest::Method::GET { "" } else { "{}" })
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), StatusCode::BAD_REQUEST, "{method} {path}");
        let body: Value = response.json().await.unwrap();
        assert_eq!(
            (body["code"].as_str(), body["culprit"].as_str()),
            (Some("invalid_query"), Some("wiat")),
            "{method} {path}"
        );
        checked += 1;
    }
    assert!(checked >= 24, "{checked}");
    // Declared ones pass the check.
    assert_eq!(app.get("/v1/inspections?limit=5").await.status(), StatusCode::OK);
    assert_eq!(app.get("/v1/connections?kind=BC").await.status(), StatusCode::OK);
    app.stop().await;
}

/// Where `value` departs from `schema` (a schema of `doc`'s, `$ref`s resolved): wrong types,
/// values outside an enum, missing required properties, and properties the schema does not
/// declare (the document is the contract: an answer may not carry more than it says).
fn departures(doc: &Value, schema: &Value, value: &Value, at: &str, out: &mut Vec<String>) {
    if let Some(reference) = schema["$ref"].as_str() {
        let target = match reference.strip_prefix("#/$defs/") {
            Some(name) => &doc["$defs"][name],
            None => &doc["components"]["schemas"][reference.trim_start_matches("#/components/schemas/")],
        };
        assert!(target.is_object(), "{at}: {reference} resolves to nothing");
        return departures(doc, target, value, at, out);
    }
    for key in ["oneOf", "anyOf"] {
        if let Some(options) = schema[key].as_array() {
            let fits = options.iter().any(|o| {
                let mut inner = Vec::new();
                departures(doc, o, value, at, &mut inner);
                inner.is_empty()
            });
            if !fits {
                out.push(format!("{at}: {value} fits none of {key} {schema}"));
            }
            return;
        }
    }
    if let Some(all) = schema["allOf"].as_array() {
        for s in all {
            departures(doc, s, value, at, out);
        }
    }
    let types: Vec<&str> = match &schema["type"] {
        Value::String(t) => vec![t.as_str()],
        Value::Array(ts) => ts.iter().filter_map(Value::as_str).collect(),
        _ => Vec::new(),
    };
    let kind = match value {
        Value::Null => "null",
        Value::Bool(_) => "boolean",
        Value::Number(n) if n.is_i64() || n.is_u64() => "integer",
        Value::Number(_) => "number",
        Value::String(_) => "string",
        Value::Array(_) => "array",
        Value::Object(_) => "object",
    };
    if !types.is_empty() && !types.contains(&kind) && !(kind == "integer" && types.contains(&"number")) {
        out.push(format!("{at}: a {kind} where the schema says {types:?}"));
        return;
    }
    if let Some(values) = schema["enum"].as_array()
        && !values.contains(value)
    {
        out.push(format!("{at}: {value} is not one of {values:?}"));
    }
    match value {
        Value::Array(items) => {
            for (i, item) in items.iter().enumerate() {
                departures(doc, &schema["items"], item, &format!("{at}[{i}]"), out);
            }
        }
        Value::Object(map) => {
            let properties = schema["properties"].as_object();
            for required in schema["required"].as_array().into_iter().flatten() {
                if !map.contains_key(required.as_str().unwrap()) {
                    out.push(format!("{at}: required {required} missing"));
                }
            }
            let Some(properties) = properties else { return };
            for (key, item) in map {
                match properties.get(key) {
                    Some(s) => departures(doc, s, item, &format!("{at}.{key}"), out),
                    None if schema.get("additionalProperties").is_some() => {}
                    None => out.push(format!("{at}.{key}: not declared by the schema")),
                }
            }
        }
        _ => {}
    }
}

/// The report, the thread table and the inspection a real run answers with are exactly what the
/// document declares for them: typed, every enum value among its values, nothing undeclared.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn answers_are_what_the_document_declares() {
    let app = spawn_app().await;
    let doc: Value = serde_json::from_str(&crestscan::service::api::openapi().to_pretty_json().unwrap()).unwrap();
    let created: Value = app.submit(ci_tar(), "").await.json().await.unwrap();
    let id = created["id"].as_str().unwrap();
    let inspection = app.wait(id, Duration::from_secs(300)).await;
    assert_eq!(inspection["status"], "succeeded", "{inspection}");
    let declared =
        |path: &str| doc["paths"][path]["get"]["responses"]["200"]["content"]["application/json"]["schema"].clone();
    for (path, template) in [
        (format!("/v1/inspections/{id}"), "/v1/inspections/{id}"),
        (format!("/v1/inspections/{id}/report"), "/v1/inspections/{id}/report"),
        (format!("/v1/inspections/{id}/threads"), "/v1/inspections/{id}/threads"),
        ("/v1/inspections".to_string(), "/v1/inspections"),
    ] {
        let body: Value = app.get(&path).await.json().await.unwrap();
        let schema = declared(template);
        assert!(schema.is_object() && schema != serde_json::json!({"type": "object"}), "{template}: {schema}");
        let mut out = Vec::new();
        departures(&doc, &schema, &body, template, &mut out);
        assert!(out.is_empty(), "{template} departs from its schema:\n{}", out.join("\n"));
    }
    // The checker itself finds a departure.
    let mut report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    report["decision"] = "maybe".into();
    report["threads"][0]["colour"] = "black".into();
    report.as_object_mut().unwrap().remove("verdict");
    let mut out = Vec::new();
    departures(&doc, &declared("/v1/inspections/{id}/report"), &report, "report", &mut out);
    assert_eq!(out.len(), 3, "{out:?}");
    app.stop().await;
}

/// The manifest's JSON Schema is served, is the committed file, and fits the bundles the simulator
/// writes (perspective and telecentric) while catching a broken one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_manifest_schema_is_published_and_fits_real_bundles() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let response = app.get("/v1/schemas/manifest").await;
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["content-type"], "application/schema+json");
    let schema: Value = response.json().await.unwrap();
    assert_eq!(schema["$schema"], "https://json-schema.org/draft/2020-12/schema");
    let committed: Value = serde_json::from_slice(
        &std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("openapi/manifest.schema.json"))
            .expect("openapi/manifest.schema.json committed"),
    )
    .unwrap();
    assert!(
        committed == schema,
        "openapi/manifest.schema.json is stale: run `cargo run -- openapi --manifest-schema > openapi/manifest.schema.json`"
    );
    assert!(!schema.to_string().contains("#/components/"), "standalone: every reference is under $defs");
    for preset in ["ci", "ci-telecentric"] {
        let manifest: Value =
            serde_json::from_slice(&std::fs::read(crate::common::rendered(preset).join("manifest.json")).unwrap())
                .unwrap();
        let mut out = Vec::new();
        departures(&schema, &schema, &manifest, "manifest", &mut out);
        assert!(out.is_empty(), "{preset}'s manifest departs from the schema:\n{}", out.join("\n"));
        let mut broken = manifest.clone();
        broken.as_object_mut().unwrap().remove("optics");
        broken["views"][0]["pose"]["angle_deg"] = "north".into();
        let mut out = Vec::new();
        departures(&schema, &schema, &broken, "manifest", &mut out);
        assert_eq!(out.len(), 2, "{out:?}");
    }
    app.stop().await;
}

/// Issue 49: every property of the report, and of every schema it refers to, says what it is in
/// the document (a description on the property, or on the `$ref` of an optional one).
#[test]
fn every_report_field_is_described() {
    let doc: Value = serde_json::from_str(&crestscan::service::api::openapi().to_pretty_json().unwrap()).unwrap();
    let missing = undescribed(&doc, "Report");
    assert!(missing.is_empty(), "{} report properties without a description: {}", missing.len(), missing.join(", "));
}

/// The properties of `root` and of every schema it reaches that carry no description.
fn undescribed(doc: &Value, root: &str) -> Vec<String> {
    fn refs(v: &Value, out: &mut Vec<String>) {
        match v {
            Value::Object(map) => {
                for (k, child) in map {
                    match (k.as_str(), child) {
                        ("$ref", Value::String(r)) => out.push(r.rsplit('/').next().unwrap().to_string()),
                        _ => refs(child, out),
                    }
                }
            }
            Value::Array(items) => items.iter().for_each(|i| refs(i, out)),
            _ => {}
        }
    }
    let described = |p: &Value| {
        p.get("description").is_some_and(|d| !d.as_str().unwrap_or("").trim().is_empty())
            || ["oneOf", "allOf", "anyOf"].iter().any(|k| {
                p.get(*k).and_then(Value::as_array).is_some_and(|members| {
                    members.iter().any(|m| m.get("description").is_some_and(|d| !d.as_str().unwrap_or("").is_empty()))
                })
            })
    };
    let schemas = &doc["components"]["schemas"];
    let (mut seen, mut pending, mut missing) = (std::collections::BTreeSet::new(), vec![root.to_string()], Vec::new());
    while let Some(name) = pending.pop() {
        if !seen.insert(name.clone()) {
            continue;
        }
        let schema = &schemas[&name];
        for (property, value) in schema["properties"].as_object().into_iter().flatten() {
            if !described(value) {
                missing.push(format!("{name}.{property}"));
            }
        }
        refs(schema, &mut pending);
    }
    missing.sort();
    missing
}

#[test]
fn the_description_check_finds_a_planted_undescribed_field() {
    let doc = serde_json::json!({"components": {"schemas": {
        "Report": {"properties": {"a_mm": {"type": "number", "description": "A length."},
                                  "part": {"$ref": "#/components/schemas/Part"},
                                  "maybe": {"oneOf": [{"type": "null"}, {"$ref": "#/components/schemas/Part", "description": "Optional."}]}}},
        "Part": {"properties": {"serial": {"type": "string"}}}
    }}});
    assert_eq!(undescribed(&doc, "Report"), ["Part.serial", "Report.part"]);
}
