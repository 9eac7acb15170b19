//! `crestscan budget`: where a simulated bundle's height error enters along the pipeline
//! ([`crestscan::eval::budget`]), as tables, and as JSON for the benchmark's roll-up.

use super::open_bundle;
use anyhow::{Context, Result};
use crestscan::bundle::OpenOptions;
use crestscan::eval::budget::{self, Budget, Variant};
use crestscan::pipeline::PipelineOptions;
use crestscan::sim::Truth;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct BudgetArgs {
    /// Simulated bundles (folders with truth/ beside manifest.json).
    #[arg(required = true)]
    bundles: Vec<PathBuf>,
    /// Pipeline options as a JSON file (as `inspect --options`); the profile MLP runs as they say
    /// in the first run only.
    #[arg(long)]
    options: Option<PathBuf>,
    /// Also write every bundle's budget here, one JSON object per line.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Only these runs (comma-separated) [default: all six].
    #[arg(long, value_enum, value_delimiter = ',')]
    variants: Vec<VariantArg>,
    /// Print the per-thread tables too.
    #[arg(long)]
    threads: bool,
}

impl BudgetArgs {
    pub fn run(self) -> Result<()> {
        let options = super::options_over(PipelineOptions::default(), self.options)?;
        let variants = if self.variants.is_empty() {
            Variant::ALL.to_vec()
        } else {
            self.variants.iter().map(|&v| Variant::from(v)).collect()
        };
        let mut lines = String::new();
        let mut failed = Vec::new();
        for dir in &self.bundles {
            let bundle = open_bundle(dir, OpenOptions::default())?;
            let truth_path = dir.join("truth").join("truth.json");
            let truth: Truth = serde_json::from_slice(
                &std::fs::read(&truth_path).with_context(|| format!("reading {}", truth_path.display()))?,
            )
            .with_context(|| format!("{}: not a simulation's truth", truth_path.display()))?;
            let case = dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into_owned());
            // One bundle the pipeline refuses does not stop the others: it is named, and the
            // command fails at the end.
            let b = match budget::budget(&case, &bundle, dir, &truth, &options, crestscan::learned::models(), &variants)
            {
                Ok(b) => b,
                Err(e) => {
                    eprintln!("{}: {e}", dir.display());
                    failed.push(dir.display().to_string());
                    continue;
                }
            };
            print!("{}", text(&b, self.threads));
            lines.push_str(&serde_json::to_string(&b)?);
            lines.push('\n');
        }
        if let Some(path) = &self.json {
            std::fs::write(path, lines).with_context(|| format!("writing {}", path.display()))?;
        }
        if !failed.is_empty() {
            anyhow::bail!(
                "the pipeline refused {} of {} bundles: {}",
                failed.len(),
                self.bundles.len(),
                failed.join(", ")
            );
        }
        Ok(())
    }
}

fn um(v: Option<f64>) -> String {
    v.filter(|v| v.is_finite()).map_or_else(|| "—".into(), |v| format!("{v:+.1}"))
}

fn text(b: &Budget, threads: bool) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\n## {} ({}; object pixel {:.3} mm, depth of field ±{:.3} mm)\n",
        b.case, b.form, b.object_pixel_mm, b.depth_of_field_mm
    );
    let _ = writeln!(s, "Per-pixel depth by band along the view (µm; measured − true along the camera axis):\n");
    let _ = writeln!(s, "| band | crest | root | height (root − crest) | median \\|e\\| | trusted |");
    let _ = writeln!(s, "|---|---|---|---|---|---|");
    for d in &b.depth {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {:.0} | {:.0}% |",
            d.band,
            um(Some(d.crest_um)),
            um(Some(d.root_um)),
            um(Some(d.height_um)),
            d.median_abs_um,
            100.0 * d.trusted
        );
    }
    let _ = writeln!(s, "\nHeights with each stage's output replaced by truth (µm; medians over threads):\n");
    let _ = writeln!(
        s,
        "| variant | RMS | worst thread bias | scatter | coverage | z_h | surface crest | surface root | window crest | window root |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for v in &b.variants {
        let _ = writeln!(
            s,
            "| {} | {:.1} | {:.1} | {:.1} | {:.0}% | {:+.0} | {} | {} | {} | {} |",
            v.variant.label(),
            v.height_rms_um,
            v.thread_bias_max_um,
            v.scatter_median_um,
            100.0 * v.coverage,
            v.z_h_error_um,
            um(Some(v.surface_crest_um)),
            um(Some(v.surface_root_um)),
            um(Some(v.window_crest_um)),
            um(Some(v.window_root_um)),
        );
    }
    let _ = writeln!(s, "\nBins truth has and the run left without a height, by why:\n");
    for v in &b.variants {
        let why: Vec<String> = v.unmeasured.iter().map(|c| format!("{} {}", c.reason.as_str(), c.bins)).collect();
        let _ = writeln!(
            s,
            "- {}: {}",
            v.variant.label(),
            if why.is_empty() { "none".to_string() } else { why.join(", ") }
        );
    }
    for (variant, reason) in &b.refused {
        let _ = writeln!(s, "\n{}: refused: {reason}", variant.label());
    }
    if threads {
        for v in &b.variants {
            let _ = writeln!(s, "\n{} per thread (µm):\n", v.variant.label());
            let _ = writeln!(
                s,
                "| thread | height bias | scatter | surface crest | surface root | window crest | window root | bins |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
            for t in &v.threads {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} | {} | {} | {}/{} |",
                    t.index,
                    um(t.height_um),
                    um(t.scatter_um),
                    um(t.surface_crest_um),
                    um(t.surface_root_um),
                    um(t.window_crest_um),
                    um(t.window_root_um),
                    t.bins_measured,
                    t.bins_true
                );
            }
        }
    }
    s
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum VariantArg {
    AsConfigured,
    Pipeline,
    TruePoses,
    TrueDepth,
    TrueDepthEverywhere,
    TrueHelix,
}

impl From<VariantArg> for Variant {
    fn from(v: VariantArg) -> Self {
        match v {
            VariantArg::AsConfigured => Variant::AsConfigured,
            VariantArg::Pipeline => Variant::Pipeline,
            VariantArg::TruePoses => Variant::TruePoses,
            VariantArg::TrueDepth => Variant::TrueDepth,
            VariantArg::TrueDepthEverywhere => Variant::TrueDepthEverywhere,
            VariantArg::TrueHelix => Variant::TrueHelix,
        }
    }
}
