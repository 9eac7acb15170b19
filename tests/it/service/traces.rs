//! OpenTelemetry trace export: the real binary with `--otlp-endpoint` pointed at a collector on
//! loopback sends OTLP/HTTP (protobuf) with the service's name, a span per request named by its
//! route, and the inspection run's span with its id.

use super::*;
use axum::body::Bytes;
use axum::http::HeaderMap;
use std::sync::{Arc, Mutex};

/// The bytes of every export the collector took, with its content type.
type Exports = Arc<Mutex<Vec<(String, Vec<u8>)>>>;

async fn start_collector() -> (Exports, String) {
    let exports: Exports = Arc::default();
    let taken = exports.clone();
    let app = axum::Router::new().route(
        "/v1/traces",
        axum::routing::post(move |headers: HeaderMap, body: Bytes| {
            let taken = taken.clone();
            async move {
                let kind = headers.get("content-type").and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
                taken.lock().unwrap().push((kind, body.to_vec()));
                axum::http::StatusCode::OK
            }
        }),
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (exports, base)
}

fn contains(haystack: &[u8], needle: &str) -> bool {
    haystack.windows(needle.len()).any(|w| w == needle.as_bytes())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn traces_reach_an_otlp_collector() {
    let (exports, collector) = start_collector().await;
    let data = tempfile::tempdir().unwrap();
    let endpoint = format!("{collector}/v1/traces");
    let (mut child, base) = start_binary(data.path(), &["--otlp-endpoint", &endpoint, "--poll-interval-ms", "50"]);
    let client = super::client();
    let id = submit_ci_to(&client, &base).await;
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        let v: Value = client.get(format!("{base}/v1/inspections/{id}")).send().await.unwrap().json().await.unwrap();
        if v["status"] == "succeeded" {
            break;
        }
        assert!(Instant::now() < deadline, "not finished: {v}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // SIGTERM: the service drains and sends the spans still batched before it exits.
    // SAFETY: a signal to our own child process.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    // Waited for without blocking a runtime thread: the child's last export goes to the collector
    // on this runtime, and a blocked worker could hold the connection's task in its own slot until
    // the child gave up on the export and exited.
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(Instant::now() < deadline, "the service did not exit within 60 s of SIGTERM");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(status.success(), "{status}");
    let exports = exports.lock().unwrap().clone();
    assert!(!exports.is_empty(), "the collector got nothing");
    assert!(
        exports.iter().all(|(kind, _)| kind == "application/x-protobuf"),
        "{:?}",
        exports.iter().map(|e| &e.0).collect::<Vec<_>>()
    );
    let all: Vec<u8> = exports.into_iter().flat_map(|(_, body)| body).collect();
    for expected in
        ["crestscan", "POST /v1/inspections", "GET /v1/inspections/{id}", "inspection", id.as_str(), "succeeded"]
    {
        assert!(contains(&all, expected), "no {expected:?} in the exported spans");
    }
}
