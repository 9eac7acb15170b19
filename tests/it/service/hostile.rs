//! Requests meant to hurt the server (issue 28): each gets a clear 4xx naming what is at fault, or a
//! job that fails cleanly, and nothing half-stored.

use super::*;
use crestscan::pipeline::options::RANGES;

/// The multipart upload of the ci bundle with `options` as its options part.
fn with_options(options: &Value) -> reqwest::multipart::Form {
    reqwest::multipart::Form::new()
        .part("bundle", reqwest::multipart::Part::bytes(ci_tar()))
        .text("options", options.to_string())
}

/// `{"pipeline": {...}}` with `value` at the dotted `field`.
fn pipeline_with(field: &str, value: Value) -> Value {
    let mut root = serde_json::json!({});
    let mut slot = &mut root;
    for key in field.split('.') {
        slot = slot.as_object_mut().unwrap().entry(key).or_insert_with(|| serde_json::json!({}));
    }
    *slot = value;
    serde_json::json!({ "pipeline": root })
}

/// `value` as JSON of the option's kind (a count as an integer).
fn number(range: &crestscan::pipeline::options::OptionRange, value: f64) -> Value {
    if range.integer { Value::from(value as i64) } else { Value::from(value) }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn options_outside_their_documented_range_are_refused_by_name() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    // The two that took the server down (a 1.28 TB allocation; a loop that never ended), then one
    // past each end of every documented range, and a fraction where a count is due.
    let mut cases = vec![
        ("cell_px", Value::from(0.01)),
        ("mesh.max_vertices", Value::from(0)),
        ("depth.window_radius_px", Value::from(2.5)),
    ];
    for r in RANGES {
        cases.push((r.field, number(r, r.max + 1.0)));
        cases.push((r.field, number(r, r.min - 1.0)));
    }
    for (field, value) in cases {
        let response = app
            .client
            .post(app.url("/v1/inspections"))
            .multipart(with_options(&pipeline_with(field, value.clone())))
            .send()
            .await
            .unwrap();
        let status = response.status();
        let v: Value = response.json().await.unwrap();
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{field} = {value}: {v}");
        // A negative count fails to parse (invalid_option) before its range is checked; either
        // way the field is named.
        assert!(["option_out_of_range", "invalid_option"].contains(&v["code"].as_str().unwrap()), "{v}");
        assert_eq!(v["culprit"], format!("pipeline.{field}"), "{v}");
    }
    // Every end of every range is inside.
    for r in RANGES {
        for edge in [r.min, r.max] {
            let options = pipeline_with(r.field, number(r, edge));
            let response =
                app.client.post(app.url("/v1/inspections")).multipart(with_options(&options)).send().await.unwrap();
            let status = response.status();
            assert_eq!(status, StatusCode::ACCEPTED, "{} = {edge}: {}", r.field, response.text().await.unwrap());
        }
    }
    app.stop().await;
}

#[test]
fn the_document_states_the_ranges_the_server_checks() {
    let document: Value = serde_json::from_str(&std::fs::read_to_string("openapi/openapi.json").unwrap()).unwrap();
    let pipeline = &document["components"]["schemas"]["SubmitOptions"]["properties"]["pipeline"];
    assert_eq!(pipeline["additionalProperties"], false);
    for r in RANGES {
        let mut node = pipeline;
        for key in r.field.split('.') {
            node = &node["properties"][key];
        }
        assert_eq!(node["minimum"].as_f64(), Some(r.min), "{}", r.field);
        assert_eq!(node["maximum"].as_f64(), Some(r.max), "{}", r.field);
        assert_eq!(node["type"], if r.integer { "integer" } else { "number" }, "{}", r.field);
    }
}
