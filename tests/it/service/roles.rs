//! Processes by role on one store: an API process that runs no job, a worker process that serves
//! only its health and metrics, and the inspection one accepts the other finishes.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_api_process_accepts_and_a_worker_process_runs_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let client = super::client();
    let (mut api, api_base) = start_binary(dir.path(), &["--role", "api"]);
    let id = submit_ci_to(&client, &api_base).await;
    // The API process runs nothing: the job waits for a worker.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let row = get_json(&client, &format!("{api_base}/v1/inspections/{id}")).await;
    assert_eq!(row["status"], "queued", "{row}");
    let ready = get_json(&client, &format!("{api_base}/readyz")).await;
    assert_eq!(ready["role"], "api", "{ready}");

    let (mut worker, worker_base) = start_binary(dir.path(), &["--role", "worker"]);
    let ready = get_json(&client, &format!("{worker_base}/readyz")).await;
    assert_eq!((ready["status"].as_str(), ready["role"].as_str()), (Some("ready"), Some("worker")), "{ready}");
    assert_eq!(client.get(format!("{worker_base}/healthz")).send().await.unwrap().status(), StatusCode::OK);
    assert!(client.get(format!("{worker_base}/metrics")).send().await.unwrap().status().is_success());
    // A worker serves no API, and says where it is.
    let response = client.get(format!("{worker_base}/v1/inspections/{id}")).send().await.unwrap();
    let problem = super::problem(response, StatusCode::NOT_FOUND, "route_not_found").await;
    assert!(problem["detail"].as_str().unwrap().contains("role worker"), "{problem}");

    let start = Instant::now();
    let done = loop {
        let row = get_json(&client, &format!("{api_base}/v1/inspections/{id}")).await;
        if row["status"] != "queued" && row["status"] != "running" {
            break row;
        }
        assert!(start.elapsed() < Duration::from_secs(120), "still {} after 120 s", row["status"]);
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(done["status"], "succeeded", "{done}");
    for child in [&mut api, &mut worker] {
        child.kill().unwrap();
        child.wait().unwrap();
    }
}

#[test]
fn a_worker_process_without_workers_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
        .args(["serve", "--bind", "127.0.0.1:0", "--role", "worker", "--workers", "0", "--data-dir"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("workers") && stderr.contains("role worker"), "{stderr}");
}

/// A `serve` process runs with few malloc arenas: it starts itself again with `MALLOC_ARENA_MAX`
/// set (one per two cores), keeping its pid, and still serves; an operator's own value is kept.
#[test]
fn serve_runs_with_few_malloc_arenas_unless_the_operator_set_them() {
    fn arenas_of(own: Option<&str>) -> Option<String> {
        let dir = tempfile::tempdir().unwrap();
        let env: Vec<(&str, &Path)> = own.map(|own| ("MALLOC_ARENA_MAX", Path::new(own))).into_iter().collect();
        let (child, _base) = start_binary_env(dir.path(), &[], &env);
        let environ = std::fs::read(format!("/proc/{}/environ", child.id())).unwrap();
        environ
            .split(|&b| b == 0)
            .find_map(|kv| kv.strip_prefix(b"MALLOC_ARENA_MAX=").map(|v| String::from_utf8_lossy(v).into_owned()))
    }
    let cores = std::thread::available_parallelism().unwrap().get();
    assert_eq!(arenas_of(None), Some((cores / 2).max(1).to_string()));
    assert_eq!(arenas_of(Some("3")).as_deref(), Some("3"));
}
