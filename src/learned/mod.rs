//! The seed's learned parts, run through ONNX Runtime: the runtime library found and loaded once
//! ([`runtime`]), the models shipped in the binary or installed beside it ([`Models`]), sessions
//! pooled across jobs ([`SessionPool`]), and the profile-correction MLP ([`profile_mlp`]).
//!
//! Nothing here is needed by the classical pipeline: a missing library or model is an error only
//! for an inspection that asked for a learned part, and it says what is missing and how to put it
//! in place.

pub mod depth_cnn;
pub mod effect;
mod pool;
pub mod profile_mlp;
mod registry;
mod runtime;

pub use pool::SessionPool;
pub use registry::{Model, ModelRole, ModelSource, ModelUse, Models, check_name, models, set_installed_dir};
pub use runtime::{RuntimeInfo, runtime};

use crate::problem::{Code, ErrorCode};

#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LearnedError {
    #[error(
        "ONNX Runtime is not available ({reason}; looked for {tried}). Run scripts/setup-onnxruntime, or \
         set CRESTSCAN_ORT_LIB to a libonnxruntime.so of version 1.31 or newer. The classical pipeline \
         (depth classic, profile correction off) needs none of it"
    )]
    RuntimeMissing { reason: String, tried: String },
    #[error("no {role} model named `{name}` (shipped: {shipped}; installed: {installed})")]
    UnknownModel { role: &'static str, name: String, shipped: String, installed: String },
    #[error("a model name is 1–64 letters, digits, '.', '_' or '-', starting with a letter or digit: `{name}`")]
    InvalidName { role: &'static str, name: String },
    #[error("model `{name}`: {message}")]
    Model { name: String, message: String },
}

impl ErrorCode for LearnedError {
    fn code(&self) -> Code {
        match self {
            LearnedError::RuntimeMissing { .. } | LearnedError::Model { .. } => Code::ModelUnavailable,
            LearnedError::UnknownModel { .. } | LearnedError::InvalidName { .. } => Code::UnknownModel,
        }
    }

    fn culprit(&self) -> Option<String> {
        match self {
            LearnedError::UnknownModel { role, .. } | LearnedError::InvalidName { role, .. } => {
                Some(role_option(role).into())
            }
            _ => None,
        }
    }
}

/// The pipeline option naming a model of the role called `role` ([`ModelRole::as_str`]).
fn role_option(role: &str) -> &'static str {
    [ModelRole::ProfileCorrection, ModelRole::Depth]
        .into_iter()
        .find(|r| r.as_str() == role)
        .map_or("profile.correction_model", ModelRole::option)
}
