//! One pitch of profile per thread and 1° bin, resampled to a fixed length: the input of the
//! seed's profile-correction MLP, and what a learned correction changes a height by.
//!
//! The pitch runs from the root centre before a crest to the root centre after it (exactly one
//! pitch: [`ThreadForm::root_centres_mm`]), in [`PITCH_SAMPLES`] equal slots along z. Each slot
//! holds the mean radius of the fused cells of the bin's columns that fall in it; empty slots are
//! filled linearly from their neighbours. Radii are given relative to the profile's own mean and
//! in units of the form's nominal thread height, so that every form and pipe size reads alike.

use super::*;

/// Samples of one pitch, as in the seed (the MLP's input width).
pub const PITCH_SAMPLES: usize = crate::learned::profile_mlp::SAMPLES;

/// Below this share of the pitch lying within one map row of data, a pitch gives no profile
/// (interpolation would make it).
const MIN_FILLED_SHARE: f64 = 0.5;

/// One pitch of profile, normalised: `(r − mean_mm) / scale_mm` per slot.
#[derive(Clone, Debug, PartialEq)]
pub struct PitchProfile {
    /// Index into the thread list (not the thread's number).
    pub thread: usize,
    /// Index into the thread's bins.
    pub bin: usize,
    pub samples: Vec<f32>,
    pub mean_mm: f64,
    pub scale_mm: f64,
    /// Share of the pitch within one map row of data (before interpolation).
    pub filled_share: f64,
}

/// Slot index ranges of the crest window and the two root windows (their halves inside the
/// pitch), as [`super::heights`] fits them.
pub fn window_slots(form: &ThreadForm) -> [std::ops::Range<usize>; 3] {
    let (crest_half, root_half) = form.window_half_widths_mm();
    let (before, after) = form.root_centres_mm();
    let span = after - before;
    let slot =
        |x: f64| (((x - before) / span) * PITCH_SAMPLES as f64).round().clamp(0.0, PITCH_SAMPLES as f64) as usize;
    [slot(-crest_half)..slot(crest_half), 0..slot(before + root_half), slot(after - root_half)..PITCH_SAMPLES]
}

/// Resamples one pitch from `(x_mm, r_mm)` samples (x relative to the crest centre), taken on a
/// map whose rows are `row_mm` apart; None where too little of the pitch lies within a row of
/// data. The share is of the pitch, not of slots: a coarse station's map has fewer rows per pitch
/// than there are slots, and every slot between two rows is then interpolation of the map's own.
pub fn resample(form: &ThreadForm, samples: &[(f64, f64)], row_mm: f64) -> Option<(Vec<f32>, f64, f64)> {
    let (before, after) = form.root_centres_mm();
    let span = after - before;
    let mut sum = [0.0f64; PITCH_SAMPLES];
    let mut count = [0u32; PITCH_SAMPLES];
    for &(x, r) in samples {
        let k = ((x - before) / span * PITCH_SAMPLES as f64).floor();
        if (0.0..PITCH_SAMPLES as f64).contains(&k) && r.is_finite() {
            sum[k as usize] += r;
            count[k as usize] += 1;
        }
    }
    let filled: Vec<usize> = (0..PITCH_SAMPLES).filter(|&k| count[k] > 0).collect();
    // Slots within a map row of a filled one.
    let reach = (row_mm / span * PITCH_SAMPLES as f64).ceil().max(0.0) as usize;
    let covered = (0..PITCH_SAMPLES)
        .filter(|&k| {
            let at = filled.partition_point(|&j| j < k);
            let near = |j: usize| j.abs_diff(k) <= reach;
            filled.get(at).is_some_and(|&j| near(j)) || (at > 0 && near(filled[at - 1]))
        })
        .count();
    let share = covered as f64 / PITCH_SAMPLES as f64;
    if filled.is_empty() || share < MIN_FILLED_SHARE {
        return None;
    }
    let value = |k: usize| sum[k] / count[k] as f64;
    let mut r = vec![0.0f64; PITCH_SAMPLES];
    let (first, last) = (filled[0], *filled.last().expect("not empty"));
    for k in 0..PITCH_SAMPLES {
        r[k] = if k <= first {
            value(first)
        } else if k >= last {
            value(last)
        } else if count[k] > 0 {
            value(k)
        } else {
            // The filled slots either side (filled is sorted).
            let after_at = filled.partition_point(|&j| j < k);
            let (a, b) = (filled[after_at - 1], filled[after_at]);
            value(a) + (value(b) - value(a)) * (k - a) as f64 / (b - a) as f64
        };
    }
    let mean = r.iter().sum::<f64>() / PITCH_SAMPLES as f64;
    let scale = form.height_mm;
    Some((r.iter().map(|v| ((v - mean) / scale) as f32).collect(), mean, share))
}

/// Every measured bin's pitch of profile (bins with a raw height), read from the fused map.
pub fn pitch_profiles(
    map: &UnrolledMap,
    form: &ThreadForm,
    helix: &Helix,
    threads: &[ThreadMeasure],
) -> Vec<PitchProfile> {
    let g = &map.grid;
    let p = helix.pitch_mm;
    let (before, after) = form.root_centres_mm();
    let jobs: Vec<(usize, usize)> = threads
        .iter()
        .enumerate()
        .flat_map(|(t, thread)| {
            thread.bins.iter().enumerate().filter(|(_, b)| b.raw_height_mm.is_some()).map(move |(k, _)| (t, k))
        })
        .collect();
    jobs.par_iter()
        .filter_map(|&(t, k)| {
            let bin = &threads[t].bins[k];
            let bin_index = (bin.angle_deg - 0.5).round().clamp(0.0, 359.0) as usize;
            let u_crest = (threads[t].index - 1) as f64 + helix.local_offset_mm(bin_index) / p;
            let (lo, hi) = (u_crest + before / p, u_crest + after / p);
            // A sample at u = hi falls past the last slot, which resample leaves out.
            let samples: Vec<(f64, f64)> = heights::samples_in_u(map, helix, g.bin_columns(bin_index), lo, hi)
                .into_iter()
                .map(|(u, r, _)| ((u - u_crest) * p, r))
                .collect();
            let (values, mean_mm, filled_share) = resample(form, &samples, g.dz_mm)?;
            Some(PitchProfile { thread: t, bin: k, samples: values, mean_mm, scale_mm: form.height_mm, filled_share })
        })
        .collect()
}

/// The height a pitch of profile reads, mm: its crest window's mean minus the two root windows'
/// means interpolated at the crest (as the height's roots are). Linear in the samples, so the
/// training code applies the same operator (training/profile_mlp.py, `height_operator`).
pub fn pitch_height_mm(form: &ThreadForm, samples: &[f32], scale_mm: f64) -> f64 {
    let [crest, root_before, root_after] = window_slots(form);
    let mean = |r: &std::ops::Range<usize>| {
        let n = r.len().max(1) as f64;
        r.clone().map(|k| samples[k] as f64).sum::<f64>() / n
    };
    let (before, after) = form.root_centres_mm();
    let (b, a) = (mean(&root_before), mean(&root_after));
    let root = b + (a - b) * (0.0 - before) / (after - before);
    scale_mm * (mean(&crest) - root)
}

/// Replaces every measured bin's own height (`raw_height_mm`) by the height its corrected pitch of
/// profile reads ([`pitch_height_mm`]), as the seed reads heights off the MLP's profile, then takes
/// the reported heights along the helix again. Bins whose pitch holds too little data
/// ([`resample`]) keep their fit. Returns how many bins the model corrected.
pub fn correct_heights(
    map: &UnrolledMap,
    form: &ThreadForm,
    helix: &Helix,
    threads: &mut [ThreadMeasure],
    options: &ProfileOptions,
    model: &crate::learned::Model,
) -> Result<usize, crate::learned::LearnedError> {
    let profiles = pitch_profiles(map, form, helix, threads);
    let input: Vec<f32> = profiles.iter().flat_map(|p| p.samples.iter().copied()).collect();
    let corrected = crate::learned::profile_mlp::correct(model, &input)?;
    for (p, out) in profiles.iter().zip(corrected.chunks_exact(PITCH_SAMPLES)) {
        let height = pitch_height_mm(form, out, p.scale_mm);
        let bin = &mut threads[p.thread].bins[p.bin];
        // A model that answers NaN for a pitch leaves the bin unmeasured rather than wrong.
        if bin.raw_height_mm.is_some() {
            if height.is_finite() {
                bin.raw_height_mm = Some(height);
            } else {
                bin.raw_height_mm = None;
                bin.unmeasured = Some(super::Unmeasured::ModelNotFinite);
            }
        }
    }
    smooth_along_helix(threads, options);
    Ok(profiles.len())
}

#[cfg(test)]
mod pitch_tests {
    use super::*;
    use crate::domain::thread::ConnectionTable;

    /// z of slot `k`'s centre relative to the crest centre, mm.
    fn slot_offset_mm(form: &ThreadForm, k: usize) -> f64 {
        let (before, after) = form.root_centres_mm();
        before + (after - before) * (k as f64 + 0.5) / PITCH_SAMPLES as f64
    }

    fn buttress() -> ThreadForm {
        let table = ConnectionTable::api5b();
        table
            .all()
            .iter()
            .find(|c| matches!(c.form().profile, ProfileShape::Trapezoid { .. }))
            .expect("a buttress")
            .form()
            .clone()
    }

    #[test]
    fn a_sparse_pitch_is_refused_and_gaps_are_interpolated() {
        let form = buttress();
        let (before, after) = form.root_centres_mm();
        let slot_mm = (after - before) / PITCH_SAMPLES as f64;
        // Data over the first third of the pitch only: under half, no profile.
        let third: Vec<(f64, f64)> = (0..PITCH_SAMPLES / 3).map(|k| (slot_offset_mm(&form, k), 1.0)).collect();
        assert!(resample(&form, &third, slot_mm).is_none());
        // Every eighth slot on a map of slot-sized rows: most slots are interpolation, no profile.
        let sparse: Vec<(f64, f64)> = (0..PITCH_SAMPLES).step_by(8).map(|k| (slot_offset_mm(&form, k), 1.0)).collect();
        assert!(resample(&form, &sparse, slot_mm).is_none());
        // The same samples on a map whose rows are eight slots apart: every row there is, a profile.
        assert!(resample(&form, &sparse, 8.0 * slot_mm).is_some());
        // A line r = x over every second slot: the missing slots lie on the same line.
        let line: Vec<(f64, f64)> =
            (0..PITCH_SAMPLES).step_by(2).map(|k| (slot_offset_mm(&form, k), slot_offset_mm(&form, k))).collect();
        let (values, mean, share) = resample(&form, &line, slot_mm).expect("half the slots");
        assert!((share - 1.0).abs() < 1e-9, "{share}");
        let slope = (after - before) / PITCH_SAMPLES as f64 / form.height_mm;
        for k in 1..PITCH_SAMPLES - 2 {
            assert!(((values[k + 1] - values[k]) as f64 - slope).abs() < 1e-5, "slot {k}");
        }
        assert!(mean.is_finite());
    }

    #[test]
    fn a_raised_crest_window_raises_the_height_by_as_much() {
        let form = buttress();
        let flat = vec![0.0f32; PITCH_SAMPLES];
        assert_eq!(pitch_height_mm(&form, &flat, form.height_mm), 0.0);
        let mut raised = flat.clone();
        let [crest, ..] = window_slots(&form);
        for k in crest {
            raised[k] = 0.01;
        }
        let height = pitch_height_mm(&form, &raised, form.height_mm);
        assert!((height - 0.01 * form.height_mm).abs() < 1e-6, "{height}");
        // The same offset everywhere changes no height.
        let offset: Vec<f32> = raised.iter().map(|v| v + 0.02).collect();
        assert!((pitch_height_mm(&form, &offset, form.height_mm) - height).abs() < 1e-6);
    }
}
