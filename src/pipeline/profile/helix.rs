//! The helix: its phase z_h, pitch and taper from the Fourier fundamental of each bin's generatrix
//! at the thread's pitch, first over the whole map, then refined over the full threads.

use super::*;

/// Fundamental Fourier coefficient of the nominal form over one pitch (crest at x = 0).
pub(super) fn form_fundamental(form: &ThreadForm) -> Complex<f64> {
    let n = 4096;
    let p = form.pitch_mm;
    let mut c = Complex::new(0.0, 0.0);
    for k in 0..n {
        let x = (k as f64 + 0.5) / n as f64 * p - p / 2.0;
        c += Complex::from_polar(form.height_at(x), -TAU * x / p);
    }
    c / n as f64
}

/// Mean generatrix r(z) of a 1° bin; None where the bin is mostly unseen.
pub(super) fn bin_generatrix(map: &UnrolledMap, bin: usize) -> Option<Vec<f64>> {
    let g = &map.grid;
    let columns = g.bin_columns(bin);
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

/// Estimates the helix from the fused map. None when no bin has enough data.
pub fn estimate_helix(map: &UnrolledMap, form: &ThreadForm) -> Option<Helix> {
    let g = &map.grid;
    let p = form.pitch_mm;
    let phase_form = form_fundamental(form).arg();
    let z: Vec<f64> = (0..g.nz).map(|i| g.z_at(i)).collect();
    let len = (g.nz * 4).next_power_of_two();
    let fft = FftPlanner::new().plan_fft_forward(len);
    let (mut sum_vec, mut slopes, mut used) = (Complex::new(0.0, 0.0), Vec::new(), 0usize);
    let mut readings = Vec::new();
    let mut amplitudes = Vec::new();
    let nominal_amplitude = form_fundamental(form).norm();
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
        readings.push((bin as u16, z_h));
        amplitudes.push(x.norm() / g.nz as f64 / nominal_amplitude);
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
        amplitude_ratio: median(&mut amplitudes),
        phase_readings: readings,
        local_offsets_mm: Vec::new(),
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
    let mut readings = Vec::new();
    for _ in 0..2 {
        let phasors: Vec<Option<(u16, Complex<f64>)>> = profiles
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
                Some((*bin as u16, Complex::from_polar(1.0, TAU * z_h / p)))
            })
            .collect();
        // Summed in bin order, so the result does not depend on the scheduling.
        let sum: Complex<f64> = phasors.iter().flatten().map(|(_, c)| c).sum();
        if sum.norm() == 0.0 {
            return helix.clone();
        }
        z_h_mm = (sum.arg() * p / TAU).rem_euclid(p);
        readings = phasors.into_iter().flatten().map(|(bin, c)| (bin, (c.arg() * p / TAU).rem_euclid(p))).collect();
    }
    Helix { z_h_mm, phase_readings: readings, ..helix.clone() }
}

/// Harmonics fitted beside the fundamental in [`fundamental_beside_a_line`].
pub(super) const HARMONICS: usize = 6;

/// The coefficient of exp(i·2πz/p) in a least-squares fit of r(z) by a line and the first
/// [`HARMONICS`] harmonics of 1/p, jointly. A line fitted first and removed would take part of an
/// asymmetric thread with it (its first moment over each pitch is not zero) and hand the
/// fundamental a ramp's share; fitted together, the line takes only the taper.
pub(super) fn fundamental_beside_a_line(samples: impl Iterator<Item = (f64, f64)>, p: f64) -> Option<Complex<f64>> {
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

/// How far the windows the one helix places may sit from the crests they are meant for, from the
/// generatrices' own phase readings ([`Helix::phase_readings`]), or where too few sectors read it,
/// from the helix's fit residual.
#[derive(Clone, Debug, PartialEq)]
pub struct PhaseUncertainty {
    /// Sectors of the circumference (one view's spacing each) that read the phase: a view's pose
    /// error moves all its generatrices together, so each sector is one independent reading.
    pub sectors: usize,
    /// RMS of the generatrices' readings about where the windows sit, mm: about z_h (where one
    /// view's crests sit off the helix), or about their bins' local phase where the windows follow
    /// it ([`Helix::with_local_phase`]), then times √2 for that local median's own error.
    pub spread_mm: f64,
    /// How a bin's windows' place along z is distributed about the crest they are meant for.
    pub error: PhaseError,
    /// Its standard deviation, mm.
    pub u_mm: f64,
    /// The phase is not known within the pitch: uniform over it.
    pub unknown: bool,
}

/// The distribution of a bin's windows' error along z.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PhaseError {
    /// Three or more sectors read the phase: normal, with the readings' spread and the windows'
    /// common error from the sectors' scatter (Student's t on their degrees of freedom, so that the
    /// coverage factor 2 gives 95%).
    Normal { sigma_mm: f64 },
    /// Fewer sectors, whose readings cannot show their own error: within ± the shift at which the
    /// nominal form moved against itself differs by the helix's fit residual (the residual holds
    /// the shift's difference and the noise, so the shift can be no larger), uniformly (GUM
    /// 4.3.7); over the whole pitch where no shift reaches the residual.
    Uniform { half_width_mm: f64 },
}

/// The smallest shift along z at which the nominal form differs from itself by `rms_mm` RMS over
/// a pitch; None where no shift up to half a pitch does.
fn shift_of_residual(form: &ThreadForm, rms_mm: f64) -> Option<f64> {
    let kernel = form.kernel();
    let p = form.pitch_mm;
    let samples: Vec<f64> = (0..400).map(|i| p * (i as f64 + 0.5) / 400.0).collect();
    (1..=200).map(|k| p * k as f64 / 400.0).find(|&shift| {
        let sq: f64 = samples.iter().map(|&x| (kernel.height_at(x) - kernel.height_at(x - shift)).powi(2)).sum();
        (sq / samples.len() as f64).sqrt() > rms_mm
    })
}

impl Helix {
    /// This helix with each 1° bin's crests read where the generatrices within `half_window_bins`
    /// of it put them: the median of their readings' departures from z_h. A view placed
    /// off along z (its encoder's axial error, or its angle's: a degree is a 360th of the pitch)
    /// shows its crests off the helix over its own bins; windows placed by the one helix would sit
    /// off them by as much, which on a round thread's arcs lowers the height with the square of the
    /// offset. Half a view's spacing either side, so that a window's mean stays within one view or
    /// the overlap two views share. Bins with readings at fewer than half the bins within reach
    /// keep z_h.
    pub fn with_local_phase(mut self, half_window_bins: usize) -> Helix {
        let mut by_bin: Vec<Option<f64>> = vec![None; 360];
        for (bin, z) in &self.phase_readings {
            if let Some(slot) = by_bin.get_mut(*bin as usize) {
                *slot = Some(self.departure_mm(*z));
            }
        }
        let w = half_window_bins.min(179) as isize;
        self.local_offsets_mm = (0..360isize)
            .map(|bin| {
                let mut read: Vec<f64> = (-w..=w).filter_map(|k| by_bin[(bin + k).rem_euclid(360) as usize]).collect();
                // Fewer readings than half the reach: the edge of what the views covered, whose
                // few generatrices are the least reliable; the helix stands there. The median, so
                // that one misread generatrix (a view's edge) does not move its neighbours.
                if (read.len() as isize) < w + 1 { 0.0 } else { median(&mut read).unwrap_or(0.0) }
            })
            .collect();
        self
    }

    /// Where bin `bin`'s crests lie along z relative to z_h, mm ([`Helix::with_local_phase`]).
    pub fn local_offset_mm(&self, bin: usize) -> f64 {
        self.local_offsets_mm.get(bin).copied().unwrap_or(0.0)
    }

    /// A phase reading's departure from z_h, wrapped into [−p/2, p/2), mm.
    fn departure_mm(&self, z_mm: f64) -> f64 {
        let p = self.pitch_mm;
        (z_mm - self.z_h_mm + p / 2.0).rem_euclid(p) - p / 2.0
    }

    /// The phase's uncertainty for `form` at a station whose views are `sector_deg` apart.
    pub fn phase_uncertainty(&self, form: &ThreadForm, sector_deg: f64) -> PhaseUncertainty {
        let p = self.pitch_mm;
        // Each reading's departure from where its bin's windows sit: z_h, or the bin's local phase.
        let left: Vec<(u16, f64)> = self
            .phase_readings
            .iter()
            .map(|&(bin, z)| (bin, self.departure_mm(z - self.local_offset_mm(bin as usize))))
            .collect();
        // Where the windows follow the local readings, what is left is each reading's departure
        // from its neighbours' median, and that median's own error, taken as large.
        let local = !self.local_offsets_mm.is_empty();
        let spread_mm = if left.is_empty() {
            0.0
        } else {
            let rms = (left.iter().map(|(_, d)| d * d).sum::<f64>() / left.len() as f64).sqrt();
            if local { std::f64::consts::SQRT_2 * rms } else { rms }
        };
        let width = sector_deg.clamp(1.0, 360.0);
        let mut sectors: std::collections::BTreeMap<usize, Complex<f64>> = Default::default();
        for (bin, d) in &left {
            *sectors.entry(((*bin as f64 + 0.5) / width) as usize).or_default() +=
                Complex::from_polar(1.0, TAU * d / p);
        }
        let means: Vec<f64> = sectors.values().map(|c| c.arg() * p / TAU).collect();
        let k = means.len();
        let uniform = |half_width_mm: f64| {
            let half_width_mm = half_width_mm.min(p / 2.0);
            PhaseUncertainty {
                sectors: k,
                spread_mm,
                error: PhaseError::Uniform { half_width_mm },
                u_mm: half_width_mm / 3f64.sqrt(),
                unknown: half_width_mm >= p / 2.0,
            }
        };
        if k < 3 {
            // The surface's profile is the form's scaled by the amplitude ratio (depth from focus
            // flattens it where the depth of field is a fair part of the height), and so is its
            // difference from itself at a shift.
            let scale = self.amplitude_ratio.unwrap_or(1.0).clamp(0.05, 1.0);
            return uniform(shift_of_residual(form, 1e-3 * self.fit_rms_um / scale).unwrap_or(p / 2.0));
        }
        // About zero: z_h is the generatrices' mean, not the sectors', and the difference counts.
        let between = (means.iter().map(|m| m * m).sum::<f64>() / (k - 1) as f64).sqrt();
        let z_h_u = 0.5 * crate::numeric::stats::student_t_975(k - 1) * between / (k as f64).sqrt();
        let sigma_mm = spread_mm.hypot(z_h_u);
        // A normal distribution as wide as the pitch's uniform one says no more than it.
        if sigma_mm >= p / 12f64.sqrt() {
            return uniform(p / 2.0);
        }
        PhaseUncertainty {
            sectors: k,
            spread_mm,
            error: PhaseError::Normal { sigma_mm },
            u_mm: sigma_mm,
            unknown: false,
        }
    }
}
