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

use crate::domain::arcs::union_arcs;
use crate::domain::rules::{self, ArcRule, RuleInput, ThreadObservation, Verdict};
use crate::domain::station::Station;
use crate::domain::thread::ThreadForm;
use crate::numeric::runs::run_spans;
use crate::numeric::sequence::local_noise;
use crate::numeric::stats::median;
use crate::pipeline::crest::{self, CrestOptions};
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
}

/// Whether the measurement cannot vouch for its own uncertainty: the quality checks say it failed
/// (too little was measured, the helix does not fit the surface, or depth from focus trusted too
/// few pixels), a learned model corrected the heights (at the standard station the MLP's own
/// error, about 10 µm, left the classical budget covering 30% of the errors: docs/models.md), or
/// the station's optics lie outside the envelope the method's uncertainty was measured in (its Type B term is known only there: on the random stations' optics heights were
/// off by tens to hundreds of µm that no local scatter shows). Such a result's heights carry the
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
            )
        })
        || station.optics_outside(&crate::domain::station::MEASURED)
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
    let method_mm = options.method_px * pixel_mm;
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
    let expanded_of = |noise_mm: f64, from_nominal_mm: f64| {
        k * (noise_mm.powi(2)
            + method_mm.powi(2)
            + registration_mm.powi(2)
            + phase_height_mm.powi(2)
            + along_mm.powi(2)
            + from_nominal_mm.powi(2) / 3.0)
            .sqrt()
    };
    let raw: Vec<Option<f64>> = threads.iter().flat_map(|t| t.bins.iter().map(|b| b.raw_height_mm)).collect();
    let noise = local_noise(&raw, options.noise_half_bins, 10);
    // Where too few neighbours were measured to read the noise, the part's median stands in; where
    // no bin has enough anywhere (a few short runs of bins), a coarser reading of the same scatter.
    let mut known: Vec<f64> = noise.iter().flatten().copied().collect();
    let part_noise = median(&mut known).or_else(|| sparse_noise(&raw, scales.station.depth_of_field_mm));
    let mut expanded = Vec::new();
    let mut means = Vec::with_capacity(threads.len());
    let mut i = 0;
    for (t, own_from_nominal) in threads.iter_mut().zip(&thread_from_nominal_mm) {
        let from_nominal_mm = own_from_nominal.unwrap_or(part_from_nominal_mm);
        let mut thread_noise = Vec::new();
        for b in &mut t.bins {
            let s = noise[i].or(part_noise);
            i += 1;
            b.uncertainty_mm = match (b.height_mm, s) {
                (Some(_), Some(s)) => {
                    thread_noise.push(s);
                    let u = expanded_of(noise_of(s, b.kept_bins.max(1) as f64), from_nominal_mm);
                    expanded.push(u);
                    Some(u)
                }
                _ => None,
            };
        }
        let n = t.bins.iter().filter(|b| b.height_mm.is_some()).count() as f64;
        let mean_u = median(&mut thread_noise).map(|s| expanded_of(noise_of(s, n), from_nominal_mm));
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

/// The decision per ISO 14253-1 on the black-crest rules.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// The verdict is accept at both bounds of the uncertainty.
    Conforms,
    /// The verdict is reject at both bounds.
    DoesNotConform,
    /// The bounds disagree: the measurement cannot decide.
    Indeterminate,
}

impl Decision {
    pub fn as_str(self) -> &'static str {
        match self {
            Decision::Conforms => "conforms",
            Decision::DoesNotConform => "does_not_conform",
            Decision::Indeterminate => "indeterminate",
        }
    }
}

/// The decision and how it was reached.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct DecisionFinding {
    /// The decision (conforms, does_not_conform, indeterminate).
    pub decision: Decision,
    /// The rules' verdict at the bound toward reject and at the bound toward accept.
    pub verdict_toward_reject: Verdict,
    /// The rules' verdict at the bound toward accept (black arcs shorter, the onset higher, Lc
    /// shorter, each by its uncertainty).
    pub verdict_toward_accept: Verdict,
    /// Crest degrees within Lc that no view showed, and counted black toward reject.
    pub unseen_crest_within_lc_deg: f64,
    /// Why, in words: empty when the decision is the verdict's.
    pub reasons: Vec<String>,
}

/// What the decision re-applies the rules with.
pub struct RuleContext<'a> {
    pub input: &'a RuleInput,
    pub arc_rule: ArcRule,
    pub pitch_mm: f64,
    pub nominal_slope: f64,
    pub crest_window_half_mm: f64,
    pub crest: &'a CrestOptions,
}

/// Unseen gaps of up to this many bins between seen, machined crests of one thread are taken as
/// their neighbours: the mill surface is smooth (ovality, eccentricity, a taper), and cannot dip
/// below the cone and rise again within a few degrees.
pub const BRIDGED_GAP_BINS: usize = 3;

/// The decision on the black-crest verdict: the rules at both bounds of the uncertainty.
pub fn decide(
    threads: &[ThreadMeasure],
    ctx: &RuleContext,
    budget: &UncertaintyBudget,
    quality: &Quality,
    station: &Station,
) -> DecisionFinding {
    let at = |shift_um: f64| {
        let options = CrestOptions { onset_shift_um: shift_um, ..ctx.crest.clone() };
        crest::observations(
            threads,
            ctx.input.lc_mm,
            ctx.pitch_mm,
            ctx.nominal_slope,
            ctx.crest_window_half_mm,
            &options,
        )
        .observations
    };
    let end_bins = budget.arc_end_deg.ceil() as usize;
    let mut toward_reject = at(-budget.crest_deficit_um);
    let mut unseen_deg = 0.0;
    for t in &mut toward_reject {
        unseen_deg += count_unseen_as_black(t, ctx.input.lc_mm + budget.z_mm);
        widen(t, budget.arc_end_deg, end_bins);
    }
    let mut toward_accept = at(budget.crest_deficit_um);
    for t in &mut toward_accept {
        narrow(t, budget.arc_end_deg, end_bins);
    }
    let verdict_at = |threads: Vec<ThreadObservation>, lc_mm: f64| {
        rules::assess(&RuleInput { threads, lc_mm, ..ctx.input.clone() }, ctx.arc_rule)
    };
    let reject_side = verdict_at(toward_reject, ctx.input.lc_mm + budget.z_mm);
    let accept_side = verdict_at(toward_accept, (ctx.input.lc_mm - budget.z_mm).max(0.0));
    let failed = measurement_failed(quality, station);
    let decision = match (reject_side.verdict, accept_side.verdict) {
        _ if failed => Decision::Indeterminate,
        (Verdict::Accept, Verdict::Accept) => Decision::Conforms,
        (Verdict::Reject, Verdict::Reject) => Decision::DoesNotConform,
        _ => Decision::Indeterminate,
    };
    let mut reasons = Vec::new();
    if failed {
        reasons.push(
            "No decision is made: crestscan cannot state how far off this measurement may be. It failed its \
             quality checks or its station's optics lie outside the envelope its uncertainty was measured in (the \
             quality reasons say which); its heights and black \
             crests may be wrong by more than their local scatter shows, and each height's uncertainty \
             includes the heights' dispersion along the helix and their thread's distance from nominal"
                .to_string(),
        );
    }
    if decision == Decision::Indeterminate && !failed {
        let margins = format!(
            "black arcs {:.1}° longer at each end, crests within {:.1} µm of the onset counted black, Lc {:.3} mm further",
            budget.arc_end_deg, budget.crest_deficit_um, budget.z_mm
        );
        let unseen = if unseen_deg > 0.0 {
            format!(", {unseen_deg:.0}° of crest within Lc that no view showed counted black")
        } else {
            String::new()
        };
        let bound = |a: &rules::Assessment| {
            let longest = a.black_threads.iter().map(|t| t.length_mm).fold(0.0, f64::max);
            let codes: Vec<String> = a
                .reasons
                .iter()
                .filter(|r| r.code != rules::ReasonCode::PartialCoverage)
                .map(|r| {
                    serde_json::to_value(r.code).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default()
                })
                .collect::<std::collections::BTreeSet<_>>()
                .into_iter()
                .collect();
            format!(
                "{} black-crested thread(s) within Lc, the longest {longest:.1} mm ({})",
                a.black_threads.len(),
                codes.join(", ")
            )
        };
        if reject_side.verdict == Verdict::Reject {
            reasons.push(format!(
                "The measurement is not certain enough to accept: within its uncertainty the part could be a reject. \
                 With {margins}{unseen}: {}",
                bound(&reject_side)
            ));
        }
        if accept_side.verdict == Verdict::Accept {
            reasons.push(format!(
                "The measurement is not certain enough to reject: within its uncertainty the part could be an \
                 accept. With black arcs {:.1}° shorter at each end, the onset {:.1} µm higher and Lc {:.3} mm \
                 shorter: {}",
                budget.arc_end_deg,
                budget.crest_deficit_um,
                budget.z_mm,
                bound(&accept_side)
            ));
        }
    }
    DecisionFinding {
        decision,
        verdict_toward_reject: reject_side.verdict,
        verdict_toward_accept: accept_side.verdict,
        unseen_crest_within_lc_deg: unseen_deg,
        reasons,
    }
}

/// Marks the thread's unseen crest bins within `lc_mm` black (on the mill surface), but for gaps
/// of up to [`BRIDGED_GAP_BINS`] between seen crests that are not black; returns the degrees so
/// marked.
fn count_unseen_as_black(t: &mut ThreadObservation, lc_mm: f64) -> f64 {
    let black = |b: &rules::CrestBin, arcs: &[[f64; 2]]| {
        b.on_mill_surface || arcs.iter().any(|a| a[0] < b.angle_deg + b.width_deg && a[1] > b.angle_deg)
    };
    let n = t.bins.len();
    let unseen: Vec<bool> = t.bins.iter().map(|b| !b.seen && !b.chamfer).collect();
    let mut marked = 0.0;
    for gap in run_spans(&unseen) {
        let bridged = gap.len() <= BRIDGED_GAP_BINS
            && gap.start > 0
            && gap.end < n
            && !black(&t.bins[gap.start - 1], &t.black_crest_arcs_deg)
            && !black(&t.bins[gap.end], &t.black_crest_arcs_deg);
        if bridged {
            continue;
        }
        for b in t.bins[gap].iter_mut().filter(|b| b.z_mm <= lc_mm) {
            b.on_mill_surface = true;
            b.mill_arc_deg = None;
            marked += b.width_deg;
        }
    }
    marked
}

/// Lengthens every black arc by `deg` at each end (photometric arcs by the angle, geometric runs
/// by `bins` bins).
fn widen(t: &mut ThreadObservation, deg: f64, bins: usize) {
    t.black_crest_arcs_deg =
        union_arcs(t.black_crest_arcs_deg.iter().map(|a| [(a[0] - deg).max(0.0), (a[1] + deg).min(360.0)]).collect());
    let on: Vec<bool> = t.bins.iter().map(|b| b.on_mill_surface).collect();
    for (i, b) in t.bins.iter_mut().enumerate() {
        let near = on[i.saturating_sub(bins)..(i + bins + 1).min(on.len())].iter().any(|&x| x);
        if near && !b.chamfer && !b.on_mill_surface {
            b.on_mill_surface = true;
            b.mill_arc_deg = None;
        }
    }
}

/// Shortens every black arc by `deg` at each end (geometric runs by `bins` bins); arcs shorter
/// than twice that vanish. A geometric run that reaches the edge of the crests the views showed
/// goes entirely: at the edge of the covered arc the machined cone is fitted least well (over a
/// sector its off-axis terms bend it there), so a crest below it there may be the fit's.
fn narrow(t: &mut ThreadObservation, deg: f64, bins: usize) {
    let n = t.bins.len();
    let on: Vec<bool> = t.bins.iter().map(|b| b.on_mill_surface).collect();
    for run in run_spans(&on) {
        let at_edge = (run.start > 0 && !t.bins[run.start - 1].seen) || (run.end < n && !t.bins[run.end].seen);
        if at_edge {
            for b in &mut t.bins[run] {
                b.on_mill_surface = false;
                b.mill_arc_deg = None;
            }
        }
    }
    t.black_crest_arcs_deg =
        t.black_crest_arcs_deg.iter().filter(|a| a[1] - a[0] > 2.0 * deg).map(|a| [a[0] + deg, a[1] - deg]).collect();
    let on: Vec<bool> = t.bins.iter().map(|b| b.on_mill_surface).collect();
    for (i, b) in t.bins.iter_mut().enumerate() {
        let whole = on[i.saturating_sub(bins)..(i + bins + 1).min(on.len())].iter().all(|&x| x)
            && i >= bins
            && i + bins < on.len();
        if b.on_mill_surface && !whole {
            b.on_mill_surface = false;
            b.mill_arc_deg = None;
        }
    }
}

/// One thread's height against nominal ± tolerance, with its uncertainty (ISO 14253-1 on the
/// thread's mean height): a finding of its own, apart from the black-crest verdict.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum HeightFinding {
    /// The mean ± its uncertainty lies within the tolerance.
    Within,
    /// The mean lies outside the tolerance by more than its uncertainty.
    Outside,
    /// The uncertainty straddles a tolerance limit.
    Indeterminate,
    /// Not judged: no full crest within Lc was measured.
    NotJudged,
}

impl HeightFinding {
    pub fn as_str(self) -> &'static str {
        match self {
            HeightFinding::Within => "within",
            HeightFinding::Outside => "outside",
            HeightFinding::Indeterminate => "indeterminate",
            HeightFinding::NotJudged => "not_judged",
        }
    }
}

/// Judges a mean height against nominal ± tolerance.
pub fn judge_height(mean_mm: Option<f64>, u_mm: Option<f64>, nominal_mm: f64, tolerance_mm: f64) -> HeightFinding {
    let (Some(mean), Some(u)) = (mean_mm, u_mm) else { return HeightFinding::NotJudged };
    let off = (mean - nominal_mm).abs();
    if off + u <= tolerance_mm {
        HeightFinding::Within
    } else if off - u > tolerance_mm {
        HeightFinding::Outside
    } else {
        HeightFinding::Indeterminate
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::thread::Family;
    use crate::pipeline::profile::{BinMeasure, Helix};
    use crate::pipeline::quality::QualityReason;

    const PITCH: f64 = 5.08;
    const SLOPE: f64 = 0.03125;

    /// Threads 1–`n` of a part whose crests follow the cone (with a few µm of scatter) except
    /// where `black(thread, bin)` puts the crest 0.1 mm below it (a polished black crest), and
    /// where `unseen(thread, bin)` no view showed it.
    fn part(n: u32, black: impl Fn(u32, usize) -> bool, unseen: impl Fn(u32, usize) -> bool) -> Vec<ThreadMeasure> {
        let mut seed = 7u64;
        (1..=n)
            .map(|index| {
                let bins = (0..360)
                    .map(|k| {
                        let angle_deg = k as f64 + 0.5;
                        let z = 10.0 + PITCH * (index as f64 - 1.0 + angle_deg / 360.0);
                        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                        let jitter = ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.006;
                        let r = 55.0 + SLOPE * z + jitter - if black(index, k) { 0.1 } else { 0.0 };
                        let seen = !unseen(index, k);
                        BinMeasure {
                            angle_deg,
                            crest_z_mm: z,
                            height_mm: seen.then_some(1.575),
                            crest_radius_mm: seen.then_some(r),
                            crest_gray: seen.then_some(0.5),
                            ..Default::default()
                        }
                    })
                    .collect();
                ThreadMeasure { index, bins }
            })
            .collect()
    }

    fn budget() -> UncertaintyBudget {
        UncertaintyBudget {
            coverage_factor: 2.0,
            method_um: 2.0,
            registration_um: 0.0,
            helix_phase_um: 0.0,
            helix_phase_sectors: 36,
            helix_phase_unknown: false,
            helix_phase_height_um: 0.0,
            noise_median_um: Some(3.0),
            along_helix_um: 0.0,
            from_nominal_um: 0.0,
            from_nominal_by_thread: vec![],
            black_crest_bins_left_out: 0,
            noise_correlation_bins: 1.0,
            expanded_median_um: Some(8.0),
            crest_deficit_um: 10.0,
            arc_end_deg: 1.0,
            z_mm: 0.05,
        }
    }

    fn ok() -> Quality {
        Quality { status: QualityStatus::Ok, reasons: vec![] }
    }

    fn decide_on(threads: &[ThreadMeasure], family: Family, quality: &Quality) -> DecisionFinding {
        let crest = CrestOptions::default();
        let findings = crest::observations(threads, 200.0, PITCH, SLOPE, 0.5, &crest);
        let input = RuleInput {
            family,
            lc_mm: 200.0,
            circumference_mm: 359.0,
            nominal_height_mm: 1.575,
            height_tolerance_mm: 0.05,
            threads: findings.observations,
        };
        let ctx = RuleContext {
            input: &input,
            arc_rule: ArcRule::PerThread,
            pitch_mm: PITCH,
            nominal_slope: SLOPE,
            crest_window_half_mm: 0.5,
            crest: &crest,
        };
        decide(threads, &ctx, &budget(), quality, &station(0.041))
    }

    #[test]
    fn a_black_crest_well_under_the_limit_conforms_and_one_at_it_is_indeterminate() {
        // Thread 4 black over 60° of its turn: 25% of the circumference is 90°.
        let short = part(6, |t, k| t == 4 && (100..160).contains(&k), |_, _| false);
        let d = decide_on(&short, Family::Buttress, &ok());
        assert_eq!(d.decision, Decision::Conforms, "{d:?}");
        // Black over 89.5° of it: a degree more at the ends passes the limit.
        let at_limit = part(6, |t, k| t == 4 && (100..190).contains(&k), |_, _| false);
        let d = decide_on(&at_limit, Family::Buttress, &ok());
        assert_eq!((d.verdict_toward_reject, d.decision), (Verdict::Reject, Decision::Indeterminate), "{d:?}");
        assert!(d.reasons[0].contains("could be a reject"), "{:?}", d.reasons);
        // Black against the edge of the crests seen (a sector's edge, where the cone is fitted
        // least well): it may be the fit's, so the verdict could be accept.
        let at_edge = part(6, |t, k| (2..=4).contains(&t) && (60..120).contains(&k), |_, k| k >= 120);
        let d = decide_on(&at_edge, Family::Buttress, &ok());
        assert_eq!((d.verdict_toward_accept, d.decision), (Verdict::Accept, Decision::Indeterminate), "{d:?}");
        // Three threads black over half a turn: reject at both bounds.
        let three = part(6, |t, k| (2..=4).contains(&t) && (0..180).contains(&k), |_, _| false);
        assert_eq!(decide_on(&three, Family::Buttress, &ok()).decision, Decision::DoesNotConform);
    }

    #[test]
    fn a_crest_no_view_showed_cannot_be_shown_to_conform() {
        // A round thread allows no black crest within Lc: 20° unseen on thread 3 might be one.
        let gap = part(6, |_, _| false, |t, k| t == 3 && (200..220).contains(&k));
        let d = decide_on(&gap, Family::Round, &ok());
        assert_eq!(d.decision, Decision::Indeterminate, "{d:?}");
        assert!((d.unseen_crest_within_lc_deg - 20.0).abs() < 1e-9, "{d:?}");
        assert!(d.reasons[0].contains("20° of crest within Lc that no view showed"), "{:?}", d.reasons);
        // A gap of two bins between machined crests is bridged: the mill surface cannot dip and
        // rise again within it.
        let bridged = part(6, |_, _| false, |t, k| t == 3 && (200..202).contains(&k));
        let d = decide_on(&bridged, Family::Round, &ok());
        assert_eq!((d.decision, d.unseen_crest_within_lc_deg), (Decision::Conforms, 0.0), "{d:?}");
    }

    #[test]
    fn a_measurement_that_failed_its_checks_decides_nothing() {
        let clean = part(6, |_, _| false, |_, _| false);
        let failed = Quality {
            status: QualityStatus::Degraded,
            reasons: vec![QualityReason { code: QualityCode::HelixResidualLarge, message: String::new() }],
        };
        let d = decide_on(&clean, Family::Buttress, &failed);
        assert_eq!(d.decision, Decision::Indeterminate);
        assert!(d.reasons[0].contains("failed its quality checks"), "{:?}", d.reasons);
        assert_eq!(decide_on(&clean, Family::Buttress, &ok()).decision, Decision::Conforms);
        // Optics outside the measured envelope: the method's uncertainty is not known there.
        assert!(measurement_failed(&ok(), &station(0.12)));
        assert!(!measurement_failed(&ok(), &station(0.041)));
    }

    fn station(object_pixel_mm: f64) -> Station {
        Station {
            projection: crate::domain::optics::Projection::Perspective,
            object_pixel_mm,
            depth_of_field_mm: 0.5,
            frame_step_mm: 0.25,
            frame_step_dof: 0.5,
            frames_per_view: 20,
            views: 45,
            axial_rows: 1,
            view_spacing_deg: Some(8.0),
            overlap_deg: Some(5.0),
            frame_noise_percent: Some(0.84),
            class: None,
        }
    }

    /// Threads whose bins' own fits scatter by `sigma_mm` (alternating ±σ, so that neighbours
    /// differ by 2σ), their reported heights the trimmed mean of 7.
    fn noisy(sigma_mm: f64) -> Vec<ThreadMeasure> {
        (1..=3)
            .map(|index| ThreadMeasure {
                index,
                bins: (0..360)
                    .map(|k| {
                        let raw = 1.575 + if k % 2 == 0 { sigma_mm } else { -sigma_mm };
                        BinMeasure {
                            angle_deg: k as f64 + 0.5,
                            height_mm: Some(1.575),
                            raw_height_mm: Some(raw),
                            kept_bins: 7,
                            ..Default::default()
                        }
                    })
                    .collect(),
            })
            .collect()
    }

    /// A registration that measured no pair.
    fn no_pairs() -> Registration {
        Registration {
            corrections: vec![],
            pairs: vec![],
            candidates: vec![],
            pairs_expected: 0,
            pairs_measured: 0,
            unregistered_views: vec![],
            placed_radially: vec![],
            placed_by_end_face: vec![],
            end_face_implausible: vec![],
            closure: None,
        }
    }

    /// API 5B's buttress form, and the phase of a helix that every bin read alike (views 10° apart).
    static BUTTRESS: std::sync::LazyLock<(ThreadForm, PhaseUncertainty)> = std::sync::LazyLock::new(|| {
        let form = ThreadForm::api_buttress(5.08, 1.575, 0.0508, 0.0625)
            .expect("a buttress form of the tests' nominal height");
        let helix = Helix {
            z_h_mm: 1.0,
            pitch_mm: form.pitch_mm,
            taper_on_diameter: 0.0625,
            fit_rms_um: 100.0,
            bins_used: 360,
            amplitude_ratio: Some(1.0),
            phase_readings: (0..360).map(|b| (b, 1.0)).collect(),
            local_offsets_mm: Vec::new(),
        };
        let phase = helix.phase_uncertainty(&form, 10.0);
        (form, phase)
    });

    /// A buttress part's scales (5-pixel focus window, 5-bin height window, no end face).
    fn scales_of<'a>(st: &'a Station, registration: &'a Registration, crests: &'a [ThreadObservation]) -> Scales<'a> {
        Scales {
            station: st,
            focus_window_radius_px: 5,
            pipe_radius_mm: 57.15,
            form: &BUTTRESS.0,
            phase: &BUTTRESS.1,
            registration,
            end_face: None,
            crests,
            height_window_half_bins: 5,
        }
    }

    /// A quality that fails the measurement's checks ([`measurement_failed`]).
    fn depth_coverage_low() -> Quality {
        Quality {
            status: QualityStatus::Degraded,
            reasons: vec![QualityReason { code: QualityCode::DepthCoverageLow, message: String::new() }],
        }
    }

    /// A part measured in scraps (no thread with 5 heights) still carries its heights' dispersion:
    /// about the part's median, where no thread's median can be read.
    #[test]
    fn a_part_measured_in_scraps_carries_the_dispersion_of_all_its_heights() {
        let registration = no_pairs();
        let st = station(0.04);
        let failed = depth_coverage_low();
        // Three heights a thread, 1.575 mm but for one 0.6 mm low on each thread.
        let mut threads = noisy(0.004);
        for t in &mut threads {
            for (k, b) in t.bins.iter_mut().enumerate() {
                b.height_mm = match k {
                    10 | 11 => Some(1.575),
                    12 => Some(0.975),
                    _ => None,
                };
            }
        }
        let (budget, _) = heights(
            &mut threads,
            &scales_of(&st, &registration, &[]),
            Some(3.0),
            &failed,
            &UncertaintyOptions::default(),
        );
        // 3 of 9 heights 0.6 mm below the part's median (1.575): √(3 · 0.6² / 9) = 346.4 µm.
        assert!((budget.along_helix_um - 346.41).abs() < 0.01, "{budget:?}");
        let u_um = 1e3 * threads[0].bins[12].uncertainty_mm.unwrap();
        assert!(u_um > 600.0, "{u_um}");
    }

    /// A failed measurement's dispersion terms read machined crests only, and each thread its own
    /// distance from nominal.
    #[test]
    fn black_crests_stay_out_of_the_dispersion_and_each_thread_has_its_own_bias() {
        let registration = no_pairs();
        let st = station(0.04);
        let failed = depth_coverage_low();
        let options = UncertaintyOptions::default();
        // Thread 2 has a black crest over 100–140° (photometric) and 200–219° (on the mill
        // surface), where its heights are 150 µm low; thread 3 reads 200 µm under nominal.
        let mut threads = noisy(0.004);
        for b in &mut threads[1].bins {
            if (100.0..140.0).contains(&b.angle_deg) || (200.0..220.0).contains(&b.angle_deg) {
                b.height_mm = Some(1.425);
            }
        }
        for b in &mut threads[2].bins {
            b.height_mm = Some(1.375);
        }
        let crests: Vec<ThreadObservation> = threads
            .iter()
            .map(|t| ThreadObservation {
                index: t.index,
                black_crest_arcs_deg: if t.index == 2 { vec![[100.0, 140.0]] } else { vec![] },
                bins: t
                    .bins
                    .iter()
                    .map(|b| rules::CrestBin {
                        angle_deg: b.angle_deg - 0.5,
                        width_deg: 1.0,
                        z_mm: 0.0,
                        height_mm: b.height_mm,
                        chamfer: false,
                        on_mill_surface: t.index == 2 && (200.0..220.0).contains(&b.angle_deg),
                        mill_arc_deg: None,
                        seen: true,
                    })
                    .collect(),
            })
            .collect();
        let scales = |crests| scales_of(&st, &registration, crests);
        let (budget, means) = heights(&mut threads, &scales(&crests), Some(3.0), &failed, &options);
        // The black crests (60 bins) and 5 bins beyond each of their ends (20) are left out: the
        // machined heights are all nominal, and nothing departs from a thread's median.
        assert_eq!(budget.black_crest_bins_left_out, 80, "{budget:?}");
        assert!(budget.along_helix_um < 1e-9, "{budget:?}");
        let by_thread: Vec<(u32, f64)> = budget.from_nominal_by_thread.iter().map(|t| (t.thread, t.um)).collect();
        assert_eq!(by_thread.len(), 3);
        assert!(
            by_thread[0].1 < 1e-9 && by_thread[1].1 < 1e-9 && (by_thread[2].1 - 200.0).abs() < 1e-6,
            "{by_thread:?}"
        );
        // Thread 3's heights carry its 200 µm; the others do not.
        let u = |t: usize| 1e3 * threads[t].bins[50].uncertainty_mm.unwrap();
        let bias_um = 2.0 * 200.0 / 3f64.sqrt();
        assert!(u(0) < 10.0 && (u(1) - u(0)).abs() < 1e-9 && u(2) > bias_um, "{} {} {}", u(0), u(1), u(2));
        assert!(1e3 * means[2].1.unwrap() > bias_um && 1e3 * means[0].1.unwrap() < 10.0);
        // Without the crest stage's findings the black crests count as scatter.
        let (budget, _) = heights(&mut threads, &scales(&[]), Some(3.0), &failed, &options);
        // 60 of 1080 heights 150 µm off their median: 35.4 µm RMS.
        assert!((budget.along_helix_um - 35.36).abs() < 0.01 && budget.black_crest_bins_left_out == 0, "{budget:?}");
    }

    #[test]
    fn every_height_gets_the_combined_uncertainty_and_a_failed_measurement_its_dispersion() {
        let registration = no_pairs();
        let st = station(0.04);
        let scales = scales_of(&st, &registration, &[]);
        let options = UncertaintyOptions::default();
        let mut threads = noisy(0.004);
        let (budget, means) = heights(&mut threads, &scales, Some(3.0), &ok(), &options);
        // Neighbours differ by 8 µm: σ = 1.4826 · 8/√2 µm (the robust scale of the differences,
        // normal-consistent); 11 pixels of 0.04 mm span 0.44 bins (L = 1); the mean of 7 divides
        // it by √7; the method adds 0.05 × 40 µm = 2 µm.
        let noise = 1.4826 * 8.0 / 2f64.sqrt() / 7f64.sqrt();
        let expected_of = |noise: f64| 2.0 * (noise * noise + 2.0 * 2.0).sqrt();
        let expected_um = expected_of(noise);
        let u = 1e3 * threads[1].bins[100].uncertainty_mm.unwrap();
        assert!((u - expected_um).abs() < 0.05, "{u} against {expected_um}");
        assert!((budget.method_um - 2.0).abs() < 1e-9 && budget.along_helix_um == 0.0, "{budget:?}");
        // A thread's mean averages 360 bins of noise, not the method's part.
        let mean_u = 1e3 * means[1].1.unwrap();
        assert!(mean_u < u && mean_u > 2.0 * 2.0, "{mean_u}");
        // Four times the scatter: about four times the noise part.
        let mut louder = noisy(0.016);
        heights(&mut louder, &scales, Some(3.0), &ok(), &options);
        assert!(1e3 * louder[1].bins[100].uncertainty_mm.unwrap() > 3.0 * u);
        // A measurement that failed its checks: every height also carries the heights' RMS
        // departure from their thread's median (a quarter of each thread 40 µm high: 20 µm) and
        // their median's from nominal (here none).
        let failed = depth_coverage_low();
        let mut wandering = noisy(0.004);
        for t in &mut wandering {
            for b in &mut t.bins[..90] {
                b.height_mm = Some(1.615);
            }
        }
        let (budget, means) = heights(&mut wandering, &scales, Some(3.0), &failed, &options);
        assert!((budget.along_helix_um - 20.0).abs() < 1e-6 && budget.from_nominal_um < 1e-9, "{budget:?}");
        let expected_um = 2.0 * (noise * noise + 2.0 * 2.0 + 20.0 * 20.0).sqrt();
        let u = 1e3 * wandering[1].bins[100].uncertainty_mm.unwrap();
        assert!((u - expected_um).abs() < 0.05, "{u} against {expected_um}");
        // A thread's mean keeps it whole: the views' errors do not average along the helix.
        assert!(1e3 * means[1].1.unwrap() > 2.0 * 20.0);
        // All heights 30 µm under nominal, evenly: the bias shows only against nominal.
        let mut low = noisy(0.004);
        for b in low.iter_mut().flat_map(|t| t.bins.iter_mut()) {
            b.height_mm = Some(1.545);
        }
        let (budget, _) = heights(&mut low, &scales, Some(3.0), &failed, &options);
        assert!(budget.along_helix_um < 1e-9 && (budget.from_nominal_um - 30.0).abs() < 1e-6, "{budget:?}");
        // As a rectangular distribution over ±30 µm: 30/√3 µm.
        let expected_um = 2.0 * (noise * noise + 2.0 * 2.0 + 30.0 * 30.0 / 3.0).sqrt();
        assert!((1e3 * low[1].bins[100].uncertainty_mm.unwrap() - expected_um).abs() < 0.05);
        // The same heights in a measurement that passed its checks: neither term.
        let (budget, _) = heights(&mut low, &scales, Some(3.0), &ok(), &options);
        assert_eq!((budget.along_helix_um, budget.from_nominal_um), (0.0, 0.0));
        // No height, no uncertainty.
        threads[0].bins[5].height_mm = None;
        heights(&mut threads, &scales, Some(3.0), &ok(), &options);
        assert_eq!(threads[0].bins[5].uncertainty_mm, None);
        // A part seen in short runs (at a random station, 38 bins in runs of 3–11): no bin has
        // ten neighbouring pairs within reach, yet every height has its uncertainty, from the
        // pairs there are; a lone height has half the depth of field.
        let mut sparse = noisy(0.004);
        for (i, b) in sparse.iter_mut().flat_map(|t| t.bins.iter_mut()).enumerate() {
            if i % 40 >= 4 {
                (b.height_mm, b.raw_height_mm) = (None, None);
            }
        }
        heights(&mut sparse, &scales, Some(3.0), &ok(), &options);
        let u = 1e3 * sparse[1].bins[1].uncertainty_mm.expect("a height in a short run has its uncertainty");
        assert!((u - expected_of(noise)).abs() < 0.05, "{u}");
        let mut lone = noisy(0.004);
        for (i, b) in lone.iter_mut().flat_map(|t| t.bins.iter_mut()).enumerate() {
            if i != 400 {
                (b.height_mm, b.raw_height_mm) = (None, None);
            }
        }
        heights(&mut lone, &scales, Some(3.0), &ok(), &options);
        let u = 1e3 * lone[1].bins[40].uncertainty_mm.expect("a lone height has its uncertainty");
        // Half of the 0.5 mm depth of field over √7 (the mean's bins), with the method's 2 µm.
        assert!((u - expected_of(250.0 / 7f64.sqrt())).abs() < 0.05, "{u}");
    }

    #[test]
    fn heights_are_judged_against_the_tolerance_with_their_uncertainty() {
        use HeightFinding::*;
        let judge = |mean, u| judge_height(Some(mean), Some(u), 1.575, 0.05);
        assert_eq!(judge(1.575, 0.01), Within);
        assert_eq!(judge(1.62, 0.01), Indeterminate);
        assert_eq!(judge(1.64, 0.01), Outside);
        assert_eq!(judge(1.51, 0.01), Outside);
        assert_eq!(judge_height(None, Some(0.01), 1.575, 0.05), NotJudged);
    }
}
