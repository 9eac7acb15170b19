//! `crestscan pairs`: the profile-correction MLP's training pairs of one bundle (JSON lines): each
//! measured bin's pitch of reconstructed profile with the simulator's truth when the bundle has
//! one (training/profile_mlp.py reads them; docs/models.md).

use super::open_bundle;
use anyhow::{Context, Result};
use crestscan::bundle::OpenOptions;
use crestscan::domain::frame::Recording;
use crestscan::eval::cmm::CmmMeasurements;
use crestscan::eval::pairs::ProfileSet;
use crestscan::pipeline::profile::Correction;
use crestscan::pipeline::{self, PipelineOptions};
use crestscan::sim::Truth;
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

#[derive(clap::Args)]
pub struct PairsArgs {
    bundle: PathBuf,
    /// The JSON-lines file to write (created or replaced).
    #[arg(long)]
    out: PathBuf,
    /// The simulator's truth [default: the bundle's truth/truth.json, when it has one].
    #[arg(long, conflicts_with = "cmm")]
    truth: Option<PathBuf>,
    /// Pair with a CMM's heights instead (JSON or CSV, as `PUT /v1/inspections/{id}/cmm` takes
    /// them; a file ending in .json is JSON).
    #[arg(long)]
    cmm: Option<PathBuf>,
    /// Pipeline options as a JSON file (as `inspect --options`); profile correction is always off:
    /// the pairs are the reconstruction's own.
    #[arg(long)]
    options: Option<PathBuf>,
}

impl PairsArgs {
    pub fn run(self) -> Result<()> {
        let b = open_bundle(&self.bundle, OpenOptions::default())?;
        let mut options = super::options_over(PipelineOptions::default(), self.options)?;
        options.profile.correction = Correction::Off;
        let truth_path = match (&self.truth, &self.cmm) {
            (Some(p), _) => Some(p.clone()),
            (None, Some(_)) => None,
            (None, None) => Some(self.bundle.join("truth").join("truth.json")).filter(|p| p.is_file()),
        };
        let read = |p: &PathBuf| std::fs::read(p).with_context(|| format!("reading {}", p.display()));
        let truth: Option<Truth> = match &truth_path {
            Some(p) => Some(
                serde_json::from_slice(&read(p)?)
                    .with_context(|| format!("{}: not a simulation's truth", p.display()))?,
            ),
            None => None,
        };
        let cmm = match &self.cmm {
            Some(p) => {
                let bytes = read(p)?;
                let parsed = if p.extension().is_some_and(|e| e == "json") {
                    CmmMeasurements::from_json(&bytes)
                } else {
                    CmmMeasurements::from_csv(&bytes)
                };
                Some(parsed.map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?)
            }
            None => None,
        };
        let inspection = pipeline::inspect(&b, &options, &|_, _| {}, &AtomicBool::new(false))?.context("cancelled")?;
        let source = self.bundle.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let optics = b.optics();
        let set = ProfileSet::of(&inspection, &b.part().form, optics.object_pixel_mm(optics.focus_distance_mm));
        let pairs = match (&truth, &cmm) {
            (Some(t), _) => set.with_truth(&source, t),
            (None, Some(c)) => set.with_cmm(&source, c),
            (None, None) => set.unanswered(&source),
        };
        let partial = self.out.with_extension("partial");
        let mut w = BufWriter::new(std::fs::File::create(&partial).with_context(|| partial.display().to_string())?);
        for p in &pairs {
            serde_json::to_writer(&mut w, p)?;
            w.write_all(b"\n")?;
        }
        w.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        std::fs::rename(&partial, &self.out)?;
        eprintln!("{}: {} pairs", self.out.display(), pairs.len());
        Ok(())
    }
}
