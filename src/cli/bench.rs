//! `crestscan bench`: a benchmark suite against the simulator's truth.

use super::{DepthArgs, LearnedArgs};
use anyhow::{Result, bail};
use crestscan::eval::{self, Suite};
use crestscan::pipeline::PipelineOptions;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct BenchArgs {
    /// accuracy: the suite the targets are read on (its own seeds; thresholds were chosen while
    /// looking at it); holdout: the defect presets again with seeds that chose nothing; tuning:
    /// the held-out seeds that chose a setting.
    #[arg(long, value_enum, default_value_t = SuiteArg::Accuracy)]
    suite: SuiteArg,
    /// Where renderings are cached [default: out/bench for accuracy, out/holdout for holdout and tuning].
    #[arg(long)]
    work: Option<PathBuf>,
    /// Only these cases of the suite (comma-separated): a preset (all its seeds) or
    /// preset-seed, e.g. bc-polished-3.
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Also write the results as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Also write each case's report here, as `<case>.json` (for looking at a setting offline,
    /// e.g. `scripts/u_variants.py`).
    #[arg(long)]
    reports: Option<PathBuf>,
    /// Time each case this many times (decode and inspection alternating) and report the
    /// medians: single timings on a shared machine scatter by tens of percent.
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// Pipeline options as a JSON file (the shape `POST /v1/inspections` takes under
    /// `pipeline`; keys it leaves out keep their defaults), for trying a setting on a suite.
    #[arg(long)]
    options: Option<PathBuf>,
    #[command(flatten)]
    depth: DepthArgs,
    #[command(flatten)]
    learned: LearnedArgs,
    /// No progress bar (it is drawn only on a terminal in any case).
    #[arg(long)]
    quiet: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SuiteArg {
    Accuracy,
    Holdout,
    /// The held-out seeds that chose a setting.
    Tuning,
    /// The defect presets at 40 random stations (seeds no setting was chosen on).
    Stations,
    /// The same at the 12 tuning stations settings are chosen on.
    StationsTuning,
    /// The same at 30 check stations (seeds 151–180), where a setting chosen on the tuning
    /// stations is checked besides the benchmark.
    StationsCheck,
}

impl From<SuiteArg> for Suite {
    fn from(s: SuiteArg) -> Self {
        match s {
            SuiteArg::Accuracy => Self::Accuracy,
            SuiteArg::Holdout => Self::Holdout,
            SuiteArg::Tuning => Self::Tuning,
            SuiteArg::Stations => Self::Stations,
            SuiteArg::StationsTuning => Self::StationsTuning,
            SuiteArg::StationsCheck => Self::StationsCheck,
        }
    }
}

impl BenchArgs {
    pub fn run(self) -> Result<()> {
        let Self { suite, work, only, json, reports, repeat, options: options_file, depth, learned, quiet } = self;
        let suite = Suite::from(suite);
        let work = work.unwrap_or_else(|| PathBuf::from(suite.default_work_dir()));
        if let Some(o) = only.iter().find(|o| !suite.cases().iter().any(|c| c.matches(o))) {
            let names: Vec<String> = suite.cases().iter().map(|c| c.name()).collect();
            bail!("--only {o:?} is no case of the {} suite; its cases: {}", suite.name(), names.join(", "));
        }
        let options = super::options_over(
            PipelineOptions { depth: depth.into(), profile: learned.apply(Default::default()), ..Default::default() },
            options_file,
        )?;
        let mut results = Vec::new();
        let stations = matches!(suite, Suite::Stations | Suite::StationsTuning | Suite::StationsCheck);
        // At a random station the pipeline may find no depth or no thread: that case is an
        // inspection refused, counted and shown, not the end of the benchmark.
        let mut refused: Vec<(String, String)> = Vec::new();
        let cases: Vec<_> =
            suite.cases().into_iter().filter(|c| only.is_empty() || only.iter().any(|o| c.matches(o))).collect();
        let bar = super::progress::bar(cases.len() as u64, "bench", quiet);
        // The log lines are printed whether or not the bar is drawn (a redirected run keeps them).
        let log = |line: String| bar.suspend(|| eprintln!("{line}"));
        for case in &cases {
            log(format!("bench: {} (seed {})", case.name(), case.seed));
            bar.set_message(case.name());
            match eval::run_case(case, &work, repeat, &options) {
                Ok(mut r) => {
                    // Written now and let go: a suite's reports are not held until its end.
                    if let (Some(dir), Some(report)) = (&reports, r.report.take()) {
                        std::fs::create_dir_all(dir)?;
                        std::fs::write(dir.join(format!("{}.json", case.name())), serde_json::to_vec(&report)?)?;
                    }
                    results.push(r)
                }
                Err(eval::BenchError::Pipeline(e)) if stations => {
                    log(format!("bench: {}: the pipeline refused: {e}", case.name()));
                    refused.push((case.name(), e.to_string()));
                }
                Err(e) => return Err(e.into()),
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        if stations {
            println!("{}", eval::table::station_table(&results, &refused));
        } else {
            println!("{}", eval::table(&results));
        }
        if let Some(path) = json {
            std::fs::write(&path, serde_json::to_vec_pretty(&results)?)?;
        }
        Ok(())
    }
}
