//! The frames' own noise, and the pre-filter the focus measure takes where it is high.
//!
//! The focus measure is a squared 4-neighbour Laplacian, whose gain is highest at the Nyquist
//! frequency: for white pixel noise its output power is 20 σ², while the part's texture (grain a
//! pixel and a half across or coarser, as any texture the optics resolve) passes at a small
//! fraction of that. Where the sensor is noisy (a small full well, a dim part) the noise floor then
//! hides the texture's focus peak, and the peaks that remain belong to the strong edges. A light
//! Gaussian pre-filter removes most of the noise's power above the texture's band and keeps the
//! texture's. Where the noise is low (the standard station) it would only widen the focus curve,
//! so it runs only above a noise level, read from the view's first frame, and only at object
//! pixels up to 0.08 mm: at coarser ones it made heights worse on every station suite case it
//! touched (docs/notebook/accuracy.md, "Stations: noisy frames"). The noise itself is read on every
//! view: the report states it and the measured envelope bounds it.

/// The standard deviation of a frame's pixel noise relative to its mean brightness (Immerkær,
/// "Fast noise variance estimation", 1996: the mean absolute response to the difference of two
/// Laplacians, which cancels any locally linear brightness, scaled to a Gaussian's σ). Image
/// structure finer than that (texture in focus, edges) adds a little; a defocused frame, as the
/// first of a stack mostly is, reads nearly the noise alone. None for frames under 3×3 or black.
pub fn relative_noise(gray: &[f32], w: usize, h: usize) -> Option<f64> {
    if w < 3 || h < 3 || gray.len() < w * h {
        return None;
    }
    let (mut sum_abs, mut sum) = (0f64, 0f64);
    for y in 1..h - 1 {
        let (up, mid, down) = (&gray[(y - 1) * w..y * w], &gray[y * w..(y + 1) * w], &gray[(y + 1) * w..(y + 2) * w]);
        let mut row_abs = 0f32;
        for x in 1..w - 1 {
            let r = (up[x - 1] + up[x + 1] + down[x - 1] + down[x + 1])
                - 2.0 * (up[x] + down[x] + mid[x - 1] + mid[x + 1])
                + 4.0 * mid[x];
            row_abs += r.abs();
        }
        sum_abs += row_abs as f64;
        sum += mid[1..w - 1].iter().map(|&v| v as f64).sum::<f64>();
    }
    let n = ((w - 2) * (h - 2)) as f64;
    let mean = sum / n;
    if mean <= 0.0 {
        return None;
    }
    let sigma = (std::f64::consts::FRAC_PI_2).sqrt() / 6.0 * sum_abs / n;
    Some(sigma / mean)
}

/// A separable Gaussian of standard deviation `sigma_px` (taps to 3σ, normalised).
pub fn gaussian_taps(sigma_px: f64) -> Vec<f32> {
    let radius = (3.0 * sigma_px).ceil().max(1.0) as usize;
    let taps: Vec<f64> =
        (0..=2 * radius).map(|i| (-(i as f64 - radius as f64).powi(2) / (2.0 * sigma_px * sigma_px)).exp()).collect();
    let total: f64 = taps.iter().sum();
    taps.iter().map(|t| (t / total) as f32).collect()
}

/// `gray` (w × h) blurred by the separable `taps` into `out`, through `scratch`; edges clamped
/// (the frame's border pixels repeat), so a flat frame stays flat.
pub fn blur(gray: &[f32], w: usize, h: usize, taps: &[f32], scratch: &mut Vec<f32>, out: &mut Vec<f32>) {
    let radius = taps.len() / 2;
    scratch.resize(w * h, 0.0);
    out.resize(w * h, 0.0);
    if w == 0 || h == 0 {
        return;
    }
    // Along rows: each output the taps over its clamped neighbours.
    for (src, dst) in gray[..w * h].chunks_exact(w).zip(scratch.chunks_exact_mut(w)) {
        for (x, o) in dst.iter_mut().enumerate() {
            let mut acc = 0f32;
            for (i, &t) in taps.iter().enumerate() {
                acc += t * src[(x + i).saturating_sub(radius).min(w - 1)];
            }
            *o = acc;
        }
    }
    // Along columns: whole rows at a time, so that the loop vectorises.
    for (y, dst) in out.chunks_exact_mut(w).enumerate() {
        dst.fill(0.0);
        for (i, &t) in taps.iter().enumerate() {
            let from = (y + i).saturating_sub(radius).min(h - 1);
            for (o, &v) in dst.iter_mut().zip(&scratch[from * w..(from + 1) * w]) {
                *o += t * v;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    fn noisy(w: usize, h: usize, sigma: f32, seed: u64, base: impl Fn(usize, usize) -> f32) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let normal = Normal::new(0.0f32, sigma).unwrap();
        (0..w * h).map(|i| base(i % w, i / w) + normal.sample(&mut rng)).collect()
    }

    #[test]
    fn reads_the_noise_on_flat_and_sloped_frames() {
        for (sigma, base) in [(0.01f32, 0.5f32), (0.04, 0.5), (0.02, 0.25)] {
            let flat = noisy(300, 200, sigma, 1, |_, _| base);
            let ramp =
                noisy(300, 200, sigma, 2, |x, y| base + 0.3 * (x as f32 / 300.0 - 0.5) + 0.1 * (y as f32 / 200.0));
            for frame in [flat, ramp] {
                let got = relative_noise(&frame, 300, 200).unwrap();
                let mean = frame.iter().map(|&v| v as f64).sum::<f64>() / frame.len() as f64;
                let want = sigma as f64 / mean;
                assert!((got / want - 1.0).abs() < 0.05, "read {got}, noise {want}");
            }
        }
    }

    #[test]
    fn a_smooth_texture_without_noise_reads_far_below_a_noisy_one() {
        // Texture a few pixels across, as the optics resolve it: little of it passes the mask.
        let texture = |x: usize, y: usize| 0.5 + 0.05 * ((x as f32 * 0.9).sin() * (y as f32 * 0.7).cos());
        let clean = noisy(300, 200, 0.0, 3, texture);
        let with_noise = noisy(300, 200, 0.01, 3, texture);
        let (clean, with_noise) =
            (relative_noise(&clean, 300, 200).unwrap(), relative_noise(&with_noise, 300, 200).unwrap());
        assert!(clean < 0.004, "texture alone read as {clean}");
        assert!((with_noise / 0.02 - 1.0).abs() < 0.15, "texture and 2% noise read as {with_noise}");
    }

    #[test]
    fn tiny_or_black_frames_have_no_reading() {
        assert_eq!(relative_noise(&[0.5; 4], 2, 2), None);
        assert_eq!(relative_noise(&[0.0; 25], 5, 5), None);
    }

    #[test]
    fn the_blur_keeps_a_flat_frame_and_the_mean_and_cuts_pixel_noise() {
        let (w, h) = (120, 80);
        let taps = gaussian_taps(0.7);
        assert!((taps.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let (mut scratch, mut out) = (Vec::new(), Vec::new());
        blur(&vec![0.3; w * h], w, h, &taps, &mut scratch, &mut out);
        assert!(out.iter().all(|&v| (v - 0.3).abs() < 1e-6));
        let frame = noisy(w, h, 0.05, 4, |_, _| 0.5);
        blur(&frame, w, h, &taps, &mut scratch, &mut out);
        let mean = |f: &[f32]| f.iter().sum::<f32>() / f.len() as f32;
        assert!((mean(&out) - mean(&frame)).abs() < 1e-3);
        // A Gaussian of σ 0.7 px keeps about 1/(4π σ²) = 16% of white noise's variance.
        let before = relative_noise(&frame, w, h).unwrap();
        let after = relative_noise(&out, w, h).unwrap();
        assert!(after < 0.25 * before, "noise read {before} before and {after} after");
    }
}
