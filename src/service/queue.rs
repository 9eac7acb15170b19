//! The queue's vocabulary, shared by the API (which submits) and the workers (which run): what an
//! inspection's stored options are, and the memory budget a bundle is held to at ingest and in
//! the worker alike (the bundle caps come from `Settings::bundle_limits`).

use crate::domain::frame::Recording;
use crate::pipeline::PipelineOptions;
use crate::problem::{Code, ErrorCode};
use crate::service::config::Settings;

/// What the API stores as an inspection's options (and the worker reads back).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct JobOptions {
    pub pipeline: PipelineOptions,
    /// Where the inspection's terminal state is POSTed (a webhook; its origin is in
    /// `callback_origins`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub callback_url: Option<String>,
}

/// A bundle whose inspection would need more memory than a worker may take.
#[derive(Debug, thiserror::Error)]
#[error(
    "inspecting this bundle needs about {needed_mib:.0} MiB at its peak ({terms}), more than the {budget_mib:.0} MiB \
     a worker may take (worker_memory_mb)"
)]
pub struct OverMemoryBudget {
    pub needed_mib: f64,
    pub budget_mib: f64,
    pub terms: String,
    pub culprit: &'static str,
}

impl ErrorCode for OverMemoryBudget {
    fn code(&self) -> Code {
        Code::InspectionTooLarge
    }
    fn culprit(&self) -> Option<String> {
        Some(self.culprit.to_string())
    }
}

/// Refuses a bundle whose estimated peak ([`crate::pipeline::memory`]) exceeds the worker's
/// budget: at upload, before the 202, and in the worker before it starts (the budget may have
/// been lowered since).
pub fn check_memory(
    recording: &dyn Recording,
    options: &PipelineOptions,
    settings: &Settings,
) -> Result<(), OverMemoryBudget> {
    let estimate = crate::pipeline::memory::estimate(recording, options, settings.compute_threads_resolved());
    let budget = settings.worker_memory_bytes();
    if estimate.peak_bytes <= budget {
        return Ok(());
    }
    let terms = estimate
        .terms
        .iter()
        .map(|(term, bytes)| format!("{term} {:.0} MiB", bytes / 1048576.0))
        .collect::<Vec<_>>()
        .join(", ");
    Err(OverMemoryBudget {
        needed_mib: estimate.peak_mib(),
        budget_mib: budget / 1048576.0,
        terms,
        culprit: estimate.culprit(),
    })
}
