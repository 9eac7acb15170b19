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

async fn report_models(app: &super::TestApp, response: reqwest::Response) -> Vec<Value> {
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let id = response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let done = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let report: Value = app.get(&format!("/v1/inspections/{id}/report")).await.json().await.unwrap();
    assert_eq!(report["provenance"]["settings"]["profile"]["correction"], "on");
    report["provenance"]["models"].as_array().cloned().unwrap_or_default()
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
    let models =
        report_models(&app, submit_with(&app, r#"{"pipeline": {"profile": {"correction": "on"}}}"#).await).await;
    assert_eq!(models.len(), 1);
    assert_eq!(models[0]["name"], "profile-mlp");
    assert_eq!(models[0]["sha256"], shipped[0].sha256.as_str());
    assert_eq!(models[0]["source"], "shipped");

    // A plant's refit installed while the service runs: the shipped model under another name.
    let dir = app.data.join("models");
    std::fs::create_dir_all(&dir).unwrap();
    let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    std::fs::copy(repo.join("profile-mlp.onnx"), dir.join("plant-a.onnx")).unwrap();
    std::fs::write(dir.join("plant-a.json"), r#"{"name": "plant-a", "role": "profile_correction"}"#).unwrap();
    let models = report_models(
        &app,
        submit_with(&app, r#"{"pipeline": {"profile": {"correction": "on", "correction_model": "plant-a"}}}"#).await,
    )
    .await;
    assert_eq!(models[0]["name"], "plant-a");
    assert_eq!(models[0]["source"], "installed");
    assert_eq!(models[0]["sha256"], shipped[0].sha256.as_str(), "the same bytes");
    app.stop().await;
}
