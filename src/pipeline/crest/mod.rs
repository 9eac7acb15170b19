//! Black-crest detection, both ways the seed names.
//!
//! Photometric: a crest showing mill scale is far darker than machined steel under the coaxial
//! light. Each thread's crest brightness per bin (on the crest centre line) is compared with the
//! median crest brightness of the part (most crests are machined): dark is below a fraction of it,
//! or below it by many times the machined crests' own scatter, whichever is the higher bar, or,
//! for a sustained dip (the median of five bins along the helix), below it by fewer scatters.
//!
//! Geometric: a black crest is the mill surface, which lies below the cone the chaser cut, so a
//! crest is on the mill surface where it falls below the machined crest cone. The cone is fitted to
//! every crest of the part (r = a + b·z + c·cos θ + d·sin θ: the lathe cuts a round cone whose axis
//! may sit off the pipe frame's), trimmed one-sidedly so that black crests do not pull it down. The
//! deficit below it, median-filtered along the helix, starts a black run where it clearly exceeds
//! the noise and extends it while it stays above a lower threshold (hysteresis: the mill surface
//! meets the cone at a shallow angle, so a black crest's ends are shallow). This catches crests
//! polished to look machined, and unlike a height threshold it does not mistake a vanishing thread
//! (shallow because its root rises, its crest still machined) for a black one. The end chamfer is
//! machined: crests within 1.5 pitches of the end face that look machined are flagged as chamfer,
//! never as black, unless the crest at the same angle beyond that zone is black too (the cone
//! rises away from the end face, so the mill surface that stands below it there stands below it
//! on every later turn; the chamfer cuts the first crests alone).

mod arch;
mod chamfer;
mod cone;
mod dark;

use crate::domain::rules::{CrestBin, ThreadObservation};
use crate::numeric::runs::{grow_runs, run_spans};
use crate::numeric::stats::{median, robust_scale};
use crate::pipeline::profile::ThreadMeasure;
use arch::*;
use chamfer::*;
use cone::*;
use dark::*;
use nalgebra::{Const, DimMin, Matrix4, SMatrix, SVector, Vector3, Vector4};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CrestOptions {
    /// A crest darker than this fraction of the median crest brightness shows mill scale…
    pub dark_fraction: f32,
    /// …and so does one darker than the median by this many times the crests' robust brightness
    /// scatter, when that is the higher threshold…
    pub dark_sigmas: f32,
    /// …and so does a sustained dip: the median of five bins along the helix below the median by
    /// this many scatters.
    pub dark_run_sigmas: f32,
    /// A dark run extends along the helix over neighbouring bins darker than the median by this
    /// many scatters: at a run's ends the scale is a thin strip on the crest line (a round crest
    /// barely cut by the mill surface) or covers part of the bin, and darkens it by less.
    pub dark_extent_sigmas: f32,
    /// The crests' brightness scatter is taken as at least this fraction of the median, so that
    /// the bars keep a margin where the crests read even (clipped, or noiseless): at random
    /// stations a glossy crest at a view's edge reads 20% dimmer than at its centre
    /// (docs/notebook/accuracy.md, "Stations: black crests out of the dispersion, each thread's
    /// bias"). 0.05 puts a single bin's bar at 70% of the median and a run's at 80%.
    pub min_gray_scatter: f32,
    /// A crest this far below the machined crest cone (median of five bins along the helix) starts
    /// a geometric black run; the threshold rises to four times the crests' own scatter when that
    /// is larger.
    pub mill_onset_um: f64,
    /// A run extends along the helix while the crest stays this far below the cone (or 1.5 times
    /// the scatter, when larger).
    pub mill_extent_um: f64,
    /// A run on geometry alone (no dark bin) must span at least this many degrees along the
    /// helix: the detection limit for polished crests. Depth errors on glossy round crests dip
    /// the crest fit by more than the onset over a few degrees at a time; a polished (or
    /// mill-surface) crest is a stretch of the crest, and mill scale is caught photometrically
    /// at any length.
    pub min_geometric_arc_deg: f64,
    /// Added to the geometric onset threshold (not an option: the decision stage moves the
    /// threshold by the deficit's uncertainty to see whether the verdict holds).
    #[serde(skip)]
    pub onset_shift_um: f64,
}

impl Default for CrestOptions {
    fn default() -> Self {
        Self {
            dark_fraction: 0.45,
            dark_sigmas: 6.0,
            dark_run_sigmas: 4.0,
            dark_extent_sigmas: 2.5,
            min_gray_scatter: 0.05,
            mill_onset_um: 15.0,
            mill_extent_um: 5.0,
            min_geometric_arc_deg: 10.0,
            onset_shift_um: 0.0,
        }
    }
}

/// The machined crest cone r = a + b·z + c·cos θ + d·sin θ fitted to the part's crests.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CrestCone {
    /// The cone's radius at the end face (z = 0), mm.
    pub radius_at_end_mm: f64,
    /// Radial growth per mm of z (half the taper on diameter).
    pub slope: f64,
    /// Offset of the cone's axis from the pipe frame's, x and y.
    pub axis_offset_mm: [f64; 2],
    /// Robust scatter of the median-filtered crest radii about the cone.
    pub scatter_um: f64,
    /// The machined crest bins the cone was fitted to.
    pub crests_fitted: usize,
    /// The thresholds the geometric test used.
    pub onset_um: f64,
    /// How far below the cone, µm, a crest run must reach somewhere to count black by geometry.
    pub extent_um: f64,
}

/// What the crest stage hands on: the rule engine's input per thread, the reference (machined)
/// crest brightness and the fitted crest cone.
#[derive(Clone, Debug)]
pub struct CrestFindings {
    pub observations: Vec<ThreadObservation>,
    pub machined_crest_gray: f32,
    pub cone: Option<CrestCone>,
}

/// The rule engine's input for each thread, the reference crest brightness and the crest cone.
/// `nominal_slope` (half the nominal taper on diameter) seeds the cone fit; `crest_window_half_mm`
/// is the half width along z over which the profile stage fitted each crest's radius.
pub fn observations(
    threads: &[ThreadMeasure],
    lc_mm: f64,
    pitch_mm: f64,
    nominal_slope: f64,
    crest_window_half_mm: f64,
    options: &CrestOptions,
) -> CrestFindings {
    let darkness = darkness(threads, options);
    // The chamfer zone's bins come first along the helix (z rises along it).
    let chamfer_zone_mm = 1.5 * pitch_mm;
    let zone_end = threads
        .iter()
        .flat_map(|t| t.bins.iter())
        .position(|b| b.crest_z_mm >= chamfer_zone_mm)
        .unwrap_or(darkness.dark.len());
    let geometry = mill_surface(threads, &darkness.dark, zone_end, nominal_slope, crest_window_half_mm, options);
    // Bins at one angle are a turn apart in helix order where every thread has a bin per degree
    // (as the profile stage measures them); otherwise the whole zone is the chamfer.
    let per_turn = threads.first().map_or(0, |t| t.bins.len());
    let mill_in_zone = if per_turn > 0 && threads.iter().all(|t| t.bins.len() == per_turn) {
        mill_surface_in_chamfer_zone(&geometry.on_mill, &darkness.dark, zone_end, per_turn)
    } else {
        vec![false; zone_end]
    };
    let observations = thread_observations(threads, lc_mm, pitch_mm, zone_end, &darkness, &geometry, &mill_in_zone);
    CrestFindings { observations, machined_crest_gray: darkness.reference, cone: geometry.cone }
}

/// Photometric evidence, per bin in helix order: the machined crests' reference brightness, which
/// bins are dark, how much of each the scale covers, and which bins start or end a dark run.
struct Darkness {
    reference: f32,
    dark: Vec<bool>,
    cover: Vec<f32>,
    run_end: Vec<(bool, bool)>,
}

fn darkness(threads: &[ThreadMeasure], options: &CrestOptions) -> Darkness {
    let mut grays: Vec<f32> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.crest_gray)).collect();
    grays.sort_by(f32::total_cmp);
    let reference = grays.get(grays.len() / 2).copied().unwrap_or(0.0);
    // Machined crests scatter little about the reference; a thin strip of mill scale (a round
    // crest barely touched by the mill surface) darkens the centre line by less than half, but
    // far beyond that scatter.
    let gray_scatter = (robust_scale(grays.iter().map(|&g| (g - reference) as f64)).unwrap_or(0.0) as f32)
        .max(options.min_gray_scatter * reference);
    let dark_below = (options.dark_fraction * reference).max(reference - options.dark_sigmas * gray_scatter);
    // A sustained dip counts at a lower bar than a single bin: the median of five bins along the
    // helix below the reference by `dark_run_sigmas` scatters (one dark speck cannot make it).
    let run_below = reference - options.dark_run_sigmas * gray_scatter;
    // Only a whole window of five makes a sustained dip: where it is cut short (the start of the
    // helix, next to an unmeasured bin) one or two dim bins would stand for five. The first
    // thread's crest meets the chamfer at the start of the helix and reads dimmer there (a
    // quarter below the reference over its first few degrees on the round presets).
    let run_gray = crate::numeric::sequence::centred_median(
        &threads.iter().flat_map(|t| t.bins.iter().map(|b| b.crest_gray.map(f64::from))).collect::<Vec<_>>(),
        2,
    );
    let in_helix_order = || threads.iter().flat_map(|t| t.bins.iter());
    let seeds: Vec<bool> = in_helix_order()
        .zip(&run_gray)
        .map(|(b, run)| b.crest_gray.is_some_and(|g| g < dark_below) || run.is_some_and(|g| g < run_below as f64))
        .collect();
    let grays: Vec<Option<f32>> = in_helix_order().map(|b| b.crest_gray).collect();
    let extent_below = reference - options.dark_extent_sigmas * gray_scatter;
    // Where the scale thins to a strip at a run's end, one bin can read just above the extent
    // bar between darker ones; a single such bin does not end the run (docs/notebook/accuracy.md,
    // False and short arcs on the round thread).
    let dark = grow_runs(&seeds, |i| grays[i].is_some_and(|g| g < extent_below), 1);
    let cover = dark_cover(&dark, &grays, reference);
    // A run's first and last bins count by how much of them the scale covers.
    let run_end: Vec<(bool, bool)> = (0..dark.len())
        .map(|i| (dark[i] && (i == 0 || !dark[i - 1]), dark[i] && (i + 1 == dark.len() || !dark[i + 1])))
        .collect();
    Darkness { reference, dark, cover, run_end }
}

/// Geometric evidence, per bin in helix order: which crests stand on the mill surface below the
/// machined crest cone, the part of each bin a polished run's fitted ends cover, and the cone.
struct MillSurface {
    on_mill: Vec<bool>,
    mill_part: Vec<Option<[f64; 2]>>,
    cone: Option<CrestCone>,
}

fn mill_surface(
    threads: &[ThreadMeasure],
    dark: &[bool],
    zone_end: usize,
    nominal_slope: f64,
    crest_window_half_mm: f64,
    options: &CrestOptions,
) -> MillSurface {
    let in_helix_order = || threads.iter().flat_map(|t| t.bins.iter());
    // Geometric: the crests' deficits below the cone fitted to the crests beyond the zone, in
    // helix order.
    let crests: Vec<(f64, f64, f64)> = in_helix_order()
        .zip(dark)
        .skip(zone_end)
        .filter(|(_, dark)| !**dark)
        .filter_map(|(b, _)| Some((b.crest_z_mm, b.angle_deg, b.crest_radius_mm?)))
        .collect();
    let (on_mill, mill_part, cone) = match fit_cone(&crests, nominal_slope) {
        None => (vec![false; in_helix_order().count()], vec![None; in_helix_order().count()], None),
        Some((params, used)) => {
            let deficits: Vec<Option<f64>> = in_helix_order()
                .map(|b| b.crest_radius_mm.map(|r| cone_basis(b.crest_z_mm, b.angle_deg).dot(&params) - r))
                .collect();
            let smoothed = crate::numeric::sequence::median_of_five(&deficits);
            let (onset_um, extent_um, scatter_um) = thresholds(&smoothed, options);
            let cone = CrestCone {
                radius_at_end_mm: params[0],
                slope: params[1],
                axis_offset_mm: [params[2], params[3]],
                scatter_um,
                crests_fitted: used,
                onset_um,
                extent_um,
            };
            let mut runs = mill_runs(&smoothed, 1e-3 * onset_um, 1e-3 * extent_um);
            defer_to_darkness(&mut runs, &dark);
            drop_short_geometric_runs(&mut runs, &dark, options.min_geometric_arc_deg.ceil() as usize);
            let helix_deg: Vec<f64> = threads
                .iter()
                .flat_map(|t| t.bins.iter().map(move |b| 360.0 * (t.index as f64 - 1.0) + b.angle_deg))
                .collect();
            let window_smear_mm = params[1].abs() * crest_window_half_mm;
            let part = fit_polished_ends(&mut runs, &dark, &deficits, &helix_deg, zone_end, window_smear_mm);
            (runs, part, Some(cone))
        }
    };
    MillSurface { on_mill, mill_part, cone }
}

/// Each thread's bins for the rule engine (chamfer, mill surface, seen) and its dark arcs within
/// Lc, the partly covered end bins of a run counted by their cover.
fn thread_observations(
    threads: &[ThreadMeasure],
    lc_mm: f64,
    pitch_mm: f64,
    zone_end: usize,
    darkness: &Darkness,
    geometry: &MillSurface,
    mill_in_zone: &[bool],
) -> Vec<ThreadObservation> {
    let Darkness { dark, cover, run_end, .. } = darkness;
    let MillSurface { on_mill, mill_part, .. } = geometry;
    let mut helix_index = 0..;
    threads
        .iter()
        .map(|t| {
            let dz_per_deg = pitch_mm / 360.0;
            let mut arcs = Vec::new();
            let mut bins = Vec::with_capacity(t.bins.len());
            for b in &t.bins {
                let i = helix_index.next().expect("unbounded");
                let start = b.angle_deg - 0.5;
                let (dark, cover, (first, last)) = (dark[i], cover[i], run_end[i]);
                let z_start = b.crest_z_mm - 0.5 * dz_per_deg;
                if dark && z_start <= lc_mm {
                    let (from, to) = match (first, last) {
                        (true, true) => (start + 0.5 - 0.5 * cover as f64, start + 0.5 + 0.5 * cover as f64),
                        (true, false) => (start + 1.0 - cover as f64, start + 1.0),
                        (false, true) => (start, start + cover as f64),
                        (false, false) => (start, start + 1.0),
                    };
                    let to = to.min(start + (lc_mm - z_start) / dz_per_deg);
                    if to > from {
                        arcs.push([from, to]);
                    }
                }
                let chamfer = !dark && i < zone_end && !mill_in_zone[i];
                // A dark run's partly covered end bin is measured by its darkness: its geometry
                // (which took its extent from the darkness) would count the whole bin.
                let partly_dark = dark && (first || last) && cover < 1.0;
                let on_mill_surface = on_mill[i] && !chamfer && !partly_dark;
                bins.push(CrestBin {
                    angle_deg: start,
                    width_deg: 1.0,
                    z_mm: b.crest_z_mm,
                    height_mm: b.height_mm,
                    chamfer,
                    on_mill_surface,
                    // Only a bin on the mill surface has a part on it.
                    mill_arc_deg: mill_part[i].filter(|_| on_mill_surface).map(|[from, to]| [start + from, start + to]),
                    seen: b.crest_gray.is_some() || b.crest_radius_mm.is_some(),
                });
            }
            ThreadObservation { index: t.index, black_crest_arcs_deg: crate::domain::arcs::union_arcs(arcs), bins }
        })
        .collect()
}

#[cfg(test)]
mod tests;
