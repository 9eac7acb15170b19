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
//! The first frame's pixel noise is read ([`noise`]) for the report and the envelope, and, as an
//! option, decides a Gaussian pre-filter for noisy views.

pub mod cnn;
pub mod estimator;
pub mod measure;
pub mod noise;
mod peak;
mod phase;
mod resample;
mod silhouette;
mod speckle;

pub use cnn::cnn_depth;
pub use peak::peak_offset;
pub use phase::{equalize_sub_frame_phase, even_frame_grid};
pub use silhouette::{FrameEdge, frame_edge};
pub use speckle::drop_speckles;

use crate::domain::frame::{Frame, FrameError, View};
use crate::domain::optics::{Optics, Projection};
use crate::domain::thread::{ProfileShape, ThreadForm};
use measure::focus_measures;
use peak::{MedianNetwork, Ties, keep_sharpest, own_peak};
use rayon::prelude::*;
use resample::{HeldFrame, Taps, axis_taps, resample_row, tap_spans};
use serde::{Deserialize, Serialize};

/// Which depth estimate a run reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthMethod {
    /// Depth from focus by the focus measure's peak ([`depth_from_focus`]).
    #[default]
    Classic,
    /// The seed's defocus and depth U-Nets ([`cnn_depth`]) at the pixels the classical stage
    /// trusts (docs/models.md).
    Cnn,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthOptions {
    /// Classical depth from focus or the U-Nets (options stored before this existed load as
    /// classic).
    #[serde(default)]
    pub method: DepthMethod,
    /// The depth model (`method: cnn`): a shipped one or one installed in the models folder; none:
    /// the shipped `depth-unet`.
    #[serde(default)]
    pub model: Option<String>,
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
    /// (docs/notebook/accuracy.md, "Depth on every second row"): the default is every row.
    #[serde(default = "row_step")]
    pub row_step: usize,
    /// Half size of a second, small box that decides which surface a pixel at a steep edge shows
    /// (0: none). Within a big box's half size of a crest's steep flank the box holds both the
    /// crest and the root, a thread's height apart, and the focus curve peaks at both; the side
    /// whose texture is stronger there wins, which moves the edge by up to the half size toward
    /// the weaker side. Under chaser marks, which shade every crest alike, that moved every edge
    /// of a part the same way (docs/notebook/accuracy.md, "Absolute z"). Where the small
    /// box's sharpest frame is
    /// [`EDGE_MIN_SEPARATION_FRAMES`] or more from the big box's, and the big curve has a peak of
    /// its own there, that peak is the pixel's.
    #[serde(default = "edge_window_radius_px")]
    pub edge_window_radius_px: usize,
    /// Drop speckles ([`drop_speckles`]): regions smaller than `speckle_min_windows` focus windows
    /// whose depths, linked within half the depth of field, do not join their surroundings, in
    /// maps where such regions are common ([`speckle::MIN_SPECKLE_SHARE`]).
    #[serde(default = "yes")]
    pub drop_speckles: bool,
    /// The least area of a region that is kept, in focus windows ((2r + 1)² pixels each).
    #[serde(default = "speckle_min_windows")]
    pub speckle_min_windows: f64,
    /// Standard deviation, pixels, of the Gaussian pre-filter the focus measure takes in views
    /// whose frames are noisy ([`noise`]; 0: never). Options stored before this existed load with
    /// the default.
    #[serde(default = "prefilter_sigma_px")]
    pub prefilter_sigma_px: f64,
    /// The frames' noise, relative to their mean brightness ([`noise::relative_noise`], read on
    /// each view's first frame), above which the pre-filter runs (0: always).
    #[serde(default = "prefilter_min_noise")]
    pub prefilter_min_noise: f64,
    /// The largest object pixel, mm, at which the pre-filter runs (0: any). Options stored before
    /// this existed load with the default.
    #[serde(default = "prefilter_max_pixel_mm")]
    pub prefilter_max_pixel_mm: f64,
    /// Where the focus box reaches across a flank from the part of a crest or root the profile
    /// reads ([`box_reaches_across_flanks`], from the form and the optics), each pixel's depth is
    /// located on the small edge box's curve ([`DepthOptions::edge_window_radius_px`]) about the
    /// big box's peak, when that curve is itself trusted ([`DepthOptions::min_peak_ratio`]) and the
    /// two lie within a frame step of each other. The big box's
    /// curve then sums the other surface's texture, which moves its shoulders: at 0.12 mm pixels
    /// a buttress read 48 µm too tall, a round thread 50–59 µm too short
    /// (docs/notebook/accuracy.md, "The error budget"). The big box still finds the peak, so the
    /// small box's noise cannot move a pixel to another surface. [`DepthOptions::for_part`] turns
    /// it off where the box stays on the flat.
    #[serde(default = "yes")]
    pub refine_across_flanks: bool,
    /// Whether this run refines: `refine_across_flanks` where [`DepthOptions::for_part`] found
    /// the box reaching across a flank at the bundle's optics; false in options not resolved for
    /// a part. Not an option of its own.
    #[serde(skip)]
    pub refine_now: bool,
}

fn prefilter_sigma_px() -> f64 {
    DepthOptions::default().prefilter_sigma_px
}

fn prefilter_min_noise() -> f64 {
    DepthOptions::default().prefilter_min_noise
}

fn prefilter_max_pixel_mm() -> f64 {
    DepthOptions::default().prefilter_max_pixel_mm
}

fn speckle_min_windows() -> f64 {
    DepthOptions::default().speckle_min_windows
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
            method: DepthMethod::Classic,
            model: None,
            window_radius_px: 4,
            flat_window_radius_px: 5,
            min_peak_ratio: 1.6,
            peak_fraction: 0.3,
            equalize_phase: true,
            row_step: 1,
            edge_window_radius_px: 1,
            drop_speckles: true,
            speckle_min_windows: 0.25,
            // σ 0.7 px above 1.5% noise was chosen on the tuning stations; the station suite (which
            // had chosen nothing) showed it helping at object pixels up to 0.08 mm and hurting above,
            // and the bound was checked on stations 141–150, rendered after it was set
            // (docs/notebook/accuracy.md, "Stations: noisy frames"). The standard station's frames
            // read 0.65–0.84%: it never runs there.
            prefilter_sigma_px: 0.7,
            prefilter_min_noise: 0.015,
            prefilter_max_pixel_mm: 0.08,
            refine_across_flanks: true,
            refine_now: false,
        }
    }
}

/// Whether a focus box of `window_radius_px` reaches from the part of a crest or root the profile
/// reads ([`crate::domain::thread::READ_SHARE_OF_FLAT`] of its own section) across the flank: its
/// half size on the part, plus the blur radius at which the other surface (a thread height away)
/// is imaged, exceeds the section's unread margin.
pub fn box_reaches_across_flanks(form: &ThreadForm, optics: &Optics, window_radius_px: usize) -> bool {
    let pixel_mm = optics.object_pixel_mm(optics.focus_distance_mm);
    let box_half_mm = window_radius_px as f64 * pixel_mm;
    let blur_half_mm = 0.5 * optics.coc_px(optics.focus_distance_mm + form.height_mm) * pixel_mm;
    let ((crest, root), (crest_read, root_read)) = (form.flat_half_widths_mm(), form.window_half_widths_mm());
    let margin_mm = (crest - crest_read).min(root - root_read);
    box_half_mm + blur_half_mm > margin_mm
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

    /// [`DepthOptions::for_form`], with [`DepthOptions::refine_across_flanks`] kept only where the
    /// box reaches across a flank at these optics, there is a small box to refine with, and the
    /// object pixel is coarser than the fine class's
    /// ([`crate::domain::station::FINE_MAX_PIXEL_MM`]). At fine pixels the windows hold many
    /// pixels and the big box's shift is a few micrometres: there the small box's noise cost more
    /// than it removed (the standard station's round thread read 6.1 → 8.0 µm RMS;
    /// docs/notebook/accuracy.md, "The error budget").
    pub fn for_part(&self, form: &ThreadForm, optics: &Optics) -> Self {
        let mut options = self.for_form(form);
        let coarse = optics.object_pixel_mm(optics.focus_distance_mm) > crate::domain::station::FINE_MAX_PIXEL_MM;
        options.refine_now = options.refine_across_flanks
            && options.edge_window_radius_px > 0
            && coarse
            && box_reaches_across_flanks(form, optics, options.window_radius_px);
        options
    }
}

/// A colour in [0, 1] as 16-bit fractions of full scale (rounded; out of range clamped).
#[inline]
pub fn unorm16(rgb: [f32; 3]) -> [u16; 3] {
    rgb.map(|v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16)
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
    /// Sharpest colour per pixel, RGB interleaved, each a 16-bit fraction of full scale
    /// ([`unorm16`]; [`DepthMap::colour`] reads it back): half the memory of f32 for every view
    /// held until fusion, with steps 257 times finer than an 8-bit frame's.
    pub all_in_focus: Vec<u16>,
    /// The end face's silhouette in each frame that shows it (for [`crate::pipeline::register::anchor`]).
    pub end_edges: Vec<FrameEdge>,
    /// The first frame's noise relative to its mean brightness ([`noise::relative_noise`]).
    pub frame_noise: Option<f64>,
    /// Whether the focus measure took the Gaussian pre-filter ([`DepthOptions::prefilter_sigma_px`]).
    pub prefiltered: bool,
}

impl DepthMap {
    /// Rows of the map: the pixel rows 0, `row_step`, 2·`row_step`, … below `height`.
    pub fn rows(&self) -> usize {
        self.height.div_ceil(self.row_step.max(1))
    }

    /// Pixel i's all-in-focus colour, RGB in [0, 1].
    #[inline]
    pub fn colour(&self, i: usize) -> [f32; 3] {
        let c = &self.all_in_focus[3 * i..3 * i + 3];
        [c[0], c[1], c[2]].map(|v| v as f32 / 65535.0)
    }

    pub fn coverage(&self) -> f64 {
        self.depth_mm.iter().filter(|d| d.is_finite()).count() as f64 / self.depth_mm.len() as f64
    }
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
    /// The small box's measure per frame, as `volume` ([`DepthOptions::refine_across_flanks`]).
    edge_volume: Vec<f32>,
    /// The pre-filtered frame and the blur's intermediate ([`noise::blur`]).
    filtered: Vec<f32>,
    filter_scratch: Vec<f32>,
    /// Whether [`depth_from_focus_in`] leaves the view's decoded frames in `kept_frames` for a
    /// second reader ([`estimator::Cnn`]) rather than dropping them.
    pub(super) keep_frames: bool,
    pub(super) kept_frames: Vec<Option<Frame>>,
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
        edge_volume,
        filtered,
        filter_scratch,
        keep_frames,
        kept_frames,
    } = buffers;
    let edge_radius = options.edge_window_radius_px;
    let edge_aware = edge_radius > 0;
    let refine = edge_aware && options.refine_now;
    if edge_aware {
        native_edge.resize(w * h, 0.0);
        refill(best_edge, plane, f32::MIN);
        refill(best_edge_frame, plane, 0u32);
        edge_row.resize(w, 0.0);
    }
    // Every cell is written before it is read (each frame fills its whole plane).
    volume.resize(plane * n, 0.0);
    if refine {
        edge_volume.resize(plane * n, 0.0);
    }
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
    // Decided on the first frame, for the whole stack: a pixel's focus curve needs one measure.
    let (mut frame_noise, mut prefilter) = (None, None::<Vec<f32>>);
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
        if k == 0 {
            frame_noise = noise::relative_noise(gray, w, h);
            let noisy = frame_noise.is_some_and(|n| n > options.prefilter_min_noise);
            let bound = options.prefilter_max_pixel_mm;
            let fine_pixels = bound <= 0.0 || optics.object_pixel_mm(big_f) <= bound;
            let wanted = noisy && fine_pixels && options.prefilter_sigma_px > 0.0;
            prefilter = wanted.then(|| noise::gaussian_taps(options.prefilter_sigma_px));
        }
        let measured: &[f32] = match &prefilter {
            Some(taps) => {
                noise::blur(gray, w, h, taps, filter_scratch, filtered);
                &filtered[..]
            }
            None => &gray[..],
        };
        let edge = edge_aware.then_some((edge_radius, &mut native_edge[..]));
        focus_measures(measured, w, h, options.window_radius_px, scratch, native, edge);
        end_edges.extend(frame_edge(gray, w, h, entry.offset_mm));
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
                let edge_measures = if refine {
                    &mut edge_volume[k * plane + r * w..k * plane + (r + 1) * w]
                } else {
                    &mut edge_row[..]
                };
                resample_row(above, below, fy, &taps.xs, &spans, &fxs, edge_measures);
                let rows = r * w..(r + 1) * w;
                keep_sharpest(
                    edge_measures,
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
    let mut all_in_focus = vec![0u16; plane * 3];
    let volume: &[f32] = volume;
    let edge_volume: &[f32] = edge_volume;
    // The frame step: how far the small box's depth may lie from the big box's (its peak is
    // looked for within a frame of the big box's).
    let step_mm = {
        let mut steps: Vec<f64> = offsets.windows(2).map(|p| (p[1] - p[0]).abs()).collect();
        crate::numeric::stats::median(&mut steps).unwrap_or(0.0)
    };
    let (best_frame, best_edge_frame): (&[u32], &[u32]) = (best_frame, best_edge_frame);
    let held_frames = &held;
    // Per row: the n frames' rows (each one contiguous run of the frame-major volume) give the
    // maximum and, copied out, the median for all of the row's pixels at once; only trusted
    // pixels' curves are walked one by one.
    let init = || (vec![0f32; n * w], vec![0f32; w], vec![0u32; w], vec![0f32; n], vec![0f32; n], vec![0f32; n]);
    depth_mm
        .par_chunks_mut(w)
        .zip(peak_ratio.par_chunks_mut(w))
        .zip(all_in_focus.par_chunks_mut(3 * w))
        .enumerate()
        .for_each_init(
            init,
            |(sorted, peak, k_best, column, small, small_sorted), (r, ((depth_row, ratio_row), colour_row))| {
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
                    colour.copy_from_slice(&held_frames[best_frame[r * w + x] as usize].colour16_at(x, y, w));
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
                            // surface's frame: the big box's colour mixes two surfaces into
                            // registration's texture (docs/notebook/accuracy.md, The depth stage's
                            // edge box).
                            colour_row[3 * x..3 * x + 3].copy_from_slice(&held_frames[k_edge].colour16_at(x, y, w));
                            k_best = own;
                        }
                    }
                    let Some(mut in_focus_offset) = peak_offset(column, &offsets, k_best, floor, options.peak_fraction)
                    else {
                        continue;
                    };
                    if refine {
                        for (k, c) in small.iter_mut().enumerate() {
                            *c = edge_volume[k * plane + r * w + x];
                        }
                        if let Some(o) = small_box_offset(
                            small,
                            small_sorted,
                            &offsets,
                            k_best,
                            options.min_peak_ratio,
                            options.peak_fraction,
                        )
                        .filter(|o| (o - in_focus_offset).abs() <= step_mm)
                        {
                            in_focus_offset = o;
                        }
                    }
                    depth_row[x] = (big_f - in_focus_offset) as f32;
                }
            },
        );
    kept_frames.clear();
    if *keep_frames {
        kept_frames.extend(held.into_iter().map(|h| Some(h.frame)));
    }
    let mut map = DepthMap {
        width: w,
        height: h,
        row_step: step,
        depth_mm,
        peak_ratio,
        all_in_focus,
        end_edges,
        frame_noise,
        prefiltered: prefilter.is_some(),
    };
    if options.drop_speckles {
        let link_mm = 0.5 * optics.depth_of_field_mm(crate::domain::station::IN_FOCUS_BLUR_PX);
        let window = (2 * options.window_radius_px + 1) as f64;
        let min_pixels = (options.speckle_min_windows * window * window / step as f64).ceil() as usize;
        drop_speckles(&mut map, link_mm as f32, min_pixels);
    }
    Ok(Some(map))
}

/// The in-focus offset on the small box's curve `small` about the big box's peak `k_best`: its
/// highest frame within one of `k_best` (inside the stack), located by [`peak_offset`] over its own
/// floor (the curve's median); None unless that frame rises `min_peak_ratio` over the floor, the
/// rule a pixel's own curve is trusted by. `sorted` is scratch of the curve's length.
fn small_box_offset(
    small: &[f32],
    sorted: &mut [f32],
    offsets: &[f64],
    k_best: usize,
    min_peak_ratio: f32,
    fraction: f32,
) -> Option<f64> {
    let n = small.len();
    if n < 3 {
        return None;
    }
    let (lo, hi) = (k_best.saturating_sub(1).max(1), (k_best + 1).min(n - 2));
    let k = (lo..=hi).fold(lo, |m, k| if small[k] > small[m] { k } else { m });
    sorted.copy_from_slice(small);
    let floor = *sorted.select_nth_unstable_by(n / 2, f32::total_cmp).1;
    (small[k] >= min_peak_ratio * floor.max(1e-12)).then(|| peak_offset(small, offsets, k, floor, fraction)).flatten()
}

#[cfg(test)]
mod tests;
