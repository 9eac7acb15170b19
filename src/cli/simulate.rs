//! `crestscan simulate`: render a bundle with ground truth, or list the presets.

use anyhow::{Context, Result, bail};
use crestscan::sim;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct SimulateArgs {
    /// Preset name (see --list).
    #[arg(long, required_unless_present = "list")]
    preset: Option<String>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output directory (created).
    #[arg(long, required_unless_present = "list")]
    out: Option<PathBuf>,
    /// Print the presets, one per line: name, then a short description.
    #[arg(long)]
    list: bool,
    /// Write only truth/truth.json (no rendering).
    #[arg(long)]
    truth_only: bool,
}

impl SimulateArgs {
    pub fn run(self) -> Result<()> {
        let Self { preset, seed, out, list, truth_only } = self;
        if list {
            for p in sim::PRESETS {
                println!("{}\t{}", p.name, p.description);
            }
            return Ok(());
        }
        let (Some(name), Some(out)) = (preset, out) else { bail!("--preset and --out are required") };
        let Some(spec) = sim::preset(&name) else {
            let names: Vec<_> = sim::PRESETS.iter().map(|p| p.name).collect();
            bail!("unknown preset {name:?}; presets: {}", names.join(", "));
        };
        if truth_only {
            let truth = sim::write_truth(&spec, seed, &out)?;
            println!("{}: {}", truth.verdict.as_str(), truth.reasons.join(" | "));
            return Ok(());
        }
        let summary = sim::simulate(&spec, seed, &out).with_context(|| format!("simulating {name}"))?;
        println!(
            "{name} seed {seed}: {} frames, {} files, {:.1} MB in {:.1} s → {}; truth verdict {}",
            summary.frames,
            summary.files,
            summary.bytes as f64 / 1e6,
            summary.seconds,
            out.display(),
            summary.verdict.as_str()
        );
        Ok(())
    }
}
