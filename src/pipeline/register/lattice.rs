//! Each view binned on the ring's unrolled (arc, z) lattice: gray, radius and confidence per cell,
//! and the texture (gray with its smooth trend removed) that pairs are correlated on.

use super::*;

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
    pub(super) fn turn_cells(&self, angle_a_rad: f64, angle_b_rad: f64) -> i64 {
        let raw = angle_b_rad - angle_a_rad;
        ((wrap_pi(raw) - raw) / TAU).round() as i64 * self.cells_around
    }
}

/// A view's points binned on a grid of lattice cells.
pub(super) struct Patch {
    pub(super) s0: i64,
    pub(super) z0: i64,
    pub(super) ns: usize,
    pub(super) nz: usize,
    pub(super) gray: Vec<f32>,
    pub(super) radius: Vec<f32>,
}

/// What registration keeps of a view, computed once (every pair that includes the view reuses
/// it): its texture and radius on the [`Lattice`], and the texture's grids for the coarse and the
/// fine correlation.
pub struct ViewGrid {
    /// The view's own angle, rad.
    pub(super) angle_rad: f64,
    /// Texture ([`texture`]) and mean radius per cell.
    pub(super) patch: Patch,
    /// The half-resolution texture's origin and its stride-two grids ([`StrideTwo`]).
    pub(super) coarse_origin: (i64, i64),
    pub(super) coarse: StrideTwo,
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
/// and the sub-cell peak would be skewed.
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
pub(super) fn fill_single_gaps_along_arc(field: &mut [f32], ns: usize) {
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

    pub(super) fn at(&self, field: &[f32], s: i64, z: i64) -> f32 {
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
pub(super) fn texture(gray: &[f32], radius: &[f32], ns: usize, nz: usize) -> Vec<f32> {
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
    normalise_contrast(&out, ns, nz, ALONG, CONTRAST_ACROSS)
}

/// Cells along the axis, to either side, over which [`normalise_contrast`] reads the contrast
/// (along the arc it reads the high-pass's own ±4).
const CONTRAST_ACROSS: usize = 2;

/// Each cell of the high-passed texture divided by its neighbourhood's RMS (±`along` cells along
/// the arc, ±`across` along the axis). At random stations, strong correlation peaks (0.5–0.7 NCC)
/// at wrong alignments between neighbouring views outweighed the texture at the true one; a
/// modulation of the texture's contrast tied to each view is the suspected cause (the all-in-focus
/// image's sharpness varies in bands where the cylinder's depth falls between two frames).
/// Dividing by the local contrast keeps the texture's pattern and takes such a modulation out:
/// tuning station 12 registered 0.31° RMS off instead of 0.75° (encoders 0.50°), station 1's five
/// wrong pairs were refused (0.69° → its encoders' 0.30°); of the stations whose pairs were right,
/// three of the suite's lost one pair each, the rest kept theirs (docs/notebook/accuracy.md,
/// Stations: wrong peaks, misread corners, a U on every height).
pub(super) fn normalise_contrast(texture: &[f32], ns: usize, nz: usize, along: usize, across: usize) -> Vec<f32> {
    let mut out = vec![f32::NAN; texture.len()];
    // Per column, the sum of squares and the count over the ±`across` rows; then a window slides
    // along the row over them.
    let (mut column_sq, mut column_n) = (vec![0f64; ns], vec![0u32; ns]);
    for z in 0..nz {
        column_sq.iter_mut().for_each(|c| *c = 0.0);
        column_n.iter_mut().for_each(|c| *c = 0);
        for zz in z.saturating_sub(across)..(z + across + 1).min(nz) {
            for (s, &t) in texture[zz * ns..(zz + 1) * ns].iter().enumerate() {
                if t.is_finite() {
                    column_sq[s] += f64::from(t * t);
                    column_n[s] += 1;
                }
            }
        }
        let (mut sum_sq, mut n) = (0f64, 0u32);
        for s in 0..along.min(ns) {
            sum_sq += column_sq[s];
            n += column_n[s];
        }
        for s in 0..ns {
            if s + along < ns {
                sum_sq += column_sq[s + along];
                n += column_n[s + along];
            }
            if s > along {
                sum_sq -= column_sq[s - along - 1];
                n -= column_n[s - along - 1];
            }
            let t = texture[z * ns + s];
            if t.is_finite() && n > 0 {
                let rms = (sum_sq.max(0.0) / f64::from(n)).sqrt() as f32;
                if rms > 0.0 {
                    out[z * ns + s] = t / rms;
                }
            }
        }
    }
    out
}
