//! The inspection report: the truth file's fields with the same names and meanings
//! (docs/bundle.md, "Result shape"), plus measures, timings and diagnostics.

use crate::domain::frame::View;
use crate::domain::optics::Optics;
use crate::domain::part::Part;
use crate::domain::rules::{Assessment, Verdict};
use crate::domain::station::Station;
use crate::domain::thread::Family;
use crate::pipeline::PipelineOptions;
use crate::pipeline::crest::CrestCone;
use crate::pipeline::profile::{Helix, ThreadMeasure, UnmeasuredCount};
use crate::pipeline::quality::Quality;
use crate::pipeline::register::{EndFace, Registration};
use crate::pipeline::uncertainty::{self, Decision, DecisionFinding, HeightFinding, UncertaintyBudget};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct HeightSeries {
    /// The centre of each 1° bin around the pipe, degrees (0.5, 1.5, …, 359.5).
    pub angles_deg: Vec<f64>,
    /// null where the views did not cover the bin.
    pub values: Vec<Option<f64>>,
    /// The expanded uncertainty (k = 2) of each value, mm; null where the value is (reports
    /// stored before it was computed have none).
    #[serde(default)]
    pub uncertainty_mm: Vec<Option<f64>>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadReport {
    /// The thread's number, 1 nearest the pipe end (the contract's numbering).
    pub index: u32,
    /// The thread's height per 1° bin around the pipe, mm, with each value's uncertainty.
    pub height_mm: HeightSeries,
    /// Arcs of black crest, [start, end] degrees around the pipe.
    pub black_crest_arcs_deg: Vec<[f64; 2]>,
    /// The black crest's length along the helix within Lc, mm (what API 5B limits).
    pub black_crest_length_mm: f64,
    // Extras.
    /// Where the thread's crest runs along the pipe axis, [first, last] mm from the end face over
    /// its turn.
    pub crest_z_mm: [f64; 2],
    /// The smallest measured height over the bins, mm; null when no bin was measured.
    pub min_height_mm: Option<f64>,
    /// The mean of the measured bins' heights, mm; null when none was.
    pub mean_height_mm: Option<f64>,
    /// The largest measured height, mm; null when no bin was measured.
    pub max_height_mm: Option<f64>,
    /// How many of the 360 bins have a height.
    pub bins_measured: usize,
    /// The bins without a height, counted by why (the window that gave no level and what it
    /// lacked; docs/pipeline.md, 5. Thread profile); reasons with no bin left out. Empty in
    /// reports stored before reasons were kept.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub unmeasured_bins: Vec<UnmeasuredCount>,
    /// The thread's height judged against nominal ± tolerance with its uncertainty: the mean over
    /// its crests within Lc that are neither black nor the chamfer, and that mean's expanded
    /// uncertainty (absent in reports stored before it was judged).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_finding: Option<ThreadHeightFinding>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadHeightFinding {
    /// The height against nominal ± tolerance, judged with the mean's uncertainty (ISO 14253-1).
    pub finding: HeightFinding,
    /// The mean height over the thread's machined crests within Lc, mm.
    pub mean_height_mm: Option<f64>,
    /// That mean's expanded uncertainty (k = 2), mm.
    pub uncertainty_mm: Option<f64>,
    /// Bins the mean is over.
    pub bins: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StageTiming {
    /// The pipeline stage (depth, register, fuse, mesh, profile, crest_and_rules), or a part of one
    /// (profile_correction, depth_cnn).
    pub stage: String,
    /// Its wall-clock time, seconds.
    pub seconds: f64,
}

/// The profile-correction MLP's part of the profile stage's time (a timing of its own, counted
/// inside `profile`).
pub const PROFILE_CORRECTION: &str = "profile_correction";

/// The depth U-Nets' share of the depth stage (`depth.method: cnn`).
pub const DEPTH_CNN: &str = "depth_cnn";

impl StageTiming {
    /// Whether this timing is part of another's (not to be added to the total).
    pub fn is_part(&self) -> bool {
        self.stage == PROFILE_CORRECTION || self.stage == DEPTH_CNN
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Report {
    /// The API 5B connection designation (`BC 4-1/2`); null for a custom thread form.
    pub connection: Option<String>,
    /// The thread form's family: round or buttress.
    pub family: Family,
    /// The pipe's outside diameter, mm.
    pub pipe_od_mm: f64,
    /// Lc, the length from the pipe end within which black crests are limited, mm.
    pub lc_mm: f64,
    /// The pipe's circumference, mm (25% of it is the buttress rule's limit on a black crest).
    pub circumference_mm: f64,
    /// The thread pitch, mm (nominal).
    pub pitch_mm: f64,
    /// The nominal thread height, mm.
    pub nominal_height_mm: f64,
    /// Per thread: heights around the pipe, black crests, and the height's finding.
    pub threads: Vec<ThreadReport>,
    /// The API 5B verdict on the measured values as they are (accept / reject).
    pub verdict: Verdict,
    /// Why the verdict is what it is, in words (the rules' reasons).
    pub reasons: Vec<String>,
    /// How far the result can be trusted: what was not measured, or measured poorly.
    #[serde(default = "Quality::not_assessed")]
    pub quality: Quality,
    /// The decision per ISO 14253-1: whether the verdict holds with every measured value moved by
    /// its uncertainty (`indeterminate` in reports stored before it was made).
    #[serde(default = "indeterminate")]
    pub decision: Decision,
    /// How the decision was reached: the verdict at each end of the uncertainty, and why it is
    /// indeterminate where it is.
    #[serde(default)]
    pub decision_finding: Option<DecisionFinding>,
    /// True when the quality is not ok or the decision indeterminate: a person should look before
    /// the verdict is acted on.
    #[serde(default = "yes")]
    pub review_required: bool,
    /// The components of the heights' uncertainty.
    #[serde(default)]
    pub uncertainty: Option<UncertaintyBudget>,
    /// The station the bundle was recorded at, from its optics and views (absent in reports
    /// stored before it was recorded).
    #[serde(default)]
    pub station: Option<Station>,
    /// The named station's qualification (ISO 15530-3): the study applied, its correction per
    /// thread with the heights before and after it, the station's uncertainty; or why it was
    /// not applied. Absent where the inspection named no qualified station.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub qualification: Option<crate::pipeline::qualify::QualificationUse>,
    /// Whether the profile-correction model ran and why: what its card measured for this family
    /// of threads at this object pixel, and the change it made per thread. Absent where the
    /// correction was off, and in reports stored before the choice was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile_correction: Option<crate::pipeline::profile::CorrectionChoice>,
    /// What made this report: the software, the settings, and (in the service) the inspection and
    /// its bundle (absent in reports stored before it was recorded).
    #[serde(default)]
    pub provenance: Option<Provenance>,
    // Extras.
    /// The part's serial number, from the bundle's manifest.
    pub serial: Option<String>,
    /// The thread-height tolerance, ± mm.
    pub height_tolerance_mm: f64,
    /// The API 5B rules' assessment in full: the black threads, the limits, the reasons by code.
    pub assessment: Assessment,
    /// The helix fitted to the surface: its pitch and how well it fits.
    pub helix: Helix,
    /// How the views were aligned: each overlap's status and measure, the corrections, the ring's
    /// closure.
    pub registration: Registration,
    /// The end face's silhouette, when the views showed it: the ring's axial offset it found and
    /// took out of every pose (registration cannot observe it).
    #[serde(default)]
    pub end_face: Option<EndFace>,
    /// The share (0–1) of the frames' pixels whose depth from focus was trusted.
    pub depth_coverage: f64,
    /// Every thread's unmeasured bins counted by why, summed over the threads.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub unmeasured_bins: Vec<UnmeasuredCount>,
    /// How many views' focus measure took the noise pre-filter (docs/pipeline.md, 1. Depth from
    /// focus; the frames' noise is the station's `frame_noise_percent`).
    #[serde(default)]
    pub depth_prefiltered_views: usize,
    /// The share (0–1) of the unrolled surface's cells (z along the inspected length × θ around
    /// the pipe) that the fused views filled.
    pub map_coverage: f64,
    /// The share of fused cells dropped as implausible: more than a thread height from their
    /// bin's mean line, so no surface of the form (docs/pipeline.md, 4. Fusion and the mesh). Absent in reports
    /// written before the gate existed.
    #[serde(default)]
    pub map_implausible_share: f64,
    /// The machined crests' brightness (0–1 grey) that a dark, black crest is told from.
    pub machined_crest_gray: f32,
    /// The machined crest cone the geometric black-crest test measured crests against.
    pub crest_cone: Option<CrestCone>,
    /// Each stage's wall-clock time.
    pub timings: Vec<StageTiming>,
    /// Peak resident memory of the process (Linux VmHWM), when known.
    pub peak_memory_mb: Option<f64>,
}

impl Report {
    /// A short human summary: verdict, the reasons, thread height statistics.
    pub fn summary(&self) -> String {
        let heights: Vec<f64> =
            self.threads.iter().flat_map(|t| t.height_mm.values.iter().flatten().copied()).collect();
        let full: Vec<f64> = heights
            .iter()
            .copied()
            .filter(|h| (h - self.nominal_height_mm).abs() <= self.height_tolerance_mm)
            .collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let mut out = format!(
            "{} {}: {}\n",
            self.serial.as_deref().unwrap_or("(no serial)"),
            self.connection.as_deref().unwrap_or("custom thread"),
            self.verdict.as_str().to_uppercase()
        );
        for r in &self.reasons {
            out.push_str(&format!("  {r}\n"));
        }
        out.push_str(&format!(
            "  decision (ISO 14253-1): {}{}\n",
            self.decision.as_str(),
            self.uncertainty
                .as_ref()
                .and_then(|u| u.expanded_median_um)
                .map_or(String::new(), |u| format!("; heights ± {u:.1} µm (median U, k = 2)"))
        ));
        if self.review_required {
            out.push_str("  REVIEW REQUIRED: this result needs a person's review before its verdict is acted on:\n");
            for r in &self.quality.reasons {
                out.push_str(&format!("    - {}\n", r.message));
            }
            for r in self.decision_finding.iter().flat_map(|d| &d.reasons) {
                out.push_str(&format!("    - {r}\n"));
            }
        }
        let registration = &self.registration;
        if registration.pairs_expected > 0 {
            out.push_str(&format!(
                "  registration: {} of {} overlaps measured{}\n",
                registration.pairs_measured,
                registration.pairs_expected,
                registration.closure.map_or(String::new(), |c| format!(
                    "; ring closure {:.4}° / {:.1} µm over {} views",
                    c.angle_deg, c.axial_um, c.views
                ))
            ));
        }
        out.push_str(&format!(
            "  {} threads, {} height bins; full crests {:.4} mm mean (nominal {:.4} ± {:.4}); helix z_h {:.3} mm\n",
            self.threads.len(),
            heights.len(),
            mean(&full),
            self.nominal_height_mm,
            self.height_tolerance_mm,
            self.helix.z_h_mm
        ));
        if !self.unmeasured_bins.is_empty() {
            let reasons: Vec<String> =
                self.unmeasured_bins.iter().map(|c| format!("{} {}", c.reason.as_str(), c.bins)).collect();
            out.push_str(&format!("  bins without a height, by why: {}\n", reasons.join(", ")));
        }
        match &self.end_face {
            Some(end) => out.push_str(&format!(
                "  z from the end face: the ring's axial offset {:+.1} µm taken out ({} views, scatter {:.1} µm)\n",
                1e3 * end.z_offset_mm,
                end.views,
                end.scatter_um
            )),
            None => out.push_str("  z from the encoders (no end face in view)\n"),
        }
        for m in self.provenance.iter().flat_map(|p| &p.models) {
            let what = match m.role {
                crate::learned::ModelRole::ProfileCorrection => "heights corrected by the profile_correction model",
                crate::learned::ModelRole::Depth => "depth from the depth model",
            };
            out.push_str(&format!("  {what} {} (sha256 {})\n", m.name, m.sha256));
        }
        // The mesh and the profile run at the same time: together they take the longer of the two.
        let seconds_of = |stage: &str| self.timings.iter().find(|t| t.stage == stage).map(|t| t.seconds);
        let overlap = match (seconds_of("mesh"), seconds_of("profile")) {
            (Some(mesh), Some(profile)) => mesh.min(profile),
            _ => 0.0,
        };
        let total: f64 = self.timings.iter().filter(|t| !t.is_part()).map(|t| t.seconds).sum::<f64>() - overlap;
        let stages: Vec<String> = self
            .timings
            .iter()
            .map(|t| match t.stage.as_str() {
                "profile" if overlap > 0.0 => format!("beside it profile {:.2}", t.seconds),
                PROFILE_CORRECTION => format!("of it the MLP {:.2}", t.seconds),
                DEPTH_CNN => format!("of it the U-Nets {:.2}", t.seconds),
                _ => format!("{} {:.2}", t.stage, t.seconds),
            })
            .collect();
        out.push_str(&format!(
            "  {:.2} s ({}){}",
            total,
            stages.join(", "),
            self.peak_memory_mb.map(|m| format!("; peak memory {m:.0} MB")).unwrap_or_default()
        ));
        out
    }
}

fn yes() -> bool {
    true
}

fn indeterminate() -> Decision {
    Decision::Indeterminate
}

/// What made a report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Provenance {
    /// crestscan's version.
    pub software_version: String,
    /// Every option the pipeline ran with, defaults filled in (the shape of `POST
    /// /v1/inspections`'s `pipeline` option).
    #[schema(value_type = Object)]
    pub settings: PipelineOptions,
    /// Set by the service: the inspection's id and the sha256 of its uploaded bundle.
    pub inspection_id: Option<String>,
    /// The sha256 of the uploaded bundle (set by the service).
    pub bundle_sha256: Option<String>,
    /// The learned models that changed this report, by sha256 (none: the classical pipeline).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub models: Vec<crate::learned::ModelUse>,
}

/// What the stages found, from which the report is assembled.
pub struct Findings<'a> {
    pub part: &'a Part,
    pub options: &'a PipelineOptions,
    pub optics: &'a Optics,
    pub views: &'a [View],
    pub station: Station,
    pub quality: Quality,
    pub uncertainty: UncertaintyBudget,
    /// Each thread's mean height's expanded uncertainty, by thread index.
    pub thread_mean_uncertainty_mm: Vec<(u32, Option<f64>)>,
    pub decision: DecisionFinding,
    pub helix: Helix,
    pub threads: &'a [ThreadMeasure],
    pub assessment: Assessment,
    pub machined_crest_gray: f32,
    pub crest_cone: Option<CrestCone>,
    pub registration: Registration,
    pub end_face: Option<EndFace>,
    pub depth_coverage: f64,
    pub depth_prefiltered_views: usize,
    pub map_coverage: f64,
    pub map_implausible_share: f64,
    pub models: Vec<crate::learned::ModelUse>,
    pub timings: Vec<StageTiming>,
    pub qualification: Option<crate::pipeline::qualify::QualificationUse>,
    pub profile_correction: Option<crate::pipeline::profile::CorrectionChoice>,
}

impl Report {
    /// The report of a run: the part's fields, each thread's heights and black crests, the verdict
    /// with its reasons, and the stages' measures.
    pub fn assemble(f: Findings) -> Self {
        let (part, helix) = (f.part, &f.helix);
        let form = &part.form;
        let threads = f
            .threads
            .iter()
            .map(|t| {
                let values: Vec<Option<f64>> = t.bins.iter().map(|b| b.height_mm).collect();
                let measured: Vec<f64> = values.iter().flatten().copied().collect();
                let black = f.assessment.black_threads.iter().find(|b| b.index == t.index);
                let height_finding = judge_thread(t, black.map(|b| b.arcs_deg.as_slice()).unwrap_or(&[]), &f);
                ThreadReport {
                    index: t.index,
                    height_mm: HeightSeries {
                        angles_deg: t.bins.iter().map(|b| b.angle_deg).collect(),
                        values,
                        uncertainty_mm: t.bins.iter().map(|b| b.height_mm.and(b.uncertainty_mm)).collect(),
                    },
                    black_crest_arcs_deg: black.map(|b| b.arcs_deg.clone()).unwrap_or_default(),
                    black_crest_length_mm: black.map_or(0.0, |b| b.length_mm),
                    crest_z_mm: [
                        t.bins[0].crest_z_mm - 0.5 * helix.pitch_mm / 360.0,
                        t.bins[359].crest_z_mm + 0.5 * helix.pitch_mm / 360.0,
                    ],
                    min_height_mm: measured.iter().copied().reduce(f64::min),
                    mean_height_mm: (!measured.is_empty())
                        .then(|| measured.iter().sum::<f64>() / measured.len() as f64),
                    max_height_mm: measured.iter().copied().reduce(f64::max),
                    bins_measured: measured.len(),
                    unmeasured_bins: crate::pipeline::profile::count_unmeasured(&t.bins),
                    height_finding: Some(height_finding),
                }
            })
            .collect();
        let station = f.station;
        let quality = f.quality;
        let decision = f.decision.decision;
        Report {
            connection: part.connection.clone(),
            family: part.family(),
            pipe_od_mm: part.pipe_od_mm,
            lc_mm: part.lc_mm,
            circumference_mm: part.circumference_mm(),
            pitch_mm: form.pitch_mm,
            nominal_height_mm: form.height_mm,
            threads,
            verdict: f.assessment.verdict,
            reasons: f.assessment.messages(),
            review_required: quality.needs_review() || decision == Decision::Indeterminate,
            quality,
            decision,
            decision_finding: Some(f.decision),
            uncertainty: Some(f.uncertainty),
            station: Some(station),
            qualification: f.qualification,
            profile_correction: f.profile_correction,
            provenance: Some(Provenance {
                software_version: env!("CARGO_PKG_VERSION").into(),
                settings: f.options.clone(),
                inspection_id: None,
                bundle_sha256: None,
                models: f.models,
            }),
            serial: part.serial.clone(),
            height_tolerance_mm: form.height_tolerance_mm,
            assessment: f.assessment,
            helix: f.helix,
            registration: f.registration,
            end_face: f.end_face,
            depth_coverage: f.depth_coverage,
            unmeasured_bins: crate::pipeline::profile::count_unmeasured(f.threads.iter().flat_map(|t| &t.bins)),
            depth_prefiltered_views: f.depth_prefiltered_views,
            map_coverage: f.map_coverage,
            map_implausible_share: f.map_implausible_share,
            machined_crest_gray: f.machined_crest_gray,
            crest_cone: f.crest_cone,
            timings: f.timings,
            peak_memory_mb: peak_memory_mb(),
        }
    }
}

/// Fewest bins a thread's height is judged over: a few degrees of crest say little of a thread.
const MIN_JUDGED_BINS: usize = 30;

/// A thread's height against nominal ± tolerance: the mean over its measured bins within Lc that
/// are neither black nor the chamfer zone's (1.5 pitches from the end face), with that mean's
/// uncertainty (the thread's, scaled to the bins it is over).
fn judge_thread(t: &ThreadMeasure, black_arcs: &[[f64; 2]], f: &Findings) -> ThreadHeightFinding {
    let (lc, chamfer_zone) = (f.part.lc_mm, 1.5 * f.part.form.pitch_mm);
    let judged: Vec<f64> = t
        .bins
        .iter()
        .filter(|b| b.crest_z_mm <= lc && b.crest_z_mm >= chamfer_zone)
        .filter(|b| !black_arcs.iter().any(|a| a[0] <= b.angle_deg && b.angle_deg <= a[1]))
        .filter_map(|b| b.height_mm)
        .collect();
    let measured = t.bins.iter().filter(|b| b.height_mm.is_some()).count();
    let u_all = f.thread_mean_uncertainty_mm.iter().find(|(i, _)| *i == t.index).and_then(|(_, u)| *u);
    if judged.len() < MIN_JUDGED_BINS {
        return ThreadHeightFinding {
            finding: HeightFinding::NotJudged,
            mean_height_mm: None,
            uncertainty_mm: None,
            bins: judged.len(),
        };
    }
    let mean = judged.iter().sum::<f64>() / judged.len() as f64;
    // The noise part of the thread's uncertainty grows as the bins it averages shrink; the
    // systematic parts do not shrink with more bins, so scaling the whole by √(measured/judged)
    // is an upper bound.
    let u = u_all.map(|u| u * (measured as f64 / judged.len() as f64).sqrt());
    let form = &f.part.form;
    ThreadHeightFinding {
        finding: uncertainty::judge_height(Some(mean), u, form.height_mm, form.height_tolerance_mm),
        mean_height_mm: Some(mean),
        uncertainty_mm: u,
        bins: judged.len(),
    }
}

/// Peak resident set size of this process in MB (Linux), read from /proc/self/status.
pub fn peak_memory_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
