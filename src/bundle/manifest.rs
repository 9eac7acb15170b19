//! manifest.json of bundle v1, as written in docs/bundle.md. Unknown fields are accepted
//! (the contract lets new optional fields appear); known fields are typed.

use crate::domain::frame::FrameEntry;
use crate::domain::optics::{Optics, ViewPose};
use crate::domain::thread::Family;
use serde::{Deserialize, Serialize};

pub const FORMAT_V1: &str = "crestscan.focal-stack/1";

/// The fields this reader knows, by their place in manifest.json (`views[].pose`; `[]` stands for
/// every item of a list). A test holds the table to the published JSON Schema.
pub const KNOWN_FIELDS: &[(&str, &[&str])] = &[
    ("", &["format", "part", "optics", "views", "station"]),
    ("part", &["serial", "connection", "thread"]),
    (
        "part.thread",
        &[
            "family",
            "pitch_mm",
            "thread_height_mm",
            "height_tolerance_mm",
            "taper_on_diameter",
            "pipe_od_mm",
            "lc_mm",
            "load_flank_deg",
            "stab_flank_deg",
            "crest_width_mm",
            "flank_deg",
            "root_truncation_mm",
        ],
    ),
    (
        "optics",
        &[
            "projection",
            "focal_length_mm",
            "f_number",
            "focus_distance_mm",
            "pixel_pitch_um",
            "principal_point_px",
            "magnification",
        ],
    ),
    ("views[]", &["id", "pose", "frames"]),
    ("views[].pose", &["angle_deg", "axial_mm", "lens_radius_mm"]),
    ("views[].frames[]", &["file", "offset_mm"]),
];

/// A field of the manifest this reader does not know: a near miss of a known field at its place
/// (a typo: refused, with the field meant), or one the contract lets a newer writer add (read past,
/// and listed for the user).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnknownField {
    /// Its path (`part.serail`, `views[2].pose.angel_deg`).
    pub path: String,
    /// The known field it nearly spells, absent from its object.
    pub did_you_mean: Option<&'static str>,
}

/// The manifest's fields that [`KNOWN_FIELDS`] does not name, in document order.
pub fn unknown_fields(manifest: &serde_json::Value) -> Vec<UnknownField> {
    fn walk(value: &serde_json::Value, place: &str, path: &str, out: &mut Vec<UnknownField>) {
        match value {
            serde_json::Value::Object(map) => {
                let Some((_, known)) = KNOWN_FIELDS.iter().find(|(p, _)| *p == place) else { return };
                for (key, child) in map {
                    let child_path = if path.is_empty() { key.clone() } else { format!("{path}.{key}") };
                    if known.contains(&key.as_str()) {
                        let child_place = if place.is_empty() { key.clone() } else { format!("{place}.{key}") };
                        walk(child, &child_place, &child_path, out);
                    } else {
                        let did_you_mean = known
                            .iter()
                            .filter(|k| !map.contains_key(**k))
                            .map(|k| (strsim::osa_distance(&key.to_ascii_lowercase(), k), *k))
                            .filter(|(d, k)| *d <= 2.min(k.len() / 3).max(1))
                            .min()
                            .map(|(_, k)| k);
                        out.push(UnknownField { path: child_path, did_you_mean });
                    }
                }
            }
            serde_json::Value::Array(items) => {
                for (i, item) in items.iter().enumerate() {
                    walk(item, &format!("{place}[]"), &format!("{path}[{i}]"), out);
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(manifest, "", "", &mut out);
    out
}

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
    /// The station the bundle was recorded at, by the name it was created with
    /// (`POST /v1/stations`): an inspection at a qualified station applies its correction and
    /// uncertainty. Optional; a submission's `station` wins over it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(min_length = 1, max_length = 64, pattern = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")]
    pub station: Option<String>,
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

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn near_misses_are_named_with_the_field_meant_and_new_fields_are_read_past() {
        let manifest = json!({
            "fromat": "crestscan.focal-stack/1",
            "part": {"serail": "P-1", "connection": "BC 4-1/2", "station_note": "line 3"},
            "optics": {"F_number": 2.8},
            "views": [{"id": "a", "pose": {"angel_deg": 0.0, "axial_mm": 1.0, "lens_radius_mm": 2.0}, "frames": []}],
            "vendor": {"anything": 1}
        });
        let found = unknown_fields(&manifest);
        let meant: Vec<(&str, Option<&str>)> = found.iter().map(|u| (u.path.as_str(), u.did_you_mean)).collect();
        assert_eq!(
            meant,
            [
                ("fromat", Some("format")),
                ("optics.F_number", Some("f_number")),
                ("part.serail", Some("serial")),
                ("part.station_note", None),
                ("vendor", None),
                ("views[0].pose.angel_deg", Some("angle_deg")),
            ]
        );
    }

    #[test]
    fn a_known_field_is_not_suggested_where_it_is_present() {
        let found = unknown_fields(&json!({"part": {"serial": "P-1", "serials": "x"}}));
        assert_eq!(found, [UnknownField { path: "part.serials".into(), did_you_mean: None }]);
    }
}
