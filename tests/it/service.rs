//! The service over real HTTP: the real app on a loopback port with a fresh SQLite file, driven by
//! reqwest; and the real binary, killed with SIGKILL and restarted.

use crate::common::{ci_bundle, walk};
use crestscan::service::config::Settings;
use crestscan::sim::Truth;
use crestscan::service::startup::Application;
use reqwest::StatusCode;
use serde_json::Value;
use std::path::Path;
use std::time::{Duration, Instant};

pub struct TestApp {
    pub base: String,
    pub client: reqwest::Client,
    pub data: std::path::PathBuf,
    dir: Option<tempfile::TempDir>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    server: Option<tokio::task::JoinHandle<()>>,
}

impl TestApp {
    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub async fn get(&self, path: &str) -> reqwest::Response {
        self.client.get(self.url(path)).send().await.unwrap()
    }

    pub async fn submit(&self, body: Vec<u8>, query: &str) -> reqwest::Response {
        self.client
            .post(self.url(&format!("/v1/inspections{query}")))
            .header("content-type", "application/x-tar")
            .body(body)
            .send()
            .await
            .unwrap()
    }

    /// Polls until the inspection is terminal.
    pub async fn wait(&self, id: &str, timeout: Duration) -> Value {
        let start = Instant::now();
        loop {
            let v: Value = self.get(&format!("/v1/inspections/{id}")).await.json().await.unwrap();
            if ["succeeded", "failed", "canceled"].contains(&v["status"].as_str().unwrap()) {
                return v;
            }
            assert!(start.elapsed() < timeout, "inspection {id} still {} after {timeout:?}", v["status"]);
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Graceful shutdown; returns the data directory (still on disk while held).
    pub async fn stop(mut self) -> Option<tempfile::TempDir> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(h) = self.server.take() {
            h.await.unwrap();
        }
        self.dir.take()
    }

    pub async fn store(&self) -> crestscan::service::store::Store {
        open_store(&self.data).await
    }

    pub fn uploads(&self) -> usize {
        let dir = self.data.join("uploads");
        if dir.exists() { walk(&dir).len() } else { 0 }
    }
}

pub fn test_settings(data: &Path) -> Settings {
    Settings {
        bind: "127.0.0.1:0".parse().unwrap(),
        data_dir: data.to_path_buf(),
        lease_seconds: 2.0,
        heartbeat_seconds: 0.2,
        poll_interval_ms: 50,
        shutdown_grace_seconds: 5.0,
        log: "warn".into(),
        ..Settings::default()
    }
}

pub async fn open_store(data: &Path) -> crestscan::service::store::Store {
    crestscan::service::store::Store::open(&data.join("crestscan.db"), &data.join("uploads"), &data.join("tmp")).await.unwrap()
}

/// Starts the real application on port 0 with a fresh data directory.
pub async fn spawn_app_with(edit: impl FnOnce(&mut Settings)) -> TestApp {
    let dir = tempfile::tempdir().unwrap();
    let mut app = spawn_app_in(dir.path(), edit).await;
    app.dir = Some(dir);
    app
}

/// Starts the real application on port 0 on an existing data directory.
pub async fn spawn_app_in(data: &Path, edit: impl FnOnce(&mut Settings)) -> TestApp {
    crestscan::service::telemetry::init_logging("warn");
    let mut settings = test_settings(data);
    edit(&mut settings);
    let app = Application::build(settings).await.unwrap();
    let base = format!("http://{}", app.address());
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(async move {
        app.run_until(async move {
            let _ = rx.await;
        })
        .await
        .unwrap();
    });
    TestApp {
        base,
        client: reqwest::Client::new(),
        data: data.to_path_buf(),
        dir: None,
        stop: Some(tx),
        server: Some(server),
    }
}

pub async fn spawn_app() -> TestApp {
    spawn_app_with(|_| {}).await
}

/// The ci bundle (without truth/) as a tar archive.
pub fn ci_tar() -> Vec<u8> {
    bundle_tar(ci_bundle(), &|_| true)
}

pub fn bundle_tar(dir: &Path, keep: &dyn Fn(&str) -> bool) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for file in walk(dir) {
        let rel = file.strip_prefix(dir).unwrap().to_string_lossy().replace('\\', "/");
        if rel.starts_with("truth") || !keep(&rel) {
            continue;
        }
        builder.append_path_with_name(&file, &rel).unwrap();
    }
    builder.into_inner().unwrap()
}

fn truth() -> Truth {
    serde_json::from_slice(&std::fs::read(ci_bundle().join("truth/truth.json")).unwrap()).unwrap()
}

async fn problem(response: reqwest::Response, status: StatusCode, code: &str) -> Value {
    assert_eq!(response.status(), status, "expected {status} {code}");
    assert_eq!(response.headers()["content-type"], "application/problem+json");
    let v: Value = response.json().await.unwrap();
    assert_eq!(v["code"], code, "{v}");
    assert_eq!(v["status"], status.as_u16(), "{v}");
    assert!(v["type"].as_str().unwrap().ends_with(code), "{v}");
    assert!(!v["detail"].as_str().unwrap().is_empty(), "{v}");
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn round_trip_on_the_ci_preset() {
    let app = spawn_app().await;
    let response = app.submit(ci_tar(), "?client_reference=MES-4711").await;
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let location = response.headers()["location"].to_str().unwrap().to_string();
    let created: Value = response.json().await.unwrap();
    let id = created["id"].as_str().unwrap().to_string();
    assert_eq!(location, format!("/v1/inspections/{id}"));
    assert_eq!(created["status"], "queued");
    assert_eq!(created["client_reference"], "MES-4711");
    assert_eq!(created["connection"], "BC 4-1/2");
    assert_eq!(created["bundle"]["views"], 3);

    let done = app.wait(&id, Duration::from_secs(300)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["attempts"], 1);
    let truth = truth();
    assert_eq!(done["verdict"], truth.verdict.as_str());
    for t in ["created_at", "started_at", "finished_at"] {
        time::OffsetDateTime::parse(done[t].as_str().unwrap(), &time::format_description::well_known::Rfc3339).unwrap();
    }

    // Report, with a strong ETag and 304 on a match.
    let response = app.get(&format!("{location}/report")).await;
    assert_eq!(response.status(), StatusCode::OK);
    let etag = response.headers()["etag"].to_str().unwrap().to_string();
    assert!(etag.starts_with('"') && !etag.starts_with("W/"));
    let report: crestscan::pipeline::report::Report = response.json().await.unwrap();
    assert_eq!(report.verdict, truth.verdict);
    let again =
        app.client.get(app.url(&format!("{location}/report"))).header("if-none-match", &etag).send().await.unwrap();
    assert_eq!(again.status(), StatusCode::NOT_MODIFIED);

    // Per-thread table: JSON and CSV carry the same heights.
    let table: Value = app.get(&format!("{location}/threads")).await.json().await.unwrap();
    let threads = table["threads"].as_array().unwrap();
    assert_eq!(threads.len(), report.threads.len());
    let json_bins: usize = threads.iter().map(|t| t["heights"].as_array().unwrap().len()).sum();
    let csv =
        app.client.get(app.url(&format!("{location}/threads"))).header("accept", "text/csv").send().await.unwrap();
    assert!(csv.headers()["content-type"].to_str().unwrap().starts_with("text/csv"));
    let csv = csv.text().await.unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("thread,angle_deg,height_mm"));
    assert_eq!(lines.count(), json_bins);
    let first_measured = report.threads.iter().find_map(|t| {
        t.height_mm.angles_deg.iter().zip(&t.height_mm.values).find_map(|(a, v)| v.map(|v| (t.index, *a, v)))
    });
    let (thread, angle, height) = first_measured.expect("some bin measured");
    assert!(csv.contains(&format!("{thread},{angle},{height:.6}")), "CSV lacks {thread},{angle},{height:.6}");
    // Weights decide, not the order the client lists them in.
    let weighted = app
        .client
        .get(app.url(&format!("{location}/threads")))
        .header("accept", "text/csv;q=0.5, application/json")
        .send()
        .await
        .unwrap();
    assert!(weighted.headers()["content-type"].to_str().unwrap().starts_with("application/json"));

    // Mesh in all three formats, images as PNG.
    let ply = app.get(&format!("{location}/mesh")).await;
    assert_eq!(ply.headers()["content-type"], "application/x-ply");
    let ply_etag = ply.headers()["etag"].clone();
    let ply = ply.bytes().await.unwrap();
    assert!(ply.starts_with(b"ply\n"));
    let stl = app.client.get(app.url(&format!("{location}/mesh"))).header("accept", "model/stl").send().await.unwrap();
    assert_eq!(stl.headers()["content-type"], "model/stl");
    let stl = stl.bytes().await.unwrap();
    let triangles = u32::from_le_bytes(stl[80..84].try_into().unwrap()) as usize;
    assert_eq!(stl.len(), 84 + 50 * triangles);
    // The GLB is made from the stored PLY: the same mesh, read back by a glTF reader.
    let glb = app.get(&format!("{location}/mesh?format=glb")).await;
    assert_eq!(glb.headers()["content-type"], "model/gltf-binary");
    let glb_etag = glb.headers()["etag"].clone();
    assert_ne!(glb_etag, ply_etag, "each representation has its own validator");
    assert!(glb.headers()["content-disposition"].to_str().unwrap().ends_with(".glb\""));
    let glb = gltf::Gltf::from_slice(&glb.bytes().await.unwrap()).unwrap();
    let blob = glb.blob.clone().unwrap();
    let primitive = glb.meshes().next().unwrap().primitives().next().unwrap();
    let reader = primitive.reader(|_| Some(&blob));
    let stored = crestscan::export::ply::read(&ply).unwrap();
    assert_eq!(reader.read_positions().unwrap().collect::<Vec<_>>(), stored.vertices);
    assert_eq!(reader.read_indices().unwrap().into_u32().count(), 3 * triangles);
    let revalidated = app
        .client
        .get(app.url(&format!("{location}/mesh")))
        .header("accept", "model/gltf-binary")
        .header("if-none-match", glb_etag)
        .send()
        .await
        .unwrap();
    assert_eq!(revalidated.status(), StatusCode::NOT_MODIFIED);
    for kind in ["height-map", "all-in-focus"] {
        let png = app.get(&format!("{location}/images/{kind}")).await;
        assert_eq!(png.headers()["content-type"], "image/png");
        let bytes = png.bytes().await.unwrap();
        let decoded = image::load_from_memory(&bytes).unwrap();
        assert!(decoded.width() > 10 && decoded.height() > 10);
    }
    problem(app.get(&format!("{location}/mesh?format=obj")).await, StatusCode::NOT_ACCEPTABLE, "not_acceptable").await;

    // CMM: the truth's heights, offset by +5 µm, at every bin crestscan measured, as the CMM's
    // CSV. crestscan − CMM is then its own error minus 5 µm: the comparison's statistics must be
    // exactly those of the listed deviations.
    let mut cmm_csv = String::from("thread,angle_deg,height_mm\n");
    for t in &report.threads {
        let truth_thread = truth.threads.iter().find(|u| u.index == t.index).expect("same numbering");
        for ((a, ours), theirs) in
            t.height_mm.angles_deg.iter().zip(&t.height_mm.values).zip(&truth_thread.height_mm.values)
        {
            if let (Some(_), Some(v)) = (ours, theirs) {
                cmm_csv.push_str(&format!("{},{a},{}\n", t.index, v + 0.005));
            }
        }
    }
    // One thread's mean, without an angle: compared with crestscan's mean of that thread.
    let mean = report.threads.iter().find(|t| t.index == thread).unwrap().mean_height_mm.unwrap();
    cmm_csv.push_str(&format!("{thread},,{}\n", mean + 0.005));
    let put = app
        .client
        .put(app.url(&format!("{location}/cmm")))
        .header("content-type", "text/csv")
        .body(cmm_csv)
        .send()
        .await
        .unwrap();
    assert_eq!(put.status(), StatusCode::OK);
    let cmp: Value = app.get(&format!("{location}/cmm-comparison")).await.json().await.unwrap();
    let devs: Vec<f64> = cmp["points"].as_array().unwrap().iter().filter_map(|p| p["deviation_mm"].as_f64()).collect();
    let agreement = &cmp["agreement"];
    assert!(devs.len() >= 10, "{cmp}");
    assert_eq!(agreement["unmatched"], 0);
    let mean_point = cmp["points"].as_array().unwrap().iter().find(|p| p["angle_deg"].is_null()).unwrap();
    assert!((mean_point["deviation_mm"].as_f64().unwrap() + 0.005).abs() < 1e-9);
    assert_eq!(agreement["compared"], devs.len());
    let bias = devs.iter().sum::<f64>() / devs.len() as f64;
    let rms = (devs.iter().map(|d| d * d).sum::<f64>() / devs.len() as f64).sqrt();
    assert!((agreement["bias_mm"].as_f64().unwrap() - bias).abs() < 1e-12);
    assert!((agreement["rms_mm"].as_f64().unwrap() - rms).abs() < 1e-12);
    assert!(bias < -0.005 + 0.015 && bias > -0.005 - 0.015, "bias {bias}: crestscan's own error is within 15 µm");
    let [lo, hi] = [
        agreement["limits_of_agreement_mm"][0].as_f64().unwrap(),
        agreement["limits_of_agreement_mm"][1].as_f64().unwrap(),
    ];
    assert!(lo < bias && bias < hi);
    // Default tolerance: a tenth of the ±tolerance band.
    let tol = cmp["height_tolerance_mm"].as_f64().unwrap();
    assert!((agreement["tolerance_mm"].as_f64().unwrap() - 2.0 * tol / 10.0).abs() < 1e-12);
    let strict: Value =
        app.get(&format!("{location}/cmm-comparison?tolerance_mm=0.000001")).await.json().await.unwrap();
    assert_eq!(strict["agreement"]["within_tolerance"], false);
    let loose: Value = app.get(&format!("{location}/cmm-comparison?tolerance_mm=1")).await.json().await.unwrap();
    assert_eq!(loose["agreement"]["within_tolerance"], true);

    // The list finds it by its client reference; metrics counted the polls by route.
    let page: Value = app.get("/v1/inspections?client_reference=MES-4711&status=succeeded").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    let metrics = app.get("/metrics").await.text().await.unwrap();
    assert!(metrics.contains(r#"route="/v1/inspections/{id}",status="200""#), "{metrics}");
    assert!(metrics.contains("crestscan_jobs_finished_total{outcome=\"succeeded\"} 1"), "{metrics}");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_their_problem_codes_and_store_nothing() {
    // No workers: this is about the API alone.
    let app = spawn_app_with(|s| s.workers = 0).await;
    let post = |ct: &'static str, body: Vec<u8>| {
        app.client.post(app.url("/v1/inspections")).header("content-type", ct).body(body).send()
    };
    problem(
        post("application/json", b"{}".to_vec()).await.unwrap(),
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_media_type",
    )
    .await;
    problem(post("application/zip", Vec::new()).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_archive")
        .await;
    problem(
        post("application/zip", b"not a zip at all".to_vec()).await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_archive",
    )
    .await;
    // A frame missing from the archive: named.
    let files: Vec<String> =
        walk(ci_bundle()).iter().map(|p| p.strip_prefix(ci_bundle()).unwrap().to_string_lossy().into_owned()).collect();
    let victim = files.iter().find(|f| f.ends_with(".png")).unwrap().clone();
    let missing_victim = bundle_tar(ci_bundle(), &|rel| rel != victim);
    let v = problem(
        post("application/x-tar", missing_victim).await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "missing_file",
    )
    .await;
    assert_eq!(v["culprit"], victim.as_str());
    assert_eq!(v["instance"], "/v1/inspections");
    // A broken manifest: the JSON path is named.
    let dir = tempfile::tempdir().unwrap();
    crate::common::copy_tree(ci_bundle(), dir.path(), &|p| !p.starts_with("truth"));
    let mut manifest: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("manifest.json")).unwrap()).unwrap();
    // The bundle with `manifest` in place of its own, posted as a tar.
    let post_with = |manifest: &Value| {
        std::fs::write(dir.path().join("manifest.json"), serde_json::to_vec(manifest).unwrap()).unwrap();
        post("application/x-tar", bundle_tar(dir.path(), &|_| true))
    };
    manifest["optics"]["f_number"] = Value::from(-2.0);
    let v = problem(post_with(&manifest).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "invalid_optics").await;
    assert!(v["culprit"].as_str().unwrap().contains("optics."), "{v}");
    // Well formed, but a pixel pitch typed in mm: refused at upload, before a worker could run
    // out of memory on it.
    manifest["optics"]["f_number"] = Value::from(1.4);
    manifest["optics"]["pixel_pitch_um"] = Value::from(0.012);
    let v =
        problem(post_with(&manifest).await.unwrap(), StatusCode::UNPROCESSABLE_ENTITY, "inspection_too_large").await;
    assert_eq!(v["culprit"], "manifest.json: optics.pixel_pitch_um", "{v}");
    // Options: unknown pipeline option, bad arc rule, bad query.
    let form = reqwest::multipart::Form::new()
        .part("bundle", reqwest::multipart::Part::bytes(ci_tar()))
        .text("options", r#"{"pipeline": {"depth": {"no_such_knob": 1}}}"#);
    let v = problem(
        app.client.post(app.url("/v1/inspections")).multipart(form).send().await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_option",
    )
    .await;
    assert_eq!(v["culprit"], "pipeline.depth.no_such_knob");
    problem(app.submit(ci_tar(), "?arc_rule=sometimes").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    let bad_multipart = app
        .client
        .post(app.url("/v1/inspections"))
        .header("content-type", "multipart/form-data; boundary=XYZ")
        .body("--XYZ\r\nnot a part")
        .send()
        .await
        .unwrap();
    problem(bad_multipart, StatusCode::BAD_REQUEST, "invalid_multipart").await;
    let traversal = reqwest::multipart::Form::new()
        .part("manifest", reqwest::multipart::Part::bytes(std::fs::read(ci_bundle().join("manifest.json")).unwrap()))
        .part("../etc/passwd", reqwest::multipart::Part::bytes(b"x".to_vec()))
        // More after the refused part: the server reads the rest, so the client gets the answer.
        .part("views/a000-z00/000.png", reqwest::multipart::Part::bytes(vec![0u8; 48 << 20]));
    problem(
        app.client.post(app.url("/v1/inspections")).multipart(traversal).send().await.unwrap(),
        StatusCode::UNPROCESSABLE_ENTITY,
        "unsafe_path",
    )
    .await;
    // Too large for the configured limit.
    let small = spawn_app_with(|s| {
        s.workers = 0;
        s.max_upload_mb = 1;
    })
    .await;
    problem(small.submit(ci_tar(), "").await, StatusCode::PAYLOAD_TOO_LARGE, "body_too_large").await;
    assert_eq!(small.uploads(), 0);
    small.stop().await;

    // Routing and ids.
    problem(app.get("/v2/nothing").await, StatusCode::NOT_FOUND, "route_not_found").await;
    problem(
        app.client.delete(app.url("/v1/inspections")).send().await.unwrap(),
        StatusCode::METHOD_NOT_ALLOWED,
        "method_not_allowed",
    )
    .await;
    problem(app.get("/v1/inspections/not-an-id").await, StatusCode::NOT_FOUND, "invalid_id").await;
    problem(app.get("/v1/inspections/01890a5d-ac96-774b-bcce-b302099a8057").await, StatusCode::NOT_FOUND, "invalid_id")
        .await;
    problem(app.get("/v1/inspections?status=done").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    problem(app.get("/v1/inspections?limit=0").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    problem(app.get("/v1/inspections?created_after=yesterday").await, StatusCode::BAD_REQUEST, "invalid_query").await;
    problem(app.get("/v1/connections/XYZ%2099").await, StatusCode::NOT_FOUND, "unknown_designation").await;

    // Nothing was stored by any of it.
    let page: Value = app.get("/v1/inspections").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 0);
    assert_eq!(app.uploads(), 0);

    // Results of an inspection that has none yet, and bad CMM data, once one exists.
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    problem(app.get(&format!("/v1/inspections/{id}/report")).await, StatusCode::CONFLICT, "inspection_not_succeeded")
        .await;
    problem(app.get(&format!("/v1/inspections/{id}/cmm")).await, StatusCode::NOT_FOUND, "cmm_not_found").await;
    let connection: Value = app.get("/v1/connections/BC%204-1%2F2").await.json().await.unwrap();
    assert_eq!(connection["designation"], "BC 4-1/2");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotent_retry_and_cancel() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let send = |key: &'static str, query: &'static str| {
        app.client
            .post(app.url(&format!("/v1/inspections{query}")))
            .header("content-type", "application/x-tar")
            .header("idempotency-key", key)
            .body(ci_tar())
            .send()
    };
    let first = send("station-7-run-42", "").await.unwrap();
    assert_eq!(first.status(), StatusCode::ACCEPTED);
    let first: Value = first.json().await.unwrap();
    let retry = send("station-7-run-42", "").await.unwrap();
    assert_eq!(retry.status(), StatusCode::ACCEPTED);
    assert_eq!(retry.headers()["idempotent-replayed"], "true");
    let retry: Value = retry.json().await.unwrap();
    assert_eq!(retry["id"], first["id"]);
    let other = send("station-7-run-42", "?arc_rule=combined").await.unwrap();
    let v = problem(other, StatusCode::UNPROCESSABLE_ENTITY, "idempotency_key_reused").await;
    assert_eq!(v["culprit"], "Idempotency-Key");
    let page: Value = app.get("/v1/inspections").await.json().await.unwrap();
    assert_eq!(page["items"].as_array().unwrap().len(), 1);
    assert_eq!(app.uploads(), 1, "one content-addressed upload");

    // Cancel while queued: at once.
    let id = first["id"].as_str().unwrap();
    let canceled = app.client.post(app.url(&format!("/v1/inspections/{id}/cancel"))).send().await.unwrap();
    assert_eq!(canceled.status(), StatusCode::OK);
    assert_eq!(canceled.json::<Value>().await.unwrap()["status"], "canceled");

    // Cancel while running: requested, seen by the lease holder at its heartbeat.
    let second: Value = send("station-7-run-43", "").await.unwrap().json().await.unwrap();
    let store = app.store().await;
    let claimed = store.claim("test-worker", Duration::from_secs(30)).await.unwrap().expect("one queued");
    assert_eq!(claimed.id, second["id"].as_str().unwrap());
    let response = app.client.post(app.url(&format!("/v1/inspections/{}/cancel", claimed.id))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    let v: Value = response.json().await.unwrap();
    assert_eq!((v["status"].as_str(), v["cancel_requested"].as_bool()), (Some("running"), Some(true)));
    let beat = store.heartbeat(&claimed.id, "test-worker", Duration::from_secs(30), None).await.unwrap();
    assert_eq!(beat, crestscan::service::store::Heartbeat::Held { cancel_requested: true });
    assert_eq!(
        store.heartbeat(&claimed.id, "someone-else", Duration::from_secs(30), None).await.unwrap(),
        crestscan::service::store::Heartbeat::Lost
    );
    assert!(
        store
            .complete_without_results(&claimed.id, "test-worker", crestscan::service::store::Status::Canceled, None)
            .await
            .unwrap()
    );
    let v: Value = app.get(&format!("/v1/inspections/{}", claimed.id)).await.json().await.unwrap();
    assert_eq!(v["status"], "canceled");
    // A finished inspection cannot be canceled.
    let response = app.client.post(app.url(&format!("/v1/inspections/{}/cancel", claimed.id))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::OK, "canceling a canceled inspection is a no-op");

    // Cancel requested while running, then the worker gives the job back (a retryable failure or
    // a release at shutdown): it ends canceled, not queued (claims skip canceled-requested jobs,
    // so a queued one would wait forever).
    let third: Value = send("station-7-run-44", "").await.unwrap().json().await.unwrap();
    let claimed = store.claim("test-worker", Duration::from_secs(30)).await.unwrap().expect("one queued");
    assert_eq!(claimed.id, third["id"].as_str().unwrap());
    let response = app.client.post(app.url(&format!("/v1/inspections/{}/cancel", claimed.id))).send().await.unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    assert!(store.requeue(&claimed.id, "test-worker", Duration::ZERO, None, true).await.unwrap());
    let v: Value = app.get(&format!("/v1/inspections/{}", claimed.id)).await.json().await.unwrap();
    assert_eq!(v["status"], "canceled");
    assert!(v["finished_at"].is_string(), "{v}");
    assert!(store.claim("test-worker", Duration::from_secs(30)).await.unwrap().is_none(), "nothing left queued");
    app.stop().await;
}

/// Uploaded bundles are deleted once every inspection that uses them finished before the cutoff;
/// one still shared by an unfinished inspection is kept, and the records stay readable.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_uploads_are_purged_and_shared_ones_kept() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let store = app.store().await;
    let later_ms =
        || (std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_millis() as i64) + 3_600_000;
    let cancel = |id: String| {
        let request = app.client.post(app.url(&format!("/v1/inspections/{id}/cancel")));
        async move { assert_eq!(request.send().await.unwrap().status(), StatusCode::OK) }
    };
    let first: Value = app.submit(ci_tar(), "").await.json().await.unwrap();
    let first = first["id"].as_str().unwrap().to_string();
    cancel(first.clone()).await;
    // The same bundle again: the same content-addressed upload, now in use by a queued inspection.
    let second: Value = app.submit(ci_tar(), "").await.json().await.unwrap();
    let second = second["id"].as_str().unwrap().to_string();
    assert_eq!(app.uploads(), 1);
    assert_eq!(store.purge_uploads(later_ms()).await.unwrap(), 0, "an unfinished inspection still needs it");
    assert_eq!(app.uploads(), 1);
    cancel(second.clone()).await;
    // Finished, but after the cutoff: kept.
    assert_eq!(store.purge_uploads(later_ms() - 7_200_000).await.unwrap(), 0);
    assert_eq!(store.purge_uploads(later_ms()).await.unwrap(), 1);
    assert_eq!(app.uploads(), 0);
    assert_eq!(store.purge_uploads(later_ms()).await.unwrap(), 0, "purged once");
    for id in [&first, &second] {
        let v: Value = app.get(&format!("/v1/inspections/{id}")).await.json().await.unwrap();
        assert_eq!(v["status"], "canceled", "{v}");
    }
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cursor_pagination_walks_every_inspection_once() {
    let app = spawn_app_with(|s| s.workers = 0).await;
    let mut ids = Vec::new();
    for i in 0..5 {
        let v: Value = app.submit(ci_tar(), &format!("?client_reference=batch-{}", i % 2)).await.json().await.unwrap();
        ids.push(v["id"].as_str().unwrap().to_string());
    }
    let mut seen = Vec::new();
    let mut cursor: Option<String> = None;
    loop {
        let path = match &cursor {
            Some(c) => format!("/v1/inspections?limit=2&cursor={c}"),
            None => "/v1/inspections?limit=2".to_string(),
        };
        let page: Value = app.get(&path).await.json().await.unwrap();
        seen.extend(page["items"].as_array().unwrap().iter().map(|i| i["id"].as_str().unwrap().to_string()));
        match page["next_cursor"].as_str() {
            Some(c) => cursor = Some(c.to_string()),
            None => break,
        }
    }
    ids.reverse();
    assert_eq!(seen, ids, "newest first, each once");
    let batch0: Value = app.get("/v1/inspections?client_reference=batch-0").await.json().await.unwrap();
    assert_eq!(batch0["items"].as_array().unwrap().len(), 3);
    let none: Value = app.get("/v1/inspections?created_after=2100-01-01T00:00:00Z").await.json().await.unwrap();
    assert_eq!(none["items"].as_array().unwrap().len(), 0);
    app.stop().await;
}

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

/// The real binary, SIGKILLed with jobs queued and running, then restarted on the same data
/// directory: every accepted inspection finishes, exactly once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_loses_no_accepted_inspection() {
    let data = tempfile::tempdir().unwrap();
    let start = |data: &Path| {
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
            .args([
                "serve",
                "--bind",
                "127.0.0.1:0",
                "--lease-seconds",
                "1",
                "--heartbeat-seconds",
                "0.2",
                "--poll-interval-ms",
                "50",
                "--log",
                "warn",
            ])
            .arg("--data-dir")
            .arg(data)
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        std::io::BufRead::read_line(&mut std::io::BufReader::new(child.stdout.take().unwrap()), &mut line).unwrap();
        let address = line.trim().rsplit("http://").next().unwrap().to_string();
        (child, format!("http://{address}"))
    };
    let client = reqwest::Client::new();
    let (mut child, base) = start(data.path());
    let mut ids = Vec::new();
    for _ in 0..3 {
        let r = client
            .post(format!("{base}/v1/inspections"))
            .header("content-type", "application/x-tar")
            .body(ci_tar())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::ACCEPTED);
        ids.push(r.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string());
    }
    // Kill it while the first is running.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let v: Value =
            client.get(format!("{base}/v1/inspections/{}", ids[0])).send().await.unwrap().json().await.unwrap();
        if v["status"] == "running" {
            break;
        }
        assert!(Instant::now() < deadline, "never started: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    child.kill().unwrap();
    child.wait().unwrap();

    let (mut child, base) = start(data.path());
    let deadline = Instant::now() + Duration::from_secs(300);
    for id in &ids {
        loop {
            let v: Value =
                client.get(format!("{base}/v1/inspections/{id}")).send().await.unwrap().json().await.unwrap();
            if v["status"] == "succeeded" {
                break;
            }
            assert!(v["status"] == "queued" || v["status"] == "running", "{v}");
            assert!(Instant::now() < deadline, "not finished: {v}");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    let first: Value =
        client.get(format!("{base}/v1/inspections/{}", ids[0])).send().await.unwrap().json().await.unwrap();
    assert_eq!(first["attempts"], 2, "the killed run and the one that finished");
    child.kill().unwrap();
    child.wait().unwrap();
    // Exactly once: one report and one set of thread rows per inspection.
    let store = open_store(data.path()).await;
    let (reports,): (i64,) = sqlx::query_as("SELECT COUNT(*) FROM reports").fetch_one(&store.pool).await.unwrap();
    assert_eq!(reports, 3);
    let (dupes,): (i64,) = sqlx::query_as(
        "SELECT COUNT(*) FROM (SELECT inspection_id, thread_index FROM threads GROUP BY 1, 2 HAVING COUNT(*) > 1)",
    )
    .fetch_one(&store.pool)
    .await
    .unwrap();
    assert_eq!(dupes, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_lets_the_running_job_finish() {
    // A grace period long enough for a starved CI machine (the compute pool runs at SCHED_IDLE).
    let app = spawn_app_with(|s| s.shutdown_grace_seconds = 300.0).await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let v: Value = app.get(&format!("/v1/inspections/{id}")).await.json().await.unwrap();
        if v["status"] == "running" {
            break;
        }
        assert_eq!(v["status"], "queued");
        assert!(Instant::now() < deadline);
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let data = app.data.clone();
    let _dir = app.stop().await;
    let row = open_store(&data).await.inspection(&id).await.unwrap();
    assert_eq!(row.status, "succeeded", "the job finished within the grace period before the process stopped");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_api_node_and_a_worker_node_share_a_data_directory_and_failures_are_problems() {
    // An API-only node accepts; the upload then vanishes (an operator's mistake).
    let api = spawn_app_with(|s| s.workers = 0).await;
    let created: Value = api.submit(ci_tar(), "").await.json().await.unwrap();
    let id = created["id"].as_str().unwrap();
    let sha = created["bundle"]["sha256"].as_str().unwrap();
    api.store().await.files.remove(sha).unwrap();
    // A worker node on the same directory claims it and fails it with a problem object.
    let worker = spawn_app_in(&api.data, |_| {}).await;
    let done = api.wait(id, Duration::from_secs(60)).await;
    assert_eq!(done["status"], "failed");
    assert_eq!(done["error"]["code"], "upload_missing");
    assert_eq!(done["error"]["status"], 500);
    assert!(done["error"]["detail"].as_str().unwrap().contains(sha));
    assert_eq!(done["attempts"], 1, "a permanent failure is not retried");
    worker.stop().await;
    api.stop().await;
}
