//! A report measured against the simulator's truth: heights per bin, black-crest arcs, verdict,
//! registration against the true poses.

use crate::pipeline::report::Report;
use crate::sim::Truth;
use serde::Serialize;

/// Per-thread height error over bins measured in both, and black-crest and verdict agreement.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Accuracy {
    pub bins_compared: usize,
    /// Bins where truth has a value and the report none (coverage loss).
    pub bins_missing: usize,
    pub height_rms_um: f64,
    pub height_max_um: f64,
    pub height_bias_um: f64,
    /// Largest |report − truth| black-crest length over threads (mm), over the crests the views
    /// showed: where the report says some crest within Lc was not seen
    /// (`assessment.seen_crest_arcs`), each thread's truth arcs are clipped to its seen arcs first.
    pub black_crest_length_max_error_mm: f64,
    /// Crest degrees within Lc the views showed, over all threads (None when they showed all).
    pub seen_crest_deg: Option<f64>,
    pub verdict_agrees: bool,
    /// The worst bins: (thread, angle, report, truth).
    pub worst: Vec<(u32, f64, f64, f64)>,
    /// The share of compared bins whose |error| is within the reported expanded uncertainty
    /// (None without uncertainties).
    pub uncertainty_coverage: Option<f64>,
    /// The 95th percentile over the compared bins of |error| / U: the factor the expanded
    /// uncertainty would need to cover 95% of them (1: as it should; under 0.5, U is over twice
    /// what that needs, padded; over 1, too small). None without uncertainties.
    #[serde(default)]
    pub uncertainty_ratio_p95: Option<f64>,
    /// How many independent errors the compared bins hold: neighbouring bins share a focus
    /// window, a view and a thread's bias, so that a case of 500 bins may hold a few dozen
    /// ([`crate::numeric::calibration::effective_count`] on each thread's error / U along the
    /// helix). None without uncertainties.
    #[serde(default)]
    pub uncertainty_effective_bins: Option<f64>,
    /// The 95% Clopper–Pearson interval of the coverage measured on that many independent bins:
    /// the true coverages this case cannot tell apart. None without uncertainties.
    #[serde(default)]
    pub uncertainty_coverage_interval: Option<[f64; 2]>,
    /// The same share had the method's standard uncertainty been each of these multiples of the
    /// object pixel (the rest of the budget as reported): how `uncertainty.method_px` is chosen.
    pub coverage_by_method_px: Vec<(f64, f64)>,
    /// The report's decision, and whether truth contradicts it (a verdict of `conforms` on a
    /// part whose truth is reject, or `does_not_conform` on one whose truth is accept).
    pub decision: Option<crate::pipeline::uncertainty::Decision>,
    pub decision_wrong: bool,
    pub review_required: bool,
}

/// Method uncertainties (object pixels) whose coverage the benchmark reports.
pub const METHOD_PX_CANDIDATES: [f64; 8] = [0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0];

/// Compares heights bin by bin (only full-coverage bins of threads present in both), black-crest
/// lengths per thread (over the crests the views showed), and the verdict.
pub fn compare(report: &Report, truth: &Truth) -> Accuracy {
    let mut errors: Vec<(f64, u32, f64, f64, f64)> = Vec::new();
    // (|error|, expanded uncertainty) per compared bin that has one, mm.
    let mut against_u: Vec<(f64, f64)> = Vec::new();
    // Per thread, bin for bin: error / U, for how many independent errors the case holds.
    let mut normalised: Vec<Vec<Option<f64>>> = Vec::new();
    let mut missing = 0;
    for t in &truth.threads {
        let Some(r) = report.threads.iter().find(|r| r.index == t.index) else {
            missing += t.height_mm.values.iter().flatten().count();
            continue;
        };
        let mut thread_normalised = vec![None; t.height_mm.values.len()];
        for (k, truth_value) in t.height_mm.values.iter().enumerate() {
            let Some(tv) = truth_value else { continue };
            match r.height_mm.values.get(k).copied().flatten() {
                Some(rv) => {
                    errors.push((1e3 * (rv - tv), t.index, t.height_mm.angles_deg[k], rv, *tv));
                    if let Some(u) = r.height_mm.uncertainty_mm.get(k).copied().flatten() {
                        against_u.push(((rv - tv).abs(), u));
                        thread_normalised[k] = (u > 0.0).then(|| (rv - tv) / u);
                    }
                }
                None => missing += 1,
            }
        }
        normalised.push(thread_normalised);
    }
    let n = errors.len().max(1) as f64;
    let rms = (errors.iter().map(|e| e.0 * e.0).sum::<f64>() / n).sqrt();
    let bias = errors.iter().map(|e| e.0).sum::<f64>() / n;
    let max = errors.iter().map(|e| e.0.abs()).fold(0.0, f64::max);
    errors.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
    let coverage = (!against_u.is_empty())
        .then(|| against_u.iter().filter(|(e, u)| e <= u).count() as f64 / against_u.len() as f64);
    let effective = crate::numeric::calibration::effective_count(&normalised, 0.05);
    let interval = coverage.zip(effective).map(|(c, n)| {
        let trials = n.round() as usize;
        let (lo, hi) = crate::numeric::calibration::share_interval((c * trials as f64).round() as usize, trials, 0.95);
        [lo, hi]
    });
    let seen = report.assessment.seen_crest_arcs.as_deref();
    let length_error =
        black_crests(report, truth).iter().map(|b| (b.reported_mm - b.truth_mm).abs()).fold(0.0, f64::max);
    Accuracy {
        bins_compared: errors.len(),
        bins_missing: missing,
        height_rms_um: rms,
        height_max_um: max,
        height_bias_um: bias,
        black_crest_length_max_error_mm: length_error,
        seen_crest_deg: seen.map(|threads| threads.iter().map(|t| crate::domain::arcs::arcs_deg(&t.arcs_deg)).sum()),
        verdict_agrees: report.verdict == truth.verdict,
        worst: errors.iter().take(5).map(|e| (e.1, e.2, e.3, e.4)).collect(),
        uncertainty_coverage: coverage,
        uncertainty_ratio_p95: ratio_p95(&against_u),
        uncertainty_effective_bins: effective,
        uncertainty_coverage_interval: interval,
        coverage_by_method_px: coverage_by_method_px(report, &against_u),
        decision: Some(report.decision),
        decision_wrong: {
            use crate::domain::rules::Verdict;
            use crate::pipeline::uncertainty::Decision;
            matches!(
                (report.decision, truth.verdict),
                (Decision::Conforms, Verdict::Reject) | (Decision::DoesNotConform, Verdict::Accept)
            )
        },
        review_required: report.review_required,
    }
}

/// The 95th percentile of |error| / U (nearest rank), None without a bin.
fn ratio_p95(against_u: &[(f64, f64)]) -> Option<f64> {
    let mut ratios: Vec<f64> = against_u.iter().map(|(e, u)| if *u > 0.0 { e / u } else { f64::INFINITY }).collect();
    if ratios.is_empty() {
        return None;
    }
    ratios.sort_by(f64::total_cmp);
    let rank = ((0.95 * ratios.len() as f64).ceil() as usize).clamp(1, ratios.len());
    Some(ratios[rank - 1])
}

/// The coverage of the expanded uncertainty had the method's term been each candidate: each
/// bin's noise part is what remains of its reported uncertainty without the method's and
/// registration's terms.
fn coverage_by_method_px(report: &Report, against_u: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let (Some(budget), Some(station)) = (&report.uncertainty, &report.station) else { return Vec::new() };
    if against_u.is_empty() {
        return Vec::new();
    }
    let k = budget.coverage_factor;
    let (m, r) = (1e-3 * budget.method_um, 1e-3 * budget.registration_um);
    METHOD_PX_CANDIDATES
        .iter()
        .map(|&px| {
            let method = px * station.object_pixel_mm;
            let covered = against_u
                .iter()
                .filter(|(e, u)| {
                    let noise_sq = ((u / k).powi(2) - m * m - r * r).max(0.0);
                    *e <= k * (noise_sq + method * method + r * r).sqrt()
                })
                .count();
            (px, covered as f64 / against_u.len() as f64)
        })
        .collect()
}

/// One thread's black crest, as reported and as true.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BlackCrest {
    pub thread: u32,
    pub reported_arcs_deg: Vec<[f64; 2]>,
    pub reported_mm: f64,
    /// Over the crests the views showed (`assessment.seen_crest_arcs`), when the report says some
    /// were not seen.
    pub truth_arcs_deg: Vec<[f64; 2]>,
    pub truth_mm: f64,
}

/// Every thread that has a black crest in the report or in truth, in thread order.
pub fn black_crests(report: &Report, truth: &Truth) -> Vec<BlackCrest> {
    let seen = report.assessment.seen_crest_arcs.as_deref();
    let mut rows: Vec<BlackCrest> = truth
        .threads
        .iter()
        .map(|t| {
            let (truth_arcs_deg, truth_mm) = match seen {
                None => (t.black_crest_arcs_deg.clone(), t.black_crest_length_mm),
                Some(seen) => {
                    let thread_seen = seen.iter().find(|s| s.index == t.index).map_or(&[][..], |s| &s.arcs_deg[..]);
                    let arcs = crate::domain::arcs::intersect_arcs(&t.black_crest_arcs_deg, thread_seen);
                    let mm = crate::domain::arcs::arc_length_mm(&arcs, truth.circumference_mm);
                    (arcs, mm)
                }
            };
            let reported = report.threads.iter().find(|r| r.index == t.index);
            BlackCrest {
                thread: t.index,
                reported_arcs_deg: reported.map_or_else(Vec::new, |r| r.black_crest_arcs_deg.clone()),
                reported_mm: reported.map_or(0.0, |r| r.black_crest_length_mm),
                truth_arcs_deg,
                truth_mm,
            }
        })
        .chain(report.threads.iter().filter(|r| truth.threads.iter().all(|t| t.index != r.index)).map(|r| BlackCrest {
            thread: r.index,
            reported_arcs_deg: r.black_crest_arcs_deg.clone(),
            reported_mm: r.black_crest_length_mm,
            truth_arcs_deg: Vec::new(),
            truth_mm: 0.0,
        }))
        .filter(|b| {
            b.reported_mm > 0.0 || b.truth_mm > 0.0 || !b.reported_arcs_deg.is_empty() || !b.truth_arcs_deg.is_empty()
        })
        .collect();
    rows.sort_by_key(|b| b.thread);
    rows
}

/// Registration error after refinement, with the global rotation and shift removed (they are not
/// observable from overlaps; the encoders' mean error stands for them).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RegistrationError {
    pub angle_rms_deg: f64,
    pub angle_max_deg: f64,
    pub axial_rms_um: f64,
    pub axial_max_um: f64,
    pub radial_rms_um: f64,
    /// The same before refinement (encoder poses), for scale.
    pub encoder_angle_rms_deg: f64,
    pub encoder_axial_rms_um: f64,
    /// Each measured pair's shift against the true one (the difference of the two views' true
    /// corrections), RMS over the pairs: along the arc at the pipe's outside radius, and axially,
    /// µm. What the pose graph starts from: a view's error after the solve is these errors summed
    /// around the ring.
    pub pair_arc_rms_um: f64,
    pub pair_axial_rms_um: f64,
    pub pairs_measured: usize,
}

pub(crate) fn gauge_free(errors: &[f64]) -> (f64, f64) {
    let mean = errors.iter().sum::<f64>() / errors.len().max(1) as f64;
    let rms = (errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / errors.len().max(1) as f64).sqrt();
    let max = errors.iter().map(|e| (e - mean).abs()).fold(0.0, f64::max);
    (rms, max)
}

pub(crate) fn registration_error(
    encoder: &[crate::domain::optics::ViewPose],
    refined: &[crate::domain::optics::ViewPose],
    truth: &[crate::domain::optics::ViewPose],
    pairs: &[crate::pipeline::register::PairMeasure],
    radius_mm: f64,
) -> RegistrationError {
    let diff = |poses: &[crate::domain::optics::ViewPose],
                f: &dyn Fn(&crate::domain::optics::ViewPose) -> f64|
     -> Vec<f64> { poses.iter().zip(truth).map(|(p, t)| f(p) - f(t)).collect() };
    let (angle_rms_deg, angle_max_deg) = gauge_free(&diff(refined, &|p| p.angle_deg));
    let (axial_rms, axial_max) = gauge_free(&diff(refined, &|p| p.axial_mm));
    let (radial_rms, _) = gauge_free(&diff(refined, &|p| p.lens_radius_mm));
    // Encoder minus truth per view: the negated correction registration should find.
    let (encoder_angle, encoder_axial) = (diff(encoder, &|p| p.angle_deg), diff(encoder, &|p| p.axial_mm));
    let (encoder_angle_rms_deg, _) = gauge_free(&encoder_angle);
    let (encoder_axial_rms, _) = gauge_free(&encoder_axial);
    // A pair measures how far b's content must move onto a's: c_b − c_a, c = truth − encoder.
    let pair_errors =
        |shift: &dyn Fn(&crate::pipeline::register::PairMeasure) -> f64, encoder_error: &[f64]| -> Vec<f64> {
            pairs.iter().map(|p| shift(p) - (encoder_error[p.a] - encoder_error[p.b])).collect()
        };
    let rms = |errors: &[f64]| (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    let pair_arc_rms_um = 1e3 * radius_mm * rms(&pair_errors(&|p| p.shift_angle_deg, &encoder_angle)).to_radians();
    let pair_axial_rms_um = 1e3 * rms(&pair_errors(&|p| p.shift_axial_mm, &encoder_axial));
    RegistrationError {
        pair_arc_rms_um,
        pair_axial_rms_um,
        pairs_measured: pairs.len(),
        angle_rms_deg,
        angle_max_deg,
        axial_rms_um: 1e3 * axial_rms,
        axial_max_um: 1e3 * axial_max,
        radial_rms_um: 1e3 * radial_rms,
        encoder_angle_rms_deg,
        encoder_axial_rms_um: 1e3 * encoder_axial_rms,
    }
}
