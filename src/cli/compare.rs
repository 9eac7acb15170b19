//! `crestscan compare`: a report against a simulated bundle's truth.

use anyhow::{Context, Result};
use crestscan::pipeline::report::Report;
use crestscan::sim::Truth;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct CompareArgs {
    /// report.json, or the folder `inspect --out` wrote it to.
    report: PathBuf,
    /// truth.json, or the simulated bundle whose truth/truth.json it is.
    truth: PathBuf,
}

/// `path`, or `path/name` where `path` is a folder.
fn file_in(path: &Path, name: &str) -> PathBuf {
    if path.is_dir() { path.join(name) } else { path.to_path_buf() }
}

impl CompareArgs {
    pub fn run(self) -> Result<()> {
        let report_path = file_in(&self.report, "report.json");
        let truth_path = file_in(&self.truth, "truth/truth.json");
        let read = |path: &Path| std::fs::read(path).with_context(|| format!("reading {}", path.display()));
        let report: Report = serde_json::from_slice(&read(&report_path)?)
            .with_context(|| format!("{}: not an inspection report", report_path.display()))?;
        let truth: Truth = serde_json::from_slice(&read(&truth_path)?)
            .with_context(|| format!("{}: not a simulation's truth", truth_path.display()))?;
        println!("{}", serde_json::to_string_pretty(&crestscan::eval::compare(&report, &truth))?);
        Ok(())
    }
}
