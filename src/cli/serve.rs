//! `crestscan serve` (the service; settings: flags > CRESTSCAN_* > config file > defaults) and
//! `crestscan healthcheck` (exit 0 when a local service answers, for container health checks).

use anyhow::{Context, Result, bail};
use crestscan::service::config::Settings;
use std::path::PathBuf;

pub fn healthcheck(addr: Option<std::net::SocketAddr>) -> Result<()> {
    use std::io::{Read, Write};
    let addr = addr.unwrap_or_else(|| {
        let port = std::env::var("CRESTSCAN_BIND")
            .ok()
            .and_then(|b| b.parse::<std::net::SocketAddr>().ok())
            .map_or(8080, |a| a.port());
        std::net::SocketAddr::from(([127, 0, 0, 1], port))
    });
    let timeout = std::time::Duration::from_secs(3);
    let mut stream =
        std::net::TcpStream::connect_timeout(&addr, timeout).with_context(|| format!("connecting to {addr}"))?;
    stream.set_read_timeout(Some(timeout))?;
    write!(stream, "GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")?;
    let mut head = [0u8; 12];
    stream.read_exact(&mut head)?;
    if &head[9..12] != b"200" {
        bail!("{addr}/healthz answered {}", String::from_utf8_lossy(&head));
    }
    Ok(())
}

#[derive(clap::Args)]
pub struct ServeArgs {
    /// TOML file with any of the settings below (snake_case keys).
    #[arg(long, env = "CRESTSCAN_CONFIG")]
    config: Option<PathBuf>,
    /// What this process does: all (the API and the workers), api (the API only) or worker (jobs
    /// only; /healthz, /readyz and /metrics on --bind) [default: all].
    #[arg(long, env = "CRESTSCAN_ROLE", value_enum)]
    role: Option<RoleArg>,
    /// Listen address [default: 127.0.0.1:8080].
    #[arg(long, env = "CRESTSCAN_BIND")]
    bind: Option<std::net::SocketAddr>,
    /// Host names besides IP addresses and localhost that requests may be addressed to,
    /// comma-separated (`*`: any) [default: none].
    #[arg(long, env = "CRESTSCAN_ALLOWED_HOSTS", value_delimiter = ',')]
    allowed_hosts: Option<Vec<String>>,
    /// Origins whose pages may post and read answers (CORS), comma-separated [default: none].
    #[arg(long, env = "CRESTSCAN_ALLOWED_ORIGINS", value_delimiter = ',')]
    allowed_origins: Option<Vec<String>>,
    /// Database, uploads and temporaries [default: ./crestscan-data].
    #[arg(long, env = "CRESTSCAN_DATA_DIR")]
    data_dir: Option<PathBuf>,
    /// Inspections run at once [default: 1; each uses every core].
    #[arg(long, env = "CRESTSCAN_WORKERS")]
    workers: Option<usize>,
    /// Compute threads for the pipeline [default: 0 = one per core].
    #[arg(long, env = "CRESTSCAN_COMPUTE_THREADS")]
    compute_threads: Option<usize>,
    /// Nice level (0-19) of the compute threads [default: 10].
    #[arg(long, env = "CRESTSCAN_COMPUTE_NICE")]
    compute_nice: Option<i32>,
    /// Run the compute threads SCHED_IDLE instead of at compute_nice (starves beside any busy
    /// neighbour) [default: false].
    #[arg(long, env = "CRESTSCAN_COMPUTE_SCHED_IDLE")]
    compute_sched_idle: Option<bool>,
    /// Largest upload in MiB [default: 4096].
    #[arg(long, env = "CRESTSCAN_MAX_UPLOAD_MB")]
    max_upload_mb: Option<u64>,
    /// Uncompressed MiB of all a bundle's files [default: 0 = four times max_upload_mb].
    #[arg(long, env = "CRESTSCAN_MAX_DECOMPRESSED_MB")]
    max_decompressed_mb: Option<u64>,
    /// Uncompressed over compressed size a zip entry of over 1 MiB may have [default: 100].
    #[arg(long, env = "CRESTSCAN_MAX_COMPRESSION_RATIO")]
    max_compression_ratio: Option<u64>,
    /// Largest manifest.json in KiB [default: 16384].
    #[arg(long, env = "CRESTSCAN_MAX_MANIFEST_KIB")]
    max_manifest_kib: Option<u64>,
    /// Views a bundle may have [default: 1000].
    #[arg(long, env = "CRESTSCAN_MAX_VIEWS")]
    max_views: Option<usize>,
    /// Frames one view may have [default: 500].
    #[arg(long, env = "CRESTSCAN_MAX_FRAMES_PER_VIEW")]
    max_frames_per_view: Option<usize>,
    /// Memory one inspection may take, MiB; bigger bundles are refused at upload [default: 0 =
    /// 60% of physical memory over the workers].
    #[arg(long, env = "CRESTSCAN_WORKER_MEMORY_MB")]
    worker_memory_mb: Option<u64>,
    /// Free space the data directory keeps, MiB: uploads that would leave less get 507 [default:
    /// 1024].
    #[arg(long, env = "CRESTSCAN_MIN_FREE_DISK_MB")]
    min_free_disk_mb: Option<u64>,
    /// Seconds a connection may take to send a request's head, or sit idle [default: 10].
    #[arg(long, env = "CRESTSCAN_HEADER_TIMEOUT_SECONDS")]
    header_timeout_seconds: Option<f64>,
    /// Seconds an upload may send nothing before it is cut off (408) [default: 30].
    #[arg(long, env = "CRESTSCAN_UPLOAD_IDLE_SECONDS")]
    upload_idle_seconds: Option<f64>,
    /// Average KiB/s an upload must keep once upload_idle_seconds have passed [default: 64].
    #[arg(long, env = "CRESTSCAN_MIN_UPLOAD_KIB_PER_S")]
    min_upload_kib_per_s: Option<f64>,
    /// Uploads received at once, all clients (503 beyond) [default: 32].
    #[arg(long, env = "CRESTSCAN_MAX_CONCURRENT_UPLOADS")]
    max_concurrent_uploads: Option<usize>,
    /// Uploads received at once from one client address (429 beyond) [default: 8].
    #[arg(long, env = "CRESTSCAN_MAX_UPLOADS_PER_CLIENT")]
    max_uploads_per_client: Option<usize>,
    /// Job lease in seconds [default: 30].
    #[arg(long, env = "CRESTSCAN_LEASE_SECONDS")]
    lease_seconds: Option<f64>,
    /// Heartbeat interval in seconds [default: 2].
    #[arg(long, env = "CRESTSCAN_HEARTBEAT_SECONDS")]
    heartbeat_seconds: Option<f64>,
    /// Retryable failures before a job is failed [default: 3].
    #[arg(long, env = "CRESTSCAN_MAX_ATTEMPTS")]
    max_attempts: Option<u32>,
    /// Deaths of the process running a job before it is failed as poisonous [default: 5].
    #[arg(long, env = "CRESTSCAN_MAX_INTERRUPTIONS")]
    max_interruptions: Option<u32>,
    /// Seconds running jobs get to finish at shutdown [default: 30].
    #[arg(long, env = "CRESTSCAN_SHUTDOWN_GRACE_SECONDS")]
    shutdown_grace_seconds: Option<f64>,
    /// Idle workers poll this often, in ms [default: 500].
    #[arg(long, env = "CRESTSCAN_POLL_INTERVAL_MS")]
    poll_interval_ms: Option<u64>,
    /// Days uploads of finished inspections are kept; 0 keeps them [default: 30].
    #[arg(long, env = "CRESTSCAN_UPLOAD_RETENTION_DAYS")]
    upload_retention_days: Option<f64>,
    /// Days meshes and images of finished inspections are kept; 0 keeps them [default: 0].
    #[arg(long, env = "CRESTSCAN_ARTIFACT_RETENTION_DAYS")]
    artifact_retention_days: Option<f64>,
    /// Seconds an artifact object no inspection names is kept before the sweep deletes it
    /// [default: 3600].
    #[arg(long, env = "CRESTSCAN_ORPHAN_GRACE_SECONDS")]
    orphan_grace_seconds: Option<f64>,
    /// Publish inspection and station events to this MQTT broker, mqtt://host:1883 or
    /// mqtts://host:8883 (off by default).
    #[arg(long, env = "CRESTSCAN_MQTT_URL")]
    mqtt_url: Option<String>,
    /// The topics' site segment, crestscan/<site>/… [default: plant].
    #[arg(long, env = "CRESTSCAN_MQTT_SITE")]
    mqtt_site: Option<String>,
    /// The MQTT broker's user name.
    #[arg(long, env = "CRESTSCAN_MQTT_USERNAME")]
    mqtt_username: Option<String>,
    /// Its password.
    #[arg(long, env = "CRESTSCAN_MQTT_PASSWORD", hide_env_values = true)]
    mqtt_password: Option<String>,
    /// PEM roots an mqtts:// broker's certificate is checked against [default: the system's].
    #[arg(long, env = "CRESTSCAN_MQTT_CA_FILE")]
    mqtt_ca_file: Option<PathBuf>,
    /// Serve an OPC UA address space on OPC 40100-1 (Machine Vision, its NodeSet loaded) at this endpoint,
    /// opc.tcp://host:4840 (off by default).
    #[arg(long, env = "CRESTSCAN_OPCUA_ENDPOINT")]
    opcua_endpoint: Option<String>,
    /// The OPC UA server's certificate store [default: <data-dir>/opcua-pki].
    #[arg(long, env = "CRESTSCAN_OPCUA_PKI_DIR")]
    opcua_pki_dir: Option<PathBuf>,
    /// Offer only signed and encrypted OPC UA endpoints.
    #[arg(long, env = "CRESTSCAN_OPCUA_REQUIRE_ENCRYPTION")]
    opcua_require_encryption: bool,
    /// Log filter [default: info].
    #[arg(long, env = "CRESTSCAN_LOG")]
    log: Option<String>,
    /// Log lines as text (colours only on a terminal) or JSON, one object a line [default: text].
    #[arg(long, value_enum, env = "CRESTSCAN_LOG_FORMAT")]
    log_format: Option<LogFormatArg>,
    /// `required`: every route but /healthz and /readyz needs an API key (crestscan keys create);
    /// `off` is allowed on a loopback address only [default: off].
    #[arg(long, value_enum, env = "CRESTSCAN_AUTH")]
    auth: Option<AuthArg>,
    /// Submissions per API key per minute, 429 beyond (0: no limit) [default: 60].
    #[arg(long, env = "CRESTSCAN_SUBMISSIONS_PER_MINUTE")]
    submissions_per_minute: Option<u32>,
    /// The only origins (scheme://host:port) a submission's callback_url may point to,
    /// comma-separated [default: none: callbacks are refused]. Webhook endpoints of the service's
    /// own are `[[webhooks]]` tables of the config file.
    #[arg(long, env = "CRESTSCAN_CALLBACK_ORIGINS", value_delimiter = ',')]
    callback_origins: Option<Vec<String>>,
    /// Secrets signing callbacks (whsec_…, crestscan webhook-secret), comma-separated; each signs.
    #[arg(long, env = "CRESTSCAN_CALLBACK_SECRETS", value_delimiter = ',', hide_env_values = true)]
    callback_secrets: Option<Vec<String>>,
    /// The longest one webhook attempt may take, seconds [default: 10].
    #[arg(long, env = "CRESTSCAN_WEBHOOK_TIMEOUT_SECONDS")]
    webhook_timeout_seconds: Option<f64>,
    /// Attempts of a webhook delivery before it is given up [default: 15].
    #[arg(long, env = "CRESTSCAN_WEBHOOK_MAX_ATTEMPTS")]
    webhook_max_attempts: Option<u32>,
    /// The wait after a delivery's first failure, seconds, doubling to an hour [default: 5].
    #[arg(long, env = "CRESTSCAN_WEBHOOK_RETRY_SECONDS")]
    webhook_retry_seconds: Option<f64>,
    /// Export traces (OpenTelemetry, OTLP/HTTP protobuf) to this collector URL, e.g.
    /// http://collector:4318/v1/traces [default: none].
    #[arg(long, env = "CRESTSCAN_OTLP_ENDPOINT")]
    otlp_endpoint: Option<String>,
    /// Keep the records in PostgreSQL, postgres://user:password@host:5432/crestscan, instead of the
    /// data directory's SQLite file (created if the server lacks it) [default: none].
    #[arg(long, env = "CRESTSCAN_DATABASE_URL", hide_env_values = true)]
    database_url: Option<String>,
    /// Keep uploaded bundles in an S3-compatible object store, s3://bucket/prefix, instead of the
    /// data directory (credentials from AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY) [default: none].
    #[arg(long, env = "CRESTSCAN_OBJECT_STORE")]
    object_store: Option<String>,
    #[command(flatten)]
    s3: super::object_store::S3Args,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum RoleArg {
    Api,
    Worker,
    All,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum AuthArg {
    Off,
    Required,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum LogFormatArg {
    Text,
    Json,
}

impl From<LogFormatArg> for crestscan::service::config::LogFormat {
    fn from(f: LogFormatArg) -> Self {
        match f {
            LogFormatArg::Text => Self::Text,
            LogFormatArg::Json => Self::Json,
        }
    }
}

impl ServeArgs {
    fn settings(self) -> Result<Settings> {
        let mut s = match &self.config {
            Some(path) => Settings::from_file(path)?,
            None => Settings::default(),
        };
        macro_rules! set {
            ($($field:ident),*) => { $( if let Some(v) = self.$field { s.$field = v; } )* };
        }
        set!(
            bind,
            allowed_hosts,
            allowed_origins,
            data_dir,
            workers,
            compute_threads,
            compute_nice,
            compute_sched_idle,
            max_upload_mb,
            max_decompressed_mb,
            max_compression_ratio,
            max_manifest_kib,
            max_views,
            max_frames_per_view,
            worker_memory_mb,
            min_free_disk_mb,
            header_timeout_seconds,
            upload_idle_seconds,
            min_upload_kib_per_s,
            max_concurrent_uploads,
            max_uploads_per_client,
            lease_seconds,
            heartbeat_seconds,
            max_attempts,
            max_interruptions,
            shutdown_grace_seconds,
            poll_interval_ms,
            upload_retention_days,
            artifact_retention_days,
            orphan_grace_seconds,
            log,
            submissions_per_minute,
            callback_origins,
            callback_secrets,
            webhook_timeout_seconds,
            webhook_max_attempts,
            webhook_retry_seconds,
            mqtt_site
        );
        for (field, value) in [
            (&mut s.mqtt_url, self.mqtt_url),
            (&mut s.mqtt_username, self.mqtt_username),
            (&mut s.mqtt_password, self.mqtt_password),
        ] {
            if value.is_some() {
                *field = value;
            }
        }
        if self.mqtt_ca_file.is_some() {
            s.mqtt_ca_file = self.mqtt_ca_file;
        }
        if self.opcua_endpoint.is_some() {
            s.opcua_endpoint = self.opcua_endpoint;
        }
        if self.opcua_pki_dir.is_some() {
            s.opcua_pki_dir = self.opcua_pki_dir;
        }
        if self.opcua_require_encryption {
            s.opcua_require_encryption = true;
        }
        if let Some(url) = self.otlp_endpoint {
            s.otlp_endpoint = Some(url);
        }
        if let Some(role) = self.role {
            s.role = match role {
                RoleArg::Api => crestscan::service::config::Role::Api,
                RoleArg::Worker => crestscan::service::config::Role::Worker,
                RoleArg::All => crestscan::service::config::Role::All,
            };
        }
        s.database_url = self.database_url.or(s.database_url.take());
        s.object_store = self.object_store.or(s.object_store.take());
        self.s3.apply(&mut s);
        if let Some(auth) = self.auth {
            s.auth = match auth {
                AuthArg::Off => crestscan::service::config::AuthMode::Off,
                AuthArg::Required => crestscan::service::config::AuthMode::Required,
            };
        }
        if let Some(format) = self.log_format {
            s.log_format = format.into();
        }
        s.validate()?;
        Ok(s)
    }

    pub fn run(self) -> Result<()> {
        let settings = self.settings()?;
        let traces =
            crestscan::service::telemetry::init(&settings.log, settings.log_format, settings.otlp_endpoint.as_deref())
                .map_err(anyhow::Error::msg)?;
        let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
        let served = runtime.block_on(async move {
        let app = crestscan::service::startup::Application::build(settings.clone()).await?;
        // One line on stdout that scripts (and the tests) read to find the port.
        println!("crestscan listening on http://{}", app.address());
        tracing::info!(address = %app.address(), data_dir = %settings.data_dir.display(), workers = settings.workers, "serving");
        app.run_until(crestscan::service::startup::shutdown_signal()).await?;
        Ok::<_, anyhow::Error>(())
    });
        // A job that ignored its stop request still holds a blocking thread: the process ends
        // without it (its lease was released, or lapses).
        runtime.shutdown_timeout(std::time::Duration::from_secs(1));
        // The spans still batched go to the collector before the process ends.
        if let Some(traces) = traces {
            traces.shutdown();
        }
        served
    }
}
