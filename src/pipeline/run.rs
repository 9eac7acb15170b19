//! A run's context: progress reports, the cancellation flag and per-stage timings, so that the
//! stages themselves only compute.

use crate::pipeline::report::StageTiming;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Depth,
    Register,
    Fuse,
    Mesh,
    Profile,
    Rules,
}

impl Stage {
    pub fn as_str(self) -> &'static str {
        match self {
            Stage::Depth => "depth",
            Stage::Register => "register",
            Stage::Fuse => "fuse",
            Stage::Mesh => "mesh",
            Stage::Profile => "profile",
            Stage::Rules => "crest_and_rules",
        }
    }
}

/// Why a run stopped before its report: cancelled (not an error), or failed.
#[derive(Debug)]
pub(crate) enum Halt<E> {
    Cancelled,
    Failed(E),
}

impl<E> From<E> for Halt<E> {
    fn from(e: E) -> Self {
        Halt::Failed(e)
    }
}

pub(crate) struct Run<'a> {
    progress: &'a (dyn Fn(Stage, f64) + Sync),
    cancel: &'a AtomicBool,
    timings: Vec<StageTiming>,
    clock: Instant,
}

impl<'a> Run<'a> {
    pub(crate) fn new(progress: &'a (dyn Fn(Stage, f64) + Sync), cancel: &'a AtomicBool) -> Self {
        Self { progress, cancel, timings: Vec::new(), clock: Instant::now() }
    }

    pub(crate) fn progress(&self, stage: Stage, fraction: f64) {
        (self.progress)(stage, fraction)
    }

    pub(crate) fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }

    /// Err(Cancelled) once cancellation was asked for: checked between frames and stages.
    pub(crate) fn check<E>(&self) -> Result<(), Halt<E>> {
        if self.cancelled() { Err(Halt::Cancelled) } else { Ok(()) }
    }

    /// Ends `stage`: its time is the time since the previous stage ended.
    /// Records `stage`'s time since the last lap and restarts the clock; the time.
    pub(crate) fn lap(&mut self, stage: Stage) -> f64 {
        let seconds = self.clock.elapsed().as_secs_f64();
        self.timings.push(StageTiming { stage: stage.as_str().into(), seconds });
        self.clock = Instant::now();
        seconds
    }

    /// Records stages that ran side by side, each with its own time, and restarts the clock.
    pub(crate) fn record_side_by_side(&mut self, stages: &[(Stage, f64)]) {
        self.timings
            .extend(stages.iter().map(|&(stage, seconds)| StageTiming { stage: stage.as_str().into(), seconds }));
        self.clock = Instant::now();
    }

    /// Records a part of a stage under its own name (not a stage of its own for progress), without
    /// restarting the clock.
    pub(crate) fn record_part(&mut self, name: &str, seconds: f64) {
        self.timings.push(StageTiming { stage: name.into(), seconds });
    }

    pub(crate) fn into_timings(self) -> Vec<StageTiming> {
        self.timings
    }
}
