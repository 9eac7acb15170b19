//! One overlap: which views overlap, and the shift between them that the correlation measures.

use super::*;
use crate::numeric::stats::median;

/// Why a candidate overlap was not measured, with what its correlation found, and the two views'
/// radial offset at their encoder poses where it can be read ([`radius_at_encoders`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Refusal {
    pub(super) status: PairStatus,
    pub(super) peak_ncc: Option<f64>,
    pub(super) rival_ratio: Option<f64>,
    pub(super) overlap_cells: Option<usize>,
    pub(super) radius_shift_mm: Option<f64>,
}

/// Cells two views must share at their encoder poses for their radial offset to be read there.
const MIN_RADIUS_CELLS: usize = 100;

/// The median over the cells views a and b share at their encoder poses of a's mean radius minus
/// b's, mm: the lens-radius correction b needs relative to a, where the texture did not register
/// the pair. The encoders' error moves b's thread profile against a's along the helix, which
/// makes the cells' differences swing both ways on the flanks; over a shared strip at least
/// `min_span_mm` (a pitch) long in z the swings cancel in the median, leaving the radial offset
/// and the taper over the encoders' axial error (0.3 mm × 1/32: 9 µm). None where they share
/// fewer cells or a shorter strip.
fn radius_at_encoders(
    pa: &lattice::Patch,
    pb: &lattice::Patch,
    turn: i64,
    cell_z_mm: f64,
    min_span_mm: f64,
) -> Option<f64> {
    let (mut dr, rows) = radius_differences(pa, pb, turn, 0, 0);
    if dr.len() < MIN_RADIUS_CELLS || rows as f64 * cell_z_mm < min_span_mm {
        return None;
    }
    median(&mut dr)
}

/// a's mean radius minus b's over the cells the two share with b's content moved by (`ds`, `dz`)
/// cells onto a's, mm, and how many rows along z those cells span (first to last).
fn radius_differences(pa: &lattice::Patch, pb: &lattice::Patch, turn: i64, ds: i64, dz: i64) -> (Vec<f64>, usize) {
    let mut dr = Vec::new();
    let (mut z_lo, mut z_hi) = (usize::MAX, 0);
    for z in 0..pa.nz {
        for s in 0..pa.ns {
            let ra = pa.radius[z * pa.ns + s];
            let rb = pb.at(&pb.radius, pa.s0 + s as i64 - ds - turn, pa.z0 + z as i64 - dz);
            if ra.is_finite() && rb.is_finite() {
                dr.push((ra - rb) as f64);
                z_lo = z_lo.min(z);
                z_hi = z_hi.max(z);
            }
        }
    }
    let rows = if dr.is_empty() { 0 } else { z_hi - z_lo + 1 };
    (dr, rows)
}

/// The strongest correlation of the coarse search away from its peak (more than two coarse cells
/// from it along either axis, beyond the peak's own width), as a fraction of the peak's: a second
/// alignment nearly as good as the best one means the texture does not decide between them.
fn rival_ratio(surface: &[(f64, i64, i64)], best: (f64, i64, i64)) -> f64 {
    let rival = surface
        .iter()
        .filter(|&&(_, ds, dz)| (ds - best.1).abs() > 2 || (dz - best.2).abs() > 2)
        .map(|&(c, _, _)| c)
        .fold(-1.0, f64::max);
    if best.0 > 0.0 { rival / best.0 } else { 1.0 }
}

/// Measures one pair of overlapping views. `fine` holds the two views' full-resolution
/// correlation grids (buffers reused from pair to pair); `pitch_mm` is the thread's, over which a
/// refused pair's radial offset is read ([`radius_at_encoders`]).
pub(super) fn measure_pair(
    a: usize,
    b: usize,
    views: &[ViewGrid],
    lattice: &Lattice,
    pitch_mm: f64,
    options: &RegisterOptions,
    fine: &mut (TextureGrid, TextureGrid),
) -> Result<PairMeasure, Refusal> {
    let (va, vb) = (&views[a], &views[b]);
    let (pa, pb) = (&va.patch, &vb.patch);
    if pa.gray.is_empty() || pb.gray.is_empty() {
        return Err(Refusal {
            status: PairStatus::NoData,
            peak_ncc: None,
            rival_ratio: None,
            overlap_cells: None,
            radius_shift_mm: None,
        });
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
    let mut surface = Vec::with_capacity(((2 * rs + 1) * (2 * rz + 1)) as usize);
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
            surface.push((c, ds, dz));
            if c > best.0 {
                best = (c, ds, dz);
            }
        }
    }
    let rival_ratio = rival_ratio(&surface, best);
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
    let refused = |status| Refusal {
        status,
        peak_ncc: Some(peak),
        rival_ratio: Some(rival_ratio),
        overlap_cells: Some(cells),
        radius_shift_mm: radius_at_encoders(pa, pb, turn, lattice.cell_z_mm, pitch_mm),
    };
    if cells < options.min_overlap_cells {
        return Err(refused(PairStatus::TooSmall));
    }
    if peak < options.min_ncc || rival_ratio > options.max_rival_ratio {
        return Err(refused(if peak < options.min_ncc { PairStatus::TooWeak } else { PairStatus::Ambiguous }));
    }
    // Along z the texture is the grain as imaged, whose correlation peak is close to a Gaussian;
    // along the arc it was high-passed (its mean over ±4 cells removed, `texture`), which narrows
    // the peak and gives it negative side lobes, so the parabola stays there (docs/notebook/
    // accuracy.md, Registration: the sub-cell step along z).
    let frac_s = sub_cell(ncc(ds - 1, dz).0, peak, ncc(ds + 1, dz).0);
    let frac_z = sub_cell_gaussian(ncc(ds, dz - 1).0, peak, ncc(ds, dz + 1).0);
    // Radial offset over the aligned overlap.
    let (mut dr, _) = radius_differences(pa, pb, turn, ds, dz);
    let Some(shift_radius_mm) = median(&mut dr) else {
        return Err(Refusal { radius_shift_mm: None, ..refused(PairStatus::NoData) });
    };
    Ok(PairMeasure {
        a,
        b,
        shift_angle_deg: ((ds as f64 + frac_s) * lattice.cell_arc_mm / lattice.radius_ref_mm).to_degrees(),
        shift_axial_mm: (dz as f64 + frac_z) * lattice.cell_z_mm,
        shift_radius_mm,
        peak_ncc: peak,
        rival_ratio,
        overlap_cells: cells,
        residual_angle_deg: 0.0,
        residual_axial_um: 0.0,
        residual_radius_um: 0.0,
    })
}

/// How far apart, in footprint half-widths, two views may stand and still be taken to overlap:
/// two, so that every pair whose footprints overlap at the encoder poses is a candidate, however
/// narrow the overlap (a station may overlap its views by 3° of a 25° footprint). Whether the
/// overlap suffices is the measurement's to say, and the report's to show (`too_small`).
pub(super) const NEIGHBOUR_REACH: f64 = 2.0;

/// Pairs of views whose footprints overlap: same axial row and adjacent in angle, or same angle and
/// adjacent in z, judged from the encoder poses and the footprint sizes.
pub fn overlapping_pairs(poses: &[ViewPose], half_angle_deg: f64, half_axial_mm: f64) -> Vec<(usize, usize)> {
    let mut pairs = Vec::new();
    for a in 0..poses.len() {
        for b in a + 1..poses.len() {
            let dang = wrap_pi((poses[b].angle_deg - poses[a].angle_deg).to_radians()).to_degrees().abs();
            let dz = (poses[b].axial_mm - poses[a].axial_mm).abs();
            let angular = dang < NEIGHBOUR_REACH * half_angle_deg && dz < 0.5 * half_axial_mm;
            let axial = dang < 0.5 * half_angle_deg && dz < NEIGHBOUR_REACH * half_axial_mm;
            if angular || axial {
                pairs.push((a, b));
            }
        }
    }
    pairs
}

/// How much the lens-radius corrections `radius_a_mm` and `radius_b_mm` of views a and b move
/// their pair's measured arc shift, in degrees: each view's points move by its correction δ along
/// its optical axis, which at angle φ from the view's centre is δ·sin φ along the arc, and the
/// overlap is centred half the views' (encoder) spacing from each centre, on opposite sides.
pub(super) fn lens_radius_arc_shift_deg(
    pose_a: &ViewPose,
    pose_b: &ViewPose,
    radius_a_mm: f64,
    radius_b_mm: f64,
    lattice: &Lattice,
) -> f64 {
    let half_spacing = 0.5 * wrap_pi((pose_b.angle_deg - pose_a.angle_deg).to_radians());
    ((radius_a_mm + radius_b_mm) * half_spacing.sin() / lattice.radius_ref_mm).to_degrees()
}
