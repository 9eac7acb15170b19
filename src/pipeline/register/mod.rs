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

pub mod anchor;
mod lattice;
mod ncc;
mod pair;
mod pose_graph;

pub use anchor::{EndFace, anchor, corners};
pub use lattice::{GridScratch, Lattice, ViewGrid, view_grid};
pub use pair::overlapping_pairs;

use crate::domain::optics::ViewPose;
use crate::numeric::angle::wrap_pi;
use crate::pipeline::cloud::SurfacePoint;
use ncc::*;
use pair::*;
use pose_graph::solve_axis;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PoseCorrection {
    /// What registration added to the view's angle, degrees.
    pub angle_deg: f64,
    /// To its axial position, mm.
    pub axial_mm: f64,
    /// To its lens radius, mm.
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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PairMeasure {
    /// The first view's index in the bundle's `views`.
    pub a: usize,
    /// The second view's.
    pub b: usize,
    /// Measured along the arc, less what the two views' solved lens-radius corrections account
    /// for there (see [`register`]).
    pub shift_angle_deg: f64,
    /// The shift along the pipe axis, mm.
    pub shift_axial_mm: f64,
    /// The shift in radius, mm.
    pub shift_radius_mm: f64,
    /// Normalised cross-correlation at the peak (1 = identical texture).
    pub peak_ncc: f64,
    /// The strongest alignment of the coarse search away from the peak, as a fraction of the
    /// peak's (see `PairCandidate`).
    #[serde(default)]
    pub rival_ratio: f64,
    /// Cells of the unrolled surface the two views share at that shift.
    pub overlap_cells: usize,
    /// Disagreement with the solved corrections after the graph solve.
    pub residual_angle_deg: f64,
    /// The axial disagreement, µm.
    pub residual_axial_um: f64,
    /// The radial disagreement, µm.
    pub residual_radius_um: f64,
}

/// What became of a candidate overlap (two views whose footprints overlap at their encoder poses).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum PairStatus {
    /// Measured and in the solve.
    Measured,
    /// Measured and in the solve, but its residual after the solve is more than three times the
    /// robust kernel's bound on some axis: the kernel gave it under a third of a pair's weight.
    Outlier,
    /// The correlation peak is weaker than `min_ncc`: too little texture in the overlap to trust.
    TooWeak,
    /// A second alignment correlates nearly as well as the best (over `max_rival_ratio` of it):
    /// the texture does not decide between them.
    Ambiguous,
    /// The aligned overlap is smaller than `min_overlap_cells`.
    TooSmall,
    /// A view has no trusted point in the overlap.
    NoData,
    /// Measured, but the solve with it moved a view further from its encoder pose than the
    /// search assumes the encoders can err (half the relative search range: ±1.25°, ±0.4 mm by
    /// default): a strong correlation peak at a wrong alignment. Left out of the solve.
    Implausible,
}

/// A candidate overlap and what became of it, with what its correlation found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PairCandidate {
    /// The first view's index in the bundle's `views`.
    pub a: usize,
    /// The second view's.
    pub b: usize,
    /// Measured, an outlier, or why it was not measured (too weak, too small, ambiguous, …).
    pub status: PairStatus,
    /// The correlation peak at the best shift found, when the search ran.
    pub peak_ncc: Option<f64>,
    /// The strongest alignment away from that peak (beyond its own width) in the coarse search, as
    /// a fraction of the peak's: near 1, the texture does not decide between two alignments.
    #[serde(default)]
    pub rival_ratio: Option<f64>,
    /// Cells the two views share at that shift, when the search ran.
    pub overlap_cells: Option<usize>,
    /// Where the texture did not register the pair: the median over the cells the two views
    /// share at their encoder poses of a's radius minus b's, µm, when they share a pitch's length
    /// along z. The radial solve places views that no measured overlap holds by it (an overlap
    /// whose texture does not register still shows the same surface).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radius_shift_um: Option<f64>,
}

/// The loop closure of a ring in one axial row: the measured shifts summed around the ring, which
/// is zero for perfect measurements; its size is the ring's accumulated measurement error.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct RingClosure {
    /// Views in the ring.
    pub views: usize,
    /// The angles summed around the ring, degrees.
    pub angle_deg: f64,
    /// The axial shifts summed around the ring, µm.
    pub axial_um: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Registration {
    /// Per view (in the bundle's order), what registration changed of its encoder pose.
    pub corrections: Vec<PoseCorrection>,
    /// The measured pairs (status measured or outlier), with their residuals.
    pub pairs: Vec<PairMeasure>,
    /// Every candidate overlap and its status (reports stored before this existed load empty).
    #[serde(default)]
    pub candidates: Vec<PairCandidate>,
    /// Candidate overlaps, and how many of them were measured (outliers included).
    #[serde(default)]
    pub pairs_expected: usize,
    /// Of those, how many were measured (outliers included).
    #[serde(default)]
    pub pairs_measured: usize,
    /// Views none of whose overlaps was measured: they keep their encoder poses (but see
    /// `placed_radially` and `placed_by_end_face`).
    #[serde(default)]
    pub unregistered_views: Vec<usize>,
    /// Views that the radial solve placed, besides the measured overlaps, by the radius of
    /// overlaps whose texture did not register ([`PairCandidate::radius_shift_um`]): their lens
    /// radius is corrected, their angle and axial position are the encoders'.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub placed_radially: Vec<usize>,
    /// Unregistered views that saw the end face and were placed axially by their own corner (the
    /// end face is z = 0 by the contract) instead of keeping their encoder's axial position.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub placed_by_end_face: Vec<usize>,
    /// Unregistered views whose own corner would have moved them axially further than the encoders
    /// can err (the same bound as the pairs': half the axial search range): the corner is taken
    /// as misread and the view keeps its encoder's axial position.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub end_face_implausible: Vec<usize>,
    /// The ring's closure, where the views form one ring in one axial row and every overlap
    /// around it was measured.
    #[serde(default)]
    pub closure: Option<RingClosure>,
}

/// The robust kernel's bound per axis (Huber), in cells of the lattice (an object pixel): a
/// quarter radially and axially, half along the arc (at the standard station's 41 µm pixel,
/// 0.01 mm, 0.02° and 0.01 mm). A pair's correlation peak is located to a fraction of a cell,
/// so the bounds follow the pixel, not a length fixed to one station.
const HUBER_RADIUS_CELLS: f64 = 0.25;
const HUBER_ARC_CELLS: f64 = 0.5;
const HUBER_AXIAL_CELLS: f64 = 0.25;
/// A residual beyond this many kernel bounds marks a pair as an outlier.
const OUTLIER_BOUNDS: f64 = 3.0;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RegisterOptions {
    /// Search half ranges (encoder error bounds, relative between two views).
    pub max_angle_deg: f64,
    pub max_axial_mm: f64,
    /// Pairs whose correlation peak is weaker than this, or whose aligned overlap is smaller than
    /// this many cells (object pixels: the unrolled overlap grids' cell is the bundle's object
    /// pixel), are not trusted.
    pub min_ncc: f64,
    pub min_overlap_cells: usize,
    /// Pairs with a second alignment this close to the best one (as a fraction of its
    /// correlation, in the coarse search) are ambiguous and not trusted (options stored before
    /// this existed load with the default).
    #[serde(default = "default_max_rival_ratio")]
    pub max_rival_ratio: f64,
}

/// Chosen with `min_ncc` on the accuracy suite, five held-out cases and the ci preset with its
/// grain weakened (docs/notebook/accuracy.md, Registration on weak texture).
fn default_max_rival_ratio() -> f64 {
    0.7
}

impl RegisterOptions {
    /// How far one view's encoder may err (angle °, axial mm), as the search assumes: half its
    /// relative range between two views. A correction beyond it rests on a misreading.
    pub fn encoder_bounds(&self) -> (f64, f64) {
        (0.5 * self.max_angle_deg, 0.5 * self.max_axial_mm)
    }
}

impl Default for RegisterOptions {
    fn default() -> Self {
        Self {
            max_angle_deg: 2.5,
            max_axial_mm: 0.8,
            min_ncc: 0.3,
            min_overlap_cells: 2000,
            max_rival_ratio: default_max_rival_ratio(),
        }
    }
}

/// Registers all views. `views[v]` is view v back-projected with its encoder pose `poses[v]` and
/// binned on `lattice` ([`view_grid`]); `pitch_mm` is the thread's.
pub fn register(
    views: &[ViewGrid],
    poses: &[ViewPose],
    lattice: &Lattice,
    half_angle_deg: f64,
    half_axial_mm: f64,
    pitch_mm: f64,
    options: &RegisterOptions,
) -> Registration {
    use rayon::prelude::*;
    let overlaps = overlapping_pairs(poses, half_angle_deg, half_axial_mm);
    let measured: Vec<Result<PairMeasure, Refusal>> = overlaps
        .par_iter()
        .map_init(Default::default, |fine, &(a, b)| measure_pair(a, b, views, lattice, pitch_mm, options, fine))
        .collect();
    let mut candidates: Vec<PairCandidate> = overlaps
        .iter()
        .zip(&measured)
        .map(|(&(a, b), m)| match m {
            Ok(p) => PairCandidate {
                a,
                b,
                status: PairStatus::Measured,
                peak_ncc: Some(p.peak_ncc),
                rival_ratio: Some(p.rival_ratio),
                overlap_cells: Some(p.overlap_cells),
                radius_shift_um: None,
            },
            Err(r) => PairCandidate {
                a,
                b,
                status: r.status,
                peak_ncc: r.peak_ncc,
                rival_ratio: r.rival_ratio,
                overlap_cells: r.overlap_cells,
                radius_shift_um: r.radius_shift_mm.map(|mm| 1e3 * mm),
            },
        })
        .collect();
    let mut pairs: Vec<PairMeasure> = measured.into_iter().flatten().collect();
    let n = poses.len();
    let huber_radius_mm = HUBER_RADIUS_CELLS * lattice.cell_z_mm;
    let huber_angle_deg = (HUBER_ARC_CELLS * lattice.cell_arc_mm / lattice.radius_ref_mm).to_degrees();
    let huber_axial_mm = HUBER_AXIAL_CELLS * lattice.cell_z_mm;
    let radial = solve_pairs_axis(n, &pairs, &|p| p.shift_radius_mm, huber_radius_mm);
    // A lens-radius error moves all of a view's points along its optical axis, which is radial
    // only at the view's centre: a point φ off it moves δ·sin φ along the arc. In an overlap, half
    // the views' spacing to either side of their centres, that adds (δ_a + δ_b)·sin(spacing/2)
    // to the measured arc shift. The radial solve knows the δs far better than that shift, so
    // that part is taken out before the angle is solved (figures: docs/notebook/accuracy.md).
    for p in pairs.iter_mut() {
        p.shift_angle_deg -= lens_radius_arc_shift_deg(&poses[p.a], &poses[p.b], radial[p.a], radial[p.b], lattice);
    }
    let (radial, angle, axial) = solve_within_encoder_bounds(
        n,
        &mut pairs,
        &mut candidates,
        Kernels { radius_mm: huber_radius_mm, angle_deg: huber_angle_deg, axial_mm: huber_axial_mm },
        options.encoder_bounds(),
    );
    let (radial, placed_radially) = place_radially(n, &pairs, &candidates, radial, huber_radius_mm);
    for p in pairs.iter_mut() {
        p.residual_angle_deg = angle[p.b] - angle[p.a] - p.shift_angle_deg;
        p.residual_axial_um = 1e3 * (axial[p.b] - axial[p.a] - p.shift_axial_mm);
        p.residual_radius_um = 1e3 * (radial[p.b] - radial[p.a] - p.shift_radius_mm);
    }
    for p in &pairs {
        let outlier = p.residual_radius_um.abs() > 1e3 * OUTLIER_BOUNDS * huber_radius_mm
            || p.residual_angle_deg.abs() > OUTLIER_BOUNDS * huber_angle_deg
            || p.residual_axial_um.abs() > 1e3 * OUTLIER_BOUNDS * huber_axial_mm;
        if let Some(c) = candidates.iter_mut().find(|c| (c.a, c.b) == (p.a, p.b)).filter(|_| outlier) {
            c.status = PairStatus::Outlier;
        }
    }
    let unregistered_views = (0..n).filter(|&v| !pairs.iter().any(|p| p.a == v || p.b == v)).collect();
    let corrections =
        (0..n).map(|v| PoseCorrection { angle_deg: angle[v], axial_mm: axial[v], lens_radius_mm: radial[v] }).collect();
    Registration {
        corrections,
        pairs_expected: candidates.len(),
        pairs_measured: pairs.len(),
        closure: ring_closure(poses, &pairs, half_angle_deg),
        candidates,
        pairs,
        unregistered_views,
        placed_radially,
        placed_by_end_face: Vec::new(),
        end_face_implausible: Vec::new(),
    }
}

/// The lens-radius corrections again, with the refused overlaps' radial offsets at the encoder
/// poses ([`PairCandidate::radius_shift_um`]) tying together what the measured pairs leave apart
/// (only those between different components of the measured pairs' graph: within one, the
/// measured pairs know the radius better). Where none does, `radial` as it was. Returns the
/// corrections and the views those offsets placed.
fn place_radially(
    n: usize,
    pairs: &[PairMeasure],
    candidates: &[PairCandidate],
    radial: Vec<f64>,
    huber_mm: f64,
) -> (Vec<f64>, Vec<usize>) {
    let component = crate::numeric::union_find::components(n, pairs.iter().map(|p| (p.a, p.b)));
    let links: Vec<(usize, usize, f64)> = candidates
        .iter()
        .filter(|c| matches!(c.status, PairStatus::TooSmall | PairStatus::TooWeak | PairStatus::Ambiguous))
        .filter(|c| component[c.a] != component[c.b])
        .filter_map(|c| Some((c.a, c.b, 1e-3 * c.radius_shift_um?)))
        .collect();
    if links.is_empty() {
        return (radial, Vec::new());
    }
    let placed: std::collections::BTreeSet<usize> = links.iter().flat_map(|&(a, b, _)| [a, b]).collect();
    let all: Vec<(usize, usize, f64)> = pairs.iter().map(|p| (p.a, p.b, p.shift_radius_mm)).chain(links).collect();
    (solve_axis(n, &all, huber_mm), placed.into_iter().collect())
}

/// One axis of the pose graph over the measured pairs: `f` reads a pair's shift on that axis.
fn solve_pairs_axis(n: usize, pairs: &[PairMeasure], f: &dyn Fn(&PairMeasure) -> f64, huber: f64) -> Vec<f64> {
    solve_axis(n, &pairs.iter().map(|p| (p.a, p.b, f(p))).collect::<Vec<_>>(), huber)
}

/// The robust kernel's bounds of the three axes' solves.
#[derive(Clone, Copy)]
pub(super) struct Kernels {
    pub radius_mm: f64,
    pub angle_deg: f64,
    pub axial_mm: f64,
}

/// Solves the pose graph (lens radius, angle, axial corrections per view) with the pairs, but
/// none whose solve moves a view further than `bounds` (angle, axial) from its encoder pose.
///
/// The search assumes each encoder errs by at most half its relative range: a solve that moves a
/// view further rests on a wrong alignment (at random stations, peaks of 0.5–0.7 NCC at wrong
/// alignments moved views by up to 3° against encoders off by 0.5° RMS). Of the pairs of views
/// beyond the bound, the one that asks the largest move is dropped (status `implausible`) and the
/// pairs left are solved again, until no view is beyond it.
pub(super) fn solve_within_encoder_bounds(
    n: usize,
    pairs: &mut Vec<PairMeasure>,
    candidates: &mut [PairCandidate],
    kernels: Kernels,
    (bound_angle_deg, bound_axial_mm): (f64, f64),
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let asks =
        |p: &PairMeasure| (p.shift_angle_deg / bound_angle_deg).abs().max((p.shift_axial_mm / bound_axial_mm).abs());
    loop {
        let angle = solve_pairs_axis(n, pairs, &|p| p.shift_angle_deg, kernels.angle_deg);
        let axial = solve_pairs_axis(n, pairs, &|p| p.shift_axial_mm, kernels.axial_mm);
        let beyond = |v: usize| angle[v].abs() > bound_angle_deg || axial[v].abs() > bound_axial_mm;
        // One pair a pass: a view can be beyond the bound only because a wrong pair elsewhere in
        // its component moved the component's mean, so dropping each such view's own largest
        // pair at once would drop good ones (a chain with a wrong pair in its middle puts every
        // view beyond); the largest ask among the pairs of views beyond it is the wrong one.
        let Some(dropped) = pairs
            .iter()
            .filter(|p| beyond(p.a) || beyond(p.b))
            .max_by(|x, y| asks(x).total_cmp(&asks(y)))
            .map(|p| (p.a, p.b))
        else {
            return (solve_pairs_axis(n, pairs, &|p| p.shift_radius_mm, kernels.radius_mm), angle, axial);
        };
        for c in candidates.iter_mut().filter(|c| (c.a, c.b) == dropped) {
            c.status = PairStatus::Implausible;
        }
        pairs.retain(|p| (p.a, p.b) != dropped);
    }
}

/// The closure of the ring the views form, where they stand in one axial row around the whole
/// turn (no gap between neighbours wider than a footprint allows to overlap) and every overlap
/// between neighbours was measured: the measured shifts summed once around.
fn ring_closure(poses: &[ViewPose], pairs: &[PairMeasure], half_angle_deg: f64) -> Option<RingClosure> {
    let n = poses.len();
    let one_row = poses.iter().all(|p| (p.axial_mm - poses[0].axial_mm).abs() < 1e-9);
    if n < 3 || !one_row {
        return None;
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| poses[a].angle_deg.rem_euclid(360.0).total_cmp(&poses[b].angle_deg.rem_euclid(360.0)));
    let (mut angle_deg, mut axial_mm) = (0.0, 0.0);
    for k in 0..n {
        let (from, to) = (order[k], order[(k + 1) % n]);
        let gap_deg = (poses[to].angle_deg - poses[from].angle_deg).rem_euclid(360.0);
        if gap_deg >= NEIGHBOUR_REACH * half_angle_deg {
            return None;
        }
        // Each pair measures c_b − c_a; walking from `from` to `to` adds it, or takes it off.
        let step = pairs.iter().find_map(|p| match (p.a, p.b) {
            (a, b) if (a, b) == (from, to) => Some((p.shift_angle_deg, p.shift_axial_mm)),
            (a, b) if (a, b) == (to, from) => Some((-p.shift_angle_deg, -p.shift_axial_mm)),
            _ => None,
        })?;
        angle_deg += step.0;
        axial_mm += step.1;
    }
    Some(RingClosure { views: n, angle_deg, axial_um: 1e3 * axial_mm })
}

#[cfg(test)]
mod tests;
