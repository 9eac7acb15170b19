//! Depth by the seed's U-Nets ([`crate::learned::depth_cnn`]): the view's frames brought onto the
//! offset-0 grid with the same bilinear taps the focus measure takes (focus breathing), then each
//! pixel's in-focus plane turned into depth through the optics. The classical map decides which
//! pixels are trusted (texture, saturation, the frame's border, speckles) and keeps its colours and
//! end-face silhouettes: the nets replace depth values, not the judgement of where depth exists,
//! so the two methods are compared on the same pixels.

use super::DepthMap;
use super::resample::{HeldFrame, Taps, axis_taps};
use crate::domain::frame::{Frame, FrameError, View};
use crate::domain::optics::{Optics, Projection};
use crate::learned::{LearnedError, Model, depth_cnn};

#[derive(Debug, thiserror::Error)]
pub enum CnnDepthError {
    #[error(transparent)]
    Frame(#[from] FrameError),
    #[error(transparent)]
    Learned(#[from] LearnedError),
}

/// Replaces `map`'s trusted depths (those finite) with the nets' over the view's stack;
/// `frame_at(k)` decodes frame k. Ok(false): cancelled.
pub fn cnn_depth(
    model: &Model,
    optics: &Optics,
    view: &View,
    mut frame_at: impl FnMut(usize) -> Result<Frame, FrameError>,
    cancelled: &dyn Fn() -> bool,
    map: &mut DepthMap,
) -> Result<bool, CnnDepthError> {
    let (w, h) = (view.format.width as usize, view.format.height as usize);
    let n = view.frames.len();
    let principal = optics.principal_point(view.format.width, view.format.height);
    let big_f = optics.focus_distance_mm;
    // Planar [n, 3, h, w], 16-bit: a 2 Mpx frame of 44 is 530 MB as f32 RGB, half of it so.
    let mut stack = vec![0u16; n * 3 * w * h];
    let mut rgb = [0f32; 3];
    for (k, entry) in view.frames.iter().enumerate() {
        if cancelled() {
            return Ok(false);
        }
        let scale = match optics.projection {
            Projection::Perspective => (big_f - entry.offset_mm) / big_f,
            Projection::Telecentric => 1.0,
        };
        let taps = Taps { xs: axis_taps(w, principal[0], scale), ys: axis_taps(h, principal[1], scale) };
        let held = HeldFrame { frame: frame_at(k)?, taps };
        let planes = &mut stack[k * 3 * w * h..(k + 1) * 3 * w * h];
        for y in 0..h {
            for x in 0..w {
                held.colour_at(x, y, w, &mut rgb);
                for (c, v) in rgb.iter().enumerate() {
                    planes[c * w * h + y * w + x] = (v.clamp(0.0, 1.0) * 65535.0).round() as u16;
                }
            }
        }
    }
    let offsets: Vec<f64> = view.frames.iter().map(|f| f.offset_mm).collect();
    let Some(planes) = depth_cnn::infer(model, &stack, n, w, h, &offsets, cancelled)? else { return Ok(false) };
    let (lo, hi) = offsets.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &o| (a.min(o), b.max(o)));
    let step_mm = (hi - lo) / (depth_cnn::PLANES - 1) as f64;
    let row_step = map.row_step.max(1);
    for (r, row) in map.depth_mm.chunks_exact_mut(w).enumerate() {
        let y = r * row_step;
        for (x, depth) in row.iter_mut().enumerate() {
            let plane = planes.plane[y * w + x];
            if depth.is_finite() && plane.is_finite() {
                *depth = (big_f - (lo + plane as f64 * step_mm)) as f32;
            }
        }
    }
    Ok(true)
}
