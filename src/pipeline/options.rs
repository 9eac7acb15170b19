//! Every stage's options in one stored shape (jobs store them; unknown keys are refused).

use crate::domain::rules::ArcRule;
use crate::pipeline::crest::CrestOptions;
use crate::pipeline::depth::DepthOptions;
use crate::pipeline::mesh::MeshOptions;
use crate::pipeline::profile::ProfileOptions;
use crate::pipeline::register::RegisterOptions;
use crate::pipeline::uncertainty::UncertaintyOptions;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PipelineOptions {
    pub depth: DepthOptions,
    pub crest: CrestOptions,
    pub register: RegisterOptions,
    pub mesh: MeshOptions,
    /// How heights are reported (options stored before this existed load with the default).
    #[serde(default)]
    pub profile: ProfileOptions,
    /// How the heights' uncertainty is combined (options stored before it existed load with the
    /// default).
    #[serde(default)]
    pub uncertainty: UncertaintyOptions,
    pub arc_rule: ArcRule,
    /// Fused-map cell size in object pixels, at most: see [`PipelineOptions::cell_mm`].
    pub cell_px: f64,
    /// Take the ring's axial offset from the end face's silhouette when the views show it.
    #[serde(default = "yes")]
    pub anchor_end_face: bool,
    /// Drop fused cells more than a thread height from their bin's mean line ([`super::gate`]).
    #[serde(default = "yes")]
    pub gate_implausible: bool,
}

fn yes() -> bool {
    true
}

impl Default for PipelineOptions {
    fn default() -> Self {
        Self {
            depth: DepthOptions::default(),
            crest: CrestOptions::default(),
            register: RegisterOptions::default(),
            mesh: MeshOptions::default(),
            profile: ProfileOptions::default(),
            uncertainty: UncertaintyOptions::default(),
            arc_rule: ArcRule::PerThread,
            cell_px: 1.5,
            anchor_end_face: true,
            gate_implausible: true,
        }
    }
}

/// Rows of the fused map a crest's window spans at the least ([`PipelineOptions::cell_mm`]): 4
/// (a row in each quarter) left a third of coarse-survey's round bins unmeasured, 5 a tenth.
pub const ROWS_PER_CREST_WINDOW: f64 = 5.0;

impl PipelineOptions {
    /// The fused map's cell, mm: `cell_px` object pixels, or less where that would give a crest's
    /// window fewer than [`ROWS_PER_CREST_WINDOW`] rows along z (never under one pixel). The
    /// window's fit needs samples in its outer quarters on both sides, and with a round thread's
    /// narrow crest arc at coarse pixels the 1.5-pixel rows left five bins of six without them
    /// (coarse-survey's round part: 16% of bins measured, 90% at one pixel; docs/notebook/accuracy.md,
    /// "The error budget").
    pub fn cell_mm(&self, object_pixel_mm: f64, form: &crate::domain::thread::ThreadForm) -> f64 {
        let window_mm = 2.0 * form.window_half_widths_mm().0;
        let wanted_mm = window_mm / ROWS_PER_CREST_WINDOW;
        (self.cell_px * object_pixel_mm).min(wanted_mm.max(object_pixel_mm))
    }

    /// The models' names, when given, are names (domain::text caps them at 64 characters), whatever
    /// the method: a name is stored with the options even where the run does not use it.
    pub fn check_model_names(&self) -> Result<(), crate::learned::LearnedError> {
        use crate::learned::{ModelRole, check_name};
        if let Some(name) = &self.depth.model {
            check_name(ModelRole::Depth, name)?;
        }
        if let Some(name) = &self.profile.correction_model {
            check_name(ModelRole::ProfileCorrection, name)?;
        }
        Ok(())
    }

    /// The learned models these options ask for, loaded (and ONNX Runtime with them): what the
    /// service checks at submission, so that a missing model is refused then rather than failing
    /// the job. Nothing is asked of a classical run.
    pub fn check_learned(&self, models: &crate::learned::Models) -> Result<(), crate::learned::LearnedError> {
        // `auto` may want the model at the bundle's station: it must exist (a name is checked);
        // the runtime's absence is said in the report instead.
        if self.profile.correction != crate::pipeline::profile::Correction::Off {
            models.get(crate::learned::ModelRole::ProfileCorrection, self.profile.correction_model.as_deref())?;
        }
        if self.profile.correction == crate::pipeline::profile::Correction::On {
            crate::learned::runtime()?;
        }
        if self.depth.method == crate::pipeline::depth::DepthMethod::Cnn {
            models.get(crate::learned::ModelRole::Depth, self.depth.model.as_deref())?;
            crate::learned::runtime()?;
        }
        Ok(())
    }
}

/// The documented range of one numeric option, by its dotted path in the stored shape.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OptionRange {
    pub field: &'static str,
    pub min: f64,
    pub max: f64,
    /// Whole numbers only (the option is a count or a size in pixels).
    pub integer: bool,
}

const fn range(field: &'static str, min: f64, max: f64) -> OptionRange {
    OptionRange { field, min, max, integer: false }
}

const fn count(field: &'static str, min: f64, max: f64) -> OptionRange {
    OptionRange { field, min, max, integer: true }
}

/// Every numeric option's range (a test checks that none is missing and every default is inside).
/// The bounds keep each stage's work and memory within a small multiple of the defaults' (a
/// fused-map cell under one object pixel only multiplies cells; a focus box past 20 px or a search
/// past 10° / 5 mm is no station's), and keep fractions and thresholds meaningful.
pub const RANGES: &[OptionRange] = &[
    count("depth.window_radius_px", 1.0, 20.0),
    count("depth.flat_window_radius_px", 1.0, 20.0),
    range("depth.min_peak_ratio", 1.0, 100.0),
    range("depth.peak_fraction", 0.05, 0.95),
    count("depth.row_step", 1.0, 8.0),
    count("depth.edge_window_radius_px", 0.0, 10.0),
    range("depth.speckle_min_windows", 0.0, 100.0),
    range("depth.prefilter_sigma_px", 0.0, 4.0),
    range("depth.prefilter_min_noise", 0.0, 1.0),
    range("depth.prefilter_max_pixel_mm", 0.0, 1.0),
    range("crest.dark_fraction", 0.0, 1.0),
    range("crest.dark_sigmas", 0.0, 50.0),
    range("crest.dark_run_sigmas", 0.0, 50.0),
    range("crest.dark_extent_sigmas", 0.0, 50.0),
    range("crest.min_gray_scatter", 0.0, 0.5),
    range("crest.mill_onset_um", 0.0, 1000.0),
    range("crest.mill_extent_um", 0.0, 1000.0),
    range("crest.min_geometric_arc_deg", 0.0, 360.0),
    range("register.max_angle_deg", 0.0, 10.0),
    range("register.max_axial_mm", 0.0, 5.0),
    range("register.min_ncc", 0.0, 1.0),
    count("register.min_overlap_cells", 1.0, 10_000_000.0),
    range("register.max_rival_ratio", 0.0, 1.0),
    count("mesh.max_vertices", 1000.0, 20_000_000.0),
    range("mesh.feature_mm", 0.0, 10.0),
    count("profile.height_window_half_bins", 0.0, 90.0),
    range("uncertainty.method_px", 0.0, 10.0),
    range("uncertainty.coverage_factor", 1.0, 5.0),
    count("uncertainty.noise_half_bins", 1.0, 180.0),
    range("uncertainty.encoder_axial_bound_mm", 0.0, 10.0),
    range("cell_px", 1.0, 10.0),
];

/// An option outside its documented range.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("pipeline.{field}: {value} is outside {min}..={max}{}", if *.integer { " (a whole number)" } else { "" })]
pub struct OptionOutOfRange {
    pub field: &'static str,
    pub value: f64,
    pub min: f64,
    pub max: f64,
    pub integer: bool,
}

impl crate::problem::ErrorCode for OptionOutOfRange {
    fn code(&self) -> crate::problem::Code {
        crate::problem::Code::OptionOutOfRange
    }
    fn culprit(&self) -> Option<String> {
        Some(format!("pipeline.{}", self.field))
    }
}

/// The numeric leaf at a dotted path of a serialised options value.
fn leaf<'a>(value: &'a serde_json::Value, field: &str) -> Option<&'a serde_json::Value> {
    field.split('.').try_fold(value, |v, key| v.get(key))
}

impl PipelineOptions {
    /// Checks every numeric option against [`RANGES`]; the first one outside is named.
    pub fn check_ranges(&self) -> Result<(), OptionOutOfRange> {
        let value = serde_json::to_value(self).expect("options serialise");
        for r in RANGES {
            // A NaN serialises as null: it is out of every range.
            let v = leaf(&value, r.field).and_then(serde_json::Value::as_f64).unwrap_or(f64::NAN);
            let whole = !r.integer || v.fract() == 0.0;
            if !(v >= r.min && v <= r.max && whole) {
                return Err(OptionOutOfRange { field: r.field, value: v, min: r.min, max: r.max, integer: r.integer });
            }
        }
        Ok(())
    }

    /// These options with `overrides` written over them, object by object (the shape `POST
    /// /v1/inspections` takes under `pipeline`; keys it leaves out keep their values).
    pub fn overridden_by(&self, overrides: serde_json::Value) -> Result<Self, serde_json::Error> {
        // A key the options do not have is refused with its path, as the service refuses it: a
        // misspelt or retired option would otherwise change nothing, silently.
        fn merge(base: &mut serde_json::Value, overrides: serde_json::Value, path: &str) -> Result<(), String> {
            match (base, overrides) {
                (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
                    for (k, v) in o {
                        let here = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                        let Some(slot) = b.get_mut(&k) else { return Err(format!("{here}: unknown option")) };
                        merge(slot, v, &here)?;
                    }
                    Ok(())
                }
                (b, o) => {
                    *b = o;
                    Ok(())
                }
            }
        }
        let mut merged = serde_json::to_value(self)?;
        merge(&mut merged, overrides, "").map_err(<serde_json::Error as serde::de::Error>::custom)?;
        serde_json::from_value(merged)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_option_the_pipeline_does_not_have_is_refused_by_its_path() {
        let options = PipelineOptions::default();
        let retired = serde_json::json!({"profile": {"correction_min_pixel_mm": 0.0}});
        let err = options.overridden_by(retired).unwrap_err().to_string();
        assert!(err.contains("profile.correction_min_pixel_mm: unknown option"), "{err}");
        let set = options.overridden_by(serde_json::json!({"profile": {"correction": "off"}})).unwrap();
        assert_eq!(set.profile.correction, crate::pipeline::profile::Correction::Off);
    }

    #[test]
    fn the_fused_cell_gives_a_round_crest_s_window_five_rows_at_coarse_pixels_only() {
        let table = crate::domain::thread::ConnectionTable::api5b();
        let (buttress, round) = (table.get("BC 4-1/2").unwrap().form(), table.get("LC 4-1/2").unwrap().form());
        let options = PipelineOptions::default();
        // The standard station's 0.041 mm pixels: 1.5 pixels for both forms.
        assert_eq!(options.cell_mm(0.041, buttress), 1.5 * 0.041);
        assert_eq!(options.cell_mm(0.041, round), 1.5 * 0.041);
        // coarse-survey's 0.12 mm: the buttress crest window (1.4 mm) keeps 1.5 pixels; the round
        // crest arc's (0.53 mm) would hold under three rows, so the cell goes to one pixel (a fifth
        // of the window is 0.106 mm, under a pixel).
        assert_eq!(options.cell_mm(0.12, buttress), 1.5 * 0.12);
        assert_eq!(options.cell_mm(0.12, round), 0.12);
        // Between the two, a fifth of the window.
        let fifth = 2.0 * round.window_half_widths_mm().0 / 5.0;
        assert!((options.cell_mm(0.08, round) - fifth).abs() < 1e-12 && fifth < 1.5 * 0.08 && fifth > 0.08);
    }

    /// Every numeric leaf of the stored shape, by dotted path.
    fn numeric_leaves(value: &serde_json::Value, prefix: &str, out: &mut Vec<String>) {
        match value {
            serde_json::Value::Object(map) => {
                for (k, v) in map {
                    let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                    numeric_leaves(v, &path, out);
                }
            }
            serde_json::Value::Number(_) => out.push(prefix.to_string()),
            _ => {}
        }
    }

    #[test]
    fn every_numeric_option_has_a_range_and_its_default_is_inside() {
        let mut leaves = Vec::new();
        numeric_leaves(&serde_json::to_value(PipelineOptions::default()).unwrap(), "", &mut leaves);
        let mut ranged: Vec<String> = RANGES.iter().map(|r| r.field.to_string()).collect();
        leaves.sort();
        ranged.sort();
        assert_eq!(leaves, ranged, "RANGES must list exactly the numeric options");
        PipelineOptions::default().check_ranges().unwrap();
    }

    #[test]
    fn an_option_outside_its_range_is_named() {
        let tiny_cells = PipelineOptions { cell_px: 0.01, ..Default::default() };
        let e = tiny_cells.check_ranges().unwrap_err();
        assert_eq!((e.field, e.value), ("cell_px", 0.01));
        assert!(e.to_string().starts_with("pipeline.cell_px: 0.01 is outside 1..=10"), "{e}");
        let mut no_vertices = PipelineOptions::default();
        no_vertices.mesh.max_vertices = 0;
        assert_eq!(no_vertices.check_ranges().unwrap_err().field, "mesh.max_vertices");
        let mut nan = PipelineOptions::default();
        nan.register.min_ncc = f64::NAN;
        assert_eq!(nan.check_ranges().unwrap_err().field, "register.min_ncc");
        let mut edge = PipelineOptions::default();
        edge.register.min_ncc = 1.0;
        edge.cell_px = 10.0;
        edge.check_ranges().unwrap();
    }

    /// Jobs store their options; those stored before the profile options existed still load.
    #[test]
    fn options_stored_before_the_profile_options_existed_load_with_their_default() {
        let mut stored = serde_json::to_value(PipelineOptions::default()).unwrap();
        stored.as_object_mut().unwrap().remove("profile");
        let options: PipelineOptions = serde_json::from_value(stored).unwrap();
        assert_eq!(options.profile, ProfileOptions::default());
        assert_eq!(options.profile.height_window_half_bins, 5);
    }
}
