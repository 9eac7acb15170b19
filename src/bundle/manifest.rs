//! manifest.json of bundle v1, as written in docs/bundle.md. Unknown fields are accepted
//! (the contract lets new optional fields appear); known fields are typed.

use crate::domain::frame::FrameEntry;
use crate::domain::optics::{Optics, ViewPose};
use crate::domain::thread::Family;
use serde::{Deserialize, Serialize};

pub const FORMAT_V1: &str = "crestscan.focal-stack/1";

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[schema(
    description = "manifest.json of a focal-stack bundle (docs/bundle.md); fields not named here are accepted and ignored"
)]
pub struct Manifest {
    /// `crestscan.focal-stack/1`.
    pub format: String,
    pub part: PartManifest,
    pub optics: Optics,
    /// The views, each a focal stack at one pose; at least one.
    pub views: Vec<ViewManifest>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct PartManifest {
    /// The part's serial number, as the plant names it: 1 to 128 characters, no control characters.
    #[serde(default)]
    #[schema(min_length = 1, max_length = 128)]
    pub serial: Option<String>,
    /// A designation of the API 5B connection table (`GET /v1/connections`): `BC 4-1/2`, `LC 5-1/2`;
    /// 1 to 64 characters.
    #[serde(default)]
    #[schema(min_length = 1, max_length = 64)]
    pub connection: Option<String>,
    /// A custom thread form, or overrides of the connection's values; one of `connection` and
    /// `thread` is needed.
    #[serde(default)]
    pub thread: Option<CustomThread>,
}

/// A custom thread form, or overrides of the connection table's values. The contract's fields plus
/// optional profile details (flank angles, crest width, root truncation).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CustomThread {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub family: Option<Family>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pitch_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub thread_height_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_tolerance_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub taper_on_diameter: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pipe_od_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lc_mm: Option<f64>,
    /// Buttress-family profile details (defaults 3°, 10°, equal crest and root flats).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load_flank_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stab_flank_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crest_width_mm: Option<f64>,
    /// Round-family details: flank half angle (default 30°) and root truncation (default half the
    /// truncation of the sharp V).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flank_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub root_truncation_mm: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ViewManifest {
    /// Unique within the bundle; 1 to 64 characters.
    #[schema(min_length = 1, max_length = 64)]
    pub id: String,
    pub pose: ViewPose,
    /// The focal stack, offsets growing from near to far; at least 3 frames.
    pub frames: Vec<FrameEntry>,
}
