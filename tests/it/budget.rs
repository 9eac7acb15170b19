//! The error budget (`crestscan budget`) on a real render: each variant replaces what it says,
//! and what the stages after the depth maps add with exact inputs is measured, not assumed.

use crate::common::{CI_SEED, ci_bundle};
use crestscan::bundle::{Bundle, OpenOptions};
use crestscan::domain::thread::ConnectionTable;
use crestscan::eval::budget::{self, BANDS, Variant};
use crestscan::pipeline::PipelineOptions;
use crestscan::pipeline::profile::Correction;
use std::sync::atomic::AtomicBool;

#[test]
fn the_budget_puts_each_stage_s_truth_in_and_measures_what_follows() {
    let dir = ci_bundle();
    let bundle = Bundle::open(dir, &ConnectionTable::api5b(), OpenOptions::default()).unwrap();
    let truth = crate::common::truth_of(dir);
    let options = PipelineOptions::default();
    let b = budget::budget("ci", &bundle, dir, &truth, &options, crestscan::learned::models(), &Variant::ALL).unwrap();
    assert_eq!(b.variants.iter().map(|v| v.variant).collect::<Vec<_>>(), Variant::ALL.to_vec());
    let of = |variant| b.variants.iter().find(|v| v.variant == variant).unwrap();

    // The pipeline's row is the plain inspection (profile MLP off) compared with truth.
    let mut plain = options.clone();
    plain.profile.correction = Correction::Off;
    let report =
        crestscan::pipeline::inspect(&bundle, &plain, &|_, _| {}, &AtomicBool::new(false)).unwrap().unwrap().report;
    let accuracy = crestscan::eval::compare(&report, &truth);
    let pipeline = of(Variant::Pipeline);
    // The first row runs the options as given: the default inspection.
    let configured =
        crestscan::pipeline::inspect(&bundle, &options, &|_, _| {}, &AtomicBool::new(false)).unwrap().unwrap().report;
    assert_eq!(of(Variant::AsConfigured).height_rms_um, crestscan::eval::compare(&configured, &truth).height_rms_um);
    assert_eq!(pipeline.height_rms_um, accuracy.height_rms_um, "seed {CI_SEED}");
    assert!(pipeline.height_rms_um > 1.0, "{pipeline:?}");

    // With the true depth maps and poses the heights are those of the later stages alone: the
    // windows read the surface within a micrometre or two, far below what depth from focus leaves.
    for variant in [Variant::TrueDepth, Variant::TrueDepthEverywhere, Variant::TrueHelix] {
        let v = of(variant);
        assert!(v.height_rms_um < 3.0 && v.height_rms_um < 0.5 * pipeline.height_rms_um, "{v:?}");
        assert!(v.surface_crest_um.abs() < 2.0 && v.surface_root_um.abs() < 2.0, "{v:?}");
        // The ci bundle is a sector: a few per cent of the ring's bins.
        assert!(v.coverage > 0.0 && v.coverage >= 0.5 * pipeline.coverage, "{v:?} against {pipeline:?}");
    }
    // Depth everywhere fills what depth from focus did not trust: coverage does not fall.
    assert!(of(Variant::TrueDepthEverywhere).coverage >= of(Variant::TrueDepth).coverage);
    // The true helix is put in as given.
    assert!(of(Variant::TrueHelix).z_h_error_um.abs() < 1e-6, "{:?}", of(Variant::TrueHelix));
    assert!(pipeline.z_h_error_um.abs() < 0.5e3 * truth.pitch_mm);

    // Per-pixel depth in bands along the view: crest and root pixels found (a band of the ci
    // bundle's narrow views may hold only one of them), each figure finite where its pixels are.
    assert_eq!(b.depth.len(), BANDS);
    assert!(b.depth.iter().map(|d| d.crest_pixels).sum::<usize>() > 1000, "{:?}", b.depth);
    assert!(b.depth.iter().map(|d| d.root_pixels).sum::<usize>() > 1000, "{:?}", b.depth);
    assert!(b.depth.iter().any(|d| d.crest_pixels > 0 && d.root_pixels > 0), "{:?}", b.depth);
    for d in &b.depth {
        assert_eq!(d.crest_um.is_finite(), d.crest_pixels > 0, "{d:?}");
        assert_eq!(d.root_um.is_finite(), d.root_pixels > 0, "{d:?}");
        if d.crest_pixels > 0 && d.root_pixels > 0 {
            assert!((d.height_um - (d.root_um - d.crest_um)).abs() < 1e-9);
            // The ci station's depth from focus is good to a few tens of micrometres per pixel.
            assert!(d.median_abs_um < 50.0, "{d:?}");
        }
        assert!(d.trusted > 0.0 && d.trusted <= 1.0, "{d:?}");
    }
    // Every thread truth has is accounted for in each variant.
    for v in &b.variants {
        assert_eq!(v.threads.len(), truth.threads.len());
        assert!(v.threads.iter().all(|t| t.bins_measured <= t.bins_true));
    }
}
