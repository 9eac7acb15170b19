//! The OPC UA Machine Vision server against a real client (asyncua from PyPI, driven by
//! tests/opcua/client.py): it browses the VisionSystem by OPC 40100-1's names and types, reads its
//! state, its recipe and a station, decodes the specification's structures from the server's own
//! definitions, subscribes to ResultReady events and sees a submitted inspection's, and finds it
//! again with GetResultById and GetResultListFiltered; with API keys
//! required it
//! refuses an anonymous session and a wrong key, and takes a key with `read`.

use super::*;
use crestscan::service::auth::Scope;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

fn client(mode: &str, url: &str, key: Option<&str>, secure: Option<&Path>) -> Command {
    let mut command = Command::new("python3");
    command.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/opcua/client.py")).args([mode, url]);
    if let Some(key) = key {
        command.args(["--key", key]);
    }
    if let Some(dir) = secure {
        command.arg("--secure").arg(dir);
    }
    command.stdout(Stdio::piped()).stderr(Stdio::piped());
    command
}

/// Runs the client to its end: its JSON lines and exit code (stderr in the panic where it is not
/// JSON: asyncua missing reads as such).
async fn probe(url: &str, key: Option<&str>, secure: Option<&Path>) -> (Vec<Value>, i32) {
    let mut command = client("probe", url, key, secure);
    let out = tokio::task::spawn_blocking(move || command.output().unwrap()).await.unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    let lines = text
        .lines()
        .map(|l| {
            serde_json::from_str(l).unwrap_or_else(|e| {
                panic!("{e}: {l}\nstderr: {} (pip install asyncua)", String::from_utf8_lossy(&out.stderr))
            })
        })
        .collect();
    (lines, out.status.code().unwrap_or(-1))
}

/// The client's next line, within 180 s.
async fn next(rx: &mut tokio::sync::mpsc::UnboundedReceiver<Value>, what: &str) -> Value {
    match tokio::time::timeout(Duration::from_secs(180), rx.recv()).await {
        Ok(Some(line)) => line,
        Ok(None) => panic!("the client ended before {what}"),
        Err(_) => panic!("no {what} within 180 s"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_opcua_client_browses_the_vision_system_and_sees_a_result_ready() {
    let app = spawn_app_with(|s| s.opcua_endpoint = Some("opc.tcp://127.0.0.1:0".into())).await;
    let url = app.opcua_url.clone().expect("the endpoint is served");
    assert!(url.starts_with("opc.tcp://127.0.0.1:") && !url.contains(":0/"), "{url}");
    let created = app.client.post(app.url("/v1/stations")).json(&serde_json::json!({"name": "line-3"})).send().await;
    assert_eq!(created.unwrap().status(), StatusCode::CREATED);

    // The server follows the events table every 0.5 s: the station appears within a few reads.
    let start = Instant::now();
    loop {
        let (lines, code) = probe(&url, None, None).await;
        assert_eq!(code, 0, "{lines:?}");
        if lines[0]["stations"] == serde_json::json!({"line-3": "unqualified"}) {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "the station never appeared: {lines:?}");
    }

    // The watcher reads the address space, subscribes, and waits for one ResultReady.
    let mut watcher = client("watch", &url, None, None).spawn().unwrap();
    let stdout = watcher.stdout.take().unwrap();
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<Value>();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(serde_json::from_str(&line).unwrap_or(Value::String(line)));
        }
    });
    let browsed = next(&mut rx, "address space").await;
    // The companion specification's NodeSet is loaded: its types, its state nodes, its names.
    let mv = browsed["namespaces"]["machine_vision"].as_u64().expect("OPC 40100-1's namespace is served");
    assert_ne!(browsed["namespaces"]["crestscan"].as_u64(), Some(mv), "{browsed}");
    assert_eq!(browsed["type"], format!("{mv}:VisionSystemType"), "{browsed}");
    assert_eq!(browsed["machine_type"], format!("{mv}:VisionStateMachineType"), "{browsed}");
    let children: Vec<String> =
        ["ConfigurationManagement", "RecipeManagement", "ResultManagement", "VisionStateMachine"]
            .iter()
            .map(|name| format!("{mv}:{name}"))
            .collect();
    assert_eq!(browsed["children"], serde_json::json!(children), "{browsed}");
    assert_eq!(browsed["state"], "Operational", "{browsed}");
    assert_eq!(browsed["state_node"], format!("{mv}:Operational"), "{browsed}");
    assert_eq!(browsed["state_number"], 4, "{browsed}");
    assert_eq!(browsed["execution"], "Ready", "{browsed}");
    let recipe: crestscan::pipeline::PipelineOptions = serde_json::from_value(browsed["recipe"].clone()).unwrap();
    assert_eq!(recipe, crestscan::pipeline::PipelineOptions::default());
    assert_eq!(browsed["stations"], serde_json::json!({"line-3": "unqualified"}), "{browsed}");
    assert_eq!(next(&mut rx, "subscription").await, serde_json::json!({"subscribed": true}));

    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let row = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(row["status"], "succeeded");
    let event = next(&mut rx, "ResultReady event").await;
    let event = &event["event"];
    assert_eq!(event["EventType"]["Identifier"], "ThreadResultReadyEventType", "{event}");
    // OPC 40100-1's fields, its structures decoded by the client from the server's definitions.
    assert_eq!(event["ResultId"], serde_json::json!({"Id": id}), "{event}");
    assert_eq!(event["JobId"], serde_json::json!({"Id": id}), "{event}");
    assert_eq!(event["InternalRecipeId"]["Id"], "default", "{event}");
    assert_eq!(event["InternalRecipeId"]["HashAlgorithm"], "SHA-256", "{event}");
    let options = serde_json::to_string(&crestscan::pipeline::PipelineOptions::default()).unwrap();
    let options_sha256: String =
        <sha2::Sha256 as sha2::Digest>::digest(options.as_bytes()).iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(event["InternalRecipeId"]["Hash"], options_sha256, "{event}");
    assert_eq!(event["InternalConfigurationId"]["Id"], row["station"].as_str().unwrap_or(""), "{event}");
    match row["serial"].as_str() {
        Some(serial) => assert_eq!(event["PartId"]["Id"], serial, "{event}"),
        None => assert_eq!(event["PartId"], Value::Null, "{event}"),
    }
    assert!(event["CreationTime"].is_string(), "{event}");
    assert_eq!(event["Verdict"], row["verdict"]);
    assert_eq!(event["Decision"], row["decision"]);
    assert_eq!(event["ReviewRequired"], row["review_required"]);
    // ResultStateDataType's Completed: the processing's state; the part's is the decision.
    assert_eq!(event["ResultState"], 1, "{event}");
    assert_eq!(event["IsPartial"], false);
    assert_eq!(event["SourceName"], "VisionSystem");
    assert_eq!(event["Report"], format!("/v1/inspections/{id}/report"));
    let (threads, _) = app.store().await.threads(&id).await.unwrap();
    assert!(!threads.is_empty());
    let numbers: Vec<i64> = threads.iter().map(|t| t.thread_index).collect();
    assert_eq!(event["ThreadNumbers"], serde_json::json!(numbers));
    let means: Vec<Option<f64>> = threads.iter().map(|t| t.mean_height_mm).collect();
    assert_eq!(event["ThreadMeanHeightsMm"], serde_json::json!(means));
    let findings: Vec<String> = threads.iter().map(|t| t.height_finding.clone().unwrap_or_default()).collect();
    assert_eq!(event["ThreadFindings"], serde_json::json!(findings));
    // GetResultById returns the announced result as OPC 40100-1's ResultDataType, and Error -1
    // for an id it does not hold.
    let got = next(&mut rx, "GetResultById's answer").await;
    assert_eq!(got["get_result_by_id"], id.as_str(), "{got}");
    assert_eq!(got["error"], 0, "{got}");
    let result = &got["result"];
    for field in
        ["ResultId", "JobId", "InternalRecipeId", "InternalConfigurationId", "PartId", "IsPartial", "ResultState"]
    {
        assert_eq!(result[field], event[field], "{field}: {got}");
    }
    assert_eq!(result["ProcessingTimes"]["EndTime"], event["CreationTime"], "{got}");
    let stored = app.store().await.inspection(&id).await.unwrap();
    let processing_ms = stored.finished_at.unwrap() - stored.started_at.unwrap();
    assert_eq!(result["ProcessingTimes"]["ProcessingDuration"], processing_ms as f64, "{got}");
    let unknown = next(&mut rx, "GetResultById's answer for an unknown id").await;
    assert_eq!(unknown["get_result_by_id"], "no-such-result", "{unknown}");
    assert_eq!(unknown["error"], -1, "{unknown}");
    assert_ne!(got["handle"], unknown["handle"], "each answer has its own handle");
    // GetResultListFiltered by the inspection's JobId finds it alone, and unfiltered lists the one
    // result this server announced.
    for job in [id.as_str(), ""] {
        let listed = next(&mut rx, "GetResultListFiltered's answer").await;
        assert_eq!(listed["get_result_list_filtered"], job, "{listed}");
        assert_eq!(listed["ids"], serde_json::json!([id]), "{listed}");
        assert_eq!(
            (&listed["complete"], &listed["count"], &listed["error"]),
            (&Value::Bool(true), &serde_json::json!(1), &serde_json::json!(0)),
            "{listed}"
        );
    }
    let status = tokio::task::spawn_blocking(move || watcher.wait().unwrap()).await.unwrap();
    assert!(status.success(), "{status}");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_keys_required_an_anonymous_session_is_refused_and_a_read_key_is_taken() {
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.auth = crestscan::service::config::AuthMode::Required;
        s.opcua_endpoint = Some("opc.tcp://127.0.0.1:0".into());
    })
    .await;
    let url = app.opcua_url.clone().unwrap();
    let store = app.store().await;
    let (_, read) = store.create_key("mes", &[Scope::Read]).await.unwrap();
    let (_, submit_only) = store.create_key("loader", &[Scope::Submit]).await.unwrap();
    let (revoked, revoked_token) = store.create_key("old", &[Scope::Read]).await.unwrap();
    store.revoke_key(&revoked.id).await.unwrap();

    // No anonymous policy is offered: asyncua's anonymous token is refused as not valid.
    let (lines, code) = probe(&url, None, None).await;
    assert_eq!(code, 3, "anonymous refused: {lines:?}");
    assert!(lines[0]["detail"].as_str().unwrap().contains("BadIdentityToken"), "{lines:?}");
    let wrong = format!("csk_{}_{}", "0".repeat(12), "0".repeat(64));
    for key in [wrong.as_str(), revoked_token.as_str(), submit_only.as_str(), "not-a-key"] {
        let (lines, code) = probe(&url, Some(key), None).await;
        assert_eq!(code, 3, "{key} refused: {lines:?}");
        assert!(lines[0]["detail"].as_str().unwrap().contains("BadIdentityTokenRejected"), "{lines:?}");
    }
    let (lines, code) = probe(&url, Some(&read), None).await;
    assert_eq!(code, 0, "{lines:?}");
    assert_eq!(lines[0]["state"], "Operational");
    assert_eq!(lines[0]["security_policy"], "http://opcfoundation.org/UA/SecurityPolicy#None");
    app.stop().await;
}

/// With `opcua_require_encryption` only signed and encrypted endpoints are offered, and a client's
/// certificate is refused until an operator moves it from the store's `rejected/` to `trusted/`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_encrypted_session_needs_a_client_certificate_the_operator_trusts() {
    let app = spawn_app_with(|s| {
        s.workers = 0;
        s.auth = crestscan::service::config::AuthMode::Required;
        s.opcua_endpoint = Some("opc.tcp://127.0.0.1:0".into());
        s.opcua_require_encryption = true;
    })
    .await;
    let url = app.opcua_url.clone().unwrap();
    let (_, read) = app.store().await.create_key("mes", &[Scope::Read]).await.unwrap();
    let certs = tempfile::tempdir().unwrap();

    let (lines, code) = probe(&url, Some(&read), None).await;
    assert_eq!(code, 3, "no unencrypted endpoint: {lines:?}");
    let (lines, code) = probe(&url, Some(&read), Some(certs.path())).await;
    assert_eq!(code, 3, "an unknown certificate is refused: {lines:?}");
    assert!(lines[0]["detail"].as_str().unwrap().contains("BadCertificateUntrusted"), "{lines:?}");
    let pki = app.data.join("opcua-pki");
    let rejected: Vec<_> = std::fs::read_dir(pki.join("rejected")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    let name = rejected[0].file_name().unwrap();
    std::fs::rename(&rejected[0], pki.join("trusted").join(name)).unwrap();

    let (lines, code) = probe(&url, Some(&read), Some(certs.path())).await;
    assert_eq!(code, 0, "{lines:?}");
    assert_eq!(lines[0]["security_policy"], "http://opcfoundation.org/UA/SecurityPolicy#Basic256Sha256");
    assert_eq!(lines[0]["state"], "Operational");
    app.stop().await;
}
