//! The height error budget: where along the pipeline a simulated bundle's height error enters.
//!
//! The bundle is inspected several times, each time with one more stage's output replaced by the
//! simulator's truth ([`crate::pipeline::Substitutes`]): the registered poses, then the depth maps
//! (at the pixels depth from focus trusted, then at every pixel), then the helix. What a variant
//! removes from the error is the share of the stage it replaced; what remains with true depth,
//! poses and helix is what fusion and the windows add on their own, which no station's optics
//! explain. Each variant is also measured at each step against truth at that step: the fused
//! surface at the crests and roots, the windows' readings, the helix phase, the heights per
//! thread. The depth maps themselves are read per pixel, crest and root apart, in bands along
//! the view's axis (where a perspective view sees the flanks obliquely).
//!
//! Heights are the classical ones (the profile MLP is off) in every run but the first, which runs
//! the options as given: the budget is of the measurement, and the MLP's effect is the difference
//! between the first two rows.

use crate::bundle::Bundle;
use crate::domain::optics::{Optics, ViewPose};
use crate::pipeline::depth::DepthMap;
use crate::pipeline::profile::{Helix, ThreadMeasure, UnmeasuredCount, count_unmeasured, sum_unmeasured};
use crate::pipeline::surface::UnrolledMap;
use crate::pipeline::{Inspection, PipelineOptions, Substitutes};
use crate::sim::Truth;
use crate::sim::part::PartModel;
use serde::Serialize;
use std::path::Path;

/// Bands along a view's axis the per-pixel depth is read in.
pub const BANDS: usize = 8;

/// One band of the views (pixel columns, the pipe's axis), over every view: depth error (measured
/// − true, along the camera axis, µm; positive: read too far, a radius too low) at crest and root
/// pixels, and the height error the two imply.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DepthBand {
    pub band: usize,
    pub crest_pixels: usize,
    pub root_pixels: usize,
    /// Median error at crest pixels and at root pixels.
    pub crest_um: f64,
    pub root_um: f64,
    /// Root's median error less the crest's: the height error of the per-pixel depths.
    pub height_um: f64,
    /// Median |error| over the band's trusted crest and root pixels.
    pub median_abs_um: f64,
    /// Share of the band's crest and root pixels depth from focus trusted.
    pub trusted: f64,
}

/// One thread in one variant: measured − true, medians over its bins, µm.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ThreadBudget {
    pub index: u32,
    /// Reported heights (the helix's trimmed mean).
    pub height_um: Option<f64>,
    /// Scatter of the height error about that median (RMS), µm.
    pub scatter_um: Option<f64>,
    /// The fused surface at the thread's crest flat and its two roots' flats (cells within the
    /// windows' half widths of the true centre lines).
    pub surface_crest_um: Option<f64>,
    pub surface_root_um: Option<f64>,
    /// The windows' readings: the crest fit, and the root the height was taken from (crest fit
    /// less height), against the true radii at the true crest line.
    pub window_crest_um: Option<f64>,
    pub window_root_um: Option<f64>,
    /// Bins measured of those truth has.
    pub bins_measured: usize,
    pub bins_true: usize,
    /// Of those truth has, the bins without a height by why.
    pub unmeasured: Vec<UnmeasuredCount>,
}

/// One run of the pipeline with some stages' outputs replaced by truth.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VariantBudget {
    pub variant: Variant,
    pub height_rms_um: f64,
    /// The largest |median error| of any thread.
    pub thread_bias_max_um: f64,
    /// Median over threads of each one's scatter about its own bias.
    pub scatter_median_um: f64,
    /// Share of truth's (thread, bin) heights measured.
    pub coverage: f64,
    /// The helix's z_h − truth's, wrapped into a pitch, µm.
    pub z_h_error_um: f64,
    /// Surface error at crests and roots, medians over threads, µm.
    pub surface_crest_um: f64,
    pub surface_root_um: f64,
    pub window_crest_um: f64,
    pub window_root_um: f64,
    /// Of the bins truth has, those without a height by why, over the threads.
    pub unmeasured: Vec<UnmeasuredCount>,
    /// Where a learned model changed the heights: the RMS of its change (reported − classical,
    /// over the bins both have), µm, which the model's effect relates its error to
    /// (docs/models.md, "Choosing when it runs").
    pub correction_rms_um: Option<f64>,
    pub threads: Vec<ThreadBudget>,
}

/// Which outputs a run took from truth.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Variant {
    /// The pipeline with the options as given, the profile MLP included where they run it (the
    /// default `auto`: at object pixels over 0.06 mm); the window columns are the classical fits.
    AsConfigured,
    /// The pipeline as it runs, the profile MLP off: the classical measurement.
    Pipeline,
    /// The true poses in fusion.
    TruePoses,
    /// True poses, and true depth at the pixels depth from focus trusted.
    TrueDepth,
    /// True poses, and true depth at every pixel that sees the part.
    TrueDepthEverywhere,
    /// True depth (trusted pixels), poses and helix: what fusion and the windows add.
    TrueHelix,
}

impl Variant {
    pub const ALL: [Variant; 6] = [
        Variant::AsConfigured,
        Variant::Pipeline,
        Variant::TruePoses,
        Variant::TrueDepth,
        Variant::TrueDepthEverywhere,
        Variant::TrueHelix,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Variant::AsConfigured => "as configured (profile MLP as the options say)",
            Variant::Pipeline => "pipeline (MLP off)",
            Variant::TruePoses => "+ true poses",
            Variant::TrueDepth => "+ true depth (trusted pixels)",
            Variant::TrueDepthEverywhere => "+ true depth (every pixel)",
            Variant::TrueHelix => "+ true depth, true helix",
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Budget {
    pub case: String,
    pub object_pixel_mm: f64,
    pub depth_of_field_mm: f64,
    pub form: String,
    pub depth: Vec<DepthBand>,
    pub variants: Vec<VariantBudget>,
    /// The runs the pipeline refused (no thread found, say), with its reason: a substitution can
    /// leave the helix without a spectrum where the pipeline's own run found one.
    pub refused: Vec<(Variant, String)>,
}

#[derive(Debug, thiserror::Error)]
pub enum BudgetError {
    /// The simulator's truth lacks what the budget reads (a pose, a depth map), named.
    #[error("{0}")]
    Truth(String),
    #[error(transparent)]
    Pipeline(#[from] crate::pipeline::PipelineError),
}

/// The budget of one simulated bundle (its truth/ beside the manifest).
pub fn budget(
    case: &str,
    bundle: &Bundle,
    dir: &Path,
    truth: &Truth,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    variants_wanted: &[Variant],
) -> Result<Budget, BudgetError> {
    let configured = options;
    let mut options = options.clone();
    options.profile.correction = crate::pipeline::profile::Correction::Off;
    let true_depth: Vec<Vec<f32>> = bundle
        .views
        .iter()
        .map(|view| crate::sim::read_true_depth(dir, &view.id))
        .collect::<Result<_, _>>()
        .map_err(BudgetError::Truth)?;
    let true_poses = truth.poses_of(&bundle.views).map_err(BudgetError::Truth)?;
    let model = &truth.part_model;
    let trusted_only = |v: usize, map: &mut DepthMap| substitute_depth(map, &true_depth[v], true);
    let everywhere = |v: usize, map: &mut DepthMap| substitute_depth(map, &true_depth[v], false);
    let true_helix = |h: &Helix| Helix {
        z_h_mm: model.helix_z_h_mm,
        pitch_mm: model.form.pitch_mm,
        local_offsets_mm: Vec::new(),
        ..h.clone()
    };
    let mut variants = Vec::new();
    let mut refused = Vec::new();
    let mut depth = Vec::new();
    for &variant in variants_wanted {
        let subs = Substitutes {
            depth: match variant {
                Variant::AsConfigured | Variant::Pipeline | Variant::TruePoses => None,
                Variant::TrueDepth | Variant::TrueHelix => Some(&trusted_only),
                Variant::TrueDepthEverywhere => Some(&everywhere),
            },
            poses: (!matches!(variant, Variant::AsConfigured | Variant::Pipeline)).then_some(true_poses.as_slice()),
            helix: (variant == Variant::TrueHelix).then_some(&true_helix),
            keep_depth_maps: true,
        };
        let run_options = if variant == Variant::AsConfigured { configured } else { &options };
        let inspection = match crate::pipeline::inspect_substituted(bundle, run_options, models, &subs) {
            Ok(inspection) => inspection,
            Err(e) => {
                refused.push((variant, e.to_string()));
                continue;
            }
        };
        if depth.is_empty() && matches!(variant, Variant::AsConfigured | Variant::Pipeline | Variant::TruePoses) {
            depth = depth_bands(&bundle.optics, &true_poses, &inspection.depth_maps, &true_depth, model);
        }
        variants.push(variant_budget(variant, &inspection, truth));
    }
    let optics = &bundle.optics;
    Ok(Budget {
        case: case.to_string(),
        object_pixel_mm: optics.object_pixel_mm(optics.focus_distance_mm),
        depth_of_field_mm: truth.depth_of_field_mm,
        form: format!("{:?}", model.form.family),
        depth,
        variants,
        refused,
    })
}

/// The map's depths replaced by truth's (every `row_step`-th row): at the trusted pixels only, or
/// at every pixel truth sees the part (with the least confidence a trusted pixel has there, so
/// that fusion weighs them alike).
fn substitute_depth(map: &mut DepthMap, truth: &[f32], trusted_only: bool) {
    let step = map.row_step.max(1);
    let width = map.width;
    for (i, d) in map.depth_mm.iter_mut().enumerate() {
        let (u, r) = (i % width, i / width);
        let Some(&t) = truth.get(r * step * width + u) else { continue };
        if d.is_finite() {
            *d = t;
        } else if !trusted_only && t.is_finite() {
            *d = t;
            map.peak_ratio[i] = map.peak_ratio[i].max(2.0);
        }
    }
}

/// Where a surface point lies on the thread: the crest flat, a root flat, or elsewhere (flank),
/// and its thread (the crest's, or the crest's before the root).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Place {
    Crest(u32),
    Root(u32),
    Flank,
}

fn place_of(model: &PartModel, z_mm: f64, theta_rad: f64) -> Place {
    let form = &model.form;
    let p = form.pitch_mm;
    let (crest_half, root_half) = form.window_half_widths_mm();
    let u = (z_mm - model.helix_z_h_mm - p * theta_rad.rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU) / p;
    let nearest = u.round();
    let dz = (u - nearest) * p;
    let thread = |k: f64| (k >= 0.0).then(|| k as u32 + 1);
    if dz.abs() <= crest_half {
        return thread(nearest).map_or(Place::Flank, Place::Crest);
    }
    let (before, after) = form.root_centres_mm();
    for centre in [before, after] {
        if (dz - centre).abs() <= root_half {
            return thread(nearest).map_or(Place::Flank, Place::Root);
        }
    }
    Place::Flank
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    crate::numeric::stats::median(&mut v)
}

fn depth_bands(
    optics: &Optics,
    true_poses: &[ViewPose],
    measured: &[DepthMap],
    truth: &[Vec<f32>],
    model: &PartModel,
) -> Vec<DepthBand> {
    // Per band: (crest errors, root errors, crest and root pixels truth has).
    let mut bands: Vec<(Vec<f64>, Vec<f64>, usize, usize)> = vec![Default::default(); BANDS];
    for ((pose, map), true_depth) in true_poses.iter().zip(measured).zip(truth) {
        let truth_map = DepthMap {
            width: map.width,
            height: map.height,
            row_step: 1,
            depth_mm: true_depth.clone(),
            peak_ratio: vec![2.0; true_depth.len()],
            all_in_focus: vec![0; 3 * true_depth.len()],
            end_edges: Vec::new(),
            frame_noise: None,
            prefiltered: false,
        };
        let step = map.row_step.max(1);
        for point in crate::pipeline::cloud::points_of(optics, pose, &truth_map) {
            let [u, r] = point.pixel.map(|c| c as usize);
            if r % step != 0 || point.position.z < 0.0 {
                continue;
            }
            let place = place_of(model, point.position.z, point.theta_rad());
            let band = (u * BANDS / map.width).min(BANDS - 1);
            let slot = &mut bands[band];
            let measured = map.depth_mm[(r / step) * map.width + u];
            let error = 1e3 * (measured as f64 - true_depth[r * map.width + u] as f64);
            match place {
                Place::Crest(_) => {
                    slot.2 += 1;
                    if measured.is_finite() {
                        slot.0.push(error);
                    }
                }
                Place::Root(_) => {
                    slot.3 += 1;
                    if measured.is_finite() {
                        slot.1.push(error);
                    }
                }
                Place::Flank => {}
            }
        }
    }
    bands
        .into_iter()
        .enumerate()
        .map(|(band, (crest, root, crest_n, root_n))| {
            let trusted = (crest.len() + root.len()) as f64 / (crest_n + root_n).max(1) as f64;
            let abs: Vec<f64> = crest.iter().chain(&root).map(|e| e.abs()).collect();
            let (c, r) = (median(crest.clone()).unwrap_or(f64::NAN), median(root.clone()).unwrap_or(f64::NAN));
            DepthBand {
                band,
                crest_pixels: crest.len(),
                root_pixels: root.len(),
                crest_um: c,
                root_um: r,
                height_um: r - c,
                median_abs_um: median(abs).unwrap_or(f64::NAN),
                trusted,
            }
        })
        .collect()
}

/// The fused surface against the true radius at each crest and root cell: per thread, medians (µm).
fn surface_by_thread(map: &UnrolledMap, model: &PartModel) -> std::collections::BTreeMap<u32, (Vec<f64>, Vec<f64>)> {
    let g = &map.grid;
    let mut by_thread: std::collections::BTreeMap<u32, (Vec<f64>, Vec<f64>)> = Default::default();
    for iz in 0..g.nz {
        let z = g.z_at(iz);
        if z < 0.0 {
            continue;
        }
        for it in 0..g.ntheta {
            let r = map.radius_mm[map.index(iz, it)];
            if !r.is_finite() {
                continue;
            }
            let theta = g.theta_deg_at(it).to_radians();
            let error = 1e3 * (r as f64 - model.radius(z, theta));
            match place_of(model, z, theta) {
                Place::Crest(t) => by_thread.entry(t).or_default().0.push(error),
                Place::Root(t) => by_thread.entry(t).or_default().1.push(error),
                Place::Flank => {}
            }
        }
    }
    by_thread
}

/// The RMS of the profile model's change to the heights over the bins the report's
/// `profile_correction` counted, µm; None where no profile model ran.
fn correction_rms_um(inspection: &Inspection) -> Option<f64> {
    let choice = inspection.report.profile_correction.as_ref().filter(|c| c.run)?;
    let (sum_sq, bins) = choice
        .change_by_thread
        .iter()
        .fold((0.0, 0usize), |(s, n), t| (s + t.rms_um * t.rms_um * t.bins as f64, n + t.bins));
    (bins > 0).then(|| (sum_sq / bins as f64).sqrt())
}

fn variant_budget(variant: Variant, inspection: &Inspection, truth: &Truth) -> VariantBudget {
    let model = &truth.part_model;
    let report = &inspection.report;
    let accuracy = crate::eval::compare(report, truth);
    let surface = surface_by_thread(&inspection.map, model);
    let threads: Vec<ThreadBudget> = truth
        .threads
        .iter()
        .map(|t| {
            let measured: Option<&ThreadMeasure> = inspection.threads.iter().find(|m| m.index == t.index);
            let reported = report.threads.iter().find(|r| r.index == t.index);
            let (mut heights, mut crests, mut roots) = (Vec::new(), Vec::new(), Vec::new());
            let mut bins_true = 0;
            let mut true_bins = Vec::new();
            for (k, true_height) in t.height_mm.values.iter().enumerate() {
                let Some(true_height) = true_height else { continue };
                bins_true += 1;
                if let Some(h) = reported.and_then(|r| r.height_mm.values.get(k).copied().flatten()) {
                    heights.push(1e3 * (h - true_height));
                }
                let angle = t.height_mm.angles_deg[k];
                let Some(bin) = measured.and_then(|m| m.bins.iter().find(|b| (b.angle_deg - angle).abs() < 1e-6))
                else {
                    continue;
                };
                true_bins.push(bin);
                let crest = model.crest_at(t.index, angle);
                let true_crest_r = model.radius(crest.z_mm, angle.to_radians());
                if let Some(c) = bin.crest_radius_mm {
                    crests.push(1e3 * (c - true_crest_r));
                    if let Some(h) = bin.raw_height_mm {
                        roots.push(1e3 * ((c - h) - (true_crest_r - crest.height_mm)));
                    }
                }
            }
            let bias = median(heights.clone());
            let scatter = bias
                .map(|b| (heights.iter().map(|e| (e - b) * (e - b)).sum::<f64>() / heights.len().max(1) as f64).sqrt());
            let (surface_crest, surface_root) =
                surface.get(&t.index).map(|(c, r)| (median(c.clone()), median(r.clone()))).unwrap_or((None, None));
            ThreadBudget {
                index: t.index,
                height_um: bias,
                scatter_um: scatter,
                surface_crest_um: surface_crest,
                surface_root_um: surface_root,
                window_crest_um: median(crests),
                window_root_um: median(roots),
                bins_measured: heights.len(),
                bins_true,
                unmeasured: count_unmeasured(true_bins),
            }
        })
        .collect();
    let over_threads =
        |f: fn(&ThreadBudget) -> Option<f64>| median(threads.iter().filter_map(f).collect()).unwrap_or(f64::NAN);
    let p = truth.part_model.form.pitch_mm;
    let dz = report.helix.z_h_mm - truth.part_model.helix_z_h_mm;
    let (measured, total) = threads.iter().fold((0, 0), |(m, n), t| (m + t.bins_measured, n + t.bins_true));
    VariantBudget {
        variant,
        height_rms_um: accuracy.height_rms_um,
        thread_bias_max_um: threads.iter().filter_map(|t| t.height_um).fold(0.0, |m, b| f64::max(m, b.abs())),
        scatter_median_um: over_threads(|t| t.scatter_um),
        coverage: measured as f64 / total.max(1) as f64,
        z_h_error_um: 1e3 * ((dz + p / 2.0).rem_euclid(p) - p / 2.0),
        surface_crest_um: over_threads(|t| t.surface_crest_um),
        surface_root_um: over_threads(|t| t.surface_root_um),
        window_crest_um: over_threads(|t| t.window_crest_um),
        window_root_um: over_threads(|t| t.window_root_um),
        unmeasured: sum_unmeasured(threads.iter().map(|t| t.unmeasured.as_slice())),
        correction_rms_um: correction_rms_um(inspection),
        threads,
    }
}
