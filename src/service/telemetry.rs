//! Logs (tracing) and Prometheus metrics (prometheus-client: a registry per app, so tests can run
//! several apps in one process): requests by matched route and status, request latency, queue
//! depth, job outcomes and durations, pipeline stage durations, verdicts and decisions, the build.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RequestLabels {
    method: String,
    route: String,
    status: u16,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RouteLabels {
    route: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StageLabels {
    stage: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct OutcomeLabels {
    outcome: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ResultLabels {
    verdict: String,
    decision: String,
    review_required: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct BuildLabels {
    version: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StateLabels {
    state: String,
}

type HistogramFamily<L> = Family<L, Histogram, fn() -> Histogram>;

pub struct Metrics {
    registry: Registry,
    requests: Family<RequestLabels, Counter>,
    request_seconds: HistogramFamily<RouteLabels>,
    stage_seconds: HistogramFamily<StageLabels>,
    jobs: Family<OutcomeLabels, Counter>,
    job_seconds: HistogramFamily<OutcomeLabels>,
    queue: Family<StateLabels, Gauge>,
    results: Family<ResultLabels, Counter>,
}

fn latency_histogram() -> Histogram {
    // 0.1 ms … 3.3 s.
    Histogram::new(exponential_buckets(0.0001, 2.0, 16))
}

fn job_histogram() -> Histogram {
    // 50 ms … 27 min.
    Histogram::new(exponential_buckets(0.05, 2.0, 16))
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("crestscan");
        let requests = Family::<RequestLabels, Counter>::default();
        let request_seconds: HistogramFamily<RouteLabels> = Family::new_with_constructor(latency_histogram);
        let stage_seconds: HistogramFamily<StageLabels> = Family::new_with_constructor(job_histogram);
        let jobs = Family::<OutcomeLabels, Counter>::default();
        let job_seconds: HistogramFamily<OutcomeLabels> = Family::new_with_constructor(job_histogram);
        let queue = Family::<StateLabels, Gauge>::default();
        registry.register("http_requests", "HTTP requests by method, matched route and status", requests.clone());
        registry.register(
            "http_request_duration_seconds",
            "HTTP request latency by matched route",
            request_seconds.clone(),
        );
        registry.register("pipeline_stage_duration_seconds", "Pipeline stage durations", stage_seconds.clone());
        registry.register(
            "jobs_finished",
            "Jobs finished by outcome (succeeded, failed, canceled, retry)",
            jobs.clone(),
        );
        registry.register("job_duration_seconds", "Job durations by outcome", job_seconds.clone());
        registry.register("queue_jobs", "Inspections queued and running", queue.clone());
        let results = Family::<ResultLabels, Counter>::default();
        registry.register(
            "inspection_results",
            "Succeeded inspections by verdict, ISO 14253-1 decision and whether they need review",
            results.clone(),
        );
        // The build, as Prometheus's convention has it: a gauge of 1 labelled with the version.
        let build = Family::<BuildLabels, Gauge>::default();
        build.get_or_create(&BuildLabels { version: env!("CARGO_PKG_VERSION").into() }).set(1);
        registry.register("build_info", "The running build (always 1), labelled with its version", build);
        Self { registry, requests, request_seconds, stage_seconds, jobs, job_seconds, queue, results }
    }

    pub fn request(&self, method: &str, route: &str, status: u16, seconds: f64) {
        self.requests.get_or_create(&RequestLabels { method: method.into(), route: route.into(), status }).inc();
        self.request_seconds.get_or_create(&RouteLabels { route: route.into() }).observe(seconds);
    }

    pub fn observe_stage(&self, stage: &str, seconds: f64) {
        self.stage_seconds.get_or_create(&StageLabels { stage: stage.into() }).observe(seconds);
    }

    pub fn job_finished(&self, outcome: &str, seconds: f64) {
        self.jobs.get_or_create(&OutcomeLabels { outcome: outcome.into() }).inc();
        self.job_seconds.get_or_create(&OutcomeLabels { outcome: outcome.into() }).observe(seconds);
    }

    /// One succeeded inspection's verdict (`accept`, `reject`), decision (`conforms`,
    /// `does_not_conform`, `indeterminate`) and review flag.
    pub fn inspection_result(&self, verdict: &str, decision: &str, review_required: bool) {
        let labels = ResultLabels {
            verdict: verdict.into(),
            decision: decision.into(),
            review_required: review_required.to_string(),
        };
        self.results.get_or_create(&labels).inc();
    }

    pub fn set_queue(&self, queued: i64, running: i64) {
        self.queue.get_or_create(&StateLabels { state: "queued".into() }).set(queued);
        self.queue.get_or_create(&StateLabels { state: "running".into() }).set(running);
    }

    /// The Prometheus text exposition.
    pub fn render(&self) -> String {
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry).expect("writing to a String cannot fail");
        out
    }
}

/// Installs the log subscriber once per process (later calls are no-ops, as in tests): text with
/// colours only when the log goes to a terminal (a log file or journal gets no escape codes), or
/// one JSON object a line.
pub fn init_logging(filter: &str, format: crate::service::config::LogFormat) {
    let _ = init(filter, format, None);
}

/// The trace export while it runs; [`Traces::shutdown`] sends the spans still batched.
pub struct Traces(opentelemetry_sdk::trace::SdkTracerProvider);

impl Traces {
    pub fn shutdown(self) {
        if let Err(e) = self.0.shutdown() {
            tracing::warn!(error = %e, "the last spans were not exported");
        }
    }
}

/// Installs the log subscriber and, with an `otlp_endpoint`, OpenTelemetry trace export over
/// OTLP/HTTP (protobuf): a span per request (`POST /v1/inspections`, by route) and per inspection
/// run, with the pipeline's stages as its events. Spans are batched on a thread of their own, so a
/// slow or absent collector holds nothing up (spans beyond the batch queue are dropped).
pub fn init(
    filter: &str,
    format: crate::service::config::LogFormat,
    otlp_endpoint: Option<&str>,
) -> Result<Option<Traces>, String> {
    use opentelemetry::trace::TracerProvider as _;
    use std::io::IsTerminal;
    use tracing_subscriber::Layer as _;
    use tracing_subscriber::layer::SubscriberExt as _;
    use tracing_subscriber::util::SubscriberInitExt as _;
    let filter =
        tracing_subscriber::EnvFilter::try_new(filter).unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let (otel, traces) = match otlp_endpoint {
        None => (None, None),
        Some(url) => {
            use opentelemetry_otlp::WithExportConfig as _;
            let exporter = opentelemetry_otlp::SpanExporter::builder()
                .with_http()
                .with_endpoint(url)
                .with_timeout(std::time::Duration::from_secs(10))
                .build()
                .map_err(|e| format!("otlp_endpoint: {e}"))?;
            let resource = opentelemetry_sdk::Resource::builder()
                .with_service_name("crestscan")
                .with_attribute(opentelemetry::KeyValue::new("service.version", env!("CARGO_PKG_VERSION")))
                .build();
            let provider = opentelemetry_sdk::trace::SdkTracerProvider::builder()
                .with_batch_exporter(exporter)
                .with_resource(resource)
                .build();
            let tracer = provider.tracer("crestscan");
            // The service's own spans and events, whatever the log filter shows.
            let ours = tracing_subscriber::filter::Targets::new().with_target("crestscan", tracing::Level::DEBUG);
            (Some(tracing_opentelemetry::layer().with_tracer(tracer).with_filter(ours)), Some(Traces(provider)))
        }
    };
    let base = tracing_subscriber::registry().with(otel);
    let installed = match format {
        crate::service::config::LogFormat::Text => base
            .with(
                tracing_subscriber::fmt::layer()
                    .with_target(false)
                    .with_ansi(std::io::stdout().is_terminal())
                    .with_filter(filter),
            )
            .try_init(),
        crate::service::config::LogFormat::Json => base
            .with(tracing_subscriber::fmt::layer().json().flatten_event(true).with_target(false).with_filter(filter))
            .try_init(),
    };
    match (installed, traces) {
        (Ok(()), traces) => Ok(traces),
        // Already installed (tests start many apps in one process): the first one stands.
        (Err(_), None) => Ok(None),
        (Err(e), Some(_)) => Err(format!("otlp_endpoint: a log subscriber was already installed ({e})")),
    }
}
