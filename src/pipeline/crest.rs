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

use crate::numeric::runs::{grow_runs, run_spans};
use crate::numeric::stats::{median, robust_scale};
use crate::pipeline::profile::ThreadMeasure;
use crate::domain::rules::{CrestBin, ThreadObservation};
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
}

impl Default for CrestOptions {
    fn default() -> Self {
        Self {
            dark_fraction: 0.45,
            dark_sigmas: 6.0,
            dark_run_sigmas: 4.0,
            dark_extent_sigmas: 2.5,
            mill_onset_um: 15.0,
            mill_extent_um: 5.0,
            min_geometric_arc_deg: 10.0,
        }
    }
}

/// The machined crest cone r = a + b·z + c·cos θ + d·sin θ fitted to the part's crests.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CrestCone {
    pub radius_at_end_mm: f64,
    /// Radial growth per mm of z (half the taper on diameter).
    pub slope: f64,
    /// Offset of the cone's axis from the pipe frame's, x and y.
    pub axis_offset_mm: [f64; 2],
    /// Robust scatter of the median-filtered crest radii about the cone.
    pub scatter_um: f64,
    pub crests_fitted: usize,
    /// The thresholds the geometric test used.
    pub onset_um: f64,
    pub extent_um: f64,
}

/// The cone's basis at (z, θ): its radius there is this dotted with (a, b, c, d).
fn cone_basis(z_mm: f64, theta_deg: f64) -> Vector4<f64> {
    let (sin, cos) = theta_deg.to_radians().sin_cos();
    Vector4::new(1.0, z_mm, cos, sin)
}

/// What the crest stage hands on: the rule engine's input per thread, the reference (machined)
/// crest brightness and the fitted crest cone.
#[derive(Clone, Debug)]
pub struct CrestFindings {
    pub observations: Vec<ThreadObservation>,
    pub machined_crest_gray: f32,
    pub cone: Option<CrestCone>,
}

/// Least-squares cone through (z, θ°, r), trimmed one-sidedly from an initial guess at the nominal
/// slope. None with fewer than 20 crests.
fn fit_cone(crests: &[(f64, f64, f64)], nominal_slope: f64) -> Option<(Vector4<f64>, usize)> {
    if crests.len() < 20 {
        return None;
    }
    let mut offsets: Vec<f64> = crests.iter().map(|&(z, _, r)| r - nominal_slope * z).collect();
    let mut params = Vector4::new(median(&mut offsets)?, nominal_slope, 0.0, 0.0);
    let mut used = 0;
    for _ in 0..6 {
        let residuals: Vec<f64> = crests.iter().map(|&(z, t, r)| r - cone_basis(z, t).dot(&params)).collect();
        // The median ignores the black minority: this is the machined crests' scatter.
        let sigma = robust_scale(residuals.iter().copied())?.max(1e-4);
        let (mut ata, mut atb) = (Matrix4::<f64>::zeros(), Vector4::<f64>::zeros());
        used = 0;
        for (&(z, t, r), &e) in crests.iter().zip(&residuals) {
            // Black crests lie below the cone: trim far more readily below than above.
            if e < -2.5 * sigma || e > 4.0 * sigma {
                continue;
            }
            let x = cone_basis(z, t);
            ata += x * x.transpose();
            atb += x * r;
            used += 1;
        }
        if used < 20 {
            return None;
        }
        params = ata.lu().solve(&atb)?;
    }
    Some((params, used))
}

/// Robust scatter of the smoothed deficits (µm) and the onset and extent thresholds it implies.
fn thresholds(smoothed: &[Option<f64>], options: &CrestOptions) -> (f64, f64, f64) {
    // Most crests are machined: their deficits scatter about zero, the black ones sit far out.
    let scatter_um = 1e3 * robust_scale(smoothed.iter().flatten().copied()).unwrap_or(0.0);
    (options.mill_onset_um.max(4.0 * scatter_um), options.mill_extent_um.max(1.5 * scatter_um), scatter_um)
}

/// Which crests of the chamfer zone (the first `zone_end` bins in helix order, `per_turn` bins a
/// turn) stand on the mill surface: those on a geometric run where the crest at the same angle
/// on the first turn beyond the zone is on the mill surface too (on a run, or dark). The cone
/// rises away from the end face while the mill surface keeps its radius along a few pitches, so a
/// crest at an angle where the mill surface stands below the cone has one below it at that angle
/// on every later turn, and a crest with a full one beyond it at its angle is not on the mill
/// surface. The chamfer (or a turned blank) cuts the first crests without any such crest beyond:
/// on the round presets it dips thread 1's crest by 10–26 µm a few degrees after the helix starts;
/// on the Table 1 case thread 1's crests sit 310–360 µm under the cone. Where the later crest is
/// not measured, the zone's crest is taken for the chamfer.
fn mill_surface_in_chamfer_zone(runs: &[bool], dark: &[bool], zone_end: usize, per_turn: usize) -> Vec<bool> {
    (0..zone_end)
        .map(|i| {
            let beyond = (i..runs.len()).step_by(per_turn.max(1)).find(|&j| j >= zone_end);
            runs[i] && beyond.is_some_and(|j| runs[j] || dark[j])
        })
        .collect()
}

/// Marks runs along the helix: a bin whose deficit reaches `onset` starts a run, which extends in
/// both directions over bins whose deficit stays at or above `extent` (a gap ends it).
fn mill_runs(smoothed: &[Option<f64>], onset_mm: f64, extent_mm: f64) -> Vec<bool> {
    let above = |i: usize, t: f64| smoothed[i].is_some_and(|d| d >= t);
    let seeds: Vec<bool> = (0..smoothed.len()).map(|i| above(i, onset_mm)).collect();
    grow_runs(&seeds, |i| above(i, extent_mm), 0)
}

/// How much of each dark bin the scale covers, read from its brightness: 1 inside a run, and at
/// a run's first and last bin the fraction of the way from the machined reference down to the
/// run's own darkness (its median) — a bin the scale covers in part is a mix of the two. Bins
/// outside runs get 1 (unused).
fn dark_cover(dark: &[bool], grays: &[Option<f32>], reference: f32) -> Vec<f32> {
    let mut cover = vec![1f32; dark.len()];
    for span in run_spans(dark) {
        let mut inside: Vec<f64> = grays[span.clone()].iter().flatten().map(|&g| g as f64).collect();
        let Some(level) = median(&mut inside).map(|l| l as f32) else { continue };
        if reference <= level {
            continue;
        }
        for i in [span.start, span.end - 1] {
            if let Some(g) = grays[i] {
                cover[i] = ((reference - g) / (reference - level)).clamp(0.0, 1.0);
            }
        }
    }
    cover
}

/// Where a geometric run shows mill scale anywhere, the darkness marks its extent: the crest
/// radius is fitted over a window as wide as the flat, and the flat mill surface cuts the rising
/// cone's far edge a few degrees before it reaches the centre line, so the geometric run starts
/// early on that side; the brightness is read on the centre line itself. A run with no dark bin
/// (a polished crest) stands on its geometry alone.
fn defer_to_darkness(runs: &mut [bool], dark: &[bool]) {
    for span in run_spans(runs) {
        if dark[span.clone()].iter().any(|&d| d) {
            runs[span.clone()].copy_from_slice(&dark[span]);
        }
    }
}

/// Removes runs without a dark bin that are shorter than `min_bins` 1° bins.
fn drop_short_geometric_runs(runs: &mut [bool], dark: &[bool], min_bins: usize) {
    for span in run_spans(runs) {
        if span.len() < min_bins && !dark[span.clone()].iter().any(|&d| d) {
            runs[span].fill(false);
        }
    }
}

/// How far inward from each end of a polished run its arch is fitted as a quadratic: a quadratic
/// describes any smooth mill surface over that much of a turn, not over a whole turn.
const ARCH_SPAN_DEG: f64 = 90.0;
/// Runs longer than this are fitted with the oval's harmonics ([`fit_long_arch`]), whose six
/// terms a shorter run does not hold well: on the rendered runs of 116° the quadratics next to each
/// end were within 0.2–0.8 mm and the harmonics 0.7–1.3 mm; on those of 155° and 192°, 2.2–3.8 mm
/// against 0.2–1.2 mm (bc-polished-long seeds 1–3, which chose this). Polished runs on several
/// turns are fitted together with the harmonics once their lengths add up to more than this.
const HARMONIC_ARCH_DEG: f64 = 135.0;
/// Bins outside a run's ends that join its fit: they hold the crest to the cone there.
const ARCH_MARGIN_DEG: f64 = 12.0;
/// A fitted end further than this from the threshold's end is not trusted (the threshold's stands).
const ARCH_MAX_SHIFT_DEG: f64 = 8.0;

/// What a crest radius fitted over a window along z reads, as a deficit below the cone, where the
/// deficit on the crest's centre line is `q` (mm): the crest rises along z with the cone while the
/// mill surface stays level, so across the window the deficit is q + k·x, x ∈ [−h, h], and only
/// its positive part is cut away; the fit's intercept is the mean of max(0, q + k·x). With
/// `smear` w = k·h: q once q ≥ w, 0 once q ≤ −w, (q + w)²/4w between. Returns the value and its
/// derivative in q.
fn window_reading(q: f64, smear: f64) -> (f64, f64) {
    if q >= smear {
        (q, 1.0)
    } else if q <= -smear {
        (0.0, 0.0)
    } else {
        ((q + smear).powi(2) / (4.0 * smear), (q + smear) / (2.0 * smear))
    }
}

/// The ends of each polished run (a geometric run with no dark bin), fitted rather than
/// thresholded. The deficit below the cone rises into a run at only a few µm per degree
/// (the mill surface meets the cone at a shallow angle) against 6–10 µm of noise per bin on a
/// polished crest, so where it first crosses a threshold scatters by degrees; and the window a
/// crest radius is fitted over reads a deficit already before the true end
/// ([`window_reading`]). Along a run the true deficit is an arch (the mill surface and the cone
/// are both smooth): a quadratic (over at most [`ARCH_SPAN_DEG`] in from each end) or, on runs
/// longer than [`HARMONIC_ARCH_DEG`], sinusoids of one and two per turn on a slope, fitted through
/// the window's reading to the run's bins and a margin either side, has its roots at the ends.
/// Where two or more polished runs beyond the chamfer zone (the first `zone_end` bins) span more
/// than [`HARMONIC_ARCH_DEG`] together, they are crests of one mill surface and are fitted as one
/// ([`fit_long_arch`]), which then gives every polished run's ends. Re-marks `runs` from the
/// fitted ends and returns, per bin, the part [from, to] (0–1 of the bin) on the mill surface
/// where an end falls inside it.
fn fit_polished_ends(
    runs: &mut [bool],
    dark: &[bool],
    deficits: &[Option<f64>],
    helix_deg: &[f64],
    zone_end: usize,
    smear_mm: f64,
) -> Vec<Option<[f64; 2]>> {
    let mut part = vec![None; runs.len()];
    let polished: Vec<std::ops::Range<usize>> =
        run_spans(runs).into_iter().filter(|span| !dark[span.clone()].iter().any(|&d| d)).collect();
    let degrees = |span: &std::ops::Range<usize>| (helix_deg[span.start] - 0.5, helix_deg[span.end - 1] + 0.5);
    // Every polished run stands on the same mill surface: fitted together where there are two or
    // more beyond the chamfer zone (whose own runs may be the chamfer) over the harmonics' span.
    let fitted_together: Vec<(f64, f64)> = polished.iter().filter(|span| span.start >= zone_end).map(degrees).collect();
    let together_deg: f64 = fitted_together.iter().map(|(first, last)| last - first).sum();
    let joint = (fitted_together.len() >= 2 && together_deg > HARMONIC_ARCH_DEG)
        .then(|| fit_long_arch(deficits, helix_deg, &fitted_together, smear_mm))
        .flatten();
    for span in polished {
        let (first, last) = degrees(&span);
        let sides = [End::Start, End::Finish];
        let whole_run = (first - ARCH_MARGIN_DEG, last + ARCH_MARGIN_DEG);
        // One fit gives both ends, except on a run whose quadratics are fitted next to each end.
        let ends: [Option<f64>; 2] = if let Some(arch) = &joint {
            sides.map(|side| arch.end(first, last, side))
        } else if last - first > HARMONIC_ARCH_DEG {
            let arch = fit_long_arch(deficits, helix_deg, &[(first, last)], smear_mm);
            sides.map(|side| arch.as_ref()?.end(first, last, side))
        } else if last - first <= ARCH_SPAN_DEG {
            let arch = fit_quadratic_arch(deficits, helix_deg, first, last, whole_run, smear_mm);
            sides.map(|side| arch.as_ref()?.end(first, last, side))
        } else {
            sides.map(|side| {
                let next_to_end = match side {
                    End::Start => (whole_run.0, first + ARCH_SPAN_DEG),
                    End::Finish => (last - ARCH_SPAN_DEG, whole_run.1),
                };
                fit_quadratic_arch(deficits, helix_deg, first, last, next_to_end, smear_mm)?.end(first, last, side)
            })
        };
        let fitted = |side: End, end: Option<f64>| {
            end.filter(|&end| (end - side.pick(first, last)).abs() <= ARCH_MAX_SHIFT_DEG)
                .unwrap_or(side.pick(first, last))
        };
        let (from, to) = (fitted(End::Start, ends[0]), fitted(End::Finish, ends[1]));
        // The run's own bins are re-marked; beyond them, bins only join it (another run there
        // keeps its marks).
        let reach = ARCH_MAX_SHIFT_DEG.ceil() as usize + 1;
        for i in span.start.saturating_sub(reach)..(span.end + reach).min(runs.len()) {
            let (lo, hi) = (helix_deg[i] - 0.5, helix_deg[i] + 0.5);
            let (a, b) = (lo.max(from), hi.min(to));
            if b > a {
                runs[i] = true;
                part[i] = (b - a < 1.0 - 1e-9).then_some([a - lo, b - lo]);
            } else if span.contains(&i) {
                runs[i] = false;
            }
        }
    }
    part
}

#[derive(Clone, Copy, PartialEq)]
enum End {
    Start,
    Finish,
}

impl End {
    fn pick(self, start: f64, finish: f64) -> f64 {
        match self {
            End::Start => start,
            End::Finish => finish,
        }
    }

    /// The sign of the direction along the helix into a run from this end.
    fn inward(self) -> f64 {
        self.pick(1.0, -1.0)
    }
}

/// The quadratic arch of a run from [first, last]° along the helix (see [`fit_polished_ends`]),
/// fitted over the `stretch` [lo, hi]°; None where the run's inner bins there are too few.
fn fit_quadratic_arch(
    deficits: &[Option<f64>],
    helix_deg: &[f64],
    first: f64,
    last: f64,
    (lo, hi): (f64, f64),
    smear_mm: f64,
) -> Option<QuadraticArch> {
    // u ∈ [−1, 1] over the stretch keeps the normal equations well conditioned.
    let (centre_deg, half_deg) = (0.5 * (lo + hi), 0.5 * (hi - lo));
    let samples = stretch_samples(deficits, helix_deg, lo, hi, |deg| (deg - centre_deg) / half_deg);
    let inner = ((first + 2.0 - centre_deg) / half_deg, (last - 2.0 - centre_deg) / half_deg);
    let inner = |u: f64| (inner.0..=inner.1).contains(&u);
    let params = fit_through_window(&samples, inner, |u| Vector3::new(1.0, u, u * u), smear_mm)?;
    Some(QuadraticArch { centre_deg, half_deg, params })
}

/// A fitted [`fit_quadratic_arch`]: the deficit at u = (θ − `centre_deg`) / `half_deg` is
/// `params · (1, u, u²)`.
struct QuadraticArch {
    centre_deg: f64,
    half_deg: f64,
    params: Vector3<f64>,
}

impl QuadraticArch {
    /// The run's end on `side` of [first, last]: the root nearest that end at which the arch
    /// rises into the run. None without one.
    fn end(&self, first: f64, last: f64, side: End) -> Option<f64> {
        let (a, b, c) = (self.params[0], self.params[1], self.params[2]);
        let roots: Vec<f64> = if c.abs() < 1e-12 {
            if b.abs() < 1e-12 { vec![] } else { vec![-a / b] }
        } else {
            let disc = b * b - 4.0 * a * c;
            if disc < 0.0 {
                return None;
            }
            let sq = disc.sqrt();
            vec![(-b - sq) / (2.0 * c), (-b + sq) / (2.0 * c)]
        };
        let end = side.pick(first, last);
        roots
            .into_iter()
            .filter(|&u| side.inward() * (b + 2.0 * c * u) > 0.0)
            .map(|u| self.centre_deg + self.half_deg * u)
            .min_by(|x, y| (x - end).abs().total_cmp(&(y - end).abs()))
    }
}

/// The arch of polished runs ([first, last]° along the helix, in helix order) by the oval's
/// harmonics: a single run longer than [`HARMONIC_ARCH_DEG`], or several runs of one mill surface.
/// Over that much of a turn a quadratic no longer follows the deficit: fitted over the 90° next to
/// each end, it left the ends of runs of 120–240° 0.7–2.1° inward noise-free, up to 5.6° on a mill
/// surface whose diameters differ by 0.2 mm, and rendered runs of 155–192° up to 3.8 mm short. The
/// pipe's outside is an oval whose centre is off the thread axis, and the cone rises along the
/// helix, so the deficit is exactly a constant, a slope and sinusoids of one and two per turn.
/// The oval does not change along the few pitches between runs on different turns, so one arch
/// holds all their deficits: a short run alone is the weakest fit (its arch is an end or two of
/// the surface's); beside the longer runs on the other turns its ends are where the same surface
/// meets its crest line. Fitted through the window's reading over each run's bins and margins,
/// not the machined crests between runs a turn apart. None where the runs' inner bins are too few.
fn fit_long_arch(
    deficits: &[Option<f64>],
    helix_deg: &[f64],
    runs_deg: &[(f64, f64)],
    smear_mm: f64,
) -> Option<LongArch> {
    let (lo, hi) = (runs_deg.first()?.0 - ARCH_MARGIN_DEG, runs_deg.last()?.1 + ARCH_MARGIN_DEG);
    let centre_deg = 0.5 * (lo + hi);
    let x_of = |deg: f64| (deg - centre_deg).to_radians();
    let near_a_run = |deg: f64| {
        runs_deg.iter().any(|&(first, last)| (first - ARCH_MARGIN_DEG..=last + ARCH_MARGIN_DEG).contains(&deg))
    };
    let samples: Vec<(f64, f64)> = helix_deg
        .iter()
        .zip(deficits)
        .filter(|(deg, _)| near_a_run(**deg))
        .filter_map(|(&deg, d)| Some((x_of(deg), (*d)?)))
        .collect();
    let inner: Vec<(f64, f64)> = runs_deg.iter().map(|&(first, last)| (x_of(first + 2.0), x_of(last - 2.0))).collect();
    let params = fit_through_window(
        &samples,
        |x| inner.iter().any(|&(from, to)| (from..=to).contains(&x)),
        LongArch::basis,
        smear_mm,
    )?;
    Some(LongArch { centre_deg, params })
}

/// A fitted [`fit_long_arch`]: the deficit at x rad from `centre_deg` is `basis(x) · params`.
struct LongArch {
    centre_deg: f64,
    params: SVector<f64, 6>,
}

impl LongArch {
    fn basis(x: f64) -> SVector<f64, 6> {
        SVector::<f64, 6>::from([1.0, x, x.cos(), x.sin(), (2.0 * x).cos(), (2.0 * x).sin()])
    }

    fn at(&self, deg: f64) -> f64 {
        Self::basis((deg - self.centre_deg).to_radians()).dot(&self.params)
    }

    /// The run's end on `side` of [first, last]: where the arch crosses zero rising inward,
    /// searched in 0.05° steps from [`ARCH_MAX_SHIFT_DEG`] inside that end outward to as far
    /// outside (the innermost crossing if there were two), then bisected. None without one.
    fn end(&self, first: f64, last: f64, side: End) -> Option<f64> {
        let (end, inward) = (side.pick(first, last), side.inward());
        let step_deg = 0.05;
        let steps = (2.0 * ARCH_MAX_SHIFT_DEG / step_deg).round() as i64;
        let mut inside = end + inward * ARCH_MAX_SHIFT_DEG;
        if self.at(inside) <= 0.0 {
            return None;
        }
        for _ in 0..steps {
            let outside = inside - inward * step_deg;
            if self.at(outside) <= 0.0 {
                let (mut a, mut b) = (inside, outside);
                for _ in 0..40 {
                    let mid = 0.5 * (a + b);
                    if self.at(mid) > 0.0 { a = mid } else { b = mid }
                }
                return Some(0.5 * (a + b));
            }
            inside = outside;
        }
        None
    }
}

/// The (coordinate, deficit) samples of the bins within [lo, hi]° along the helix.
fn stretch_samples(
    deficits: &[Option<f64>],
    helix_deg: &[f64],
    lo: f64,
    hi: f64,
    coordinate: impl Fn(f64) -> f64,
) -> Vec<(f64, f64)> {
    helix_deg
        .iter()
        .zip(deficits)
        .filter(|(deg, _)| (lo..=hi).contains(*deg))
        .filter_map(|(&deg, d)| Some((coordinate(deg), (*d)?)))
        .collect()
}

/// The arch `basis · p` fitted through the window's reading ([`window_reading`]) to `samples` by
/// Levenberg–Marquardt, from the plain least-squares fit to the samples for which `inner` holds
/// (the runs' inner bins, where the window reads the deficit itself); None with fewer than 12
/// there.
fn fit_through_window<const N: usize>(
    samples: &[(f64, f64)],
    inner: impl Fn(f64) -> bool,
    basis: impl Fn(f64) -> SVector<f64, N>,
    smear_mm: f64,
) -> Option<SVector<f64, N>>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    let inner: Vec<&(f64, f64)> = samples.iter().filter(|(u, _)| inner(*u)).collect();
    if inner.len() < 12 {
        return None;
    }
    let (mut ata, mut atb) = (SMatrix::<f64, N, N>::zeros(), SVector::<f64, N>::zeros());
    for &&(u, d) in &inner {
        ata += basis(u) * basis(u).transpose();
        atb += basis(u) * d;
    }
    let mut p = ata.lu().solve(&atb)?;
    let sse = |p: &SVector<f64, N>| -> f64 {
        samples.iter().map(|&(u, d)| (d - window_reading(basis(u).dot(p), smear_mm).0).powi(2)).sum()
    };
    let (mut cost, mut lambda) = (sse(&p), 1e-3);
    for _ in 0..100 {
        let (mut jtj, mut jtr) = (SMatrix::<f64, N, N>::zeros(), SVector::<f64, N>::zeros());
        for &(u, d) in samples {
            let (reading, slope) = window_reading(basis(u).dot(&p), smear_mm);
            let row = basis(u) * slope;
            jtj += row * row.transpose();
            jtr += row * (d - reading);
        }
        let damped = jtj + SMatrix::<f64, N, N>::from_diagonal(&jtj.diagonal()) * lambda;
        let Some(step) = damped.lu().solve(&jtr) else { break };
        let trial = p + step;
        let trial_cost = sse(&trial);
        if trial_cost < cost {
            let converged = cost - trial_cost <= 1e-12 * cost.max(1e-30);
            (p, cost, lambda) = (trial, trial_cost, (lambda / 3.0).max(1e-9));
            if converged {
                break;
            }
        } else {
            lambda *= 4.0;
            if lambda > 1e6 {
                break;
            }
        }
    }
    Some(p)
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
    let mut grays: Vec<f32> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.crest_gray)).collect();
    grays.sort_by(f32::total_cmp);
    let reference = grays.get(grays.len() / 2).copied().unwrap_or(0.0);
    // Machined crests scatter little about the reference; a thin strip of mill scale (a round
    // crest barely touched by the mill surface) darkens the centre line by less than half, but
    // far beyond that scatter.
    // (Floored at 3% of the reference, so that noiseless data cannot call the median itself dark.)
    let gray_scatter =
        (robust_scale(grays.iter().map(|&g| (g - reference) as f64)).unwrap_or(0.0) as f32).max(0.03 * reference);
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
    let chamfer_zone_mm = 1.5 * pitch_mm;
    let in_helix_order = || threads.iter().flat_map(|t| t.bins.iter());
    let seeds: Vec<bool> = in_helix_order()
        .zip(&run_gray)
        .map(|(b, run)| b.crest_gray.is_some_and(|g| g < dark_below) || run.is_some_and(|g| g < run_below as f64))
        .collect();
    let grays: Vec<Option<f32>> = in_helix_order().map(|b| b.crest_gray).collect();
    let extent_below = reference - options.dark_extent_sigmas * gray_scatter;
    // Where the scale thins to a strip at a run's end, one bin can read just above the extent
    // bar between darker ones (round seed 2 of the held-out suite: 0.519 between 0.486 and the
    // run, against a bar at 0.513); a single such bin does not end the run.
    let dark = grow_runs(&seeds, |i| grays[i].is_some_and(|g| g < extent_below), 1);
    let cover = dark_cover(&dark, &grays, reference);
    // A run's first and last bins count by how much of them the scale covers.
    let run_end: Vec<(bool, bool)> = (0..dark.len())
        .map(|i| (dark[i] && (i == 0 || !dark[i - 1]), dark[i] && (i + 1 == dark.len() || !dark[i + 1])))
        .collect();

    // The chamfer zone's bins come first along the helix (z rises along it).
    let zone_end = in_helix_order().position(|b| b.crest_z_mm >= chamfer_zone_mm).unwrap_or(dark.len());
    // Geometric: the crests' deficits below the cone fitted to the crests beyond the zone, in
    // helix order.
    let crests: Vec<(f64, f64, f64)> = in_helix_order()
        .zip(&dark)
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

    // Bins at one angle are a turn apart in helix order where every thread has a bin per degree
    // (as the profile stage measures them); otherwise the whole zone is the chamfer.
    let per_turn = threads.first().map_or(0, |t| t.bins.len());
    let mill_in_zone = if per_turn > 0 && threads.iter().all(|t| t.bins.len() == per_turn) {
        mill_surface_in_chamfer_zone(&on_mill, &dark, zone_end, per_turn)
    } else {
        vec![false; zone_end]
    };
    let mut helix_index = 0..;
    let observations = threads
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
            ThreadObservation { index: t.index, black_crest_arcs_deg: crate::domain::rules::union_arcs(arcs), bins }
        })
        .collect();
    CrestFindings { observations, machined_crest_gray: reference, cone }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::profile::BinMeasure;

    const PITCH: f64 = 5.08;
    const SLOPE: f64 = 0.0625 / 2.0;
    /// The profile stage's crest window on a buttress crest (0.6 of the 2.36 mm flat's half).
    const WINDOW_HALF_MM: f64 = 0.708;

    /// Seven threads whose crests lie on a cone whose axis is 0.04 mm off the frame's, with ±4 µm
    /// of deterministic scatter; `crest(index, θ°, cone radius)` may move a crest below the cone.
    fn part(crest: impl Fn(u32, f64, f64) -> f64) -> Vec<ThreadMeasure> {
        let mut seed = 7u64;
        (1..=7)
            .map(|index| {
                let bins = (0..360)
                    .map(|k| {
                        let angle_deg = k as f64 + 0.5;
                        let z = 1.0 + PITCH * (index as f64 - 1.0 + angle_deg / 360.0);
                        let cone = 55.0 + SLOPE * z + 0.04 * angle_deg.to_radians().cos();
                        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                        let jitter = ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.008;
                        BinMeasure {
                            angle_deg,
                            crest_z_mm: z,
                            height_mm: Some(1.5),
                            crest_radius_mm: Some(crest(index, angle_deg, cone) + jitter),
                            crest_gray: Some(0.5),
                        }
                    })
                    .collect();
                ThreadMeasure { index, bins }
            })
            .collect()
    }

    fn mill_arcs(findings: &CrestFindings, index: u32) -> Vec<[f64; 2]> {
        let t = findings.observations.iter().find(|t| t.index == index).unwrap();
        crate::domain::rules::union_arcs(
            t.bins.iter().filter(|b| b.on_mill_surface).map(|b| b.mill_arc_deg.unwrap_or(b.span_deg())).collect(),
        )
    }

    /// The crest radius the profile stage reads where a level mill surface at `mill` cuts a crest
    /// that rises along z with the cone: the least-squares line through the window's samples, at
    /// its centre (for `n` samples spread evenly about it, their mean).
    fn window_fit(cone: f64, mill: f64, n: usize) -> f64 {
        let sum: f64 = (0..n)
            .map(|k| {
                let x = WINDOW_HALF_MM * (2.0 * k as f64 / (n - 1) as f64 - 1.0);
                (cone + SLOPE * x).min(mill) - SLOPE * x
            })
            .sum();
        sum / n as f64
    }

    /// [`part`] with thread 5's crest line meeting a mill surface `eccentricity_mm` off centre
    /// toward 310°, which crosses it at 130° ± `half_span_deg`; the crest is read through the window.
    fn polished_thread_5(eccentricity_mm: f64, half_span_deg: f64) -> Vec<ThreadMeasure> {
        polished_thread_5_oval(eccentricity_mm, 0.0, half_span_deg)
    }

    /// [`polished_thread_5`] on an oval mill surface: its radius varies by ±`ovality_mm` twice a
    /// turn (diameters 4·`ovality_mm` apart), with the same crossings.
    fn polished_thread_5_oval(eccentricity_mm: f64, ovality_mm: f64, half_span_deg: f64) -> Vec<ThreadMeasure> {
        part(|index, theta, cone| {
            if index != 5 {
                return cone;
            }
            polished_crest(theta, cone, eccentricity_mm, ovality_mm, half_span_deg)
        })
    }

    /// A crest at `cone` read through the window where the mill surface of
    /// [`polished_thread_5_oval`] cuts it.
    fn polished_crest(theta: f64, cone: f64, eccentricity_mm: f64, ovality_mm: f64, half_span_deg: f64) -> f64 {
        let (x, h) = ((theta - 130.0).to_radians(), half_span_deg.to_radians());
        let deficit = eccentricity_mm * (x.cos() - h.cos()) + ovality_mm * ((2.0 * x).cos() - (2.0 * h).cos());
        window_fit(cone, cone - deficit, 201)
    }

    #[test]
    fn the_window_reading_is_the_mean_of_the_cut_over_the_window() {
        let smear = SLOPE * WINDOW_HALF_MM;
        for q_um in [-40.0, -22.0, -15.0, -5.0, 0.0, 5.0, 15.0, 21.0, 30.0, 60.0] {
            let q = 1e-3 * q_um;
            let read = 55.0 - window_fit(55.0, 55.0 - q, 200_001);
            assert!((window_reading(q, smear).0 - read).abs() < 1e-7, "q {q_um} µm: {read}");
        }
    }

    #[test]
    fn a_polished_crest_below_the_cone_is_found_to_its_shallow_ends() {
        // Thread 5 meets a mill surface 0.4 mm off centre toward 310° that crosses its crest
        // line at 100° and 160°: 54 µm deep in the middle and rising into the run at 3.5 µm/°.
        // Its crest is read through the window, which sees a deficit from 6° before either end.
        let threads = polished_thread_5(0.4, 30.0);
        let findings = observations(&threads, 40.0, PITCH, SLOPE, WINDOW_HALF_MM, &CrestOptions::default());
        let cone = findings.cone.as_ref().unwrap();
        assert!((cone.axis_offset_mm[0] - 0.04).abs() < 0.002 && cone.axis_offset_mm[1].abs() < 0.002, "{cone:?}");
        assert!((cone.slope - SLOPE).abs() < 1e-3, "{cone:?}");
        assert!(cone.scatter_um < 4.0, "{cone:?}");
        let arcs = mill_arcs(&findings, 5);
        assert_eq!(arcs.len(), 1, "{arcs:?}");
        // The fitted ends, to a fraction of a bin (the threshold's were whole bins, 2–3° inside).
        assert!((arcs[0][0] - 100.0).abs() <= 0.4 && (arcs[0][1] - 160.0).abs() <= 0.4, "{arcs:?}");
        for index in [1, 2, 3, 4, 6, 7] {
            assert!(mill_arcs(&findings, index).is_empty(), "thread {index}");
        }
        // The rule engine reports it as a polished black crest (bright, found by geometry).
        let input = crate::domain::rules::RuleInput {
            family: crate::domain::thread::Family::Buttress,
            lc_mm: 40.0,
            circumference_mm: 350.0,
            nominal_height_mm: 1.5,
            height_tolerance_mm: 0.05,
            threads: findings.observations,
        };
        let a = crate::domain::rules::assess(&input, crate::domain::rules::ArcRule::PerThread);
        assert_eq!(a.black_threads.len(), 1);
        assert_eq!(a.black_threads[0].evidence, crate::domain::rules::BlackCrestEvidence::Geometric);
    }

    #[test]
    fn a_long_polished_run_on_an_oval_off_centre_mill_surface_is_fitted_to_its_ends() {
        // 200° runs: a mill surface 0.2 mm off centre toward 310°, round or oval (diameters 0.2 mm
        // apart), crossing thread 5's crest line at 30° and 230°. A quadratic cannot follow the
        // whole arch: fitted over the 90° next to each end, it left them 1.6–1.8° inward on the
        // round surface and 4.4–4.7° on the oval one; one sinusoid per turn without the second
        // left the oval one's 1–3° out.
        for ovality_mm in [0.0, 0.05, -0.05] {
            let threads = polished_thread_5_oval(0.2, ovality_mm, 100.0);
            let findings = observations(&threads, 40.0, PITCH, SLOPE, WINDOW_HALF_MM, &CrestOptions::default());
            let arcs = mill_arcs(&findings, 5);
            assert_eq!(arcs.len(), 1, "{ovality_mm}: {arcs:?}");
            assert!((arcs[0][0] - 30.0).abs() <= 0.6 && (arcs[0][1] - 230.0).abs() <= 0.6, "{ovality_mm}: {arcs:?}");
        }
    }

    /// Polished runs on threads 5–7 where one mill surface (0.5 mm off centre toward 310°, oval by
    /// 0.2 mm on diameter, level along z) meets the rising cone: 63°, 107° and 143° long. Thread 5's
    /// run has two bins just inside its start that read −18 and 0 µm among its 10–20 µm deficits,
    /// as held-out bc-polished-long seed 4's 63° run does; alone, its quadratic followed them and
    /// put the start 1.1° late and the end 0.5° early. Fitted with the other turns' runs, the ends
    /// are those of the one surface.
    #[test]
    fn polished_runs_on_several_turns_are_fitted_as_one_mill_surface() {
        let mill = |theta: f64| {
            56.15 + 0.5 * (theta - 310.0).to_radians().cos() + 0.05 * (2.0 * (theta - 40.0)).to_radians().cos()
        };
        let threads = part(|index, theta, cone| match (index, theta) {
            (5, 100.5) => cone + 0.018,
            (5, 101.5) => cone,
            _ => window_fit(cone, mill(theta), 201),
        });
        // Where the crest line of thread `index` meets the surface, rising into the run.
        let cone_at = |index: u32, theta: f64| {
            let z = 1.0 + PITCH * (index as f64 - 1.0 + theta / 360.0);
            55.0 + SLOPE * z + 0.04 * theta.to_radians().cos()
        };
        let crossing = |index: u32, (mut outside, mut inside): (f64, f64)| {
            for _ in 0..60 {
                let mid = 0.5 * (outside + inside);
                if cone_at(index, mid) > mill(mid) { inside = mid } else { outside = mid }
            }
            0.5 * (outside + inside)
        };
        let findings = observations(&threads, 40.0, PITCH, SLOPE, WINDOW_HALF_MM, &CrestOptions::default());
        for (index, middle) in [(5, 130.0), (6, 130.0), (7, 130.0)] {
            let truth = [crossing(index, (0.0, middle)), crossing(index, (260.0, middle))];
            let arcs = mill_arcs(&findings, index);
            assert_eq!(arcs.len(), 1, "thread {index}: {arcs:?}");
            assert!(
                (arcs[0][0] - truth[0]).abs() <= 0.4 && (arcs[0][1] - truth[1]).abs() <= 0.4,
                "thread {index}: {arcs:?} against {truth:?}"
            );
        }
        for index in 1..=4 {
            assert!(mill_arcs(&findings, index).is_empty(), "thread {index}");
        }
    }

    /// Thread 1 and thread 2 up to 110° lie within 1.5 pitches of the end face (the chamfer zone),
    /// where every crest that looked machined was once taken for the chamfer. A crest there is
    /// the mill surface where the crest at its angle beyond the zone is (the cone rises away from
    /// the end face): a polished crest across threads 1–3 at 100°–160° is black on all three; the
    /// same crest on thread 1 alone, and a lead-in 330 µm under the cone over thread 1's first 30°
    /// (as the Table 1 case's turned blank leaves it), are the chamfer.
    #[test]
    fn a_polished_crest_in_the_chamfer_zone_is_black_where_the_crest_beyond_it_is() {
        for (lead_in_deg, polished_threads) in [(0.0, 3), (30.0, 3), (30.0, 1)] {
            let threads = part(|index, theta, cone| match index {
                1 if theta < lead_in_deg => cone - 0.33,
                i if i <= polished_threads => polished_crest(theta, cone, 0.4, 0.0, 30.0),
                _ => cone,
            });
            let findings = observations(&threads, 40.0, PITCH, SLOPE, WINDOW_HALF_MM, &CrestOptions::default());
            let case = format!("lead-in {lead_in_deg}°, polished threads 1–{polished_threads}");
            for index in 1..=7 {
                let arcs = mill_arcs(&findings, index);
                if polished_threads == 3 && index <= 3 {
                    assert_eq!(arcs.len(), 1, "{case}, thread {index}: {arcs:?}");
                    let [from, to] = arcs[0];
                    assert!(
                        (from - 100.0).abs() <= 0.4 && (to - 160.0).abs() <= 0.4,
                        "{case}, thread {index}: {arcs:?}"
                    );
                } else {
                    assert!(arcs.is_empty(), "{case}, thread {index}: {arcs:?}");
                }
            }
            // Thread 1's crests are the chamfer but where they are black.
            for b in &findings.observations[0].bins {
                let black = polished_threads == 3 && (101.0..159.0).contains(&b.angle_deg);
                let chamfer = polished_threads == 1 || !(98.0..162.0).contains(&b.angle_deg);
                assert!(!(black && b.chamfer) && (!chamfer || b.chamfer), "{case}: {b:?}");
            }
        }
    }

    #[test]
    fn a_vanishing_thread_with_machined_crests_is_not_black() {
        // Heights fall to a third toward the vanish end because the roots rise; crests stay on the cone.
        let mut threads = part(|_, _, cone| cone);
        for t in threads.iter_mut().filter(|t| t.index >= 5) {
            t.bins.iter_mut().for_each(|b| b.height_mm = Some(0.5));
        }
        let findings = observations(&threads, 40.0, PITCH, SLOPE, WINDOW_HALF_MM, &CrestOptions::default());
        assert!(findings.observations.iter().all(|t| t.bins.iter().all(|b| !b.on_mill_surface)));
        let input = crate::domain::rules::RuleInput {
            family: crate::domain::thread::Family::Round,
            lc_mm: 40.0,
            circumference_mm: 350.0,
            nominal_height_mm: 1.5,
            height_tolerance_mm: 0.05,
            threads: findings.observations,
        };
        assert_eq!(
            crate::domain::rules::assess(&input, crate::domain::rules::ArcRule::PerThread).verdict,
            crate::domain::rules::Verdict::Accept
        );
    }

    #[test]
    fn runs_start_at_the_onset_and_extend_over_the_extent() {
        let d = |v: &[f64]| v.iter().map(|&x| Some(x)).collect::<Vec<_>>();
        let runs = mill_runs(&d(&[0.0, 0.006, 0.010, 0.020, 0.007, 0.004, 0.009, 0.0]), 0.015, 0.005);
        assert_eq!(runs, [false, true, true, true, true, false, false, false]);
        // A gap (unmeasured bin) ends a run; extent-level bins alone start nothing.
        let mut gapped = d(&[0.020, 0.010, 0.010, 0.0]);
        gapped[1] = None;
        assert_eq!(mill_runs(&gapped, 0.015, 0.005), [true, false, false, false]);
    }

    #[test]
    fn short_runs_on_geometry_alone_are_dropped() {
        let mut runs = vec![false, true, true, true, false, true, true, false, true, true, true, true, true];
        let dark = [false, false, false, false, false, false, true, false, false, false, false, false, false];
        drop_short_geometric_runs(&mut runs, &dark, 4);
        assert_eq!(runs, [false, false, false, false, false, true, true, false, true, true, true, true, true]);
    }

    #[test]
    fn darkness_marks_the_extent_of_runs_that_show_it() {
        let mut runs = vec![false, true, true, true, true, false, true, true, false];
        let dark = [false, false, true, true, false, false, false, false, false];
        defer_to_darkness(&mut runs, &dark);
        assert_eq!(runs, [false, false, true, true, false, false, true, true, false]);
    }

    /// One 5.08 mm pitch thread starting at `z0_mm`, crest brightness per bin from `gray`.
    fn one_thread(index: u32, z0_mm: f64, crest_radius_mm: Option<f64>, gray: impl Fn(usize) -> f32) -> ThreadMeasure {
        let bins = (0..360)
            .map(|k| BinMeasure {
                angle_deg: k as f64 + 0.5,
                crest_z_mm: z0_mm + 5.08 * (k as f64 + 0.5) / 360.0,
                height_mm: Some(1.5),
                crest_radius_mm,
                crest_gray: Some(gray(k)),
            })
            .collect();
        ThreadMeasure { index, bins }
    }

    #[test]
    fn a_sustained_faint_dip_is_dark_and_a_single_faint_bin_is_not() {
        // Reference 0.6, scatter at its 3% floor (0.018): one bin must fall below 0.492, five in a
        // row below 0.528. Bins 100–111 sit at 0.51; bin 300 alone at 0.51.
        let threads = vec![one_thread(4, 20.0, None, |k| if (100..112).contains(&k) || k == 300 { 0.51 } else { 0.6 })];
        let findings = observations(&threads, 40.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default());
        assert_eq!(findings.observations[0].black_crest_arcs_deg, vec![[100.0, 112.0]]);
    }

    /// The helix starts with thread 1 at the chamfer, where its crest reads a little dim over a
    /// few degrees: faint bins there are not a sustained dip unless five in a row are (a window cut
    /// short at the helix's start, or by an unmeasured bin, would let one or two bins stand for
    /// five).
    #[test]
    fn faint_bins_where_the_helix_starts_or_a_gap_cuts_the_window_are_not_a_sustained_dip() {
        // Reference 0.6, scatter at its 3% floor: one bin must fall below 0.492, five in a row
        // below 0.528. Bins 0–1 read 0.51 (then 0.6); bins 200–201 read 0.51 next to a gap at 202.
        let mut thread = one_thread(1, 1.1, None, |k| if k < 2 || k == 200 || k == 201 { 0.51 } else { 0.6 });
        thread.bins[202].crest_gray = None;
        let findings = observations(&[thread.clone()], 40.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default());
        let arcs = &findings.observations[0].black_crest_arcs_deg;
        assert!(arcs.is_empty(), "{arcs:?}");
        // Five faint bins in a row at the start are a dip, as anywhere else.
        thread.bins[..5].iter_mut().for_each(|b| b.crest_gray = Some(0.51));
        let findings = observations(&[thread], 40.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default());
        assert_eq!(findings.observations[0].black_crest_arcs_deg, vec![[0.0, 5.0]]);
    }

    #[test]
    fn faint_ends_extend_a_dark_run_and_partly_covered_end_bins_count_by_their_darkness() {
        // Reference 0.6, scatter at its floor (0.018): a bin starts a run below 0.492 and extends
        // one below 0.555. Bins 100–109 are scale (0.1); bin 99 (0.35) is half covered; bin 110
        // (0.53) is a faint end, bin 111 (0.57) is not; bin 300 (0.53) alone starts nothing.
        let gray = |k: usize| match k {
            99 => 0.35,
            100..=109 => 0.1,
            110 | 300 => 0.53,
            111 => 0.57,
            _ => 0.6,
        };
        let threads = vec![one_thread(4, 20.0, None, gray)];
        let findings = observations(&threads, 40.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default());
        let arcs = &findings.observations[0].black_crest_arcs_deg;
        assert_eq!(arcs.len(), 1, "{arcs:?}");
        // Covers (0.6 − g) / (0.6 − 0.1): half of bin 99 (its end side), 0.14 of bin 110.
        assert!((arcs[0][0] - 99.5).abs() < 1e-6 && (arcs[0][1] - 110.14).abs() < 1e-5, "{arcs:?}");
    }

    #[test]
    fn one_bin_just_above_the_extent_bar_does_not_end_a_dark_run_but_two_do() {
        // As above (extent bar 0.555): after the scale (100–109), bin 110 reads 0.56, just above
        // the bar, and bin 111 0.53 below it again: the run goes on to 111, which counts by its
        // darkness (0.14). With two bins above the bar (110, 111) before 112's 0.53 it ends at 109.
        let arcs_with = |faint: &'static [usize], end: usize| {
            let threads = vec![one_thread(4, 20.0, None, move |k| match k {
                100..=109 => 0.1,
                k if faint.contains(&k) => 0.56,
                k if k == end => 0.53,
                _ => 0.6,
            })];
            observations(&threads, 40.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default()).observations[0]
                .black_crest_arcs_deg
                .clone()
        };
        let arcs = arcs_with(&[110], 111);
        assert_eq!(arcs.len(), 1, "{arcs:?}");
        assert!((arcs[0][0] - 100.0).abs() < 1e-6 && (arcs[0][1] - 111.14).abs() < 1e-5, "{arcs:?}");
        assert_eq!(arcs_with(&[110, 111], 112), vec![[100.0, 110.0]]);
    }

    #[test]
    fn dark_crests_within_lc_become_arcs_clipped_at_lc() {
        let threads = vec![one_thread(6, 30.0, Some(57.0), |k| if (100..200).contains(&k) { 0.05 } else { 0.5 })];
        // Lc at z = 31.0 → θ = (31 − 30) / 5.08 · 360 = 70.9°: no dark crest within Lc.
        let findings = observations(&threads, 31.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default());
        assert_eq!(findings.machined_crest_gray, 0.5);
        assert!(findings.observations[0].black_crest_arcs_deg.is_empty());
        // Lc at z = 32.0 → θ = 141.7°: the dark arc runs 100° to 141.7°.
        let findings = observations(&threads, 32.0, 5.08, 0.0, WINDOW_HALF_MM, &CrestOptions::default());
        let arc = findings.observations[0].black_crest_arcs_deg[0];
        assert_eq!(arc[0], 100.0);
        assert!((arc[1] - 2.0 / 5.08 * 360.0).abs() < 1e-9, "{arc:?}");
    }
}
