//! crestscan: thread geometry of oil-country tubing and casing from focal stacks, and API 5B
//! black-crest acceptance.
//!
//! Data flows bundle → depth → cloud → register → fuse (the unrolled surface) → mesh and profile →
//! crest → rules → report. The modules below are listed in layer order (a blank line between each
//! keeps rustfmt from sorting them): each imports only the ones above it, and nothing above
//! [`service`] imports axum, sqlx or tokio (docs/architecture.md; `tests/it/layers.rs` checks it).

/// The error vocabulary: one typed [`problem::Code`] per failure, its status and title, no HTTP. A
/// leaf: every layer below may name its failures with it.
pub mod problem;

/// Numeric primitives: medians and robust scales, filters along a gappy sequence, run spans and
/// hysteresis, angles, small least squares, connected components. No domain knowledge.
pub mod numeric;

/// The domain: thread forms and the API 5B table, optics, parts, views and frames, the station,
/// arcs, the 5B rules.
pub mod domain;

/// The learned models (the seed's MLP) run through ONNX Runtime: the library, the shipped and
/// installed models, pooled sessions.
pub mod learned;

/// The input edge: the bundle v1 reader (directory, zip, tar) and its validation.
pub mod bundle;

/// The pure stages, in data-flow order, and [`pipeline::inspect`] that runs them.
pub mod pipeline;

/// The physically based focal-stack simulator and its ground truth.
pub mod sim;

/// The output edge: PLY, STL, GLB and PNG writers.
pub mod export;

/// Evaluation: a report against the simulator's truth (the benchmark suites) or a CMM.
pub mod eval;

/// The HTTP service: settings, telemetry, start-up, the job queue and workers, the store, the API.
pub mod service;
