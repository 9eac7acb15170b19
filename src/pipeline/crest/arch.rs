//! A polished run's ends: the mill surface's arch below the cone, fitted through what the crest
//! window reads (a quadratic next to each end of a short run, the oval's harmonics over long runs
//! and over several runs of one surface).

use super::*;
use crate::numeric::lsq::levenberg_marquardt;

/// How far inward from each end of a polished run its arch is fitted as a quadratic: a quadratic
/// describes any smooth mill surface over that much of a turn, not over a whole turn.
pub(super) const ARCH_SPAN_DEG: f64 = 90.0;

/// Runs longer than this are fitted with the oval's harmonics ([`fit_long_arch`]), whose six
/// terms a shorter run does not hold well (chosen on bc-polished-long seeds 1–3, the tuning suite;
/// figures: docs/notebook/accuracy.md). Polished runs on several
/// turns are fitted together with the harmonics once their lengths add up to more than this.
pub(super) const HARMONIC_ARCH_DEG: f64 = 135.0;

/// Bins outside a run's ends that join its fit: they hold the crest to the cone there.
pub(super) const ARCH_MARGIN_DEG: f64 = 12.0;

/// A fitted end further than this from the threshold's end is not trusted (the threshold's stands).
pub(super) const ARCH_MAX_SHIFT_DEG: f64 = 8.0;

/// What a crest radius fitted over a window along z reads, as a deficit below the cone, where the
/// deficit on the crest's centre line is `q` (mm): the crest rises along z with the cone while the
/// mill surface stays level, so across the window the deficit is q + k·x, x ∈ [−h, h], and only
/// its positive part is cut away; the fit's intercept is the mean of max(0, q + k·x). With
/// `smear` w = k·h: q once q ≥ w, 0 once q ≤ −w, (q + w)²/4w between. Returns the value and its
/// derivative in q.
pub(super) fn window_reading(q: f64, smear: f64) -> (f64, f64) {
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
pub(super) fn fit_polished_ends(
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
pub(super) enum End {
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
pub(super) fn fit_quadratic_arch(
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
pub(super) struct QuadraticArch {
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
pub(super) fn fit_long_arch(
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
pub(super) struct LongArch {
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
pub(super) fn stretch_samples(
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
pub(super) fn fit_through_window<const N: usize>(
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
    let p = ata.lu().solve(&atb)?;
    Some(levenberg_marquardt(p, samples, |u, p| {
        let (reading, slope) = window_reading(basis(u).dot(p), smear_mm);
        (reading, basis(u) * slope)
    }))
}
