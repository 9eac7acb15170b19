//! API 5B black-crest acceptance, as the project states it (docs/rules.md; the shared DOMAIN.md).
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

use crate::domain::arcs::{arc_length_mm, arcs_deg, union_arcs};
use crate::domain::thread::Family;
use serde::{Deserialize, Serialize};

/// How the buttress 25% limit applies; the public paraphrases of 5B do not settle it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ArcRule {
    #[default]
    PerThread,
    Combined,
}

impl ArcRule {
    /// The names as the API and the stored options spell them (serde's).
    pub const NAMES: [&str; 2] = ["per_thread", "combined"];
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

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Accept,
    Reject,
}

impl Verdict {
    pub const ALL: [Verdict; 2] = [Verdict::Accept, Verdict::Reject];

    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Accept => "accept",
            Verdict::Reject => "reject",
        }
    }
}

/// How a black crest was recognised.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum BlackCrestEvidence {
    /// Mill-scale appearance on the crest.
    Photometric,
    /// Only the crest height gives it away: a polished or otherwise bright black crest.
    Geometric,
    Both,
}

/// A thread with black crests within Lc.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct BlackThread {
    /// The thread's number, 1 nearest the pipe end.
    pub index: u32,
    /// Its black-crest arcs within Lc, [from, to] degrees around the pipe.
    pub arcs_deg: Vec<[f64; 2]>,
    /// Their length along the helix, mm.
    pub length_mm: f64,
    /// What showed the crests black: their brightness, their geometry (below the machined cone),
    /// or both.
    pub evidence: BlackCrestEvidence,
}

/// Stable machine codes of the reasons.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
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

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Reason {
    /// The reason's stable machine code.
    pub code: ReasonCode,
    /// The reason in words.
    pub message: String,
    /// Threads the reason is about.
    pub threads: Vec<u32>,
    /// The measured quantity and the limit it was held against, where there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub value: Option<f64>,
    /// The limit `value` was held against, in `unit`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub limit: Option<f64>,
    /// The unit of `value` and `limit` (`mm`, `deg`, `threads`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unit: Option<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Assessment {
    /// The rules' verdict (accept / reject).
    pub verdict: Verdict,
    /// Each rule's finding, with its code, threads, value and limit.
    pub reasons: Vec<Reason>,
    /// The threads with black crest within Lc.
    pub black_threads: Vec<BlackThread>,
    /// Lc, mm.
    pub lc_mm: f64,
    /// The pipe's circumference, mm.
    pub circumference_mm: f64,
    /// How a black arc is measured against the buttress limit: per thread, or along the whole
    /// helix (the submission's `arc_rule`).
    pub arc_rule: ArcRule,
    /// The buttress arc limit in mm (25% of the circumference); None for round threads.
    pub arc_limit_mm: Option<f64>,
    /// Per thread with crests within Lc, the crest arcs within Lc the views showed
    /// ([`CrestBin::seen`]), where some crest within Lc was not seen; absent when every one was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seen_crest_arcs: Option<Vec<ThreadArcs>>,
}

/// Arcs [from, to] in degrees of one thread.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadArcs {
    /// The thread's number.
    pub index: u32,
    /// Its arcs, [from, to] degrees around the pipe.
    pub arcs_deg: Vec<[f64; 2]>,
}

impl Assessment {
    pub fn messages(&self) -> Vec<String> {
        self.reasons.iter().map(|r| r.message.clone()).collect()
    }
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
    let black_threads = black_threads_within_lc(input);
    let mut reasons: Vec<Reason> =
        black_threads.iter().filter(|t| t.evidence == BlackCrestEvidence::Geometric).map(polished_reason).collect();
    let all: Vec<&BlackThread> = black_threads.iter().collect();
    let (verdict, arc_limit_mm) = match input.family {
        Family::Round => (round_verdict(input.lc_mm, &all, &mut reasons), None),
        Family::Buttress => {
            let (verdict, limit) = buttress_verdict(input, arc_rule, &all, &mut reasons);
            (verdict, Some(limit))
        }
    };
    // Last, after the verdict's own reason: it qualifies the verdict, it does not decide it.
    let seen_crest_arcs = partial_coverage(input, &mut reasons);
    Assessment {
        verdict,
        reasons,
        black_threads,
        lc_mm: input.lc_mm,
        circumference_mm: input.circumference_mm,
        arc_rule,
        arc_limit_mm,
        seen_crest_arcs,
    }
}

/// Every thread with a black crest within Lc, by the photometric arcs, the geometric ones or both.
fn black_threads_within_lc(input: &RuleInput) -> Vec<BlackThread> {
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
    black_threads
}

/// The reason a crest on the mill surface with a machined look gets: polished to look full.
fn polished_reason(t: &BlackThread) -> Reason {
    Reason {
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
    }
}

/// Round threads: any black crest within Lc rejects.
fn round_verdict(lc: f64, all: &[&BlackThread], reasons: &mut Vec<Reason>) -> Verdict {
    if all.is_empty() {
        reasons.push(Reason {
            code: ReasonCode::NoBlackCrestWithinLc,
            message: format!("Lc {lc:.1} mm; no black-crested thread within Lc; accept"),
            threads: vec![],
            value: Some(0.0),
            limit: Some(0.0),
            unit: Some("mm".into()),
        });
        Verdict::Accept
    } else {
        for t in all {
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
        Verdict::Reject
    }
}

/// Buttress threads: at most two black-crested threads within Lc, each (or together) at most 25%
/// of the circumference. The verdict and the arc limit in mm.
fn buttress_verdict(
    input: &RuleInput,
    arc_rule: ArcRule,
    all: &[&BlackThread],
    reasons: &mut Vec<Reason>,
) -> (Verdict, f64) {
    let (lc, circ) = (input.lc_mm, input.circumference_mm);
    let indices: Vec<u32> = all.iter().map(|t| t.index).collect();
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
    (if failed { Verdict::Reject } else { Verdict::Accept }, limit)
}

/// Where the views did not show every crest within Lc: the reason saying what was seen, and the
/// seen arcs per thread (None when everything within Lc was seen).
fn partial_coverage(input: &RuleInput, reasons: &mut Vec<Reason>) -> Option<Vec<ThreadArcs>> {
    let lc = input.lc_mm;
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
    partial.then(|| crests.into_iter().map(|(t, _)| t).collect())
}

fn arcs_text(arcs: &[[f64; 2]]) -> String {
    arcs.iter().map(|a| format!("{:.1}°–{:.1}°", a[0], a[1])).collect::<Vec<_>>().join(", ")
}

#[cfg(test)]
mod tests;
