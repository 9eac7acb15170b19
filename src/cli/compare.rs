//! `crestscan compare`: a report against a simulated bundle's truth.

use anyhow::Result;
use crestscan::pipeline::report::Report;
use crestscan::sim::Truth;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct CompareArgs {
    report: PathBuf,
    truth: PathBuf,
}

impl CompareArgs {
    pub fn run(self) -> Result<()> {
        let report: Report = serde_json::from_slice(&std::fs::read(&self.report)?)?;
        let truth: Truth = serde_json::from_slice(&std::fs::read(&self.truth)?)?;
        println!("{}", serde_json::to_string_pretty(&crestscan::eval::compare(&report, &truth))?);
        Ok(())
    }
}
