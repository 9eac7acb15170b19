//! Locating each pixel's focus peak along its stack: the running k sharpest frames (a median
//! network per k), the peak between frames by the midpoint of its shoulders, and a pixel's own peak
//! where its window holds two surfaces.

/// A comparator network that leaves the median (the element of rank `n / 2`, as
/// `select_nth_unstable(n / 2)` finds) of `n` values at that index: Batcher's odd–even merge sort
/// pruned to the comparators the median depends on. Applied to `n` rows of pixels at once, each
/// comparator is a min and a max over whole rows, which vectorise; a selection per pixel does not.
use crate::pipeline::depth::{EDGE_MIN_SEPARATION_FRAMES, EDGE_PEAK_FRACTION};
#[derive(Clone, Debug)]
pub(super) struct MedianNetwork {
    pairs: Vec<(usize, usize)>,
    pub(super) rank: usize,
}

impl MedianNetwork {
    pub(super) fn new(n: usize) -> Self {
        // Batcher's odd–even merge sort for any n (Knuth, TAOCP 5.3.4, the merge-exchange form).
        let mut pairs = Vec::new();
        let mut p = 1;
        while p < n {
            let mut k = p;
            while k >= 1 {
                let mut j = k % p;
                while j + k < n {
                    for i in 0..k.min(n - j - k) {
                        if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                            pairs.push((i + j, i + j + k));
                        }
                    }
                    j += 2 * k;
                }
                k /= 2;
            }
            p *= 2;
        }
        // Keep only comparators whose outputs reach the median's position.
        let rank = n / 2;
        let mut needed = vec![false; n];
        if n > 0 {
            needed[rank] = true;
        }
        let mut kept: Vec<(usize, usize)> = Vec::new();
        for &(a, b) in pairs.iter().rev() {
            if needed[a] || needed[b] {
                needed[a] = true;
                needed[b] = true;
                kept.push((a, b));
            }
        }
        kept.reverse();
        Self { pairs: kept, rank }
    }

    /// `rows` holds n rows of `w` values; afterwards row `rank` holds each column's median (the
    /// other rows are left partly ordered).
    pub(super) fn apply(&self, rows: &mut [f32], w: usize) {
        for &(a, b) in &self.pairs {
            let (low, high) = rows.split_at_mut(b * w);
            let (low, high) = (&mut low[a * w..(a + 1) * w], &mut high[..w]);
            for (u, v) in low.iter_mut().zip(high.iter_mut()) {
                // Compare-and-select, which is one minps / maxps each: f32::min and max also order
                // NaNs, which the measures never are, at three more instructions apiece.
                let (x, y) = (*u, *v);
                (*u, *v) = if y < x { (y, x) } else { (x, y) };
            }
        }
    }
}

/// Which frame a pixel keeps when a later frame's measure equals its best so far.
#[derive(Clone, Copy, PartialEq)]
pub(super) enum Ties {
    KeepEarlier,
    TakeLater,
}

/// Per pixel, the greater of `best` and frame `k`'s `measures`, and the frame it came from.
/// Selected by bit masks: written as `if`s, the compiler keeps a branch per pixel (the loop does
/// not vectorise, and the branch is unpredictable where measures are close).
pub(super) fn keep_sharpest(measures: &[f32], k: u32, best: &mut [f32], best_frame: &mut [u32], ties: Ties) {
    let n = measures.len().min(best.len()).min(best_frame.len());
    let (measures, best, best_frame) = (&measures[..n], &mut best[..n], &mut best_frame[..n]);
    for x in 0..n {
        let (m, b) = (measures[x], best[x]);
        let sharper = match ties {
            Ties::KeepEarlier => m > b,
            Ties::TakeLater => m >= b,
        };
        let mask = 0u32.wrapping_sub(sharper as u32);
        best[x] = f32::from_bits((b.to_bits() & !mask) | (m.to_bits() & mask));
        best_frame[x] = (best_frame[x] & !mask) | (k & mask);
    }
}

/// The in-focus offset of one pixel's focus curve. The curve is flat-topped (within the depth of
/// field the image is as sharp as the pixels allow: two frames or so at the presets' step) and
/// falls off symmetrically, so the top says little about where focus lies and the shoulders say
/// it: the centre is the midpoint of the two points where the curve, linearly interpolated between
/// frames, crosses `fraction` of its height above the floor on either side of the maximum. (A
/// centroid of the frames above a cut has about twice this estimator's sub-frame phase bias on
/// the sharp plateaus of glossy crests, and no less noise.)
pub fn peak_offset(column: &[f32], offsets: &[f64], k_best: usize, floor: f32, fraction: f32) -> Option<f64> {
    let peak = column[k_best];
    let cut = floor + fraction * (peak - floor);
    let (mut lo, mut hi) = (k_best, k_best);
    while lo > 0 && column[lo - 1] > cut {
        lo -= 1;
    }
    while hi + 1 < column.len() && column[hi + 1] > cut {
        hi += 1;
    }
    if lo == 0 || hi + 1 == column.len() {
        return None; // the peak runs off the stack: focus not bracketed
    }
    let cross = |outside: usize, inside: usize| -> f64 {
        let (a, b) = (column[outside] as f64, column[inside] as f64);
        let t = if b > a { (cut as f64 - a) / (b - a) } else { 0.5 };
        offsets[outside] + t * (offsets[inside] - offsets[outside])
    };
    Some(0.5 * (cross(lo - 1, lo) + cross(hi + 1, hi)))
}

/// The frame of the peak that is the pixel's own on a focus curve `column` whose maximum is at
/// `k_best`, given the small box's sharpest frame `k_edge` ([`DepthOptions::edge_window_radius_px`]):
/// the curve's local maximum within a frame of `k_edge` when that is [`EDGE_MIN_SEPARATION_FRAMES`]
/// or more from `k_best`, inside the stack with a frame to spare on either side, and rises
/// [`EDGE_PEAK_FRACTION`] of the maximum's height above `floor`; otherwise `k_best`.
pub(super) fn own_peak(column: &[f32], k_best: usize, k_edge: usize, floor: f32) -> usize {
    let n = column.len();
    if k_edge.abs_diff(k_best) < EDGE_MIN_SEPARATION_FRAMES || k_edge < 2 || k_edge + 2 >= n {
        return k_best;
    }
    let k = (k_edge - 1..=k_edge + 1).fold(k_edge - 1, |m, k| if column[k] > column[m] { k } else { m });
    let local_max = column[k] >= column[k - 1] && column[k] >= column[k + 1];
    if local_max && column[k] - floor >= EDGE_PEAK_FRACTION * (column[k_best] - floor) { k } else { k_best }
}
