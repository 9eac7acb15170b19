//! One pitch of profile per thread and 1° bin, resampled to a fixed length: the input of the
//! seed's profile-correction MLP, and what a learned correction changes a height by.
//!
//! The pitch runs from the root centre before a crest to the root centre after it (exactly one
//! pitch: [`ThreadForm::root_centres_mm`]), in [`PITCH_SAMPLES`] equal slots along z. Each slot
//! holds the mean radius of the fused cells of the bin's columns that fall in it; empty slots are
//! filled linearly from their neighbours. Radii are given relative to the profile's own mean and
//! in units of the form's nominal thread height, so that every form and pipe size reads alike.

use super::*;

/// Samples of one pitch, as in the seed.
pub const PITCH_SAMPLES: usize = 256;

/// Below this share of slots holding data, a pitch gives no profile (interpolation would make it).
const MIN_FILLED_SHARE: f64 = 0.25;

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
    /// Share of slots that held data before interpolation.
    pub filled_share: f64,
}

/// Slot index ranges of the crest window and the two root windows (their halves inside the
/// pitch), as [`super::heights`] fits them.
pub fn window_slots(form: &ThreadForm) -> [std::ops::Range<usize>; 3] {
    let (crest_half, root_half) = heights::windows(form);
    let (before, after) = form.root_centres_mm();
    let span = after - before;
    let slot =
        |x: f64| (((x - before) / span) * PITCH_SAMPLES as f64).round().clamp(0.0, PITCH_SAMPLES as f64) as usize;
    [slot(-crest_half)..slot(crest_half), 0..slot(before + root_half), slot(after - root_half)..PITCH_SAMPLES]
}

/// Resamples one pitch from `(x_mm, r_mm)` samples (x relative to the crest centre); None where too
/// few slots hold data.
pub fn resample(form: &ThreadForm, samples: &[(f64, f64)]) -> Option<(Vec<f32>, f64, f64)> {
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
    let share = filled.len() as f64 / PITCH_SAMPLES as f64;
    if share < MIN_FILLED_SHARE {
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
            let u_crest = (threads[t].index - 1) as f64;
            let (lo, hi) = (u_crest + before / p, u_crest + after / p);
            let bin_index = (bin.angle_deg - 0.5).round().clamp(0.0, 359.0) as usize;
            // A sample at u = hi falls past the last slot, which resample leaves out.
            let samples: Vec<(f64, f64)> = heights::samples_in_u(map, helix, g.bin_columns(bin_index), lo, hi)
                .into_iter()
                .map(|(u, r, _)| ((u - u_crest) * p, r))
                .collect();
            let (values, mean_mm, filled_share) = resample(form, &samples)?;
            Some(PitchProfile { thread: t, bin: k, samples: values, mean_mm, scale_mm: form.height_mm, filled_share })
        })
        .collect()
}

/// What a corrected profile changes the height by, mm: the change of the crest window's mean
/// minus the change of the two root windows' means interpolated at the crest (as the height's
/// roots are).
pub fn height_change_mm(form: &ThreadForm, input: &[f32], corrected: &[f32], scale_mm: f64) -> f64 {
    let [crest, root_before, root_after] = window_slots(form);
    let mean_change = |r: &std::ops::Range<usize>| {
        let n = r.len().max(1) as f64;
        r.clone().map(|k| (corrected[k] - input[k]) as f64).sum::<f64>() / n
    };
    let (before, after) = form.root_centres_mm();
    let (b, a) = (mean_change(&root_before), mean_change(&root_after));
    let root = b + (a - b) * (0.0 - before) / (after - before);
    scale_mm * (mean_change(&crest) - root)
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
        // Every fifth slot holds data: under a quarter, no profile.
        let sparse: Vec<(f64, f64)> = (0..PITCH_SAMPLES).step_by(5).map(|k| (slot_offset_mm(&form, k), 1.0)).collect();
        assert!(resample(&form, &sparse).is_none());
        // A line r = x over every second slot: the missing slots lie on the same line.
        let line: Vec<(f64, f64)> =
            (0..PITCH_SAMPLES).step_by(2).map(|k| (slot_offset_mm(&form, k), slot_offset_mm(&form, k))).collect();
        let (values, mean, share) = resample(&form, &line).expect("half the slots");
        assert!((share - 0.5).abs() < 1e-9);
        let slope = (after - before) / PITCH_SAMPLES as f64 / form.height_mm;
        for k in 1..PITCH_SAMPLES - 2 {
            assert!(((values[k + 1] - values[k]) as f64 - slope).abs() < 1e-5, "slot {k}");
        }
        assert!(mean.is_finite());
    }

    #[test]
    fn a_raised_crest_window_raises_the_height_by_as_much() {
        let form = buttress();
        let input = vec![0.0f32; PITCH_SAMPLES];
        let mut corrected = input.clone();
        let [crest, ..] = window_slots(&form);
        for k in crest {
            corrected[k] = 0.01;
        }
        let change = height_change_mm(&form, &input, &corrected, form.height_mm);
        assert!((change - 0.01 * form.height_mm).abs() < 1e-6, "{change}");
        // The same change everywhere is an offset: no change of height.
        let offset = vec![0.02f32; PITCH_SAMPLES];
        assert!(height_change_mm(&form, &input, &offset, form.height_mm).abs() < 1e-9);
    }
}
