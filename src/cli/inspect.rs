//! `crestscan inspect`: the whole pipeline on one bundle; the summary or the report, and the files.

use super::{DepthArgs, LearnedArgs, open_bundle};
use anyhow::{Context, Result};
use crestscan::bundle::OpenOptions;
use crestscan::domain::rules::ArcRule;
use crestscan::export::{glb, html, ply, png, stl};
use crestscan::pipeline::mesh::{Mesh, MeshOptions};
use crestscan::pipeline::profile::ProfileOptions;
use crestscan::pipeline::{self, PipelineOptions};
use std::io::BufWriter;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

#[derive(clap::Args)]
pub struct InspectArgs {
    bundle: PathBuf,
    /// Write report.json, report.html (the report as one self-contained page), report.qif (the
    /// results as a QIF 3.0 document), height-map.png, all-in-focus.png, mesh.ply, mesh.stl and
    /// mesh.glb here.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the report as JSON instead of the summary.
    #[arg(long)]
    json: bool,
    /// How the buttress 25% limit applies.
    #[arg(long, value_enum, default_value_t = ArcRuleArg::PerThread)]
    arc_rule: ArcRuleArg,
    /// Report each 1° bin's height as the trimmed mean (the middle half or so) of the 2N + 1
    /// bins centred on it along the helix (0: each bin's own fit, noisier; a dent of a degree
    /// or two is trimmed away, one of a few degrees flattened).
    #[arg(long, default_value_t = ProfileOptions::default().height_window_half_bins)]
    height_window_half_bins: usize,
    /// Pipeline options as a JSON file (the shape `POST /v1/inspections` takes under
    /// `pipeline`; keys it leaves out keep their defaults), written over the flags above.
    #[arg(long)]
    options: Option<PathBuf>,
    /// Inspect at a qualified station: apply this qualification (what `crestscan qualify`
    /// writes) where the bundle matches its fingerprint and form; the report says which.
    #[arg(long)]
    qualification: Option<PathBuf>,
    #[command(flatten)]
    depth: DepthArgs,
    #[command(flatten)]
    learned: LearnedArgs,
    /// No progress bar (it is drawn only on a terminal in any case).
    #[arg(long)]
    quiet: bool,
}

/// Spelt as the API spells `arc_rule` (`per_thread`); `per-thread`, the spelling before, is
/// still taken.
#[derive(Clone, Copy, clap::ValueEnum)]
enum ArcRuleArg {
    #[value(name = "per_thread", alias = "per-thread")]
    PerThread,
    Combined,
}

impl InspectArgs {
    pub fn run(self) -> Result<()> {
        let Self {
            bundle,
            out,
            json,
            arc_rule,
            height_window_half_bins,
            options: options_file,
            qualification,
            depth,
            learned,
            quiet,
        } = self;
        let at = match &qualification {
            None => None,
            Some(path) => {
                let bytes = std::fs::read(path).with_context(|| format!("--qualification {}", path.display()))?;
                let q: crestscan::domain::qualification::Qualification =
                    serde_json::from_slice(&bytes).with_context(|| {
                        format!(
                            "--qualification {}: not a qualification (crestscan qualify writes one)",
                            path.display()
                        )
                    })?;
                Some(pipeline::qualify::AtStation::Qualified(q))
            }
        };
        let b = open_bundle(&bundle, OpenOptions::default())?;
        let options = PipelineOptions {
            arc_rule: match arc_rule {
                ArcRuleArg::PerThread => ArcRule::PerThread,
                ArcRuleArg::Combined => ArcRule::Combined,
            },
            profile: learned.apply(ProfileOptions { height_window_half_bins, ..Default::default() }),
            depth: depth.into(),
            ..Default::default()
        };
        let options = super::options_over(options, options_file)?;
        let cancel = AtomicBool::new(false);
        let bar = super::progress::stages("inspect", quiet);
        // Stages in order, each a share of the bar by its usual part of the time.
        let progress = |stage: pipeline::Stage, fraction: f64| {
            let (start, share) = match stage {
                pipeline::Stage::Depth => (0.0, 0.6),
                pipeline::Stage::Register => (0.6, 0.1),
                pipeline::Stage::Fuse => (0.7, 0.15),
                pipeline::Stage::Mesh | pipeline::Stage::Profile => (0.85, 0.1),
                pipeline::Stage::Rules => (0.95, 0.05),
            };
            bar.set_message(stage.as_str());
            bar.set_position((1000.0 * (start + share * fraction.clamp(0.0, 1.0))) as u64);
        };
        let inspection =
            pipeline::inspect_at(&b, &options, crestscan::learned::models(), &progress, &cancel, at.as_ref());
        bar.finish_and_clear();
        let inspection = inspection?.context("cancelled")?;
        if let Some(dir) = &out {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let report_path = dir.join("report.json");
            std::fs::write(&report_path, crestscan::export::json::to_vec_pretty(&inspection.report)?)
                .with_context(|| format!("writing {}", report_path.display()))?;
            let height_map = png::height_map_png(&inspection.map)?;
            let mosaic = png::mosaic_png(&inspection.map)?;
            let (mosaic_preview, height_map_preview) = (
                png::preview_png(&mosaic, html::IMAGE_WIDTH_PX)?,
                png::preview_png(&height_map, html::IMAGE_WIDTH_PX)?,
            );
            // The page's 3D view takes a lighter mesh than the files: inlined, it is the page's
            // bulk (the standard ring's full mesh is 14 MB of GLB).
            let light = crestscan::pipeline::mesh::build(
                &inspection.map,
                &MeshOptions { max_vertices: html::VIEWER_MAX_VERTICES, ..options.mesh.clone() },
            )?;
            let mut light_glb = Vec::new();
            glb::write(&light, &mut light_glb)?;
            let html = html::report_page(
                &inspection.report,
                &html::PageInputs {
                    mosaic_png: Some(&mosaic_preview),
                    height_map_png: Some(&height_map_preview),
                    mesh: Some(html::MeshSource::Inline(&light_glb)),
                    full_images: Some(["all-in-focus.png".into(), "height-map.png".into()]),
                    ..Default::default()
                },
            );
            let qif =
                crestscan::export::qif::document(&inspection.report, &crestscan::export::qif::QifInputs::default());
            for (name, bytes) in [
                ("report.qif", qif.as_bytes()),
                ("height-map.png", &height_map[..]),
                ("all-in-focus.png", &mosaic[..]),
                ("report.html", html.as_bytes()),
            ] {
                let path = dir.join(name);
                std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
            }
            type Writer = fn(&Mesh, BufWriter<std::fs::File>) -> std::io::Result<()>;
            for (name, write) in
                [("mesh.ply", ply::write as Writer), ("mesh.stl", stl::write), ("mesh.glb", glb::write)]
            {
                let path = dir.join(name);
                let file = std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
                write(&inspection.mesh, BufWriter::new(file)).with_context(|| format!("writing {}", path.display()))?;
            }
        }
        if json {
            println!("{}", String::from_utf8(crestscan::export::json::to_vec_pretty(&inspection.report)?)?);
        } else {
            println!("{}", inspection.report.summary());
            if let Some(dir) = &out {
                println!(
                    "  wrote report.json, report.html, report.qif, height-map.png, all-in-focus.png, mesh.ply, mesh.stl and mesh.glb ({} vertices, {} triangles) to {}",
                    inspection.mesh.vertices.len(),
                    inspection.mesh.triangles.len(),
                    dir.display()
                );
            }
        }
        Ok(())
    }
}
