//! The service over real HTTP: the real app on a loopback port with a fresh SQLite file, driven by
//! reqwest; and the real binary, killed with SIGKILL and restarted.

mod auth;
mod blobs;
mod browser;
mod caps;
mod disk_full;
mod hostile;
mod inspections;
mod interchange;
mod migrate;
mod models;
mod mqtt;
mod opcua;
mod openapi;
mod queue;
mod report_page;
mod results;
mod roles;
mod stations;
mod tls;
mod traces;
mod webhooks;

use crate::common::{ci_bundle, walk};
use crestscan::service::config::Settings;
use crestscan::service::startup::Application;
use crestscan::sim::Truth;
use reqwest::StatusCode;
use serde_json::Value;
use std::path::Path;
use std::time::{Duration, Instant};

pub struct TestApp {
    pub base: String,
    pub client: reqwest::Client,
    pub data: std::path::PathBuf,
    /// The OPC UA endpoint, where one is served (`opcua_endpoint`).
    pub opcua_url: Option<String>,
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

    /// Submits the ci bundle as a page of `origin` would.
    pub async fn submit_from(&self, origin: &str) -> reqwest::Response {
        self.client
            .post(self.url("/v1/inspections"))
            .header("content-type", "application/x-tar")
            .header("origin", origin)
            .body(ci_tar())
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

    /// Uploaded bundles stored, in whichever blob store the app keeps them.
    pub async fn uploads(&self) -> usize {
        self.store().await.blobs.list().await.unwrap().len()
    }
}

/// The S3-compatible server the service tests run against where `CRESTSCAN_TEST_S3_ENDPOINT`
/// names one (`.ci/run` runs the service suite a second time so, against moto; the bucket
/// `crestscan-it` must exist, credentials from the AWS_* environment): each data directory's
/// uploads go under a prefix of its own. None: the embedded default, the local directory.
pub fn test_object_store(data: &Path) -> Option<(String, String)> {
    let endpoint = std::env::var("CRESTSCAN_TEST_S3_ENDPOINT").ok().filter(|e| !e.is_empty())?;
    let name = data.file_name().unwrap().to_string_lossy().to_ascii_lowercase();
    let prefix: String = name.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '-' }).collect();
    Some((format!("s3://crestscan-it/{prefix}"), endpoint))
}

/// The free space a test server keeps, MiB. The shipped 1 GiB floor would turn a test into a 507
/// wherever the build and the suite's renders leave less free (a CI machine's disk did); the floor
/// itself is tested where a test sets it (`hostile.rs`, `disk_full.rs`).
pub const TEST_MIN_FREE_DISK_MB: u64 = 64;

pub fn test_settings(data: &Path) -> Settings {
    let (object_store, s3_endpoint) = test_object_store(data).unzip();
    Settings {
        bind: "127.0.0.1:0".parse().unwrap(),
        data_dir: data.to_path_buf(),
        lease_seconds: 2.0,
        heartbeat_seconds: 0.2,
        poll_interval_ms: 50,
        shutdown_grace_seconds: 5.0,
        log: "warn".into(),
        s3_access_key_id: object_store.as_ref().map(|_| "test".into()),
        s3_secret_access_key: object_store.as_ref().map(|_| "test".into()),
        object_store,
        s3_endpoint,
        database_url: crate::common::test_database_url(data),
        min_free_disk_mb: TEST_MIN_FREE_DISK_MB,
        ..Settings::default()
    }
}

/// Settings edited back to the embedded default, whichever backends the suite runs on: the records
/// in the data directory's SQLite file, the uploads under it (a single node before a move).
pub fn single_node(s: &mut Settings) {
    s.database_url = None;
    s.object_store = None;
    s.s3_endpoint = None;
    s.s3_access_key_id = None;
    s.s3_secret_access_key = None;
}

/// The store of a data directory as the app opens it: its records where the tests keep them
/// (its SQLite file, or a PostgreSQL database: [`crate::common::test_database_url`]), and its
/// blobs likewise ([`test_object_store`]).
pub async fn open_store(data: &Path) -> crestscan::service::store::Store {
    use crestscan::service::store::blobs::{S3Blobs, S3Location, S3Settings};
    let database = test_settings(data).database();
    let mut store =
        crestscan::service::store::Store::connect(&database, &data.join("uploads"), &data.join("tmp")).await.unwrap();
    if let Some((url, endpoint)) = test_object_store(data) {
        let s3 =
            S3Settings { endpoint: Some(endpoint), region: None, credentials: Some(("test".into(), "test".into())) };
        let blobs =
            std::sync::Arc::new(S3Blobs::open(S3Location::parse(&url).unwrap(), &s3, &data.join("tmp")).unwrap());
        store.blobs = blobs.clone();
        store.artifact_objects = Some(blobs);
    }
    store
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
    crestscan::service::telemetry::init_logging("warn", Default::default());
    let mut settings = test_settings(data);
    edit(&mut settings);
    let app = Application::build(settings).await.unwrap();
    let base = format!("http://{}", app.address());
    let opcua_url = app.opcua_url().map(String::from);
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
        client: client(),
        data: data.to_path_buf(),
        opcua_url,
        dir: None,
        stop: Some(tx),
        server: Some(server),
    }
}

/// An HTTP client as the service asks its clients to be: a pooled connection idles at most half
/// `header_timeout_seconds` (10 s in tests), so it is never reused in the instant the server
/// closes it, which a POST would meet as a broken pipe mid-body (docs/service.md, "Connections").
pub fn client_builder() -> reqwest::ClientBuilder {
    reqwest::Client::builder().pool_idle_timeout(Duration::from_secs(5))
}

pub fn client() -> reqwest::Client {
    client_builder().build().unwrap()
}

pub async fn spawn_app() -> TestApp {
    spawn_app_with(|_| {}).await
}

/// A `crestscan serve` child process (it derefs to the `Child`), killed and reaped when dropped
/// if it is still running, so that a failed assertion never leaves a service behind.
pub struct ServeChild(std::process::Child);

impl std::ops::Deref for ServeChild {
    type Target = std::process::Child;
    fn deref(&self) -> &std::process::Child {
        &self.0
    }
}

impl std::ops::DerefMut for ServeChild {
    fn deref_mut(&mut self) -> &mut std::process::Child {
        &mut self.0
    }
}

impl Drop for ServeChild {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// The real binary, `crestscan serve` on a loopback port over `data` with `extra` arguments: the
/// child and its base URL (read off the line it prints when listening).
pub fn start_binary(data: &Path, extra: &[&str]) -> (ServeChild, String) {
    start_binary_env(data, extra, &[])
}

/// [`start_binary`] with environment variables of the child's own.
pub fn start_binary_env(data: &Path, extra: &[&str], env: &[(&str, &Path)]) -> (ServeChild, String) {
    let blobs: Vec<String> = test_object_store(data)
        .map(|(url, endpoint)| {
            let key = ["--s3-access-key-id", "test", "--s3-secret-access-key", "test"].map(String::from);
            [vec!["--object-store".into(), url, "--s3-endpoint".into(), endpoint], key.to_vec()].concat()
        })
        .unwrap_or_default();
    let records: Vec<String> =
        crate::common::test_database_url(data).map(|url| vec!["--database-url".into(), url]).unwrap_or_default();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
        .args(["serve", "--bind", "127.0.0.1:0", "--log", "warn"])
        .args(["--min-free-disk-mb", &TEST_MIN_FREE_DISK_MB.to_string()])
        .args(&blobs)
        .args(&records)
        .args(extra)
        // The child's malloc arenas are the service's own choice unless a test names them.
        .env_remove("MALLOC_ARENA_MAX")
        .envs(env.iter().copied())
        .arg("--data-dir")
        .arg(data)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .map(ServeChild)
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(child.stdout.take().unwrap()), &mut line).unwrap();
    let address = line.trim().rsplit("http://").next().unwrap().to_string();
    (child, format!("http://{address}"))
}

/// Submits the ci bundle to a service at `base` (one [`start_binary`] started); the new id, after
/// checking the 202.
pub async fn submit_ci_to(client: &reqwest::Client, base: &str) -> String {
    let response = client
        .post(format!("{base}/v1/inspections"))
        .header("content-type", "application/x-tar")
        .body(ci_tar())
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::ACCEPTED);
    response.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string()
}

/// GETs `url` and reads its JSON body.
pub async fn get_json(client: &reqwest::Client, url: &str) -> Value {
    client.get(url).send().await.unwrap().json().await.unwrap()
}

/// The ci bundle (without truth/) as a tar archive.
pub fn ci_tar() -> Vec<u8> {
    bundle_tar(ci_bundle(), &|_| true)
}

pub fn bundle_tar(dir: &Path, keep: &dyn Fn(&str) -> bool) -> Vec<u8> {
    tar_of(dir, keep, None)
}

/// The bundle in `dir` (without its truth) as a tar whose `manifest.json` is `manifest` instead,
/// in the same place: the render stays shared and unedited.
pub fn bundle_tar_with_manifest(dir: &Path, manifest: &[u8]) -> Vec<u8> {
    tar_of(dir, &|_| true, Some(manifest))
}

/// The files under `dir` that `keep` takes, truth left out, as a tar; `manifest.json` from
/// `manifest` where given.
fn tar_of(dir: &Path, keep: &dyn Fn(&str) -> bool, manifest: Option<&[u8]>) -> Vec<u8> {
    let mut builder = tar::Builder::new(Vec::new());
    for file in walk(dir) {
        let rel = file.strip_prefix(dir).unwrap().to_string_lossy().replace('\\', "/");
        if rel.starts_with("truth") || !keep(&rel) {
            continue;
        }
        match manifest {
            Some(manifest) if rel == "manifest.json" => {
                let mut header = tar::Header::new_gnu();
                header.set_size(manifest.len() as u64);
                header.set_mode(0o644);
                builder.append_data(&mut header, &rel, manifest).unwrap();
            }
            _ => builder.append_path_with_name(&file, &rel).unwrap(),
        }
    }
    builder.into_inner().unwrap()
}

fn truth() -> Truth {
    crate::common::truth_of(ci_bundle())
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

/// Every operation of the OpenAPI document (the router's own list): method, template, and a
/// concrete path (ids that exist nowhere, a real connection, a real image kind).
pub fn documented_operations() -> Vec<(reqwest::Method, String, String)> {
    let doc: Value = serde_json::from_str(&crestscan::service::api::openapi().to_pretty_json().unwrap()).unwrap();
    let mut operations = Vec::new();
    for (path, item) in doc["paths"].as_object().unwrap() {
        let id = if path.starts_with("/v1/keys") { "0123456789ab" } else { "00000000-0000-0000-0000-000000000000" };
        let concrete =
            path.replace("{id}", id).replace("{designation}", "BC%204-1%2F2").replace("{kind}", "height-map");
        for method in item.as_object().unwrap().keys() {
            operations.push((method.to_uppercase().parse().unwrap(), path.clone(), concrete.clone()));
        }
    }
    operations
}
