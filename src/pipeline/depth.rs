//! Depth from focus, per view.
//!
//! Frames are decoded one at a time. A focus measure (squared Laplacian, box-summed) is taken on
//! each frame's own pixel grid, then brought onto the geometry of offset 0: the sensor distance is
//! fixed, so moving the camera back by `o` shrinks the image of a point at depth d (from the
//! offset-0 lens) by d / (d + o); the points that matter in frame k are those in focus there
//! (d + o = F), so the measure is scaled about the principal point by F / (F − o). (Resampling the
//! smooth measure rather than the image keeps interpolation from blurring some frames more than
//! others, which would bias the peak.) Each pixel's focus curve is located between frames by the
//! midpoint of its shoulders (see [`peak_offset`]), the bundle's sub-frame phases are equalised
//! (see [`equalize_sub_frame_phase`]), and the result is turned into depth through the optics: in
//! focus at offset o* means depth F − o* at offset 0. The confidence
//! says how sharply the measure peaks above its floor, so that texture-less and saturated pixels
//! are recognised rather than trusted. The all-in-focus image keeps each pixel's sharpest colour.
//! At a steep edge, where the box holds two surfaces and the curve peaks at both, a small box
//! says which peak (and colour) is the pixel's own ([`DepthOptions::edge_window_radius_px`]).

use crate::domain::frame::{Frame, FrameError, SampleValue, Samples, View};
use crate::domain::optics::{Optics, Projection};
use crate::domain::thread::{ProfileShape, ThreadForm};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthOptions {
    /// Half size of the box that sums the focus measure. [`DepthOptions::for_form`] sets it from
    /// the thread's profile: this value where crests and roots are arcs, `flat_window_radius_px`
    /// where they are flat.
    pub window_radius_px: usize,
    /// The box's half size on a form with flat crests and roots (buttress). Each pixel's focus
    /// curve is the sum over the box, so a wider box averages more texture and its depth is less
    /// noisy; on an arc it would also average depth over a curved section and flatten crests and
    /// roots (lower their heights), but a flat is many boxes wide.
    #[serde(default = "flat_window_radius_px")]
    pub flat_window_radius_px: usize,
    /// Pixels whose peak-to-floor ratio is below this are not trusted (depth NaN).
    pub min_peak_ratio: f32,
    /// The focus curve's centre is the midpoint of its crossings of this fraction of its height.
    pub peak_fraction: f32,
    /// Undo the sub-frame phase bias over the bundle ([`equalize_sub_frame_phase`]).
    #[serde(default = "yes")]
    pub equalize_phase: bool,
    /// Depth is estimated on every `row_step`-th pixel row (rows run across the arc: the frames'
    /// height spans the view's angle, their width the pipe's axis). A pixel's focus curve is the
    /// sum over a box 2·radius + 1 rows tall, so neighbouring rows' curves share all but one of
    /// its rows, and along the arc the thread changes slowly (a pitch per turn); every row of
    /// every frame still feeds the focus measure. 2 inspects the rings about a fifth faster
    /// with heights as accurate, but registration loses precision and black-crest ends move
    /// (docs/accuracy.md, "Depth on every second row"): the default is every row.
    #[serde(default = "row_step")]
    pub row_step: usize,
    /// Half size of a second, small box that decides which surface a pixel at a steep edge shows
    /// (0: none). Within a big box's half size of a crest's steep flank the box holds both the
    /// crest and the root, a thread's height apart, and the focus curve peaks at both; the side
    /// whose texture is stronger there wins, which moves the edge by up to the half size toward
    /// the weaker side. Under chaser marks, which shade every crest alike, that moved every edge
    /// of a part the same way (docs/accuracy.md, "Absolute z"). Where the small
    /// box's sharpest frame is
    /// [`EDGE_MIN_SEPARATION_FRAMES`] or more from the big box's, and the big curve has a peak of
    /// its own there, that peak is the pixel's.
    #[serde(default = "edge_window_radius_px")]
    pub edge_window_radius_px: usize,
}

/// Frames between the small box's sharpest frame and the big box's beyond which they see two
/// surfaces rather than one curve's plateau (about two frames wide at the presets' step).
pub const EDGE_MIN_SEPARATION_FRAMES: usize = 3;

/// The big curve's peak at the small box's frame must rise this fraction of the main peak's
/// height above the floor (the shoulders' cut, [`DepthOptions::peak_fraction`]'s default).
const EDGE_PEAK_FRACTION: f32 = 0.3;

fn yes() -> bool {
    true
}

fn flat_window_radius_px() -> usize {
    DepthOptions::default().flat_window_radius_px
}

fn row_step() -> usize {
    DepthOptions::default().row_step
}

fn edge_window_radius_px() -> usize {
    DepthOptions::default().edge_window_radius_px
}

impl Default for DepthOptions {
    fn default() -> Self {
        Self {
            window_radius_px: 4,
            flat_window_radius_px: 5,
            min_peak_ratio: 1.6,
            peak_fraction: 0.3,
            equalize_phase: true,
            row_step: 1,
            edge_window_radius_px: 1,
        }
    }
}

impl DepthOptions {
    /// These options for a thread of `form`: the focus window is `flat_window_radius_px` where the
    /// crests and roots are flat, `window_radius_px` where they are arcs. Meant for the options as
    /// configured: the result's `window_radius_px` is the window that runs.
    pub fn for_form(&self, form: &ThreadForm) -> Self {
        let window_radius_px = match form.profile {
            ProfileShape::Trapezoid { .. } => self.flat_window_radius_px,
            ProfileShape::Rounded { .. } => self.window_radius_px,
        };
        Self { window_radius_px, ..self.clone() }
    }
}

/// A view's depth map on the offset-0 pixel grid: every column, every `row_step`-th row.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    /// The frames' size in pixels.
    pub width: usize,
    pub height: usize,
    /// Map row r is pixel row r · `row_step` ([`DepthOptions::row_step`]); the map holds
    /// [`DepthMap::rows`] rows of `width` values.
    pub row_step: usize,
    /// Depth along the camera axis from the offset-0 lens centre; NaN where not trusted.
    pub depth_mm: Vec<f32>,
    /// Peak focus measure over its floor (median over the stack); ≥ 1.
    pub peak_ratio: Vec<f32>,
    /// Sharpest colour per pixel, RGB interleaved in [0, 1].
    pub all_in_focus: Vec<f32>,
    /// The end face's silhouette in each frame that shows it (for [`crate::pipeline::endface`]).
    pub end_edges: Vec<crate::pipeline::endface::FrameEdge>,
}

impl DepthMap {
    /// Rows of the map: the pixel rows 0, `row_step`, 2·`row_step`, … below `height`.
    pub fn rows(&self) -> usize {
        self.height.div_ceil(self.row_step.max(1))
    }

    pub fn coverage(&self) -> f64 {
        self.depth_mm.iter().filter(|d| d.is_finite()).count() as f64 / self.depth_mm.len() as f64
    }
}

/// Bilinear taps along one axis: where reference index i of the offset-0 grid falls in a frame
/// scaled by `scale` about `centre` (the scale is separable, so rows and columns are computed once
/// per frame): (i0, i1, fraction).
fn axis_taps(len: usize, centre: f64, scale: f64) -> Vec<(usize, usize, f32)> {
    (0..len)
        .map(|i| {
            let s = centre + (i as f64 + 0.5 - centre) * scale - 0.5;
            let i0 = (s.floor() as isize).clamp(0, len as isize - 1) as usize;
            (i0, (i0 + 1).min(len - 1), (s - i0 as f64).clamp(0.0, 1.0) as f32)
        })
        .collect()
}

/// A frame's bilinear taps onto the offset-0 grid, columns and rows ([`axis_taps`]).
struct Taps {
    xs: Vec<(usize, usize, f32)>,
    ys: Vec<(usize, usize, f32)>,
}

/// A decoded frame held until its view's colours are taken, with its taps.
struct HeldFrame {
    frame: Frame,
    taps: Taps,
}

impl HeldFrame {
    /// The frame's colour (RGB; a gray frame's value thrice) at reference pixel `x` of pixel row
    /// `y` of the offset-0 grid.
    #[inline]
    fn colour_at(&self, x: usize, y: usize, w: usize, out: &mut [f32]) {
        let corners = (self.taps.xs[x], self.taps.ys[y]);
        match &self.frame.samples {
            Samples::Eight(samples) => mix_corners(samples, self.frame.channels, w, corners, out),
            Samples::Sixteen(samples) => mix_corners(samples, self.frame.channels, w, corners, out),
            Samples::Float(samples) => mix_corners(samples, self.frame.channels, w, corners, out),
        }
    }
}

/// Bilinear interpolation between four values: `fx` of the way from the 0 to the 1 column, `fy`
/// from the 0 to the 1 row (along the columns first: every resampling here rounds the same way).
#[inline]
fn bilinear(p00: f32, p01: f32, p10: f32, p11: f32, fx: f32, fy: f32) -> f32 {
    let a = p00 * (1.0 - fx) + p01 * fx;
    let b = p10 * (1.0 - fx) + p11 * fx;
    a * (1.0 - fy) + b * fy
}

/// The four corners' values of one pixel, mixed per channel (a gray frame's value thrice).
#[inline]
fn mix_corners<T: SampleValue>(
    samples: &[T],
    channels: u8,
    w: usize,
    ((x0, x1, fx), (y0, y1, fy)): ((usize, usize, f32), (usize, usize, f32)),
    out: &mut [f32],
) {
    let at = |s: &[T], y: usize, x: usize| s[y * w + x].value();
    match channels {
        1 => out.fill(bilinear(
            at(samples, y0, x0),
            at(samples, y0, x1),
            at(samples, y1, x0),
            at(samples, y1, x1),
            fx,
            fy,
        )),
        _ => {
            let (pixels, _) = samples.as_chunks::<3>();
            let (p00, p01, p10, p11) =
                (pixels[y0 * w + x0], pixels[y0 * w + x1], pixels[y1 * w + x0], pixels[y1 * w + x1]);
            for (c, out) in out.iter_mut().enumerate() {
                *out = bilinear(p00[c].value(), p01[c].value(), p10[c].value(), p11[c].value(), fx, fy);
            }
        }
    }
}

/// A run of reference columns whose taps (see [`axis_taps`]) are `x0 + i` and `x0 + i + 1` for the
/// run's i-th column (`shifted`), or columns taken one by one (taps clamped at the frame's edge).
struct TapSpan {
    start: usize,
    len: usize,
    x0: usize,
    shifted: bool,
}

/// Splits a row's taps into [`TapSpan`]s: the scale is within a few percent of 1, so the offset
/// between a column and its first tap changes only a few times across a row.
fn tap_spans(taps: &[(usize, usize, f32)]) -> Vec<TapSpan> {
    let mut spans: Vec<TapSpan> = Vec::new();
    for (x, &(x0, x1, _)) in taps.iter().enumerate() {
        let shifted = x1 == x0 + 1;
        match spans.last_mut() {
            Some(s) if s.shifted && shifted && s.x0 + s.len == x0 && s.start + s.len == x => s.len += 1,
            Some(s) if !s.shifted && !shifted && s.start + s.len == x => s.len += 1,
            _ => spans.push(TapSpan { start: x, len: 1, x0, shifted }),
        }
    }
    spans
}

/// One row of the offset-0 grid from the two native rows around it (`fy` of the way to `below`),
/// bilinearly, through the row's taps (`fxs` are their fractions, `spans` from [`tap_spans`]).
fn resample_row(
    above: &[f32],
    below: &[f32],
    fy: f32,
    xs: &[(usize, usize, f32)],
    spans: &[TapSpan],
    fxs: &[f32],
    out: &mut [f32],
) {
    for span in spans {
        let (x, len, x0) = (span.start, span.len, span.x0);
        let (out, f) = (&mut out[x..x + len], &fxs[x..x + len]);
        if span.shifted {
            // Contiguous taps: the same arithmetic as below, over slices, so that it vectorises.
            let (a0, a1) = (&above[x0..x0 + len], &above[x0 + 1..x0 + 1 + len]);
            let (b0, b1) = (&below[x0..x0 + len], &below[x0 + 1..x0 + 1 + len]);
            for i in 0..len {
                out[i] = bilinear(a0[i], a1[i], b0[i], b1[i], f[i], fy);
            }
        } else {
            for (i, m) in out.iter_mut().enumerate() {
                let (x0, x1, fx) = xs[x + i];
                *m = bilinear(above[x0], above[x1], below[x0], below[x1], fx, fy);
            }
        }
    }
}

/// [`focus_measures`] with one box.
#[cfg(test)]
fn focus_measure(gray: &[f32], w: usize, h: usize, r: usize, scratch: &mut [f32], out: &mut [f32]) {
    focus_measures(gray, w, h, r, scratch, out, None)
}

/// Squared Laplacian, box-summed over (2r+1)², written into `out`; with `edge` = (r_edge, plane),
/// the same Laplacian summed over the box of half size r_edge into that plane as well (one
/// Laplacian for both). `scratch` is reused.
///
/// Every pass runs along whole rows so that it vectorises: the Laplacian, a running sum of rows
/// (the vertical box), then the horizontal box as 2r+1 shifted row additions (a running sum along
/// a row is one long dependency chain).
fn focus_measures(
    gray: &[f32],
    w: usize,
    h: usize,
    r: usize,
    scratch: &mut [f32],
    out: &mut [f32],
    edge: Option<(usize, &mut [f32])>,
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2 (checked just above).
        return unsafe { focus_measures_avx2(gray, w, h, r, scratch, out, edge) };
    }
    focus_measures_body::<false>(gray, w, h, r, scratch, out, edge)
}

/// [`focus_measures_body`] compiled for AVX2. The build targets baseline x86-64 (SSE2), so the
/// binary runs anywhere; these passes are element-wise, so either copy gives the same numbers
/// (unit-tested). Single-threaded on the standard preset the depth stage takes 3.65 → 3.49 s with
/// it. The median network and the argmax over frames were slower with AVX2 on this machine (depth
/// 3.49 → 3.85 s and 3.57 → 3.99 s), as was the whole program built for x86-64-v3, so they keep
/// the baseline build.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn focus_measures_avx2(
    gray: &[f32],
    w: usize,
    h: usize,
    r: usize,
    scratch: &mut [f32],
    out: &mut [f32],
    edge: Option<(usize, &mut [f32])>,
) {
    focus_measures_body::<true>(gray, w, h, r, scratch, out, edge)
}

/// `AVX2`: the horizontal box by [`horizontal_box_row_avx2`] (only where the processor has it).
#[inline(always)]
fn focus_measures_body<const AVX2: bool>(
    gray: &[f32],
    w: usize,
    h: usize,
    r: usize,
    scratch: &mut [f32],
    out: &mut [f32],
    edge: Option<(usize, &mut [f32])>,
) {
    if w == 0 || h == 0 {
        return;
    }
    match edge {
        None => {
            laplacian_squared(gray, w, h, out);
            vertical_box(out, w, h, r, scratch);
            horizontal_box::<AVX2>(scratch, w, h, r, out);
        }
        Some((r_edge, edge_out)) => {
            laplacian_squared(gray, w, h, edge_out);
            vertical_box(edge_out, w, h, r, scratch);
            horizontal_box::<AVX2>(scratch, w, h, r, out);
            vertical_box(edge_out, w, h, r_edge, scratch);
            horizontal_box::<AVX2>(scratch, w, h, r_edge, edge_out);
        }
    }
}

/// The squared Laplacian (4-neighbour), zero on the frame's border.
#[inline(always)]
fn laplacian_squared(gray: &[f32], w: usize, h: usize, out: &mut [f32]) {
    out[..w].fill(0.0);
    out[(h - 1) * w..].fill(0.0);
    for y in 1..h.saturating_sub(1) {
        let (up, mid, down) = (&gray[(y - 1) * w..y * w], &gray[y * w..(y + 1) * w], &gray[(y + 1) * w..(y + 2) * w]);
        let row = &mut out[y * w..(y + 1) * w];
        row[0] = 0.0;
        row[w - 1] = 0.0;
        let inner = w.saturating_sub(2);
        let (left, centre, right) = (&mid[..inner], &mid[1..inner + 1], &mid[2..inner + 2]);
        let (up, down) = (&up[1..inner + 1], &down[1..inner + 1]);
        for (i, o) in row[1..inner + 1].iter_mut().enumerate() {
            let lap = 4.0 * centre[i] - left[i] - right[i] - up[i] - down[i];
            *o = lap * lap;
        }
    }
}

/// The vertical box of half size r: a running sum of rows, `src` → `dst`.
#[inline(always)]
fn vertical_box(src: &[f32], w: usize, h: usize, r: usize, dst: &mut [f32]) {
    let mut acc = vec![0f32; w];
    for y in 0..r.min(h) {
        for (a, &v) in acc.iter_mut().zip(&src[y * w..(y + 1) * w]) {
            *a += v;
        }
    }
    for y in 0..h {
        if y + r < h {
            for (a, &v) in acc.iter_mut().zip(&src[(y + r) * w..(y + r + 1) * w]) {
                *a += v;
            }
        }
        if y > r {
            for (a, &v) in acc.iter_mut().zip(&src[(y - r - 1) * w..(y - r) * w]) {
                *a -= v;
            }
        }
        dst[y * w..(y + 1) * w].copy_from_slice(&acc);
    }
}

/// The horizontal box of half size r, `src` → `dst`, as 2r+1 shifted row additions; clamped at
/// zero (the running sums' rounding can leave a hair below it).
#[inline(always)]
fn horizontal_box<const AVX2: bool>(src: &[f32], w: usize, h: usize, r: usize, dst: &mut [f32]) {
    for y in 0..h {
        let (src, dst) = (&src[y * w..(y + 1) * w], &mut dst[y * w..(y + 1) * w]);
        #[cfg(target_arch = "x86_64")]
        if AVX2 {
            // SAFETY: AVX2 is only asked for from `focus_measures_avx2`, which runs where the
            // processor has it.
            unsafe { horizontal_box_row_avx2(src, r, dst) };
            continue;
        }
        dst.fill(0.0);
        for d in 0..=2 * r {
            // dst[x] += src[x + d − r] wherever both are in the row.
            let (from, to) = if d >= r { (d - r, 0) } else { (0, r - d) };
            let len = w.saturating_sub(from.max(to));
            if len == 0 {
                continue; // a row narrower than the box: this shift reaches no pixel
            }
            for (o, &v) in dst[to..to + len].iter_mut().zip(&src[from..from + len]) {
                *o += v;
            }
        }
        for o in dst.iter_mut() {
            *o = o.max(0.0);
        }
    }
}

/// One row of [`horizontal_box`] with each output's 2r + 1 terms added into one AVX2 accumulator,
/// eight outputs at a time, in the same order as the shifted row additions (bit for bit the same
/// sums): the row additions store and reload the row 2r + 1 times. Written with intrinsics because
/// the compiler turned the overlapping loads of plain slices into shuffles.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn horizontal_box_row_avx2(src: &[f32], r: usize, dst: &mut [f32]) {
    use std::arch::x86_64::{_mm256_add_ps, _mm256_loadu_ps, _mm256_max_ps, _mm256_setzero_ps, _mm256_storeu_ps};
    const LANES: usize = 8;
    let w = src.len().min(dst.len());
    // The terms within the row, left to right from 0 (the row additions' order where the box
    // reaches past an end).
    let at_edge = |x: usize| src[x.saturating_sub(r)..=(x + r).min(w - 1)].iter().fold(0f32, |a, &v| a + v).max(0.0);
    let inner_end = w.saturating_sub(r); // every x in r..inner_end has its whole box in the row
    let mut x = 0;
    while x < r.min(w) {
        dst[x] = at_edge(x);
        x += 1;
    }
    // Four blocks at a time: four independent chains of additions, not one waiting on the last.
    while x + 4 * LANES <= inner_end {
        // SAFETY: as below, for each of the four blocks.
        unsafe {
            let p = src.as_ptr().add(x - r);
            let (mut a0, mut a1, mut a2, mut a3) =
                (_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps());
            for d in 0..=2 * r {
                a0 = _mm256_add_ps(a0, _mm256_loadu_ps(p.add(d)));
                a1 = _mm256_add_ps(a1, _mm256_loadu_ps(p.add(d + LANES)));
                a2 = _mm256_add_ps(a2, _mm256_loadu_ps(p.add(d + 2 * LANES)));
                a3 = _mm256_add_ps(a3, _mm256_loadu_ps(p.add(d + 3 * LANES)));
            }
            let out = dst.as_mut_ptr().add(x);
            for (k, a) in [a0, a1, a2, a3].into_iter().enumerate() {
                _mm256_storeu_ps(out.add(k * LANES), _mm256_max_ps(a, _mm256_setzero_ps()));
            }
        }
        x += 4 * LANES;
    }
    while x + LANES <= inner_end {
        // SAFETY: x − r + d + 7 ≤ x + r + 7 < inner_end + r = w for every d ≤ 2r, and x + 7 < w.
        unsafe {
            let mut acc = _mm256_setzero_ps();
            for d in 0..=2 * r {
                acc = _mm256_add_ps(acc, _mm256_loadu_ps(src.as_ptr().add(x - r + d)));
            }
            // The sums are never −0 (they start at +0), so maxps and f32::max agree.
            _mm256_storeu_ps(dst.as_mut_ptr().add(x), _mm256_max_ps(acc, _mm256_setzero_ps()));
        }
        x += LANES;
    }
    while x < w {
        dst[x] = at_edge(x);
        x += 1;
    }
}

/// A comparator network that leaves the median (the element of rank `n / 2`, as
/// `select_nth_unstable(n / 2)` finds) of `n` values at that index: Batcher's odd–even merge sort
/// pruned to the comparators the median depends on. Applied to `n` rows of pixels at once, each
/// comparator is a min and a max over whole rows, which vectorise; a selection per pixel does not.
#[derive(Clone, Debug)]
struct MedianNetwork {
    pairs: Vec<(usize, usize)>,
    rank: usize,
}

impl MedianNetwork {
    fn new(n: usize) -> Self {
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
    fn apply(&self, rows: &mut [f32], w: usize) {
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
enum Ties {
    KeepEarlier,
    TakeLater,
}

/// Per pixel, the greater of `best` and frame `k`'s `measures`, and the frame it came from.
/// Selected by bit masks: written as `if`s, the compiler keeps a branch per pixel (the loop does
/// not vectorise, and the branch is unpredictable where measures are close).
fn keep_sharpest(measures: &[f32], k: u32, best: &mut [f32], best_frame: &mut [u32], ties: Ties) {
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
pub(crate) fn peak_offset(column: &[f32], offsets: &[f64], k_best: usize, floor: f32, fraction: f32) -> Option<f64> {
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

/// Runs depth from focus over one view. `frame_at(k)` decodes frame k (called once per frame, in
/// order); `cancelled()` is polled between frames.
pub fn depth_from_focus(
    optics: &Optics,
    view: &View,
    options: &DepthOptions,
    frame_at: impl FnMut(usize) -> Result<Frame, FrameError>,
    cancelled: &dyn Fn() -> bool,
) -> Result<Option<DepthMap>, FrameError> {
    depth_from_focus_in(&mut DepthScratch::default(), optics, view, options, frame_at, cancelled)
}

/// The working buffers of [`depth_from_focus_in`]: the focus volume (frames × pixels, tens of MB)
/// and a few frame-sized planes, which a caller keeps from view to view: fresh ones cost a page
/// fault per 4 kB.
#[derive(Default)]
pub struct DepthScratch {
    volume: Vec<f32>,
    best: Vec<f32>,
    best_frame: Vec<u32>,
    gray: Vec<f32>,
    native: Vec<f32>,
    scratch: Vec<f32>,
    /// The small box's measure, its best so far and where ([`DepthOptions::edge_window_radius_px`]).
    native_edge: Vec<f32>,
    best_edge: Vec<f32>,
    best_edge_frame: Vec<u32>,
    edge_row: Vec<f32>,
}

/// `buffer` holding `len` copies of `value` (its allocation kept).
fn refill<T: Copy>(buffer: &mut Vec<T>, len: usize, value: T) {
    buffer.clear();
    buffer.resize(len, value);
}

/// [`depth_from_focus`] in buffers the caller keeps from view to view ([`DepthScratch`]).
pub fn depth_from_focus_in(
    buffers: &mut DepthScratch,
    optics: &Optics,
    view: &View,
    options: &DepthOptions,
    mut frame_at: impl FnMut(usize) -> Result<Frame, FrameError>,
    cancelled: &dyn Fn() -> bool,
) -> Result<Option<DepthMap>, FrameError> {
    let (w, h) = (view.format.width as usize, view.format.height as usize);
    let step = options.row_step.max(1);
    // Map rows: pixel rows 0, step, 2·step, …
    let rows = h.div_ceil(step);
    let n = view.frames.len();
    let principal = optics.principal_point(view.format.width, view.format.height);
    let big_f = optics.focus_distance_mm;
    // Focus volume, frame-major: each frame's measure is written as one contiguous plane (a
    // pixel-major layout would scatter every write to its own cache line); the peak search gathers
    // a row's curves from the n planes.
    let plane = w * rows;
    let DepthScratch {
        volume,
        best,
        best_frame,
        gray,
        native,
        scratch,
        native_edge,
        best_edge,
        best_edge_frame,
        edge_row,
    } = buffers;
    let edge_radius = options.edge_window_radius_px;
    let edge_aware = edge_radius > 0;
    if edge_aware {
        native_edge.resize(w * h, 0.0);
        refill(best_edge, plane, f32::MIN);
        refill(best_edge_frame, plane, 0u32);
        edge_row.resize(w, 0.0);
    }
    // Every cell is written before it is read (each frame fills its whole plane).
    volume.resize(plane * n, 0.0);
    refill(best, plane, f32::MIN);
    // The frame (index) where each pixel's measure is highest so far (the first such).
    refill(best_frame, plane, 0u32);
    // Every cell of these is written before it is read, frame by frame.
    native.resize(w * h, 0.0);
    scratch.resize(w * h, 0.0);
    let mut end_edges = Vec::new();
    // The view's frames are held until its colours are taken, once per pixel from its sharpest
    // frame when the stack is done (0.8 MB a frame of the standard preset's: one view's stack per
    // view in flight, never every view's). Sampled as the stack streamed, every pixel was mixed
    // at each frame that was its sharpest so far, and the search for those pixels scanned the
    // frame: 10% of an inspection, against 2.5% once per pixel.
    let mut held: Vec<HeldFrame> = Vec::with_capacity(n);
    for (k, entry) in view.frames.iter().enumerate() {
        if cancelled() {
            return Ok(None);
        }
        let frame = frame_at(k)?;
        let scale = match optics.projection {
            Projection::Perspective => (big_f - entry.offset_mm) / big_f,
            Projection::Telecentric => 1.0,
        };
        frame.gray_into(gray);
        let edge = edge_aware.then_some((edge_radius, &mut native_edge[..]));
        focus_measures(gray, w, h, options.window_radius_px, scratch, native, edge);
        end_edges.extend(crate::pipeline::endface::frame_edge(gray, w, h, entry.offset_mm));
        let taps = Taps { xs: axis_taps(w, principal[0], scale), ys: axis_taps(h, principal[1], scale) };
        let (spans, fxs) = (tap_spans(&taps.xs), taps.xs.iter().map(|t| t.2).collect::<Vec<f32>>());
        let k32 = k as u32;
        // Map row r is pixel row r · step.
        for (r, &(y0, y1, fy)) in taps.ys.iter().step_by(step).enumerate() {
            let (above, below) = (&native[y0 * w..(y0 + 1) * w], &native[y1 * w..(y1 + 1) * w]);
            let measures = &mut volume[k * plane + r * w..k * plane + (r + 1) * w];
            resample_row(above, below, fy, &taps.xs, &spans, &fxs, measures);
            let (best_row, best_frame_row) = (&mut best[r * w..(r + 1) * w], &mut best_frame[r * w..(r + 1) * w]);
            keep_sharpest(measures, k32, best_row, best_frame_row, Ties::KeepEarlier);
            if edge_aware {
                let (above, below) = (&native_edge[y0 * w..(y0 + 1) * w], &native_edge[y1 * w..(y1 + 1) * w]);
                resample_row(above, below, fy, &taps.xs, &spans, &fxs, edge_row);
                let rows = r * w..(r + 1) * w;
                keep_sharpest(
                    edge_row,
                    k32,
                    &mut best_edge[rows.clone()],
                    &mut best_edge_frame[rows],
                    Ties::KeepEarlier,
                );
            }
        }
        held.push(HeldFrame { frame, taps });
    }
    let offsets: Vec<f64> = view.frames.iter().map(|f| f.offset_mm).collect();
    // Breathing moves content by up to |o|/F of its distance from the principal point.
    let max_offset = offsets.iter().fold(0.0f64, |m, o| m.max(o.abs()));
    let breathing_px = match optics.projection {
        Projection::Perspective => (max_offset / big_f * (w.max(h) as f64)).ceil() as usize,
        Projection::Telecentric => 0,
    };
    let border = options.window_radius_px + 1 + breathing_px;
    let mut depth_mm = vec![f32::NAN; plane];
    let mut peak_ratio = vec![1f32; plane];
    let network = MedianNetwork::new(n);
    let mut all_in_focus = vec![0f32; plane * 3];
    let volume: &[f32] = volume;
    let (best_frame, best_edge_frame): (&[u32], &[u32]) = (best_frame, best_edge_frame);
    let held = &held;
    // Per row: the n frames' rows (each one contiguous run of the frame-major volume) give the
    // maximum and, copied out, the median for all of the row's pixels at once; only trusted
    // pixels' curves are walked one by one.
    let init = || (vec![0f32; n * w], vec![0f32; w], vec![0u32; w], vec![0f32; n]);
    depth_mm
        .par_chunks_mut(w)
        .zip(peak_ratio.par_chunks_mut(w))
        .zip(all_in_focus.par_chunks_mut(3 * w))
        .enumerate()
        .for_each_init(init, |(sorted, peak, k_best, column), (r, ((depth_row, ratio_row), colour_row))| {
            let y = r * step;
            let row_of = |k: usize| &volume[k * plane + r * w..k * plane + (r + 1) * w];
            for k in 0..n {
                sorted[k * w..(k + 1) * w].copy_from_slice(row_of(k));
            }
            // The last maximum, as `max_by` would give.
            peak.copy_from_slice(row_of(0));
            k_best.fill(0);
            for k in 1..n {
                keep_sharpest(row_of(k), k as u32, peak, k_best, Ties::TakeLater);
            }
            network.apply(sorted, w);
            let floors = &sorted[network.rank * w..(network.rank + 1) * w];
            // Every pixel's colour from its sharpest frame (the first of equals).
            for (x, colour) in colour_row.chunks_exact_mut(3).enumerate() {
                held[best_frame[r * w + x] as usize].colour_at(x, y, w, colour);
            }
            for x in 0..w {
                let floor = floors[x].max(1e-12);
                let (peak, mut k_best) = (peak[x], k_best[x] as usize);
                let ratio = peak / floor;
                ratio_row[x] = ratio;
                if x < border || y < border || x + border >= w || y + border >= h {
                    continue; // the focus window or the breathing correction runs off the frame
                }
                if ratio < options.min_peak_ratio || k_best == 0 || k_best + 1 == n {
                    continue;
                }
                for (k, c) in column.iter_mut().enumerate() {
                    *c = volume[k * plane + r * w + x];
                }
                if edge_aware {
                    let k_edge = best_edge_frame[r * w + x] as usize;
                    let own = own_peak(column, k_best, k_edge, floor);
                    if own != k_best {
                        // The pixel's colour where the small box is sharpest, not from the other
                        // surface's frame (with the big box's colour, registration's texture lost
                        // precision: standard's axial error 1.6 → 4.4 µm RMS; with this, 1.5 µm).
                        held[k_edge].colour_at(x, y, w, &mut colour_row[3 * x..3 * x + 3]);
                        k_best = own;
                    }
                }
                if let Some(in_focus_offset) = peak_offset(column, &offsets, k_best, floor, options.peak_fraction) {
                    depth_row[x] = (big_f - in_focus_offset) as f32;
                }
            }
        });
    Ok(Some(DepthMap { width: w, height: h, row_step: step, depth_mm, peak_ratio, all_in_focus, end_edges }))
}

/// The frame of the peak that is the pixel's own on a focus curve `column` whose maximum is at
/// `k_best`, given the small box's sharpest frame `k_edge` ([`DepthOptions::edge_window_radius_px`]):
/// the curve's local maximum within a frame of `k_edge` when that is [`EDGE_MIN_SEPARATION_FRAMES`]
/// or more from `k_best`, inside the stack with a frame to spare on either side, and rises
/// [`EDGE_PEAK_FRACTION`] of the maximum's height above `floor`; otherwise `k_best`.
fn own_peak(column: &[f32], k_best: usize, k_edge: usize, floor: f32) -> usize {
    let n = column.len();
    if k_edge.abs_diff(k_best) < EDGE_MIN_SEPARATION_FRAMES || k_edge < 2 || k_edge + 2 >= n {
        return k_best;
    }
    let k = (k_edge - 1..=k_edge + 1).fold(k_edge - 1, |m, k| if column[k] > column[m] { k } else { m });
    let local_max = column[k] >= column[k - 1] && column[k] >= column[k + 1];
    if local_max && column[k] - floor >= EDGE_PEAK_FRACTION * (column[k_best] - floor) { k } else { k_best }
}

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
const PHASE_BINS: usize = 64;

/// Equalisation needs trusted depths (each frame with at least 1% of them) over this many frames.
const MIN_FRAMES_SPANNED: usize = 3;

/// Largest correction, in frames, that equalisation applies (the benchmark's are about 0.05).
const MAX_PHASE_CORRECTION: f64 = 0.15;

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_stored_before_the_flat_window_existed_still_load_with_its_default() {
        let old = r#"{"window_radius_px": 3, "min_peak_ratio": 1.6, "peak_fraction": 0.3}"#;
        let options: DepthOptions = serde_json::from_str(old).unwrap();
        assert_eq!((options.window_radius_px, options.flat_window_radius_px), (3, 5));
        assert!(options.equalize_phase);
        assert_eq!(options.row_step, 1);
        assert_eq!(options.edge_window_radius_px, 1);
    }

    #[test]
    fn at_a_steep_edge_the_small_box_picks_which_of_two_peaks_is_the_pixels_own() {
        // A big box straddling a crest edge: the crest's peak at frame 4 (stronger texture) and
        // the root's at frame 11, a thread's height further; floor 1.
        let two_peaks = [1.0, 1.2, 3.0, 8.0, 10.0, 8.0, 3.0, 1.3, 1.5, 2.5, 4.5, 5.0, 4.0, 2.0, 1.1, 1.0];
        // The pixel's own 3×3 box is sharpest on the root: the root's peak is its own.
        assert_eq!(own_peak(&two_peaks, 4, 11, 1.0), 11);
        // Within a frame of it counts too (the small box is noisier than the big one).
        assert_eq!(own_peak(&two_peaks, 4, 10, 1.0), 11);
        assert_eq!(own_peak(&two_peaks, 4, 12, 1.0), 11);
        // The small box agrees with the big one, or sits on the same peak's plateau: unchanged.
        assert_eq!(own_peak(&two_peaks, 4, 4, 1.0), 4);
        assert_eq!(own_peak(&two_peaks, 4, 6, 1.0), 4);
        // One curve with a single peak: a small box sharpest far from it (noise on a dull
        // surface) finds no peak of the big curve there, so the maximum stands.
        let one_peak = [1.0, 1.2, 3.0, 8.0, 10.0, 8.0, 3.0, 1.5, 1.2, 1.1, 1.1, 1.0, 1.0, 1.0, 1.0, 1.0];
        assert_eq!(own_peak(&one_peak, 4, 10, 1.0), 4);
        // A second peak too faint to be a surface (under 30% of the maximum's height above the
        // floor): the maximum stands.
        let faint = [1.0, 1.2, 3.0, 8.0, 10.0, 8.0, 3.0, 1.3, 1.5, 2.5, 3.4, 3.6, 3.0, 2.0, 1.1, 1.0];
        assert_eq!(own_peak(&faint, 4, 11, 1.0), 4);
        // The small box at the stack's ends (no frame to spare for the shoulders): unchanged.
        assert_eq!(own_peak(&two_peaks, 4, 15, 1.0), 4);
        assert_eq!(own_peak(&two_peaks, 11, 1, 1.0), 11);
    }

    #[test]
    fn keeping_the_sharpest_frame_by_masks_matches_the_branches_and_their_ties() {
        // Measures on a coarse lattice so that ties are frequent; 37 pixels (not a lane multiple).
        let frames: Vec<Vec<f32>> =
            (0..9u32).map(|k| (0..37u32).map(|x| ((x * 7 + k * 13) % 5) as f32 * 0.5).collect()).collect();
        for ties in [Ties::KeepEarlier, Ties::TakeLater] {
            let (mut best, mut best_frame) = (frames[0].clone(), vec![0u32; 37]);
            let (mut want, mut want_frame) = (frames[0].clone(), vec![0u32; 37]);
            for (k, measures) in frames.iter().enumerate().skip(1) {
                keep_sharpest(measures, k as u32, &mut best, &mut best_frame, ties);
                for x in 0..37 {
                    let sharper = if ties == Ties::TakeLater { measures[x] >= want[x] } else { measures[x] > want[x] };
                    if sharper {
                        (want[x], want_frame[x]) = (measures[x], k as u32);
                    }
                }
            }
            assert_eq!((&best, &best_frame), (&want, &want_frame));
        }
        // The tie rule decides between equal peaks in frames 1 and 3.
        let curve = [[0.0f32], [2.0], [1.0], [2.0]];
        for (ties, frame) in [(Ties::KeepEarlier, 1), (Ties::TakeLater, 3)] {
            let (mut best, mut best_frame) = ([curve[0][0]], [0u32]);
            for (k, m) in curve.iter().enumerate().skip(1) {
                keep_sharpest(m, k as u32, &mut best, &mut best_frame, ties);
            }
            assert_eq!((best, best_frame), ([2.0], [frame]));
        }
    }

    #[test]
    fn flat_topped_curve_centre_moves_smoothly_with_focus() {
        let offsets: Vec<f64> = (0..12).map(|k| -1.5 + 0.25 * k as f64).collect();
        // A plateau 0.5 mm wide with symmetric shoulders, centred at `c`.
        let curve = |c: f64| -> Vec<f32> {
            offsets
                .iter()
                .map(|&o| (1.0 / (1.0 + (((o - c).abs() - 0.25).max(0.0) / 0.2).powi(2))) as f32 + 0.05)
                .collect()
        };
        for c in [-0.4, -0.33, -0.2, 0.0, 0.11, 0.3] {
            let column = curve(c);
            let k_best = (0..column.len()).max_by(|&a, &b| column[a].total_cmp(&column[b])).unwrap();
            let got = peak_offset(&column, &offsets, k_best, 0.05, 0.3).unwrap();
            assert!((got - c).abs() < 0.03, "centre {c}: {got}");
        }
        // A peak at the end of the stack is not bracketed.
        let column = curve(1.4);
        assert!(peak_offset(&column, &offsets, 11, 0.05, 0.3).is_none());
    }

    /// The estimate's error depends on where the true focus falls between two frames. This pins
    /// down its size on a model curve (plateau ±0.25 mm, Lorentzian shoulders): about ±20 µm at the
    /// presets' 0.25 mm frame step, under 3 µm at 0.1 mm: what [`equalize_sub_frame_phase`] exists
    /// to remove.
    #[test]
    fn sub_frame_bias_depends_on_the_frame_step() {
        let shape = |o: f64, c: f64| (1.0 / (1.0 + (((o - c).abs() - 0.25).max(0.0) / 0.2).powi(2))) as f32 + 0.05;
        let worst = |step: f64| -> f64 {
            let offsets: Vec<f64> = (0..=(3.0 / step).round() as usize).map(|k| -1.5 + step * k as f64).collect();
            (0..=120)
                .map(|i| -0.3 + 0.005 * i as f64)
                .map(|c| {
                    let column: Vec<f32> = offsets.iter().map(|&o| shape(o, c)).collect();
                    let k_best = (0..column.len()).max_by(|&a, &b| column[a].total_cmp(&column[b])).unwrap();
                    (peak_offset(&column, &offsets, k_best, 0.05, 0.3).unwrap() - c).abs()
                })
                .fold(0.0, f64::max)
        };
        let (coarse, fine) = (worst(0.25), worst(0.1));
        assert!((0.015..0.03).contains(&coarse), "0.25 mm step: {coarse}");
        assert!(fine < 0.003, "0.1 mm step: {fine}");
    }

    /// The pruned network selects the median of every 0/1 input up to n = 12 (so, by the 0/1
    /// principle, of every input), and finds what `select_nth_unstable(n / 2)` finds on random
    /// rows with many ties.
    #[test]
    fn median_network_matches_selection() {
        for n in 1..=12usize {
            for bits in 0u32..(1 << n) {
                let mut rows: Vec<f32> = (0..n).map(|k| ((bits >> k) & 1) as f32).collect();
                let mut expected = rows.clone();
                expected.sort_by(f32::total_cmp);
                let network = MedianNetwork::new(n);
                network.apply(&mut rows, 1);
                assert_eq!(rows[n / 2], expected[n / 2], "n {n}, input {bits:b}");
            }
        }
        let mut state = 12345u64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            // Few distinct values, so that ties are common.
            ((state >> 33) % 17) as f32 * 0.25
        };
        for n in [3, 7, 8, 16, 20, 21, 31, 40, 64] {
            let w = 37;
            let network = MedianNetwork::new(n);
            let mut rows: Vec<f32> = (0..n * w).map(|_| next()).collect();
            let expected: Vec<f32> = (0..w)
                .map(|x| {
                    let mut column: Vec<f32> = (0..n).map(|k| rows[k * w + x]).collect();
                    *column.select_nth_unstable_by(n / 2, f32::total_cmp).1
                })
                .collect();
            network.apply(&mut rows, w);
            assert_eq!(&rows[network.rank * w..(network.rank + 1) * w], &expected[..], "n {n}");
        }
    }

    /// The row resampling by spans gives, bit for bit, the bilinear sample through each column's
    /// own taps, for frames scaled up and down about centres inside and outside the row (taps
    /// clamped at either edge).
    #[test]
    fn resampling_by_spans_matches_tap_by_tap() {
        let w = 97;
        let above: Vec<f32> = (0..w).map(|i| ((i * 37) % 23) as f32 / 7.0).collect();
        let below: Vec<f32> = (0..w).map(|i| ((i * 11) % 19) as f32 / 5.0).collect();
        for (centre, scale) in [(48.5, 1.011), (48.5, 0.989), (10.0, 1.05), (90.0, 0.95), (-20.0, 1.0), (48.5, 1.0)] {
            let xs = axis_taps(w, centre, scale);
            let fxs: Vec<f32> = xs.iter().map(|t| t.2).collect();
            let spans = tap_spans(&xs);
            assert_eq!(spans.iter().map(|s| s.len).sum::<usize>(), w);
            let mut out = vec![0f32; w];
            resample_row(&above, &below, 0.3, &xs, &spans, &fxs, &mut out);
            for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
                let a = above[x0] * (1.0 - fx) + above[x1] * fx;
                let b = below[x0] * (1.0 - fx) + below[x1] * fx;
                assert_eq!(out[x], a * (1.0 - 0.3) + b * 0.3, "centre {centre}, scale {scale}, column {x}");
            }
        }
    }

    /// The same frames stored as 8-bit, 16-bit (v·257, the same value v / 255) and f32 samples,
    /// gray and RGB, give the same depth map, confidence and all-in-focus colour bit for bit.
    #[test]
    fn every_sample_depth_gives_the_same_depth_map() {
        let (w, h, n) = (40usize, 24usize, 7usize);
        // A checkerboard whose contrast peaks at frame 3 on the left half and frame 4 on the right.
        let level = |x: usize, y: usize, k: usize| -> u8 {
            let peak = if x < w / 2 { 3.0 } else { 4.0 };
            let contrast = (-(k as f32 - peak).powi(2) / 2.0).exp();
            let checker = if (x + y).is_multiple_of(2) { 1.0 } else { -1.0 };
            (255.0 * (0.45 + 0.02 * k as f32 + 0.3 * contrast * checker)).round() as u8
        };
        let optics = Optics {
            projection: Projection::Perspective,
            focal_length_mm: Some(50.0),
            f_number: 2.8,
            focus_distance_mm: 220.0,
            pixel_pitch_um: 12.0,
            principal_point_px: None,
            magnification: None,
        };
        for channels in [1u8, 3] {
            let values = |k: usize| -> Vec<u8> {
                (0..w * h)
                    .flat_map(|i| {
                        let v = level(i % w, i / w, k);
                        [v, v / 2, 255 - v].into_iter().take(channels as usize)
                    })
                    .collect()
            };
            let frames_as = |samples: &dyn Fn(Vec<u8>) -> Samples| -> Vec<Frame> {
                (0..n)
                    .map(|k| Frame { width: w as u32, height: h as u32, channels, samples: samples(values(k)) })
                    .collect()
            };
            let view = View {
                id: "v".into(),
                pose: crate::domain::optics::ViewPose { angle_deg: 0.0, axial_mm: 0.0, lens_radius_mm: 250.0 },
                frames: (0..n)
                    .map(|k| crate::domain::frame::FrameEntry { file: format!("{k}.png"), offset_mm: -0.75 + 0.25 * k as f64 })
                    .collect(),
                format: crate::domain::frame::FrameFormat { width: w as u32, height: h as u32, channels, bit_depth: 8 },
            };
            let depth_of = |frames: Vec<Frame>| {
                depth_from_focus(&optics, &view, &DepthOptions::default(), |k| Ok(frames[k].clone()), &|| false)
                    .unwrap()
                    .unwrap()
            };
            let eight = depth_of(frames_as(&Samples::Eight));
            let sixteen = depth_of(frames_as(&|v| Samples::Sixteen(v.iter().map(|&v| v as u16 * 257).collect())));
            let float = depth_of(frames_as(&|v| Samples::Float(v.iter().map(|&v| v as f32 / 255.0).collect())));
            assert!(eight.depth_mm.iter().any(|d| d.is_finite()), "some pixels are in focus");
            let bits = |m: &DepthMap| -> Vec<u32> {
                m.depth_mm.iter().chain(&m.peak_ratio).chain(&m.all_in_focus).map(|v| v.to_bits()).collect()
            };
            assert_eq!(bits(&eight), bits(&sixteen), "{channels} channels: 8 vs 16 bits");
            assert_eq!(bits(&eight), bits(&float), "{channels} channels: 8 bits vs f32");

            // Depth on every row and on every second or third row: the sparser maps are the full
            // map's rows 0, step, 2·step, … bit for bit (the focus measure still sees every row).
            let frames = frames_as(&Samples::Eight);
            let with_step = |row_step: usize| {
                let options = DepthOptions { row_step, ..DepthOptions::default() };
                depth_from_focus(&optics, &view, &options, |k| Ok(frames[k].clone()), &|| false).unwrap().unwrap()
            };
            let full = with_step(1);
            assert_eq!(full.rows(), h);
            for step in [2, 3] {
                let sparse = with_step(step);
                assert_eq!(
                    (sparse.width, sparse.height, sparse.row_step, sparse.rows()),
                    (w, h, step, h.div_ceil(step))
                );
                let rows_of = |m: &DepthMap, values: &[f32], per: usize| -> Vec<Vec<u32>> {
                    values.chunks_exact(per * m.width).map(|r| r.iter().map(|v| v.to_bits()).collect()).collect()
                };
                for (values_full, values_sparse, per) in [
                    (&full.depth_mm, &sparse.depth_mm, 1),
                    (&full.peak_ratio, &sparse.peak_ratio, 1),
                    (&full.all_in_focus, &sparse.all_in_focus, 3),
                ] {
                    let want: Vec<Vec<u32>> = rows_of(&full, values_full, per).into_iter().step_by(step).collect();
                    assert_eq!(rows_of(&sparse, values_sparse, per), want, "{channels} channels, step {step}");
                }
                assert!(sparse.depth_mm.iter().any(|d| d.is_finite()), "step {step}");
            }
        }
    }

    /// The all-in-focus colour of each pixel is its sharpest frame's, whether that frame is the
    /// first, one in the middle, the last, or the higher of two peaks. Frame k's gray level
    /// carries k (0.3 + 0.05·k) under a checkerboard whose contrast per column band peaks at
    /// the band's frame.
    #[test]
    fn all_in_focus_takes_each_pixel_from_its_sharpest_frame() {
        let (w, h, n) = (48usize, 20usize, 7usize);
        // Contrast of band b (12 columns each) in frame k.
        let contrast = |band: usize, k: usize| -> f32 {
            let peaks: [&[f32]; 4] = [
                &[1.0, 0.6, 0.3, 0.2, 0.1, 0.1, 0.1],
                &[0.1, 0.3, 0.6, 1.0, 0.6, 0.3, 0.1],
                &[0.1, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0],
                &[0.2, 0.7, 0.3, 0.2, 0.5, 0.9, 0.4],
            ];
            peaks[band][k]
        };
        let sharpest = [0usize, 3, 6, 5];
        let frames: Vec<Frame> = (0..n)
            .map(|k| Frame {
                width: w as u32,
                height: h as u32,
                channels: 1,
                samples: Samples::Float(
                    (0..w * h)
                        .map(|i| {
                            let (x, y) = (i % w, i / w);
                            let checker = if (x + y).is_multiple_of(2) { 1.0 } else { -1.0 };
                            0.3 + 0.05 * k as f32 + 0.1 * contrast(x / 12, k) * checker
                        })
                        .collect(),
                ),
            })
            .collect();
        let optics = Optics {
            projection: Projection::Telecentric,
            focal_length_mm: Some(50.0),
            f_number: 8.0,
            focus_distance_mm: 100.0,
            pixel_pitch_um: 10.0,
            principal_point_px: None,
            magnification: Some(0.5),
        };
        let view = View {
            id: "v".into(),
            pose: crate::domain::optics::ViewPose { angle_deg: 0.0, axial_mm: 0.0, lens_radius_mm: 150.0 },
            frames: (0..n)
                .map(|k| crate::domain::frame::FrameEntry { file: format!("{k}.png"), offset_mm: 0.25 * k as f64 })
                .collect(),
            format: crate::domain::frame::FrameFormat { width: w as u32, height: h as u32, channels: 1, bit_depth: 8 },
        };
        let map = depth_from_focus(&optics, &view, &DepthOptions::default(), |k| Ok(frames[k].clone()), &|| false)
            .unwrap()
            .unwrap();
        // Pixels clear of the band edges by more than the focus window, on the map's rows.
        assert_eq!(map.row_step, DepthOptions::default().row_step);
        for y in (5..h - 5).filter(|y| y.is_multiple_of(map.row_step)) {
            let i = (y / map.row_step) * w;
            for x in (0..w).filter(|&x| (6..=7).contains(&(x % 12)) || (1..4).contains(&x)) {
                let k = sharpest[x / 12];
                let expected = frames[k].samples.value(y * w + x);
                assert_eq!(&map.all_in_focus[3 * (i + x)..3 * (i + x) + 3], &[expected; 3], "({x}, {y})");
            }
        }
    }

    #[test]
    fn box_sum_matches_brute_force() {
        // A field several boxes wide, and frames narrower or shorter than one box (a bundle may
        // hold frames of a few pixels: they give no depth, and must not fail).
        for (w, h, r) in [(13, 9, 2), (3, 3, 5), (2, 160, 5), (384, 2, 5), (1, 1, 4), (7, 4, 5)] {
            let gray: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 11) as f32 / 11.0).collect();
            let mut scratch = vec![0f32; w * h];
            let mut out = vec![0f32; w * h];
            focus_measure(&gray, w, h, r, &mut scratch, &mut out);
            let lap = |x: usize, y: usize| {
                if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    return 0.0;
                }
                let i = y * w + x;
                let l = 4.0 * gray[i] - gray[i - 1] - gray[i + 1] - gray[i - w] - gray[i + w];
                l * l
            };
            for y in 0..h {
                for x in 0..w {
                    let mut s = 0.0;
                    for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                        for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                            s += lap(xx, yy);
                        }
                    }
                    assert!((out[y * w + x] - s).abs() < 1e-4, "{w}×{h} ({x},{y}) {} vs {s}", out[y * w + x]);
                }
            }
        }
        // The baseline and the AVX2 copy give the same measure, bit for bit (a frame-sized field,
        // with rows longer than the vector loops' blocks; the edge box's size, and both of the
        // big box's).
        let (w, h) = (203, 37);
        let gray: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 257) as f32 / 257.0).collect();
        let mut scratch = vec![0f32; w * h];
        let mut baseline = vec![0f32; w * h];
        for r in [1, 5, 4] {
            focus_measures_body::<false>(&gray, w, h, r, &mut scratch, &mut baseline, None);
            let mut dispatched = vec![0f32; w * h];
            focus_measure(&gray, w, h, r, &mut scratch, &mut dispatched);
            assert_eq!(dispatched, baseline, "r {r}");
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                let mut wide = vec![0f32; w * h];
                // SAFETY: the processor has AVX2 (checked just above).
                unsafe { focus_measures_avx2(&gray, w, h, r, &mut scratch, &mut wide, None) };
                assert_eq!(wide, baseline, "r {r}");
            }
        }
        let r = 4;
        // Both boxes from one Laplacian: each the same as its own measure, bit for bit.
        let (mut big, mut small, mut small_alone) = (vec![0f32; w * h], vec![0f32; w * h], vec![0f32; w * h]);
        focus_measures(&gray, w, h, r, &mut scratch, &mut big, Some((1, &mut small)));
        focus_measure(&gray, w, h, 1, &mut scratch, &mut small_alone);
        assert_eq!(big, baseline);
        assert_eq!(small, small_alone);
    }

    /// A depth map whose estimates carry an odd sub-frame bias (as the centroid's) over depths
    /// that fall at every phase: equalising the phases removes most of it.
    #[test]
    fn phase_equalisation_removes_an_odd_sub_frame_bias() {
        let (origin, step, big_f) = (-2.5, 0.25, 220.0);
        let (w, h) = (400, 100);
        let true_offset = |i: usize| -1.0 + 2.0 * ((i * 7919) % (w * h)) as f64 / (w * h) as f64;
        let bias = |o: f64| {
            let phase = ((o - origin) / step).rem_euclid(1.0);
            0.012 * (std::f64::consts::TAU * phase).sin()
        };
        let depth: Vec<f32> = (0..w * h).map(|i| (big_f - true_offset(i) - bias(true_offset(i))) as f32).collect();
        let map = DepthMap {
            width: w,
            height: h,
            row_step: 1,
            depth_mm: depth,
            peak_ratio: vec![5.0; w * h],
            all_in_focus: vec![0.5; 3 * w * h],
            end_edges: Vec::new(),
        };
        let worst = |maps: &[DepthMap]| {
            (0..w * h).map(|i| (maps[0].depth_mm[i] as f64 - (big_f - true_offset(i))).abs()).fold(0.0, f64::max)
        };
        let mut maps = vec![map.clone()];
        let before = worst(&maps);
        let grid = even_frame_grid(&(0..21).map(|k| origin + step * k as f64).collect::<Vec<_>>());
        assert_eq!(grid, Some((origin, step)));
        equalize_sub_frame_phase(&mut maps, &[grid], big_f);
        let after = worst(&maps);
        assert!(before > 0.011 && after < 0.002, "before {before}, after {after}");
        // A flat surface whose depths all sit within a third of a frame: not equalised.
        let flat: Vec<f32> = (0..w * h).map(|i| (big_f - 0.3 - 0.08 * (i % 97) as f64 / 97.0) as f32).collect();
        let flat_map = DepthMap { depth_mm: flat.clone(), ..map.clone() };
        let mut maps = vec![flat_map];
        equalize_sub_frame_phase(&mut maps, &[grid], big_f);
        assert_eq!(maps[0].depth_mm, flat);
        // A stack that is not on one even grid is left alone.
        let mut untouched = vec![map.clone()];
        let uneven = even_frame_grid(&[-1.0, -0.7, -0.5, 0.0]);
        assert_eq!(uneven, None);
        equalize_sub_frame_phase(&mut untouched, &[uneven], big_f);
        assert_eq!(untouched[0].depth_mm, map.depth_mm);
    }
}
