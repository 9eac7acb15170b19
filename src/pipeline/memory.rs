//! How much memory an inspection will take at its peak, estimated from the bundle's declared
//! sizes (the frames' headers, the optics, the poses) and the options, before any frame is
//! decoded. The service refuses at upload a bundle whose estimate exceeds its worker's budget,
//! and the worker checks again before it starts: an allocation the machine cannot give ends the
//! whole process, and would end it again at each re-claim.
//!
//! The model counts the buffers the stages hold at once: per view in
//! flight, the depth stage's focus volume (4 bytes a sample; 8 where the small box refines the
//! depth at flanks), its held frames (as decoded) and
//! about a dozen single-precision planes; per view, its depth map, confidence and colour until
//! fusion; the fused grid's cells with registration's view grids; the mesh. The coefficients are
//! upper bounds of what those stages allocate, checked against measured peaks
//! (`scripts/memory-check`; figures in docs/notebook/service.md).

use crate::domain::frame::Recording;
use crate::domain::station::surface_pixels;
use crate::pipeline::PipelineOptions;

/// Bytes the process holds before any stage (the binary, the runtime, the connection table,
/// allocator slack).
const BASE_BYTES: f64 = 64.0 * 1024.0 * 1024.0;
/// Single-precision planes of the depth stage's scratch and output per view in flight (gray,
/// native and box sums, best and best frame, the small box's three, the map, its ratio and the
/// all-in-focus colour).
const DEPTH_PLANES: f64 = 16.0;
/// Bytes a view keeps per pixel from depth to fusion (depth and confidence 4 each, colour 6 as
/// 16-bit fractions, its cloud).
const KEPT_BYTES_PER_VIEW_PIXEL: f64 = 18.0;
/// Bytes per fused-map cell over the stages that build grids over the surface (registration's
/// view grids, the fused map's accumulators and result, the height map and images).
const BYTES_PER_SURFACE_CELL: f64 = 64.0;
/// Bytes per mesh vertex (its position, colour and triangles, and the triangulation's own).
const BYTES_PER_MESH_VERTEX: f64 = 160.0;

/// The estimate, with the term that dominates it (named as the bundle field that makes it large).
#[derive(Clone, Debug, PartialEq)]
pub struct MemoryEstimate {
    pub peak_bytes: f64,
    /// (term, bytes), largest first: `depth` (the views' focal stacks in flight), `views` (all
    /// views' maps), `surface` (the grids over the covered surface), `mesh`.
    pub terms: Vec<(&'static str, f64)>,
}

impl MemoryEstimate {
    pub fn peak_mib(&self) -> f64 {
        self.peak_bytes / (1024.0 * 1024.0)
    }

    /// The bundle or option field behind the largest term.
    pub fn culprit(&self) -> &'static str {
        match self.terms.first().map(|t| t.0) {
            Some("depth") => "views[].frames",
            Some("views") => "views",
            Some("surface") => "optics.pixel_pitch_um",
            Some("mesh") => "pipeline.mesh.max_vertices",
            _ => "views",
        }
    }
}

/// The peak memory of inspecting `recording` with `options` on `threads` compute threads.
pub fn estimate(recording: &dyn Recording, options: &PipelineOptions, threads: usize) -> MemoryEstimate {
    let views = recording.views();
    let pixels = |v: &crate::domain::frame::View| v.format.width as f64 * v.format.height as f64;
    // Each thread holds one view's stack at a time; the largest views bound what is in flight.
    // Where the small box refines the depth at flanks, its measure is a second focus volume.
    let depth_options = options.depth.for_part(&recording.part().form, recording.optics());
    let volume_bytes = if depth_options.refine_now { 8.0 } else { 4.0 };
    let mut stacks: Vec<f64> = views
        .iter()
        .map(|v| {
            let frames = v.frames.len() as f64;
            let sample_bytes = v.format.channels as f64 * (v.format.bit_depth as f64 / 8.0).ceil();
            frames * pixels(v) * (volume_bytes + sample_bytes) + DEPTH_PLANES * 4.0 * pixels(v)
        })
        .collect();
    stacks.sort_by(|a, b| b.total_cmp(a));
    let depth: f64 = stacks.iter().take(threads.max(1)).sum();
    let view_bytes: f64 = views.iter().map(pixels).sum::<f64>() * KEPT_BYTES_PER_VIEW_PIXEL;
    let band = surface_pixels(recording.optics(), views, recording.part().circumference_mm());
    let pixel_mm = recording.optics().object_pixel_mm(recording.optics().focus_distance_mm);
    let cell_px = options.cell_mm(pixel_mm, &recording.part().form) / pixel_mm;
    let cells = band.pixels / (cell_px * cell_px);
    let surface = cells * BYTES_PER_SURFACE_CELL;
    let mesh_vertices = (options.mesh.max_vertices as f64).min(cells);
    let mesh = mesh_vertices * BYTES_PER_MESH_VERTEX;
    let mut terms = vec![("depth", depth), ("views", view_bytes), ("surface", surface), ("mesh", mesh)];
    terms.sort_by(|a, b| b.1.total_cmp(&a.1));
    // The depth stage's stacks are gone before the grids are built, but the views' maps are held
    // across both: the peak is the larger of the two phases.
    let peak = BASE_BYTES + view_bytes + depth.max(surface + mesh);
    MemoryEstimate { peak_bytes: peak, terms }
}
