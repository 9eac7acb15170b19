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
    /// Fused-map cell size in object pixels.
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

impl PipelineOptions {
    /// These options with `overrides` written over them, object by object (the shape `POST
    /// /v1/inspections` takes under `pipeline`; keys it leaves out keep their values).
    pub fn overridden_by(&self, overrides: serde_json::Value) -> Result<Self, serde_json::Error> {
        fn merge(base: &mut serde_json::Value, overrides: serde_json::Value) {
            match (base, overrides) {
                (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
                    for (k, v) in o {
                        merge(b.entry(k).or_insert(serde_json::Value::Null), v);
                    }
                }
                (b, o) => *b = o,
            }
        }
        let mut merged = serde_json::to_value(self)?;
        merge(&mut merged, overrides);
        serde_json::from_value(merged)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
