//! Submissions per API key in the last minute (`submissions_per_minute`): state the keys guard
//! ([`super::keys`]) keeps in the application state.

use std::collections::{HashMap, VecDeque};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Submissions per key in the last minute (`submissions_per_minute`).
#[derive(Default)]
pub struct SubmissionLimiter {
    recent: Mutex<HashMap<String, VecDeque<Instant>>>,
}

impl SubmissionLimiter {
    /// Counts a submission of `key`; Err(seconds to wait) when it would exceed `per_minute`.
    pub fn admit(&self, key: &str, per_minute: u32, now: Instant) -> Result<(), u64> {
        let mut recent = self.recent.lock().unwrap_or_else(|p| p.into_inner());
        let window = recent.entry(key.to_string()).or_default();
        while window.front().is_some_and(|t| now.duration_since(*t) >= Duration::from_secs(60)) {
            window.pop_front();
        }
        if window.len() >= per_minute as usize {
            let oldest = *window.front().expect("a full window is not empty");
            let wait = Duration::from_secs(60).saturating_sub(now.duration_since(oldest));
            return Err(wait.as_secs_f64().ceil().max(1.0) as u64);
        }
        window.push_back(now);
        Ok(())
    }
}
