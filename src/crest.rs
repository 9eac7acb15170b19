//! Black-crest detection, photometric half: a crest showing mill scale is far darker than machined
//! steel under the coaxial light. Each thread's crest brightness per bin is compared with the
//! median crest brightness of the part (most crests are machined). The geometric half (a crest
//! below nominal − tolerance, which also catches polished black crests) is applied by the rule
//! engine from the heights, which this stage hands over median-filtered over three bins. The end
//! chamfer is machined: crests within 1.5 pitches of the end face
//! that look machined are flagged as chamfer, never as black.

use crate::profile::ThreadMeasure;
use crate::rules::{CrestBin, ThreadObservation};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CrestOptions {
    /// A crest darker than this fraction of the median crest brightness shows mill scale.
    pub dark_fraction: f32,
}

impl Default for CrestOptions {
    fn default() -> Self {
        Self { dark_fraction: 0.45 }
    }
}

/// The height the geometric test sees at bin k: the median of the bin and its two neighbours, so a
/// single noisy bin cannot make a black crest, while any real one (a crest left at the mill radius
/// spans degrees) still shows. None unless at least two of the three were measured.
fn detection_height(bins: &[crate::profile::BinMeasure], k: usize) -> Option<f64> {
    let mut values: Vec<f64> =
        [k.checked_sub(1), Some(k), Some(k + 1)].into_iter().flatten().filter_map(|i| bins.get(i)?.height_mm).collect();
    if values.len() < 2 || bins[k].height_mm.is_none() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    Some(if values.len() == 3 { values[1] } else { 0.5 * (values[0] + values[1]) })
}

/// The rule engine's input for each thread, and the reference (machined) crest brightness.
pub fn observations(
    threads: &[ThreadMeasure],
    lc_mm: f64,
    pitch_mm: f64,
    options: &CrestOptions,
) -> (Vec<ThreadObservation>, f32) {
    let mut grays: Vec<f32> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.crest_gray)).collect();
    grays.sort_by(f32::total_cmp);
    let reference = grays.get(grays.len() / 2).copied().unwrap_or(0.0);
    let dark_below = options.dark_fraction * reference;
    let observations = threads
        .iter()
        .map(|t| {
            let dz_per_deg = pitch_mm / 360.0;
            let mut arcs = Vec::new();
            let mut bins = Vec::with_capacity(t.bins.len());
            for (k, b) in t.bins.iter().enumerate() {
                let start = b.angle_deg - 0.5;
                let dark = b.crest_gray.is_some_and(|g| g < dark_below);
                let z_start = b.crest_z_mm - 0.5 * dz_per_deg;
                if dark && z_start <= lc_mm {
                    let end = (start + 1.0).min(start + (lc_mm - z_start) / dz_per_deg);
                    arcs.push([start, end]);
                }
                bins.push(CrestBin {
                    angle_deg: start,
                    width_deg: 1.0,
                    z_mm: b.crest_z_mm,
                    height_mm: detection_height(&t.bins, k),
                    chamfer: !dark && b.crest_z_mm < 1.5 * pitch_mm,
                });
            }
            ThreadObservation { index: t.index, black_crest_arcs_deg: crate::rules::union_arcs(arcs), bins }
        })
        .collect();
    (observations, reference)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::profile::BinMeasure;

    #[test]
    fn dark_crests_within_lc_become_arcs_clipped_at_lc() {
        let bins = (0..360)
            .map(|k| BinMeasure {
                angle_deg: k as f64 + 0.5,
                crest_z_mm: 30.0 + 5.08 * (k as f64 + 0.5) / 360.0,
                height_mm: Some(1.5),
                crest_radius_mm: Some(57.0),
                crest_gray: Some(if (100..200).contains(&k) { 0.05 } else { 0.5 }),
            })
            .collect();
        let threads = vec![ThreadMeasure { index: 6, bins }];
        // Lc at z = 31.0 → θ = (31 − 30) / 5.08 · 360 = 70.9°: no dark crest within Lc.
        let (obs, reference) = observations(&threads, 31.0, 5.08, &CrestOptions::default());
        assert_eq!(reference, 0.5);
        assert!(obs[0].black_crest_arcs_deg.is_empty());
        // Lc at z = 32.0 → θ = 141.7°: the dark arc runs 100° to 141.7°.
        let (obs, _) = observations(&threads, 32.0, 5.08, &CrestOptions::default());
        let arc = obs[0].black_crest_arcs_deg[0];
        assert_eq!(arc[0], 100.0);
        assert!((arc[1] - 2.0 / 5.08 * 360.0).abs() < 1e-9, "{arc:?}");
    }
}
