//! `crestscan validate`: the bundle reader's checks without an inspection.

use super::open_bundle;
use anyhow::Result;
use crestscan::bundle::{FrameCheck, OpenOptions};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct ValidateArgs {
    bundle: PathBuf,
    /// Decode every frame completely, not only its header.
    #[arg(long)]
    decode: bool,
}

impl ValidateArgs {
    pub fn run(self) -> Result<()> {
        let options = OpenOptions {
            frame_check: if self.decode { FrameCheck::Decode } else { FrameCheck::Headers },
            ..Default::default()
        };
        let b = open_bundle(&self.bundle, options)?;
        let threads = rayon::current_num_threads();
        let memory = crestscan::pipeline::memory::estimate(&b, &Default::default(), threads);
        println!(
            "{}: valid bundle v1; {} ({}), {} views, {} frames; an inspection takes about {:.0} MiB at its peak \
             on {threads} threads ({})",
            self.bundle.display(),
            b.part.connection.as_deref().unwrap_or("custom thread"),
            b.part.family().as_str(),
            b.views.len(),
            b.frame_count(),
            memory.peak_mib(),
            memory.terms.iter().map(|(t, v)| format!("{t} {:.0}", v / 1048576.0)).collect::<Vec<_>>().join(", ")
        );
        Ok(())
    }
}
