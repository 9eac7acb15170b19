//! API 5B black-crest acceptance, as ../DOMAIN.md states it for this project.
//!
//! - Round threads: no black-crest point within Lc.
//! - Buttress: at most two threads may show black crests within Lc, and the black-crest length may
//!   not exceed 25% of the circumference, per thread (default) or over all threads combined.
//!
//! A crest point is black where the photometric stage saw mill scale on it (arcs, already clipped to
//! Lc) or where the crest stage found the crest geometrically on the mill surface within Lc (below
//! the machined crest cone, which catches crests polished to look machined; a low height alone is
//! not enough: a vanishing thread is shallow because its root rises, its crest is still machined).
//! The chamfer at the pipe end is machined: bins flagged `chamfer` never count as geometric black
//! crests.

use crate::domain::thread::Family;
use serde::{Deserialize, Serialize};

/// How the buttress 25% limit applies; the public paraphrases of 5B do not settle it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ArcRule {
    #[default]
    PerThread,
    Combined,
}

/// Fraction of the circumference a buttress black crest may cover.
pub const BUTTRESS_ARC_LIMIT: f64 = 0.25;
/// Threads within Lc that may show black crests on buttress.
pub const BUTTRESS_MAX_BLACK_THREADS: usize = 2;

/// One 1° crest bin of a thread, as measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CrestBin {
    /// Bin start angle; the bin spans [angle_deg, angle_deg + width_deg).
    pub angle_deg: f64,
    pub width_deg: f64,
    /// Crest centre-line z at the bin centre.
    pub z_mm: f64,
    /// None where the views did not cover the bin.
    pub height_mm: Option<f64>,
    /// The crest here is the machined end chamfer, not a thread crest.
    #[serde(default)]
    pub chamfer: bool,
    /// The crest stage found this crest below the machined crest cone: it is the mill surface.
    #[serde(default)]
    pub on_mill_surface: bool,
    /// The part of the bin on the mill surface, [from, to] in degrees, where a geometric run's
    /// fitted end falls inside the bin; None: all of it (when `on_mill_surface`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mill_arc_deg: Option<[f64; 2]>,
    /// The views showed this crest (its brightness or its radius was measured). Crests within Lc
    /// that no view showed make the verdict one over the crests seen: see
    /// [`ReasonCode::PartialCoverage`].
    #[serde(default = "yes")]
    pub seen: bool,
}

impl CrestBin {
    /// The bin's whole arc [from, to] in degrees.
    pub fn span_deg(&self) -> [f64; 2] {
        [self.angle_deg, self.angle_deg + self.width_deg]
    }
}

fn yes() -> bool {
    true
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ThreadObservation {
    pub index: u32,
    /// Photometric black-crest arcs [from, to] in degrees within [0, 360], already clipped to Lc.
    pub black_crest_arcs_deg: Vec<[f64; 2]>,
    pub bins: Vec<CrestBin>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RuleInput {
    pub family: Family,
    pub lc_mm: f64,
    pub circumference_mm: f64,
    pub nominal_height_mm: f64,
    pub height_tolerance_mm: f64,
    pub threads: Vec<ThreadObservation>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Accept,
    Reject,
}

impl Verdict {
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Accept => "accept",
            Verdict::Reject => "reject",
        }
    }
}

/// How a black crest was recognised.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BlackCrestEvidence {
    /// Mill-scale appearance on the crest.
    Photometric,
    /// Only the crest height gives it away: a polished or otherwise bright black crest.
    Geometric,
    Both,
}

/// A thread with black crests within Lc.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BlackThread {
    pub index: u32,
    pub arcs_deg: Vec<[f64; 2]>,
    pub length_mm: f64,
    pub evidence: BlackCrestEvidence,
}

/// Stable machine codes of the reasons.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReasonCode {
    NoBlackCrestWithinLc,
    RoundBlackCrestWithinLc,
    ButtressBlackCrestsWithinLimits,
    ButtressTooManyBlackThreads,
    ButtressArcOverLimit,
    ButtressCombinedArcOverLimit,
    PolishedBlackCrest,
    /// The views showed only part of the thread crests within Lc (value: crest degrees seen, limit:
    /// crest degrees within Lc): the verdict is over the crests seen. Informational; it does not
    /// change the verdict.
    PartialCoverage,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reason {
    pub code: ReasonCode,
    pub message: String,
    /// Threads the reason is about.
    pub threads: Vec<u32>,
    /// The measured quantity and the limit it was held against, where there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub value: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub limit: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unit: Option<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Assessment {
    pub verdict: Verdict,
    pub reasons: Vec<Reason>,
    pub black_threads: Vec<BlackThread>,
    pub lc_mm: f64,
    pub circumference_mm: f64,
    pub arc_rule: ArcRule,
    /// The buttress arc limit in mm (25% of the circumference); None for round threads.
    pub arc_limit_mm: Option<f64>,
    /// Per thread with crests within Lc, the crest arcs within Lc the views showed
    /// ([`CrestBin::seen`]), where some crest within Lc was not seen; absent when every one was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seen_crest_arcs: Option<Vec<ThreadArcs>>,
}

/// Arcs [from, to] in degrees of one thread.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadArcs {
    pub index: u32,
    pub arcs_deg: Vec<[f64; 2]>,
}

impl Assessment {
    pub fn messages(&self) -> Vec<String> {
        self.reasons.iter().map(|r| r.message.clone()).collect()
    }
}

/// Merges overlapping or touching intervals.
pub fn union_arcs(mut arcs: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    arcs.retain(|a| a[1] > a[0]);
    arcs.sort_by(|a, b| a[0].total_cmp(&b[0]));
    let mut merged: Vec<[f64; 2]> = Vec::with_capacity(arcs.len());
    for arc in arcs {
        match merged.last_mut() {
            Some(last) if arc[0] <= last[1] + 1e-9 => last[1] = last[1].max(arc[1]),
            _ => merged.push(arc),
        }
    }
    merged
}

/// The parts of `arcs` that lie within `within` (both lists of [from, to] in degrees).
pub fn intersect_arcs(arcs: &[[f64; 2]], within: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let within = union_arcs(within.to_vec());
    let pieces = arcs.iter().flat_map(|a| within.iter().map(move |w| [a[0].max(w[0]), a[1].min(w[1])])).collect();
    union_arcs(pieces)
}

/// Degrees the arcs span (arcs as [`union_arcs`] leaves them: not overlapping).
pub fn arcs_deg(arcs: &[[f64; 2]]) -> f64 {
    arcs.iter().map(|a| a[1] - a[0]).sum()
}

pub fn arc_length_mm(arcs: &[[f64; 2]], circumference_mm: f64) -> f64 {
    arcs_deg(arcs) / 360.0 * circumference_mm
}

/// The arcs [from, to] that `arc` picks out of one thread's bins (None: none of the bin), within
/// Lc: the part beyond Lc is cut off by interpolating the crest z across the bin.
fn arcs_within_lc(bins: &[CrestBin], lc_mm: f64, arc: impl Fn(&CrestBin) -> Option<[f64; 2]>) -> Vec<[f64; 2]> {
    let mut arcs = Vec::new();
    for (k, bin) in bins.iter().enumerate() {
        let Some([from, to]) = arc(bin) else { continue };
        // z grows linearly along the helix: estimate dz/dθ from the neighbours.
        let dz_per_deg = neighbour_slope(bins, k);
        let z_from = bin.z_mm + dz_per_deg * (from - (bin.angle_deg + bin.width_deg / 2.0));
        if z_from > lc_mm {
            continue;
        }
        let to = if dz_per_deg > 0.0 { to.min(from + (lc_mm - z_from) / dz_per_deg) } else { to };
        arcs.push([from, to]);
    }
    arcs
}

/// Black arcs of one thread from its geometry: the parts of bins within Lc whose crest is on the
/// mill surface.
fn geometric_arcs(bins: &[CrestBin], lc_mm: f64) -> Vec<[f64; 2]> {
    arcs_within_lc(bins, lc_mm, |b| (!b.chamfer && b.on_mill_surface).then(|| b.mill_arc_deg.unwrap_or(b.span_deg())))
}

fn neighbour_slope(bins: &[CrestBin], k: usize) -> f64 {
    let (a, b) = match (k.checked_sub(1), bins.get(k + 1)) {
        (_, Some(_)) => (k, k + 1),
        (Some(prev), None) => (prev, k),
        (None, None) => return 0.0,
    };
    let dtheta = bins[b].angle_deg - bins[a].angle_deg;
    if dtheta.abs() < 1e-12 { 0.0 } else { (bins[b].z_mm - bins[a].z_mm) / dtheta }
}

fn count_word(n: usize) -> String {
    match n {
        0 => "no".into(),
        1 => "one".into(),
        2 => "two".into(),
        3 => "three".into(),
        _ => n.to_string(),
    }
}

fn lengths_text(threads: &[&BlackThread]) -> String {
    let parts: Vec<String> = threads.iter().map(|t| format!("{:.1} mm", t.length_mm)).collect();
    match parts.len() {
        0 => String::new(),
        1 => parts[0].clone(),
        _ => format!("{} and {}", parts[..parts.len() - 1].join(", "), parts[parts.len() - 1]),
    }
}

/// Applies the acceptance rules.
pub fn assess(input: &RuleInput, arc_rule: ArcRule) -> Assessment {
    let mut black_threads = Vec::new();
    for thread in &input.threads {
        let photometric = union_arcs(thread.black_crest_arcs_deg.clone());
        let geometric = union_arcs(geometric_arcs(&thread.bins, input.lc_mm));
        let evidence = match (photometric.is_empty(), geometric.is_empty()) {
            (true, true) => continue,
            (false, true) => BlackCrestEvidence::Photometric,
            (true, false) => BlackCrestEvidence::Geometric,
            (false, false) => BlackCrestEvidence::Both,
        };
        let arcs = union_arcs(photometric.into_iter().chain(geometric).collect());
        let length_mm = arc_length_mm(&arcs, input.circumference_mm);
        black_threads.push(BlackThread { index: thread.index, arcs_deg: arcs, length_mm, evidence });
    }

    let lc = input.lc_mm;
    let circ = input.circumference_mm;
    let mut reasons = Vec::new();
    for t in black_threads.iter().filter(|t| t.evidence == BlackCrestEvidence::Geometric) {
        reasons.push(Reason {
            code: ReasonCode::PolishedBlackCrest,
            message: format!(
                "thread {}: crest on the mill surface, below the machined crest cone, over {:.1} mm within Lc \
                 with a machined look: a black crest polished or finished to look full",
                t.index, t.length_mm
            ),
            threads: vec![t.index],
            value: Some(t.length_mm),
            limit: None,
            unit: Some("mm".into()),
        });
    }
    let all: Vec<&BlackThread> = black_threads.iter().collect();
    let indices: Vec<u32> = all.iter().map(|t| t.index).collect();

    let (verdict, arc_limit_mm) = match input.family {
        Family::Round => {
            if all.is_empty() {
                reasons.push(Reason {
                    code: ReasonCode::NoBlackCrestWithinLc,
                    message: format!("Lc {lc:.1} mm; no black-crested thread within Lc; accept"),
                    threads: vec![],
                    value: Some(0.0),
                    limit: Some(0.0),
                    unit: Some("mm".into()),
                });
                (Verdict::Accept, None)
            } else {
                for t in &all {
                    reasons.push(Reason {
                        code: ReasonCode::RoundBlackCrestWithinLc,
                        message: format!(
                            "Lc {lc:.1} mm; round thread {} black-crested within Lc over {:.1} mm ({}); \
                             round threads allow none; reject",
                            t.index,
                            t.length_mm,
                            arcs_text(&t.arcs_deg)
                        ),
                        threads: vec![t.index],
                        value: Some(t.length_mm),
                        limit: Some(0.0),
                        unit: Some("mm".into()),
                    });
                }
                (Verdict::Reject, None)
            }
        }
        Family::Buttress => {
            let limit = BUTTRESS_ARC_LIMIT * circ;
            let head = format!(
                "Lc {lc:.1} mm; {} black-crested thread{} within Lc{}{}; circumference {circ:.1} mm, 25% = {limit:.1} mm",
                count_word(all.len()),
                if all.len() == 1 { "" } else { "s" },
                if all.is_empty() { "" } else { ", " },
                lengths_text(&all)
            );
            let mut failed = false;
            if all.len() > BUTTRESS_MAX_BLACK_THREADS {
                failed = true;
                reasons.push(Reason {
                    code: ReasonCode::ButtressTooManyBlackThreads,
                    message: format!("{head}; more than {BUTTRESS_MAX_BLACK_THREADS} threads; reject"),
                    threads: indices.clone(),
                    value: Some(all.len() as f64),
                    limit: Some(BUTTRESS_MAX_BLACK_THREADS as f64),
                    unit: Some("threads".into()),
                });
            }
            match arc_rule {
                ArcRule::PerThread => {
                    for t in all.iter().filter(|t| t.length_mm > limit) {
                        failed = true;
                        reasons.push(Reason {
                            code: ReasonCode::ButtressArcOverLimit,
                            message: format!(
                                "{head}; thread {} black crest {:.1} mm exceeds 25% of the circumference; reject",
                                t.index, t.length_mm
                            ),
                            threads: vec![t.index],
                            value: Some(t.length_mm),
                            limit: Some(limit),
                            unit: Some("mm".into()),
                        });
                    }
                }
                ArcRule::Combined => {
                    let total: f64 = all.iter().map(|t| t.length_mm).sum();
                    if total > limit {
                        failed = true;
                        reasons.push(Reason {
                            code: ReasonCode::ButtressCombinedArcOverLimit,
                            message: format!(
                                "{head}; combined black crest {total:.1} mm exceeds 25% of the circumference; reject"
                            ),
                            threads: indices.clone(),
                            value: Some(total),
                            limit: Some(limit),
                            unit: Some("mm".into()),
                        });
                    }
                }
            }
            if !failed {
                let longest = all.iter().map(|t| t.length_mm).fold(0.0, f64::max);
                let total: f64 = all.iter().map(|t| t.length_mm).sum();
                reasons.push(Reason {
                    code: if all.is_empty() {
                        ReasonCode::NoBlackCrestWithinLc
                    } else {
                        ReasonCode::ButtressBlackCrestsWithinLimits
                    },
                    message: format!("{head}; accept"),
                    threads: indices,
                    value: Some(if arc_rule == ArcRule::Combined { total } else { longest }),
                    limit: Some(limit),
                    unit: Some("mm".into()),
                });
            }
            (if failed { Verdict::Reject } else { Verdict::Accept }, Some(limit))
        }
    };

    // Last, after the verdict's own reason: it qualifies the verdict, it does not decide it.
    let crests: Vec<(ThreadArcs, f64)> = input
        .threads
        .iter()
        .map(|t| {
            let seen = union_arcs(arcs_within_lc(&t.bins, lc, |b| b.seen.then(|| b.span_deg())));
            (
                ThreadArcs { index: t.index, arcs_deg: seen },
                arcs_deg(&arcs_within_lc(&t.bins, lc, |b| Some(b.span_deg()))),
            )
        })
        .filter(|(_, within_deg)| *within_deg > 0.0)
        .collect();
    let seen_deg: f64 = crests.iter().map(|(t, _)| arcs_deg(&t.arcs_deg)).sum();
    let within_deg: f64 = crests.iter().map(|(_, d)| d).sum();
    let partial = seen_deg < within_deg - 1e-6;
    if partial {
        let seen_threads: Vec<&ThreadArcs> = crests.iter().map(|(t, _)| t).filter(|t| !t.arcs_deg.is_empty()).collect();
        reasons.push(Reason {
            code: ReasonCode::PartialCoverage,
            message: if seen_threads.is_empty() {
                "the views showed none of the thread crests within Lc: nothing within Lc was inspected".into()
            } else {
                format!(
                    "the views showed {seen_deg:.0}° of the {within_deg:.0}° of thread crest within Lc ({}): the \
                     verdict holds for the crests seen",
                    seen_threads
                        .iter()
                        .map(|t| format!("thread {} {}", t.index, arcs_text(&t.arcs_deg)))
                        .collect::<Vec<_>>()
                        .join("; ")
                )
            },
            threads: seen_threads.iter().map(|t| t.index).collect(),
            value: Some(seen_deg),
            limit: Some(within_deg),
            unit: Some("deg".into()),
        });
    }
    Assessment {
        verdict,
        reasons,
        black_threads,
        lc_mm: lc,
        circumference_mm: circ,
        arc_rule,
        arc_limit_mm,
        seen_crest_arcs: partial.then(|| crests.into_iter().map(|(t, _)| t).collect()),
    }
}

fn arcs_text(arcs: &[[f64; 2]]) -> String {
    arcs.iter().map(|a| format!("{:.1}°–{:.1}°", a[0], a[1])).collect::<Vec<_>>().join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    const SEED_CIRC: f64 = 358.9;

    fn arc_of(length_mm: f64, start_deg: f64, circ: f64) -> [f64; 2] {
        [start_deg, start_deg + length_mm / circ * 360.0]
    }

    fn buttress(threads: Vec<ThreadObservation>) -> RuleInput {
        RuleInput {
            family: Family::Buttress,
            lc_mm: 35.8,
            circumference_mm: SEED_CIRC,
            nominal_height_mm: 1.000,
            height_tolerance_mm: 0.030,
            threads,
        }
    }

    fn dark(index: u32, length_mm: f64) -> ThreadObservation {
        ThreadObservation { index, black_crest_arcs_deg: vec![arc_of(length_mm, 40.0, SEED_CIRC)], bins: vec![] }
    }

    /// Full machined bins everywhere except `low` (start, end) degrees, where the height is `height`
    /// and the crest is on the mill surface.
    fn bins(z0: f64, pitch: f64, low: (usize, usize), height: f64, chamfer: bool) -> Vec<CrestBin> {
        (0..360)
            .map(|k| {
                let is_low = (low.0..low.1).contains(&k);
                CrestBin {
                    angle_deg: k as f64,
                    width_deg: 1.0,
                    z_mm: z0 + pitch * (k as f64 + 0.5) / 360.0,
                    height_mm: Some(if is_low { height } else { 1.0 }),
                    chamfer: chamfer && is_low,
                    on_mill_surface: is_low,
                    mill_arc_deg: None,
                    seen: true,
                }
            })
            .collect()
    }

    #[test]
    fn seed_example_accepts_and_quotes_the_numbers() {
        let input = buttress(vec![dark(6, 22.3), dark(7, 40.5)]);
        let a = assess(&input, ArcRule::PerThread);
        assert_eq!(a.verdict, Verdict::Accept);
        assert_eq!(
            a.reasons[0].message,
            "Lc 35.8 mm; two black-crested threads within Lc, 22.3 mm and 40.5 mm; circumference 358.9 mm, \
             25% = 89.7 mm; accept"
        );
        assert_eq!(a.reasons[0].code, ReasonCode::ButtressBlackCrestsWithinLimits);
        assert!((a.arc_limit_mm.unwrap() - 89.725).abs() < 1e-9);
        assert_eq!(a.black_threads.len(), 2);
        assert!((a.black_threads[1].length_mm - 40.5).abs() < 1e-9);
    }

    #[test]
    fn three_black_threads_reject() {
        let a = assess(&buttress(vec![dark(5, 5.0), dark(6, 10.0), dark(7, 12.0)]), ArcRule::PerThread);
        assert_eq!(a.verdict, Verdict::Reject);
        let r = a.reasons.iter().find(|r| r.code == ReasonCode::ButtressTooManyBlackThreads).unwrap();
        assert_eq!(r.threads, vec![5, 6, 7]);
        assert_eq!(r.value, Some(3.0));
        assert_eq!(r.limit, Some(2.0));
    }

    #[test]
    fn one_thread_over_a_quarter_rejects() {
        let a = assess(&buttress(vec![dark(7, 95.0)]), ArcRule::PerThread);
        assert_eq!(a.verdict, Verdict::Reject);
        let r = a.reasons.iter().find(|r| r.code == ReasonCode::ButtressArcOverLimit).unwrap();
        assert_eq!(r.threads, vec![7]);
        assert!((r.value.unwrap() - 95.0).abs() < 1e-9);
        assert!((r.limit.unwrap() - 89.725).abs() < 1e-9);
        assert!(r.message.contains("95.0 mm exceeds 25%"), "{}", r.message);
    }

    #[test]
    fn combined_rule_flips_the_verdict() {
        let input = buttress(vec![dark(6, 50.0), dark(7, 60.0)]);
        assert_eq!(assess(&input, ArcRule::PerThread).verdict, Verdict::Accept);
        let combined = assess(&input, ArcRule::Combined);
        assert_eq!(combined.verdict, Verdict::Reject);
        let r = &combined.reasons[0];
        assert_eq!(r.code, ReasonCode::ButtressCombinedArcOverLimit);
        assert!((r.value.unwrap() - 110.0).abs() < 1e-9);
    }

    #[test]
    fn crests_within_lc_no_view_showed_are_said_after_the_verdict_and_do_not_change_it() {
        // Thread 2's crest runs from z 5.08 to 10.16 mm; Lc 35.8 takes all of it.
        let mut thread =
            ThreadObservation { index: 2, black_crest_arcs_deg: vec![], bins: bins(5.08, 5.08, (0, 0), 1.0, false) };
        let mut input = buttress(vec![dark(6, 50.0), thread.clone()]);
        let whole = assess(&input, ArcRule::PerThread);
        assert!(whole.seen_crest_arcs.is_none());
        assert!(whole.reasons.iter().all(|r| r.code != ReasonCode::PartialCoverage));
        // 40° of its crest seen, across 0°.
        for b in thread.bins.iter_mut() {
            b.seen = b.angle_deg >= 350.0 || b.angle_deg < 30.0;
        }
        input.threads[1] = thread.clone();
        let partial = assess(&input, ArcRule::PerThread);
        assert_eq!(partial.verdict, whole.verdict);
        assert_eq!(partial.black_threads, whole.black_threads);
        assert_eq!(partial.reasons[..whole.reasons.len()], whole.reasons[..]);
        let last = partial.reasons.last().unwrap();
        assert_eq!(last.code, ReasonCode::PartialCoverage);
        assert_eq!(last.threads, vec![2]);
        assert_eq!((last.unit.as_deref(), last.limit), (Some("deg"), Some(360.0)));
        assert!((last.value.unwrap() - 40.0).abs() < 1e-9, "{last:?}");
        assert!(last.message.contains("40° of the 360°"), "{}", last.message);
        let seen = partial.seen_crest_arcs.clone().unwrap();
        assert_eq!(seen, vec![ThreadArcs { index: 2, arcs_deg: vec![[0.0, 30.0], [350.0, 360.0]] }]);
        // Crests beyond Lc are not asked for: with Lc at z 7.62 mm (the crest's middle) only the
        // first half of the turn counts, of which 30° were seen.
        input.lc_mm = 7.62;
        let half = assess(&input, ArcRule::PerThread);
        let last = half.reasons.last().unwrap();
        assert!((last.value.unwrap() - 30.0).abs() < 1e-9 && (last.limit.unwrap() - 180.0).abs() < 1e-6, "{last:?}");
        input.lc_mm = 35.8;
        // No crest seen at all says so in words.
        thread.bins.iter_mut().for_each(|b| b.seen = false);
        input.threads[1] = thread;
        let none = assess(&input, ArcRule::PerThread);
        let last = none.reasons.last().unwrap();
        assert_eq!((last.code, last.value), (ReasonCode::PartialCoverage, Some(0.0)));
        assert!(last.message.contains("none of the thread crests"), "{}", last.message);
        // A reject stays a reject: what was seen already fails.
        input.threads[0] = dark(6, 100.0);
        assert_eq!(assess(&input, ArcRule::PerThread).verdict, Verdict::Reject);
    }

    #[test]
    fn arcs_intersect_piecewise() {
        let within = [[350.0, 360.0], [0.0, 20.0], [15.0, 30.0]];
        assert_eq!(intersect_arcs(&[[0.0, 22.96]], &within), vec![[0.0, 22.96]]);
        assert_eq!(intersect_arcs(&[[354.41, 360.0], [25.0, 40.0]], &within), vec![[25.0, 30.0], [354.41, 360.0]]);
        assert!(intersect_arcs(&[[100.0, 200.0]], &within).is_empty());
    }

    #[test]
    fn round_thread_with_any_black_crest_within_lc_rejects() {
        let input = RuleInput {
            family: Family::Round,
            lc_mm: 47.6,
            circumference_mm: 359.08,
            nominal_height_mm: 1.81,
            height_tolerance_mm: 0.051,
            threads: vec![ThreadObservation { index: 14, black_crest_arcs_deg: vec![[200.0, 200.5]], bins: vec![] }],
        };
        let a = assess(&input, ArcRule::PerThread);
        assert_eq!(a.verdict, Verdict::Reject);
        assert_eq!(a.reasons[0].code, ReasonCode::RoundBlackCrestWithinLc);
        assert_eq!(a.reasons[0].threads, vec![14]);
        assert!(a.reasons[0].message.contains("0.5 mm"), "{}", a.reasons[0].message);
    }

    #[test]
    fn black_crests_only_beyond_lc_accept() {
        // Thread whose crest z runs from 36 to 41 mm, beyond Lc 35.8: low heights there are imperfect
        // threads, not black crests within Lc; photometric arcs arrive already clipped (none left).
        let mut t =
            ThreadObservation { index: 8, black_crest_arcs_deg: vec![], bins: bins(36.0, 5.08, (0, 360), 0.6, false) };
        let a = assess(&buttress(vec![t.clone()]), ArcRule::PerThread);
        assert_eq!(a.verdict, Verdict::Accept);
        assert_eq!(a.reasons[0].code, ReasonCode::NoBlackCrestWithinLc);
        // Same for round threads.
        let mut round = buttress(vec![t.clone()]);
        round.family = Family::Round;
        assert_eq!(assess(&round, ArcRule::PerThread).verdict, Verdict::Accept);
        // Moving the same thread inside Lc makes it black.
        t.bins = bins(20.0, 5.08, (0, 360), 0.6, false);
        round.threads = vec![t];
        assert_eq!(assess(&round, ArcRule::PerThread).verdict, Verdict::Reject);
    }

    #[test]
    fn polished_crest_is_black_by_its_geometry() {
        // Bright crest (no photometric arc) on the mill surface over 30°.
        let t = ThreadObservation {
            index: 4,
            black_crest_arcs_deg: vec![],
            bins: bins(18.0, 5.08, (100, 130), 0.95, false),
        };
        let mut input = buttress(vec![t]);
        input.family = Family::Round;
        let a = assess(&input, ArcRule::PerThread);
        assert_eq!(a.verdict, Verdict::Reject);
        assert_eq!(a.black_threads[0].evidence, BlackCrestEvidence::Geometric);
        assert_eq!(a.black_threads[0].arcs_deg, vec![[100.0, 130.0]]);
        assert!(a.reasons.iter().any(|r| r.code == ReasonCode::PolishedBlackCrest));
        // A shallow thread whose crest is machined (a vanishing thread: its root rises) is not black.
        let mut shallow = bins(18.0, 5.08, (100, 130), 0.45, false);
        shallow.iter_mut().for_each(|b| b.on_mill_surface = false);
        input.threads = vec![ThreadObservation { index: 4, black_crest_arcs_deg: vec![], bins: shallow }];
        assert_eq!(assess(&input, ArcRule::PerThread).verdict, Verdict::Accept);
    }

    #[test]
    fn a_partly_covered_mill_bin_counts_by_its_mill_arc_cut_at_lc() {
        // Bins 100–129 on the mill surface, the fitted ends inside the first and last: 100.6° and
        // 129.3°. The crest line reaches Lc at 120° (z = 18 + 5.08·120/360).
        let mut b = bins(18.0, 5.08, (100, 130), 0.95, false);
        b[100].mill_arc_deg = Some([100.6, 101.0]);
        b[129].mill_arc_deg = Some([129.0, 129.3]);
        let mut input = buttress(vec![ThreadObservation { index: 4, black_crest_arcs_deg: vec![], bins: b }]);
        let black = |input: &RuleInput| assess(input, ArcRule::PerThread).black_threads[0].arcs_deg.clone();
        let arcs = black(&input);
        assert_eq!(arcs.len(), 1);
        assert!((arcs[0][0] - 100.6).abs() < 1e-9 && (arcs[0][1] - 129.3).abs() < 1e-9, "{arcs:?}");
        input.lc_mm = 18.0 + 5.08 * 120.0 / 360.0;
        let arcs = black(&input);
        assert!((arcs[0][0] - 100.6).abs() < 1e-9 && (arcs[0][1] - 120.0).abs() < 1e-9, "{arcs:?}");
    }

    #[test]
    fn chamfered_crest_is_not_black() {
        let t = ThreadObservation { index: 1, black_crest_arcs_deg: vec![], bins: bins(0.5, 5.08, (0, 90), 0.3, true) };
        let mut input = buttress(vec![t]);
        input.family = Family::Round;
        assert_eq!(assess(&input, ArcRule::PerThread).verdict, Verdict::Accept);
    }

    #[test]
    fn geometric_arc_is_clipped_at_lc() {
        // Crest z crosses Lc = 35.8 at θ = (35.8 − 33.0) / 5.08 · 360 = 198.4°.
        let t = ThreadObservation {
            index: 7,
            black_crest_arcs_deg: vec![],
            bins: bins(33.0, 5.08, (150, 260), 0.5, false),
        };
        let a = assess(&buttress(vec![t]), ArcRule::PerThread);
        let arc = a.black_threads[0].arcs_deg[0];
        assert_eq!(arc[0], 150.0);
        assert!((arc[1] - (35.8 - 33.0) / 5.08 * 360.0).abs() < 1e-6, "{arc:?}");
    }

    #[test]
    fn photometric_and_geometric_arcs_merge() {
        let t = ThreadObservation {
            index: 3,
            black_crest_arcs_deg: vec![[10.0, 25.5], [24.0, 30.0]],
            bins: bins(10.0, 5.08, (28, 40), 0.5, false),
        };
        let a = assess(&buttress(vec![t]), ArcRule::PerThread);
        assert_eq!(a.black_threads[0].arcs_deg, vec![[10.0, 40.0]]);
        assert_eq!(a.black_threads[0].evidence, BlackCrestEvidence::Both);
        assert!((a.black_threads[0].length_mm - 30.0 / 360.0 * SEED_CIRC).abs() < 1e-9);
    }
}
