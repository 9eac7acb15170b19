use super::truth::*;
use super::*;

#[test]
fn suites_name_existing_presets_and_share_no_case() {
    for suite in [Suite::Accuracy, Suite::Holdout, Suite::Tuning] {
        for case in suite.cases() {
            assert!(crate::sim::preset(case.preset).is_some(), "{}", case.name());
        }
    }
    for a in ACCURACY_SUITE {
        assert!(HOLDOUT_SUITE.iter().all(|h| h.name() != a.name()), "{}", a.name());
    }
    for t in TUNING_SUITE {
        let name = t.name();
        assert!(HOLDOUT_SUITE.iter().chain(ACCURACY_SUITE).all(|h| h.name() != name), "{name} tunes and is held out");
    }
    let mut names: Vec<String> = HOLDOUT_SUITE.iter().chain(TUNING_SUITE).map(Case::name).collect();
    names.sort();
    names.dedup();
    assert_eq!(names.len(), HOLDOUT_SUITE.len() + TUNING_SUITE.len());
}

fn result(preset: &str, height_max_um: f64, inspect_over_decode: f64) -> CaseResult {
    CaseResult {
        preset: preset.into(),
        seed: 1,
        station_seed: None,
        station: None,
        sector_deg: None,
        verdict: crate::domain::rules::Verdict::Accept,
        truth_verdict: crate::domain::rules::Verdict::Accept,
        quality: crate::pipeline::quality::QualityStatus::Ok,
        quality_codes: Vec::new(),
        pairs_expected: 45,
        pairs_measured: 45,
        accuracy: Accuracy {
            bins_compared: 100,
            bins_missing: 0,
            height_rms_um: 2.0,
            height_max_um,
            height_bias_um: 0.0,
            black_crest_length_max_error_mm: 0.5,
            seen_crest_deg: None,
            verdict_agrees: true,
            worst: Vec::new(),
            uncertainty_coverage: None,
            uncertainty_ratio_p95: None,
            uncertainty_effective_bins: None,
            uncertainty_coverage_interval: None,
            coverage_by_method_px: Vec::new(),
            decision: None,
            decision_wrong: false,
            review_required: false,
        },
        depth_rms_um: 0.0,
        depth_median_um: 0.0,
        depth_coverage: 1.0,
        report: None,
        registration: RegistrationError {
            angle_rms_deg: 0.01,
            angle_max_deg: 0.02,
            axial_rms_um: 3.0,
            axial_max_um: 6.0,
            radial_rms_um: 1.0,
            encoder_angle_rms_deg: 0.6,
            encoder_axial_rms_um: 180.0,
            pair_arc_rms_um: 1.5,
            pair_axial_rms_um: 1.2,
            pairs_measured: 45,
        },
        decode_seconds: 1.0,
        inspect_seconds: inspect_over_decode,
        render: crate::sim::SimSummary {
            files: 1,
            bytes: 1,
            frames: 1,
            seconds: 1.0,
            verdict: crate::domain::rules::Verdict::Accept,
        },
        stage_seconds: Vec::new(),
        table1: Vec::new(),
        helix_z_error_um: 0.0,
        encoder_mean_axial_offset_um: 0.0,
        black_crests: Vec::new(),
    }
}

fn check(results: &[CaseResult], target: &str) -> Option<TargetCheck> {
    targets(results).into_iter().find(|c| c.target.starts_with(target))
}

#[test]
fn targets_name_the_worst_case_and_whether_it_is_met() {
    let standard = result("standard", 7.2, 4.4);
    let mut round = result("lc-round-black", 20.3, 4.0);
    let both = [standard.clone(), round.clone()];
    let max = check(&both, "per-thread height max").unwrap();
    assert!(max.met);
    assert_eq!(max.worst, "20.3 µm, lc-round-black seed 1");
    let speed = check(&both, "standard inspection").unwrap();
    assert!(!speed.met);
    assert_eq!(speed.worst, "4.40×, standard seed 1");
    assert!(check(&both, "verdicts agree").unwrap().met);
    // No Table 1 case, no Table 1 target; no standard case, no speed target.
    assert!(check(&both, "Table 1").is_none());
    assert!(check(&both[1..], "standard inspection").is_none());

    // Limits are inclusive; just past one, the target is not met.
    round.registration.axial_rms_um = 5.0;
    assert!(check(std::slice::from_ref(&round), "registration ≤ 5 µm (RMS").unwrap().met);
    // Its worst view (6 µm) is over: read per view, the target is not met.
    let every_view = check(std::slice::from_ref(&round), "registration ≤ 5 µm (every").unwrap();
    assert_eq!((every_view.met, every_view.worst.as_str()), (false, "6.0 µm, lc-round-black seed 1"));
    round.registration.axial_rms_um = 5.01;
    round.accuracy.height_max_um = 25.1;
    round.accuracy.verdict_agrees = false;
    let both = [standard.clone(), round.clone()];
    assert!(!check(&both, "registration ≤ 5 µm (RMS").unwrap().met);
    assert!(!check(&both, "per-thread height max").unwrap().met);
    let verdicts = check(&both, "verdicts agree").unwrap();
    assert_eq!((verdicts.met, verdicts.worst.as_str()), (false, "1 of 2"));

    let mut table1 = result("seed-table1", 10.8, 5.9);
    table1.table1 = vec![(2, 0.9884, 0.9823), (10, 0.4263, 0.4207)];
    let t = check(std::slice::from_ref(&table1), "Table 1").unwrap();
    assert_eq!((t.met, t.worst.as_str()), (true, "6.1 µm, thread 2"));
    table1.table1.push((6, 0.9370, 0.9479));
    let t = check(std::slice::from_ref(&table1), "Table 1").unwrap();
    assert_eq!((t.met, t.worst.as_str()), (false, "10.9 µm, thread 6"));
}

#[test]
fn pair_errors_are_read_against_the_true_corrections_difference() {
    use crate::domain::optics::ViewPose;
    let pose = |angle_deg: f64, axial_mm: f64| ViewPose { angle_deg, axial_mm, lens_radius_mm: 270.0 };
    let encoder = [pose(0.0, 10.0), pose(8.0, 10.0), pose(16.0, 10.0)];
    // True corrections (truth − encoder): +0.5°, −0.3°, +0.1° and +0.10, −0.05, 0 mm.
    let truth = [pose(0.5, 10.1), pose(7.7, 9.95), pose(16.1, 10.0)];
    let pair = |a: usize, b: usize, angle_error_deg: f64, axial_error_mm: f64| crate::pipeline::register::PairMeasure {
        a,
        b,
        shift_angle_deg: (truth[b].angle_deg - encoder[b].angle_deg) - (truth[a].angle_deg - encoder[a].angle_deg)
            + angle_error_deg,
        shift_axial_mm: (truth[b].axial_mm - encoder[b].axial_mm) - (truth[a].axial_mm - encoder[a].axial_mm)
            + axial_error_mm,
        shift_radius_mm: 0.0,
        peak_ncc: 0.5,
        rival_ratio: 0.0,
        overlap_cells: 5000,
        residual_angle_deg: 0.0,
        residual_axial_um: 0.0,
        residual_radius_um: 0.0,
    };
    let radius_mm = 57.15;
    // Exact pairs: no error. Errors of 3 µm of arc and 4 µm axially on one pair of two.
    let exact = [pair(0, 1, 0.0, 0.0), pair(1, 2, 0.0, 0.0)];
    let e = registration_error(&encoder, &truth, &truth, &exact, radius_mm);
    assert!(e.pair_arc_rms_um < 1e-9 && e.pair_axial_rms_um < 1e-9, "{e:?}");
    assert_eq!(e.pairs_measured, 2);
    let arc_deg = (0.003 / radius_mm).to_degrees();
    let off = [pair(0, 1, arc_deg, 0.004), pair(1, 2, 0.0, 0.0)];
    let e = registration_error(&encoder, &truth, &truth, &off, radius_mm);
    assert!((e.pair_arc_rms_um - 3.0 / 2f64.sqrt()).abs() < 1e-6, "{e:?}");
    assert!((e.pair_axial_rms_um - 4.0 / 2f64.sqrt()).abs() < 1e-6, "{e:?}");
    // No pairs: nothing to read.
    assert!(registration_error(&encoder, &truth, &truth, &[], radius_mm).pair_arc_rms_um.is_nan());
}

#[test]
fn only_picks_a_preset_or_one_seed_of_it() {
    let case = Case::at("bc-polished", 3);
    assert!(case.matches("bc-polished"));
    assert!(case.matches("bc-polished-3"));
    assert!(!case.matches("bc-polished-30"));
    assert!(!case.matches("bc-black-2"));
    assert!(!Case::at("bc-black-2", 1).matches("bc-black"));
}

#[test]
fn station_suites_share_no_seed() {
    let seeds = |suite: Suite| suite.cases().iter().map(|c| c.seed).collect::<std::collections::BTreeSet<u64>>();
    let (tuning, bench, check) = (seeds(Suite::StationsTuning), seeds(Suite::Stations), seeds(Suite::StationsCheck));
    assert!(tuning.is_disjoint(&bench) && tuning.is_disjoint(&check) && bench.is_disjoint(&check));
    assert_eq!((tuning.len(), bench.len(), check.len()), (12, 40, 30));
}

#[test]
fn the_station_table_reads_each_coverage_on_its_independent_bins() {
    let at_station = |coverage: f64, effective: f64| {
        let mut r = result("standard", 7.0, 4.0);
        r.station = Some(crate::domain::station::Station {
            projection: crate::domain::optics::Projection::Perspective,
            object_pixel_mm: 0.08,
            depth_of_field_mm: 0.3,
            frame_step_mm: 0.2,
            frame_step_dof: 0.67,
            frames_per_view: 20,
            views: 12,
            axial_rows: 1,
            view_spacing_deg: Some(30.0),
            overlap_deg: Some(4.0),
            frame_noise_percent: None,
            class: None,
            qualified_by: None,
        });
        r.accuracy.uncertainty_coverage = Some(coverage);
        r.accuracy.uncertainty_ratio_p95 = Some(0.8);
        r.accuracy.uncertainty_effective_bins = Some(effective);
        let (lo, hi) = crate::numeric::calibration::share_interval(
            (coverage * effective).round() as usize,
            effective as usize,
            0.95,
        );
        r.accuracy.uncertainty_coverage_interval = Some([lo, hi]);
        r
    };
    // All of 10 independent errors covered reads 100% yet meets the band; 20 of 40 is below it;
    // 990 of 1000 meets it without holding 95%.
    let rows = [at_station(1.0, 10.0), at_station(0.5, 40.0), at_station(0.99, 1000.0)];
    let table = super::table::station_table(&rows, &[]);
    let medium = table.lines().find(|l| l.starts_with("| medium |")).unwrap();
    assert!(medium.contains("| 1 / 1 / 1 |"), "{medium}");
    assert!(medium.contains("| 2 / 0 / 1 (1) |"), "{medium}");
    // Over the class's 1050 independent bins: 10 + 20 + 990 covered.
    assert!(medium.contains("(97.1% [") && medium.contains("on 1050)"), "{medium}");
    let first = table.lines().nth(2).unwrap();
    assert!(first.contains("100.0% (0.80) [69–100% on 10]"), "{first}");
}
