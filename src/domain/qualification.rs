//! A station's qualification (ISO 15530-3): what a study over calibrated masters measured of the
//! station — its fingerprint, the correction of its systematic error, the components of its
//! uncertainty and the gauge-study figures — and the checks an inspection at that station passes
//! before the qualification may be applied to it. Pure data and rules: the study itself is
//! `eval::qualify`, its application `pipeline::qualify`.

use crate::domain::optics::Projection;
use crate::domain::station::Station;
use serde::{Deserialize, Serialize};

/// How far a bundle's station may depart from the qualified fingerprint and still be that
/// station: relative on the object pixel, the depth of field and the frame step (a refocus or a
/// lens change moves them by more), absolute on the overlap; projection, views and rows exactly.
pub const PIXEL_TOLERANCE: f64 = 0.03;
pub const DEPTH_OF_FIELD_TOLERANCE: f64 = 0.10;
pub const FRAME_STEP_TOLERANCE: f64 = 0.10;
pub const OVERLAP_TOLERANCE_DEG: f64 = 1.0;

/// The station as a qualification is bound to it: the report's `station` figures that decide
/// what the depth maps can resolve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Fingerprint {
    /// The camera's projection.
    pub projection: Projection,
    /// One pixel on the part at the focus distance, mm.
    pub object_pixel_mm: f64,
    /// The depth of field, mm.
    pub depth_of_field_mm: f64,
    /// The frames' spacing, mm.
    pub frame_step_mm: f64,
    /// Views around the part.
    pub views: usize,
    /// Distinct axial positions of the views.
    pub axial_rows: usize,
    /// Neighbouring views' overlap along the arc, degrees; null for one view per row.
    pub overlap_deg: Option<f64>,
}

impl Fingerprint {
    pub fn of(station: &Station) -> Self {
        Self {
            projection: station.projection,
            object_pixel_mm: station.object_pixel_mm,
            depth_of_field_mm: station.depth_of_field_mm,
            frame_step_mm: station.frame_step_mm,
            views: station.views,
            axial_rows: station.axial_rows,
            overlap_deg: station.overlap_deg,
        }
    }

    /// Where `station` departs from this fingerprint beyond the tolerances, each named with both
    /// values; empty when it is this station.
    pub fn mismatches(&self, station: &Station) -> Vec<String> {
        let mut out = Vec::new();
        let relative = |name: &str, ours: f64, theirs: f64, tolerance: f64, out: &mut Vec<String>| {
            if (theirs - ours).abs() > tolerance * ours.abs() {
                out.push(format!(
                    "{name} {theirs:.4} mm against the qualified {ours:.4} mm (±{:.0}%)",
                    100.0 * tolerance
                ));
            }
        };
        if station.projection != self.projection {
            out.push(format!("projection {:?} against the qualified {:?}", station.projection, self.projection));
        }
        relative("object pixel", self.object_pixel_mm, station.object_pixel_mm, PIXEL_TOLERANCE, &mut out);
        relative(
            "depth of field",
            self.depth_of_field_mm,
            station.depth_of_field_mm,
            DEPTH_OF_FIELD_TOLERANCE,
            &mut out,
        );
        relative("frame step", self.frame_step_mm, station.frame_step_mm, FRAME_STEP_TOLERANCE, &mut out);
        if station.views != self.views {
            out.push(format!("{} views against the qualified {}", station.views, self.views));
        }
        if station.axial_rows != self.axial_rows {
            out.push(format!("{} axial rows against the qualified {}", station.axial_rows, self.axial_rows));
        }
        match (self.overlap_deg, station.overlap_deg) {
            (Some(a), Some(b)) if (a - b).abs() > OVERLAP_TOLERANCE_DEG => {
                out.push(format!("overlap {b:.1}° against the qualified {a:.1}° (±{OVERLAP_TOLERANCE_DEG}°)"))
            }
            (Some(_), None) | (None, Some(_)) => out.push("the views' overlap differs from the qualified".into()),
            _ => {}
        }
        out
    }
}

/// The correction model a study chose: the station's systematic height error as a function of
/// where a height is measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CorrectionModel {
    /// No correction: the station's error showed no systematic part the study could carry.
    None,
    /// One bias per thread (its position along the view and the thread form's profile there).
    PerThread,
}

impl CorrectionModel {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::PerThread => "per_thread",
        }
    }
}

/// One thread's correction, µm: subtracted from each of its heights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadBias {
    /// The thread's number, 1 nearest the pipe end.
    pub thread: u32,
    /// The station's bias on this thread's heights (measured − certified), µm.
    pub bias_um: f64,
    /// The standard uncertainty of that bias, µm.
    pub u_um: f64,
    /// Heights (bins × runs) it was estimated from.
    pub samples: usize,
}

/// The correction as applied.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Correction {
    /// The model the study chose.
    pub model: CorrectionModel,
    /// Per thread; a thread not listed was not measured on any master.
    pub threads: Vec<ThreadBias>,
}

impl Correction {
    /// The correction of a height of `thread`, mm; None where the thread has none.
    pub fn at_mm(&self, thread: u32) -> Option<f64> {
        if self.model == CorrectionModel::None {
            return Some(0.0);
        }
        self.threads.iter().find(|t| t.thread == thread).map(|t| 1e-3 * t.bias_um)
    }
}

/// The station's standard uncertainties per ISO 15530-3, µm.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StationUncertainty {
    /// The masters' calibration (their certificates' expanded uncertainty over k = 2).
    pub u_cal_um: f64,
    /// Repeatability: one height's scatter over the repositioned runs of a master.
    pub u_p_um: f64,
    /// The correction's own uncertainty: each bias's standard error and what the model leaves
    /// systematic at a bin.
    pub u_b_um: f64,
    /// Master to master: the spread of the correction between masters (0 with one master, which
    /// `u_w_measured` says).
    pub u_w_um: f64,
    /// Whether u_w was measured (at least two masters).
    pub u_w_measured: bool,
    /// The combined standard uncertainty of a corrected height, µm.
    pub combined_um: f64,
    /// The coverage factor.
    pub coverage_factor: f64,
    /// k × combined, µm.
    pub expanded_um: f64,
}

/// The type-1 gauge study (VDA 5 / AIAG MSA) per thread on the masters' repeat runs, and the
/// gauge R&R (ANOVA) over the masters' threads as parts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct GaugeStudy {
    /// The height tolerance band the figures are read against (2 × the form's ± tolerance), µm.
    pub tolerance_um: f64,
    /// Per thread of each master: bias before and after the correction, repeatability, Cg, Cgk.
    pub threads: Vec<ThreadGauge>,
    /// The lowest Cg over the threads (≥ 1.33 is the usual acceptance).
    pub cg_min: Option<f64>,
    /// The lowest Cgk after correction.
    pub cgk_min: Option<f64>,
    /// %GRR against the tolerance (6 σ_GRR / T); null with fewer than 2 parts × 2 repeats.
    pub grr_percent_tolerance: Option<f64>,
    /// %GRR against the total variation of the study.
    pub grr_percent_total: Option<f64>,
    /// The number of distinct categories, 1.41 σ_parts / σ_GRR.
    pub ndc: Option<f64>,
    /// Parts (a master's thread) the ANOVA used.
    pub parts: usize,
    /// Repeats per part the ANOVA used.
    pub repeats: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadGauge {
    /// The master's serial.
    pub master: String,
    /// The thread's number.
    pub thread: u32,
    /// The thread's mean height per run minus its certified mean, averaged over the runs, µm.
    pub bias_before_um: f64,
    /// The same after the correction (estimated without the run it is read on), µm.
    pub bias_after_um: f64,
    /// The standard deviation of the thread's mean height over the runs, µm.
    pub repeatability_um: f64,
    /// Cg = 0.2 T / (6 s).
    pub cg: Option<f64>,
    /// Cgk = (0.1 T − |bias after|) / (3 s).
    pub cgk: Option<f64>,
    /// Runs of the master.
    pub runs: usize,
}

/// What the study covered: the masters' forms and finishes. A part of another connection is
/// outside it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct MasterSummary {
    /// The master's serial.
    pub serial: String,
    /// The API 5B designation, or null for a custom form.
    pub connection: Option<String>,
    /// Its runs in the study.
    pub runs: usize,
    /// The certificate's instrument.
    pub instrument: String,
    /// The certificate's date.
    pub calibrated_at: String,
    /// The certificate's expanded uncertainty, µm.
    pub certificate_u_um: f64,
}

/// A qualified station: what `crestscan qualify` writes and `POST /v1/stations/{id}/studies`
/// stores, and what an inspection at that station applies.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Qualification {
    /// The station's name.
    pub station: String,
    /// The study's id (a content hash of its inputs where the CLI made it).
    pub study: String,
    /// The station as the study bound it.
    pub fingerprint: Fingerprint,
    /// The masters it measured.
    pub masters: Vec<MasterSummary>,
    /// The correction applied to the station's heights.
    pub correction: Correction,
    /// The station's uncertainty components.
    pub uncertainty: StationUncertainty,
    /// The gauge-study figures.
    pub gauge: GaugeStudy,
    /// The candidates' held-out RMS error, µm, by model, and how they were held out.
    pub selection: ModelSelection,
    /// The heights' RMS error against the certificates before the correction, µm (after it: the
    /// correction estimated without the run or master it is read on).
    pub rms_before_um: f64,
    /// After the correction (held out), µm.
    pub rms_after_um: f64,
    /// The largest helix residual of the study's runs, µm: an inspection at the station whose
    /// helix fits within 1.25 times this is not failed for its fit.
    pub helix_fit_rms_max_um: f64,
    /// The median over the study's runs of their heights' local scatter (the uncertainty
    /// budget's `noise_median_um`), µm: u_p already holds that much, so an inspection's bin adds
    /// only the scatter beyond it.
    #[serde(default)]
    pub noise_median_um: Option<f64>,
    /// The control charts' limits, per master and statistic, that check runs are judged against
    /// (empty in studies made before checks were charted).
    #[serde(default)]
    pub control: Vec<crate::domain::control::ControlLimits>,
    /// The last moment the qualification holds (RFC 3339); null: until requalified.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valid_until: Option<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ModelSelection {
    /// `leave_one_master_out` with two masters or more, else `leave_one_run_out`.
    pub method: String,
    /// Each candidate model's held-out error.
    pub candidates: Vec<CandidateScore>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CandidateScore {
    /// The candidate model.
    pub model: CorrectionModel,
    /// RMS of the held-out heights' error after this model's correction, µm.
    pub held_out_rms_um: f64,
}

/// Why a qualification does not apply to an inspection, in words that name the cause.
pub fn refusal(q: &Qualification, station: &Station, connection: Option<&str>) -> Option<String> {
    let mismatches = q.fingerprint.mismatches(station);
    if !mismatches.is_empty() {
        return Some(format!(
            "This bundle was not recorded at station {} as it was qualified ({}): {}",
            q.station,
            q.study,
            mismatches.join("; ")
        ));
    }
    if !q.masters.iter().any(|m| m.connection.as_deref() == connection) {
        let covered: Vec<String> =
            q.masters.iter().map(|m| m.connection.clone().unwrap_or_else(|| "a custom form".into())).collect();
        return Some(format!(
            "Station {}'s study covered {} only; this part is {}",
            q.station,
            covered.join(", "),
            connection.unwrap_or("a custom form")
        ));
    }
    None
}
