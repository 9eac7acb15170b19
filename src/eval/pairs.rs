//! Training pairs for the profile-correction MLP (training/profile_mlp.py reads them): each
//! measured bin's pitch of reconstructed profile ([`crate::pipeline::profile::pitch`]) beside the
//! answer: the simulator's true pitch and height, or a CMM's height.
//!
//! One JSON object per line. The true pitch is sampled on the part model at the thread's true
//! crest (the truth's helix, not the measured one: a CMM measures the part where it is) and
//! normalised as the input is (its own mean removed, in units of the nominal thread height), so
//! that the windows of [`pitch::window_slots`] read the true height off it.

use crate::domain::thread::ThreadForm;
use crate::eval::cmm::CmmMeasurements;
use crate::pipeline::Inspection;
use crate::pipeline::profile::pitch::{self, PITCH_SAMPLES};
use crate::sim::Truth;
use serde::{Deserialize, Serialize};

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
    /// The true pitch, normalised alike (simulated parts only; a CMM gives heights).
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

/// One measured bin's pitch of profile, as an inspection keeps it for later pairing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileBin {
    pub thread: u32,
    pub angle_deg: f64,
    pub raw_height_mm: f64,
    pub filled_share: f64,
    #[serde(skip)]
    pub input: Vec<f32>,
}

/// Every measured bin's pitch of profile of one inspection, with what pairing needs of the form:
/// what the service keeps with a result (`pitch-profiles`) so that CMM data uploaded later makes
/// training pairs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileSet {
    pub version: u32,
    pub object_pixel_mm: f64,
    pub scale_mm: f64,
    pub windows: [[usize; 2]; 3],
    pub root_weight_after: f64,
    pub bins: Vec<ProfileBin>,
}

#[derive(Debug, thiserror::Error)]
#[error("stored pitch profiles unreadable: {0}")]
pub struct ProfileSetError(String);

impl ProfileSet {
    /// The pitches of every bin `inspection` measured (with profile correction off or on: the
    /// pitches are read off the map, before any correction).
    pub fn of(inspection: &Inspection, form: &ThreadForm, object_pixel_mm: f64) -> Self {
        let helix = &inspection.report.helix;
        let profiles = pitch::pitch_profiles(&inspection.map, form, helix, &inspection.threads);
        let (before, after) = form.root_centres_mm();
        let bins = profiles
            .into_iter()
            .filter_map(|p| {
                let thread = &inspection.threads[p.thread];
                let bin = &thread.bins[p.bin];
                Some(ProfileBin {
                    thread: thread.index,
                    angle_deg: bin.angle_deg,
                    raw_height_mm: bin.raw_height_mm?,
                    filled_share: p.filled_share,
                    input: p.samples,
                })
            })
            .collect();
        Self {
            version: 1,
            object_pixel_mm,
            scale_mm: form.height_mm,
            windows: windows(form),
            root_weight_after: (0.0 - before) / (after - before),
            bins,
        }
    }

    /// A JSON header line, then every bin's samples as little-endian f32: 1 kB a bin (2.5 MB for
    /// the standard station's ring), under half the samples' JSON text.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = serde_json::to_vec(self).expect("serialises");
        out.push(b'\n');
        out.reserve(self.bins.len() * PITCH_SAMPLES * 4);
        for b in &self.bins {
            for v in &b.input {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, ProfileSetError> {
        let newline = bytes.iter().position(|&b| b == b'\n').ok_or_else(|| ProfileSetError("no header".into()))?;
        let mut set: ProfileSet =
            serde_json::from_slice(&bytes[..newline]).map_err(|e| ProfileSetError(e.to_string()))?;
        let body = &bytes[newline + 1..];
        if set.version != 1 || body.len() != set.bins.len() * PITCH_SAMPLES * 4 {
            return Err(ProfileSetError(format!("version {} with {} bytes of samples", set.version, body.len())));
        }
        for (b, chunk) in set.bins.iter_mut().zip(body.chunks_exact(PITCH_SAMPLES * 4)) {
            b.input = chunk.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        }
        Ok(set)
    }

    fn pair(&self, source: &str, b: &ProfileBin, target: Option<Vec<f32>>, target_height_mm: Option<f64>) -> Pair {
        Pair {
            source: source.into(),
            thread: b.thread,
            angle_deg: b.angle_deg,
            object_pixel_mm: self.object_pixel_mm,
            input: b.input.clone(),
            scale_mm: self.scale_mm,
            filled_share: b.filled_share,
            windows: self.windows,
            root_weight_after: self.root_weight_after,
            raw_height_mm: b.raw_height_mm,
            target,
            target_height_mm,
        }
    }

    /// Pairs against a simulated bundle's truth: the true pitch and height of every bin that has
    /// a true height (one beyond the inspected length, or chamfered away, teaches nothing).
    pub fn with_truth(&self, source: &str, truth: &Truth) -> Vec<Pair> {
        self.bins
            .iter()
            .filter_map(|b| {
                let tt = truth.threads.iter().find(|tt| tt.index == b.thread)?;
                let k = tt.height_mm.angles_deg.iter().position(|a| (a - b.angle_deg).abs() < 1e-6)?;
                let h = tt.height_mm.values[k]?;
                Some(self.pair(source, b, Some(true_pitch(truth, b.thread, b.angle_deg)), Some(h)))
            })
            .collect()
    }

    /// Pairs against a CMM's heights: every bin with a CMM point of its thread in its 1° bin (the
    /// mean of several); points without an angle (a thread's mean) pair with no bin.
    pub fn with_cmm(&self, source: &str, cmm: &CmmMeasurements) -> Vec<Pair> {
        self.bins
            .iter()
            .filter_map(|b| {
                let heights: Vec<f64> = cmm
                    .points
                    .iter()
                    .filter(|p| p.thread == b.thread)
                    .filter(|p| p.angle_deg.is_some_and(|a| (a - (b.angle_deg - 0.5)).rem_euclid(360.0) < 1.0))
                    .map(|p| p.height_mm)
                    .collect();
                (!heights.is_empty())
                    .then(|| self.pair(source, b, None, Some(heights.iter().sum::<f64>() / heights.len() as f64)))
            })
            .collect()
    }

    /// Pairs without answers (a bundle with neither truth nor CMM data: the inputs only).
    pub fn unanswered(&self, source: &str) -> Vec<Pair> {
        self.bins.iter().map(|b| self.pair(source, b, None, None)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::profile::pitch::pitch_height_mm;

    /// The true pitch's windows read the truth's height: the target and the height agree, so a
    /// model trained on the profile learns the height.
    #[test]
    fn stored_profiles_read_back_and_pair_with_cmm_points_by_bin() {
        let bin = |thread, angle_deg, v: f32| ProfileBin {
            thread,
            angle_deg,
            raw_height_mm: 1.5,
            filled_share: 0.9,
            input: (0..PITCH_SAMPLES).map(|k| v + k as f32 * 1e-3).collect(),
        };
        let set = ProfileSet {
            version: 1,
            object_pixel_mm: 0.04,
            scale_mm: 1.5748,
            windows: [[97, 169], [0, 36], [220, 256]],
            root_weight_after: 0.5,
            bins: vec![bin(2, 10.5, 0.1), bin(2, 11.5, 0.2), bin(3, 10.5, -0.3)],
        };
        let back = ProfileSet::decode(&set.encode()).expect("reads back");
        assert_eq!(back, set);
        assert!(ProfileSet::decode(&set.encode()[..100]).is_err());
        let cmm = CmmMeasurements {
            instrument: None,
            measured_at: None,
            points: vec![
                crate::eval::cmm::CmmPoint { thread: 2, angle_deg: Some(10.2), height_mm: 1.50, uncertainty_mm: None },
                crate::eval::cmm::CmmPoint { thread: 2, angle_deg: Some(10.8), height_mm: 1.52, uncertainty_mm: None },
                crate::eval::cmm::CmmPoint { thread: 2, angle_deg: None, height_mm: 1.4, uncertainty_mm: None },
                crate::eval::cmm::CmmPoint { thread: 4, angle_deg: Some(10.5), height_mm: 1.4, uncertainty_mm: None },
            ],
            uncertainty_mm: None,
        };
        let pairs = set.with_cmm("x", &cmm);
        assert_eq!(pairs.len(), 1, "one bin has CMM points: thread 2 at 10–11°");
        assert_eq!((pairs[0].thread, pairs[0].angle_deg), (2, 10.5));
        assert!((pairs[0].target_height_mm.unwrap() - 1.51).abs() < 1e-12);
        assert!(pairs[0].target.is_none());
        assert_eq!(pairs[0].input, set.bins[0].input);
    }

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
