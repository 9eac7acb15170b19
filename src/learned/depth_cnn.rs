//! The seed's defocus and depth U-Nets, one graph (training/depth_cnn.py): a view's frames on the
//! offset-0 pixel grid in (`frames` [n, 3, H, W], RGB in [0, 1]) with the linear weights of
//! [`PLANES`] fixed planes on them (`planes` [PLANES, n], [`plane_matrix`]); each pixel's in-focus
//! plane out (`plane`, a soft argmax in plane units) with its peak probability (`confidence`).
//!
//! Frames of any size run in tiles of at most [`TILE_PX`] a side, each with a [`MARGIN_PX`] border
//! of context that is thrown away (edge pixels repeated where a tile runs off the frame), so
//! memory per run is bounded by the stack's length, not the frame's size.

use super::{LearnedError, Model};
use ort::value::Tensor;
use std::ops::Range;

/// Planes the stack is resampled onto (the depth U-Net's channels).
pub const PLANES: usize = 16;

/// The U-Net pools four times: tile sides are multiples of this.
const MULTIPLE: usize = 16;

/// A tile's side at most, and the context kept around its core on each side.
pub const TILE_PX: usize = 512;
pub const MARGIN_PX: usize = 32;

/// [PLANES × n]: plane j sits at offset lo + (hi − lo)·j/(PLANES − 1) over the stack's offsets,
/// and takes the two frames around it by linear weights (as training/depth_cnn.py's
/// `plane_matrix`).
pub fn plane_matrix(offsets_mm: &[f64]) -> Vec<f32> {
    let n = offsets_mm.len();
    let mut m = vec![0f32; PLANES * n];
    if n < 2 {
        return m;
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| offsets_mm[a].total_cmp(&offsets_mm[b]));
    let sorted: Vec<f64> = order.iter().map(|&i| offsets_mm[i]).collect();
    let (lo, hi) = (sorted[0], sorted[n - 1]);
    for j in 0..PLANES {
        let p = lo + (hi - lo) * j as f64 / (PLANES - 1) as f64;
        // The last frame at or below p, kept off the stack's last frame.
        let k = sorted.partition_point(|&o| o <= p).saturating_sub(1).min(n - 2);
        let span = sorted[k + 1] - sorted[k];
        let f = if span <= 0.0 { 0.0 } else { ((p - sorted[k]) / span).clamp(0.0, 1.0) };
        m[j * n + order[k]] += (1.0 - f) as f32;
        m[j * n + order[k + 1]] += f as f32;
    }
    m
}

/// The in-focus plane and the confidence of every pixel of a frame.
pub struct PlaneMap {
    pub plane: Vec<f32>,
    pub confidence: Vec<f32>,
}

/// One axis's tile: input indices `origin..origin + size` (clamped into the frame) and the
/// frame's indices `keep` whose output it gives.
#[derive(Clone, Debug, PartialEq)]
struct Span {
    origin: isize,
    size: usize,
    keep: Range<usize>,
}

fn axis_spans(len: usize) -> Vec<Span> {
    if len <= TILE_PX {
        return vec![Span { origin: 0, size: len.next_multiple_of(MULTIPLE), keep: 0..len }];
    }
    let core = TILE_PX - 2 * MARGIN_PX;
    (0..len)
        .step_by(core)
        .map(|k0| Span { origin: k0 as isize - MARGIN_PX as isize, size: TILE_PX, keep: k0..(k0 + core).min(len) })
        .collect()
}

/// Runs the graph on one tile: `frames` [n, 3, h, w] in [0, 1], `planes` [PLANES, n].
pub fn run_tile(
    model: &Model,
    frames: Vec<f32>,
    n: usize,
    h: usize,
    w: usize,
    planes: &[f32],
) -> Result<PlaneMap, LearnedError> {
    model.pool.with(|session| {
        let frames = Tensor::from_array(([n, 3, h, w], frames))?;
        let planes = Tensor::from_array(([PLANES, n], planes.to_vec()))?;
        let outputs = session.run(ort::inputs!["frames" => frames, "planes" => planes])?;
        let take = |name: &str| -> Result<Vec<f32>, ort::Error> {
            let (shape, values) = outputs[name].try_extract_tensor::<f32>()?;
            if shape.iter().product::<i64>() as usize != h * w {
                return Err(ort::Error::new(format!("{name}: shape {shape:?} for a {w}×{h} tile")));
            }
            Ok(values.to_vec())
        };
        Ok(PlaneMap { plane: take("plane")?, confidence: take("confidence")? })
    })
}

/// The plane map of a whole view. `stack` holds the n frames on the offset-0 grid, planar
/// [n, 3, height, width], as 16-bit fractions of full scale (half an f32 stack's memory).
pub fn infer(
    model: &Model,
    stack: &[u16],
    n: usize,
    width: usize,
    height: usize,
    offsets_mm: &[f64],
    cancelled: &dyn Fn() -> bool,
) -> Result<Option<PlaneMap>, LearnedError> {
    assert_eq!(stack.len(), n * 3 * width * height, "a whole stack");
    let planes = plane_matrix(offsets_mm);
    let mut out = PlaneMap { plane: vec![f32::NAN; width * height], confidence: vec![0.0; width * height] };
    let (xs, ys) = (axis_spans(width), axis_spans(height));
    let mut tile = Vec::new();
    for ty in &ys {
        for tx in &xs {
            if cancelled() {
                return Ok(None);
            }
            let (tw, th) = (tx.size, ty.size);
            let clamp = |o: isize, i: usize, len: usize| (o + i as isize).clamp(0, len as isize - 1) as usize;
            let cols: Vec<usize> = (0..tw).map(|i| clamp(tx.origin, i, width)).collect();
            tile.clear();
            tile.reserve(n * 3 * th * tw);
            for channel in stack.chunks_exact(width * height) {
                for i in 0..th {
                    let row = &channel[clamp(ty.origin, i, height) * width..][..width];
                    tile.extend(cols.iter().map(|&x| row[x] as f32 / 65535.0));
                }
            }
            let got = run_tile(model, std::mem::take(&mut tile), n, th, tw, &planes)?;
            for y in ty.keep.clone() {
                let ty_i = (y as isize - ty.origin) as usize;
                for x in tx.keep.clone() {
                    let tx_i = (x as isize - tx.origin) as usize;
                    out.plane[y * width + x] = got.plane[ty_i * tw + tx_i];
                    out.confidence[y * width + x] = got.confidence[ty_i * tw + tx_i];
                }
            }
        }
    }
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_plane_weighs_the_frames_around_it_and_sums_to_one() {
        // Frames listed out of order, unevenly spaced.
        let offsets = [0.5, -0.5, 0.0, 0.25];
        let m = plane_matrix(&offsets);
        for j in 0..PLANES {
            let row = &m[j * 4..(j + 1) * 4];
            assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-6, "plane {j}: {row:?}");
            let at: f64 = row.iter().zip(&offsets).map(|(w, o)| *w as f64 * o).sum();
            let want = -0.5 + j as f64 / (PLANES - 1) as f64;
            assert!((at - want).abs() < 1e-6, "plane {j} at {at}, want {want}");
        }
        // The first plane is the nearest frame alone, the last the farthest.
        assert_eq!(m[1], 1.0);
        assert_eq!(m[(PLANES - 1) * 4], 1.0);
    }

    #[test]
    fn tiles_cover_every_index_once_with_context_around() {
        for len in [1, 15, 16, 200, 512, 513, 900, 1400, 3001] {
            let spans = axis_spans(len);
            let mut seen = vec![0; len];
            for s in &spans {
                assert_eq!(s.size % MULTIPLE, 0);
                assert!(s.size <= TILE_PX);
                for i in s.keep.clone() {
                    seen[i] += 1;
                    let inside = i as isize - s.origin;
                    assert!(inside >= 0 && (inside as usize) < s.size);
                    if spans.len() > 1 {
                        // Context on both sides, or the frame's edge.
                        assert!(inside as usize >= MARGIN_PX.min(i));
                        assert!(s.size - inside as usize > MARGIN_PX.min(len - 1 - i));
                    }
                }
            }
            assert!(seen.iter().all(|&c| c == 1), "len {len}");
        }
    }
}
