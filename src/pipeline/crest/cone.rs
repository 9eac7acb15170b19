//! The machined crest cone (r = a + b·z + c·cos θ + d·sin θ), fitted one-sidedly to every crest,
//! and the runs of crests standing below it (hysteresis between an onset and an extent threshold).

use super::*;

/// The cone's basis at (z, θ): its radius there is this dotted with (a, b, c, d).
pub(super) fn cone_basis(z_mm: f64, theta_deg: f64) -> Vector4<f64> {
    let (sin, cos) = theta_deg.to_radians().sin_cos();
    Vector4::new(1.0, z_mm, cos, sin)
}

/// Least-squares cone through (z, θ°, r), trimmed one-sidedly from an initial guess at the nominal
/// slope. None with fewer than 20 crests.
pub(super) fn fit_cone(crests: &[(f64, f64, f64)], nominal_slope: f64) -> Option<(Vector4<f64>, usize)> {
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
pub(super) fn thresholds(smoothed: &[Option<f64>], options: &CrestOptions) -> (f64, f64, f64) {
    // Most crests are machined: their deficits scatter about zero, the black ones sit far out.
    let scatter_um = 1e3 * robust_scale(smoothed.iter().flatten().copied()).unwrap_or(0.0);
    let extent_um = options.mill_extent_um.max(1.5 * scatter_um);
    let onset_um = (options.mill_onset_um.max(4.0 * scatter_um) + options.onset_shift_um).max(extent_um);
    (onset_um, extent_um, scatter_um)
}

/// Marks runs along the helix: a bin whose deficit reaches `onset` starts a run, which extends in
/// both directions over bins whose deficit stays at or above `extent` (a gap ends it).
pub(super) fn mill_runs(smoothed: &[Option<f64>], onset_mm: f64, extent_mm: f64) -> Vec<bool> {
    let above = |i: usize, t: f64| smoothed[i].is_some_and(|d| d >= t);
    let seeds: Vec<bool> = (0..smoothed.len()).map(|i| above(i, onset_mm)).collect();
    grow_runs(&seeds, |i| above(i, extent_mm), 0)
}

/// Removes runs without a dark bin that are shorter than `min_bins` 1° bins.
pub(super) fn drop_short_geometric_runs(runs: &mut [bool], dark: &[bool], min_bins: usize) {
    for span in run_spans(runs) {
        if span.len() < min_bins && !dark[span.clone()].iter().any(|&d| d) {
            runs[span].fill(false);
        }
    }
}
