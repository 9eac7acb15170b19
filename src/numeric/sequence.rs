//! Filters along a gappy sequence (one value or none per bin, e.g. the 1° bins along the helix):
//! each window is centred on its bin and used only where every value in it was measured.

/// Each bin's value replaced by the trimmed mean of the 2·`half` + 1 bins centred on it along the
/// helix (a quarter of them, rounded down but at least one, dropped at each end: the median of
/// three), where all were measured, else over the widest centred window that was. Unmeasured bins
/// stay unmeasured. As in [`median_of_five`], the sequence is a line (the helix), not a circle.
pub fn trimmed_mean(values: &[Option<f64>], half: usize) -> Vec<Option<f64>> {
    trimmed_mean_counted(values, half).into_iter().map(|v| v.map(|(mean, _)| mean)).collect()
}

/// [`trimmed_mean`], with the number of values each mean kept (1 where a bin keeps its own).
pub fn trimmed_mean_counted(values: &[Option<f64>], half: usize) -> Vec<Option<(f64, usize)>> {
    let mut window = Vec::with_capacity(2 * half + 1);
    (0..values.len())
        .map(|i| {
            let own = values[i]?;
            if !widest_whole_window(values, i, half, 1, &mut window) {
                return Some((own, 1));
            }
            let trim = (window.len() / 4).max(1);
            let kept = &window[trim..window.len() - trim];
            Some((kept.iter().sum::<f64>() / kept.len() as f64, kept.len()))
        })
        .collect()
}

/// Each measured value's local noise: the robust scale of the differences between neighbouring
/// measured values within `half` of it, over √2 (the difference of two independent errors has
/// twice their variance; a slow trend along the sequence cancels in a difference). None where
/// fewer than `min_pairs` neighbouring pairs lie within reach.
pub fn local_noise(values: &[Option<f64>], half: usize, min_pairs: usize) -> Vec<Option<f64>> {
    let diffs: Vec<Option<f64>> = values.windows(2).map(|w| Some(w[1]? - w[0]?)).collect();
    let mut window = Vec::with_capacity(2 * half + 1);
    (0..values.len())
        .map(|i| {
            values[i]?;
            let (lo, hi) = (i.saturating_sub(half), (i + half).min(diffs.len()));
            window.clear();
            window.extend(diffs.get(lo..hi).unwrap_or(&[]).iter().flatten().map(|d| d.abs()));
            if window.len() < min_pairs.max(1) {
                return None;
            }
            crate::numeric::stats::median(&mut window).map(|m| 1.4826 * m / std::f64::consts::SQRT_2)
        })
        .collect()
}

/// Each bin's value (a crest's deficit below the cone) replaced by the median of the five bins
/// around it along the helix (three, else its own, at the ends of the measured runs), where all
/// were measured. One bin's fit can be thrown by a few bad samples (a specular pixel, a flank
/// leaking into a window); a real change (a black crest) spans many bins and keeps its edges,
/// which a median does not move. The sequence is the helix, not the circle: across 360° → 0° a
/// crest continues as the next thread.
pub fn median_of_five(heights: &[Option<f64>]) -> Vec<Option<f64>> {
    let mut window = Vec::with_capacity(5);
    (0..heights.len())
        .map(|i| {
            let own = heights[i]?;
            Some(if widest_whole_window(heights, i, 2, 1, &mut window) { window[window.len() / 2] } else { own })
        })
        .collect()
}

/// The median of the 2·`half` + 1 bins centred on each bin along the helix; None wherever one of
/// them is unmeasured or the window runs off either end of the helix.
pub fn centred_median(values: &[Option<f64>], half: usize) -> Vec<Option<f64>> {
    let mut window = Vec::with_capacity(2 * half + 1);
    (0..values.len()).map(|i| widest_whole_window(values, i, half, half, &mut window).then(|| window[half])).collect()
}

/// Fills `window` with the 2h + 1 values centred on bin `i`, sorted, for the widest half width h
/// from `widest` down to `narrowest` whose window lies within the sequence and was measured
/// throughout; false (and `window` unspecified) when none does.
fn widest_whole_window(
    values: &[Option<f64>],
    i: usize,
    widest: usize,
    narrowest: usize,
    window: &mut Vec<f64>,
) -> bool {
    for h in (narrowest..=widest).rev() {
        if i < h || i + h >= values.len() {
            continue;
        }
        window.clear();
        window.extend(values[i - h..=i + h].iter().map_while(|v| *v));
        if window.len() == 2 * h + 1 {
            window.sort_by(f64::total_cmp);
            return true;
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn local_noise_reads_white_noise_and_ignores_a_trend() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        // Gaussian noise of σ = 0.01 (sum of twelve uniforms) on a steep trend.
        let values: Vec<Option<f64>> = (0..2000)
            .map(|i| {
                let g: f64 = (0..12).map(|_| rng.random_range(0.0..1.0)).sum::<f64>() - 6.0;
                Some(0.5 + 1e-3 * i as f64 + 0.01 * g)
            })
            .collect();
        let noise = local_noise(&values, 200, 20);
        for n in noise.iter().step_by(97) {
            let n = n.unwrap();
            assert!((n - 0.01).abs() < 0.0015, "{n}");
        }
        let mut gappy = values.clone();
        for v in gappy.iter_mut().skip(1).step_by(2) {
            *v = None;
        }
        // No neighbouring pair is measured: no estimate, rather than a wrong one.
        assert!(local_noise(&gappy, 200, 20).iter().all(Option::is_none));
        let counted = trimmed_mean_counted(&values, 5);
        assert_eq!(counted[100].unwrap().1, 7);
        assert_eq!(counted[0].unwrap().1, 1);
    }

    #[test]
    fn the_median_of_five_removes_spikes_and_keeps_steps() {
        let mut h: Vec<Option<f64>> = (0..16).map(|i| Some(if i < 8 { 1.0 } else { 0.8 })).collect();
        h[3] = Some(1.3);
        h[4] = Some(0.7);
        h[12] = None;
        let m = median_of_five(&h);
        assert_eq!((m[3], m[4]), (Some(1.0), Some(1.0)), "two adjacent spikes removed");
        assert_eq!((m[7], m[8]), (Some(1.0), Some(0.8)), "step kept in place");
        assert_eq!(m[12], None, "gaps stay gaps");
        assert_eq!((m[11], m[13]), (Some(0.8), Some(0.8)));
        assert_eq!((m[0], m[15]), (Some(1.0), Some(0.8)), "ends are not wrapped");
    }

    #[test]
    fn the_trimmed_mean_drops_spikes_averages_scatter_and_keeps_a_ramp() {
        let smooth = |v: &[Option<f64>], half| trimmed_mean(v, half);
        // A spike in a level run is trimmed away entirely.
        let mut level: Vec<Option<f64>> = vec![Some(1.0); 30];
        level[15] = Some(1.5);
        assert!(smooth(&level, 5).iter().all(|h| (h.unwrap() - 1.0).abs() < 1e-12), "{:?}", smooth(&level, 5));
        // Alternating ±10 µm scatter: each bin's own value is 10 µm off, the mean of the kept middle
        // is within 10/7 µm (7 of 11 kept: at most one sign in excess).
        let scatter: Vec<Option<f64>> = (0..40).map(|i| Some(1.0 + if i % 2 == 0 { 0.010 } else { -0.010 })).collect();
        let out = smooth(&scatter, 5);
        for (i, h) in out.iter().enumerate().take(35).skip(5) {
            assert!((h.unwrap() - 1.0).abs() <= 0.010 / 7.0 + 1e-12, "bin {i}: {h:?}");
        }
        // A ramp (a vanishing thread's height) is kept where the window is whole: its values are
        // symmetric about the centre.
        let ramp: Vec<Option<f64>> = (0..40).map(|i| Some(1.5 - 0.005 * i as f64)).collect();
        for (i, (h, r)) in smooth(&ramp, 5).iter().zip(&ramp).enumerate() {
            assert!((h.unwrap() - r.unwrap()).abs() < 1e-12, "bin {i}");
        }
        // Gaps stay gaps; next to one (and at the ends, which do not wrap) the window narrows to
        // what is measured on both sides: bins 20 and 22 beside the gap at 21 keep their own
        // values, bin 1 takes the median of bins 0–2.
        let mut gappy = scatter.clone();
        gappy[21] = None;
        let out = smooth(&gappy, 5);
        assert_eq!(out[21], None);
        assert_eq!((out[20], out[22]), (gappy[20], gappy[22]));
        assert_eq!(out[0], gappy[0], "the first bin has no bin before it");
        assert_eq!(out[1], Some(1.0 + 0.010), "three bins: the median");
        // Half width 0 reports each bin's own value.
        assert_eq!(smooth(&scatter, 0), scatter);
    }

    #[test]
    fn centred_medians_need_the_whole_window() {
        let mut v: Vec<Option<f64>> = (0..10).map(|i| Some(i as f64)).collect();
        v[6] = None;
        let m = centred_median(&v, 2);
        assert_eq!(&m[..], &[None, None, Some(2.0), Some(3.0), None, None, None, None, None, None]);
    }
}
