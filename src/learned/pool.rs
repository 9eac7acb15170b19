//! Sessions of one model, kept for reuse across jobs: `Session::run` takes `&mut self`, so each
//! concurrent run takes its own session; building one costs milliseconds to a second (graph
//! optimisation), running a small batch less.

use super::{LearnedError, runtime};
use ort::session::Session;
use std::sync::{Arc, Mutex};

pub struct SessionPool {
    name: String,
    bytes: Arc<[u8]>,
    idle: Mutex<Vec<Session>>,
    /// Sessions kept idle at most (one per worker thread): memory stays bounded however many
    /// runs once overlapped.
    max_idle: usize,
}

impl SessionPool {
    pub fn new(name: &str, bytes: Arc<[u8]>) -> Self {
        Self { name: name.into(), bytes, idle: Mutex::new(Vec::new()), max_idle: rayon::current_num_threads().max(1) }
    }

    fn open(&self) -> Result<Session, LearnedError> {
        let runtime = runtime()?;
        let error = |e: String| LearnedError::Model { name: self.name.clone(), message: e };
        // One thread per session: runs are parallel across sessions (rayon's workers), and on 2
        // cores one intra-op thread was faster than two under load (shared/notes/ort.md).
        Session::builder(runtime.environment())
            .map_err(|e| error(e.to_string()))?
            .with_intra_threads(1)
            .map_err(|e| error(e.to_string()))?
            .commit_from_memory(&self.bytes)
            .map_err(|e| error(e.to_string()))
    }

    /// Runs `f` on an idle session (or a new one), and keeps the session for the next run.
    pub fn with<T>(&self, f: impl FnOnce(&mut Session) -> Result<T, ort::Error>) -> Result<T, LearnedError> {
        let idle = self.idle.lock().unwrap_or_else(|e| e.into_inner()).pop();
        let mut session = match idle {
            Some(s) => s,
            None => self.open()?,
        };
        let out = f(&mut session).map_err(|e| LearnedError::Model { name: self.name.clone(), message: e.to_string() });
        let mut idle = self.idle.lock().unwrap_or_else(|e| e.into_inner());
        if idle.len() < self.max_idle {
            idle.push(session);
        }
        out
    }

    /// Sessions idle now (for tests of reuse).
    pub fn idle_sessions(&self) -> usize {
        self.idle.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}
