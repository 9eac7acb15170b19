//! Depth from focus against the truth depth maps of a simulated bundle: bias, median |error|, and
//! the mean error by sub-frame phase and by peak ratio, before and after phase equalisation. A
//! working tool for the notebook (docs/notebook/accuracy.md), not part of the product.
//!
//! cargo run --release --example depth_diag -- BUNDLE_DIR [OPTIONS_JSON]
mod common;

use crestscan::domain::frame::FrameError;
use crestscan::pipeline::depth::{DepthMap, depth_from_focus, equalize_sub_frame_phase, even_frame_grid};

const VIEWS: usize = 12;
const BINS: usize = 8;

fn main() {
    let (dir, bundle, options) = common::bundle_and_options();
    let optics = bundle.optics.clone();
    let depth_options = options.depth.for_form(&bundle.part.form);
    let views: Vec<_> = bundle.views.iter().take(VIEWS).collect();
    let mut maps: Vec<DepthMap> = views
        .iter()
        .enumerate()
        .map(|(v, view)| {
            depth_from_focus(
                &optics,
                view,
                &depth_options,
                |k| bundle.read_frame(v, k).map_err(|e| FrameError::of(&e)),
                &|| false,
            )
            .unwrap()
            .unwrap()
        })
        .collect();
    let truths: Vec<Vec<f32>> = views
        .iter()
        .map(|view| {
            crestscan::sim::pfm::read(&std::fs::read(dir.join(format!("truth/{}.depth.pfm", view.id))).unwrap())
                .unwrap()
                .2
        })
        .collect();
    if let Ok(path) = std::env::var("DUMP") {
        // View 0's estimated depth, raw little-endian f32, width × rows.
        let bytes: Vec<u8> = maps[0].depth_mm.iter().flat_map(|d| d.to_le_bytes()).collect();
        std::fs::write(&path, bytes).unwrap();
        let ratio: Vec<u8> = maps[0].peak_ratio.iter().flat_map(|d| d.to_le_bytes()).collect();
        std::fs::write(format!("{path}.ratio"), ratio).unwrap();
        let pixels = maps[0].all_in_focus.len() / 3;
        let aif: Vec<u8> = (0..pixels)
            .flat_map(|i| {
                let c = maps[0].colour(i);
                ((c[0] + c[1] + c[2]) / 3.0).to_le_bytes()
            })
            .collect();
        std::fs::write(format!("{path}.aif"), aif).unwrap();
        println!("dumped {}×{}", maps[0].width, maps[0].rows());
    }
    println!("raw:");
    report(&views, &maps, &truths, optics.focus_distance_mm);
    let grids: Vec<_> =
        views.iter().map(|v| even_frame_grid(&v.frames.iter().map(|f| f.offset_mm).collect::<Vec<_>>())).collect();
    equalize_sub_frame_phase(&mut maps, &grids, optics.focus_distance_mm);
    println!("equalized:");
    report(&views, &maps, &truths, optics.focus_distance_mm);
}

fn report(views: &[&crestscan::domain::frame::View], maps: &[DepthMap], truths: &[Vec<f32>], big_f: f64) {
    let (mut all, mut by_phase, mut by_ratio) = (Vec::new(), vec![Vec::new(); BINS], vec![Vec::new(); 6]);
    let (mut total, mut seen) = (0usize, 0usize);
    for ((view, map), t) in views.iter().zip(maps).zip(truths) {
        let offsets: Vec<f64> = view.frames.iter().map(|f| f.offset_mm).collect();
        let step = (offsets[offsets.len() - 1] - offsets[0]) / (offsets.len() - 1) as f64;
        // The map holds every `row_step`-th pixel row; truth holds every row.
        let truth_rows = t.chunks_exact(map.width).step_by(map.row_step.max(1)).flatten();
        for (i, (&d, &tr)) in map.depth_mm.iter().zip(truth_rows).enumerate() {
            if !tr.is_finite() {
                continue;
            }
            total += 1;
            if !d.is_finite() {
                continue;
            }
            seen += 1;
            let e = 1e3 * (d - tr) as f64;
            all.push(e);
            let p = (big_f - tr as f64 - offsets[0]) / step;
            by_phase[(((p - p.floor()) * BINS as f64) as usize).min(BINS - 1)].push(e);
            let r = map.peak_ratio[i];
            let rb = [2.0, 3.0, 5.0, 10.0, 30.0].iter().position(|&b| r < b).unwrap_or(5);
            by_ratio[rb].push(e);
        }
    }
    let (m, med, rms) = stats(&all);
    let gross = all.iter().filter(|e| e.abs() > 250.0).count() as f64 / all.len().max(1) as f64;
    let inliers: Vec<f64> = all.iter().copied().filter(|e| e.abs() <= 250.0).collect();
    println!(
        "  all: coverage {:.1}%  mean {:.1}  median|e| {:.1}  rms {:.1} µm; gross (>0.25 mm) {:.2}%, inlier rms {:.1}",
        100.0 * seen as f64 / total.max(1) as f64,
        m,
        med,
        rms,
        100.0 * gross,
        stats(&inliers).2
    );
    let line: Vec<String> = by_phase.iter().map(|e| format!("{:.0}", stats(e).0)).collect();
    println!("  mean by phase (eighths): {}", line.join(" "));
    let line: Vec<String> = by_ratio.iter().map(|e| format!("{}:{:.0}", e.len(), stats(e).1)).collect();
    println!("  n:median|e| by ratio <2 <3 <5 <10 <30 more: {}", line.join(" "));
}

fn stats(e: &[f64]) -> (f64, f64, f64) {
    if e.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    let rms = (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt();
    let mut a: Vec<f64> = e.iter().map(|x| x.abs()).collect();
    a.sort_by(f64::total_cmp);
    (mean, a[a.len() / 2], rms)
}
