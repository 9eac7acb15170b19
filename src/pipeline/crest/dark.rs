//! Photometric evidence: how much of a dark bin the mill scale covers, and dark runs marking the
//! extent of the geometric runs that show it.

use super::*;

/// How much of each dark bin the scale covers, read from its brightness: 1 inside a run, and at
/// a run's first and last bin the fraction of the way from the machined reference down to the
/// run's own darkness (its median) — a bin the scale covers in part is a mix of the two. Bins
/// outside runs get 1 (unused).
pub(super) fn dark_cover(dark: &[bool], grays: &[Option<f32>], reference: f32) -> Vec<f32> {
    let mut cover = vec![1f32; dark.len()];
    for span in run_spans(dark) {
        let mut inside: Vec<f64> = grays[span.clone()].iter().flatten().map(|&g| g as f64).collect();
        let Some(level) = median(&mut inside).map(|l| l as f32) else { continue };
        if reference <= level {
            continue;
        }
        for i in [span.start, span.end - 1] {
            if let Some(g) = grays[i] {
                cover[i] = ((reference - g) / (reference - level)).clamp(0.0, 1.0);
            }
        }
    }
    cover
}

/// Where a geometric run shows mill scale anywhere, the darkness marks its extent: the crest
/// radius is fitted over a window as wide as the flat, and the flat mill surface cuts the rising
/// cone's far edge a few degrees before it reaches the centre line, so the geometric run starts
/// early on that side; the brightness is read on the centre line itself. A run with no dark bin
/// (a polished crest) stands on its geometry alone.
pub(super) fn defer_to_darkness(runs: &mut [bool], dark: &[bool]) {
    for span in run_spans(runs) {
        if dark[span.clone()].iter().any(|&d| d) {
            runs[span.clone()].copy_from_slice(&dark[span]);
        }
    }
}
