//! A station's qualification study (ISO 15530-3) over repeated inspections of calibrated masters:
//! the heights' error against each master's certificate, the correction model chosen by its
//! held-out error, the station's uncertainty components (u_cal, u_p, u_b, u_w), and the gauge
//! figures (type-1 Cg/Cgk per thread, %GRR and ndc by ANOVA). Pure: reports and certificates in,
//! a [`Qualification`] out.

use crate::domain::control::{ChartPoint, CheckStatistic, ControlLimits};
use crate::domain::qualification::{
    CandidateScore, Correction, CorrectionModel, Fingerprint, GaugeStudy, MasterSummary, ModelSelection, Qualification,
    StationUncertainty, ThreadBias, ThreadGauge,
};
use crate::eval::cmm::{CmmError, CmmMeasurements};
use crate::numeric::stats::median;
use crate::pipeline::report::Report;
use std::collections::BTreeMap;

/// The fewest runs of a master a study takes (ISO 15530-3 asks for at least 10; 20 or more is
/// usual: 25 is the service's default suggestion).
pub const MIN_RUNS: usize = 10;

/// A master's calibration certificate: CMM measurements of its thread heights that state their
/// instrument, date and expanded uncertainty, in the CMM formats `PUT …/cmm` takes.
#[derive(Clone, Debug, PartialEq)]
pub struct Certificate {
    pub points: CmmMeasurements,
    pub instrument: String,
    pub calibrated_at: String,
    /// The largest expanded uncertainty (k = 2) its points state, mm.
    pub expanded_uncertainty_mm: f64,
}

impl Certificate {
    /// A certificate from CMM JSON (a body starting with `{`) or CSV; it must state its
    /// instrument, its date (`measured_at`) and an uncertainty for every point.
    pub fn parse(bytes: &[u8]) -> Result<Self, CmmError> {
        let json = bytes.iter().find(|b| !b.is_ascii_whitespace()) == Some(&b'{');
        if json { Self::from_json(bytes) } else { Self::from_csv(bytes) }
    }

    /// A certificate from CMM JSON.
    pub fn from_json(bytes: &[u8]) -> Result<Self, CmmError> {
        Self::of(CmmMeasurements::from_json(bytes)?)
    }

    /// A certificate from CMM CSV.
    pub fn from_csv(bytes: &[u8]) -> Result<Self, CmmError> {
        Self::of(CmmMeasurements::from_csv(bytes)?)
    }

    fn of(points: CmmMeasurements) -> Result<Self, CmmError> {
        let missing =
            |field: &str, what: &str| CmmError { field: field.into(), message: format!("a certificate states {what}") };
        let instrument =
            points.instrument.clone().ok_or_else(|| missing("instrument", "the instrument that calibrated it"))?;
        let calibrated_at =
            points.measured_at.clone().ok_or_else(|| missing("measured_at", "when it was calibrated"))?;
        let mut worst: f64 = 0.0;
        for (i, p) in points.points.iter().enumerate() {
            match p.uncertainty_mm {
                Some(u) => worst = worst.max(u),
                None => {
                    return Err(CmmError {
                        field: format!("points[{i}].uncertainty_mm"),
                        message: "a certificate states the expanded uncertainty (k = 2) of every height: \
                                  `uncertainty_mm` for all points or on each"
                            .into(),
                    });
                }
            }
        }
        Ok(Self { points, instrument, calibrated_at, expanded_uncertainty_mm: worst })
    }
}

/// One master's runs.
pub struct MasterRuns<'a> {
    pub serial: String,
    pub certificate: &'a Certificate,
    /// (run id, report): an inspection id, or a bundle's folder.
    pub runs: Vec<(String, &'a Report)>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StudyError {
    #[error("master {serial}: {runs} runs; a study takes at least {min} of each master")]
    TooFewRuns { serial: String, runs: usize, min: usize },
    #[error("no masters: a study takes at least one master with its runs")]
    NoMasters,
    #[error("run {run}: {detail}")]
    OtherStation { run: String, detail: String },
    #[error(
        "run {run}: its heights were corrected by a learned model; a study takes the classical heights (profile.correction off)"
    )]
    LearnedHeights { run: String },
    #[error("run {run}: it is master {serial}'s run but measures {found}, the certificate's part is {expected}")]
    OtherPart { run: String, serial: String, found: String, expected: String },
    #[error("master {serial}: certificate thread(s) {unknown} are not threads its runs measured (they have {known})")]
    UnknownThreads { serial: String, unknown: String, known: String },
    #[error("master {serial}: no certified height falls on a measured one")]
    NoOverlap { serial: String },
    #[error(
        "master {serial}: study {study} set no control limits for it (not one of its masters, or made before checks were charted): requalify with it"
    )]
    NoLimits { serial: String, study: String },
    #[error("run {run}: it does not measure the {statistic} its chart needs")]
    Unmeasured { run: String, statistic: String },
}

impl StudyError {
    /// The field or input the error is about, for a problem's culprit.
    pub fn culprit(&self) -> String {
        match self {
            Self::TooFewRuns { serial, .. }
            | Self::UnknownThreads { serial, .. }
            | Self::NoOverlap { serial }
            | Self::NoLimits { serial, .. } => {
                format!("masters.{serial}")
            }
            Self::NoMasters => "masters".into(),
            Self::OtherStation { run, .. }
            | Self::LearnedHeights { run }
            | Self::OtherPart { run, .. }
            | Self::Unmeasured { run, .. } => {
                format!("runs.{run}")
            }
        }
    }
}

/// One height's error against its certificate.
#[derive(Clone, Copy, Debug)]
struct Sample {
    master: usize,
    run: usize,
    thread: u32,
    bin: usize,
    error_mm: f64,
}

/// Runs the study. `valid_until` is stored as given.
pub fn study(
    station: &str,
    study_id: &str,
    masters: &[MasterRuns],
    coverage_factor: f64,
    valid_until: Option<String>,
) -> Result<Qualification, StudyError> {
    let first = masters.first().ok_or(StudyError::NoMasters)?;
    let (_, first_report) =
        first.runs.first().ok_or(StudyError::TooFewRuns { serial: first.serial.clone(), runs: 0, min: MIN_RUNS })?;
    let reference = first_report.station.clone().ok_or_else(|| StudyError::OtherStation {
        run: first.runs[0].0.clone(),
        detail: "the report states no station (stored before stations were recorded)".into(),
    })?;
    let fingerprint = Fingerprint::of(&reference);
    let mut samples = Vec::new();
    let mut summaries = Vec::new();
    let mut tolerance_mm: f64 = 0.0;
    for (m, master) in masters.iter().enumerate() {
        if master.runs.len() < MIN_RUNS {
            return Err(StudyError::TooFewRuns {
                serial: master.serial.clone(),
                runs: master.runs.len(),
                min: MIN_RUNS,
            });
        }
        let connection = master.runs[0].1.connection.clone();
        let certified = certified_heights(master.certificate);
        let mut measured_threads = std::collections::BTreeSet::new();
        for (r, (run, report)) in master.runs.iter().enumerate() {
            admit(&fingerprint, &master.serial, connection.as_deref(), run, report)?;
            tolerance_mm = tolerance_mm.max(report.height_tolerance_mm);
            measured_threads.extend(report.threads.iter().map(|t| t.index));
            for (thread, bin, error_mm) in errors_against(report, &certified) {
                samples.push(Sample { master: m, run: r, thread, bin, error_mm });
            }
        }
        let unknown: Vec<String> =
            certified.keys().map(|k| k.0).filter(|t| !measured_threads.contains(t)).map(|t| t.to_string()).collect();
        if !unknown.is_empty() {
            let mut unknown = unknown;
            unknown.dedup();
            return Err(StudyError::UnknownThreads {
                serial: master.serial.clone(),
                unknown: unknown.join(", "),
                known: measured_threads.iter().map(u32::to_string).collect::<Vec<_>>().join(", "),
            });
        }
        if !samples.iter().any(|s| s.master == m) {
            return Err(StudyError::NoOverlap { serial: master.serial.clone() });
        }
        summaries.push(MasterSummary {
            serial: master.serial.clone(),
            connection,
            runs: master.runs.len(),
            instrument: master.certificate.instrument.clone(),
            calibrated_at: master.certificate.calibrated_at.clone(),
            certificate_u_um: 1e3 * master.certificate.expanded_uncertainty_mm,
        });
    }

    // Held out: a master at a time where there are two or more, else a run at a time.
    let by_master = masters.len() >= 2;
    let groups: Vec<usize> =
        if by_master { (0..masters.len()).collect() } else { (0..masters[0].runs.len()).collect() };
    let held = |s: &Sample| if by_master { s.master } else { s.run };
    let candidates = [CorrectionModel::None, CorrectionModel::PerThread];
    let mut scores = Vec::new();
    for model in candidates {
        let mut squares = 0.0;
        let mut n = 0usize;
        for &g in &groups {
            let train: Vec<Sample> = samples.iter().copied().filter(|s| held(s) != g).collect();
            let correction = fit(model, &train);
            for s in samples.iter().filter(|s| held(s) == g) {
                if let Some(c) = correction.at_mm(s.thread) {
                    squares += (s.error_mm - c).powi(2);
                    n += 1;
                }
            }
        }
        scores.push(CandidateScore { model, held_out_rms_um: 1e3 * (squares / n.max(1) as f64).sqrt() });
    }
    let chosen = scores
        .iter()
        .min_by(|a, b| a.held_out_rms_um.total_cmp(&b.held_out_rms_um))
        .map(|c| c.model)
        .unwrap_or(CorrectionModel::None);
    let correction = fit(chosen, &samples);
    let rms_before_um = 1e3 * rms(samples.iter().map(|s| s.error_mm));
    let rms_after_um = scores.iter().find(|c| c.model == chosen).map_or(rms_before_um, |c| c.held_out_rms_um);

    // u_p: one height's scatter over the runs, pooled over (master, thread, bin).
    let mut cells: BTreeMap<(usize, u32, usize), Vec<f64>> = BTreeMap::new();
    for s in &samples {
        cells.entry((s.master, s.thread, s.bin)).or_default().push(s.error_mm);
    }
    let (mut pooled, mut dof) = (0.0, 0usize);
    for v in cells.values().filter(|v| v.len() >= 2) {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        pooled += v.iter().map(|e| (e - mean).powi(2)).sum::<f64>();
        dof += v.len() - 1;
    }
    let u_p_mm = if dof > 0 { (pooled / dof as f64).sqrt() } else { 0.0 };
    // u_b: each thread's bias known to its standard error over the runs, and what the model leaves
    // systematic at a bin (the bins' mean error over the runs about the correction, less the part
    // of it the runs' own scatter explains).
    let runs_min = masters.iter().map(|m| m.runs.len()).min().unwrap_or(1) as f64;
    let mut thread_se = Vec::new();
    for t in &correction.threads {
        thread_se.push(1e-3 * t.u_um);
    }
    let se_mm = rms(thread_se.into_iter());
    let residual_mm = rms(cells.iter().filter_map(|((_, thread, _), v)| {
        let c = correction.at_mm(*thread)?;
        Some(v.iter().sum::<f64>() / v.len() as f64 - c)
    }));
    let systematic_mm = (residual_mm.powi(2) - u_p_mm.powi(2) / runs_min).max(0.0).sqrt();
    let u_b_mm = (se_mm.powi(2) + systematic_mm.powi(2)).sqrt();
    // u_w: the correction's spread between masters (per thread, pooled), measured only with two.
    let (u_w_mm, u_w_measured) = if by_master {
        let per_master: Vec<Correction> = (0..masters.len())
            .map(|m| fit(chosen, &samples.iter().copied().filter(|s| s.master == m).collect::<Vec<_>>()))
            .collect();
        let mut spreads = Vec::new();
        for t in &correction.threads {
            let values: Vec<f64> = per_master
                .iter()
                .filter_map(|c| c.threads.iter().find(|x| x.thread == t.thread))
                .map(|x| 1e-3 * x.bias_um)
                .collect();
            if values.len() >= 2 {
                let mean = values.iter().sum::<f64>() / values.len() as f64;
                spreads.push(values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (values.len() - 1) as f64);
            }
        }
        ((spreads.iter().sum::<f64>() / spreads.len().max(1) as f64).sqrt(), true)
    } else {
        (0.0, false)
    };
    let u_cal_mm = masters.iter().map(|m| m.certificate.expanded_uncertainty_mm / 2.0).fold(0.0, f64::max);
    let combined_mm = (u_cal_mm.powi(2) + u_p_mm.powi(2) + u_b_mm.powi(2) + u_w_mm.powi(2)).sqrt();
    let uncertainty = StationUncertainty {
        u_cal_um: 1e3 * u_cal_mm,
        u_p_um: 1e3 * u_p_mm,
        u_b_um: 1e3 * u_b_mm,
        u_w_um: 1e3 * u_w_mm,
        u_w_measured,
        combined_um: 1e3 * combined_mm,
        coverage_factor,
        expanded_um: 1e3 * coverage_factor * combined_mm,
    };
    let without = refits_without_each_run(chosen, &samples);
    let gauge = gauge_study(masters, &samples, &without, 2.0 * tolerance_mm);
    let control = control_limits(&fingerprint, masters, &samples, &without);
    Ok(Qualification {
        station: station.to_string(),
        study: study_id.to_string(),
        fingerprint,
        masters: summaries,
        correction,
        uncertainty,
        gauge,
        selection: ModelSelection {
            method: if by_master { "leave_one_master_out" } else { "leave_one_run_out" }.into(),
            candidates: scores,
        },
        rms_before_um,
        rms_after_um,
        helix_fit_rms_max_um: masters
            .iter()
            .flat_map(|m| m.runs.iter().map(|(_, r)| r.helix.fit_rms_um))
            .fold(0.0, f64::max),
        noise_median_um: median(
            &mut masters
                .iter()
                .flat_map(|m| m.runs.iter().filter_map(|(_, r)| r.uncertainty.as_ref()?.noise_median_um))
                .collect::<Vec<_>>(),
        ),
        control,
        valid_until,
    })
}

/// The certificate's heights by (thread, 1° bin); a point without an angle (a thread's mean) is
/// not a bin's.
fn certified_heights(certificate: &Certificate) -> BTreeMap<(u32, i64), f64> {
    certificate.points.points.iter().filter_map(|p| Some(((p.thread, bin_of(p.angle_deg?)), p.height_mm))).collect()
}

/// The 1° bin an angle falls in.
/// Whether `report` may be a run of master `serial` at the station `fingerprint` binds: recorded
/// there, its heights classical, of the master's form.
fn admit(
    fingerprint: &Fingerprint,
    serial: &str,
    connection: Option<&str>,
    run: &str,
    report: &Report,
) -> Result<(), StudyError> {
    let station = report
        .station
        .as_ref()
        .ok_or_else(|| StudyError::OtherStation { run: run.into(), detail: "the report states no station".into() })?;
    let mismatches = fingerprint.mismatches(station);
    if !mismatches.is_empty() {
        return Err(StudyError::OtherStation { run: run.into(), detail: mismatches.join("; ") });
    }
    if report.provenance.iter().flat_map(|p| &p.models).any(|m| m.role == crate::learned::ModelRole::ProfileCorrection)
    {
        return Err(StudyError::LearnedHeights { run: run.into() });
    }
    if report.connection.as_deref() != connection {
        let name = |c: Option<&str>| c.map_or_else(|| "a custom form".into(), str::to_string);
        return Err(StudyError::OtherPart {
            run: run.into(),
            serial: serial.into(),
            found: name(report.connection.as_deref()),
            expected: name(connection),
        });
    }
    Ok(())
}

/// A report's heights against a certificate, as (thread, bin, error in mm), each height as the
/// station measured it: before any station correction the inspection applied, so that a study or
/// a check reads the station's own error whichever qualification was in force when the run was
/// inspected (the per-thread correction is one value per thread, which the report states).
fn errors_against(report: &Report, certified: &BTreeMap<(u32, i64), f64>) -> Vec<(u32, usize, f64)> {
    let applied = report.qualification.as_ref().filter(|q| q.applied);
    let mut out = Vec::new();
    for t in &report.threads {
        let undo_mm = applied
            .and_then(|q| q.threads.iter().find(|u| u.thread == t.index))
            .map_or(0.0, |u| 1e-3 * u.correction_um);
        for (bin, (angle, value)) in t.height_mm.angles_deg.iter().zip(&t.height_mm.values).enumerate() {
            let (Some(h), Some(c)) = (value, certified.get(&(t.index, bin_of(*angle)))) else { continue };
            out.push((t.index, bin, h + undo_mm - c));
        }
    }
    out
}

/// A check run of master `serial` charted against the study `q`: each statistic's value and its
/// distance from the centre line in σ.
pub fn check(
    q: &Qualification,
    serial: &str,
    certificate: &Certificate,
    run: &str,
    report: &Report,
) -> Result<Vec<ChartPoint>, StudyError> {
    let limits: Vec<&ControlLimits> = q.control.iter().filter(|l| l.master == serial).collect();
    let master = q.masters.iter().find(|m| m.serial == serial);
    let (Some(master), false) = (master, limits.is_empty()) else {
        return Err(StudyError::NoLimits { serial: serial.into(), study: q.study.clone() });
    };
    admit(&q.fingerprint, serial, master.connection.as_deref(), run, report)?;
    let errors = errors_against(report, &certified_heights(certificate));
    let corrected: Vec<f64> =
        errors.iter().filter_map(|&(thread, _, e)| Some(1e3 * (e - q.correction.at_mm(thread)?))).collect();
    let mut points = Vec::new();
    for l in limits {
        let value_um = match l.statistic {
            CheckStatistic::HeightBias => median(&mut corrected.clone()),
            CheckStatistic::CrestConeRadius => report.crest_cone.as_ref().map(|c| 1e3 * c.radius_at_end_mm),
        };
        let Some(value_um) = value_um else {
            return Err(StudyError::Unmeasured { run: run.into(), statistic: l.statistic.describe().into() });
        };
        points.push(ChartPoint { statistic: l.statistic, value_um, z: l.z(value_um) });
    }
    Ok(points)
}

/// Each master's control limits: its runs' height bias (read with the correction fitted without
/// the run, as a later check run meets the correction) and, where every run found it, the crest
/// cone's radius.
fn control_limits(
    fingerprint: &Fingerprint,
    masters: &[MasterRuns],
    samples: &[Sample],
    without: &BTreeMap<(usize, usize), Correction>,
) -> Vec<ControlLimits> {
    let mut out = Vec::new();
    for (m, master) in masters.iter().enumerate() {
        let mut bias_um = Vec::new();
        for r in 0..master.runs.len() {
            let errors: Vec<f64> = samples
                .iter()
                .filter(|s| s.master == m && s.run == r)
                .filter_map(|s| Some(s.error_mm - without.get(&(m, r))?.at_mm(s.thread)?))
                .collect();
            let mut errors = errors;
            if let Some(m) = median(&mut errors) {
                bias_um.push(1e3 * m);
            }
        }
        out.extend(ControlLimits::of(&master.serial, CheckStatistic::HeightBias, &bias_um));
        let radii_um: Option<Vec<f64>> =
            master.runs.iter().map(|(_, r)| r.crest_cone.as_ref().map(|c| 1e3 * c.radius_at_end_mm)).collect();
        if let Some(mut limits) =
            radii_um.and_then(|r| ControlLimits::of(&master.serial, CheckStatistic::CrestConeRadius, &r))
        {
            // A refocus moves the surface the station sees by as much: to be worth judging, the
            // radius must show a refocus of one frame step at 3σ.
            let step_um = 1e3 * fingerprint.frame_step_mm;
            if 3.0 * limits.sigma_um > step_um {
                limits.charted = false;
                limits.not_charted_because = Some(format!(
                    "its runs scatter by {:.0} µm (σ): a refocus of one frame step ({step_um:.0} µm) would not stand out at 3σ",
                    limits.sigma_um
                ));
            }
            out.push(limits);
        }
    }
    out
}

/// The correction fitted without each run, by (master, run): fitted once per run (every thread
/// of it reads the same).
fn refits_without_each_run(model: CorrectionModel, samples: &[Sample]) -> BTreeMap<(usize, usize), Correction> {
    let mut without = BTreeMap::new();
    for s in samples {
        without.entry((s.master, s.run)).or_insert_with(|| {
            let train: Vec<Sample> =
                samples.iter().copied().filter(|x| !(x.master == s.master && x.run == s.run)).collect();
            fit(model, &train)
        });
    }
    without
}

fn bin_of(angle_deg: f64) -> i64 {
    angle_deg.rem_euclid(360.0).floor() as i64
}

fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}

/// The model fitted to `samples`: per thread, the median error (robust to a black crest's bins,
/// whose certified and measured heights may disagree at its ends), with the standard error of the
/// thread's mean error over the runs.
fn fit(model: CorrectionModel, samples: &[Sample]) -> Correction {
    if model == CorrectionModel::None {
        return Correction { model, threads: Vec::new() };
    }
    let mut by_thread: BTreeMap<u32, Vec<&Sample>> = BTreeMap::new();
    for s in samples {
        by_thread.entry(s.thread).or_default().push(s);
    }
    let threads = by_thread
        .into_iter()
        .map(|(thread, v)| {
            let mut errors: Vec<f64> = v.iter().map(|s| s.error_mm).collect();
            let bias = median(&mut errors).unwrap_or(0.0);
            let mut per_run: BTreeMap<(usize, usize), (f64, usize)> = BTreeMap::new();
            for s in &v {
                let e = per_run.entry((s.master, s.run)).or_default();
                e.0 += s.error_mm;
                e.1 += 1;
            }
            let means: Vec<f64> = per_run.values().map(|(sum, n)| sum / *n as f64).collect();
            let se = if means.len() >= 2 {
                let mean = means.iter().sum::<f64>() / means.len() as f64;
                (means.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (means.len() - 1) as f64 / means.len() as f64)
                    .sqrt()
            } else {
                0.0
            };
            ThreadBias { thread, bias_um: 1e3 * bias, u_um: 1e3 * se, samples: v.len() }
        })
        .collect();
    Correction { model, threads }
}

/// Type-1 per thread of each master (the thread's mean height per run against its certified
/// mean), and the gauge R&R by one-way ANOVA with the masters' threads as parts and the runs as
/// repeats.
fn gauge_study(
    masters: &[MasterRuns],
    samples: &[Sample],
    without: &BTreeMap<(usize, usize), Correction>,
    tolerance_mm: f64,
) -> GaugeStudy {
    let mut per: BTreeMap<(usize, u32), BTreeMap<usize, Vec<f64>>> = BTreeMap::new();
    for s in samples {
        per.entry((s.master, s.thread)).or_default().entry(s.run).or_default().push(s.error_mm);
    }
    let mut threads = Vec::new();
    // The ANOVA's parts: (master, thread) with their runs' mean errors (the certified height is
    // constant per part, so errors and readings have the same variances).
    let mut parts: Vec<Vec<f64>> = Vec::new();
    for (&(m, thread), runs) in &per {
        let means: Vec<f64> = runs.values().map(|v| v.iter().sum::<f64>() / v.len() as f64).collect();
        let n = means.len();
        let mean = means.iter().sum::<f64>() / n as f64;
        let s =
            if n >= 2 { (means.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() } else { 0.0 };
        // After the correction estimated without the run it is read on.
        let after: Vec<f64> = runs
            .keys()
            .map(|&r| {
                let c = without[&(m, r)].at_mm(thread).unwrap_or(0.0);
                runs[&r].iter().sum::<f64>() / runs[&r].len() as f64 - c
            })
            .collect();
        let bias_after = after.iter().sum::<f64>() / after.len().max(1) as f64;
        let (cg, cgk) = if s > 0.0 && tolerance_mm > 0.0 {
            (Some(0.2 * tolerance_mm / (6.0 * s)), Some((0.1 * tolerance_mm - bias_after.abs()) / (3.0 * s)))
        } else {
            (None, None)
        };
        threads.push(ThreadGauge {
            master: masters[m].serial.clone(),
            thread,
            bias_before_um: 1e3 * mean,
            bias_after_um: 1e3 * bias_after,
            repeatability_um: 1e3 * s,
            cg,
            cgk,
            runs: n,
        });
        parts.push(means);
    }
    let repeats = parts.iter().map(Vec::len).min().unwrap_or(0);
    let (grr_tol, grr_total, ndc) = anova(&parts, repeats, tolerance_mm);
    let low = |f: &dyn Fn(&ThreadGauge) -> Option<f64>| threads.iter().filter_map(f).reduce(f64::min);
    GaugeStudy {
        tolerance_um: 1e3 * tolerance_mm,
        cg_min: low(&|t| t.cg),
        cgk_min: low(&|t| t.cgk),
        threads,
        grr_percent_tolerance: grr_tol,
        grr_percent_total: grr_total,
        ndc,
        parts: parts.len(),
        repeats,
    }
}

/// One-way ANOVA over parts with `r` repeats each (the first r of each): σ²_repeat = MS_within,
/// σ²_parts = (MS_between − MS_within) / r; %GRR against the tolerance and the total variation,
/// and ndc = 1.41 σ_parts / σ_GRR. None with fewer than 2 parts × 2 repeats.
fn anova(parts: &[Vec<f64>], r: usize, tolerance_mm: f64) -> (Option<f64>, Option<f64>, Option<f64>) {
    let p = parts.len();
    if p < 2 || r < 2 {
        return (None, None, None);
    }
    let means: Vec<f64> = parts.iter().map(|v| v[..r].iter().sum::<f64>() / r as f64).collect();
    let grand = means.iter().sum::<f64>() / p as f64;
    let ss_between = r as f64 * means.iter().map(|m| (m - grand).powi(2)).sum::<f64>();
    let ss_within: f64 =
        parts.iter().zip(&means).map(|(v, m)| v[..r].iter().map(|x| (x - m).powi(2)).sum::<f64>()).sum();
    let ms_between = ss_between / (p - 1) as f64;
    let ms_within = ss_within / (p * (r - 1)) as f64;
    let var_grr = ms_within;
    let var_parts = ((ms_between - ms_within) / r as f64).max(0.0);
    let sigma_grr = var_grr.sqrt();
    let total = (var_grr + var_parts).sqrt();
    let tol = (tolerance_mm > 0.0).then(|| 100.0 * 6.0 * sigma_grr / tolerance_mm);
    let of_total = (total > 0.0).then(|| 100.0 * sigma_grr / total);
    let ndc = (sigma_grr > 0.0).then(|| 1.41 * var_parts.sqrt() / sigma_grr);
    (tol, of_total, ndc)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anova_separates_parts_from_repeats() {
        // Three parts 10 apart, repeats ±1: σ_repeat = 1 (a pair of ±1 has variance 2 with 1 dof).
        let parts = vec![vec![-1.0, 1.0], vec![9.0, 11.0], vec![19.0, 21.0]];
        let (tol, total, ndc) = anova(&parts, 2, 60.0);
        let sigma_grr = 2f64.sqrt();
        assert!((tol.unwrap() - 100.0 * 6.0 * sigma_grr / 60.0).abs() < 1e-9);
        // σ²_parts = (MS_between − MS_within)/r = (200 − 2)/2 = 99.
        assert!((ndc.unwrap() - 1.41 * 99f64.sqrt() / sigma_grr).abs() < 1e-9);
        assert!((total.unwrap() - 100.0 * sigma_grr / (2.0 + 99.0f64).sqrt()).abs() < 1e-9);
        assert_eq!(anova(&parts[..1], 2, 60.0), (None, None, None));
    }

    #[test]
    fn per_thread_fit_is_each_threads_median_error() {
        let mut samples = Vec::new();
        for run in 0..4 {
            for bin in 0..5 {
                samples.push(Sample { master: 0, run, thread: 1, bin, error_mm: 0.010 + 0.001 * run as f64 });
                samples.push(Sample { master: 0, run, thread: 2, bin, error_mm: -0.020 });
            }
        }
        let c = fit(CorrectionModel::PerThread, &samples);
        // The upper median of 20 (`numeric::stats::median`).
        assert!((c.at_mm(1).unwrap() - 0.012).abs() < 1e-9, "{c:?}");
        assert!((c.at_mm(2).unwrap() + 0.020).abs() < 1e-12);
        assert_eq!(c.at_mm(3), None);
        assert!(c.threads[1].u_um.abs() < 1e-9 && c.threads[0].u_um > 0.0);
        assert_eq!(fit(CorrectionModel::None, &samples).at_mm(3), Some(0.0));
    }

    #[test]
    fn a_certificate_states_its_instrument_date_and_uncertainty() {
        let ok = br#"{"instrument": "CMM 1", "measured_at": "2026-01-05T08:00:00Z", "uncertainty_mm": 0.002,
            "points": [{"thread": 1, "angle_deg": 0.5, "height_mm": 1.5748}]}"#;
        let c = Certificate::parse(ok).unwrap();
        assert_eq!((c.instrument.as_str(), c.expanded_uncertainty_mm), ("CMM 1", 0.002));
        let no_u = br#"{"instrument": "CMM 1", "measured_at": "2026-01-05T08:00:00Z",
            "points": [{"thread": 1, "angle_deg": 0.5, "height_mm": 1.5748}]}"#;
        assert_eq!(Certificate::parse(no_u).unwrap_err().field, "points[0].uncertainty_mm");
        let no_date =
            br#"{"instrument": "CMM 1", "uncertainty_mm": 0.002, "points": [{"thread": 1, "height_mm": 1.5}]}"#;
        assert_eq!(Certificate::parse(no_date).unwrap_err().field, "measured_at");
        let csv = b"# instrument: CMM 2\n# measured_at: 2026-01-05T08:00:00Z\n# uncertainty_mm: 0.003\nthread,angle_deg,height_mm\n1,0.5,1.5748\n";
        assert_eq!(Certificate::parse(csv).unwrap().expanded_uncertainty_mm, 0.003);
    }
}
