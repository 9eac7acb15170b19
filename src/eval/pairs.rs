//! Training pairs for the profile-correction MLP (training/profile_mlp.py reads them): each
//! measured bin's pitch of reconstructed profile ([`crate::pipeline::profile::pitch`]) beside the
//! answer: the simulator's true pitch and height, or a CMM's height.
//!
//! One JSON object per line. The true pitch is sampled on the part model at the thread's true
//! crest (the truth's helix, not the measured one: a CMM measures the part where it is) and
//! normalised as the input is (its own mean removed, in units of the nominal thread height), so
//! that the windows of [`pitch::window_slots`] read the true height off it.

use crate::domain::thread::ThreadForm;
use crate::pipeline::Inspection;
use crate::pipeline::profile::pitch::{self, PITCH_SAMPLES};
use crate::sim::Truth;
use serde::Serialize;

#[derive(Clone, Debug, Serialize)]
pub struct Pair {
    /// Where the pair came from (a case name or an inspection id).
    pub source: String,
    pub thread: u32,
    pub angle_deg: f64,
    /// The station's object pixel, mm (the benchmark's station classes split on it).
    pub object_pixel_mm: f64,
    /// The reconstructed pitch, normalised.
    pub input: Vec<f32>,
    /// The nominal thread height the samples are in units of, mm.
    pub scale_mm: f64,
    pub filled_share: f64,
    /// The crest window and the two root windows, as slot ranges `[start, end)`.
    pub windows: [[usize; 2]; 3],
    /// The weight of the root after the crest in the root level at the crest (the one before
    /// weighs 1 minus this): the roots are interpolated at the crest's z.
    pub root_weight_after: f64,
    /// The bin's own height fit (before the trimmed mean along the helix), mm.
    pub raw_height_mm: f64,
    /// The true pitch, normalised alike (simulated parts only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target: Option<Vec<f32>>,
    /// The true (or CMM) height of the bin, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target_height_mm: Option<f64>,
}

/// The slot ranges as JSON arrays.
pub fn windows(form: &ThreadForm) -> [[usize; 2]; 3] {
    pitch::window_slots(form).map(|r| [r.start, r.end])
}

/// The true pitch of thread `index` at `angle_deg` on the simulated part, normalised.
fn true_pitch(truth: &Truth, index: u32, angle_deg: f64) -> Vec<f32> {
    let part = &truth.part_model;
    let (before, after) = part.form.root_centres_mm();
    let crest_z = part.crest_z(index, angle_deg);
    let theta = angle_deg.to_radians();
    // Before the end face the thread continues on its root cone (as the truth's heights take it).
    let r: Vec<f64> = (0..PITCH_SAMPLES)
        .map(|k| crest_z + before + (after - before) * (k as f64 + 0.5) / PITCH_SAMPLES as f64)
        .map(|z| if z < 0.0 { part.root_cone_radius(z) } else { part.radius(z, theta) })
        .collect();
    let mean = r.iter().sum::<f64>() / PITCH_SAMPLES as f64;
    r.iter().map(|v| ((v - mean) / part.form.height_mm) as f32).collect()
}

/// Pairs of every measured bin of `inspection` (run with profile correction off) against a
/// simulated bundle's truth, or without answers when there is none.
pub fn pairs(
    source: &str,
    inspection: &Inspection,
    form: &ThreadForm,
    object_pixel_mm: f64,
    truth: Option<&Truth>,
) -> Vec<Pair> {
    let helix = &inspection.report.helix;
    let profiles = pitch::pitch_profiles(&inspection.map, form, helix, &inspection.threads);
    let windows = windows(form);
    let (before, after) = form.root_centres_mm();
    let root_weight_after = (0.0 - before) / (after - before);
    profiles
        .into_iter()
        .filter_map(|p| {
            let thread = &inspection.threads[p.thread];
            let bin = &thread.bins[p.bin];
            let raw_height_mm = bin.raw_height_mm?;
            let true_height = truth.and_then(|t| {
                let tt = t.threads.iter().find(|tt| tt.index == thread.index)?;
                let k = tt.height_mm.angles_deg.iter().position(|a| (a - bin.angle_deg).abs() < 1e-6)?;
                tt.height_mm.values[k]
            });
            // A simulated bin without a true height (beyond the inspected length, or chamfered
            // away) teaches nothing.
            if truth.is_some() && true_height.is_none() {
                return None;
            }
            Some(Pair {
                source: source.into(),
                thread: thread.index,
                angle_deg: bin.angle_deg,
                object_pixel_mm,
                input: p.samples,
                scale_mm: p.scale_mm,
                filled_share: p.filled_share,
                windows,
                root_weight_after,
                raw_height_mm,
                target: truth.map(|t| true_pitch(t, thread.index, bin.angle_deg)),
                target_height_mm: true_height,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::profile::pitch::pitch_height_mm;

    /// The true pitch's windows read the truth's height: the target and the height agree, so a
    /// model trained on the profile learns the height.
    #[test]
    fn the_true_pitch_reads_the_true_height() {
        let spec = crate::sim::presets::preset("bc-black-2").expect("preset");
        let truth = spec.truth(7);
        let form = &truth.part_model.form;
        let mut checked = 0;
        for t in truth.threads.iter().take(6) {
            for (k, h) in t.height_mm.values.iter().enumerate().step_by(45) {
                let Some(h) = h else { continue };
                let target = true_pitch(&truth, t.index, t.height_mm.angles_deg[k]);
                let read = pitch_height_mm(form, &target, form.height_mm);
                assert!((read - h).abs() < 0.02 * form.height_mm, "thread {} at {k}: {read} against {h}", t.index);
                checked += 1;
            }
        }
        assert!(checked >= 20, "{checked}");
    }
}
