//! The benchmark's printout: the table of cases, the targets read on them, and the breakdowns below.

use super::suite::CaseResult;
use serde::Serialize;

/// One of the pipeline issue's targets, read on a set of benchmark results.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TargetCheck {
    pub target: &'static str,
    pub met: bool,
    /// The worst value and where it was found.
    pub worst: String,
}

/// The pipeline issue's targets over these results: per-thread height RMS ≤ 10 µm and max ≤ 25 µm,
/// every verdict agreeing, black-crest length within 2 mm, registration within 0.02° and 5 µm
/// (after refinement; over the views and for every view), the Table 1 threads within 10 µm and the standard preset's inspection
/// within 3× its decode. A target with no case to read it on is left out.
pub fn targets(results: &[CaseResult]) -> Vec<TargetCheck> {
    let worst = |f: &dyn Fn(&CaseResult) -> f64| -> Option<(f64, &CaseResult)> {
        results.iter().map(|r| (f(r), r)).max_by(|a, b| a.0.total_cmp(&b.0))
    };
    let mut checks = Vec::new();
    let mut at_most = |target: &'static str, limit: f64, unit: &str, digits: usize, f: &dyn Fn(&CaseResult) -> f64| {
        if let Some((value, r)) = worst(f) {
            checks.push(TargetCheck {
                target,
                met: value <= limit,
                worst: format!("{value:.digits$}{unit}, {}", r.label()),
            });
        }
    };
    at_most("per-thread height RMS ≤ 10 µm", 10.0, " µm", 1, &|r| r.accuracy.height_rms_um);
    at_most("per-thread height max ≤ 25 µm", 25.0, " µm", 1, &|r| r.accuracy.height_max_um);
    at_most("black-crest length error ≤ 2 mm per thread", 2.0, " mm", 2, &|r| {
        r.accuracy.black_crest_length_max_error_mm
    });
    // The issue does not say over what registration's bound holds: over the views (RMS), or for
    // every view (its worst). Both readings are printed.
    at_most("registration ≤ 0.02° (RMS over views)", 0.02, "°", 4, &|r| r.registration.angle_rms_deg);
    at_most("registration ≤ 5 µm (RMS over views)", 5.0, " µm", 1, &|r| r.registration.axial_rms_um);
    at_most("registration ≤ 0.02° (every view)", 0.02, "°", 4, &|r| r.registration.angle_max_deg);
    at_most("registration ≤ 5 µm (every view)", 5.0, " µm", 1, &|r| r.registration.axial_max_um);
    if !results.is_empty() {
        let agree = results.iter().filter(|r| r.accuracy.verdict_agrees).count();
        checks.push(TargetCheck {
            target: "verdicts agree",
            met: agree == results.len(),
            worst: format!("{agree} of {}", results.len()),
        });
    }
    let table1: Vec<(u32, f64)> =
        results.iter().flat_map(|r| r.table1.iter().map(|(i, m, t)| (*i, 1e3 * (m - t).abs()))).collect();
    if let Some((thread, error_um)) = table1.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1)) {
        checks.push(TargetCheck {
            target: "Table 1 threads within 10 µm",
            met: error_um <= 10.0,
            worst: format!("{error_um:.1} µm, thread {thread}"),
        });
    }
    for r in results.iter().filter(|r| r.preset == "standard" && r.station_seed.is_none()) {
        let ratio = r.inspect_seconds / r.decode_seconds;
        checks.push(TargetCheck {
            target: "standard inspection ≤ 3× its decode",
            met: ratio <= 3.0,
            worst: format!("{ratio:.2}×, {}", r.label()),
        });
    }
    checks
}

/// The benchmark table, markdown.
pub fn table(results: &[CaseResult]) -> String {
    let mut out = String::from(
        "| case | height RMS / max µm | bins | depth RMS / median µm, coverage | registration ° / axial µm (encoder) | black-crest length err mm | verdict | decode s | inspect s (ratio) |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let a = &r.accuracy;
        let g = &r.registration;
        out.push_str(&format!(
            "| {} | {:.1} / {:.1} | {} | {:.0} / {:.1}, {:.1}% | {:.4} / {:.1} ({:.2} / {:.0}) | {:.2} | {} | {:.2} | {:.2} ({:.2}×) |\n",
            r.label(),
            a.height_rms_um,
            a.height_max_um,
            a.bins_compared,
            r.depth_rms_um,
            r.depth_median_um,
            100.0 * r.depth_coverage,
            g.angle_rms_deg,
            g.axial_rms_um,
            g.encoder_angle_rms_deg,
            g.encoder_axial_rms_um,
            a.black_crest_length_max_error_mm,
            if a.verdict_agrees { "agrees" } else { "DISAGREES" },
            r.decode_seconds,
            r.inspect_seconds,
            r.inspect_seconds / r.decode_seconds
        ));
    }
    for r in results.iter().filter(|r| !r.table1.is_empty()) {
        out.push_str("\nSeed Table 1 (mean of bins 0–4°): thread, measured mm, truth mm, error µm\n");
        for (i, m, t) in &r.table1 {
            out.push_str(&format!("  {i:2}  {m:.4}  {t:.4}  {:+.1}\n", 1e3 * (m - t)));
        }
    }
    if results.iter().any(|r| !r.black_crests.is_empty()) {
        out.push_str("\nBlack crests within Lc, per thread: arcs found (true arcs), length error mm\n");
        let arcs = |a: &[[f64; 2]]| -> String {
            if a.is_empty() {
                return "none".into();
            }
            a.iter().map(|[s, e]| format!("{s:.1}°–{e:.1}°")).collect::<Vec<_>>().join(", ")
        };
        for r in results.iter().filter(|r| !r.black_crests.is_empty()) {
            let rows: Vec<String> = r
                .black_crests
                .iter()
                .map(|b| {
                    format!(
                        "thread {} {} ({}) {:.2}",
                        b.thread,
                        arcs(&b.reported_arcs_deg),
                        arcs(&b.truth_arcs_deg),
                        (b.reported_mm - b.truth_mm).abs()
                    )
                })
                .collect();
            out.push_str(&format!("  {}: {}\n", r.label(), rows.join("; ")));
        }
    }
    out.push_str(
        "\nRegistration, every view and every pair: the worst view's angle ° and axial µm (after the solve), and \
         the pairs' measured shifts against the true ones, RMS along the arc / axially µm (pairs measured)\n",
    );
    for r in results {
        let g = &r.registration;
        out.push_str(&format!(
            "  {}: worst view {:.4}° / {:.1} µm; pairs {:.1} / {:.1} µm ({})\n",
            r.label(),
            g.angle_max_deg,
            g.axial_max_um,
            g.pair_arc_rms_um,
            g.pair_axial_rms_um,
            g.pairs_measured
        ));
    }
    out.push_str(
        "\nAbsolute z (overlaps cannot observe it; taken from the end face where the views show it): helix z_h \
         measured − truth, and the encoders' mean axial offset, µm\n",
    );
    for r in results {
        out.push_str(&format!(
            "  {}: {:+.1} ({:+.1})\n",
            r.label(),
            r.helix_z_error_um,
            r.encoder_mean_axial_offset_um
        ));
    }
    let checks = targets(results);
    if !checks.is_empty() {
        out.push_str("\nTargets of the pipeline issue, read on these cases (worst value, where):\n");
        for c in &checks {
            out.push_str(&format!("  {}: {} ({})\n", c.target, if c.met { "met" } else { "NOT MET" }, c.worst));
        }
    }
    let stages: Vec<String> = results
        .iter()
        .map(|r| {
            format!(
                "{}: {}",
                r.label(),
                r.stage_seconds.iter().map(|(s, t)| format!("{s} {t:.2}")).collect::<Vec<_>>().join(", ")
            )
        })
        .collect();
    out.push_str(&format!("\nStage times (s):\n  {}\n", stages.join("\n  ")));
    out.push_str("\nRenderings (this machine, when first rendered): preset, frames, MB, seconds\n");
    for r in results {
        out.push_str(&format!(
            "  {}: {} frames, {:.0} MB, {:.1} s\n",
            r.label(),
            r.render.frames,
            r.render.bytes as f64 / 1e6,
            r.render.seconds
        ));
    }
    out
}

/// A station's class by its object pixel alone: fine (≤ 0.06 mm), medium (≤ 0.10 mm) or coarse,
/// the bounds of the envelope's classes (`domain::station::StationClass`; the benchmark groups a
/// station outside their other ranges by its pixel too).
pub fn station_class(object_pixel_mm: f64) -> &'static str {
    use crate::domain::station::{FINE_MAX_PIXEL_MM, MEDIUM_MAX_PIXEL_MM};
    if object_pixel_mm <= FINE_MAX_PIXEL_MM {
        "fine"
    } else if object_pixel_mm <= MEDIUM_MAX_PIXEL_MM {
        "medium"
    } else {
        "coarse"
    }
}

/// " [lo–hi% on n]": the coverage's 95% interval on the case's independent bins, or nothing.
fn interval_text(a: &crate::eval::truth::Accuracy) -> String {
    match (a.uncertainty_coverage_interval, a.uncertainty_effective_bins) {
        (Some([lo, hi]), Some(n)) => format!(" [{:.0}–{:.0}% on {n:.0}]", 100.0 * lo, 100.0 * hi),
        _ => String::new(),
    }
}

/// The station benchmark's table: one row per case (its station, heights, coverage,
/// registration, black-crest length, verdict and decision, the uncertainty's coverage), then a
/// summary per station class.
pub fn station_table(results: &[CaseResult], refused: &[(String, String)]) -> String {
    let mut out = String::from(
        "| case | class | pixel mm | DOF mm | step DOF | views (rows) | arc | height RMS / max µm | bins seen | pairs | reg ° / µm | black-crest err mm | verdict (truth) | decision | U coverage (p95 \\|e\\|/U) [95% interval on n independent bins] | quality |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let Some(s) = &r.station else { continue };
        let a = &r.accuracy;
        let seen = a.bins_compared as f64 / (a.bins_compared + a.bins_missing).max(1) as f64;
        out.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} | {:.2} | {} ({}) | {} | {:.1} / {:.1} | {:.0}% | {}/{} | {:.3} / {:.0} | {:.2} | {} ({}) | {}{} | {} | {:?} |\n",
            r.label(),
            station_class(s.object_pixel_mm),
            s.object_pixel_mm,
            s.depth_of_field_mm,
            s.frame_step_dof,
            s.views,
            s.axial_rows,
            r.sector_deg.map_or("ring".into(), |d| format!("{d:.0}°")),
            a.height_rms_um,
            a.height_max_um,
            100.0 * seen,
            r.pairs_measured,
            r.pairs_expected,
            r.registration.angle_rms_deg,
            r.registration.axial_rms_um,
            a.black_crest_length_max_error_mm,
            r.verdict.as_str(),
            r.truth_verdict.as_str(),
            a.decision.map_or("-", |d| d.as_str()),
            if a.decision_wrong { " WRONG" } else { "" },
            match (a.uncertainty_coverage, a.uncertainty_ratio_p95) {
                (Some(c), Some(q)) => format!("{:.1}% ({q:.2}){}", 100.0 * c, interval_text(a)),
                (Some(c), None) => format!("{:.1}%{}", 100.0 * c, interval_text(a)),
                _ => "-".into(),
            },
            r.quality,
        ));
    }
    for (case, why) in refused {
        out.push_str(&format!("| {case} | refused: {why} |\n"));
    }
    out.push_str(
        "\n| class | cases | height RMS median / worst µm | height max worst µm | verdicts wrong | decisions wrong | indeterminate | U coverage min / median | U coverage within 90–99% / over / under | U interval meets 90–99% / above / below (holds 95%) | U coverage over the class's bins (over its independent bins [95% interval] on n) | p95 \\|e\\|/U min / max | pairs measured |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for class in ["fine", "medium", "coarse"] {
        let rows: Vec<&CaseResult> = results
            .iter()
            .filter(|r| r.station.as_ref().is_some_and(|s| station_class(s.object_pixel_mm) == class))
            .collect();
        if rows.is_empty() {
            continue;
        }
        let mut rms: Vec<f64> = rows.iter().map(|r| r.accuracy.height_rms_um).filter(|v| v.is_finite()).collect();
        let worst_rms = rms.iter().copied().fold(0.0, f64::max);
        let median_rms = crate::numeric::stats::median(&mut rms).unwrap_or(f64::NAN);
        let worst_max = rows.iter().map(|r| r.accuracy.height_max_um).fold(0.0, f64::max);
        let mut cov: Vec<f64> = rows.iter().filter_map(|r| r.accuracy.uncertainty_coverage).collect();
        let cov_min = cov.iter().copied().fold(1.0, f64::min);
        let cov_median = crate::numeric::stats::median(&mut cov).unwrap_or(f64::NAN);
        let (measured, expected) = rows.iter().fold((0, 0), |(m, e), r| (m + r.pairs_measured, e + r.pairs_expected));
        let within = cov.iter().filter(|c| (0.90..=0.99).contains(*c)).count();
        let over = cov.iter().filter(|c| **c > 0.99).count();
        let under = cov.iter().filter(|c| **c < 0.90).count();
        let intervals: Vec<[f64; 2]> = rows.iter().filter_map(|r| r.accuracy.uncertainty_coverage_interval).collect();
        let meets = intervals.iter().filter(|i| i[1] >= 0.90 && i[0] <= 0.99).count();
        let above = intervals.iter().filter(|i| i[0] > 0.99).count();
        let below = intervals.iter().filter(|i| i[1] < 0.90).count();
        let holds_95 = intervals.iter().filter(|i| i[0] <= 0.95 && i[1] >= 0.95).count();
        let (covered, compared) = rows.iter().fold((0.0, 0usize), |(c, n), r| match r.accuracy.uncertainty_coverage {
            Some(share) => (c + share * r.accuracy.bins_compared as f64, n + r.accuracy.bins_compared),
            None => (c, n),
        });
        // On the independent bins of all the class's cases together: what the class can tell.
        let (hits, trials) = rows.iter().fold((0usize, 0usize), |(h, n), r| {
            match (r.accuracy.uncertainty_coverage, r.accuracy.uncertainty_effective_bins) {
                (Some(c), Some(e)) => (h + (c * e.round()).round() as usize, n + e.round() as usize),
                _ => (h, n),
            }
        });
        let (lo, hi) = crate::numeric::calibration::share_interval(hits, trials, 0.95);
        let pooled = if compared > 0 && trials > 0 {
            format!(
                "{:.1}% ({:.1}% [{:.0}–{:.0}%] on {trials})",
                100.0 * covered / compared as f64,
                100.0 * hits as f64 / trials as f64,
                100.0 * lo,
                100.0 * hi
            )
        } else {
            "-".into()
        };
        let ratios: Vec<f64> = rows.iter().filter_map(|r| r.accuracy.uncertainty_ratio_p95).collect();
        let ratio_min = ratios.iter().copied().fold(f64::INFINITY, f64::min);
        let ratio_max = ratios.iter().copied().fold(0.0, f64::max);
        out.push_str(&format!(
            "| {class} | {} | {:.1} / {:.1} | {:.1} | {} | {} | {} | {:.1}% / {:.1}% | {within} / {over} / {under} | {meets} / {above} / {below} ({holds_95}) | {pooled} | {ratio_min:.2} / {ratio_max:.2} | {}/{} ({:.0}%) |\n",
            rows.len(),
            median_rms,
            worst_rms,
            worst_max,
            rows.iter().filter(|r| !r.accuracy.verdict_agrees).count(),
            rows.iter().filter(|r| r.accuracy.decision_wrong).count(),
            rows.iter()
                .filter(|r| r.accuracy.decision == Some(crate::pipeline::uncertainty::Decision::Indeterminate))
                .count(),
            100.0 * cov_min,
            100.0 * cov_median,
            measured,
            expected,
            100.0 * measured as f64 / expected.max(1) as f64,
        ));
    }
    if !refused.is_empty() {
        out.push_str(&format!(
            "\n{} case(s) refused by the pipeline (an error, no report: no height, no verdict, no decision): {}\n",
            refused.len(),
            refused.iter().map(|(c, _)| c.as_str()).collect::<Vec<_>>().join(", ")
        ));
    }
    // How the method's uncertainty is chosen: the coverage over all bins of these cases had it
    // been each candidate multiple of the object pixel.
    let candidates = results.iter().find_map(|r| (!r.accuracy.coverage_by_method_px.is_empty()).then_some(r));
    if let Some(first) = candidates {
        out.push_str("\nU coverage had the method's standard uncertainty been k × object pixel (median and least over the cases):\n");
        for (i, (px, _)) in first.accuracy.coverage_by_method_px.iter().enumerate() {
            let mut c: Vec<f64> =
                results.iter().filter_map(|r| r.accuracy.coverage_by_method_px.get(i).map(|x| x.1)).collect();
            let least = c.iter().copied().fold(1.0, f64::min);
            out.push_str(&format!(
                "  {px:.2} px: median {:.1}%, least {:.1}%\n",
                100.0 * crate::numeric::stats::median(&mut c).unwrap_or(f64::NAN),
                100.0 * least
            ));
        }
    }
    out
}
