//! Registration: refines every view's pose (the fixture's three axes: angle about the pipe axis,
//! axial position, lens radius) from the overlaps with its neighbours, with global consistency.
//!
//! The thread surface is a helix, invariant under a screw motion, so geometry alone cannot fix how
//! two overlapping views slide along the helix. The surface texture (mill-scale grain, chaser marks,
//! albedo variation) is tied to the part and breaks that symmetry: each overlapping pair is aligned
//! by normalised cross-correlation of the high-passed all-in-focus brightness in the unrolled
//! (arc, z) plane (each view binned once, on one lattice for the ring: [`Lattice`]), coarse to fine
//! with sub-cell peak interpolation; the radial offset is the median
//! radius difference over the aligned overlap. All pair measurements then enter a pose graph (one
//! least-squares problem per axis over the whole ring, Huber-reweighted, the mean correction fixed
//! at zero since the encoders' mean error is), so no error accumulates around the circumference.
//! The radial axis is solved first: a lens-radius error also moves a view's points along the arc
//! away from its centre, and that part of each pair's arc shift is taken out before the angle is
//! solved.

use crate::pipeline::cloud::SurfacePoint;
use crate::domain::optics::ViewPose;
use crate::numeric::angle::wrap_pi;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseCorrection {
    pub angle_deg: f64,
    pub axial_mm: f64,
    pub lens_radius_mm: f64,
}

impl PoseCorrection {
    pub fn apply(&self, pose: &ViewPose) -> ViewPose {
        ViewPose {
            angle_deg: pose.angle_deg + self.angle_deg,
            axial_mm: pose.axial_mm + self.axial_mm,
            lens_radius_mm: pose.lens_radius_mm + self.lens_radius_mm,
        }
    }
}

/// One overlapping pair: how far view b's content must move to match view a's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairMeasure {
    pub a: usize,
    pub b: usize,
    /// Measured along the arc, less what the two views' solved lens-radius corrections account
    /// for there (see [`register`]).
    pub shift_angle_deg: f64,
    pub shift_axial_mm: f64,
    pub shift_radius_mm: f64,
    /// Normalised cross-correlation at the peak (1 = identical texture).
    pub peak_ncc: f64,
    pub overlap_cells: usize,
    /// Disagreement with the solved corrections after the graph solve.
    pub residual_angle_deg: f64,
    pub residual_axial_um: f64,
    pub residual_radius_um: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Registration {
    pub corrections: Vec<PoseCorrection>,
    pub pairs: Vec<PairMeasure>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RegisterOptions {
    /// Cell of the unrolled overlap grids, mm.
    pub cell_mm: f64,
    /// Search half ranges (encoder error bounds, relative between two views).
    pub max_angle_deg: f64,
    pub max_axial_mm: f64,
    /// Pairs whose correlation peak is weaker than this, or whose aligned overlap is smaller than
    /// this many cells, are not trusted.
    pub min_ncc: f64,
    pub min_overlap_cells: usize,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        Self { cell_mm: 0.041, max_angle_deg: 2.5, max_axial_mm: 0.8, min_ncc: 0.1, min_overlap_cells: 2000 }
    }
}

/// The unrolled (arc, z) lattice every view is binned on: arc measured from angle 0 at the
/// reference radius, in cells that divide the circumference evenly (an even number of them, so
/// that the half-resolution lattice divides it too), and z in cells of the nominal size. One
/// lattice for the ring lets each view be binned once, whichever neighbour it is compared with: a
/// pair across angle 0 differs by whole turns, which are whole cells.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    pub radius_ref_mm: f64,
    /// Cells around the circumference (even).
    pub cells_around: i64,
    pub cell_arc_mm: f64,
    pub cell_z_mm: f64,
}

impl Lattice {
    /// `cell_mm` is the nominal cell; along the arc it is adjusted (by less than a cell per turn)
    /// to divide the circumference.
    pub fn new(radius_ref_mm: f64, cell_mm: f64) -> Self {
        let circumference = TAU * radius_ref_mm;
        let cells_around = (2.0 * (circumference / cell_mm / 2.0).round()).max(2.0) as i64;
        Self { radius_ref_mm, cells_around, cell_arc_mm: circumference / cells_around as f64, cell_z_mm: cell_mm }
    }

    /// Lattice cells from view b's arc indices to view a's: both are measured from angle 0 at each
    /// view's own (unwrapped) angle, so they differ by the whole turns between the two angles as
    /// given and as wrapped.
    fn turn_cells(&self, angle_a_rad: f64, angle_b_rad: f64) -> i64 {
        let raw = angle_b_rad - angle_a_rad;
        ((wrap_pi(raw) - raw) / TAU).round() as i64 * self.cells_around
    }
}

/// A view's points binned on a grid of lattice cells.
struct Patch {
    s0: i64,
    z0: i64,
    ns: usize,
    nz: usize,
    gray: Vec<f32>,
    radius: Vec<f32>,
}

/// What registration keeps of a view, computed once (every pair that includes the view reuses
/// it): its texture and radius on the [`Lattice`], and the texture's grids for the coarse and the
/// fine correlation.
pub struct ViewGrid {
    /// The view's own angle, rad.
    angle_rad: f64,
    /// Texture ([`texture`]) and mean radius per cell.
    patch: Patch,
    /// The half-resolution texture's origin and its stride-two grids ([`StrideTwo`]).
    coarse_origin: (i64, i64),
    coarse: StrideTwo,
    z_range_mm: (f64, f64),
}

/// Buffers [`view_grid`] reuses from view to view: a view's binned points and cell sums are
/// megabytes, and fresh ones cost a page fault per 4 kB.
#[derive(Default)]
pub struct GridScratch {
    cells: Vec<(i64, i64, f32, f32, f32)>,
    sum: Vec<(f32, f32, f32)>,
}

impl ViewGrid {
    /// Least and greatest z of the view's points at the pose they were projected with. A pose's z
    /// enters a point's z as its axial position alone, so a refined pose's range is this one moved
    /// by the axial correction (no second projection needed to size the fused grid).
    pub fn z_range_mm(&self) -> (f64, f64) {
        self.z_range_mm
    }
}

/// Bins a view's points (as [`crate::pipeline::cloud::points_of`] gives them) on the lattice: brightness and
/// radius per cell, weighted by the points' focus peak ratios; then the view's texture and its
/// correlation grid (the fine one is built per pair, in buffers the pairs reuse). With
/// `fill_arc_gaps` (depth maps on every second pixel row, which leave every other arc cell of a
/// pixel's size empty), a cell missing between two present ones along the arc takes their mean:
/// left empty, the correlation at odd arc shifts would meet half the cells it does at even ones
/// and the sub-cell peak would be skewed (standard: 0.029° and 8.2 µm against 0.013° and 4.6 µm
/// filled).
pub fn view_grid(
    points: impl IntoIterator<Item = SurfacePoint>,
    view_angle_rad: f64,
    lattice: &Lattice,
    fill_arc_gaps: bool,
    scratch: &mut GridScratch,
) -> ViewGrid {
    let points = points.into_iter();
    let GridScratch { cells, sum } = scratch;
    cells.clear();
    cells.reserve(crate::pipeline::cloud::capacity_for(&points));
    let mut z_range_mm = (f64::MAX, f64::MIN);
    let angle = crate::numeric::angle::AngleFrom::new(view_angle_rad);
    let (per_arc, per_z) = (lattice.radius_ref_mm / lattice.cell_arc_mm, 1.0 / lattice.cell_z_mm);
    for p in points {
        // Near the view's own angle a point's arc is its angle from the view plus the view's angle.
        let s = (view_angle_rad + angle.of(p.position.x, p.position.y)) * per_arc;
        let z = p.position.z;
        z_range_mm = (z_range_mm.0.min(z), z_range_mm.1.max(z));
        let (g, r, w) = (crate::domain::frame::luminance(p.rgb), p.radius_mm() as f32, p.confidence());
        cells.push((crate::numeric::angle::floor_i64(s), crate::numeric::angle::floor_i64(z * per_z), g, r, w));
    }
    let (s0, s1) = cells.iter().fold((i64::MAX, i64::MIN), |(a, b), c| (a.min(c.0), b.max(c.0)));
    let (z0, z1) = cells.iter().fold((i64::MAX, i64::MIN), |(a, b), c| (a.min(c.1), b.max(c.1)));
    // A view without a trusted point has an empty grid (no pair with it is measured).
    let (s0, z0, ns, nz) =
        if cells.is_empty() { (0, 0, 0, 0) } else { (s0, z0, (s1 - s0 + 1) as usize, (z1 - z0 + 1) as usize) };
    sum.clear();
    sum.resize(ns * nz, (0.0, 0.0, 0.0));
    for &(s, z, g, r, w) in cells.iter() {
        let i = (z - z0) as usize * ns + (s - s0) as usize;
        sum[i].0 += w * g;
        sum[i].1 += w * r;
        sum[i].2 += w;
    }
    let mut gray: Vec<f32> = sum.iter().map(|c| if c.2 > 0.0 { c.0 / c.2 } else { f32::NAN }).collect();
    let mut radius: Vec<f32> = sum.iter().map(|c| if c.2 > 0.0 { c.1 / c.2 } else { f32::NAN }).collect();
    if fill_arc_gaps {
        fill_single_gaps_along_arc(&mut gray, ns);
        fill_single_gaps_along_arc(&mut radius, ns);
    }
    let patch = Patch { s0, z0, ns, nz, gray: texture(&gray, &radius, ns, nz), radius };
    let half = patch.halved();
    ViewGrid {
        angle_rad: view_angle_rad,
        coarse_origin: (half.s0, half.z0),
        coarse: StrideTwo::new(&half.gray, (half.ns, half.nz)),
        patch,
        z_range_mm,
    }
}

/// Cells missing between two present ones along the arc (rows of `ns` cells) get their mean.
/// A row is read as it was binned: a filled cell does not fill its neighbour.
fn fill_single_gaps_along_arc(field: &mut [f32], ns: usize) {
    if ns < 3 {
        return;
    }
    for row in field.chunks_exact_mut(ns) {
        for s in 1..ns - 1 {
            if row[s].is_nan() && row[s - 1].is_finite() && row[s + 1].is_finite() {
                row[s] = 0.5 * (row[s - 1] + row[s + 1]);
            }
        }
    }
}

impl Patch {
    /// The patch at half resolution (2×2 cells averaged; origins floored to even cells).
    fn halved(&self) -> Patch {
        let (s0, z0) = (self.s0.div_euclid(2), self.z0.div_euclid(2));
        let ns = ((self.s0 + self.ns as i64 - 1).div_euclid(2) - s0 + 1) as usize;
        let nz = ((self.z0 + self.nz as i64 - 1).div_euclid(2) - z0 + 1) as usize;
        let mut sum = vec![(0f32, 0f32, 0u32); ns * nz];
        for z in 0..self.nz {
            for s in 0..self.ns {
                let (g, r) = (self.gray[z * self.ns + s], self.radius[z * self.ns + s]);
                if g.is_nan() {
                    continue;
                }
                let cs = ((self.s0 + s as i64).div_euclid(2) - s0) as usize;
                let cz = ((self.z0 + z as i64).div_euclid(2) - z0) as usize;
                let c = &mut sum[cz * ns + cs];
                c.0 += g;
                c.1 += r;
                c.2 += 1;
            }
        }
        let gray = sum.iter().map(|c| if c.2 > 0 { c.0 / c.2 as f32 } else { f32::NAN }).collect();
        let radius = sum.iter().map(|c| if c.2 > 0 { c.1 / c.2 as f32 } else { f32::NAN }).collect();
        Patch { s0, z0, ns, nz, gray, radius }
    }

    fn at(&self, field: &[f32], s: i64, z: i64) -> f32 {
        let (ds, dz) = (s - self.s0, z - self.z0);
        if ds < 0 || dz < 0 || ds as usize >= self.ns || dz as usize >= self.nz {
            return f32::NAN;
        }
        field[dz as usize * self.ns + ds as usize]
    }
}

/// The texture that pins the screw motion down: brightness minus its mean along the arc (±4 cells),
/// which removes everything constant along the helix (flank edges, chaser marks) and keeps the
/// grain; cells on flanks (steep in z) are dropped, their brightness being edges, not texture.
fn texture(gray: &[f32], radius: &[f32], ns: usize, nz: usize) -> Vec<f32> {
    const ALONG: usize = 4;
    const FLANK_MM: f32 = 0.03;
    let mut out = vec![f32::NAN; gray.len()];
    for z in 1..nz.saturating_sub(1) {
        for s in 0..ns {
            let i = z * ns + s;
            let (v, up, down) = (gray[i], radius[i - ns], radius[i + ns]);
            if v.is_nan() || !(up - radius[i]).abs().max((down - radius[i]).abs()).lt(&FLANK_MM) {
                continue;
            }
            let (mut sum, mut n) = (0f32, 0);
            for ss in s.saturating_sub(ALONG)..(s + ALONG + 1).min(ns) {
                let g = gray[z * ns + ss];
                if g.is_finite() {
                    sum += g;
                    n += 1;
                }
            }
            out[i] = v - sum / n as f32;
        }
    }
    out
}

/// A texture grid laid out for correlation: missing cells are zero in the values and their
/// squares and 0 in the mask, so that the sums over a shifted overlap need no branches (and run
/// eight cells at a time). Stored by arc column (z fastest): an overlap between neighbours is long
/// in z and short in arc, and long rows keep the per-row overhead small.
#[derive(Default)]
struct TextureGrid {
    /// Arc cells (rows of the layout) and z cells (along a row).
    ns: usize,
    nz: usize,
    value: Vec<f32>,
    square: Vec<f32>,
    mask: Vec<f32>,
}

impl TextureGrid {
    /// Every `step`-th cell of the (z-major) `field` starting at (s_phase, z_phase).
    fn sampled(field: &[f32], ns: usize, nz: usize, step: usize, s_phase: usize, z_phase: usize) -> Self {
        let mut grid = Self::default();
        grid.sample(field, ns, nz, step, s_phase, z_phase);
        grid
    }

    /// [`TextureGrid::sampled`] into this grid's buffers.
    fn sample(&mut self, field: &[f32], ns: usize, nz: usize, step: usize, s_phase: usize, z_phase: usize) {
        let (gs, gz) = (ns.saturating_sub(s_phase).div_ceil(step), nz.saturating_sub(z_phase).div_ceil(step));
        let cells = gs * gz;
        let grid = self;
        (grid.ns, grid.nz) = (gs, gz);
        for buffer in [&mut grid.value, &mut grid.square, &mut grid.mask] {
            buffer.clear();
            buffer.resize(cells, 0.0);
        }
        for s in 0..gs {
            for z in 0..gz {
                let v = field[(z_phase + z * step) * ns + s_phase + s * step];
                if v.is_finite() {
                    let i = s * gz + z;
                    (grid.value[i], grid.square[i], grid.mask[i]) = (v, v * v, 1.0);
                }
            }
        }
    }
}

/// Every other cell of a grid in each of the four parities (s, z), for the coarse search: a's
/// even cells are met by b's cells in the parity a shift brings onto them.
struct StrideTwo {
    parities: [TextureGrid; 4],
}

impl StrideTwo {
    fn new(field: &[f32], (ns, nz): (usize, usize)) -> Self {
        let at = |p: usize| TextureGrid::sampled(field, ns, nz, 2, p % 2, p / 2);
        Self { parities: [at(0), at(1), at(2), at(3)] }
    }

    /// NCC over a's even cells (s, z) against b's (s + off_s, z + off_z): a's cell 2i meets b's
    /// cell 2i + off = 2(i + off.div_euclid(2)) + off.rem_euclid(2).
    fn ncc(a: &StrideTwo, b: &StrideTwo, off_s: i64, off_z: i64, min_cells: usize) -> (f64, usize) {
        let phase = (off_s.rem_euclid(2) + 2 * off_z.rem_euclid(2)) as usize;
        ncc_grids(&a.parities[0], &b.parities[phase], off_s.div_euclid(2), off_z.div_euclid(2), min_cells)
    }
}

/// Σ a·b over equal-length slices, in eight f32 lanes (one pass per product vectorises cleanly;
/// six products in one loop spill registers).
fn dot(a: &[f32], b: &[f32]) -> f64 {
    const LANES: usize = 8;
    let (a_chunks, a_rest) = a.as_chunks::<LANES>();
    let (b_chunks, b_rest) = b.as_chunks::<LANES>();
    let mut lanes = [0f32; LANES];
    for (x, y) in a_chunks.iter().zip(b_chunks) {
        for l in 0..LANES {
            lanes[l] += x[l] * y[l];
        }
    }
    let rest: f32 = a_rest.iter().zip(b_rest).map(|(x, y)| x * y).sum();
    lanes.iter().map(|&v| v as f64).sum::<f64>() + rest as f64
}

/// The six sums of [`ncc_grids`] over the overlap: per column, the dot products of (mask a, mask
/// b), (a, mask b), (mask a, b), (a², mask b), (mask a, b²) and (a, b), accumulated in f64.
#[inline(always)]
fn overlap_sums(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64, one_pass: bool) -> [f64; 6] {
    let (s_lo, s_hi) = ((-off_s).max(0), (b.ns as i64 - off_s).min(a.ns as i64));
    let (z_lo, z_hi) = ((-off_z).max(0), (b.nz as i64 - off_z).min(a.nz as i64));
    let mut total = [0f64; 6];
    if z_lo >= z_hi {
        return total;
    }
    let len = (z_hi - z_lo) as usize;
    for s in s_lo..s_hi {
        let (ia, ib) = (s as usize * a.nz + z_lo as usize, (s + off_s) as usize * b.nz + (z_lo + off_z) as usize);
        let (xa, qa, ma) = (&a.value[ia..ia + len], &a.square[ia..ia + len], &a.mask[ia..ia + len]);
        let (xb, qb, mb) = (&b.value[ib..ib + len], &b.square[ib..ib + len], &b.mask[ib..ib + len]);
        let pairs = [(ma, mb), (xa, mb), (ma, xb), (qa, mb), (ma, qb), (xa, xb)];
        if one_pass {
            // The same eight lanes per product, added in the same order as `dot` adds them (so the
            // sums are bit for bit those of six passes), in one pass over the twelve rows: with
            // sixteen 256-bit registers the six accumulators and the loads fit.
            const LANES: usize = 8;
            let mut lanes = [[0f32; LANES]; 6];
            let chunks = len / LANES;
            for c in 0..chunks {
                let at = c * LANES;
                for (acc, (u, v)) in lanes.iter_mut().zip(pairs) {
                    let (u, v) = (&u[at..at + LANES], &v[at..at + LANES]);
                    for l in 0..LANES {
                        acc[l] += u[l] * v[l];
                    }
                }
            }
            for ((t, acc), (u, v)) in total.iter_mut().zip(&lanes).zip(pairs) {
                let rest: f32 = u[chunks * LANES..].iter().zip(&v[chunks * LANES..]).map(|(x, y)| x * y).sum();
                *t += acc.iter().map(|&v| v as f64).sum::<f64>() + rest as f64;
            }
        } else {
            for (t, (u, v)) in total.iter_mut().zip(pairs) {
                *t += dot(u, v);
            }
        }
    }
    total
}

/// [`overlap_sums`] compiled for AVX2, where the one-pass form fits in registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn overlap_sums_avx2(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64) -> [f64; 6] {
    overlap_sums(a, b, off_s, off_z, true)
}

/// NCC of a's values with b's where a's cell (s, z) meets b's cell (s + off_s, z + off_z), over
/// the cells where both have data; (−1, n) when fewer than `min_cells` meet. Returns (ncc, cells).
///
/// The build targets baseline x86-64 (SSE2), so the binary runs anywhere; this loop, registration's
/// largest, takes AVX2 where the processor has it (the same sums either way; standard preset:
/// registration 0.79–0.80 → 0.59–0.69 s). Only loops measured faster that way have two copies (see
/// also `depth::focus_measure`): the whole program built for x86-64-v3 was slower.
fn ncc_grids(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64, min_cells: usize) -> (f64, usize) {
    #[cfg(target_arch = "x86_64")]
    let total = if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2 (checked just above).
        unsafe { overlap_sums_avx2(a, b, off_s, off_z) }
    } else {
        overlap_sums(a, b, off_s, off_z, false)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let total = overlap_sums(a, b, off_s, off_z, false);
    let [n, sa, sb, saa, sbb, sab] = total;
    let cells = n.round() as usize;
    if cells < min_cells {
        return (-1.0, cells);
    }
    let cov = sab - sa * sb / n;
    let var = (saa - sa * sa / n) * (sbb - sb * sb / n);
    (if var > 0.0 { cov / var.sqrt() } else { -1.0 }, cells)
}

/// Vertex offset in (−0.5, 0.5) of the parabola through three equally spaced samples.
fn sub_cell(left: f64, centre: f64, right: f64) -> f64 {
    let denom = left - 2.0 * centre + right;
    if denom < 0.0 { (0.5 * (left - right) / denom).clamp(-0.5, 0.5) } else { 0.0 }
}

/// Centre offset in (−0.5, 0.5) of the Gaussian through three equally spaced samples (the
/// parabola through their logarithms), exact for a Gaussian peak, where a parabola's estimate is
/// pulled toward the centre cell; the parabola's when a neighbour is not positive.
fn sub_cell_gaussian(left: f64, centre: f64, right: f64) -> f64 {
    if left > 0.0 && centre > 0.0 && right > 0.0 {
        sub_cell(left.ln(), centre.ln(), right.ln())
    } else {
        sub_cell(left, centre, right)
    }
}

/// Measures one pair of overlapping views. `fine` holds the two views' full-resolution
/// correlation grids (buffers reused from pair to pair).
fn measure_pair(
    a: usize,
    b: usize,
    views: &[ViewGrid],
    lattice: &Lattice,
    options: &RegisterOptions,
    fine: &mut (TextureGrid, TextureGrid),
) -> Option<PairMeasure> {
    let (va, vb) = (&views[a], &views[b]);
    let (pa, pb) = (&va.patch, &vb.patch);
    if pa.gray.is_empty() || pb.gray.is_empty() {
        return None;
    }
    // b's arc indices in a's turn.
    let turn = lattice.turn_cells(va.angle_rad, vb.angle_rad);
    let b_s0 = pb.s0 + turn;
    let (b_coarse_s0, b_coarse_z0) = (vb.coarse_origin.0 + turn / 2, vb.coarse_origin.1);
    let (a_coarse_s0, a_coarse_z0) = va.coarse_origin;

    // The grain's correlation peak is a cell or two wide: search every shift at half resolution,
    // then ±2 cells around the best at full resolution, then sub-cell. A shift (ds, dz) moves b's
    // content onto a's: a's cell c meets b's cell c − d.
    let rs = (lattice.radius_ref_mm * options.max_angle_deg.to_radians() / lattice.cell_arc_mm / 2.0).ceil() as i64;
    let rz = (options.max_axial_mm / lattice.cell_z_mm / 2.0).ceil() as i64;
    let mut best = (f64::MIN, 0i64, 0i64);
    for dz in -rz..=rz {
        for ds in -rs..=rs {
            // Every other cell of the overlap is plenty to find the peak at this level.
            let (c, _) = StrideTwo::ncc(
                &va.coarse,
                &vb.coarse,
                a_coarse_s0 - ds - b_coarse_s0,
                a_coarse_z0 - dz - b_coarse_z0,
                70,
            );
            if c > best.0 {
                best = (c, ds, dz);
            }
        }
    }
    fine.0.sample(&pa.gray, pa.ns, pa.nz, 1, 0, 0);
    fine.1.sample(&pb.gray, pb.ns, pb.nz, 1, 0, 0);
    let (fine_a, fine_b) = (&fine.0, &fine.1);
    let ncc = |ds: i64, dz: i64| ncc_grids(fine_a, fine_b, pa.s0 - ds - b_s0, pa.z0 - dz - pb.z0, 220);
    let (cs, cz) = (2 * best.1, 2 * best.2);
    let mut fine = (f64::MIN, cs, cz);
    for dz in cz - 2..=cz + 2 {
        for ds in cs - 2..=cs + 2 {
            let (c, _) = ncc(ds, dz);
            if c > fine.0 {
                fine = (c, ds, dz);
            }
        }
    }
    let (peak, ds, dz) = fine;
    let (_, cells) = ncc(ds, dz);
    if peak < options.min_ncc || cells < options.min_overlap_cells {
        return None;
    }
    // Along z the texture is the grain as imaged, whose correlation peak is close to a Gaussian;
    // along the arc it was high-passed (its mean over ±4 cells removed, `texture`), which narrows
    // the peak and gives it negative side lobes, so the parabola stays there. (Gaussian along z:
    // axial RMS 1.7–3.8 → 1.1–2.3 µm on the accuracy suite, better on 17 of the 18 held-out cases.)
    let frac_s = sub_cell(ncc(ds - 1, dz).0, peak, ncc(ds + 1, dz).0);
    let frac_z = sub_cell_gaussian(ncc(ds, dz - 1).0, peak, ncc(ds, dz + 1).0);
    // Radial offset over the aligned overlap.
    let mut dr = Vec::new();
    for z in 0..pa.nz {
        for s in 0..pa.ns {
            let ra = pa.radius[z * pa.ns + s];
            let rb = pb.at(&pb.radius, pa.s0 + s as i64 - ds - turn, pa.z0 + z as i64 - dz);
            if ra.is_finite() && rb.is_finite() {
                dr.push((ra - rb) as f64);
            }
        }
    }
    if dr.is_empty() {
        return None;
    }
    let median = dr.len() / 2;
    let shift_radius_mm = *dr.select_nth_unstable_by(median, f64::total_cmp).1;
    Some(PairMeasure {
        a,
        b,
        shift_angle_deg: ((ds as f64 + frac_s) * lattice.cell_arc_mm / lattice.radius_ref_mm).to_degrees(),
        shift_axial_mm: (dz as f64 + frac_z) * lattice.cell_z_mm,
        shift_radius_mm,
        peak_ncc: peak,
        overlap_cells: cells,
        residual_angle_deg: 0.0,
        residual_axial_um: 0.0,
        residual_radius_um: 0.0,
    })
}

/// Pairs of views whose footprints overlap: same axial row and adjacent in angle, or same angle and
/// adjacent in z, judged from the encoder poses and the footprint sizes.
pub fn overlapping_pairs(poses: &[ViewPose], half_angle_deg: f64, half_axial_mm: f64) -> Vec<(usize, usize)> {
    let mut pairs = Vec::new();
    for a in 0..poses.len() {
        for b in a + 1..poses.len() {
            let dang = wrap_pi((poses[b].angle_deg - poses[a].angle_deg).to_radians()).to_degrees().abs();
            let dz = (poses[b].axial_mm - poses[a].axial_mm).abs();
            let angular = dang < 1.7 * half_angle_deg && dz < 0.5 * half_axial_mm;
            let axial = dang < 0.5 * half_angle_deg && dz < 1.7 * half_axial_mm;
            if angular || axial {
                pairs.push((a, b));
            }
        }
    }
    pairs
}

/// Which connected component of the pair graph each of `n` views is in (union–find; a view in no
/// pair is a component of its own), as the component's least view.
fn components(n: usize, pairs: &[(usize, usize, f64)]) -> Vec<usize> {
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(parent: &mut [usize], mut v: usize) -> usize {
        while parent[v] != v {
            parent[v] = parent[parent[v]];
            v = parent[v];
        }
        v
    }
    for &(a, b, _) in pairs {
        let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
        parent[ra.max(rb)] = ra.min(rb);
    }
    (0..n).map(|v| root(&mut parent, v)).collect()
}

/// Solves, per axis, min Σ w (c_b − c_a − m)² + Σ_C (Σ_{v ∈ C} c_v)², with Huber reweighting of
/// the pairs. Overlaps fix only differences: each connected component of the pair graph gets its
/// own gauge (its corrections sum to zero), so a view none of whose pairs was measured stays
/// where the encoder put it, and a ring split in two keeps both parts near their encoder poses
/// (one gauge for all would leave the system singular).
fn solve_axis(n: usize, pairs: &[(usize, usize, f64)], huber: f64) -> Vec<f64> {
    let mut weights = vec![1.0; pairs.len()];
    let mut c = vec![0.0; n];
    let component = components(n, pairs);
    for _ in 0..5 {
        // The gauge terms.
        let mut lhs =
            nalgebra::DMatrix::<f64>::from_fn(n, n, |i, j| if component[i] == component[j] { 1.0 } else { 0.0 });
        let mut rhs = nalgebra::DVector::<f64>::zeros(n);
        for (&(a, b, m), w) in pairs.iter().zip(&weights) {
            lhs[(a, a)] += w;
            lhs[(b, b)] += w;
            lhs[(a, b)] -= w;
            lhs[(b, a)] -= w;
            rhs[b] += w * m;
            rhs[a] -= w * m;
        }
        let Some(sol) = lhs.lu().solve(&rhs) else { break };
        c = sol.iter().copied().collect();
        for (&(a, b, m), w) in pairs.iter().zip(weights.iter_mut()) {
            let r = (c[b] - c[a] - m).abs();
            *w = if r <= huber { 1.0 } else { huber / r };
        }
    }
    c
}

/// How much the lens-radius corrections `radius_a_mm` and `radius_b_mm` of views a and b move
/// their pair's measured arc shift, in degrees: each view's points move by its correction δ along
/// its optical axis, which at angle φ from the view's centre is δ·sin φ along the arc, and the
/// overlap is centred half the views' (encoder) spacing from each centre, on opposite sides.
fn lens_radius_arc_shift_deg(
    pose_a: &ViewPose,
    pose_b: &ViewPose,
    radius_a_mm: f64,
    radius_b_mm: f64,
    lattice: &Lattice,
) -> f64 {
    let half_spacing = 0.5 * wrap_pi((pose_b.angle_deg - pose_a.angle_deg).to_radians());
    ((radius_a_mm + radius_b_mm) * half_spacing.sin() / lattice.radius_ref_mm).to_degrees()
}

/// Registers all views. `views[v]` is view v back-projected with its encoder pose `poses[v]` and
/// binned on `lattice` ([`view_grid`]).
pub fn register(
    views: &[ViewGrid],
    poses: &[ViewPose],
    lattice: &Lattice,
    half_angle_deg: f64,
    half_axial_mm: f64,
    options: &RegisterOptions,
) -> Registration {
    use rayon::prelude::*;
    let candidates = overlapping_pairs(poses, half_angle_deg, half_axial_mm);
    let mut pairs: Vec<PairMeasure> = candidates
        .par_iter()
        .map_init(Default::default, |fine, &(a, b)| measure_pair(a, b, views, lattice, options, fine))
        .flatten_iter()
        .collect();
    let n = poses.len();
    let axis = |pairs: &[PairMeasure], f: &dyn Fn(&PairMeasure) -> f64, huber: f64| {
        solve_axis(n, &pairs.iter().map(|p| (p.a, p.b, f(p))).collect::<Vec<_>>(), huber)
    };
    let radial = axis(&pairs, &|p| p.shift_radius_mm, 0.01);
    // A lens-radius error moves all of a view's points along its optical axis, which is radial
    // only at the view's centre: a point φ off it moves δ·sin φ along the arc. In an overlap, half
    // the views' spacing to either side of their centres, that adds (δ_a + δ_b)·sin(spacing/2)
    // to the measured arc shift (±0.05 mm lens errors: up to 7 µm, 2.6 µm RMS on the held-out
    // pairs against 1.6 µm for the rest of their error). The radial solve knows the δs to a
    // micrometre or two, so that part is taken out before the angle is solved.
    for p in pairs.iter_mut() {
        p.shift_angle_deg -= lens_radius_arc_shift_deg(&poses[p.a], &poses[p.b], radial[p.a], radial[p.b], lattice);
    }
    let angle = axis(&pairs, &|p| p.shift_angle_deg, 0.02);
    let axial = axis(&pairs, &|p| p.shift_axial_mm, 0.01);
    for p in pairs.iter_mut() {
        p.residual_angle_deg = angle[p.b] - angle[p.a] - p.shift_angle_deg;
        p.residual_axial_um = 1e3 * (axial[p.b] - axial[p.a] - p.shift_axial_mm);
        p.residual_radius_um = 1e3 * (radial[p.b] - radial[p.a] - p.shift_radius_mm);
    }
    let corrections =
        (0..n).map(|v| PoseCorrection { angle_deg: angle[v], axial_mm: axial[v], lens_radius_mm: radial[v] }).collect();
    Registration { corrections, pairs }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gaussian_peaks_centre_is_found_exactly_where_a_parabola_pulls_it_toward_the_cell() {
        for true_offset in [-0.4, -0.25, -0.1, 0.0, 0.1, 0.25, 0.4] {
            // A peak one cell wide (σ), sampled at the best cell and its two neighbours.
            let peak = |x: f64| 0.8 * (-(x - true_offset).powi(2) / 2.0).exp();
            let (left, centre, right) = (peak(-1.0), peak(0.0), peak(1.0));
            assert!((sub_cell_gaussian(left, centre, right) - true_offset).abs() < 1e-12, "{true_offset}");
            // The parabola's bias: 0.022, 0.045 and 0.038 cells at 0.1, 0.25 and 0.4.
            let parabola = sub_cell(left, centre, right);
            assert!(parabola.abs() <= true_offset.abs() - 0.02 || true_offset == 0.0, "{true_offset}: {parabola}");
        }
        // A neighbour that is not positive has no logarithm: the parabola's estimate.
        assert_eq!(sub_cell_gaussian(-0.1, 0.5, 0.3), sub_cell(-0.1, 0.5, 0.3));
        assert_eq!(sub_cell_gaussian(0.2, 0.5, 0.0), sub_cell(0.2, 0.5, 0.0));
    }

    #[test]
    fn a_lens_radius_error_shifts_an_overlap_along_the_arc_as_the_geometry_does() {
        // A surface point midway between two views (their overlap's centre). A view whose lens is
        // δ farther out than its pose says places the point δ nearer the axis along its optical
        // axis; the content shift b → a is then the angle where a places it minus where b does.
        let lattice = Lattice::new(57.15, 0.041);
        let r = lattice.radius_ref_mm;
        for (angle_a, angle_b, delta_a, delta_b) in
            [(10.0, 17.8, 0.05, -0.03), (17.8, 10.0, 0.05, -0.03), (356.0, 3.8, -0.04, -0.05), (30.0, 30.0, 0.05, 0.05)]
        {
            let pose = |angle_deg: f64| ViewPose { angle_deg, axial_mm: 10.0, lens_radius_mm: 270.0 };
            let (pa, pb) = (pose(angle_a), pose(angle_b));
            let mid = pa.angle_deg.to_radians() + 0.5 * wrap_pi((pb.angle_deg - pa.angle_deg).to_radians());
            let placed = |view_deg: f64, delta: f64| {
                let axis = view_deg.to_radians();
                let (x, y) = (r * mid.cos() - delta * axis.cos(), r * mid.sin() - delta * axis.sin());
                y.atan2(x)
            };
            let exact = wrap_pi(placed(angle_a, delta_a) - placed(angle_b, delta_b)).to_degrees();
            let model = lens_radius_arc_shift_deg(&pa, &pb, delta_a, delta_b, &lattice);
            // First order in δ/r: within 1% (0.3% here, a few nanometres of arc).
            assert!((model - exact).abs() <= 1e-2 * exact.abs(), "{angle_a}→{angle_b}: {model} vs {exact}");
            if angle_a != angle_b {
                // 0.05 mm at 3.9° off centre: several µm of arc, more than a pair's other errors.
                assert!(exact.abs().to_radians() * r > 1e-3, "{exact}");
            }
        }
    }

    #[test]
    fn views_cut_off_from_the_ring_stay_at_their_encoder_poses() {
        // Six views; pairs 2–3 and 3–4 failed (view 3 is alone) and 5–0 failed: components
        // {0, 1, 2} and {4, 5} each keep their measured differences about a zero mean.
        let truth = [0.3, -0.1, 0.2, 0.0, 0.25, -0.05];
        let pairs: Vec<(usize, usize, f64)> =
            [(0, 1), (1, 2), (4, 5)].iter().map(|&(a, b)| (a, b, truth[b] - truth[a])).collect();
        assert_eq!(components(6, &pairs), [0, 0, 0, 3, 4, 4]);
        let c = solve_axis(6, &pairs, 0.02);
        assert!(c.iter().all(|v| v.is_finite() && v.abs() < 1.0), "{c:?}");
        assert!(c[3].abs() < 1e-12, "{c:?}");
        for &(a, b, m) in &pairs {
            assert!((c[b] - c[a] - m).abs() < 1e-9, "{c:?}");
        }
        assert!((c[0] + c[1] + c[2]).abs() < 1e-9 && (c[4] + c[5]).abs() < 1e-9, "{c:?}");
    }

    #[test]
    fn graph_solve_spreads_a_ring_consistently() {
        // Four views in a ring with true corrections (0.3, −0.1, 0.2, −0.4): measured differences
        // c_b − c_a, one of them corrupted; Huber weighting keeps the corrupt one from spreading.
        let truth = [0.3, -0.1, 0.2, -0.4];
        let mut pairs: Vec<(usize, usize, f64)> =
            (0..4).map(|a| (a, (a + 1) % 4, truth[(a + 1) % 4] - truth[a])).collect();
        pairs.push((0, 2, truth[2] - truth[0]));
        pairs.push((1, 3, truth[3] - truth[1]));
        pairs[1].2 += 0.5;
        let c = solve_axis(4, &pairs, 0.02);
        for v in 0..4 {
            assert!((c[v] - truth[v]).abs() < 0.02, "{c:?}");
        }
    }

    /// Brute-force NCC of a's cells (s, z) on the `step` grid against b's (s + off_s, z + off_z),
    /// both z-major with NaN for missing cells: what the masked grids must reproduce.
    fn brute_ncc(
        a: &[f32],
        (ans, anz): (usize, usize),
        b: &[f32],
        (bns, bnz): (usize, usize),
        off: (i64, i64),
        step: usize,
    ) -> f64 {
        let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
        for z in (0..anz).step_by(step) {
            for s in (0..ans).step_by(step) {
                let (bs, bz) = (s as i64 + off.0, z as i64 + off.1);
                if bs < 0 || bz < 0 || bs >= bns as i64 || bz >= bnz as i64 {
                    continue;
                }
                let (x, y) = (a[z * ans + s], b[bz as usize * bns + bs as usize]);
                if x.is_nan() || y.is_nan() {
                    continue;
                }
                let (x, y) = (x as f64, y as f64);
                (n, sa, sb, saa, sbb, sab) = (n + 1.0, sa + x, sb + y, saa + x * x, sbb + y * y, sab + x * y);
            }
        }
        (sab - sa * sb / n) / ((saa - sa * sa / n) * (sbb - sb * sb / n)).sqrt()
    }

    #[test]
    fn masked_grids_match_a_brute_force_ncc_at_every_parity() {
        let mut state = 7u64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((state >> 33) % 1000) as f32 / 1000.0 - 0.5
        };
        let (ans, anz, bns, bnz) = (23, 57, 29, 61);
        let a: Vec<f32> = (0..ans * anz).map(|i| if i % 17 == 3 { f32::NAN } else { next() }).collect();
        // b holds a's texture moved by (3, −2) cells, noise elsewhere, and holes of its own.
        let b: Vec<f32> = (0..bns * bnz)
            .map(|i| {
                let (s, z) = ((i % bns) as i64 - 3, (i / bns) as i64 + 2);
                let v = if s >= 0 && z >= 0 && (s as usize) < ans && (z as usize) < anz {
                    a[z as usize * ans + s as usize]
                } else {
                    next()
                };
                if i % 13 == 5 { f32::NAN } else { v }
            })
            .collect();
        let full = (TextureGrid::sampled(&a, ans, anz, 1, 0, 0), TextureGrid::sampled(&b, bns, bnz, 1, 0, 0));
        let (peak, _) = ncc_grids(&full.0, &full.1, 3, -2, 20);
        assert!((peak - 1.0).abs() < 1e-6, "{peak}");
        let coarse = (StrideTwo::new(&a, (ans, anz)), StrideTwo::new(&b, (bns, bnz)));
        for off_s in -4..=5i64 {
            for off_z in -3..=4i64 {
                let want = brute_ncc(&a, (ans, anz), &b, (bns, bnz), (off_s, off_z), 1);
                let (got, _) = ncc_grids(&full.0, &full.1, off_s, off_z, 20);
                assert!((got - want).abs() < 1e-5, "full ({off_s}, {off_z}): {got} vs {want}");
                // One pass over the twelve rows or six passes (and AVX2, where there is one): the
                // same sums, bit for bit, so the choice of loop never moves a registration.
                let six_passes = overlap_sums(&full.0, &full.1, off_s, off_z, false);
                assert_eq!(overlap_sums(&full.0, &full.1, off_s, off_z, true), six_passes);
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the processor has AVX2 (checked just above).
                    assert_eq!(unsafe { overlap_sums_avx2(&full.0, &full.1, off_s, off_z) }, six_passes);
                }
                let want = brute_ncc(&a, (ans, anz), &b, (bns, bnz), (off_s, off_z), 2);
                let (got, _) = StrideTwo::ncc(&coarse.0, &coarse.1, off_s, off_z, 20);
                assert!((got - want).abs() < 1e-5, "stride 2 ({off_s}, {off_z}): {got} vs {want}");
            }
        }
    }

    #[test]
    fn the_lattice_divides_the_turn_and_carries_a_neighbour_across_angle_zero() {
        let lattice = Lattice::new(57.15, 0.041);
        assert_eq!(lattice.cells_around % 2, 0);
        assert!((lattice.cell_arc_mm * lattice.cells_around as f64 - TAU * 57.15).abs() < 1e-9);
        assert!((lattice.cell_arc_mm - 0.041).abs() < 0.041 / lattice.cells_around as f64);
        let turn = |a_deg: f64, b_deg: f64| lattice.turn_cells(a_deg.to_radians(), b_deg.to_radians());
        assert_eq!(turn(8.0, 16.0), 0);
        // b at 0° is a's neighbour at 360°: its indices move up a turn, and back the other way.
        assert_eq!(turn(352.0, 0.0), lattice.cells_around);
        assert_eq!(turn(0.0, 352.0), -lattice.cells_around);
        assert_eq!(turn(-8.0, 352.0), -lattice.cells_around);
        // A point seen at 359.9° by b and 359.9° − 360° by a lands in the same cell of a's turn.
        let cell = |deg: f64| (deg.to_radians() * lattice.radius_ref_mm / lattice.cell_arc_mm).floor() as i64;
        assert_eq!(cell(359.9) + turn(-8.0, 352.0), cell(-0.1));
    }

    #[test]
    fn a_view_without_trusted_points_is_left_where_the_encoder_put_it() {
        let lattice = Lattice::new(57.15, 0.041);
        let poses: Vec<ViewPose> =
            // 352°, 0° and 8°: the first pair spans angle 0.
            [352.0, 0.0, 8.0].map(|angle_deg| ViewPose { angle_deg, axial_mm: 10.0, lens_radius_mm: 200.0 }).into();
        let grids: Vec<ViewGrid> = poses
            .iter()
            .map(|p| {
                view_grid(std::iter::empty(), p.angle_deg.to_radians(), &lattice, false, &mut GridScratch::default())
            })
            .collect();
        let registration = register(&grids, &poses, &lattice, 7.0, 17.0, &RegisterOptions::default());
        assert!(registration.pairs.is_empty());
        assert!(registration.corrections.iter().all(|c| *c == PoseCorrection::default()));
    }

    #[test]
    fn neighbours_include_the_wrap_around_pair() {
        let poses: Vec<ViewPose> =
            (0..8).map(|i| ViewPose { angle_deg: i as f64 * 45.0, axial_mm: 10.0, lens_radius_mm: 200.0 }).collect();
        let pairs = overlapping_pairs(&poses, 30.0, 15.0);
        assert_eq!(pairs.len(), 8);
        assert!(pairs.contains(&(0, 7)));
    }
}
