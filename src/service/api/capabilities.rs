//! What this service can measure: the station envelope its accuracy figures were measured in.

use super::common::AppState;
use super::problem::Problem;
use crate::domain::station::{Envelope, IN_FOCUS_BLUR_PX, MAX_OBJECT_PIXEL_MM, MEASURED, StationClass};
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(get_capabilities))
}

/// A closed range of one station parameter.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Range {
    pub min: f64,
    pub max: f64,
    pub unit: String,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StationEnvelope {
    /// One pixel on the part at the focus distance.
    pub object_pixel: Range,
    /// The depth range over which the blur circle stays within `in_focus_blur_px` pixels.
    pub depth_of_field: Range,
    pub in_focus_blur_px: f64,
    /// The frames' offset step, in depths of field.
    pub frame_step: Range,
    /// How far neighbouring views' footprints overlap along the arc.
    pub overlap: Range,
    /// The frames' pixel noise in per cent of their brightness, as the depth stage reads it on
    /// each view's first frame (the report's `station.frame_noise_percent`).
    pub frame_noise: Range,
}

/// One class of the declared envelope.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StationClassRanges {
    /// As a report's `station.class` names it.
    pub class: StationClass,
    pub ranges: StationEnvelope,
    /// What a result at such a station gets, and where its figures are.
    pub results: String,
}

/// A station parameter that refuses a bundle at validation (`station_out_of_range`, the culprit
/// naming the manifest field).
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct StationRefusal {
    /// The manifest field named as the culprit.
    pub field: String,
    pub rule: String,
}

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Capabilities {
    pub version: String,
    /// The stations the published accuracy figures were measured at (the class `standard`). A
    /// bundle outside it is inspected; its report's `quality` is `degraded` with the reason
    /// `station_unmeasured`, naming each parameter outside and the station's class, and
    /// `review_required` is true.
    pub measured_envelope: StationEnvelope,
    /// The declared envelope's classes, finest first; a report's `station.class` names the first
    /// whose ranges hold all its parameters (none: unclassified).
    pub station_classes: Vec<StationClassRanges>,
    /// What refuses a bundle outright, per parameter; every other station is inspected.
    pub refused: Vec<StationRefusal>,
    pub description: String,
    /// The coverage factor of every height's expanded uncertainty (`uncertainty_mm`).
    pub coverage_factor: f64,
    /// How a report's `decision` is made from the verdict and the uncertainties.
    pub decision_rule: String,
}

/// The station envelope the accuracy figures hold in.
#[utoipa::path(get, path = "/v1/capabilities", operation_id = "get_capabilities", tag = "operations",
    responses(
        (status = 200, description = "What this service measures, and where its figures hold", body = Capabilities),
        (status = 500, description = "Server error", body = Problem, content_type = "application/problem+json"),
    ))]
pub async fn get_capabilities() -> Json<Capabilities> {
    let range = |(min, max): (f64, f64), unit: &str| Range { min, max, unit: unit.into() };
    let envelope = |e: Envelope| StationEnvelope {
        object_pixel: range(e.object_pixel_mm, "mm"),
        depth_of_field: range(e.depth_of_field_mm, "mm"),
        in_focus_blur_px: IN_FOCUS_BLUR_PX,
        frame_step: range(e.frame_step_dof, "depths of field"),
        overlap: range(e.overlap_deg, "deg"),
        frame_noise: range(e.frame_noise_percent, "% of the brightness"),
    };
    let station_classes = StationClass::ALL
        .into_iter()
        .map(|class| StationClassRanges {
            class,
            ranges: envelope(class.envelope()),
            results: match class {
                StationClass::Standard => "the accuracy suites' station: the published accuracy figures hold \
                                           (docs/status.md, docs/benchmark.md); decisions conform or not by the uncertainty"
                    .into(),
                _ => format!(
                    "inspected, quality degraded (station_unmeasured), review_required; where the optics (object \
                     pixel, depth of field, frame step, frame noise) lie outside the standard class, the decision \
                     is indeterminate and each height's uncertainty includes the heights' dispersion along the \
                     helix and their thread's distance from nominal. The station benchmark's {} class figures \
                     (docs/status.md, Accuracy; docs/benchmark.md) are far from the targets",
                    class.as_str()
                ),
            },
        })
        .collect();
    let refused = vec![
        StationRefusal {
            field: "optics.pixel_pitch_um".into(),
            rule: format!(
                "an object pixel over {:.2} mm (beyond the coarse class), or fewer than 10 object pixels per \
                 thread pitch",
                MAX_OBJECT_PIXEL_MM
            ),
        },
        StationRefusal {
            field: "views[i].frames".into(),
            rule: "frames more than 2 depths of field apart, or a stack spanning less offset than the thread is \
                   deep"
                .into(),
        },
    ];
    Json(Capabilities {
        version: env!("CARGO_PKG_VERSION").into(),
        measured_envelope: envelope(MEASURED),
        station_classes,
        refused,
        description: format!(
            "Every accuracy figure so far was measured at one station design (the simulator's presets): \
             this envelope is that station ±10% on each parameter of its optics and layout, with frames \
             no noisier than {}% of their brightness (its sensor's read 0.65–0.84%, measured on the \
             frames by the depth stage). Stations outside it are inspected \
             and their results flagged for review: on the station benchmark's random stations \
             (object pixels 0.03–0.15 mm, the classes fine, medium and coarse) crestscan does not yet \
             measure within its targets (docs/benchmark.md, Stations).",
            MEASURED.frame_noise_percent.1
        ),
        coverage_factor: crate::pipeline::uncertainty::UncertaintyOptions::default().coverage_factor,
        decision_rule: "ISO 14253-1: the black-crest rules applied again with every measured value moved by its \
                        uncertainty toward reject and toward accept (black arcs lengthened or shortened at each end, \
                        the geometric onset moved by the crest scatter, Lc by the uncertainty of absolute z, crests \
                        no view showed counted black toward reject); conforms / does_not_conform where both bounds \
                        agree, indeterminate otherwise or where the measurement failed its quality checks"
            .into(),
    })
}
