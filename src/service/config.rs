//! Service settings. Precedence: built-in defaults < config file (TOML) < environment
//! (`CRESTSCAN_*`) < command-line flags; the CLI layer (clap, with `env`) merges the last two.

use crate::bundle::Limits;
use crate::service::webhook_settings::{EndpointSettings, Secret};
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Settings {
    /// What this process does (`all`: the API and the workers, the embedded default; `api`: the
    /// API only, no job is run here; `worker`: jobs only, with `/healthz`, `/readyz` and
    /// `/metrics` on `bind` and nothing else). Processes of different roles share the store.
    pub role: Role,
    /// Address the HTTP server listens on.
    pub bind: SocketAddr,
    /// Host names (besides IP addresses and `localhost`) requests may be addressed to; `*` takes
    /// any. Other names get 421 `host_not_allowed`: they are how DNS rebinding reaches a service.
    pub allowed_hosts: Vec<String>,
    /// Origins (`https://mes.plant.local`) whose pages may change state and read answers
    /// (CORS); none by default, so only requests without `Origin` (MES, curl, SDKs) and the
    /// service's own pages may post.
    pub allowed_origins: Vec<String>,
    /// SQLite database (`crestscan.db`), file store (`uploads/`) and temporary files (`tmp/`).
    pub data_dir: PathBuf,
    /// Inspections run at once. Each already uses every core (rayon), so 1 is right on small machines;
    /// 0 makes an API-only node (another process on the same data directory runs the jobs).
    pub workers: usize,
    /// Threads of the pipeline's compute pool (0: one per core).
    pub compute_threads: usize,
    /// Nice level of the compute pool's threads (0–19): request handling, at 0, keeps its latency
    /// while inspections saturate the CPU, and a busy neighbour at the same level shares it fairly.
    pub compute_nice: i32,
    /// Schedule the compute pool SCHED_IDLE instead: it then runs only on CPU nothing else wants, so
    /// any busy neighbour, even one at nice 19, starves inspections (docs/notebook/service.md).
    pub compute_sched_idle: bool,
    /// Largest accepted upload.
    pub max_upload_mb: u64,
    /// Uncompressed bytes of all a bundle's files, MiB (0: four times `max_upload_mb`).
    pub max_decompressed_mb: u64,
    /// Uncompressed over compressed size of any zip entry of over 1 MiB (a bomb beyond it).
    pub max_compression_ratio: u64,
    /// Size of a bundle's manifest.json, KiB: it is parsed in memory, about ten times its size.
    pub max_manifest_kib: u64,
    /// Views in a bundle's manifest.
    pub max_views: usize,
    /// Frames of one view.
    pub max_frames_per_view: usize,
    /// Memory one inspection may take at its peak, MiB (0: sized to the machine, 60% of its
    /// physical memory shared among the workers). A bundle whose estimated peak
    /// ([`crate::pipeline::memory`]) is larger is refused at upload (422 `inspection_too_large`).
    pub worker_memory_mb: u64,
    /// Free space the data directory keeps, MiB: an upload that would leave less is refused with
    /// 507 before (or while) it is written, `/readyz` reports not ready below it, and workers
    /// claim no job until space returns.
    pub min_free_disk_mb: u64,
    /// The longest a connection may take to send a request's head (and may sit idle between
    /// requests), seconds; then it is closed.
    pub header_timeout_seconds: f64,
    /// The longest an upload may send nothing, seconds (408 `request_timeout` after).
    pub upload_idle_seconds: f64,
    /// Once `upload_idle_seconds` have passed, the average rate an upload must keep, KiB/s.
    pub min_upload_kib_per_s: f64,
    /// Uploads received at once, over all clients (503 with Retry-After beyond): each holds a
    /// writer thread and a file.
    pub max_concurrent_uploads: usize,
    /// Uploads received at once from one client address (429 with Retry-After beyond).
    pub max_uploads_per_client: usize,
    /// A running job's lease; a worker that stops heartbeating loses it after this long.
    pub lease_seconds: f64,
    /// How often a running job renews its lease and publishes progress.
    pub heartbeat_seconds: f64,
    /// Attempts that end in a retryable failure before the job is failed (a crash of the process
    /// running it is not such an attempt).
    pub max_attempts: u32,
    /// Deaths of the process running a job (its lease lapsed) before the job is failed as
    /// poisonous (`job_poisonous`): a crash is re-run without blame until it repeats this often.
    pub max_interruptions: u32,
    /// On shutdown, running jobs get this long to finish before they are released for re-claiming.
    pub shutdown_grace_seconds: f64,
    /// How often idle workers look for work (new uploads also wake them at once), and the webhook
    /// dispatcher for finished inspections and due deliveries.
    pub poll_interval_ms: u64,
    /// Uploaded bundles of finished inspections are deleted after this many days (0: kept).
    pub upload_retention_days: f64,
    /// Meshes and images of finished inspections are deleted after this many days (0: kept); the
    /// reports and thread tables stay.
    pub artifact_retention_days: f64,
    /// Artifact objects (an object store's meshes and images) that no record names are deleted
    /// once written longer ago than this: a worker uploads its results just before the commit
    /// that names them.
    pub orphan_grace_seconds: f64,
    /// Tracing filter (`info`, `crestscan=debug,tower_http=info`, ...).
    pub log: String,
    /// Log lines as text (colours only on a terminal) or as one JSON object each (for a log
    /// collector).
    pub log_format: LogFormat,
    /// `required`: every route but `/healthz` and `/readyz` needs an API key (`crestscan keys
    /// create`); `off`: none does, allowed only on a loopback address.
    pub auth: AuthMode,
    /// Submissions per API key per minute (429 with Retry-After beyond; 0: no limit).
    pub submissions_per_minute: u32,
    /// Endpoints told of every inspection's terminal state (`[[webhooks]]` tables of the config
    /// file: `name`, `url`, `secrets`, `events`; docs/service.md, Webhooks).
    pub webhooks: Vec<EndpointSettings>,
    /// The only origins (`https://mes.plant.local:8443`: scheme, host and port) a submission's
    /// `callback_url` may point to; none by default, so `callback_url` is refused and the service
    /// calls nothing a client names.
    pub callback_origins: Vec<String>,
    /// Secrets signing `callback_url` deliveries (`whsec_…`; each one signs, for rotation).
    pub callback_secrets: Vec<String>,
    /// The longest one webhook attempt may take, seconds.
    pub webhook_timeout_seconds: f64,
    /// Attempts of a delivery before it is given up (recorded as failed).
    pub webhook_max_attempts: u32,
    /// The wait after a delivery's first failed attempt, seconds; it doubles per attempt up to an
    /// hour, with ±25% jitter.
    pub webhook_retry_seconds: f64,
    /// An OpenTelemetry collector's OTLP/HTTP traces URL (`http://collector:4318/v1/traces`):
    /// spans of requests and inspection runs are exported there; none by default.
    pub otlp_endpoint: Option<String>,
    /// Keep the records in PostgreSQL, `postgres://user:password@host:port/database`, instead of
    /// the data directory's SQLite file: API and worker processes on several machines then share
    /// them (docs/operations.md, "Beyond one machine"). The database is created if the server
    /// lacks it. Never logged with its password. None by default.
    #[serde(skip_serializing)]
    pub database_url: Option<String>,
    /// Keep uploaded bundles in an S3-compatible object store, `s3://bucket/prefix`, instead of
    /// the data directory's `uploads/` (docs/operations.md, "Beyond one machine"); credentials
    /// from the usual `AWS_ACCESS_KEY_ID` / `AWS_SECRET_ACCESS_KEY`. None by default.
    pub object_store: Option<String>,
    /// The object store's endpoint, for a store other than AWS (`http://minio:9000`): requests
    /// are then path-style, and plain HTTP is allowed.
    pub s3_endpoint: Option<String>,
    /// The object store's region (`AWS_REGION` otherwise; `us-east-1` where neither says).
    pub s3_region: Option<String>,
    /// The object store's access key, where it is not the environment's `AWS_ACCESS_KEY_ID`.
    pub s3_access_key_id: Option<String>,
    /// Its secret (`CRESTSCAN_S3_SECRET_ACCESS_KEY`, or the config file); never logged.
    #[serde(skip_serializing)]
    pub s3_secret_access_key: Option<String>,
    /// Publish every inspection's state changes, each finished result's summary and each
    /// station's status to this MQTT broker, `mqtt://host:1883` or `mqtts://host:8883`
    /// (docs/interchange.md, "MQTT events"). None (off) by default.
    pub mqtt_url: Option<String>,
    /// The site segment of the topics, `crestscan/<site>/…`: 1–64 of `A–Z a–z 0–9 _ -`.
    pub mqtt_site: String,
    /// The broker's user name and password, where it asks for them.
    pub mqtt_username: Option<String>,
    #[serde(skip_serializing)]
    pub mqtt_password: Option<String>,
    /// PEM certificates of the authorities an `mqtts://` broker's certificate is checked against
    /// (without it, the system's roots).
    pub mqtt_ca_file: Option<PathBuf>,
    /// Serve an OPC UA address space on OPC 40100-1 (Machine Vision, its NodeSet loaded) at this endpoint,
    /// `opc.tcp://host:4840` (docs/interchange.md, "OPC UA"). None (off) by default.
    pub opcua_endpoint: Option<String>,
    /// The OPC UA server's certificate store: its own certificate and key (made on the first
    /// start), the client certificates it trusts (`trusted/certs/`) and those it refused
    /// (`rejected/`). `<data_dir>/opcua-pki` by default.
    pub opcua_pki_dir: Option<PathBuf>,
    /// Offer only the signed and encrypted endpoints (Basic256Sha256, Aes256Sha256RsaPss); false
    /// also offers an unencrypted one (`None`), where passwords are still encrypted.
    pub opcua_require_encryption: bool,
}

/// A process's role ([`Settings::role`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Api,
    Worker,
    #[default]
    All,
}

impl Role {
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Api => "api",
            Role::Worker => "worker",
            Role::All => "all",
        }
    }

    /// Whether this process serves the API.
    pub fn serves_api(self) -> bool {
        self != Role::Worker
    }

    /// Whether this process runs jobs.
    pub fn runs_jobs(self) -> bool {
        self != Role::Api
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AuthMode {
    #[default]
    Off,
    Required,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LogFormat {
    #[default]
    Text,
    Json,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            role: Role::All,
            bind: SocketAddr::from(([127, 0, 0, 1], 8080)),
            allowed_hosts: Vec::new(),
            allowed_origins: Vec::new(),
            data_dir: PathBuf::from("crestscan-data"),
            workers: 1,
            compute_threads: 0,
            compute_nice: 10,
            compute_sched_idle: false,
            max_upload_mb: 4096,
            max_decompressed_mb: 0,
            max_compression_ratio: Limits::default().max_compression_ratio,
            max_manifest_kib: Limits::default().max_manifest_bytes >> 10,
            max_views: Limits::default().max_views,
            max_frames_per_view: Limits::default().max_frames_per_view,
            worker_memory_mb: 0,
            min_free_disk_mb: 1024,
            header_timeout_seconds: 10.0,
            upload_idle_seconds: 30.0,
            min_upload_kib_per_s: 64.0,
            max_concurrent_uploads: 32,
            max_uploads_per_client: 8,
            lease_seconds: 30.0,
            heartbeat_seconds: 2.0,
            max_attempts: 3,
            max_interruptions: 5,
            shutdown_grace_seconds: 30.0,
            poll_interval_ms: 500,
            upload_retention_days: 30.0,
            artifact_retention_days: 0.0,
            orphan_grace_seconds: 3600.0,
            log: "info".into(),
            log_format: LogFormat::Text,
            auth: AuthMode::Off,
            submissions_per_minute: 60,
            webhooks: Vec::new(),
            callback_origins: Vec::new(),
            callback_secrets: Vec::new(),
            webhook_timeout_seconds: 10.0,
            webhook_max_attempts: 15,
            webhook_retry_seconds: 5.0,
            otlp_endpoint: None,
            database_url: None,
            object_store: None,
            mqtt_url: None,
            mqtt_site: "plant".into(),
            mqtt_username: None,
            mqtt_password: None,
            mqtt_ca_file: None,
            opcua_endpoint: None,
            opcua_pki_dir: None,
            opcua_require_encryption: false,
            s3_endpoint: None,
            s3_region: None,
            s3_access_key_id: None,
            s3_secret_access_key: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: {message}")]
    File { path: String, message: String },
    #[error("{field}: {message}")]
    Invalid { field: &'static str, message: String },
}

impl Settings {
    /// Reads a TOML file whose keys are the field names (all optional).
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ConfigError::File { path: path.display().to_string(), message: e.to_string() })?;
        toml::from_str(&text)
            .map_err(|e| ConfigError::File { path: path.display().to_string(), message: e.to_string() })
    }

    // `!(x > 0.0)` rather than `x <= 0.0`: a NaN from a config file fails the check too.
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field, message: &str| Err(ConfigError::Invalid { field, message: message.into() });
        if self.max_upload_mb == 0 {
            return invalid("max_upload_mb", "must be at least 1");
        }
        if self.max_compression_ratio == 0 || self.max_manifest_kib == 0 {
            return invalid("max_compression_ratio", "and max_manifest_kib must be at least 1");
        }
        if self.max_views == 0 || self.max_frames_per_view < crate::bundle::MIN_FRAMES {
            return invalid(
                "max_views",
                &format!("must be at least 1, and max_frames_per_view at least {}", crate::bundle::MIN_FRAMES),
            );
        }
        if self.role == Role::Worker && self.workers == 0 {
            return invalid("workers", "must be at least 1 for a worker process (role worker)");
        }
        if !(0..=19).contains(&self.compute_nice) {
            return invalid("compute_nice", "must be 0 to 19");
        }
        if !(self.heartbeat_seconds > 0.0) {
            return invalid("heartbeat_seconds", "must be positive");
        }
        if !(self.lease_seconds >= 2.0 * self.heartbeat_seconds) {
            return invalid("lease_seconds", "must be at least twice heartbeat_seconds, or leases lapse while healthy");
        }
        if !(self.header_timeout_seconds > 0.0) {
            return invalid("header_timeout_seconds", "must be positive");
        }
        if !(self.upload_idle_seconds > 0.0) {
            return invalid("upload_idle_seconds", "must be positive");
        }
        if !(self.min_upload_kib_per_s >= 0.0) {
            return invalid("min_upload_kib_per_s", "must be non-negative (0: no floor)");
        }
        if self.max_concurrent_uploads == 0 || self.max_uploads_per_client == 0 {
            return invalid("max_concurrent_uploads", "and max_uploads_per_client must be at least 1");
        }
        if self.max_interruptions == 0 {
            return invalid("max_interruptions", "must be at least 1");
        }
        if self.max_attempts == 0 {
            return invalid("max_attempts", "must be at least 1");
        }
        if !(self.shutdown_grace_seconds >= 0.0) {
            return invalid("shutdown_grace_seconds", "must be non-negative");
        }
        if !(self.orphan_grace_seconds >= 0.0) {
            return invalid("orphan_grace_seconds", "must be non-negative");
        }
        if !(self.artifact_retention_days >= 0.0) {
            return invalid("artifact_retention_days", "must be non-negative (0 keeps them)");
        }
        if self.auth == AuthMode::Off && !self.bind.ip().is_loopback() {
            return Err(ConfigError::Invalid {
                field: "auth",
                message: format!(
                    "binding {} with auth off would let anyone on the network submit, read and cancel: run with \
                     --auth required (CRESTSCAN_AUTH=required; the first key: crestscan keys create --name NAME \
                     --scopes admin), or bind a loopback address such as 127.0.0.1",
                    self.bind
                ),
            });
        }
        if !(self.upload_retention_days >= 0.0) {
            return invalid("upload_retention_days", "must be non-negative (0 keeps uploads)");
        }
        self.validate_webhooks()
    }

    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    fn validate_webhooks(&self) -> Result<(), ConfigError> {
        use crate::service::webhook_settings::{CALLBACK, origin_of};
        let invalid = |field, message: String| Err(ConfigError::Invalid { field, message });
        if !(self.webhook_timeout_seconds > 0.0 && self.webhook_timeout_seconds <= 600.0) {
            return invalid("webhook_timeout_seconds", "must be more than 0 and at most 600".into());
        }
        if !(self.webhook_retry_seconds > 0.0 && self.webhook_retry_seconds <= 3600.0) {
            return invalid("webhook_retry_seconds", "must be more than 0 and at most 3600".into());
        }
        if self.webhook_max_attempts == 0 {
            return invalid("webhook_max_attempts", "must be at least 1".into());
        }
        let mut names = std::collections::HashSet::new();
        for (i, endpoint) in self.webhooks.iter().enumerate() {
            let name = &endpoint.name;
            let well_formed = !name.is_empty()
                && name.len() <= 64
                && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
            if !well_formed || name == CALLBACK {
                return invalid(
                    "webhooks",
                    format!("[{i}].name {name:?}: 1–64 letters, digits, - or _, and not {CALLBACK:?}"),
                );
            }
            if !names.insert(name) {
                return invalid("webhooks", format!("[{i}].name {name:?} is used twice"));
            }
            if let Err(e) = origin_of(&endpoint.url) {
                return invalid("webhooks", format!("[{i}] ({name}).url: {e}"));
            }
            if endpoint.secrets.is_empty() {
                return invalid("webhooks", format!("[{i}] ({name}).secrets: at least one (crestscan webhook-secret)"));
            }
            if let Some(e) = endpoint.secrets.iter().find_map(|s| Secret::parse(s).err()) {
                return invalid("webhooks", format!("[{i}] ({name}).secrets: {e}"));
            }
            if endpoint.events.is_empty() {
                return invalid("webhooks", format!("[{i}] ({name}).events: at least one, or leave it out for all"));
            }
        }
        for origin in &self.callback_origins {
            let parsed = reqwest::Url::parse(origin).map_err(|e| e.to_string());
            let bare = parsed.as_ref().is_ok_and(|u| u.path() == "/" && u.query().is_none() && u.fragment().is_none());
            if let Err(e) = origin_of(origin) {
                return invalid("callback_origins", e);
            }
            if !bare {
                return invalid(
                    "callback_origins",
                    format!(
                        "{origin:?}: an origin is a scheme, host and port, without a path (https://mes.plant.local:8443)"
                    ),
                );
            }
        }
        if let Some(e) = self.callback_secrets.iter().find_map(|s| Secret::parse(s).err()) {
            return invalid("callback_secrets", e);
        }
        if let Some(url) = &self.otlp_endpoint
            && let Err(e) = origin_of(url)
        {
            return invalid("otlp_endpoint", e);
        }
        if let Some(url) = &self.database_url
            && let Err(e) = check_database_url(url)
        {
            return invalid("database_url", e);
        }
        if let Some(url) = &self.object_store
            && let Err(e) = crate::service::store::blobs::S3Location::parse(url)
        {
            return invalid("object_store", e);
        }
        if let Some(url) = &self.s3_endpoint
            && let Err(e) = origin_of(url)
        {
            return invalid("s3_endpoint", e);
        }
        if self.s3_access_key_id.is_some() != self.s3_secret_access_key.is_some() {
            return invalid("s3_access_key_id", "and s3_secret_access_key are set together or not at all".into());
        }
        if self.s3_endpoint.is_some() && self.object_store.is_none() {
            return invalid("s3_endpoint", "is set without object_store (s3://bucket/prefix)".into());
        }
        if let Some(url) = &self.mqtt_url
            && let Err(e) = crate::service::mqtt_settings::Broker::parse(url, self.mqtt_ca_file.as_deref())
        {
            return invalid("mqtt_url", e);
        }
        if let Err(e) = crate::service::mqtt_settings::check_site(&self.mqtt_site) {
            return invalid("mqtt_site", e);
        }
        if let Some(url) = &self.opcua_endpoint
            && let Err(e) = crate::service::opcua_settings::Endpoint::parse(url)
        {
            return invalid("opcua_endpoint", e);
        }
        if self.mqtt_username.is_some() != self.mqtt_password.is_some() {
            return invalid("mqtt_username", "and mqtt_password are set together or not at all".into());
        }
        if !self.callback_origins.is_empty() && self.callback_secrets.is_empty() {
            return invalid(
                "callback_secrets",
                "callback_origins allows callbacks but no secret signs them: add one (crestscan webhook-secret)".into(),
            );
        }
        Ok(())
    }

    /// What reaches the object store besides its location ([`Settings::object_store`]).
    pub fn s3(&self) -> crate::service::store::blobs::S3Settings {
        crate::service::store::blobs::S3Settings {
            endpoint: self.s3_endpoint.clone(),
            region: self.s3_region.clone(),
            credentials: self.s3_access_key_id.clone().zip(self.s3_secret_access_key.clone()),
        }
    }

    pub fn database_path(&self) -> PathBuf {
        self.data_dir.join("crestscan.db")
    }

    /// Where the records live: PostgreSQL at `database_url`, else the data directory's SQLite file.
    pub fn database(&self) -> crate::service::store::Database {
        match &self.database_url {
            Some(url) => crate::service::store::Database::Postgres(url.clone()),
            None => crate::service::store::Database::Sqlite(self.database_path()),
        }
    }
    pub fn uploads_dir(&self) -> PathBuf {
        self.data_dir.join("uploads")
    }
    pub fn tmp_dir(&self) -> PathBuf {
        self.data_dir.join("tmp")
    }

    /// The OPC UA server's certificate store ([`Settings::opcua_pki_dir`], else under the data
    /// directory).
    pub fn opcua_pki_dir(&self) -> PathBuf {
        self.opcua_pki_dir.clone().unwrap_or_else(|| self.data_dir.join("opcua-pki"))
    }

    /// Installed learned models (`<name>.onnx` with its card `<name>.json`; docs/models.md).
    pub fn models_dir(&self) -> PathBuf {
        self.data_dir.join("models")
    }
    pub fn max_upload_bytes(&self) -> u64 {
        self.max_upload_mb.saturating_mul(1 << 20)
    }

    /// The caps a bundle is opened with, at ingest and in the worker alike.
    pub fn bundle_limits(&self) -> Limits {
        let decompressed_mb =
            if self.max_decompressed_mb > 0 { self.max_decompressed_mb } else { self.max_upload_mb.saturating_mul(4) };
        Limits {
            max_total_bytes: decompressed_mb.saturating_mul(1 << 20),
            max_manifest_bytes: self.max_manifest_kib.saturating_mul(1 << 10),
            max_views: self.max_views,
            max_frames_per_view: self.max_frames_per_view,
            max_compression_ratio: self.max_compression_ratio,
            ..Limits::default()
        }
    }

    /// The memory one inspection may take, bytes: the setting, else 60% of the machine's physical
    /// memory over the workers.
    pub fn worker_memory_bytes(&self) -> f64 {
        if self.worker_memory_mb > 0 {
            return self.worker_memory_mb as f64 * 1048576.0;
        }
        0.6 * physical_memory_bytes() / self.workers.max(1) as f64
    }

    /// The pipeline's compute threads: the setting, else one per core.
    pub fn compute_threads_resolved(&self) -> usize {
        if self.compute_threads > 0 {
            self.compute_threads
        } else {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        }
    }
}

/// The machine's physical memory (4 GiB where the system does not say).
fn physical_memory_bytes() -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: sysconf reads system constants; no memory is passed.
        let (pages, page) = unsafe { (libc::sysconf(libc::_SC_PHYS_PAGES), libc::sysconf(libc::_SC_PAGESIZE)) };
        if pages > 0 && page > 0 {
            return pages as f64 * page as f64;
        }
    }
    4.0 * 1024.0 * 1024.0 * 1024.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_overrides_defaults_and_unknown_keys_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("crestscan.toml");
        std::fs::write(&path, "bind = \"0.0.0.0:9000\"\nworkers = 2\n").unwrap();
        let s = Settings::from_file(&path).unwrap();
        assert_eq!(s.bind.port(), 9000);
        assert_eq!(s.workers, 2);
        assert_eq!(s.lease_seconds, Settings::default().lease_seconds);
        std::fs::write(&path, "wokers = 2\n").unwrap();
        let e = Settings::from_file(&path).unwrap_err().to_string();
        assert!(e.contains("wokers"), "{e}");
        let bad = Settings { lease_seconds: 1.0, heartbeat_seconds: 2.0, ..Settings::default() };
        assert!(bad.validate().unwrap_err().to_string().starts_with("lease_seconds"));
    }

    #[test]
    fn webhook_settings_read_from_the_file_and_are_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("crestscan.toml");
        let secret = "whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw";
        std::fs::write(
            &path,
            format!(
                "callback_origins = [\"https://mes.plant.local\"]\ncallback_secrets = [\"{secret}\"]\n\
                 [[webhooks]]\nname = \"mes\"\nurl = \"https://mes.plant.local/in\"\nsecrets = [\"{secret}\"]\n\
                 events = [\"inspection.failed\"]\n"
            ),
        )
        .unwrap();
        let s = Settings::from_file(&path).unwrap();
        s.validate().unwrap();
        assert_eq!(s.webhooks[0].events, vec![crate::service::webhook_settings::EventType::Failed]);
        let endpoint = s.webhooks[0].clone();
        let refused = |edit: &dyn Fn(&mut Settings)| {
            let mut bad = s.clone();
            edit(&mut bad);
            bad.validate().unwrap_err().to_string()
        };
        assert!(refused(&|b| b.webhooks[0].secrets = vec!["whsec_c2hvcnQ=".into()]).contains("24 to 64"));
        assert!(refused(&|b| b.webhooks[0].secrets.clear()).contains("at least one"));
        assert!(refused(&|b| b.webhooks[0].url = "ftp://x/".into()).contains("http"));
        assert!(refused(&|b| b.webhooks[0].name = "callback".into()).starts_with("webhooks"));
        assert!(refused(&|b| b.webhooks.push(endpoint.clone())).contains("twice"));
        assert!(
            refused(&|b| b.callback_origins = vec!["https://mes.plant.local/in".into()]).contains("without a path")
        );
        assert!(refused(&|b| b.callback_secrets.clear()).starts_with("callback_secrets"));
        assert!(refused(&|b| b.webhook_max_attempts = 0).starts_with("webhook_max_attempts"));
        assert!(refused(&|b| b.webhook_timeout_seconds = f64::INFINITY).starts_with("webhook_timeout_seconds"));
        assert!(refused(&|b| b.webhook_retry_seconds = f64::NAN).starts_with("webhook_retry_seconds"));
    }

    #[test]
    fn bundle_limits_follow_the_settings() {
        let s = Settings::default();
        let limits = s.bundle_limits();
        assert_eq!(limits.max_total_bytes, 4 * s.max_upload_bytes());
        assert_eq!(limits.max_manifest_bytes, Limits::default().max_manifest_bytes);
        let s = Settings {
            max_decompressed_mb: 100,
            max_manifest_kib: 64,
            max_views: 7,
            max_frames_per_view: 9,
            max_compression_ratio: 5,
            ..Settings::default()
        };
        let limits = s.bundle_limits();
        assert_eq!(limits.max_total_bytes, 100 << 20);
        assert_eq!(limits.max_manifest_bytes, 64 << 10);
        assert_eq!((limits.max_views, limits.max_frames_per_view, limits.max_compression_ratio), (7, 9, 5));
        for bad in [
            Settings { compute_nice: 20, ..Settings::default() },
            Settings { compute_nice: -1, ..Settings::default() },
            Settings { max_frames_per_view: 2, ..Settings::default() },
            Settings { max_compression_ratio: 0, ..Settings::default() },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }
}

/// A PostgreSQL URL this build can connect to: `postgres://` or `postgresql://`, with a host.
fn check_database_url(url: &str) -> Result<(), String> {
    let parsed = reqwest::Url::parse(url)
        .map_err(|e| format!("not a URL ({e}): postgres://user:password@host:5432/crestscan"))?;
    if !matches!(parsed.scheme(), "postgres" | "postgresql") {
        return Err(format!(
            "scheme {:?} is not PostgreSQL: postgres://user:password@host:5432/crestscan (leave it unset for the \
             data directory's SQLite file)",
            parsed.scheme()
        ));
    }
    if parsed.host_str().is_none_or(str::is_empty) {
        return Err("has no host: postgres://user:password@host:5432/crestscan".into());
    }
    Ok(())
}
