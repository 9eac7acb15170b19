//! Sub-frame phase equalisation across the views of a bundle whose frames lie on an even grid.

use super::DepthMap;
use rayon::prelude::*;

/// The frame grid of a stack whose offsets are evenly spaced (within 1% of the step), as
/// (first offset, step); None otherwise.
pub fn even_frame_grid(offsets: &[f64]) -> Option<(f64, f64)> {
    if offsets.len() < 3 {
        return None;
    }
    let step = (offsets[offsets.len() - 1] - offsets[0]) / (offsets.len() - 1) as f64;
    let even = step.abs() > 0.0
        && offsets.iter().enumerate().all(|(k, &o)| (o - offsets[0] - step * k as f64).abs() <= 0.01 * step.abs());
    even.then_some((offsets[0], step))
}

/// Bins of the sub-frame phase histogram.
pub(super) const PHASE_BINS: usize = 64;

/// Equalisation needs trusted depths (each frame with at least 1% of them) over this many frames.
pub(super) const MIN_FRAMES_SPANNED: usize = 3;

/// Largest correction, in frames, that equalisation applies (the benchmark's are about 0.05).
pub(super) const MAX_PHASE_CORRECTION: f64 = 0.15;

/// Removes the sub-frame phase bias ("peak locking") of the in-focus estimates.
///
/// The estimate from a few samples of a flat-topped focus curve is pulled towards frames or
/// half-frames depending on where the true focus falls between two frames (on a model curve about
/// ±20 µm at a 0.25 mm step, see `sub_frame_bias_depends_on_the_frame_step`; on the sharp
/// highlights of glossy crests more than on textured flanks). Over a whole bundle the surface's
/// depths fall at every phase equally often, so the estimated phases should be uniform; their
/// cumulative histogram is the estimator's phase response, and mapping each estimate through it
/// undoes the bias (as done for sub-pixel peak locking in particle image velocimetry). The
/// histogram is symmetrised about half a frame (a symmetric focus curve's bias is odd), which
/// halves what an uneven depth distribution contributes. Maps whose stacks are not on one even
/// frame grid are left as they are, and so are bundles whose depths span fewer than
/// [`MIN_FRAMES_SPANNED`] frames or whose phase response would move an estimate by more than
/// [`MAX_PHASE_CORRECTION`] of a frame: their phases are not uniform to begin with.
pub fn equalize_sub_frame_phase(maps: &mut [DepthMap], grids: &[Option<(f64, f64)>], focus_distance_mm: f64) {
    let Some(Some((_, step))) = grids.first() else { return };
    if grids.iter().any(|g| !matches!(g, Some((_, s)) if (s - step).abs() <= 0.01 * step.abs())) {
        return;
    }
    let phase_of = |depth: f32, origin: f64| -> (f64, f64) {
        let p = (focus_distance_mm - depth as f64 - origin) / step;
        let whole = p.floor();
        (whole, p - whole)
    };
    // Counts per map, summed (whole numbers: the sum does not depend on the order).
    // Estimates per whole frame index (an estimate lies within the stack, so the index is ≥ 0).
    let count = |map: &DepthMap, grid: &Option<(f64, f64)>| {
        let origin = grid.expect("checked above").0;
        let (mut histogram, mut per_frame) = ([0f64; PHASE_BINS], Vec::<f64>::new());
        for &d in map.depth_mm.iter().filter(|d| d.is_finite()) {
            let (whole, phase) = phase_of(d, origin);
            let k = whole.max(0.0) as usize;
            if k >= per_frame.len() {
                per_frame.resize(k + 1, 0.0);
            }
            per_frame[k] += 1.0;
            let bin = ((phase * PHASE_BINS as f64) as usize).min(PHASE_BINS - 1);
            histogram[bin] += 1.0;
            histogram[PHASE_BINS - 1 - bin] += 1.0;
        }
        (histogram, per_frame)
    };
    let add = |(mut h, mut f): ([f64; PHASE_BINS], Vec<f64>), (h2, f2): ([f64; PHASE_BINS], Vec<f64>)| {
        h.iter_mut().zip(&h2).for_each(|(a, b)| *a += b);
        if f2.len() > f.len() {
            f.resize(f2.len(), 0.0);
        }
        f.iter_mut().zip(&f2).for_each(|(a, b)| *a += b);
        (h, f)
    };
    let (histogram, per_frame) =
        maps.par_iter().zip(grids).map(|(map, grid)| count(map, grid)).reduce(|| ([0f64; PHASE_BINS], Vec::new()), add);
    let total: f64 = histogram.iter().sum();
    if total < (100 * PHASE_BINS) as f64 {
        return; // too few estimates for a histogram
    }
    // The phases are only uniform if the surface spans several frame steps of depth (a flat
    // plate square to the camera sits at one phase: equalising would smear it over a frame).
    let spanned = per_frame.iter().filter(|&&n| n >= 0.01 * total / 2.0).count();
    if spanned < MIN_FRAMES_SPANNED {
        return;
    }
    // cdf[i] = fraction of estimates below bin edge i / PHASE_BINS.
    let mut cdf = [0f64; PHASE_BINS + 1];
    for i in 0..PHASE_BINS {
        cdf[i + 1] = cdf[i] + histogram[i] / total;
    }
    // A phase response further from uniform than any focus-curve estimator's bias is an uneven
    // depth distribution, not peak locking: leave the estimates alone.
    let largest = (0..=PHASE_BINS).map(|i| (cdf[i] - i as f64 / PHASE_BINS as f64).abs()).fold(0.0, f64::max);
    if largest > MAX_PHASE_CORRECTION {
        return;
    }
    maps.par_iter_mut().zip(grids).for_each(|(map, grid)| {
        let origin = grid.expect("checked above").0;
        for d in map.depth_mm.iter_mut().filter(|d| d.is_finite()) {
            let (whole, phase) = phase_of(*d, origin);
            let x = phase * PHASE_BINS as f64;
            let i = (x as usize).min(PHASE_BINS - 1);
            let equalized = cdf[i] + (cdf[i + 1] - cdf[i]) * (x - i as f64);
            *d = (focus_distance_mm - origin - step * (whole + equalized)) as f32;
        }
    });
}
