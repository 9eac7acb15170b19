use crate::common::rendered;
use crestscan::bundle::{Bundle, OpenOptions};
use crestscan::domain::frame::FrameSource;
use crestscan::domain::thread::{ConnectionTable, ThreadForm};
use crestscan::pipeline::depth::{DepthOptions, depth_from_focus};
use crestscan::sim::pfm;

/// Depth errors (µm) against truth: all trusted pixels, and those on smooth surface (truth depth
/// varies < 40 µm within ±`smooth_radius_px`: crests, roots, mill surface, where no focus window
/// of that reach straddles a flank) keyed by pixel (view by view, in image order). `options`
/// gives the depth options for the bundle's form.
fn depth_errors(
    preset: &'static str,
    options: impl Fn(&ThreadForm) -> DepthOptions,
    smooth_radius_px: impl Fn(&DepthOptions) -> usize,
) -> (Vec<f64>, Vec<(usize, f64)>, f64) {
    let dir = rendered(preset);
    let bundle = Bundle::open(dir, &ConnectionTable::api5b(), OpenOptions::default()).unwrap();
    let options = options(&bundle.part.form);
    let r = smooth_radius_px(&options);
    let (mut all, mut smooth, mut pixels) = (Vec::new(), Vec::new(), 0);
    for (v, view) in bundle.views.iter().enumerate() {
        let map =
            depth_from_focus(&bundle.optics, view, &options, |k| FrameSource::read_frame(&bundle, v, k), &|| false)
                .unwrap()
                .expect("not cancelled");
        let truth_pfm = std::fs::read(dir.join(format!("truth/{}.depth.pfm", view.id))).unwrap();
        let (w, h, truth) = pfm::read(&truth_pfm).unwrap();
        assert_eq!((w, h), (map.width, map.height));
        assert_eq!(map.depth_mm.len(), w * map.rows());
        let first_pixel = pixels;
        pixels += map.depth_mm.len();
        for (i, &d) in map.depth_mm.iter().enumerate() {
            // Map row r is pixel row r · row_step.
            let (x, y) = (i % w, (i / w) * map.row_step);
            let t = truth[y * w + x];
            if !(d.is_finite() && t.is_finite()) {
                continue;
            }
            let error_um = (d - t) as f64 * 1e3;
            all.push(error_um);
            if x >= r && y >= r && x + r < w && y + r < h {
                let (mut lo, mut hi) = (f32::MAX, f32::MIN);
                for yy in y - r..=y + r {
                    for xx in x - r..=x + r {
                        lo = lo.min(truth[yy * w + xx]);
                        hi = hi.max(truth[yy * w + xx]);
                    }
                }
                if hi - lo < 0.04 {
                    smooth.push((first_pixel + i, error_um));
                }
            }
        }
    }
    let coverage = all.len() as f64 / pixels as f64;
    (all, smooth, coverage)
}

fn median_abs(errors: &[f64]) -> f64 {
    assert!(!errors.is_empty());
    let mut a: Vec<f64> = errors.iter().map(|e| e.abs()).collect();
    a.sort_by(f64::total_cmp);
    a[a.len() / 2]
}

#[test]
fn depth_from_focus_recovers_truth_depth() {
    // As the pipeline runs it: the window follows the form (buttress on ci, round on telecentric).
    for preset in ["ci", "ci-telecentric"] {
        let (all, smooth, coverage) =
            depth_errors(preset, |form| DepthOptions::default().for_form(form), |o| o.window_radius_px);
        let smooth: Vec<f64> = smooth.into_iter().map(|(_, e)| e).collect();
        let bias = smooth.iter().sum::<f64>() / smooth.len() as f64;
        eprintln!(
            "{preset}: coverage {coverage:.3}; median |error| {:.1} µm over all, {:.1} µm on {} smooth pixels (bias {bias:.1} µm)",
            median_abs(&all),
            median_abs(&smooth),
            smooth.len()
        );
        // A border of window + breathing shift (10 px on the small ci frames with the buttress window,
        // 17% of them) is left out: ci measures 0.826, the telecentric bundle 0.908.
        assert!(coverage > 0.8, "{preset}: {coverage}");
        assert!(smooth.len() > 1000, "{preset}: {} smooth pixels", smooth.len());
        // Frames are 150–250 µm apart; the peak is found to a tenth of a step. Measured at seed 7
        // (2026-12-04): median 8.7 and 8.6 µm, bias 7.1 and 1.6 µm (the flank-adjacent pixels of
        // ci's small frames pull it); the limits are the larger plus about 40%.
        assert!(median_abs(&smooth) < 12.0, "{preset}: {}", median_abs(&smooth));
        assert!(bias.abs() < 10.0, "{preset}: bias {bias}");
    }
}

#[test]
fn a_flat_crested_forms_wider_focus_window_measures_flats_with_less_noise() {
    // ci renders a buttress part: for_form widens the window there, and only there.
    let bundle = Bundle::open(rendered("ci"), &ConnectionTable::api5b(), OpenOptions::default()).unwrap();
    let defaults = DepthOptions::default();
    let wide = defaults.for_form(&bundle.part.form);
    assert!(wide.window_radius_px > defaults.window_radius_px);
    let table = ConnectionTable::api5b();
    let round = table.get("LC 5-1/2").expect("in the table").form().clone();
    assert_eq!(defaults.for_form(&round).window_radius_px, defaults.window_radius_px);
    // The same pixels for both: smooth over the wider window's reach and trusted in both maps.
    let reach = |_: &DepthOptions| wide.window_radius_px;
    let (_, narrow_smooth, _) = depth_errors("ci", |_| defaults.clone(), reach);
    let (_, wide_smooth, _) = depth_errors("ci", |_| wide.clone(), reach);
    let wide_by_pixel: std::collections::HashMap<usize, f64> = wide_smooth.into_iter().collect();
    let (narrow_errors, wide_errors): (Vec<f64>, Vec<f64>) =
        narrow_smooth.iter().filter_map(|(pixel, e)| Some((*e, *wide_by_pixel.get(pixel)?))).unzip();
    assert!(narrow_errors.len() > 100_000, "{} pixels in common", narrow_errors.len());
    let (narrow, wide) = (median_abs(&narrow_errors), median_abs(&wide_errors));
    eprintln!("ci smooth pixels trusted in both ({}), median |error|: {narrow:.2} → {wide:.2} µm", narrow_errors.len());
    assert!(wide < 0.95 * narrow, "{narrow} → {wide}");
}
