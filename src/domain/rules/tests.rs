use super::*;
use crate::domain::arcs::intersect_arcs;

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
    let t =
        ThreadObservation { index: 4, black_crest_arcs_deg: vec![], bins: bins(18.0, 5.08, (100, 130), 0.95, false) };
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
    let t =
        ThreadObservation { index: 7, black_crest_arcs_deg: vec![], bins: bins(33.0, 5.08, (150, 260), 0.5, false) };
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

#[test]
fn the_rule_and_verdict_names_are_serdes() {
    for (rule, name) in [ArcRule::PerThread, ArcRule::Combined].into_iter().zip(ArcRule::NAMES) {
        assert_eq!(serde_json::to_value(rule).unwrap(), name);
    }
    for verdict in Verdict::ALL {
        assert_eq!(serde_json::to_value(verdict).unwrap(), verdict.as_str());
    }
}
