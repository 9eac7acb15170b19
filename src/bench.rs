//! Accuracy of a report against simulated truth, and the benchmark suite behind `crestscan bench`.

use crate::report::Report;
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
    /// Largest |report − truth| black-crest length over threads (mm).
    pub black_crest_length_max_error_mm: f64,
    pub verdict_agrees: bool,
    /// The worst bins: (thread, angle, report, truth).
    pub worst: Vec<(u32, f64, f64, f64)>,
}

/// Compares heights bin by bin (only full-coverage bins of threads present in both), black-crest
/// lengths per thread, and the verdict.
pub fn compare(report: &Report, truth: &Truth) -> Accuracy {
    let mut errors: Vec<(f64, u32, f64, f64, f64)> = Vec::new();
    let mut missing = 0;
    for t in &truth.threads {
        let Some(r) = report.threads.iter().find(|r| r.index == t.index) else {
            missing += t.height_mm.values.iter().flatten().count();
            continue;
        };
        for (k, truth_value) in t.height_mm.values.iter().enumerate() {
            let Some(tv) = truth_value else { continue };
            match r.height_mm.values.get(k).copied().flatten() {
                Some(rv) => errors.push((1e3 * (rv - tv), t.index, t.height_mm.angles_deg[k], rv, *tv)),
                None => missing += 1,
            }
        }
    }
    let n = errors.len().max(1) as f64;
    let rms = (errors.iter().map(|e| e.0 * e.0).sum::<f64>() / n).sqrt();
    let bias = errors.iter().map(|e| e.0).sum::<f64>() / n;
    let max = errors.iter().map(|e| e.0.abs()).fold(0.0, f64::max);
    errors.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
    let length_error = truth
        .threads
        .iter()
        .map(|t| {
            let reported = report.threads.iter().find(|r| r.index == t.index).map_or(0.0, |r| r.black_crest_length_mm);
            (reported - t.black_crest_length_mm).abs()
        })
        .chain(report.threads.iter().filter(|r| truth.threads.iter().all(|t| t.index != r.index)).map(|r| r.black_crest_length_mm))
        .fold(0.0, f64::max);
    Accuracy {
        bins_compared: errors.len(),
        bins_missing: missing,
        height_rms_um: rms,
        height_max_um: max,
        height_bias_um: bias,
        black_crest_length_max_error_mm: length_error,
        verdict_agrees: report.verdict == truth.verdict,
        worst: errors.iter().take(5).map(|e| (e.1, e.2, e.3, e.4)).collect(),
    }
}
