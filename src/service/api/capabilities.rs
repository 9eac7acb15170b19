//! What this service can measure: the station envelope its accuracy figures were measured in.

use super::AppState;
use super::problem::Problem;
use crate::domain::station::{IN_FOCUS_BLUR_PX, MEASURED};
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

#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Capabilities {
    pub version: String,
    /// The stations the published accuracy figures were measured at. A bundle outside it is
    /// inspected; its report's `quality` is `degraded` with the reason `station_unmeasured`, naming
    /// each parameter outside, and `review_required` is true.
    pub measured_envelope: StationEnvelope,
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
    Json(Capabilities {
        version: env!("CARGO_PKG_VERSION").into(),
        measured_envelope: StationEnvelope {
            object_pixel: range(MEASURED.object_pixel_mm, "mm"),
            depth_of_field: range(MEASURED.depth_of_field_mm, "mm"),
            in_focus_blur_px: IN_FOCUS_BLUR_PX,
            frame_step: range(MEASURED.frame_step_dof, "depths of field"),
            overlap: range(MEASURED.overlap_deg, "deg"),
            frame_noise: range(MEASURED.frame_noise_percent, "% of the brightness"),
        },
        description: format!(
            "Every accuracy figure so far was measured at one station design (the simulator's presets): \
             this envelope is that station ±10% on each parameter of its optics and layout, with frames \
             no noisier than {}% of their brightness (its sensor's read 0.65–0.84%, measured on the \
             frames by the depth stage). Stations outside it are inspected \
             and their results flagged for review: on the station benchmark's random stations \
             (object pixels 0.03–0.15 mm) crestscan does not yet measure within its targets \
             (docs/benchmark.md, Stations).",
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
