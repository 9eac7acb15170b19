use super::*;
use crate::domain::rules::{self, ArcRule, RuleInput, Verdict};
use crate::domain::thread::Family;
use crate::pipeline::crest::{self, CrestOptions};
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
        model_by_thread: vec![],
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
        qualified_by: None,
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
    let form =
        ThreadForm::api_buttress(5.08, 1.575, 0.0508, 0.0625).expect("a buttress form of the tests' nominal height");
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
        station_u_mm: None,
        station_noise_mm: None,
        model_by_thread_mm: &[],
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
    let (budget, _) =
        heights(&mut threads, &scales_of(&st, &registration, &[]), Some(3.0), &failed, &UncertaintyOptions::default());
    // 3 of 9 heights 0.6 mm below the part's median (1.575): √(3 · 0.6² / 9) = 346.4 µm.
    assert!((budget.along_helix_um - 346.41).abs() < 0.01, "{budget:?}");
    let u_um = 1e3 * threads[0].bins[12].uncertainty_mm.unwrap();
    assert!(u_um > 600.0, "{u_um}");
}

/// A learned correction's term and the failed path's read the same error: a height's U takes the
/// larger. Smaller than the dispersion it changes nothing; larger, it replaces it, thread by
/// thread, and a thread without its own takes the largest.
#[test]
fn a_corrections_term_and_the_dispersion_count_once() {
    let registration = no_pairs();
    let st = station(0.04);
    let failed = depth_coverage_low();
    let run = |model: &[(u32, f64)]| {
        let mut threads = noisy(0.004);
        // Thread 2 reads 30 µm off along half its turn: a dispersion of 15 µm RMS.
        for b in threads[1].bins.iter_mut().take(180) {
            b.height_mm = b.height_mm.map(|h| h + 0.030);
        }
        let scales = Scales { model_by_thread_mm: model, ..scales_of(&st, &registration, &[]) };
        let (budget, _) = heights(&mut threads, &scales, Some(3.0), &failed, &UncertaintyOptions::default());
        let u: Vec<f64> = threads.iter().map(|t| t.bins[200].uncertainty_mm.unwrap()).collect();
        (budget, u)
    };
    let (plain, u0) = run(&[]);
    assert!(plain.model_by_thread.is_empty());
    let (small, u_small) = run(&[(1, 1e-4), (2, 1e-4), (3, 1e-4)]);
    assert_eq!(u_small, u0, "a term under the dispersion changes nothing");
    assert_eq!(small.model_by_thread.len(), 3);
    let (_, u_large) = run(&[(1, 0.2), (2, 1e-4)]);
    assert!(u_large[0] > 0.39 && u_large[0] < 0.41 + u0[0], "k · 0.2 mm and little else: {}", u_large[0]);
    assert_eq!(u_large[1], u0[1], "thread 2's own term is small");
    assert_eq!(u_large[2], u_large[0], "thread 3 takes the largest");
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
    assert!(by_thread[0].1 < 1e-9 && by_thread[1].1 < 1e-9 && (by_thread[2].1 - 200.0).abs() < 1e-6, "{by_thread:?}");
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
