//! The learned models through the API: profile correction as a pipeline option, the report naming
//! the model by sha256, an unknown model refused at submission, a model installed in the data
//! folder's models/ used without a restart.

use super::{ci_tar, problem, spawn_app};
use reqwest::StatusCode;
use serde_json::Value;
use std::time::Duration;

async fn submit_with(app: &super::TestApp, options: &str) -> reqwest::Response {
    let form = reqwest::multipart::Form::new()
        .part("bundle", reqwest::multipart::Part::bytes(ci_tar()))
        .text("options", options.to_string());
    app.client.post(app.url("/v1/inspections")).multipart(form).send().await.unwrap()
}

/// The models a finished inspection's report names, and the report.
async fn report_models(app: &super::TestApp, response: reqwest::Response) -> (String, Value, Vec<Value>) {
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let done = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    assert_eq!(report["provenance"]["settings"]["profile"]["correction"], "on");
    let models = report["provenance"]["models"].as_array().cloned().unwrap_or_default();
    (id, report, models)
}

#[tokio::test]
async fn profile_correction_runs_through_the_api_and_names_the_model() {
    let app = spawn_app().await;
    let unknown =
        submit_with(&app, r#"{"pipeline": {"profile": {"correction": "on", "correction_model": "plant-a"}}}"#).await;
    let v = problem(unknown, StatusCode::UNPROCESSABLE_ENTITY, "unknown_model").await;
    assert_eq!(v["culprit"], "pipeline.profile.correction_model");
    assert!(v["detail"].as_str().unwrap().contains("profile-mlp"), "{v}");
    let bad = submit_with(&app, r#"{"pipeline": {"profile": {"correction": "maybe"}}}"#).await;
    problem(bad, StatusCode::UNPROCESSABLE_ENTITY, "invalid_option").await;

    let shipped = crestscan::learned::models().shipped();
    let (id, report, models) =
        report_models(&app, submit_with(&app, r#"{"pipeline": {"profile": {"correction": "on"}}}"#).await).await;
    assert_eq!(models.len(), 1);
    assert_eq!(models[0]["name"], "profile-mlp");
    assert_eq!(models[0]["sha256"], shipped[0].sha256.as_str());
    assert_eq!(models[0]["source"], "shipped");

    // CMM data makes training pairs: every measured bin with a CMM point in it, and none other.
    let pairs_url = format!("/v1/inspections/{id}/training-pairs");
    problem(app.get(&pairs_url).await, StatusCode::NOT_FOUND, "cmm_not_found").await;
    // The first five measured bins of the first thread that has five.
    let measured_of = |thread: &Value| -> Vec<(f64, f64)> {
        thread["height_mm"]["angles_deg"]
            .as_array()
            .unwrap()
            .iter()
            .zip(thread["height_mm"]["values"].as_array().unwrap())
            .filter_map(|(a, v)| Some((a.as_f64()?, v.as_f64()?)))
            .take(5)
            .collect()
    };
    let thread = report["threads"].as_array().unwrap().iter().find(|t| measured_of(t).len() == 5).expect("a thread");
    let measured = measured_of(thread);
    let mut csv = String::from("thread;angle_deg;height_mm\n");
    for (a, h) in &measured {
        let comma = |v: f64| v.to_string().replace('.', ",");
        csv += &format!("{};{};{}\n", thread["index"], comma(*a), comma(h + 0.01));
    }
    let put =
        app.client.put(app.url(&format!("/v1/inspections/{id}/cmm"))).header("content-type", "text/csv").body(csv);
    assert_eq!(put.send().await.unwrap().status(), StatusCode::OK);
    let response = app.get(&pairs_url).await;
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["content-type"], "application/x-ndjson");
    let text = response.text().await.unwrap();
    let pairs: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(!pairs.is_empty() && pairs.len() <= 5, "{}", pairs.len());
    for p in &pairs {
        assert_eq!(p["thread"], thread["index"]);
        assert_eq!(p["input"].as_array().unwrap().len(), 256);
        let (a, h) = measured.iter().find(|(a, _)| (a - p["angle_deg"].as_f64().unwrap()).abs() < 1e-9).unwrap();
        assert!((p["target_height_mm"].as_f64().unwrap() - (h + 0.01)).abs() < 1e-9, "{a}: {p}");
        assert!(p.get("target").is_none());
    }

    // A plant's refit installed while the service runs: the shipped model under another name.
    let dir = app.data.join("models");
    std::fs::create_dir_all(&dir).unwrap();
    let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    std::fs::copy(repo.join("profile-mlp.onnx"), dir.join("plant-a.onnx")).unwrap();
    std::fs::write(dir.join("plant-a.json"), r#"{"name": "plant-a", "role": "profile_correction"}"#).unwrap();
    let (_, _, models) = report_models(
        &app,
        submit_with(&app, r#"{"pipeline": {"profile": {"correction": "on", "correction_model": "plant-a"}}}"#).await,
    )
    .await;
    assert_eq!(models[0]["name"], "plant-a");
    assert_eq!(models[0]["source"], "installed");
    assert_eq!(models[0]["sha256"], shipped[0].sha256.as_str(), "the same bytes");
    app.stop().await;
}

#[tokio::test]
async fn cnn_depth_runs_through_the_api_and_names_the_model() {
    let app = spawn_app().await;
    let unknown = submit_with(&app, r#"{"pipeline": {"depth": {"method": "cnn", "model": "plant-depth"}}}"#).await;
    let v = problem(unknown, StatusCode::UNPROCESSABLE_ENTITY, "unknown_model").await;
    assert_eq!(v["culprit"], "pipeline.depth.model");
    assert!(v["detail"].as_str().unwrap().contains("depth-unet"), "{v}");
    let bad = submit_with(&app, r#"{"pipeline": {"depth": {"method": "deep"}}}"#).await;
    problem(bad, StatusCode::UNPROCESSABLE_ENTITY, "invalid_option").await;

    let response =
        submit_with(&app, r#"{"pipeline": {"depth": {"method": "cnn"}, "profile": {"correction": "off"}}}"#).await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let done = app.wait(&id, Duration::from_secs(300)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    assert_eq!(report["provenance"]["settings"]["depth"]["method"], "cnn");
    let models = report["provenance"]["models"].as_array().cloned().unwrap_or_default();
    assert_eq!(models.len(), 1, "{models:?}");
    assert_eq!((models[0]["name"].as_str(), models[0]["role"].as_str()), (Some("depth-unet"), Some("depth")));
    let depth = crestscan::learned::models().get(crestscan::learned::ModelRole::Depth, None).unwrap();
    assert_eq!(models[0]["sha256"], depth.identity.sha256.as_str());
    let timings = report["timings"].as_array().unwrap();
    assert!(timings.iter().any(|t| t["stage"] == "depth_cnn"), "{timings:?}");
}
