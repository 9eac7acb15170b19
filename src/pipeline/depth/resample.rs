//! Bringing each frame's focus measure and colour onto the offset-0 grid: bilinear taps per axis
//! (the focus breathing scale is separable), applied row by row.

use crate::domain::frame::{Frame, SampleValue, Samples};

/// Bilinear taps along one axis: where reference index i of the offset-0 grid falls in a frame
/// scaled by `scale` about `centre` (the scale is separable, so rows and columns are computed once
/// per frame): (i0, i1, fraction).
pub(super) fn axis_taps(len: usize, centre: f64, scale: f64) -> Vec<(usize, usize, f32)> {
    (0..len)
        .map(|i| {
            let s = centre + (i as f64 + 0.5 - centre) * scale - 0.5;
            let i0 = (s.floor() as isize).clamp(0, len as isize - 1) as usize;
            (i0, (i0 + 1).min(len - 1), (s - i0 as f64).clamp(0.0, 1.0) as f32)
        })
        .collect()
}

/// A frame's bilinear taps onto the offset-0 grid, columns and rows ([`axis_taps`]).
pub(super) struct Taps {
    pub(super) xs: Vec<(usize, usize, f32)>,
    pub(super) ys: Vec<(usize, usize, f32)>,
}

/// A decoded frame held until its view's colours are taken, with its taps.
pub(super) struct HeldFrame {
    pub(super) frame: Frame,
    pub(super) taps: Taps,
}

impl HeldFrame {
    /// The frame's colour (RGB; a gray frame's value thrice) at reference pixel `x` of pixel row
    /// `y` of the offset-0 grid.
    #[inline]
    pub(super) fn colour_at(&self, x: usize, y: usize, w: usize, out: &mut [f32]) {
        let corners = (self.taps.xs[x], self.taps.ys[y]);
        match &self.frame.samples {
            Samples::Eight(samples) => mix_corners(samples, self.frame.channels, w, corners, out),
            Samples::Sixteen(samples) => mix_corners(samples, self.frame.channels, w, corners, out),
            Samples::Float(samples) => mix_corners(samples, self.frame.channels, w, corners, out),
        }
    }

    /// [`HeldFrame::colour_at`] as a depth map holds it ([`super::unorm16`]).
    #[inline]
    pub(super) fn colour16_at(&self, x: usize, y: usize, w: usize) -> [u16; 3] {
        let mut rgb = [0f32; 3];
        self.colour_at(x, y, w, &mut rgb);
        super::unorm16(rgb)
    }
}

/// Bilinear interpolation between four values: `fx` of the way from the 0 to the 1 column, `fy`
/// from the 0 to the 1 row (along the columns first: every resampling here rounds the same way).
#[inline]
pub(super) fn bilinear(p00: f32, p01: f32, p10: f32, p11: f32, fx: f32, fy: f32) -> f32 {
    let a = p00 * (1.0 - fx) + p01 * fx;
    let b = p10 * (1.0 - fx) + p11 * fx;
    a * (1.0 - fy) + b * fy
}

/// The four corners' values of one pixel, mixed per channel (a gray frame's value thrice).
#[inline]
pub(super) fn mix_corners<T: SampleValue>(
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
pub(super) struct TapSpan {
    start: usize,
    pub(super) len: usize,
    x0: usize,
    shifted: bool,
}

/// Splits a row's taps into [`TapSpan`]s: the scale is within a few percent of 1, so the offset
/// between a column and its first tap changes only a few times across a row.
pub(super) fn tap_spans(taps: &[(usize, usize, f32)]) -> Vec<TapSpan> {
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
pub(super) fn resample_row(
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
