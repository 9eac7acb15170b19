//! A qualified station's correction applied to the classical heights (ISO 15530-3), after the
//! crest stage and before the uncertainty: each height less the station's bias where it was
//! measured, the report saying what was applied and the heights before and after. Where the
//! qualification may not be applied (another station, a part the study did not cover, a suspended
//! or expired station) nothing is corrected and the quality says why.

use crate::domain::qualification::{CorrectionModel, Qualification, StationUncertainty, refusal};
use crate::domain::station::Station;
use crate::pipeline::profile::ThreadMeasure;
use serde::{Deserialize, Serialize};

/// What the caller knows of the inspection's station.
#[derive(Clone, Debug)]
pub enum AtStation {
    /// A qualified station: its qualification, to be applied if the bundle matches it.
    Qualified(Qualification),
    /// A named station whose qualification may not be used (suspended, expired): why.
    Refused { station: String, reason: String },
}

/// What the report says of the station's qualification.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct QualificationUse {
    /// The station's name.
    pub station: String,
    /// The study whose correction and uncertainty were applied; null where none was.
    pub study: Option<String>,
    /// Whether the correction and the station's uncertainty were applied.
    pub applied: bool,
    /// Why they were not, naming the cause; null where they were.
    pub refused: Option<String>,
    /// The correction model applied.
    pub model: Option<CorrectionModel>,
    /// The station's uncertainty components, µm, as the study measured them.
    pub uncertainty: Option<StationUncertainty>,
    /// Per thread: the correction subtracted and the mean height before and after it.
    pub threads: Vec<ThreadCorrectionUse>,
    /// The largest helix residual of the study's runs, µm (what this inspection's fit is judged
    /// against).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub helix_fit_rms_max_um: Option<f64>,
    /// The study's median local scatter of a height, µm: a bin's own scatter adds to the
    /// station's uncertainty only beyond it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_median_um: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadCorrectionUse {
    /// The thread's number, 1 nearest the pipe end.
    pub thread: u32,
    /// The mean correction subtracted from the thread's heights, µm.
    pub correction_um: f64,
    /// The thread's mean measured height before the correction, mm.
    pub mean_before_mm: Option<f64>,
    /// And after it, mm.
    pub mean_after_mm: Option<f64>,
}

/// Applies `at` to the measured threads: corrects their heights where the qualification applies,
/// marks the station qualified, and returns what the report says.
pub fn apply(
    at: &AtStation,
    station: &mut Station,
    connection: Option<&str>,
    threads: &mut [ThreadMeasure],
) -> QualificationUse {
    let q = match at {
        AtStation::Refused { station: name, reason } => return refused(name, reason.clone()),
        AtStation::Qualified(q) => q,
    };
    if let Some(reason) = refusal(q, station, connection) {
        return refused(&q.station, reason);
    }
    let uncovered: Vec<String> = threads
        .iter()
        .filter(|t| t.bins.iter().any(|b| b.height_mm.is_some()))
        .filter(|t| q.correction.at_mm(t.index).is_none())
        .map(|t| t.index.to_string())
        .collect();
    if !uncovered.is_empty() {
        return refused(
            &q.station,
            format!(
                "Station {}'s study measured no correction for thread(s) {} of this part",
                q.station,
                uncovered.join(", ")
            ),
        );
    }
    let mut used = Vec::with_capacity(threads.len());
    for t in threads.iter_mut() {
        let (mut before, mut after, mut correction, mut n) = (0.0, 0.0, 0.0, 0usize);
        for b in &mut t.bins {
            let Some(h) = b.height_mm else { continue };
            let c = q.correction.at_mm(t.index).unwrap_or(0.0);
            b.height_mm = Some(h - c);
            before += h;
            after += h - c;
            correction += c;
            n += 1;
        }
        let mean = |sum: f64| (n > 0).then(|| sum / n as f64);
        used.push(ThreadCorrectionUse {
            thread: t.index,
            correction_um: 1e3 * mean(correction).unwrap_or(0.0),
            mean_before_mm: mean(before),
            mean_after_mm: mean(after),
        });
    }
    station.qualified_by = Some(q.study.clone());
    QualificationUse {
        station: q.station.clone(),
        study: Some(q.study.clone()),
        applied: true,
        refused: None,
        model: Some(q.correction.model),
        uncertainty: Some(q.uncertainty.clone()),
        threads: used,
        helix_fit_rms_max_um: Some(q.helix_fit_rms_max_um),
        noise_median_um: q.noise_median_um,
    }
}

fn refused(station: &str, reason: String) -> QualificationUse {
    QualificationUse {
        station: station.to_string(),
        study: None,
        applied: false,
        refused: Some(reason),
        model: None,
        uncertainty: None,
        threads: Vec::new(),
        helix_fit_rms_max_um: None,
        noise_median_um: None,
    }
}
