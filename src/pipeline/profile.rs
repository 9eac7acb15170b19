//! Thread profile: the helix (phase z_h, pitch, taper) by Fourier analysis along the generatrix,
//! then every thread's height per 1° bin measured on the fused map per the bundle contract.
//!
//! Along one generatrix the surface is r(z) = taper line + the thread form shifted to the crest
//! positions. Removing the line leaves the thread spectrum: its fundamental at 1/pitch carries the
//! crest position in its phase (offset by the form's own fundamental phase, known analytically for
//! asymmetric forms such as buttress). Combining bins gives z_h, the crest of thread 1 at θ = 0.
//! Heights are then measured directly on the data, at the contract's points: the crest on its
//! centre line and the two adjacent roots at their centres, each by a local least-squares fit over
//! the flat (or arc) around that point, so that noise averages out and edges are avoided.

use crate::pipeline::surface::UnrolledMap;
use crate::domain::thread::{ProfileShape, ThreadForm};
use crate::numeric::sequence::trimmed_mean;
use crate::numeric::stats::median;
use rayon::prelude::*;
use rustfft::FftPlanner;
use rustfft::num_complex::Complex;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Helix {
    /// z of thread 1's crest centre line at θ = 0, in [0, pitch).
    pub z_h_mm: f64,
    pub pitch_mm: f64,
    /// Measured taper on diameter (from the detrended generatrix slope).
    pub taper_on_diameter: f64,
    /// RMS of the analytic profile (nominal form at the measured phase, taper line) against data.
    pub fit_rms_um: f64,
    pub bins_used: usize,
}

/// One thread at one 1° bin.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BinMeasure {
    /// Bin centre.
    pub angle_deg: f64,
    pub crest_z_mm: f64,
    pub height_mm: Option<f64>,
    pub crest_radius_mm: Option<f64>,
    /// Mean brightness of the crest (all-in-focus), for the photometric black-crest test.
    pub crest_gray: Option<f32>,
}

/// How the profile stage reports heights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProfileOptions {
    /// Each 1° bin's reported height is the trimmed mean of the 2h + 1 bins centred on it along
    /// the helix (a quarter of them, rounded down, dropped at each end: the middle 7 of 11), h
    /// being this half width (fewer at the ends of a measured run). One bin's own fit scatters by
    /// 4–13 µm RMS (its depth is noisy and the fit spans a few dozen samples); the thread's true
    /// height changes slowly along the helix (taper, run-out, the mill surface meeting the cone at
    /// a shallow angle), so averaging over a few degrees lowers the scatter, and the trimming
    /// keeps a spike out. The price is resolution: a dent of a degree or two is trimmed away and
    /// one of a few degrees flattened. 0 reports each bin's own fit.
    pub height_window_half_bins: usize,
}

impl Default for ProfileOptions {
    fn default() -> Self {
        Self { height_window_half_bins: 5 }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadMeasure {
    pub index: u32,
    pub bins: Vec<BinMeasure>,
}

/// Fundamental Fourier coefficient of the nominal form over one pitch (crest at x = 0).
fn form_fundamental(form: &ThreadForm) -> Complex<f64> {
    let n = 4096;
    let p = form.pitch_mm;
    let mut c = Complex::new(0.0, 0.0);
    for k in 0..n {
        let x = (k as f64 + 0.5) / n as f64 * p - p / 2.0;
        c += Complex::from_polar(form.height_at(x), -TAU * x / p);
    }
    c / n as f64
}

/// The map columns whose centres fall in the 1° bin [bin, bin + 1).
fn bin_columns(g: &crate::pipeline::surface::GridSpec, bin: usize) -> std::ops::Range<usize> {
    let per_bin = g.ntheta as f64 / 360.0;
    let start = (bin as f64 * per_bin).ceil() as usize;
    let end = (((bin + 1) as f64 * per_bin).ceil() as usize).min(g.ntheta);
    start..end
}

/// Mean generatrix r(z) of a 1° bin; None where the bin is mostly unseen.
fn bin_generatrix(map: &UnrolledMap, bin: usize) -> Option<Vec<f64>> {
    let g = &map.grid;
    let columns = bin_columns(g, bin);
    let mut profile = vec![f64::NAN; g.nz];
    let mut seen = 0;
    for (iz, value) in profile.iter_mut().enumerate() {
        let (mut s, mut n) = (0.0, 0);
        for it in columns.clone() {
            let r = map.radius_mm[map.index(iz, it)];
            if r.is_finite() {
                s += r as f64;
                n += 1;
            }
        }
        if n > 0 {
            *value = s / n as f64;
            seen += 1;
        }
    }
    if (seen as f64) < 0.7 * g.nz as f64 {
        return None;
    }
    // Fill gaps linearly so the spectrum sees no steps.
    let known: Vec<usize> = (0..g.nz).filter(|&i| profile[i].is_finite()).collect();
    for i in 0..g.nz {
        if profile[i].is_nan() {
            let after = known.iter().position(|&k| k > i);
            profile[i] = match after {
                Some(0) => profile[known[0]],
                Some(j) => {
                    let (a, b) = (known[j - 1], known[j]);
                    profile[a] + (profile[b] - profile[a]) * (i - a) as f64 / (b - a) as f64
                }
                None => profile[*known.last().unwrap()],
            };
        }
    }
    Some(profile)
}

/// Least-squares line through (z_k, r_k): (intercept at z = 0, slope).
fn fit_line(z: &[f64], r: &[f64]) -> (f64, f64) {
    let n = z.len() as f64;
    let (mz, mr) = (z.iter().sum::<f64>() / n, r.iter().sum::<f64>() / n);
    let (mut szz, mut szr) = (0.0, 0.0);
    for (a, b) in z.iter().zip(r) {
        szz += (a - mz) * (a - mz);
        szr += (a - mz) * (b - mr);
    }
    let slope = if szz > 0.0 { szr / szz } else { 0.0 };
    (mr - slope * mz, slope)
}

/// Estimates the helix from the fused map. None when no bin has enough data.
pub fn estimate_helix(map: &UnrolledMap, form: &ThreadForm) -> Option<Helix> {
    let g = &map.grid;
    let p = form.pitch_mm;
    let phase_form = form_fundamental(form).arg();
    let z: Vec<f64> = (0..g.nz).map(|i| g.z_at(i)).collect();
    let len = (g.nz * 4).next_power_of_two();
    let fft = FftPlanner::new().plan_fft_forward(len);
    let (mut sum_vec, mut slopes, mut used) = (Complex::new(0.0, 0.0), Vec::new(), 0usize);
    let mut per_bin = Vec::new();
    let mut buffer = vec![Complex::new(0.0, 0.0); len];
    for bin in 0..360 {
        let Some(profile) = bin_generatrix(map, bin) else { continue };
        let (a, slope) = fit_line(&z, &profile);
        // The spectrum: the strongest peak near the nominal fundamental says the data are a thread.
        for (k, slot) in buffer.iter_mut().enumerate() {
            *slot = if k < g.nz { Complex::new(profile[k] - a - slope * z[k], 0.0) } else { Complex::new(0.0, 0.0) };
        }
        fft.process(&mut buffer);
        let nominal_bin = (len as f64 * g.dz_mm / p).round() as usize;
        let lo = (nominal_bin as f64 * 0.85) as usize;
        let hi = ((nominal_bin as f64 * 1.15) as usize).min(len / 2 - 1);
        let peak = (lo..=hi).max_by(|&x, &y| buffer[x].norm().total_cmp(&buffer[y].norm()))?;
        let floor: f64 = buffer[1..len / 2].iter().map(|c| c.norm()).sum::<f64>() / (len / 2 - 1) as f64;
        if buffer[peak].norm() < 4.0 * floor {
            continue;
        }
        // Phase at exactly 1/pitch (direct DFT), then the crest position.
        let theta_deg = bin as f64 + 0.5;
        let x: Complex<f64> =
            (0..g.nz).map(|k| Complex::from_polar(profile[k] - a - slope * z[k], -TAU * z[k] / p)).sum();
        let z_crest = (phase_form - x.arg()) * p / TAU;
        let z_h = (z_crest - p * theta_deg / 360.0).rem_euclid(p);
        sum_vec += Complex::from_polar(1.0, TAU * z_h / p);
        slopes.push(slope);
        per_bin.push((bin, a, slope, profile));
        used += 1;
    }
    if used == 0 {
        return None;
    }
    let z_h_mm = (sum_vec.arg() * p / TAU).rem_euclid(p);
    slopes.sort_by(f64::total_cmp);
    let slope = slopes[slopes.len() / 2];
    // Residual of the analytic profile: nominal form at the measured phase on each bin's line.
    let kernel = form.kernel();
    let (mut sq, mut n) = (0.0, 0usize);
    for (bin, _, _, profile) in &per_bin {
        let theta_deg = *bin as f64 + 0.5;
        let model: Vec<f64> = z.iter().map(|&zz| kernel.height_at(zz - z_h_mm - p * theta_deg / 360.0)).collect();
        let resid: Vec<f64> = profile.iter().zip(&model).map(|(r, m)| r - m).collect();
        let (a, b) = fit_line(&z, &resid);
        for k in 0..z.len() {
            let e = resid[k] - a - b * z[k];
            sq += e * e;
            n += 1;
        }
    }
    Some(Helix {
        z_h_mm,
        pitch_mm: p,
        taper_on_diameter: 2.0 * slope,
        fit_rms_um: 1e3 * (sq / n as f64).sqrt(),
        bins_used: used,
    })
}

/// The helix phase again, from the full threads only and over whole pitches.
///
/// [`estimate_helix`] reads the phase over each generatrix's whole length, which takes in what is
/// not the nominal form: the chamfer at the pipe end and the vanishing threads at the far end
/// (crests on the mill surface, roots rising). On an asymmetric form those shift the fundamental's
/// phase (tens of µm on a few views of a short-threaded part). Here each 1° bin is read only
/// between the first and last full threads (nine bins in ten within max(tolerance, 2% of the
/// height) of nominal, the crest at least 1.5 pitches from the end face, clear of the chamfer zone
/// as the crest stage takes it, and measured over at least half as many bins as the most measured
/// thread), from half a pitch before the first crest centre line to half a pitch after the last: a
/// whole number of pitches, over which the taper line is fitted beside the harmonics
/// ([`fundamental_beside_a_line`]). Twice, since the window follows the phase. The first estimate
/// stands where fewer than two full threads are measured.
pub fn refine_helix(map: &UnrolledMap, form: &ThreadForm, helix: &Helix, threads: &[ThreadMeasure]) -> Helix {
    let p = helix.pitch_mm;
    let g = &map.grid;
    let close = form.height_tolerance_mm.max(0.02 * form.height_mm);
    // Full threads are measured around as much of the circumference as any thread is.
    let most_bins = threads.iter().map(|t| t.bins.iter().filter(|b| b.height_mm.is_some()).count()).max().unwrap_or(0);
    let full: Vec<bool> = threads
        .iter()
        .map(|t| {
            let heights: Vec<f64> = t.bins.iter().filter_map(|b| b.height_mm).collect();
            let clear_of_chamfer = t.bins.first().is_some_and(|b| b.crest_z_mm >= 1.5 * p);
            let near = heights.iter().filter(|h| (*h - form.height_mm).abs() <= close).count();
            heights.len() >= (most_bins / 2).max(1) && clear_of_chamfer && near as f64 >= 0.9 * heights.len() as f64
        })
        .collect();
    // The longest run of full threads (the first of equally long ones: max_by_key keeps the last).
    let best = crate::numeric::runs::run_spans(&full).into_iter().rev().max_by_key(|run| run.len()).unwrap_or(0..0);
    if best.len() < 2 {
        return helix.clone();
    }
    let (first, last) = (threads[best.start].index as f64, threads[best.end - 1].index as f64);
    let phase_form = form_fundamental(form).arg();
    let profiles: Vec<(usize, Vec<f64>)> =
        (0..360).into_par_iter().filter_map(|bin| Some((bin, bin_generatrix(map, bin)?))).collect();
    let mut z_h_mm = helix.z_h_mm;
    for _ in 0..2 {
        let phasors: Vec<Option<Complex<f64>>> = profiles
            .par_iter()
            .map(|(bin, profile)| {
                let theta_deg = *bin as f64 + 0.5;
                let centre = |index: f64| z_h_mm + p * (index - 1.0 + theta_deg / 360.0);
                let (lo, hi) = (centre(first) - 0.5 * p, centre(last) + 0.5 * p);
                let rows: Vec<usize> = (0..g.nz).filter(|&iz| (lo..hi).contains(&g.z_at(iz))).collect();
                if (rows.len() as f64) < 0.9 * (hi - lo) / g.dz_mm {
                    return None; // the window runs off the map
                }
                let fundamental = fundamental_beside_a_line(rows.iter().map(|&iz| (g.z_at(iz), profile[iz])), p)?;
                let z_crest = (phase_form - fundamental.arg()) * p / TAU;
                let z_h = (z_crest - p * theta_deg / 360.0).rem_euclid(p);
                Some(Complex::from_polar(1.0, TAU * z_h / p))
            })
            .collect();
        // Summed in bin order, so the result does not depend on the scheduling.
        let sum: Complex<f64> = phasors.into_iter().flatten().sum();
        if sum.norm() == 0.0 {
            return helix.clone();
        }
        z_h_mm = (sum.arg() * p / TAU).rem_euclid(p);
    }
    Helix { z_h_mm, ..helix.clone() }
}

/// Harmonics fitted beside the fundamental in [`fundamental_beside_a_line`].
const HARMONICS: usize = 6;

/// The coefficient of exp(i·2πz/p) in a least-squares fit of r(z) by a line and the first
/// [`HARMONICS`] harmonics of 1/p, jointly. A line fitted first and removed would take part of an
/// asymmetric thread with it (its first moment over each pitch is not zero) and hand the
/// fundamental a ramp's share; fitted together, the line takes only the taper.
fn fundamental_beside_a_line(samples: impl Iterator<Item = (f64, f64)>, p: f64) -> Option<Complex<f64>> {
    const N: usize = 2 + 2 * HARMONICS;
    let (mut ata, mut atb) = (nalgebra::SMatrix::<f64, N, N>::zeros(), nalgebra::SVector::<f64, N>::zeros());
    let mut count = 0;
    for (z, r) in samples {
        let mut row = nalgebra::SVector::<f64, N>::zeros();
        row[0] = 1.0;
        row[1] = z;
        for k in 1..=HARMONICS {
            let (sin, cos) = (TAU * k as f64 * z / p).sin_cos();
            row[2 * k] = cos;
            row[2 * k + 1] = sin;
        }
        ata += row * row.transpose();
        atb += row * r;
        count += 1;
    }
    if count < 4 * N {
        return None;
    }
    let solution = ata.cholesky()?.solve(&atb);
    // r ⊃ c·cos + s·sin = Re((c − i·s)·exp(i·2πz/p)): the coefficient the DFT's phase reads.
    Some(Complex::new(solution[2], -solution[3]))
}

/// Half width of the strip around the crest centre line whose brightness decides black crests.
const CREST_LINE_HALF_MM: f64 = 0.15;

/// Half width along z of the window a crest's radius is fitted over (the crest stage models how a
/// mill surface that cuts part of that window shows in the fitted radius).
pub fn crest_window_half_mm(form: &ThreadForm) -> f64 {
    windows(form).0
}

/// Half widths of the windows fitted around the crest and root centres.
fn windows(form: &ThreadForm) -> (f64, f64) {
    match form.profile {
        ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, crest_width_mm } => {
            let root = form.pitch_mm
                - crest_width_mm
                - form.height_mm * (load_flank_deg.to_radians().tan() + stab_flank_deg.to_radians().tan());
            (0.6 * crest_width_mm / 2.0, 0.6 * root / 2.0)
        }
        ProfileShape::Rounded { flank_deg, .. } => {
            // An arc meets its flanks at ρ·cos α either side of its centre.
            let cos = flank_deg.to_radians().cos();
            let (crest, root) = form.arc_radii_mm().expect("a rounded form");
            (0.6 * (crest * cos), 0.6 * (root * cos))
        }
    }
}

/// Nominal curvatures (c of r = c·x²) of a rounded form's crest and root arcs (∓1/2ρ); None for
/// a flat-crested form.
fn nominal_curvatures(form: &ThreadForm) -> Option<(f64, f64)> {
    form.arc_radii_mm().map(|(crest, root)| (-0.5 / crest, 0.5 / root))
}

/// The part of a crest's or root's section about its centre that is fitted once for the whole
/// part rather than per bin: flat for a buttress, r = c·x² for a round thread.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Section {
    Flat,
    Parabola { c_per_mm: f64 },
}

impl Section {
    fn offset_mm(self, x: f64) -> f64 {
        match self {
            Section::Flat => 0.0,
            Section::Parabola { c_per_mm } => c_per_mm * x * x,
        }
    }
}

/// Least-squares curvature c of r = a + b·x + c·x² (None without enough samples spread in x).
fn fit_curvature(pts: &[(f64, f64)]) -> Option<f64> {
    if pts.len() < 9 {
        return None;
    }
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for &(x, r) in pts {
        let row = nalgebra::Vector3::new(1.0, x, x * x);
        ata += row * row.transpose();
        atb += row * r;
    }
    ata.lu().solve(&atb).map(|sol| sol[2])
}

/// The section's curvature shared by all crests (or roots) of a round thread: the median of the
/// windows' own curvatures. Measured rather than taken from the form because the fused surface is
/// the true one smoothed by the focus window; fitted once, it costs each bin no variance, whereas a
/// free curvature per bin more than doubles the variance of the height at the centre. Falls back
/// to the form's nominal curvature when too few windows are usable.
fn shared_section(windows: &[&[(f64, f64)]], nominal_c_per_mm: f64) -> Section {
    let mut c: Vec<f64> = windows.iter().filter_map(|w| fit_curvature(w)).filter(|c| c.is_finite()).collect();
    let measured = if c.len() < 30 { None } else { median(&mut c) };
    Section::Parabola { c_per_mm: measured.unwrap_or(nominal_c_per_mm) }
}

/// Value at x = 0 of a least-squares fit r = a + b·x + section(x) with one pass of outlier rejection
/// (residuals beyond 3 MAD). The section's shape is known from the form, so only its height and
/// tilt are fitted: a free curvature term would more than double the variance of the height at
/// the centre. None unless samples lie on both sides of the centre (`half` is the window's half
/// width): an edge of the data would make it an extrapolation.
fn fit_at_centre(samples: &[(f64, f64)], section: Section, half: f64) -> Option<f64> {
    let (lo, hi) = samples.iter().fold((f64::MAX, f64::MIN), |(l, h), s| (l.min(s.0), h.max(s.0)));
    if lo > -0.5 * half || hi < 0.5 * half {
        return None;
    }
    let levelled: Vec<(f64, f64)> = samples.iter().map(|&(x, r)| (x, r - section.offset_mm(x))).collect();
    let (a, b) = fit_line_checked(&levelled)?;
    let mut resid: Vec<f64> = levelled.iter().map(|&(x, r)| (r - a - b * x).abs()).collect();
    let mut sorted = resid.clone();
    sorted.sort_by(f64::total_cmp);
    let mad = sorted[sorted.len() / 2].max(1e-6);
    let kept: Vec<(f64, f64)> =
        levelled.iter().zip(resid.iter_mut()).filter(|(_, e)| **e <= 3.0 * 1.4826 * mad).map(|(s, _)| *s).collect();
    fit_line_checked(&kept).map(|(a, _)| a)
}

/// [`fit_line`] through at least six samples that spread in x.
fn fit_line_checked(pts: &[(f64, f64)]) -> Option<(f64, f64)> {
    let (x, r): (Vec<f64>, Vec<f64>) = pts.iter().copied().unzip();
    let spread = x.iter().fold(f64::MAX, |m, &v| m.min(v)) < x.iter().fold(f64::MIN, |m, &v| m.max(v));
    (pts.len() >= 6 && spread).then(|| fit_line(&x, &r))
}

/// Heights of every thread whose crest line starts within the map, per 1° bin.
pub fn measure_threads(
    map: &UnrolledMap,
    form: &ThreadForm,
    helix: &Helix,
    options: &ProfileOptions,
) -> Vec<ThreadMeasure> {
    measure_threads_every(map, form, helix, options, 1)
}

/// Bins between surveyed ones in [`survey_threads`].
const SURVEY_BIN_STEP: usize = 6;

/// [`measure_threads`] on every sixth 1° bin only (0.5°, 6.5°, …), for [`refine_helix`], which
/// asks of the first helix estimate only which threads are full (fractions of each thread's
/// bins): a sixth of the work, and on every benchmark and held-out case the same threads, hence
/// the same refined helix and report, as all 360 bins.
pub fn survey_threads(
    map: &UnrolledMap,
    form: &ThreadForm,
    helix: &Helix,
    options: &ProfileOptions,
) -> Vec<ThreadMeasure> {
    measure_threads_every(map, form, helix, options, SURVEY_BIN_STEP)
}

fn measure_threads_every(
    map: &UnrolledMap,
    form: &ThreadForm,
    helix: &Helix,
    options: &ProfileOptions,
    bin_step: usize,
) -> Vec<ThreadMeasure> {
    let g = &map.grid;
    let p = helix.pitch_mm;
    let (crest_half, root_half) = windows(form);
    let (before, after) = form.root_centres_mm();
    let z_max = g.z0_mm + g.nz as f64 * g.dz_mm;
    let mut threads: Vec<ThreadMeasure> = Vec::new();
    let mut index = 1u32;
    while helix.z_h_mm + p * (index - 1) as f64 <= z_max {
        threads.push(ThreadMeasure { index, bins: Vec::with_capacity(360) });
        index += 1;
    }
    /// One thread's windows in one bin, in thread coordinates (x = z − centre, r).
    struct Pending {
        thread: usize,
        angle_deg: f64,
        crest_z_mm: f64,
        crest: Vec<(f64, f64)>,
        root_before: Vec<(f64, f64)>,
        root_after: Vec<(f64, f64)>,
        crest_gray: Option<f32>,
    }
    // A window's samples in thread coordinates u = (z − z_h)/p − θ/360 (crest of thread i at
    // u = i − 1): per column of the bin, the rows whose u falls in the window (found from the
    // window's z range, then each one checked on u itself), sorted by u; ties keep the order of
    // the columns, then the rows.
    let window = |columns: std::ops::Range<usize>, centre_u: f64, half_mm: f64| -> Vec<(f64, f64, f32)> {
        let (lo, hi) = (centre_u - half_mm / p, centre_u + half_mm / p);
        let mut samples: Vec<(f64, f64, f32)> = Vec::new();
        for it in columns {
            let theta = g.theta_deg_at(it);
            // Rows whose centre z is in the window's z range, a row's slack either side.
            let row_of =
                |u: f64| ((helix.z_h_mm + p * (u + theta / 360.0) - g.z0_mm) / g.dz_mm - 0.5).clamp(-1.0, g.nz as f64);
            let first = (row_of(lo).floor() - 1.0).max(0.0) as usize;
            let last = ((row_of(hi).ceil() + 1.0).max(0.0) as usize).min(g.nz.saturating_sub(1));
            for iz in first..=last {
                let i = map.index(iz, it);
                let r = map.radius_mm[i];
                if r.is_finite() {
                    let u = (g.z_at(iz) - helix.z_h_mm) / p - theta / 360.0;
                    if u >= lo && u <= hi {
                        samples.push((u, r as f64, map.gray(i)));
                    }
                }
            }
        }
        samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        samples.into_iter().map(|(u, r, g)| ((u - centre_u) * p, r, g)).collect()
    };
    // Bins are gathered in parallel and kept in bin order, then thread order.
    let pending: Vec<Pending> = (0..360)
        .into_par_iter()
        .step_by(bin_step.max(1))
        .map(|bin| {
            let centre_deg = bin as f64 + 0.5;
            let columns = bin_columns(g, bin);
            threads
                .iter()
                .enumerate()
                .map(|(t, thread)| {
                    let u_crest = (thread.index - 1) as f64;
                    let crest_z = helix.z_h_mm + p * (u_crest + centre_deg / 360.0);
                    let crest = window(columns.clone(), u_crest, crest_half);
                    let xy = |w: &[(f64, f64, f32)]| w.iter().map(|&(x, r, _)| (x, r)).collect::<Vec<_>>();
                    // Black is defined on the crest centre line: its brightness, not the whole flat's
                    // (at the onset of a black crest only a strip around the centre line keeps the
                    // mill scale).
                    let centre_line: Vec<f32> =
                        crest.iter().filter(|s| s.0.abs() <= CREST_LINE_HALF_MM).map(|s| s.2).collect();
                    let crest_gray =
                        (!centre_line.is_empty()).then(|| centre_line.iter().sum::<f32>() / centre_line.len() as f32);
                    Pending {
                        thread: t,
                        angle_deg: centre_deg,
                        crest_z_mm: crest_z,
                        crest: xy(&crest),
                        root_before: xy(&window(columns.clone(), u_crest + before / p, root_half)),
                        root_after: xy(&window(columns.clone(), u_crest + after / p, root_half)),
                        crest_gray,
                    }
                })
                .collect::<Vec<_>>()
        })
        .flatten_iter()
        .collect();
    let (crest_section, root_section) = match nominal_curvatures(form) {
        None => (Section::Flat, Section::Flat),
        Some((crest_c, root_c)) => {
            let crests: Vec<&[(f64, f64)]> = pending.iter().map(|w| w.crest.as_slice()).collect();
            let roots: Vec<&[(f64, f64)]> =
                pending.iter().flat_map(|w| [w.root_before.as_slice(), w.root_after.as_slice()]).collect();
            (shared_section(&crests, crest_c), shared_section(&roots, root_c))
        }
    };
    let measured: Vec<BinMeasure> = pending
        .par_iter()
        .map(|w| {
            let crest_r = fit_at_centre(&w.crest, crest_section, crest_half);
            let rb = fit_at_centre(&w.root_before, root_section, root_half);
            let ra = fit_at_centre(&w.root_after, root_section, root_half);
            // A root whose window reaches past the end face is not on the part (or is the chamfer):
            // there is no adjacent root to measure from. Nor is one whose window reaches into the
            // map's first cell on the part: that cell holds the end face's edge, whose silhouette
            // pulls the fused radius off the root (round thread 1's first bins read 25–50 µm high).
            let root_on_part = w.crest_z_mm + before - root_half > g.dz_mm;
            let height = match (crest_r, rb, ra) {
                (Some(c), Some(b), Some(a)) if root_on_part => {
                    Some(c - (b + (a - b) * (0.0 - before) / (after - before)))
                }
                _ => None,
            };
            BinMeasure {
                angle_deg: w.angle_deg,
                crest_z_mm: w.crest_z_mm,
                height_mm: height,
                crest_radius_mm: crest_r,
                crest_gray: w.crest_gray,
            }
        })
        .collect();
    for (w, bin) in pending.iter().zip(measured) {
        threads[w.thread].bins.push(bin);
    }
    // Along the helix, thread i's last bin (359.5°) is followed by thread i + 1's first (0.5°).
    let helix_order: Vec<Option<f64>> = threads.iter().flat_map(|t| t.bins.iter().map(|b| b.height_mm)).collect();
    let filtered = trimmed_mean(&helix_order, options.height_window_half_bins);
    for (bin, h) in threads.iter_mut().flat_map(|t| t.bins.iter_mut()).zip(filtered) {
        bin.height_mm = h;
    }
    threads
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::pipeline::surface::GridSpec;

    /// A synthetic fused map of an ideal buttress thread.
    fn ideal_map(z_h: f64, noise: f64) -> (UnrolledMap, ThreadForm) {
        ideal_map_of(ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap(), z_h, noise)
    }

    /// A synthetic fused map of an ideal thread of `form`, with uniform noise of ± `noise` mm.
    fn ideal_map_of(form: ThreadForm, z_h: f64, noise: f64) -> (UnrolledMap, ThreadForm) {
        let pitch = form.pitch_mm;
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.04, nz: 800, ntheta: 1440 };
        let mut radius = Vec::with_capacity(grid.nz * grid.ntheta);
        let mut seed = 12345u64;
        for iz in 0..grid.nz {
            for it in 0..grid.ntheta {
                let (z, theta) = (grid.z_at(iz), grid.theta_deg_at(it));
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let jitter = ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 2.0 * noise;
                let r = 55.0 + z * form.radius_slope() + form.height_at(z - z_h - pitch * theta / 360.0) + jitter;
                radius.push(r as f32);
            }
        }
        let cells = radius.len();
        (UnrolledMap { grid, radius_mm: radius, weight: vec![1.0; cells], rgb: vec![[0.6; 3]; cells] }, form)
    }

    /// Threads vanishing towards the far end (their roots rising, as on the seed's Table 1 part)
    /// pull the whole-length phase of an asymmetric form; read over the full threads alone (and
    /// with the taper line fitted beside the harmonics), the phase is the crests' again.
    #[test]
    fn the_helix_phase_is_read_over_the_full_threads() {
        let z_h = 1.234;
        let (mut map, form) = ideal_map(z_h, 0.0);
        let g = map.grid.clone();
        // From z = 26 mm the roots rise 0.25 mm per mm above the root cone.
        for iz in 0..g.nz {
            let floor_mm = 55.0 + g.z_at(iz) * form.radius_slope() + 0.25 * (g.z_at(iz) - 26.0).max(0.0);
            for it in 0..g.ntheta {
                let i = map.index(iz, it);
                map.radius_mm[i] = map.radius_mm[i].max(floor_mm as f32);
            }
        }
        let first = estimate_helix(&map, &form).unwrap();
        let threads = measure_threads(&map, &form, &first, &ProfileOptions::default());
        let refined = refine_helix(&map, &form, &first, &threads);
        assert!(refined.z_h_mm != first.z_h_mm, "two full threads were found, so the phase was read again");
        let after_um = 1e3 * (refined.z_h_mm - z_h).abs();
        assert!(after_um < 1.0, "full threads {after_um} µm");
        // The survey of every sixth bin (what the pipeline hands refine_helix) finds the same full
        // threads, so the same helix, bit for bit.
        let surveyed = survey_threads(&map, &form, &first, &ProfileOptions::default());
        assert!(surveyed.iter().all(|t| t.bins.len() == 60 && t.bins[1].angle_deg == 6.5), "every sixth bin");
        assert_eq!(refine_helix(&map, &form, &first, &surveyed), refined);
    }

    /// Over a few pitches of an asymmetric (buttress) form on a taper, a line removed first takes
    /// part of the thread with it and shifts the fundamental's phase; fitted beside the harmonics
    /// it does not.
    #[test]
    fn the_fundamental_is_fitted_beside_the_taper_line() {
        let form = ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap();
        let p = form.pitch_mm;
        let phase_form = form_fundamental(&form).arg();
        let z_crest = 1.1;
        let samples: Vec<(f64, f64)> = (0..381)
            .map(|k| 0.04 * k as f64 + z_crest - 0.5 * p)
            .map(|z| (z, 55.0 + form.radius_slope() * z + form.height_at(z - z_crest)))
            .collect();
        let crest_from = |c: Complex<f64>| (phase_form - c.arg()) * p / TAU;
        let joint = crest_from(fundamental_beside_a_line(samples.iter().copied(), p).unwrap());
        let (z, r): (Vec<f64>, Vec<f64>) = samples.iter().copied().unzip();
        let (a, b) = fit_line(&z, &r);
        let line_first =
            crest_from(z.iter().zip(&r).map(|(&z, &r)| Complex::from_polar(r - a - b * z, -TAU * z / p)).sum());
        let wrap = |x: f64| 1e3 * ((x - z_crest + 0.5 * p).rem_euclid(p) - 0.5 * p).abs();
        assert!(
            wrap(joint) < 0.2 && wrap(line_first) > 1.0,
            "joint {} µm, line first {} µm",
            wrap(joint),
            wrap(line_first)
        );
    }

    #[test]
    fn helix_and_heights_of_an_ideal_thread() {
        let (map, form) = ideal_map(1.234, 0.0);
        let helix = estimate_helix(&map, &form).unwrap();
        assert!((helix.z_h_mm - 1.234).abs() < 0.01, "{}", helix.z_h_mm);
        assert!((helix.taper_on_diameter - 0.0625).abs() < 0.005, "{}", helix.taper_on_diameter);
        let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
        let mut checked = 0;
        for t in &threads {
            for b in &t.bins {
                if let Some(h) = b.height_mm {
                    assert!((h - 1.5748).abs() < 0.002, "thread {} at {}: {h}", t.index, b.angle_deg);
                    checked += 1;
                }
            }
        }
        assert!(checked > 360 * 4, "{checked}");
    }

    #[test]
    fn noise_averages_out() {
        let (map, form) = ideal_map(3.9, 0.06);
        let helix = estimate_helix(&map, &form).unwrap();
        assert!((helix.z_h_mm - 3.9).abs() < 0.02, "{}", helix.z_h_mm);
        let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
        let heights: Vec<f64> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.height_mm)).collect();
        let rms = (heights.iter().map(|h| (h - 1.5748).powi(2)).sum::<f64>() / heights.len() as f64).sqrt();
        assert!(rms < 0.01, "{rms}");
    }

    /// The map's first cell on the part holds the end face's edge, whose silhouette pulls the
    /// fused radius off the surface: no root window reaches into it.
    #[test]
    fn the_end_face_cell_is_not_taken_for_a_root() {
        let form = ThreadForm::api_round(3.175, 1.810, 0.05, 0.0625, None).unwrap();
        let (mut map, form) = ideal_map_of(form, 1.1, 0.01);
        let helix = estimate_helix(&map, &form).unwrap();
        let options = ProfileOptions { height_window_half_bins: 0 };
        let clean = measure_threads(&map, &form, &helix, &options);
        // The edge reads 12 µm low all round (within the noise's reach: no outlier to reject).
        let ntheta = map.grid.ntheta;
        map.radius_mm[..ntheta].iter_mut().for_each(|r| *r -= 0.012);
        let edged = measure_threads(&map, &form, &helix, &options);
        // Every height as before, but for the shared section's curvature, refitted over windows
        // that include the edge (−0.017 µm on every bin here). With the root windows allowed into
        // the edge cell, thread 1's first bin reads +0.44 µm.
        let mut measured = 0;
        for (e, c) in edged[0].bins.iter().zip(&clean[0].bins) {
            assert_eq!(e.height_mm.is_some(), c.height_mm.is_some());
            if let (Some(edged_mm), Some(clean_mm)) = (e.height_mm, c.height_mm) {
                assert!(
                    (edged_mm - clean_mm).abs() < 1e-4,
                    "{}° moved {} µm",
                    e.angle_deg,
                    (edged_mm - clean_mm) * 1e3
                );
                measured += 1;
            }
        }
        assert!(measured > 200, "{measured}");
    }

    /// A round thread's crest and root arcs: the shared curvature is measured from the map (here
    /// the form's own, ∓1/2ρ) and the heights come out unbiased with less scatter than a free
    /// curvature per bin would give.
    #[test]
    fn round_thread_heights_with_a_shared_section() {
        let form = ThreadForm::api_round(3.175, 1.810, 0.05, 0.0625, None).unwrap();
        let nominal = form.height_mm;
        let (crest_c, root_c) = nominal_curvatures(&form).unwrap();
        assert!(crest_c < 0.0 && root_c > 0.0, "{crest_c} {root_c}");
        let (map, form) = ideal_map_of(form, 2.2, 0.03);
        let helix = estimate_helix(&map, &form).unwrap();
        assert!((helix.z_h_mm - 2.2).abs() < 0.02, "{}", helix.z_h_mm);
        let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
        let heights: Vec<f64> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.height_mm)).collect();
        assert!(heights.len() > 360 * 5, "{}", heights.len());
        let mean = heights.iter().sum::<f64>() / heights.len() as f64;
        let rms = (heights.iter().map(|h| (h - nominal).powi(2)).sum::<f64>() / heights.len() as f64).sqrt();
        assert!((mean - nominal).abs() < 0.002, "bias {}", mean - nominal);
        assert!(rms < 0.006, "{rms}");
    }

    #[test]
    fn fixed_section_fit_recovers_the_centre_of_an_arc() {
        let radius = 0.45;
        let section = Section::Parabola { c_per_mm: -0.5 / radius };
        // An arc seen from x = −0.25 … 0.25 mm, tilted by the taper.
        let pts: Vec<(f64, f64)> =
            (0..=50).map(|i| -0.25 + 0.01 * i as f64).map(|x| (x, 10.0 + 0.03 * x - x * x / (2.0 * radius))).collect();
        let centre = fit_at_centre(&pts, section, 0.25).unwrap();
        assert!((centre - 10.0).abs() < 1e-9, "{centre}");
        let measured = fit_curvature(&pts).unwrap();
        assert!((measured + 0.5 / radius).abs() < 1e-6, "{measured}");
        // Samples on one side only: an extrapolation, refused.
        assert!(fit_at_centre(&pts[30..], section, 0.25).is_none());
    }
}
