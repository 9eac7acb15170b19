//! The queue's vocabulary, shared by the API (which submits) and the workers (which run): what an
//! inspection's stored options are, and the caps a bundle is opened with at ingest and in the
//! worker alike.

use crate::bundle::Limits;
use crate::pipeline::PipelineOptions;

/// What the API stores as an inspection's options (and the worker reads back).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct JobOptions {
    pub pipeline: PipelineOptions,
}

/// The caps a bundle is opened with, at ingest and in the worker alike.
pub fn bundle_limits(max_upload_bytes: u64) -> Limits {
    Limits { max_total_bytes: max_upload_bytes.saturating_mul(4), ..Limits::default() }
}
