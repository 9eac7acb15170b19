//! Registration: refines every view's pose (the fixture's three axes: angle about the pipe axis,
//! axial position, lens radius) from the overlaps with its neighbours, with global consistency.
//!
//! The thread surface is a helix, invariant under a screw motion, so geometry alone cannot fix how
//! two overlapping views slide along the helix. The surface texture (mill-scale grain, chaser marks,
//! albedo variation) is tied to the part and breaks that symmetry: each overlapping pair is aligned
//! by normalised cross-correlation of the high-passed all-in-focus brightness in the unrolled
//! (arc, z) plane, coarse to fine with sub-cell peak interpolation; the radial offset is the median
//! radius difference over the aligned overlap. All pair measurements then enter a pose graph (one
//! least-squares problem per axis over the whole ring, Huber-reweighted, the mean correction fixed
//! at zero since the encoders' mean error is), so no error accumulates around the circumference.

use crate::cloud::SurfacePoint;
use crate::optics::ViewPose;
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

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

/// Wraps an angle difference to (−π, π].
fn wrap(a: f64) -> f64 {
    let w = a.rem_euclid(TAU);
    if w > PI { w - TAU } else { w }
}

/// A view's points binned on a grid in (arc, z) around a reference angle.
struct Patch {
    s0: i64,
    z0: i64,
    ns: usize,
    nz: usize,
    gray: Vec<f32>,
    radius: Vec<f32>,
}

/// What registration needs of a surface point, computed once per view (every pair reuses it).
#[derive(Clone, Copy)]
struct Sample {
    /// Angle about the pipe axis from the view's own angle, wrapped to (−π, π].
    phi_rad: f64,
    z_mm: f64,
    gray: f32,
    radius_mm: f32,
    weight: f32,
}

/// A view's samples in image order, with each image row's span and its angular extent about the
/// view's own angle (rows run along θ), so that a pair's patches visit only the rows that can
/// reach the overlap, and the view's half extent along the arc.
pub struct ViewSamples {
    samples: Vec<Sample>,
    /// (samples of the row, least and greatest wrap(θ − view angle) in it, rad).
    rows: Vec<(std::ops::Range<usize>, f64, f64)>,
    half_extent_rad: f64,
    z_range_mm: (f64, f64),
}

impl ViewSamples {
    /// Least and greatest z of the view's points at the pose they were projected with. A pose's z
    /// enters a point's z as its axial position alone, so a refined pose's range is this one moved
    /// by the axial correction (no second projection needed to size the fused grid).
    pub fn z_range_mm(&self) -> (f64, f64) {
        self.z_range_mm
    }
}

/// What registration keeps of a view's points (in image order, as [`crate::cloud::points_of`]
/// gives them) seen from the view's own angle.
pub fn view_samples(points: impl IntoIterator<Item = SurfacePoint>, view_angle_rad: f64) -> ViewSamples {
    let points = points.into_iter();
    let mut samples: Vec<Sample> = Vec::with_capacity(crate::cloud::capacity_for(&points));
    let mut rows: Vec<(std::ops::Range<usize>, f64, f64)> = Vec::new();
    let mut half_extent_rad = 0f64;
    let mut z_range_mm = (f64::MAX, f64::MIN);
    let mut row_of_last = None;
    let angle = crate::cloud::AngleFrom::new(view_angle_rad);
    for (i, p) in points.enumerate() {
        let phi = angle.of(p.position.x, p.position.y);
        let s = Sample {
            phi_rad: phi,
            z_mm: p.position.z,
            gray: crate::bundle::luminance(p.rgb),
            radius_mm: p.radius_mm() as f32,
            weight: crate::fuse::point_weight(p.weight),
        };
        half_extent_rad = half_extent_rad.max(phi.abs());
        z_range_mm = (z_range_mm.0.min(s.z_mm), z_range_mm.1.max(s.z_mm));
        match rows.last_mut() {
            Some((range, lo, hi)) if row_of_last == Some(p.pixel[1]) => {
                range.end = i + 1;
                (*lo, *hi) = (lo.min(phi), hi.max(phi));
            }
            _ => rows.push((i..i + 1, phi, phi)),
        }
        row_of_last = Some(p.pixel[1]);
        samples.push(s);
    }
    ViewSamples { samples, rows, half_extent_rad, z_range_mm }
}

impl Patch {
    /// The cells of `view` (whose own angle is `view_angle`) within `s_range` of arc around
    /// `ref_angle`.
    fn build(
        view: &ViewSamples,
        view_angle: f64,
        ref_angle: f64,
        radius_ref: f64,
        cell: f64,
        s_range: (f64, f64),
    ) -> Option<Patch> {
        // Rows are skipped on their extent about the view's angle shifted to the reference; the
        // slack covers rounding, and near ±π (no neighbour is there) nothing is skipped.
        const SLACK_MM: f64 = 1e-6;
        let delta = wrap(view_angle - ref_angle);
        let mut cells: Vec<(i64, i64, f32, f32, f32)> = Vec::new();
        for (range, lo, hi) in &view.rows {
            let (lo, hi) = (lo + delta, hi + delta);
            let far = lo.abs().max(hi.abs()) > PI - 0.1;
            if !far && (radius_ref * hi + SLACK_MM < s_range.0 || radius_ref * lo - SLACK_MM > s_range.1) {
                continue;
            }
            for p in &view.samples[range.clone()] {
                // Near the view's own angle the arc from the reference is the sample's angle from
                // its view plus the views' separation; only a row near ±π needs wrapping again.
                let s = if far { radius_ref * wrap(p.phi_rad + delta) } else { radius_ref * (p.phi_rad + delta) };
                if s < s_range.0 || s > s_range.1 {
                    continue;
                }
                cells.push(((s / cell).floor() as i64, (p.z_mm / cell).floor() as i64, p.gray, p.radius_mm, p.weight));
            }
        }
        if cells.is_empty() {
            return None;
        }
        let (s0, s1) = cells.iter().fold((i64::MAX, i64::MIN), |(a, b), c| (a.min(c.0), b.max(c.0)));
        let (z0, z1) = cells.iter().fold((i64::MAX, i64::MIN), |(a, b), c| (a.min(c.1), b.max(c.1)));
        let (ns, nz) = ((s1 - s0 + 1) as usize, (z1 - z0 + 1) as usize);
        let mut sum = vec![(0f32, 0f32, 0f32); ns * nz];
        for (s, z, g, r, w) in cells {
            let i = (z - z0) as usize * ns + (s - s0) as usize;
            sum[i].0 += w * g;
            sum[i].1 += w * r;
            sum[i].2 += w;
        }
        let gray: Vec<f32> = sum.iter().map(|c| if c.2 > 0.0 { c.0 / c.2 } else { f32::NAN }).collect();
        let radius: Vec<f32> = sum.iter().map(|c| if c.2 > 0.0 { c.1 / c.2 } else { f32::NAN }).collect();
        Some(Patch { s0, z0, ns, nz, gray: texture(&gray, &radius, ns, nz), radius })
    }

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
        let (gs, gz) = (ns.saturating_sub(s_phase).div_ceil(step), nz.saturating_sub(z_phase).div_ceil(step));
        let cells = gs * gz;
        let mut grid =
            Self { ns: gs, nz: gz, value: vec![0.0; cells], square: vec![0.0; cells], mask: vec![0.0; cells] };
        for s in 0..gs {
            for z in 0..gz {
                let v = field[(z_phase + z * step) * ns + s_phase + s * step];
                if v.is_finite() {
                    let i = s * gz + z;
                    (grid.value[i], grid.square[i], grid.mask[i]) = (v, v * v, 1.0);
                }
            }
        }
        grid
    }
}

/// Every other cell of two grids, for the coarse search: a's even cells, and b's cells in the
/// four parities a shift can bring onto them.
struct StrideTwo {
    a: TextureGrid,
    b: [TextureGrid; 4],
}

impl StrideTwo {
    fn new(a: &[f32], (ans, anz): (usize, usize), b: &[f32], (bns, bnz): (usize, usize)) -> Self {
        let b_at = |p: usize| TextureGrid::sampled(b, bns, bnz, 2, p % 2, p / 2);
        Self { a: TextureGrid::sampled(a, ans, anz, 2, 0, 0), b: [b_at(0), b_at(1), b_at(2), b_at(3)] }
    }

    /// NCC over a's even cells (s, z) against b's (s + off_s, z + off_z): a's cell 2i meets b's
    /// cell 2i + off = 2(i + off.div_euclid(2)) + off.rem_euclid(2).
    fn ncc(&self, off_s: i64, off_z: i64, min_cells: usize) -> (f64, usize) {
        let phase = (off_s.rem_euclid(2) + 2 * off_z.rem_euclid(2)) as usize;
        ncc_grids(&self.a, &self.b[phase], off_s.div_euclid(2), off_z.div_euclid(2), min_cells)
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

/// NCC of a's values with b's where a's cell (s, z) meets b's cell (s + off_s, z + off_z), over
/// the cells where both have data; (−1, n) when fewer than `min_cells` meet. Returns (ncc, cells).
fn ncc_grids(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64, min_cells: usize) -> (f64, usize) {
    let (s_lo, s_hi) = ((-off_s).max(0), (b.ns as i64 - off_s).min(a.ns as i64));
    let (z_lo, z_hi) = ((-off_z).max(0), (b.nz as i64 - off_z).min(a.nz as i64));
    // Per column (a few hundred cells) six dot products in f32 lanes, accumulated in f64.
    let mut total = [0f64; 6];
    if z_lo < z_hi {
        let len = (z_hi - z_lo) as usize;
        for s in s_lo..s_hi {
            let (ia, ib) = (s as usize * a.nz + z_lo as usize, (s + off_s) as usize * b.nz + (z_lo + off_z) as usize);
            let (xa, qa, ma) = (&a.value[ia..ia + len], &a.square[ia..ia + len], &a.mask[ia..ia + len]);
            let (xb, qb, mb) = (&b.value[ib..ib + len], &b.square[ib..ib + len], &b.mask[ib..ib + len]);
            for (t, (u, v)) in total.iter_mut().zip([(ma, mb), (xa, mb), (ma, xb), (qa, mb), (ma, qb), (xa, xb)]) {
                *t += dot(u, v);
            }
        }
    }
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

/// Measures one pair of overlapping views.
fn measure_pair(
    a: usize,
    b: usize,
    views: &[ViewSamples],
    angles_rad: &[f64],
    radius_ref: f64,
    options: &RegisterOptions,
) -> Option<PairMeasure> {
    let cell = options.cell_mm;
    let ref_angle = angles_rad[a];
    let margin = radius_ref * options.max_angle_deg.to_radians();
    // a's data near b, and b's data near a, in a's frame.
    let offset_b = radius_ref * wrap(angles_rad[b] - ref_angle);
    let half = |v: usize| (radius_ref * views[v].half_extent_rad).min(radius_ref * PI / 2.0);
    let (half_a, half_b) = (half(a), half(b));
    let lo = (offset_b - half_b - margin).max(-half_a);
    let hi = (offset_b + half_b + margin).min(half_a);
    if hi <= lo {
        return None;
    }
    let patch = |v: usize, s_range| Patch::build(&views[v], angles_rad[v], ref_angle, radius_ref, cell, s_range);
    let pa = patch(a, (lo.max(offset_b - half_b - margin), hi))?;
    let pb = patch(b, (-half_a - margin, half_a + margin))?;

    // The grain's correlation peak is a cell or two wide: search every shift at half resolution,
    // then ±2 cells around the best at full resolution, then sub-cell.
    let (ca, cb) = (pa.halved(), pb.halved());
    let rs = (margin / cell / 2.0).ceil() as i64;
    let rz = (options.max_axial_mm / cell / 2.0).ceil() as i64;
    // Every other cell of the overlap is plenty to find the peak at this level.
    let coarse = StrideTwo::new(&ca.gray, (ca.ns, ca.nz), &cb.gray, (cb.ns, cb.nz));
    let mut best = (f64::MIN, 0i64, 0i64);
    for dz in -rz..=rz {
        for ds in -rs..=rs {
            let (c, _) = coarse.ncc(ca.s0 - ds - cb.s0, ca.z0 - dz - cb.z0, 70);
            if c > best.0 {
                best = (c, ds, dz);
            }
        }
    }
    let (fine_a, fine_b) =
        (TextureGrid::sampled(&pa.gray, pa.ns, pa.nz, 1, 0, 0), TextureGrid::sampled(&pb.gray, pb.ns, pb.nz, 1, 0, 0));
    let ncc = |ds: i64, dz: i64| ncc_grids(&fine_a, &fine_b, pa.s0 - ds - pb.s0, pa.z0 - dz - pb.z0, 220);
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
    let frac_s = sub_cell(ncc(ds - 1, dz).0, peak, ncc(ds + 1, dz).0);
    let frac_z = sub_cell(ncc(ds, dz - 1).0, peak, ncc(ds, dz + 1).0);
    // Radial offset over the aligned overlap.
    let mut dr = Vec::new();
    for z in 0..pa.nz {
        for s in 0..pa.ns {
            let ra = pa.radius[z * pa.ns + s];
            let rb = pb.at(&pb.radius, pa.s0 + s as i64 - ds, pa.z0 + z as i64 - dz);
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
        shift_angle_deg: ((ds as f64 + frac_s) * cell / radius_ref).to_degrees(),
        shift_axial_mm: (dz as f64 + frac_z) * cell,
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
            let dang = wrap((poses[b].angle_deg - poses[a].angle_deg).to_radians()).to_degrees().abs();
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

/// Solves, per axis, min Σ w (c_b − c_a − m)² + (Σ c)², with Huber reweighting of the pairs.
fn solve_axis(n: usize, pairs: &[(usize, usize, f64)], huber: f64) -> Vec<f64> {
    let mut weights = vec![1.0; pairs.len()];
    let mut c = vec![0.0; n];
    for _ in 0..5 {
        let mut lhs = nalgebra::DMatrix::<f64>::from_element(n, n, 1.0); // the gauge term
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

/// Registers all views. `views[v]` are the samples of view v back-projected with its encoder pose
/// `poses[v]` ([`view_samples`]).
pub fn register(
    views: &[ViewSamples],
    poses: &[ViewPose],
    radius_ref: f64,
    half_angle_deg: f64,
    half_axial_mm: f64,
    options: &RegisterOptions,
) -> Registration {
    use rayon::prelude::*;
    let angles: Vec<f64> = poses.iter().map(|p| p.angle_deg.to_radians()).collect();
    let candidates = overlapping_pairs(poses, half_angle_deg, half_axial_mm);
    let mut pairs: Vec<PairMeasure> =
        candidates.par_iter().filter_map(|&(a, b)| measure_pair(a, b, views, &angles, radius_ref, options)).collect();
    let n = poses.len();
    let axis = |f: &dyn Fn(&PairMeasure) -> f64, huber: f64| {
        solve_axis(n, &pairs.iter().map(|p| (p.a, p.b, f(p))).collect::<Vec<_>>(), huber)
    };
    let angle = axis(&|p| p.shift_angle_deg, 0.02);
    let axial = axis(&|p| p.shift_axial_mm, 0.01);
    let radial = axis(&|p| p.shift_radius_mm, 0.01);
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
        let coarse = StrideTwo::new(&a, (ans, anz), &b, (bns, bnz));
        for off_s in -4..=5i64 {
            for off_z in -3..=4i64 {
                let want = brute_ncc(&a, (ans, anz), &b, (bns, bnz), (off_s, off_z), 1);
                let (got, _) = ncc_grids(&full.0, &full.1, off_s, off_z, 20);
                assert!((got - want).abs() < 1e-5, "full ({off_s}, {off_z}): {got} vs {want}");
                let want = brute_ncc(&a, (ans, anz), &b, (bns, bnz), (off_s, off_z), 2);
                let (got, _) = coarse.ncc(off_s, off_z, 20);
                assert!((got - want).abs() < 1e-5, "stride 2 ({off_s}, {off_z}): {got} vs {want}");
            }
        }
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
