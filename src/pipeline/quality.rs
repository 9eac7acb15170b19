//! How far a result can be trusted: a status and the reasons for it, each with a code and a
//! message that names its figures. A result whose quality is not `ok` needs review: the verdict is
//! the rule applied to what was measured, and something was not measured as it should have been.
//!
//! The reasons assessed so far: a station outside the envelope the accuracy figures were measured
//! in, overlaps that registration did not measure (so some views keep their encoder poses),
//! measured overlaps the solve down-weighted as outliers, and crests within Lc the views did not
//! show.

use crate::domain::frame::View;
use crate::domain::part::Part;
use crate::domain::rules::{Assessment, ReasonCode};
use crate::domain::station::{self, Station};
use crate::pipeline::profile::{Helix, PhaseUncertainty};
use crate::pipeline::register::{PairStatus, Registration};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum QualityStatus {
    /// Everything the verdict rests on was measured.
    Ok,
    /// Part of it was not measured, or measured poorly: the result is still useful, with care.
    Degraded,
    /// Too little was measured for the verdict to mean much.
    Insufficient,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum QualityCode {
    /// Some candidate overlaps were not measured.
    RegistrationIncomplete,
    /// Some views had no overlap measured: they keep their encoder poses.
    ViewsUnregistered,
    /// Several views and no overlap between them: every view keeps its encoder pose.
    NoOverlaps,
    /// Some measured overlaps disagree with the solved ring by more than the robust kernel allows.
    RegistrationOutliers,
    /// The views did not show every crest within Lc.
    PartialCoverage,
    /// The station lies outside the envelope the accuracy figures were measured in.
    StationUnmeasured,
    /// The inspection named a station whose qualification could not be applied: another
    /// fingerprint, a part the study did not cover, a suspended or expired station.
    StationNotQualified,
    /// The helix (nominal form at the measured phase and taper) fits the surface poorly.
    HelixResidualLarge,
    /// Depth from focus trusted few of the pixels that saw the part.
    DepthCoverageLow,
    /// The report was stored before quality was assessed.
    NotAssessed,
    /// The station called for the profile-correction MLP and it could not run: the heights are
    /// the classical fits.
    ProfileCorrectionUnavailable,
    /// The heights were corrected by the profile-correction MLP: the method's uncertainty was
    /// measured for the classical heights, not for the model's.
    ProfileCorrected,
    /// Depth came from the U-Nets (`depth.method: cnn`): the method's uncertainty was measured for
    /// the classical depth, not for the nets'.
    DepthLearned,
    /// Too few sectors of the circumference read the helix phase, or their readings scatter over
    /// the pitch: the heights' windows may sit anywhere between crest and root.
    HelixPhaseUnknown,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct QualityReason {
    /// The reason's stable machine code.
    pub code: QualityCode,
    /// The reason in words: a plain sentence first, the figures after it.
    pub message: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Quality {
    /// ok, degraded (some of the surface or registration is missing or weak) or insufficient (too
    /// little was measured to trust the result).
    pub status: QualityStatus,
    /// What was not measured, or measured poorly; empty when the status is ok.
    pub reasons: Vec<QualityReason>,
}

impl Quality {
    /// Flags what a learned model did to this measurement: made the depth, corrected the heights,
    /// or could not run where the station needed it. Each says why no decision is made.
    pub fn flag_learned(
        &mut self,
        depth_model: Option<&crate::learned::ModelUse>,
        corrected: Option<&crate::pipeline::profile::CorrectionChoice>,
        unavailable: Option<&crate::learned::LearnedError>,
    ) {
        if let Some(m) = depth_model {
            self.flag(
                QualityStatus::Degraded,
                QualityCode::DepthLearned,
                format!(
                    "Depth came from a learned model whose accuracy crestscan has not measured, so no decision is made. \
                     The {} model {} (sha256 {}) made the depth; the method's uncertainty was measured for the \
                     classical depth, so each height's U includes the heights' dispersion along the helix and their \
                     thread's distance from nominal, and no decision is made (docs/models.md)",
                    m.role.as_str(),
                    m.name,
                    m.sha256
                ),
            );
        }
        if let Some(c) = corrected {
            self.flag(
                QualityStatus::Degraded,
                QualityCode::ProfileCorrected,
                format!(
                    "The heights were corrected by the profile model {}, so no decision is made. {} Each height's U \
                     carries {:.2} µm of error per µm the model changed its thread, besides the heights' dispersion \
                     along the helix and their thread's distance from nominal (docs/models.md, \"Choosing when it runs\")",
                    c.model,
                    c.why,
                    c.error_per_change()
                ),
            );
        }
        if let Some(e) = unavailable {
            self.flag(
                QualityStatus::Degraded,
                QualityCode::ProfileCorrectionUnavailable,
                format!(
                    "The heights could not be corrected as this station needs, so they may be about twice as far off. \
                     This station's object pixel called for the profile-correction MLP (profile.correction auto) and it \
                     could not run: the heights are the classical fits (docs/models.md). {e}"
                ),
            );
        }
    }

    /// Adds a reason of at least `at`.
    pub fn flag(&mut self, at: QualityStatus, code: QualityCode, message: String) {
        self.status = self.status.max(at);
        self.reasons.push(QualityReason { code, message });
    }

    /// What a report stored before quality was assessed reads as: not known to be ok.
    pub fn not_assessed() -> Self {
        Self {
            status: QualityStatus::Degraded,
            reasons: vec![QualityReason {
                code: QualityCode::NotAssessed,
                message: "stored before the quality of a result was assessed".into(),
            }],
        }
    }

    pub fn needs_review(&self) -> bool {
        self.status != QualityStatus::Ok
    }
}

/// The quality of a result from its station, its registration and the rule engine's coverage.
/// The helix's fit residual, as a fraction of the thread height, beyond which the profile's
/// windows may not sit on the crests and roots they measure.
pub const HELIX_RESIDUAL_OF_HEIGHT: f64 = 0.15;
/// The share of pixels depth from focus trusts below which the surface is mostly interpolated.
pub const MIN_DEPTH_COVERAGE: f64 = 0.5;

/// How well the surface was measured: the helix's fit and depth's coverage.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceFit {
    pub helix_fit_rms_um: f64,
    pub thread_height_mm: f64,
    pub depth_coverage: f64,
    /// Sectors of the circumference that read the helix phase, and whether the phase is unknown
    /// within the pitch ([`Helix::phase_uncertainty`]).
    pub phase_sectors: usize,
    pub phase_unknown: bool,
    /// At a qualified station, the largest helix residual its study's runs had, µm: a residual
    /// the study measured the station's heights with is the station's, not this part's failure.
    pub qualified_helix_fit_rms_um: Option<f64>,
}

/// How far above its study's largest helix residual a qualified station's may go.
pub const QUALIFIED_HELIX_MARGIN: f64 = 1.25;

impl SurfaceFit {
    /// `phase`: the helix phase's uncertainty ([`Helix::phase_uncertainty`]).
    pub fn of(helix: &Helix, part: &Part, depth_coverage: f64, phase: &PhaseUncertainty) -> Self {
        Self {
            helix_fit_rms_um: helix.fit_rms_um,
            thread_height_mm: part.form.height_mm,
            depth_coverage,
            phase_sectors: phase.sectors,
            phase_unknown: phase.unknown,
            qualified_helix_fit_rms_um: None,
        }
    }
}

pub fn assess(
    station: &Station,
    registration: &Registration,
    views: &[View],
    assessment: &Assessment,
    surface: &SurfaceFit,
) -> Quality {
    let mut reasons = Vec::new();
    let mut status = QualityStatus::Ok;
    let mut flag = |at: QualityStatus, code: QualityCode, message: String| {
        status = status.max(at);
        reasons.push(QualityReason { code, message });
    };
    // A qualified station's uncertainty was measured on the station itself.
    let outside = if station.qualified_by.is_some() { Vec::new() } else { station.outside(&station::MEASURED) };
    if !outside.is_empty() {
        flag(
            QualityStatus::Degraded,
            QualityCode::StationUnmeasured,
            format!(
                "This station is unlike those crestscan's accuracy was measured at, so its heights may be further off \
                 than the stated figures. Outside the measured envelope: {}; {}",
                outside.join("; "),
                match station.class {
                    Some(class) => format!(
                        "it is in the {} station class, whose figures (GET /v1/capabilities, docs/status.md) are far from \
                         the targets",
                        class.as_str()
                    ),
                    None => "it is in no station class the station benchmark measured (GET /v1/capabilities)".into(),
                }
            ),
        );
    }
    let height_um = 1e3 * surface.thread_height_mm;
    let limit_um = HELIX_RESIDUAL_OF_HEIGHT * height_um;
    match surface.qualified_helix_fit_rms_um {
        Some(study_um) if surface.helix_fit_rms_um > limit_um.max(QUALIFIED_HELIX_MARGIN * study_um) => flag(
            QualityStatus::Degraded,
            QualityCode::HelixResidualLarge,
            format!(
                "The thread's helix fits the surface worse than at the station's qualification, so heights may have \
                 been read off the crests and roots. The helix fits with a residual of {:.0} µm RMS, over {:.2} times \
                 the {:.0} µm the study's runs reached",
                surface.helix_fit_rms_um, QUALIFIED_HELIX_MARGIN, study_um
            ),
        ),
        None if surface.helix_fit_rms_um > limit_um => flag(
            QualityStatus::Degraded,
            QualityCode::HelixResidualLarge,
            format!(
                "The thread's helix fits the surface poorly, so heights may have been read off the crests and roots. \
                 The helix fits with a residual of {:.0} µm RMS, over {:.0}% of the {:.0} µm thread height",
                surface.helix_fit_rms_um,
                100.0 * HELIX_RESIDUAL_OF_HEIGHT,
                height_um
            ),
        ),
        _ => {}
    }
    if surface.phase_unknown {
        flag(
            QualityStatus::Insufficient,
            QualityCode::HelixPhaseUnknown,
            format!(
                "Where the crests lie along the pipe could not be read reliably, so any height may have been taken \
                 between a crest and a root. The helix phase was read on {} sector{} of the circumference (one \
                 view's spacing each) and the helix fits the surface too loosely to bound it, or the sectors' \
                 readings scatter over the pitch; each height's U takes in the whole pitch",
                surface.phase_sectors,
                if surface.phase_sectors == 1 { "" } else { "s" }
            ),
        );
    }
    let depth_coverage = surface.depth_coverage;
    if depth_coverage < MIN_DEPTH_COVERAGE {
        flag(
            QualityStatus::Degraded,
            QualityCode::DepthCoverageLow,
            format!(
                "Much of the surface could not be measured. Depth from focus trusted {:.0}% of the pixels (under \
                 {:.0}%)",
                100.0 * depth_coverage,
                100.0 * MIN_DEPTH_COVERAGE
            ),
        );
    }
    let name = |v: usize| views.get(v).map_or_else(|| format!("#{v}"), |view| view.id.clone());
    let unmeasured: Vec<String> = registration
        .candidates
        .iter()
        .filter(|c| !matches!(c.status, PairStatus::Measured | PairStatus::Outlier))
        .map(|c| {
            let figures = match (c.peak_ncc, c.rival_ratio, c.overlap_cells) {
                (Some(ncc), Some(rival), Some(cells)) => {
                    format!(" (peak NCC {ncc:.3}, rival at {:.0}% of it, {cells} cells)", 100.0 * rival)
                }
                _ => String::new(),
            };
            format!("{}–{}: {}{figures}", name(c.a), name(c.b), status_word(c.status))
        })
        .collect();
    if !unmeasured.is_empty() {
        flag(
            QualityStatus::Degraded,
            QualityCode::RegistrationIncomplete,
            format!(
                "Some neighbouring views could not be aligned by their texture, so the surface may be pieced together \
                 less exactly. Registration measured {} of {} overlaps; not measured: {}",
                registration.pairs_measured,
                registration.pairs_expected,
                unmeasured.join("; ")
            ),
        );
    }
    if views.len() > 1 && registration.pairs_expected == 0 {
        flag(
            QualityStatus::Degraded,
            QualityCode::NoOverlaps,
            format!(
                "The views do not overlap, so none could be aligned with another. Each of the {} views keeps its \
                 encoder pose",
                views.len()
            ),
        );
    } else if views.len() > 1 && !registration.unregistered_views.is_empty() {
        let names: Vec<String> = registration.unregistered_views.iter().map(|&v| name(v)).collect();
        let names_of = |views_of: &[usize]| views_of.iter().map(|&v| name(v)).collect::<Vec<String>>();
        let mut placed = String::new();
        let radially: Vec<String> = registration
            .unregistered_views
            .iter()
            .filter(|v| registration.placed_radially.contains(v))
            .map(|&v| name(v))
            .collect();
        if !radially.is_empty() {
            placed += &format!(
                "; the radius of their overlaps at the encoder poses placed {} of them radially (lens radius only): {}",
                radially.len(),
                radially.join(", ")
            );
        }
        let by_corner = names_of(&registration.placed_by_end_face);
        if !by_corner.is_empty() {
            placed += &format!(
                "; the end face placed {} of them axially on their own: {}",
                by_corner.len(),
                by_corner.join(", ")
            );
        }
        let misread = names_of(&registration.end_face_implausible);
        if !misread.is_empty() {
            placed += &format!(
                "; the end face's corner would have moved {} of them further than the encoders can err, so it was \
                 taken as misread: {}",
                misread.len(),
                misread.join(", ")
            );
        }
        // With half the views or more unplaced, the surface is mostly where the encoders put it.
        let at = if 2 * names.len() >= views.len() { QualityStatus::Insufficient } else { QualityStatus::Degraded };
        flag(
            at,
            QualityCode::ViewsUnregistered,
            format!(
                "Some views could not be aligned with any other and stay where the encoders put them. {} of {} views \
                 have no measured overlap: {}{placed}",
                names.len(),
                views.len(),
                names.join(", ")
            ),
        );
    }
    let outliers: Vec<String> = registration
        .candidates
        .iter()
        .filter(|c| c.status == PairStatus::Outlier)
        .map(|c| format!("{}–{}", name(c.a), name(c.b)))
        .collect();
    if !outliers.is_empty() {
        flag(
            QualityStatus::Degraded,
            QualityCode::RegistrationOutliers,
            format!(
                "Some view alignments disagreed with the rest and were set aside. {} measured overlap(s) disagree \
                 with the solved ring by over three times the robust kernel's bound: {}",
                outliers.len(),
                outliers.join(", ")
            ),
        );
    }
    if let Some(partial) = assessment.reasons.iter().find(|r| r.code == ReasonCode::PartialCoverage) {
        let (seen_deg, within_deg) = (partial.value.unwrap_or(0.0), partial.limit.unwrap_or(0.0));
        let at = if seen_deg <= 0.0 { QualityStatus::Insufficient } else { QualityStatus::Degraded };
        flag(
            at,
            QualityCode::PartialCoverage,
            format!(
                "Only {:.0}% of the thread crest within Lc was imaged; the unseen crests could be black. The views \
                 showed {seen_deg:.0}° of the {within_deg:.0}° of crest within Lc: the verdict holds for the crests \
                 seen",
                100.0 * seen_deg / within_deg.max(1e-9)
            ),
        );
    }
    Quality { status, reasons }
}

fn status_word(status: PairStatus) -> &'static str {
    match status {
        PairStatus::Measured => "measured",
        PairStatus::Outlier => "outlier",
        PairStatus::TooWeak => "too weak (too little texture to trust the correlation)",
        PairStatus::Ambiguous => "ambiguous (a second alignment correlates nearly as well)",
        PairStatus::TooSmall => "too small (the aligned overlap is under the minimum)",
        PairStatus::NoData => "no data (a view has no trusted point in the overlap)",
        PairStatus::Implausible => {
            "implausible (solved with it, a view moved further from its encoder pose than the encoders can err)"
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::frame::{FrameEntry, FrameFormat};
    use crate::domain::optics::ViewPose;
    use crate::domain::rules::{ArcRule, RuleInput, assess as assess_rules};
    use crate::domain::thread::Family;
    use crate::pipeline::register::PairCandidate;

    fn views(n: usize) -> Vec<View> {
        (0..n)
            .map(|v| View {
                id: format!("v{v:02}"),
                pose: ViewPose { angle_deg: 8.0 * v as f64, axial_mm: 0.0, lens_radius_mm: 250.0 },
                frames: vec![FrameEntry { file: "0.png".into(), offset_mm: 0.0 }],
                format: FrameFormat { width: 4, height: 4, channels: 1, bit_depth: 8 },
            })
            .collect()
    }

    /// The suites' station: inside the measured envelope.
    fn standard() -> Station {
        Station {
            projection: crate::domain::optics::Projection::Perspective,
            object_pixel_mm: 0.0408,
            depth_of_field_mm: 0.503,
            frame_step_mm: 0.25,
            frame_step_dof: 0.497,
            frames_per_view: 20,
            views: 45,
            axial_rows: 1,
            view_spacing_deg: Some(8.0),
            overlap_deg: Some(5.09),
            frame_noise_percent: Some(0.84),
            class: None,
            qualified_by: None,
        }
    }

    /// A surface the helix fits as on the standard preset (175 µm on a 1.575 mm thread).
    fn fit() -> SurfaceFit {
        SurfaceFit {
            helix_fit_rms_um: 175.0,
            thread_height_mm: 1.575,
            depth_coverage: 0.9,
            phase_sectors: 12,
            phase_unknown: false,
            qualified_helix_fit_rms_um: None,
        }
    }

    #[test]
    fn a_qualified_station_judges_the_helix_fit_against_its_study() {
        use PairStatus::*;
        let all = registration(&[(0, 1, Measured), (1, 2, Measured), (2, 3, Measured)], 4);
        let as_studied = SurfaceFit { helix_fit_rms_um: 300.0, qualified_helix_fit_rms_um: Some(290.0), ..fit() };
        assert!(assess(&standard(), &all, &views(4), &covered(), &as_studied).reasons.is_empty());
        let worse = SurfaceFit { helix_fit_rms_um: 400.0, ..as_studied };
        let q = assess(&standard(), &all, &views(4), &covered(), &worse);
        assert_eq!(q.reasons[0].code, QualityCode::HelixResidualLarge);
        assert!(q.reasons[0].message.contains("290 µm the study's runs reached"), "{}", q.reasons[0].message);
    }

    #[test]
    fn a_poor_helix_fit_and_little_depth_are_each_named() {
        use PairStatus::*;
        let all = registration(&[(0, 1, Measured), (1, 2, Measured), (2, 3, Measured)], 4);
        let poor = SurfaceFit { helix_fit_rms_um: 460.0, ..fit() };
        let q = assess(&standard(), &all, &views(4), &covered(), &poor);
        assert_eq!((q.status, q.reasons.len()), (QualityStatus::Degraded, 1));
        assert_eq!(q.reasons[0].code, QualityCode::HelixResidualLarge);
        assert!(q.reasons[0].message.contains("460 µm RMS"), "{}", q.reasons[0].message);
        let sparse = SurfaceFit { depth_coverage: 0.3, ..fit() };
        let q = assess(&standard(), &all, &views(4), &covered(), &sparse);
        assert_eq!(q.reasons[0].code, QualityCode::DepthCoverageLow);
        assert!(q.reasons[0].message.contains("30%"), "{}", q.reasons[0].message);
        // A phase read on one sector, with a residual that does not bound it: insufficient.
        let lost = SurfaceFit { phase_sectors: 1, phase_unknown: true, ..fit() };
        let q = assess(&standard(), &all, &views(4), &covered(), &lost);
        assert_eq!((q.status, q.reasons[0].code), (QualityStatus::Insufficient, QualityCode::HelixPhaseUnknown));
        assert!(q.reasons[0].message.contains("on 1 sector of"), "{}", q.reasons[0].message);
        assert!(q.needs_review());
    }

    fn covered() -> Assessment {
        let input = RuleInput {
            family: Family::Buttress,
            lc_mm: 50.0,
            circumference_mm: 359.0,
            nominal_height_mm: 1.575,
            height_tolerance_mm: 0.05,
            threads: vec![],
        };
        assess_rules(&input, ArcRule::PerThread)
    }

    fn registration(statuses: &[(usize, usize, PairStatus)], views: usize) -> Registration {
        let candidates: Vec<PairCandidate> = statuses
            .iter()
            .map(|&(a, b, status)| PairCandidate {
                a,
                b,
                status,
                peak_ncc: Some(0.04),
                rival_ratio: Some(0.03),
                overlap_cells: Some(9000),
                radius_shift_um: None,
            })
            .collect();
        let measured: Vec<&PairCandidate> =
            candidates.iter().filter(|c| matches!(c.status, PairStatus::Measured | PairStatus::Outlier)).collect();
        Registration {
            corrections: vec![Default::default(); views],
            pairs: vec![],
            pairs_expected: candidates.len(),
            pairs_measured: measured.len(),
            unregistered_views: (0..views).filter(|&v| !measured.iter().any(|c| c.a == v || c.b == v)).collect(),
            closure: None,
            placed_radially: vec![],
            placed_by_end_face: vec![],
            end_face_implausible: vec![],
            candidates,
        }
    }

    #[test]
    fn a_fully_measured_ring_is_ok_and_every_unmeasured_overlap_is_named() {
        use PairStatus::*;
        let all = registration(&[(0, 1, Measured), (1, 2, Measured), (2, 3, Measured)], 4);
        assert_eq!(assess(&standard(), &all, &views(4), &covered(), &fit()).status, QualityStatus::Ok);

        let weak = registration(&[(0, 1, Measured), (1, 2, TooWeak), (2, 3, TooWeak)], 4);
        let q = assess(&standard(), &weak, &views(4), &covered(), &fit());
        assert!(q.needs_review());
        let incomplete = q.reasons.iter().find(|r| r.code == QualityCode::RegistrationIncomplete).unwrap();
        assert!(incomplete.message.contains("1 of 3 overlaps"), "{}", incomplete.message);
        assert!(incomplete.message.contains("v01–v02: too weak") && incomplete.message.contains("peak NCC 0.040"));
        // Views v02 and v03 had nothing measured: half the views, so the result is insufficient.
        let unplaced = q.reasons.iter().find(|r| r.code == QualityCode::ViewsUnregistered).unwrap();
        assert!(unplaced.message.contains("v02, v03"), "{}", unplaced.message);
        assert_eq!(q.status, QualityStatus::Insufficient);
        // The end face placed v02; v03's corner asked for a move beyond the encoders' bound.
        let mut anchored = weak.clone();
        anchored.placed_by_end_face = vec![2];
        anchored.end_face_implausible = vec![3];
        // The overlaps' radius placed both radially (and v01, which a measured pair holds).
        anchored.placed_radially = vec![1, 2, 3];
        let q = assess(&standard(), &anchored, &views(4), &covered(), &fit());
        let unplaced = q.reasons.iter().find(|r| r.code == QualityCode::ViewsUnregistered).unwrap();
        assert!(unplaced.message.contains("placed 1 of them axially on their own: v02"), "{}", unplaced.message);
        assert!(unplaced.message.contains("taken as misread: v03"), "{}", unplaced.message);
        assert!(
            unplaced.message.contains("placed 2 of them radially (lens radius only): v02, v03"),
            "{}",
            unplaced.message
        );
        // Placed radially, they are still unregistered in angle and along the axis.
        assert_eq!(q.status, QualityStatus::Insufficient);
    }

    #[test]
    fn outliers_and_views_that_do_not_overlap_are_reported() {
        let outlier = registration(&[(0, 1, PairStatus::Measured), (1, 2, PairStatus::Outlier)], 3);
        let q = assess(&standard(), &outlier, &views(3), &covered(), &fit());
        assert_eq!(q.status, QualityStatus::Degraded);
        assert_eq!(q.reasons.iter().map(|r| r.code).collect::<Vec<_>>(), [QualityCode::RegistrationOutliers]);
        let apart = registration(&[], 3);
        assert_eq!(assess(&standard(), &apart, &views(3), &covered(), &fit()).reasons[0].code, QualityCode::NoOverlaps);
        // One view alone has nothing to register.
        assert_eq!(assess(&standard(), &registration(&[], 1), &views(1), &covered(), &fit()).status, QualityStatus::Ok);
    }

    #[test]
    fn a_station_outside_the_measured_envelope_is_named_and_needs_review() {
        use PairStatus::*;
        let all = registration(&[(0, 1, Measured), (1, 2, Measured), (2, 3, Measured)], 4);
        let coarse =
            Station { object_pixel_mm: 0.12, depth_of_field_mm: 0.48, ..standard() }.with_frame_noise(Some(0.84));
        let q = assess(&coarse, &all, &views(4), &covered(), &fit());
        assert_eq!(q.status, QualityStatus::Degraded);
        assert_eq!(q.reasons.len(), 1);
        assert_eq!(q.reasons[0].code, QualityCode::StationUnmeasured);
        assert!(
            q.reasons[0].message.contains("object pixel 0.120 mm (measured: 0.037–0.045 mm)"),
            "{}",
            q.reasons[0].message
        );
        assert!(!q.reasons[0].message.contains("depth of field"), "{}", q.reasons[0].message);
        assert!(q.reasons[0].message.contains("in the coarse station class"), "{}", q.reasons[0].message);
        let wide = Station { depth_of_field_mm: 2.5, ..coarse }.with_frame_noise(Some(0.84));
        let q = assess(&wide, &all, &views(4), &covered(), &fit());
        assert!(q.reasons[0].message.contains("in no station class"), "{}", q.reasons[0].message);
    }
}
