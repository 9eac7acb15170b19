//! The decision per ISO 14253-1: the black-crest rules again at both bounds of the uncertainty,
//! and each thread's height judged against nominal ± tolerance with its mean's uncertainty.

use super::{UncertaintyBudget, measurement_failed};
use crate::domain::arcs::union_arcs;
use crate::domain::rules::{self, ArcRule, RuleInput, ThreadObservation, Verdict};
use crate::domain::station::Station;
use crate::numeric::runs::run_spans;
use crate::pipeline::crest::{self, CrestOptions};
use crate::pipeline::profile::ThreadMeasure;
use crate::pipeline::quality::Quality;
use serde::{Deserialize, Serialize};

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
