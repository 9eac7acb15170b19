//! Per-thread heights per 1° bin: crest and root radii fitted over windows along z with the form's
//! known section, crest minus root, then a trimmed mean along the helix.

use super::*;

/// Half width of the strip around the crest centre line whose brightness decides black crests.
pub(super) const CREST_LINE_HALF_MM: f64 = 0.15;

/// Half width along z of the window a crest's radius is fitted over (the crest stage models how a
/// mill surface that cuts part of that window shows in the fitted radius).
pub fn crest_window_half_mm(form: &ThreadForm) -> f64 {
    form.window_half_widths_mm().0
}

/// Nominal curvatures (c of r = c·x²) of a rounded form's crest and root arcs (∓1/2ρ); None for
/// a flat-crested form.
pub(super) fn nominal_curvatures(form: &ThreadForm) -> Option<(f64, f64)> {
    form.arc_radii_mm().map(|(crest, root)| (-0.5 / crest, 0.5 / root))
}

/// The part of a crest's or root's section about its centre that is fitted once for the whole
/// part rather than per bin: flat for a buttress, r = c·x² for a round thread.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Section {
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
pub(super) fn fit_curvature(pts: &[(f64, f64)]) -> Option<f64> {
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
pub(super) fn shared_section(windows: &[&[(f64, f64)]], nominal_c_per_mm: f64) -> Section {
    let mut c: Vec<f64> = windows.iter().filter_map(|w| fit_curvature(w)).filter(|c| c.is_finite()).collect();
    let measured = if c.len() < 30 { None } else { median(&mut c) };
    Section::Parabola { c_per_mm: measured.unwrap_or(nominal_c_per_mm) }
}

/// Value at x = 0 of a fit r = a + b·x + section(x) robust to a minority of samples from another
/// surface. The section's shape is known from the form, so only its height and tilt are fitted: a
/// free curvature term would more than double the variance of the height at the centre. None
/// unless samples lie on both sides of the centre (`half` is the window's half width): an edge of
/// the data would make it an extrapolation.
///
/// Near a flank a window holds, besides its own surface, pixels that took the other surface's
/// depth (a thread height away) and focus peaks on noise: at coarse stations a third of the
/// samples. One pass of rejection at 3 MAD about a least-squares line does not reject them there
/// (the line and the MAD are pulled by what is to be rejected), so the level is first taken as
/// the mean of the half of the samples nearest their median, then of the half nearest that level
/// until the level holds (least trimmed squares by concentration steps, on the level alone: a
/// half can sit at one end of the window, where a tilt would be an extrapolation). The window's
/// own surface is then what lies within `separation_mm` of that level (half the thread height:
/// the other surface is a whole height away), and the height is a least-squares line through it
/// with one pass of rejection at 3 MAD about the line. Kept about the level alone instead, within
/// 3 of its robust scales, a window that is a little tilted (a round crest read off its centre,
/// the taper) lost samples at one end, and the line through the rest carried the section's misfit
/// to the centre (docs/notebook/accuracy.md).
pub(super) fn fit_at_centre(
    samples: &[(f64, f64)],
    section: Section,
    half: f64,
    separation_mm: f64,
) -> Result<f64, WindowMiss> {
    if samples.is_empty() {
        return Err(WindowMiss::Empty);
    }
    if samples.len() < 6 {
        return Err(WindowMiss::TooFew);
    }
    let (lo, hi) = samples.iter().fold((f64::MAX, f64::MIN), |(l, h), s| (l.min(s.0), h.max(s.0)));
    if lo > -0.5 * half || hi < 0.5 * half {
        return Err(WindowMiss::OneSided);
    }
    let levelled: Vec<(f64, f64)> = samples.iter().map(|&(x, r)| (x, r - section.offset_mm(x))).collect();
    let n = levelled.len();
    let h = n.div_ceil(2).max(6).min(n);
    let mut abs: Vec<f64> = levelled.iter().map(|s| s.1).collect();
    let mut level = median(&mut abs).expect("at least six samples");
    for _ in 0..8 {
        // The h-th smallest distance from the level bounds the half nearest it.
        abs.clear();
        abs.extend(levelled.iter().map(|s| (s.1 - level).abs()));
        let bound = *abs.select_nth_unstable_by(h - 1, f64::total_cmp).1;
        let (sum, count) = levelled
            .iter()
            .filter(|s| (s.1 - level).abs() <= bound)
            .fold((0.0, 0usize), |(sum, count), s| (sum + s.1, count + 1));
        let next = sum / count as f64;
        let settled = next == level;
        level = next;
        if settled {
            break;
        }
    }
    let own: Vec<(f64, f64)> = levelled.iter().copied().filter(|s| (s.1 - level).abs() <= separation_mm).collect();
    // The half nearest the level holds at least six samples, so what is near it is never empty.
    let (a, b) = fit_line_checked(&own).ok_or(WindowMiss::OneSided)?;
    abs.clear();
    abs.extend(own.iter().map(|&(x, r)| (r - a - b * x).abs()));
    let mad = median(&mut abs).expect("at least six samples").max(1e-6);
    let kept: Vec<(f64, f64)> =
        own.iter().copied().filter(|&(x, r)| (r - a - b * x).abs() <= 3.0 * 1.4826 * mad).collect();
    let (lo, hi) = kept.iter().fold((f64::MAX, f64::MIN), |(l, h), s| (l.min(s.0), h.max(s.0)));
    if lo > -0.5 * half || hi < 0.5 * half {
        return Err(WindowMiss::OneSided); // what is kept lies to one side: the centre would be extrapolated
    }
    fit_line_checked(&kept).map(|(a, _)| a).ok_or(WindowMiss::OneSided)
}

/// Why [`fit_at_centre`] gave no level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WindowMiss {
    /// No sample at all.
    Empty,
    /// Fewer than six.
    TooFew,
    /// The samples, or those the window's own surface kept, lie to one side of its centre (or
    /// do not spread along it).
    OneSided,
}

/// [`fit_line`] through at least six samples that spread in x.
pub(super) fn fit_line_checked(pts: &[(f64, f64)]) -> Option<(f64, f64)> {
    let (x, r): (Vec<f64>, Vec<f64>) = pts.iter().copied().unzip();
    let spread = x.iter().fold(f64::MAX, |m, &v| m.min(v)) < x.iter().fold(f64::MIN, |m, &v| m.max(v));
    (pts.len() >= 6 && spread).then(|| fit_line(&x, &r))
}

/// The fused cells of `columns` whose thread coordinate u = (z − z_h)/p − θ/360 (crest of thread i
/// at u = i − 1) lies in [lo, hi], as (u, r, gray), column by column, row by row: per column the
/// rows are found from the range's z span (a row's slack either side), then each checked on u.
pub(super) fn samples_in_u(
    map: &UnrolledMap,
    helix: &Helix,
    columns: std::ops::Range<usize>,
    lo: f64,
    hi: f64,
) -> Vec<(f64, f64, f32)> {
    let g = &map.grid;
    let p = helix.pitch_mm;
    let mut samples: Vec<(f64, f64, f32)> = Vec::new();
    for it in columns {
        let theta = g.theta_deg_at(it);
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
    samples
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
pub(super) const SURVEY_BIN_STEP: usize = 6;

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

pub(super) fn measure_threads_every(
    map: &UnrolledMap,
    form: &ThreadForm,
    helix: &Helix,
    options: &ProfileOptions,
    bin_step: usize,
) -> Vec<ThreadMeasure> {
    let g = &map.grid;
    let p = helix.pitch_mm;
    let (crest_half, root_half) = form.window_half_widths_mm();
    let (before, after) = form.root_centres_mm();
    let z_max = g.z0_mm + g.nz as f64 * g.dz_mm;
    // Threads whose phase lies inside the grid. The pitch is the form's, validated positive and
    // held by the station check to several object pixels, so the cap never binds on a bundle the
    // reader accepted; it keeps this loop bounded whatever it is given.
    const MAX_THREADS: u32 = 10_000;
    let mut threads: Vec<ThreadMeasure> = Vec::new();
    let mut index = 1u32;
    while index <= MAX_THREADS && helix.z_h_mm + p * (index - 1) as f64 <= z_max {
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
        let mut samples = samples_in_u(map, helix, columns, centre_u - half_mm / p, centre_u + half_mm / p);
        samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        samples.into_iter().map(|(u, r, g)| ((u - centre_u) * p, r, g)).collect()
    };
    // Bins are gathered in parallel and kept in bin order, then thread order.
    let pending: Vec<Pending> = (0..360)
        .into_par_iter()
        .step_by(bin_step.max(1))
        .map(|bin| {
            let centre_deg = bin as f64 + 0.5;
            let columns = g.bin_columns(bin);
            threads
                .iter()
                .enumerate()
                .map(|(t, thread)| {
                    let u_crest = (thread.index - 1) as f64;
                    // The crest is where the helix puts it; the data show it where the bin's own
                    // generatrices read it, and the windows go there.
                    let crest_z = helix.z_h_mm + p * (u_crest + centre_deg / 360.0);
                    let u_crest = u_crest + helix.local_offset_mm(bin) / p;
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
    // A window's own surface lies within half the thread height of its level; the other, a height away.
    let separation = 0.5 * form.height_mm;
    let measured: Vec<BinMeasure> = pending
        .par_iter()
        .map(|w| {
            let crest_r = fit_at_centre(&w.crest, crest_section, crest_half, separation);
            let rb = fit_at_centre(&w.root_before, root_section, root_half, separation);
            let ra = fit_at_centre(&w.root_after, root_section, root_half, separation);
            // A root whose window reaches past the end face is not on the part (or is the chamfer):
            // there is no adjacent root to measure from. Nor is one whose window reaches into the
            // map's first cell on the part: that cell holds the end face's edge, whose silhouette
            // pulls the fused radius off the root, and the first bins would read high.
            let root_on_part = w.crest_z_mm + before - root_half > g.dz_mm;
            let height = match (crest_r, rb, ra) {
                _ if !root_on_part => Err(Unmeasured::RootOffPart),
                (Err(miss), _, _) => Err(Unmeasured::of_window(miss, true)),
                (_, Err(miss), _) | (_, _, Err(miss)) => Err(Unmeasured::of_window(miss, false)),
                (Ok(c), Ok(b), Ok(a)) => Ok(over_roots(c, b, a, before, after)),
            };
            BinMeasure {
                angle_deg: w.angle_deg,
                crest_z_mm: w.crest_z_mm,
                height_mm: height.ok(),
                crest_radius_mm: crest_r.ok(),
                crest_gray: w.crest_gray,
                raw_height_mm: height.ok(),
                kept_bins: usize::from(height.is_ok()),
                uncertainty_mm: None,
                unmeasured: height.err(),
            }
        })
        .collect();
    for (w, bin) in pending.iter().zip(measured) {
        threads[w.thread].bins.push(bin);
    }
    smooth_along_helix(&mut threads, options);
    threads
}

/// Each bin's reported height from the bins' own fits (`raw_height_mm`): the trimmed mean along
/// the helix ([`ProfileOptions::height_window_half_bins`]).
pub fn smooth_along_helix(threads: &mut [ThreadMeasure], options: &ProfileOptions) {
    // Along the helix, thread i's last bin (359.5°) is followed by thread i + 1's first (0.5°).
    let helix_order: Vec<Option<f64>> = threads.iter().flat_map(|t| t.bins.iter().map(|b| b.raw_height_mm)).collect();
    let filtered = trimmed_mean_counted(&helix_order, options.height_window_half_bins);
    for (bin, h) in threads.iter_mut().flat_map(|t| t.bins.iter_mut()).zip(filtered) {
        bin.height_mm = h.map(|(mean, _)| mean);
        bin.kept_bins = h.map_or(0, |(_, kept)| kept);
    }
}

/// A bin's height on the nominal form, measured as [`measure_threads_every`] measures it but by
/// least squares, with its windows `offset_mm` along z from the crest and roots they are meant
/// for. [`fit_at_centre`]'s robust steps would trim noiseless samples by the section's small
/// misfit (a circle's quartic) and move the level by a micrometre at any shift; on measured data
/// the noise keeps every sample of the window's own surface, as least squares does, and where a
/// window reaches a flank least squares counts it whole, which errs on the cautious side.
fn height_off_centre(form: &ThreadForm, offset_mm: f64) -> Option<f64> {
    let kernel = form.kernel();
    let (crest_half, root_half) = form.window_half_widths_mm();
    let (before, after) = form.root_centres_mm();
    let (crest_section, root_section) = match nominal_curvatures(form) {
        None => (Section::Flat, Section::Flat),
        Some((crest_c, root_c)) => (Section::Parabola { c_per_mm: crest_c }, Section::Parabola { c_per_mm: root_c }),
    };
    // Samples 5 µm apart, far finer than any station's, so that the windows' content decides.
    let fit = |centre: f64, half: f64, section: Section| -> Option<f64> {
        let n = (2.0 * half / 0.005).ceil() as usize;
        let levelled: Vec<(f64, f64)> = (0..=n)
            .map(|i| -half + 2.0 * half * i as f64 / n as f64)
            .map(|x| (x, kernel.height_at(centre + x + offset_mm) - section.offset_mm(x)))
            .collect();
        fit_line_checked(&levelled).map(|(a, _)| a)
    };
    let crest = fit(0.0, crest_half, crest_section)?;
    let rb = fit(before, root_half, root_section)?;
    let ra = fit(after, root_half, root_section)?;
    Some(over_roots(crest, rb, ra, before, after))
}

/// The crest's radius over the root line between the roots before and after it (their radii and
/// their centres' offsets along z from the crest's): the contract's height.
fn over_roots(crest_mm: f64, before_mm: f64, after_mm: f64, before_z_mm: f64, after_z_mm: f64) -> f64 {
    crest_mm - (before_mm + (after_mm - before_mm) * (0.0 - before_z_mm) / (after_z_mm - before_z_mm))
}

/// The RMS change of a bin's height when its windows sit off their crest and roots by a phase
/// error distributed as `error`, on the nominal form, as the profile stage fits it. On a flat crest
/// it is nil until the windows reach a flank; on a round thread's arcs it grows with δ² from the
/// start; at half a pitch the crest window sits on a root, and the height reads negative.
pub fn phase_height_rms_mm(form: &ThreadForm, error: PhaseError) -> f64 {
    let Some(at_centre) = height_off_centre(form, 0.0) else { return form.height_mm };
    // A window that finds no fit reads nothing at all: its change is taken as the whole height.
    let change = |offset: f64| height_off_centre(form, offset).map_or(form.height_mm, |h| h - at_centre);
    // Quadrature nodes (offset, weight): the midpoints of 120 equal steps over a uniform
    // distribution, or a normal's density at 0.1 σ steps out to 4 σ.
    let nodes: Vec<(f64, f64)> = match error {
        PhaseError::Uniform { half_width_mm } if half_width_mm > 0.0 => {
            (0..120).map(|i| (half_width_mm * (2.0 * (i as f64 + 0.5) / 120.0 - 1.0), 1.0)).collect()
        }
        PhaseError::Normal { sigma_mm } if sigma_mm > 0.0 => {
            (0..81).map(|i| -4.0 + 0.1 * i as f64).map(|z| (z * sigma_mm, (-0.5 * z * z).exp())).collect()
        }
        _ => return 0.0,
    };
    let (sum_sq, weight) =
        nodes.iter().fold((0.0, 0.0), |(s, w), &(offset, weight)| (s + weight * change(offset).powi(2), w + weight));
    (sum_sq / weight).sqrt()
}
