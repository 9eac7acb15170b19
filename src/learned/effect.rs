//! What a profile-correction model is known to do to heights: measured against truth on renders it
//! was not trained on, by thread family and object pixel (its card's `effect`, written by
//! `scripts/mlp-effect` from `crestscan budget` runs; docs/models.md, "Choosing when it runs").
//! `auto` runs a model only where this says it helps, and a corrected height's uncertainty carries
//! the error the model is known to leave per micrometre it changes.

use crate::domain::thread::Family;
use serde::{Deserialize, Serialize};

/// A model's measured effect, as its card states it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Effect {
    /// How it was measured: the command that reproduces it.
    pub measured_by: String,
    pub entries: Vec<EffectEntry>,
}

/// The effect on one family of threads over one range of object pixels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct EffectEntry {
    /// The thread family measured: round or buttress.
    pub family: Family,
    /// The range of object pixels, mm: above the first, up to the second.
    pub object_pixel_mm: [f64; 2],
    /// Rendered cases measured.
    pub cases: usize,
    /// How many of them the model brought closer to truth.
    pub better_cases: usize,
    /// The median over the cases of the heights' RMS error without the model, µm.
    pub classical_rms_um: f64,
    /// The same with the model, µm.
    pub corrected_rms_um: f64,
    /// The corrected heights' RMS error per unit RMS change the model made, at the upper quartile
    /// of the cases (at least the largest where fewer than four): what a corrected height's
    /// uncertainty carries per micrometre of change.
    pub error_per_change: f64,
}

impl EffectEntry {
    /// Whether the model is known to help here: closer to truth on most cases and on the median.
    pub fn helps(&self) -> bool {
        2 * self.better_cases > self.cases && self.corrected_rms_um < self.classical_rms_um
    }

    fn covers(&self, family: Family, object_pixel_mm: f64) -> bool {
        let [lo, hi] = self.object_pixel_mm;
        self.family == family && object_pixel_mm > lo && object_pixel_mm <= hi
    }
}

impl Effect {
    /// The entry for a thread family at a station's object pixel, if one was measured.
    pub fn at(&self, family: Family, object_pixel_mm: f64) -> Option<&EffectEntry> {
        self.entries.iter().find(|e| e.covers(family, object_pixel_mm))
    }

    /// Why the card's effect cannot be used, if it cannot: ranges that are empty or not finite,
    /// ratios that are negative, more better cases than cases.
    pub fn check(&self) -> Result<(), String> {
        for (i, e) in self.entries.iter().enumerate() {
            let [lo, hi] = e.object_pixel_mm;
            let finite =
                [lo, hi, e.classical_rms_um, e.corrected_rms_um, e.error_per_change].iter().all(|v| v.is_finite());
            if !finite || lo < 0.0 || hi <= lo {
                return Err(format!(
                    "effect.entries[{i}]: object_pixel_mm must be [lo, hi] with 0 ≤ lo < hi, all finite"
                ));
            }
            if e.error_per_change < 0.0 || e.classical_rms_um < 0.0 || e.corrected_rms_um < 0.0 {
                return Err(format!("effect.entries[{i}]: RMS values and error_per_change must not be negative"));
            }
            if e.better_cases > e.cases || e.cases == 0 {
                return Err(format!("effect.entries[{i}]: better_cases must not exceed cases, and cases must be ≥ 1"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(family: Family, lo: f64, hi: f64, better: usize, classical: f64, corrected: f64) -> EffectEntry {
        EffectEntry {
            family,
            object_pixel_mm: [lo, hi],
            cases: 4,
            better_cases: better,
            classical_rms_um: classical,
            corrected_rms_um: corrected,
            error_per_change: 0.8,
        }
    }

    #[test]
    fn the_entry_is_found_by_family_and_pixel_and_helps_only_where_it_was_seen_to() {
        let effect = Effect {
            measured_by: "test".into(),
            entries: vec![
                entry(Family::Buttress, 0.0, 0.06, 1, 3.0, 12.0),
                entry(Family::Buttress, 0.06, 0.2, 4, 60.0, 25.0),
                // Better on the median, but on only two of four cases: not known to help.
                entry(Family::Round, 0.06, 0.2, 2, 60.0, 25.0),
            ],
        };
        assert!(effect.check().is_ok());
        assert!(!effect.at(Family::Buttress, 0.041).unwrap().helps());
        assert!(effect.at(Family::Buttress, 0.12).unwrap().helps());
        // The bound belongs to the lower range.
        assert_eq!(effect.at(Family::Buttress, 0.06).unwrap().object_pixel_mm, [0.0, 0.06]);
        assert!(!effect.at(Family::Round, 0.12).unwrap().helps());
        assert!(effect.at(Family::Round, 0.041).is_none(), "nothing measured there");
        let bad = Effect { measured_by: "x".into(), entries: vec![entry(Family::Round, 0.1, 0.05, 1, 1.0, 1.0)] };
        assert!(bad.check().unwrap_err().contains("entries[0]"));
    }
}
