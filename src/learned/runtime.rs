//! Finding and loading the ONNX Runtime library, once per process.
//!
//! ort is built with `load-dynamic`: nothing is linked or downloaded at build time, and the library
//! (the PyPI wheel's, put in place by `scripts/setup-onnxruntime`) is opened on first use. Where it
//! is looked for, in order: `CRESTSCAN_ORT_LIB` (only there, when set); `libonnxruntime.so` beside
//! the executable (the Dockerfile's place); `onnxruntime/libonnxruntime.so` one and two folders up
//! from it (`target/onnxruntime/` for `target/release/crestscan` and for test binaries in
//! `target/debug/deps/`); the checkout's `target/onnxruntime/` as built.

use super::LearnedError;
use std::path::PathBuf;
use std::sync::OnceLock;

const LIBRARY: &str = "libonnxruntime.so";

/// The loaded library.
#[derive(Debug)]
pub struct RuntimeInfo {
    pub library: PathBuf,
    /// ONNX Runtime's own build description (version and commit).
    pub build: String,
    environment: ort::environment::Environment,
}

impl RuntimeInfo {
    pub fn environment(&self) -> &ort::environment::Environment {
        &self.environment
    }
}

static RUNTIME: OnceLock<Result<RuntimeInfo, LearnedError>> = OnceLock::new();

/// The runtime, loaded on the first call; the same answer (or the same error) after that.
pub fn runtime() -> Result<&'static RuntimeInfo, LearnedError> {
    RUNTIME.get_or_init(load).as_ref().map_err(Clone::clone)
}

fn candidates() -> Vec<PathBuf> {
    if let Some(path) = std::env::var_os("CRESTSCAN_ORT_LIB") {
        return vec![PathBuf::from(path)];
    }
    let mut paths = Vec::new();
    if let Some(dir) = std::env::current_exe().ok().and_then(|e| e.parent().map(PathBuf::from)) {
        paths.push(dir.join(LIBRARY));
        for up in dir.ancestors().skip(1).take(2) {
            paths.push(up.join("onnxruntime").join(LIBRARY));
        }
    }
    paths.push(PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/target/onnxruntime")).join(LIBRARY));
    paths
}

fn load() -> Result<RuntimeInfo, LearnedError> {
    let tried = candidates();
    let listed = || tried.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ");
    let Some(library) = tried.iter().find(|p| p.is_file()).cloned() else {
        return Err(LearnedError::RuntimeMissing { reason: "no such file".into(), tried: listed() });
    };
    let missing = |reason: String| LearnedError::RuntimeMissing { reason, tried: library.display().to_string() };
    let environment = ort::init_from(&library)
        .map_err(|e| missing(e.to_string()))?
        .with_name("crestscan")
        .build()
        .map_err(|e| missing(e.to_string()))?;
    Ok(RuntimeInfo { library, build: ort::info().trim().to_string(), environment })
}
