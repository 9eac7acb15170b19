//! The models: those shipped in the binary (built from `models/`, so the binary finds them with
//! no configuration) and those installed in a folder at run time (a plant's refitted MLP,
//! docs/models.md), each known by name and identified in reports by its sha256.
//!
//! An installed model is `<dir>/<name>.onnx` with its card `<dir>/<name>.json` (`{"role":
//! "profile_correction", …}`); it is read when an inspection names it, so a model installed
//! while the service runs is used by the next inspection that asks for it, no restart needed.

use super::{LearnedError, SessionPool};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ModelRole {
    /// One pitch of profile in, the corrected pitch out ([`super::profile_mlp`]).
    ProfileCorrection,
    /// A view's stack in, each pixel's in-focus plane out ([`super::depth_cnn`]).
    Depth,
}

impl ModelRole {
    pub fn as_str(self) -> &'static str {
        match self {
            ModelRole::ProfileCorrection => "profile_correction",
            ModelRole::Depth => "depth",
        }
    }

    /// The pipeline option that names a model of this role.
    pub fn option(self) -> &'static str {
        match self {
            ModelRole::ProfileCorrection => "profile.correction_model",
            ModelRole::Depth => "depth.model",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ModelSource {
    Shipped,
    Installed,
}

impl ModelSource {
    pub fn as_str(self) -> &'static str {
        match self {
            ModelSource::Shipped => "shipped",
            ModelSource::Installed => "installed",
        }
    }
}

/// Which model produced part of a report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ModelUse {
    /// What the model does: depth from focus, or the profile correction.
    pub role: ModelRole,
    /// Its name (a shipped model's, or one installed in `<data_dir>/models`).
    pub name: String,
    /// The sha256 of its ONNX file: which weights ran.
    pub sha256: String,
    /// Whether it shipped with crestscan or was installed.
    pub source: ModelSource,
}

/// A model ready to run: its identity and its sessions.
pub struct Model {
    pub identity: ModelUse,
    pub pool: SessionPool,
    /// What it is known to do to heights (a profile-correction model's card; None where the
    /// card measured nothing: `auto` then leaves the heights classical).
    pub effect: Option<super::effect::Effect>,
}

/// The part of a model card the binary reads (the rest is for people: docs/models.md).
#[derive(Deserialize)]
struct Card {
    role: ModelRole,
    #[serde(default)]
    effect: Option<serde_json::Value>,
}

impl Card {
    /// The card's effect, checked; an error names what is wrong with it.
    fn effect(&self, name: &str) -> Result<Option<super::effect::Effect>, LearnedError> {
        let bad = |message: String| LearnedError::Model { name: name.into(), message: format!("its card's {message}") };
        let Some(value) = &self.effect else { return Ok(None) };
        let effect: super::effect::Effect =
            serde_json::from_value(value.clone()).map_err(|e| bad(format!("effect: {e}")))?;
        effect.check().map_err(bad)?;
        Ok(Some(effect))
    }
}

struct Shipped {
    name: &'static str,
    role: ModelRole,
    bytes: &'static [u8],
    #[cfg_attr(not(test), allow(dead_code))]
    card: &'static str,
}

const SHIPPED: &[Shipped] = &[
    Shipped {
        name: "profile-mlp",
        role: ModelRole::ProfileCorrection,
        bytes: include_bytes!("../../models/profile-mlp.onnx"),
        card: include_str!("../../models/profile-mlp.json"),
    },
    Shipped {
        name: "depth-unet",
        role: ModelRole::Depth,
        bytes: include_bytes!("../../models/depth-unet.onnx"),
        card: include_str!("../../models/depth-unet.json"),
    },
];

pub struct Models {
    shipped: Vec<Arc<Model>>,
    installed_dir: Option<PathBuf>,
    /// Installed models opened so far, by the sha256 of their weights and card (a file replaced
    /// under the same name is a new model).
    installed: Mutex<HashMap<String, Arc<Model>>>,
}

static INSTALLED_DIR: OnceLock<Option<PathBuf>> = OnceLock::new();
static MODELS: OnceLock<Models> = OnceLock::new();

/// Where the process's models ([`models`]) look for installed ones (the CLI's `--models-dir`; the
/// service keeps its own [`Models`]); to be called before the first inspection. False if it was
/// already set.
pub fn set_installed_dir(dir: Option<PathBuf>) -> bool {
    INSTALLED_DIR.set(dir).is_ok()
}

/// The process's models.
pub fn models() -> &'static Models {
    MODELS.get_or_init(|| Models::new(INSTALLED_DIR.get().cloned().flatten()))
}

fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// A name that can only mean a file in the models folder.
/// A model's name: 1 to 64 characters of letters, digits, `.`, `_` and `-`, starting with a letter or
/// digit (a file name in the models directory, so never a path).
pub fn check_name(role: ModelRole, name: &str) -> Result<(), LearnedError> {
    let ok = (1..=crate::domain::text::MODEL_NAME_CHARS).contains(&name.len())
        && name.starts_with(|c: char| c.is_ascii_alphanumeric())
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
        && !name.contains("..");
    if ok {
        Ok(())
    } else {
        Err(LearnedError::InvalidName { role: role.as_str(), name: name.chars().take(80).collect() })
    }
}

impl Models {
    pub fn new(installed_dir: Option<PathBuf>) -> Self {
        let shipped = SHIPPED
            .iter()
            .map(|s| {
                Arc::new(Model {
                    identity: ModelUse {
                        role: s.role,
                        name: s.name.into(),
                        sha256: sha256_hex(s.bytes),
                        source: ModelSource::Shipped,
                    },
                    pool: SessionPool::new(s.name, Arc::from(s.bytes)),
                    effect: serde_json::from_str::<Card>(s.card)
                        .expect("a shipped card is JSON with a role")
                        .effect(s.name)
                        .expect("a shipped card's effect is checked by its test"),
                })
            })
            .collect();
        Self { shipped, installed_dir, installed: Mutex::new(HashMap::new()) }
    }

    /// The shipped models' identities.
    pub fn shipped(&self) -> Vec<ModelUse> {
        self.shipped.iter().map(|m| m.identity.clone()).collect()
    }

    /// The model of `role` called `name`: the shipped one when `name` is None or names it, else
    /// the installed one.
    pub fn get(&self, role: ModelRole, name: Option<&str>) -> Result<Arc<Model>, LearnedError> {
        let of_role = || self.shipped.iter().filter(move |m| m.identity.role == role);
        let Some(name) = name else {
            return Ok(of_role().next().expect("a shipped model of every role").clone());
        };
        check_name(role, name)?;
        if let Some(m) = of_role().find(|m| m.identity.name == name) {
            return Ok(m.clone());
        }
        let unknown = || LearnedError::UnknownModel {
            role: role.as_str(),
            name: name.into(),
            shipped: of_role().map(|m| m.identity.name.clone()).collect::<Vec<_>>().join(", "),
            installed: match &self.installed_dir {
                Some(dir) => match self.installed_names(dir, role) {
                    names if names.is_empty() => "none".into(),
                    names => names.join(", "),
                },
                None => "none (no models folder configured)".into(),
            },
        };
        let Some(dir) = &self.installed_dir else { return Err(unknown()) };
        let (onnx, card) = (dir.join(format!("{name}.onnx")), dir.join(format!("{name}.json")));
        let card_bytes = std::fs::read(&card).map_err(|_| unknown())?;
        let Ok(card) = serde_json::from_slice::<Card>(&card_bytes) else { return Err(unknown()) };
        if card.role != role {
            return Err(unknown());
        }
        let effect = card.effect(name)?;
        let bytes = std::fs::read(&onnx).map_err(|_| unknown())?;
        let sha256 = sha256_hex(&bytes);
        let mut installed = self.installed.lock().unwrap_or_else(|e| e.into_inner());
        // A card rewritten beside the same weights (its effect measured again) is a new model too.
        let key = format!("{sha256}:{}", sha256_hex(&card_bytes));
        let model = installed.entry(key).or_insert_with(|| {
            Arc::new(Model {
                identity: ModelUse { role, name: name.into(), sha256, source: ModelSource::Installed },
                pool: SessionPool::new(name, Arc::from(bytes)),
                effect,
            })
        });
        Ok(model.clone())
    }

    fn installed_names(&self, dir: &Path, role: ModelRole) -> Vec<String> {
        let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
        let mut names: Vec<String> = entries
            .filter_map(|e| e.ok())
            .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(".json")).map(String::from))
            .filter(|n| check_name(role, n).is_ok() && dir.join(format!("{n}.onnx")).is_file())
            .filter(|n| read_role(&dir.join(format!("{n}.json"))) == Some(role))
            .collect();
        names.sort();
        names
    }
}

fn read_role(card: &Path) -> Option<ModelRole> {
    let text = std::fs::read(card).ok()?;
    serde_json::from_slice::<Card>(&text).ok().map(|c| c.role)
}

/// The shipped cards, for the test that their sha256 matches the bytes.
#[cfg(test)]
fn shipped_cards() -> Vec<(&'static str, &'static str, String)> {
    SHIPPED.iter().map(|s| (s.name, s.card, sha256_hex(s.bytes))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_shipped_card_names_its_model_role_and_sha256() {
        for (name, card, sha256) in shipped_cards() {
            let card: serde_json::Value = serde_json::from_str(card).expect("card is JSON");
            assert_eq!(card["name"], name);
            assert_eq!(card["sha256"], sha256.as_str(), "{name}: the card's sha256 is stale");
            assert!(card["role"].is_string());
        }
        // Every shipped card's effect parses and passes its checks (Models::new relies on it).
        for s in SHIPPED {
            let card: Card = serde_json::from_str(s.card).unwrap();
            card.effect(s.name).unwrap_or_else(|e| panic!("{}: {e}", s.name));
        }
    }

    #[test]
    fn names_that_could_leave_the_folder_are_refused() {
        let models = Models::new(Some(std::env::temp_dir()));
        for bad in ["../x", "a/b", "", ".hidden", "a..b", &"x".repeat(65)] {
            let err = models.get(ModelRole::ProfileCorrection, Some(bad)).err().expect(bad);
            assert!(matches!(err, LearnedError::InvalidName { .. }), "{bad}: {err}");
        }
        let err = models.get(ModelRole::ProfileCorrection, Some("not-there")).err().expect("unknown");
        assert!(matches!(err, LearnedError::UnknownModel { .. }), "{err}");
        assert!(err.to_string().contains("profile-mlp"), "{err}");
    }
}
