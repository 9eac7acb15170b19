//! How sure the measurement is: an expanded uncertainty (k = 2) on every height, combined
//! GUM-style from independent components, and a decision per ISO 14253-1 that uses it.
//!
//! Per 1° bin the reported height is the trimmed mean of the bins' own fits along the helix
//! (profile stage). Its standard uncertainty combines
//! - **noise** (Type A): the local scatter of the bins' own fits, from the differences between
//!   neighbours along the helix (a slow change of the true height cancels in a difference),
//!   corrected for the correlation between neighbouring bins that share the focus window and
//!   divided by the bins the mean kept;
//! - **the method** (Type B): what the depth-from-focus reconstruction gets wrong at a station
//!   in ways that do not average out along the helix (the focus window smoothing the section,
//!   the sub-frame phase, texture and gloss), as a multiple of the object pixel, chosen on the
//!   tuning stations (docs/notebook/accuracy.md, "Uncertainty");
//! - **registration**: the pairs' radial residuals after the ring's solve, which a fused cell
//!   mixes where views overlap;
//! - where the measurement failed its checks or its station lies outside the measured envelope
//!   ([`measurement_failed`]), so that the method's term is unknown: the heights' dispersion along
//!   the helix and each thread's median's distance from nominal, both read off the measurement
//!   itself, over the crests the crest stage found machined (a black crest's lower height is the
//!   part's, not an error of the method).
//!
//! The decision asks whether the verdict survives every measured value moved by its
//! uncertainty: the black-crest rules are applied again at both bounds. At the bound toward
//! reject, each black arc is lengthened at both ends by its end's uncertainty, crests whose
//! deficit below the machined cone falls short of the onset threshold by less than the deficit's
//! uncertainty count as black, Lc reaches further by the uncertainty of absolute z, and crests
//! within Lc that no view showed count as black (a crest not measured cannot be shown to
//! conform). At the bound toward accept, the same the other way, and unseen crests count as
//! machined. Both bounds accept: `conforms`; both reject: `does_not_conform`; else
//! `indeterminate`.

use crate::domain::rules::ThreadObservation;
use crate::domain::station::Station;
use crate::domain::thread::ThreadForm;
use crate::numeric::sequence::local_noise;
use crate::numeric::stats::median;
use crate::pipeline::profile::{self, PhaseUncertainty, ThreadMeasure};
use crate::pipeline::quality::{Quality, QualityCode, QualityStatus};
use crate::pipeline::register::{EndFace, PairMeasure, Registration};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct UncertaintyOptions {
    /// The method's standard uncertainty on a height, in object pixels (Type B).
    pub method_px: f64,
    /// The coverage factor of the expanded uncertainty.
    pub coverage_factor: f64,
    /// Half width, in bins along the helix, of the window a bin's noise is read over.
    pub noise_half_bins: usize,
    /// The encoders' axial error bound, mm, for the uncertainty of absolute z where no end face
    /// is in view (the bundle does not declare it; the simulator's fixtures err by up to 0.3 mm).
    pub encoder_axial_bound_mm: f64,
}

impl Default for UncertaintyOptions {
    fn default() -> Self {
        Self { method_px: 0.05, coverage_factor: 2.0, noise_half_bins: 30, encoder_axial_bound_mm: 0.3 }
    }
}

/// The components of the heights' uncertainty, as the report states them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct UncertaintyBudget {
    /// k, the coverage factor of every expanded uncertainty (2: about 95%).
    pub coverage_factor: f64,
    /// Standard uncertainties, µm: the method's (Type B) and registration's, the same for every
    /// bin; the median over the bins of the noise's (Type A).
    pub method_um: f64,
    /// Registration's standard uncertainty of a height, µm.
    pub registration_um: f64,
    /// The helix phase: the standard uncertainty of a bin's windows' place along z (µm), the
    /// sectors of the circumference that read it, whether it is unknown within the pitch (fewer
    /// than three sectors and a fit residual too large to bound it, or sectors scattering by
    /// p/√12 or more), and the standard uncertainty that puts on a height (µm): the RMS change of
    /// the nominal form's fitted height over that distribution
    /// ([`profile::phase_height_rms_mm`], [`profile::PhaseUncertainty`]).
    #[serde(default)]
    pub helix_phase_um: f64,
    /// Sectors of the circumference (one view's spacing each) that read the helix phase.
    #[serde(default)]
    pub helix_phase_sectors: usize,
    /// Whether the helix phase is unknown within the pitch (each height's U then takes in the
    /// whole pitch).
    #[serde(default)]
    pub helix_phase_unknown: bool,
    /// The standard uncertainty the helix phase puts on a height, µm.
    #[serde(default)]
    pub helix_phase_height_um: f64,
    /// The median over the bins of the noise's standard uncertainty (Type A), µm.
    pub noise_median_um: Option<f64>,
    /// Where the measurement failed its checks ([`measurement_failed`]) and the method's Type B
    /// term is unknown, two standard uncertainties every height carries besides the others, µm
    /// (0 otherwise), both over the crests the crest stage found machined (heights within the
    /// profile's height window of a black crest left out): the heights' RMS departure from their
    /// thread's median along the helix (Type A), and the departure of the heights' median from
    /// the nominal height (Type B: a bound on a bias common to a thread, which no scatter shows,
    /// taken as a rectangular distribution, so that its standard uncertainty is the distance over
    /// √3; it includes the part's own departure, which makes it cautious). `from_nominal_um` is
    /// the part's distance, which a thread with fewer than 5 such heights carries;
    /// `from_nominal_by_thread` each other thread's own.
    #[serde(default)]
    pub along_helix_um: f64,
    /// The part's heights' median distance from nominal as a standard uncertainty (over √3), µm:
    /// what a thread with fewer than 5 machined heights carries.
    #[serde(default)]
    pub from_nominal_um: f64,
    /// Each other thread's own distance from nominal, as a standard uncertainty, µm.
    #[serde(default)]
    pub from_nominal_by_thread: Vec<ThreadTerm>,
    /// Where a learned model corrected the heights, the standard uncertainty it puts on each
    /// thread's heights, µm: its card's measured error per micrometre of change (1 where the card
    /// measured nothing for the station) times the RMS change it made to that thread
    /// (docs/models.md, "Choosing when it runs"). It and the two terms above estimate the same
    /// error: a height's U takes the larger, not both.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub model_by_thread: Vec<ThreadTerm>,
    /// Heights left out of those two terms as on or beside a black crest.
    #[serde(default)]
    pub black_crest_bins_left_out: usize,
    /// Bins along the helix that share a focus window: noise is correlated over this many.
    pub noise_correlation_bins: f64,
    /// The median expanded uncertainty of a bin's height, µm.
    pub expanded_median_um: Option<f64>,
    /// The decision's margins: the expanded uncertainty of a crest's deficit below the machined
    /// cone (µm), of a black arc's end (degrees) and of absolute z (mm).
    pub crest_deficit_um: f64,
    /// The expanded uncertainty of a black arc's end, degrees.
    pub arc_end_deg: f64,
    /// The expanded uncertainty of absolute z (where Lc ends), mm.
    pub z_mm: f64,
}

/// One thread's value of a term of the budget, µm.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadTerm {
    /// The thread's number.
    pub thread: u32,
    /// Its value of the term, µm.
    pub um: f64,
}

/// Where the uncertainty stage reads its scales: the station, the depth window and the part.
pub struct Scales<'a> {
    pub station: &'a Station,
    /// Half size of the depth stage's focus window, pixels.
    pub focus_window_radius_px: usize,
    pub pipe_radius_mm: f64,
    pub form: &'a ThreadForm,
    /// How far the heights' windows may sit from their crests
    /// ([`profile::Helix::phase_uncertainty`]).
    pub phase: &'a PhaseUncertainty,
    pub registration: &'a Registration,
    pub end_face: Option<&'a EndFace>,
    /// The crest stage's findings per thread, bin for bin with the heights: which crests are black.
    pub crests: &'a [ThreadObservation],
    /// Half width, in bins, of the profile's trimmed mean along the helix: a black crest lowers
    /// the reported heights this far beyond its own bins.
    pub height_window_half_bins: usize,
    /// A qualified station's combined standard uncertainty of a corrected height (ISO 15530-3),
    /// mm: it stands in for the method's Type B term.
    pub station_u_mm: Option<f64>,
    /// The qualification study's median local scatter of a height, mm: at a qualified station a
    /// bin's own scatter counts only beyond it (the station's repeatability holds the rest).
    pub station_noise_mm: Option<f64>,
    /// Per thread, the standard uncertainty a learned correction puts on its heights, mm (empty
    /// where none ran; a thread not listed takes the largest listed).
    pub model_by_thread_mm: &'a [(u32, f64)],
}

/// Whether the measurement cannot vouch for its own uncertainty: the quality checks say it failed
/// (too little was measured, the helix does not fit the surface, or depth from focus trusted too
/// few pixels), a learned model corrected the heights (the model's own error is not in the
/// classical budget: docs/models.md), or the station's optics lie outside the envelope the
/// method's uncertainty was measured in (its Type B term is known only there: docs/benchmark.md).
/// Such a result's heights carry the
/// dispersion along the helix besides their local scatter, and no decision is made on it.
pub fn measurement_failed(quality: &Quality, station: &Station) -> bool {
    quality.status == QualityStatus::Insufficient
        || quality.reasons.iter().any(|r| {
            matches!(
                r.code,
                QualityCode::HelixResidualLarge
                    | QualityCode::HelixPhaseUnknown
                    | QualityCode::DepthCoverageLow
                    | QualityCode::ProfileCorrected
                    | QualityCode::DepthLearned
                    | QualityCode::StationNotQualified
            )
        })
        || (station.qualified_by.is_none() && station.optics_outside(&crate::domain::station::MEASURED))
}

/// Sets every bin's `uncertainty_mm` and returns the budget with each thread's mean's expanded
/// uncertainty (by thread index).
pub fn heights(
    threads: &mut [ThreadMeasure],
    scales: &Scales,
    crest_scatter_um: Option<f64>,
    quality: &Quality,
    options: &UncertaintyOptions,
) -> (UncertaintyBudget, Vec<(u32, Option<f64>)>) {
    let k = options.coverage_factor;
    let pixel_mm = scales.station.object_pixel_mm;
    let bin_arc_mm = scales.pipe_radius_mm.to_radians();
    // A focus window spans (2r + 1) pixels along the arc: bins within it share depth errors.
    let correlation = ((2 * scales.focus_window_radius_px + 1) as f64 * pixel_mm / bin_arc_mm).max(1.0);
    let method_mm = scales.station_u_mm.unwrap_or(options.method_px * pixel_mm);
    // Where the measurement failed its checks, its errors vary along the helix on scales the local
    // scatter does not see (a view's depth bias, a misplaced view): a machined thread's height is
    // constant along the helix to within its tolerance, so the heights' departure from their
    // thread's median measures those errors (with the true variation, which makes it cautious).
    let failed = measurement_failed(quality, scales.station);
    let machined = machined_heights(threads, scales.crests, scales.height_window_half_bins);
    let left_out: usize = threads
        .iter()
        .zip(&machined)
        .map(|(t, m)| t.bins.iter().zip(m).filter(|(b, m)| b.height_mm.is_some() && !**m).count())
        .sum();
    let along_mm = if failed { along_helix_rms(threads, &machined) } else { 0.0 };
    // A thread's heights can all be off together (the focus window or a depth of field comparable
    // to the thread's height compressing its profiles: at one random station, 0.35 mm of a 1.0 mm
    // thread; the run-out threads' shallow profiles read 0.2 mm high at others): its median's
    // distance from nominal bounds that. A thread with too few heights of its own takes the part's.
    let (part_from_nominal_mm, thread_from_nominal_mm) =
        if failed { from_nominal(threads, &machined, scales.form.height_mm) } else { (0.0, vec![None; threads.len()]) };
    // RMS over the measured pairs of one of their residuals (0 without pairs).
    let pairs = &scales.registration.pairs;
    let pairs_rms = |residual_mm: &dyn Fn(&PairMeasure) -> f64| {
        if pairs.is_empty() {
            0.0
        } else {
            (pairs.iter().map(|p| residual_mm(p).powi(2)).sum::<f64>() / pairs.len() as f64).sqrt()
        }
    };
    // A fused cell averages the views that saw it: half the pairs' radial disagreement.
    let registration_mm = 0.5 * pairs_rms(&|p| 1e-3 * p.residual_radius_um);
    // Windows placed by the one helix sit off the crests of a view whose own phase departs from
    // it, and all of them off by z_h's own error: the height that costs on the nominal form. Shared
    // by the bins of a view, so a thread's mean carries it whole.
    let phase = scales.phase;
    let phase_height_mm = profile::phase_height_rms_mm(scales.form, phase.error);
    // A bin's noise `s`, correlated over `correlation` bins, in a mean of `m` bins: neighbour
    // differences see 1/L of the variance, and the mean averages m/L independent ones (at most m).
    let noise_of = |s: f64, m: f64| s * (correlation * (correlation / m).min(1.0)).sqrt();
    // The distance from nominal bounds a bias of unknown sign and size within it: a rectangular
    // distribution over ± the distance, whose standard uncertainty is the distance over √3 (GUM
    // 4.3.7).
    // A learned correction's term and the failed path's two read the same thing, the corrected
    // heights' error, from two sides (the card's measured effect; the heights' own dispersion and
    // distance from nominal): the larger is taken, not both; summed, they over-cover
    // (docs/models.md, "Choosing when it runs").
    let expanded_of = |noise_mm: f64, from_nominal_mm: f64, model_mm: f64| {
        let read_off = along_mm.powi(2) + from_nominal_mm.powi(2) / 3.0;
        k * (noise_mm.powi(2)
            + method_mm.powi(2)
            + registration_mm.powi(2)
            + phase_height_mm.powi(2)
            + read_off.max(model_mm.powi(2)))
        .sqrt()
    };
    let raw: Vec<Option<f64>> = threads.iter().flat_map(|t| t.bins.iter().map(|b| b.raw_height_mm)).collect();
    let noise = local_noise(&raw, options.noise_half_bins, 10);
    // Where too few neighbours were measured to read the noise, the part's median stands in; where
    // no bin has enough anywhere (a few short runs of bins), a coarser reading of the same scatter.
    let mut known: Vec<f64> = noise.iter().flatten().copied().collect();
    let part_noise = median(&mut known).or_else(|| sparse_noise(&raw, scales.station.depth_of_field_mm));
    let largest_model_mm = scales.model_by_thread_mm.iter().map(|&(_, mm)| mm).fold(0.0, f64::max);
    let model_of = |thread: u32| {
        scales.model_by_thread_mm.iter().find(|&&(t, _)| t == thread).map_or(largest_model_mm, |&(_, mm)| mm)
    };
    let mut expanded = Vec::new();
    let mut means = Vec::with_capacity(threads.len());
    let mut i = 0;
    for (t, own_from_nominal) in threads.iter_mut().zip(&thread_from_nominal_mm) {
        let from_nominal_mm = own_from_nominal.unwrap_or(part_from_nominal_mm);
        let model_mm = model_of(t.index);
        let mut thread_noise = Vec::new();
        for b in &mut t.bins {
            let s = noise[i].or(part_noise);
            i += 1;
            // At a qualified station u_p holds the scatter its study saw; a bin adds what is beyond.
            let s = match scales.station_noise_mm {
                Some(study) => s.map(|s| (s * s - study * study).max(0.0).sqrt()),
                None => s,
            };
            b.uncertainty_mm = match (b.height_mm, s) {
                (Some(_), Some(s)) => {
                    thread_noise.push(s);
                    let u = expanded_of(noise_of(s, b.kept_bins.max(1) as f64), from_nominal_mm, model_mm);
                    expanded.push(u);
                    Some(u)
                }
                _ => None,
            };
        }
        let n = t.bins.iter().filter(|b| b.height_mm.is_some()).count() as f64;
        // The model's term is a thread's common error: its mean carries it whole.
        let mean_u = median(&mut thread_noise).map(|s| expanded_of(noise_of(s, n), from_nominal_mm, model_mm));
        means.push((t.index, mean_u));
    }
    let z_mm = match scales.end_face {
        Some(end) => 1e-3 * end.scatter_um / (end.views.max(1) as f64).sqrt(),
        // Uniform within ± the bound, the mean over the views (registration keeps the mean).
        None => options.encoder_axial_bound_mm / 3f64.sqrt() / (scales.station.views.max(1) as f64).sqrt(),
    };
    let registration_arc_mm = pairs_rms(&|p| p.residual_angle_deg.to_radians() * scales.pipe_radius_mm);
    // An arc's end: the bin's quantisation, the focus window's reach along the arc and the views'
    // angular disagreement; never less than a bin.
    let end_u_mm = ((bin_arc_mm / 12f64.sqrt()).powi(2)
        + (scales.focus_window_radius_px as f64 * pixel_mm / 3f64.sqrt()).powi(2)
        + registration_arc_mm.powi(2))
    .sqrt();
    let budget = UncertaintyBudget {
        coverage_factor: k,
        method_um: 1e3 * method_mm,
        registration_um: 1e3 * registration_mm,
        helix_phase_um: 1e3 * phase.u_mm,
        helix_phase_sectors: phase.sectors,
        helix_phase_unknown: phase.unknown,
        helix_phase_height_um: 1e3 * phase_height_mm,
        noise_median_um: part_noise.map(|s| 1e3 * s),
        along_helix_um: 1e3 * along_mm,
        from_nominal_um: 1e3 * part_from_nominal_mm,
        from_nominal_by_thread: threads
            .iter()
            .zip(&thread_from_nominal_mm)
            .filter_map(|(t, v)| v.map(|mm| ThreadTerm { thread: t.index, um: 1e3 * mm }))
            .collect(),
        model_by_thread: threads
            .iter()
            .filter(|_| !scales.model_by_thread_mm.is_empty())
            .map(|t| ThreadTerm { thread: t.index, um: 1e3 * model_of(t.index) })
            .collect(),
        black_crest_bins_left_out: if failed { left_out } else { 0 },
        noise_correlation_bins: correlation,
        expanded_median_um: median(&mut expanded).map(|u| 1e3 * u),
        crest_deficit_um: k * crest_scatter_um.unwrap_or(0.0),
        arc_end_deg: (k * end_u_mm / bin_arc_mm).max(1.0),
        z_mm: k * z_mm,
    };
    (budget, means)
}

/// The noise of a part too sparsely measured for [`local_noise`] (fewer than its minimum of
/// neighbouring pairs around every bin), so that no height goes without an uncertainty: the robust
/// scale of every neighbouring pair's difference over √2; without a single pair, the RMS spread of
/// the heights about their median; for a lone height, half the depth of field, within which depth
/// from focus has nothing to place a surface by but the one focus curve. None without a height.
fn sparse_noise(raw: &[Option<f64>], depth_of_field_mm: f64) -> Option<f64> {
    let mut diffs: Vec<f64> = raw.windows(2).filter_map(|w| Some((w[1]? - w[0]?).abs())).collect();
    if let Some(m) = median(&mut diffs) {
        return Some(1.4826 * m / std::f64::consts::SQRT_2);
    }
    let mut heights: Vec<f64> = raw.iter().flatten().copied().collect();
    match heights.len() {
        0 => None,
        1 => Some(0.5 * depth_of_field_mm),
        n => {
            let centre = median(&mut heights)?;
            Some((heights.iter().map(|h| (h - centre).powi(2)).sum::<f64>() / n as f64).sqrt())
        }
    }
}

/// Per thread, per bin: whether the bin's height reads a machined crest, i.e. lies more than
/// `reach_bins` along the helix from every crest the crest stage found black (on the mill surface,
/// or in a photometric black arc). A thread the crest stage did not see counts as machined.
fn machined_heights(threads: &[ThreadMeasure], crests: &[ThreadObservation], reach_bins: usize) -> Vec<Vec<bool>> {
    threads
        .iter()
        .map(|t| {
            let n = t.bins.len();
            let Some(obs) = crests.iter().find(|o| o.index == t.index) else { return vec![true; n] };
            let black: Vec<bool> = t
                .bins
                .iter()
                .enumerate()
                .map(|(k, b)| {
                    obs.bins.get(k).is_some_and(|c| c.on_mill_surface)
                        || obs.black_crest_arcs_deg.iter().any(|a| a[0] < b.angle_deg + 0.5 && a[1] > b.angle_deg - 0.5)
                })
                .collect();
            // A black bin's low height reaches `reach_bins` further through the trimmed mean.
            let mut machined = vec![true; n];
            for (k, _) in black.iter().enumerate().filter(|(_, b)| **b) {
                for m in &mut machined[k.saturating_sub(reach_bins)..(k + reach_bins + 1).min(n)] {
                    *m = false;
                }
            }
            machined
        })
        .collect()
}

/// Each thread's measured heights on machined crests (`machined`, bin for bin).
fn machined_of<'a>(t: &'a ThreadMeasure, machined: &'a [bool]) -> impl Iterator<Item = f64> + 'a {
    t.bins.iter().zip(machined).filter(|(_, m)| **m).filter_map(|(b, _)| b.height_mm)
}

/// RMS over the measured machined bins of each height's departure from its thread's median
/// (threads with fewer than 5 such bins left out), mm. Where no thread has 5, the departure of
/// every machined height from the part's median (of every height, where fewer than 5 are
/// machined): a part measured in scraps is not one whose heights agree. 0 with fewer than two
/// heights. A thread's mean carries it whole: the errors it measures are shared by the bins one
/// view saw, so they do not average out along the helix.
fn along_helix_rms(threads: &[ThreadMeasure], machined: &[Vec<bool>]) -> f64 {
    let rms_about_median = |mut heights: Vec<f64>| -> Option<(f64, usize)> {
        let centre = median(&mut heights)?;
        Some((heights.iter().map(|h| (h - centre).powi(2)).sum::<f64>(), heights.len()))
    };
    let (mut sum_sq, mut n) = (0.0, 0usize);
    for (t, m) in threads.iter().zip(machined) {
        let heights: Vec<f64> = machined_of(t, m).collect();
        if heights.len() < 5 {
            continue;
        }
        if let Some((s, k)) = rms_about_median(heights) {
            sum_sq += s;
            n += k;
        }
    }
    if n == 0 {
        let mut part: Vec<f64> = threads.iter().zip(machined).flat_map(|(t, m)| machined_of(t, m)).collect();
        if part.len() < 5 {
            part = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.height_mm)).collect();
        }
        if part.len() >= 2 {
            (sum_sq, n) = rms_about_median(part).unwrap_or((0.0, 0));
        }
    }
    if n == 0 { 0.0 } else { (sum_sq / n as f64).sqrt() }
}

/// The machined heights' median's distance from nominal: the part's (over every thread; over
/// every height where no crest is machined), and each thread's own where it has 5 or more, mm.
fn from_nominal(threads: &[ThreadMeasure], machined: &[Vec<bool>], nominal_mm: f64) -> (f64, Vec<Option<f64>>) {
    let mut all: Vec<f64> = threads.iter().zip(machined).flat_map(|(t, m)| machined_of(t, m)).collect();
    if all.is_empty() {
        all = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.height_mm)).collect();
    }
    let part = median(&mut all).map_or(0.0, |m| (m - nominal_mm).abs());
    let own = threads
        .iter()
        .zip(machined)
        .map(|(t, m)| {
            let mut heights: Vec<f64> = machined_of(t, m).collect();
            if heights.len() < 5 { None } else { median(&mut heights).map(|m| (m - nominal_mm).abs()) }
        })
        .collect();
    (part, own)
}

mod decision;
pub use decision::{BRIDGED_GAP_BINS, Decision, DecisionFinding, HeightFinding, RuleContext, decide, judge_height};

#[cfg(test)]
mod tests;
