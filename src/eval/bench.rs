//! Accuracy of a report against simulated truth, and the benchmark suite behind `crestscan bench`.

use crate::pipeline::report::Report;
use crate::sim::Truth;
use serde::Serialize;

/// Per-thread height error over bins measured in both, and black-crest and verdict agreement.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Accuracy {
    pub bins_compared: usize,
    /// Bins where truth has a value and the report none (coverage loss).
    pub bins_missing: usize,
    pub height_rms_um: f64,
    pub height_max_um: f64,
    pub height_bias_um: f64,
    /// Largest |report − truth| black-crest length over threads (mm), over the crests the views
    /// showed: where the report says some crest within Lc was not seen
    /// (`assessment.seen_crest_arcs`), each thread's truth arcs are clipped to its seen arcs first.
    pub black_crest_length_max_error_mm: f64,
    /// Crest degrees within Lc the views showed, over all threads (None when they showed all).
    pub seen_crest_deg: Option<f64>,
    pub verdict_agrees: bool,
    /// The worst bins: (thread, angle, report, truth).
    pub worst: Vec<(u32, f64, f64, f64)>,
}

/// Compares heights bin by bin (only full-coverage bins of threads present in both), black-crest
/// lengths per thread (over the crests the views showed), and the verdict.
pub fn compare(report: &Report, truth: &Truth) -> Accuracy {
    let mut errors: Vec<(f64, u32, f64, f64, f64)> = Vec::new();
    let mut missing = 0;
    for t in &truth.threads {
        let Some(r) = report.threads.iter().find(|r| r.index == t.index) else {
            missing += t.height_mm.values.iter().flatten().count();
            continue;
        };
        for (k, truth_value) in t.height_mm.values.iter().enumerate() {
            let Some(tv) = truth_value else { continue };
            match r.height_mm.values.get(k).copied().flatten() {
                Some(rv) => errors.push((1e3 * (rv - tv), t.index, t.height_mm.angles_deg[k], rv, *tv)),
                None => missing += 1,
            }
        }
    }
    let n = errors.len().max(1) as f64;
    let rms = (errors.iter().map(|e| e.0 * e.0).sum::<f64>() / n).sqrt();
    let bias = errors.iter().map(|e| e.0).sum::<f64>() / n;
    let max = errors.iter().map(|e| e.0.abs()).fold(0.0, f64::max);
    errors.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
    let seen = report.assessment.seen_crest_arcs.as_deref();
    let length_error =
        black_crests(report, truth).iter().map(|b| (b.reported_mm - b.truth_mm).abs()).fold(0.0, f64::max);
    Accuracy {
        bins_compared: errors.len(),
        bins_missing: missing,
        height_rms_um: rms,
        height_max_um: max,
        height_bias_um: bias,
        black_crest_length_max_error_mm: length_error,
        seen_crest_deg: seen.map(|threads| threads.iter().map(|t| crate::domain::arcs::arcs_deg(&t.arcs_deg)).sum()),
        verdict_agrees: report.verdict == truth.verdict,
        worst: errors.iter().take(5).map(|e| (e.1, e.2, e.3, e.4)).collect(),
    }
}

/// One thread's black crest, as reported and as true.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BlackCrest {
    pub thread: u32,
    pub reported_arcs_deg: Vec<[f64; 2]>,
    pub reported_mm: f64,
    /// Over the crests the views showed (`assessment.seen_crest_arcs`), when the report says some
    /// were not seen.
    pub truth_arcs_deg: Vec<[f64; 2]>,
    pub truth_mm: f64,
}

/// Every thread that has a black crest in the report or in truth, in thread order.
pub fn black_crests(report: &Report, truth: &Truth) -> Vec<BlackCrest> {
    let seen = report.assessment.seen_crest_arcs.as_deref();
    let mut rows: Vec<BlackCrest> = truth
        .threads
        .iter()
        .map(|t| {
            let (truth_arcs_deg, truth_mm) = match seen {
                None => (t.black_crest_arcs_deg.clone(), t.black_crest_length_mm),
                Some(seen) => {
                    let thread_seen = seen.iter().find(|s| s.index == t.index).map_or(&[][..], |s| &s.arcs_deg[..]);
                    let arcs = crate::domain::arcs::intersect_arcs(&t.black_crest_arcs_deg, thread_seen);
                    let mm = crate::domain::arcs::arc_length_mm(&arcs, truth.circumference_mm);
                    (arcs, mm)
                }
            };
            let reported = report.threads.iter().find(|r| r.index == t.index);
            BlackCrest {
                thread: t.index,
                reported_arcs_deg: reported.map_or_else(Vec::new, |r| r.black_crest_arcs_deg.clone()),
                reported_mm: reported.map_or(0.0, |r| r.black_crest_length_mm),
                truth_arcs_deg,
                truth_mm,
            }
        })
        .chain(report.threads.iter().filter(|r| truth.threads.iter().all(|t| t.index != r.index)).map(|r| BlackCrest {
            thread: r.index,
            reported_arcs_deg: r.black_crest_arcs_deg.clone(),
            reported_mm: r.black_crest_length_mm,
            truth_arcs_deg: Vec::new(),
            truth_mm: 0.0,
        }))
        .filter(|b| {
            b.reported_mm > 0.0 || b.truth_mm > 0.0 || !b.reported_arcs_deg.is_empty() || !b.truth_arcs_deg.is_empty()
        })
        .collect();
    rows.sort_by_key(|b| b.thread);
    rows
}

/// A benchmark case: a preset rendered with one seed.
#[derive(Clone, Copy, Debug)]
pub struct Case {
    pub preset: &'static str,
    pub seed: u64,
}

/// The accuracy suite: the standard preset, the defects that decide verdicts, and the seed's
/// Table 1, each with a seed of its own that no test or tuning uses.
pub const ACCURACY_SUITE: &[Case] = &[
    Case { preset: "standard", seed: 9001 },
    Case { preset: "bc-black-2", seed: 9002 },
    Case { preset: "bc-arc-over-25", seed: 9003 },
    Case { preset: "lc-round-black", seed: 9004 },
    Case { preset: "bc-polished", seed: 9005 },
    Case { preset: "seed-table1", seed: 9006 },
];

/// The held-out suite: the defect presets rendered again with other seeds. The black-crest
/// thresholds were chosen while looking at the accuracy suite's cases, so these show whether its
/// numbers carry over (the polished crest sixteen times: its ends scatter most). Not untouched: the
/// round seeds 1–3 chose the width of the height window and round seed 2 showed the faint end bin
/// a dark run now bridges (README); round seeds 4–6 and the second seeds of the other two were
/// rendered only after that change, to check it. bc-arc-over-25 seed 3 and polished seeds 9–12 were
/// first rendered after the steep-edge depth change, to check it (polished seed 9 got a wrong
/// verdict there), and joined the suite in the round that fitted the polished crest's ends;
/// polished seeds 13–16 were rendered after that fit was written, to check it. bc-black-1,
/// bc-black-3 and lc-accept (seed 1), the presets no suite had, joined in the same round, seen by
/// nothing before, and bc-black-1 seed 2 after seed 1's 1.77 mm.
pub const HOLDOUT_SUITE: &[Case] = &[
    Case { preset: "lc-round-black", seed: 1 },
    Case { preset: "lc-round-black", seed: 2 },
    Case { preset: "lc-round-black", seed: 3 },
    Case { preset: "lc-round-black", seed: 4 },
    Case { preset: "lc-round-black", seed: 5 },
    Case { preset: "lc-round-black", seed: 6 },
    Case { preset: "lc-accept", seed: 1 },
    Case { preset: "bc-black-1", seed: 1 },
    Case { preset: "bc-black-1", seed: 2 },
    Case { preset: "bc-black-2", seed: 1 },
    Case { preset: "bc-black-2", seed: 2 },
    Case { preset: "bc-black-3", seed: 1 },
    Case { preset: "bc-arc-over-25", seed: 1 },
    Case { preset: "bc-arc-over-25", seed: 2 },
    Case { preset: "bc-arc-over-25", seed: 3 },
    Case { preset: "bc-polished", seed: 1 },
    Case { preset: "bc-polished", seed: 2 },
    Case { preset: "bc-polished", seed: 3 },
    Case { preset: "bc-polished", seed: 4 },
    Case { preset: "bc-polished", seed: 5 },
    Case { preset: "bc-polished", seed: 6 },
    Case { preset: "bc-polished", seed: 7 },
    Case { preset: "bc-polished", seed: 8 },
    Case { preset: "bc-polished", seed: 9 },
    Case { preset: "bc-polished", seed: 10 },
    Case { preset: "bc-polished", seed: 11 },
    Case { preset: "bc-polished", seed: 12 },
    Case { preset: "bc-polished", seed: 13 },
    Case { preset: "bc-polished", seed: 14 },
    Case { preset: "bc-polished", seed: 15 },
    Case { preset: "bc-polished", seed: 16 },
    Case { preset: "bc-polished-long", seed: 1 },
    Case { preset: "bc-polished-long", seed: 2 },
    Case { preset: "bc-polished-long", seed: 3 },
    Case { preset: "bc-polished-long", seed: 4 },
    Case { preset: "bc-polished-end", seed: 1 },
    Case { preset: "bc-polished-end", seed: 2 },
    Case { preset: "bc-polished-end", seed: 3 },
    Case { preset: "lc-round-black", seed: 7 },
    Case { preset: "bc-polished-long", seed: 5 },
    Case { preset: "bc-polished-long", seed: 6 },
    Case { preset: "bc-polished-end", seed: 4 },
    Case { preset: "bc-polished-end", seed: 5 },
];

/// A named benchmark suite.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Suite {
    Accuracy,
    Holdout,
}

impl Suite {
    pub fn name(self) -> &'static str {
        match self {
            Suite::Accuracy => "accuracy",
            Suite::Holdout => "holdout",
        }
    }

    pub fn cases(self) -> &'static [Case] {
        match self {
            Suite::Accuracy => ACCURACY_SUITE,
            Suite::Holdout => HOLDOUT_SUITE,
        }
    }

    /// Where its renderings are cached unless `--work` says otherwise.
    pub fn default_work_dir(self) -> &'static str {
        match self {
            Suite::Accuracy => "out/bench",
            Suite::Holdout => "out/holdout",
        }
    }
}

impl Case {
    /// The case's folder under the work directory, and its name for `--only`.
    pub fn name(&self) -> String {
        format!("{}-{}", self.preset, self.seed)
    }

    /// `--only` picks a case by its preset (every seed) or by `preset-seed`.
    pub fn matches(&self, only: &str) -> bool {
        only == self.preset || only == self.name()
    }
}

/// Registration error after refinement, with the global rotation and shift removed (they are not
/// observable from overlaps; the encoders' mean error stands for them).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RegistrationError {
    pub angle_rms_deg: f64,
    pub angle_max_deg: f64,
    pub axial_rms_um: f64,
    pub axial_max_um: f64,
    pub radial_rms_um: f64,
    /// The same before refinement (encoder poses), for scale.
    pub encoder_angle_rms_deg: f64,
    pub encoder_axial_rms_um: f64,
    /// Each measured pair's shift against the true one (the difference of the two views' true
    /// corrections), RMS over the pairs: along the arc at the pipe's outside radius, and axially,
    /// µm. What the pose graph starts from: a view's error after the solve is these errors summed
    /// around the ring.
    pub pair_arc_rms_um: f64,
    pub pair_axial_rms_um: f64,
    pub pairs_measured: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CaseResult {
    pub preset: String,
    pub seed: u64,
    pub accuracy: Accuracy,
    pub depth_rms_um: f64,
    pub depth_median_um: f64,
    pub depth_coverage: f64,
    pub registration: RegistrationError,
    pub decode_seconds: f64,
    pub inspect_seconds: f64,
    pub render: crate::sim::SimSummary,
    pub stage_seconds: Vec<(String, f64)>,
    /// Seed Table 1: (thread, measured mean of bins 0–4, truth mean of the same bins), mm.
    pub table1: Vec<(u32, f64, f64)>,
    /// Absolute z, which overlaps cannot observe: measured helix phase z_h minus truth (wrapped to
    /// ±half a pitch), and the encoders' mean axial offset (encoder − true), which registration
    /// keeps (its mean correction is zero), µm.
    pub helix_z_error_um: f64,
    pub encoder_mean_axial_offset_um: f64,
    pub black_crests: Vec<BlackCrest>,
}

impl CaseResult {
    /// How the benchmark's blocks name the case: "preset seed N".
    pub fn label(&self) -> String {
        format!("{} seed {}", self.preset, self.seed)
    }
}

fn gauge_free(errors: &[f64]) -> (f64, f64) {
    let mean = errors.iter().sum::<f64>() / errors.len().max(1) as f64;
    let rms = (errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / errors.len().max(1) as f64).sqrt();
    let max = errors.iter().map(|e| (e - mean).abs()).fold(0.0, f64::max);
    (rms, max)
}

fn registration_error(
    encoder: &[crate::domain::optics::ViewPose],
    refined: &[crate::domain::optics::ViewPose],
    truth: &[crate::domain::optics::ViewPose],
    pairs: &[crate::pipeline::register::PairMeasure],
    radius_mm: f64,
) -> RegistrationError {
    let diff = |poses: &[crate::domain::optics::ViewPose], f: &dyn Fn(&crate::domain::optics::ViewPose) -> f64| -> Vec<f64> {
        poses.iter().zip(truth).map(|(p, t)| f(p) - f(t)).collect()
    };
    let (angle_rms_deg, angle_max_deg) = gauge_free(&diff(refined, &|p| p.angle_deg));
    let (axial_rms, axial_max) = gauge_free(&diff(refined, &|p| p.axial_mm));
    let (radial_rms, _) = gauge_free(&diff(refined, &|p| p.lens_radius_mm));
    // Encoder minus truth per view: the negated correction registration should find.
    let (encoder_angle, encoder_axial) = (diff(encoder, &|p| p.angle_deg), diff(encoder, &|p| p.axial_mm));
    let (encoder_angle_rms_deg, _) = gauge_free(&encoder_angle);
    let (encoder_axial_rms, _) = gauge_free(&encoder_axial);
    // A pair measures how far b's content must move onto a's: c_b − c_a, c = truth − encoder.
    let pair_errors = |shift: &dyn Fn(&crate::pipeline::register::PairMeasure) -> f64, encoder_error: &[f64]| -> Vec<f64> {
        pairs.iter().map(|p| shift(p) - (encoder_error[p.a] - encoder_error[p.b])).collect()
    };
    let rms = |errors: &[f64]| (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
    let pair_arc_rms_um = 1e3 * radius_mm * rms(&pair_errors(&|p| p.shift_angle_deg, &encoder_angle)).to_radians();
    let pair_axial_rms_um = 1e3 * rms(&pair_errors(&|p| p.shift_axial_mm, &encoder_axial));
    RegistrationError {
        pair_arc_rms_um,
        pair_axial_rms_um,
        pairs_measured: pairs.len(),
        angle_rms_deg,
        angle_max_deg,
        axial_rms_um: 1e3 * axial_rms,
        axial_max_um: 1e3 * axial_max,
        radial_rms_um: 1e3 * radial_rms,
        encoder_angle_rms_deg,
        encoder_axial_rms_um: 1e3 * encoder_axial_rms,
    }
}

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("unknown preset {0}")]
    Preset(String),
    #[error(transparent)]
    Sim(#[from] crate::sim::SimError),
    #[error(transparent)]
    Bundle(#[from] crate::bundle::BundleError),
    #[error(transparent)]
    Pipeline(#[from] crate::pipeline::PipelineError),
    #[error("{0}")]
    Other(String),
}

/// Renders the case into `work/<preset>-<seed>` unless a complete rendering is there, times a plain
/// decode of every frame (the yardstick), inspects it, and compares with truth. With `repeat` > 1
/// the decode and the inspection alternate that many times and the median times are reported.
pub fn run_case(
    case: &Case,
    work: &std::path::Path,
    repeat: usize,
    options: &crate::pipeline::PipelineOptions,
) -> Result<CaseResult, BenchError> {
    use crate::bundle::{Bundle, OpenOptions};
    use rayon::prelude::*;
    let spec = crate::sim::preset(case.preset).ok_or_else(|| BenchError::Preset(case.preset.into()))?;
    let dir = work.join(case.name());
    // A finished rendering leaves its summary (render time, size) beside the bundle.
    let done = dir.join("render-summary.json");
    let rendered: crate::sim::SimSummary = match std::fs::read(&done).ok().and_then(|b| serde_json::from_slice(&b).ok())
    {
        Some(summary) => summary,
        None => {
            let _ = std::fs::remove_dir_all(&dir);
            let summary = crate::sim::simulate(&spec, case.seed, &dir)?;
            std::fs::write(&done, serde_json::to_vec(&summary).expect("serialises"))
                .map_err(|e| BenchError::Other(e.to_string()))?;
            summary
        }
    };
    // Truth is rewritten every run (it is cheap, the frames are not): a cached rendering keeps its
    // pixels, but the verdict and black-crest arcs must follow the current rule engine.
    let truth: Truth = crate::sim::write_truth(&spec, case.seed, &dir)?;
    let table = crate::domain::thread::ConnectionTable::api5b();
    let bundle = Bundle::open(&dir, &table, OpenOptions::default())?;

    // Yardstick: decode every frame once, with the pipeline's parallelism (views across cores).
    // Decode and inspection alternate `repeat` times and each time is the median of its runs: on a
    // shared 2-core machine one run of either can be 30% off.
    let decode = || -> Result<f64, BenchError> {
        let started = std::time::Instant::now();
        bundle.views.par_iter().enumerate().try_for_each(|(v, view)| {
            for k in 0..view.frames.len() {
                std::hint::black_box(bundle.read_frame(v, k)?);
            }
            Ok::<_, crate::bundle::BundleError>(())
        })?;
        Ok(started.elapsed().as_secs_f64())
    };
    let cancel = std::sync::atomic::AtomicBool::new(false);
    // (decode s, inspect s, stage times) per run; the results are the same every run, so only
    // the last inspection is kept.
    let mut runs = Vec::new();
    let mut last = None;
    for _ in 0..repeat.max(1) {
        let decode_seconds = decode()?;
        drop(last.take()); // the previous run's maps are not held while this one runs
        let started = std::time::Instant::now();
        let inspection = crate::pipeline::inspect(&bundle, options, &|_, _| {}, &cancel)?
            .ok_or_else(|| BenchError::Other("cancelled".into()))?;
        let stages: Vec<(String, f64)> =
            inspection.report.timings.iter().map(|t| (t.stage.clone(), t.seconds)).collect();
        runs.push((decode_seconds, started.elapsed().as_secs_f64(), stages));
        last = Some(inspection);
    }
    let inspection = last.expect("at least one run");
    let median_of = |mut v: Vec<f64>| crate::numeric::stats::median(&mut v).expect("at least one run");
    let decode_seconds = median_of(runs.iter().map(|r| r.0).collect());
    let inspect_seconds = median_of(runs.iter().map(|r| r.1).collect());
    // Stage times of the run whose inspection time is the median.
    let stage_seconds = runs
        .into_iter()
        .min_by(|a, b| (a.1 - inspect_seconds).abs().total_cmp(&(b.1 - inspect_seconds).abs()))
        .expect("at least one run")
        .2;

    let accuracy = compare(&inspection.report, &truth);
    let (mut sq, mut errors, mut seen, mut total) = (0.0, Vec::new(), 0usize, 0usize);
    for (view, depth) in bundle.views.iter().zip(&inspection.depth_maps) {
        let bytes = std::fs::read(dir.join(format!("truth/{}.depth.pfm", view.id)))
            .map_err(|e| BenchError::Other(e.to_string()))?;
        let (_, _, t) = crate::sim::pfm::read(&bytes).map_err(BenchError::Other)?;
        // The map holds every `row_step`-th pixel row; truth holds every row.
        let truth_rows = t.chunks_exact(depth.width).step_by(depth.row_step.max(1)).flatten();
        for (d, t) in depth.depth_mm.iter().zip(truth_rows) {
            if t.is_finite() {
                total += 1;
                if d.is_finite() {
                    let e = 1e3 * (d - t) as f64;
                    sq += e * e;
                    errors.push(e.abs());
                    seen += 1;
                }
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    let truth_poses = bundle
        .views
        .iter()
        .map(|v| {
            truth
                .true_poses
                .get(&v.id)
                .copied()
                .ok_or_else(|| BenchError::Other(format!("truth lacks the pose of {}", v.id)))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let encoder: Vec<_> = bundle.views.iter().map(|v| v.pose).collect();
    let table1 = if case.preset == "seed-table1" {
        (1..=10u32)
            .filter_map(|i| {
                let r = inspection.report.threads.iter().find(|t| t.index == i)?;
                let t = truth.threads.iter().find(|t| t.index == i)?;
                let bins: Vec<(f64, f64)> =
                    (0..5).filter_map(|k| Some((r.height_mm.values[k]?, t.height_mm.values[k]?))).collect();
                (!bins.is_empty()).then(|| {
                    let n = bins.len() as f64;
                    (i, bins.iter().map(|b| b.0).sum::<f64>() / n, bins.iter().map(|b| b.1).sum::<f64>() / n)
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    Ok(CaseResult {
        black_crests: black_crests(&inspection.report, &truth),
        preset: case.preset.into(),
        seed: case.seed,
        accuracy,
        depth_rms_um: (sq / seen.max(1) as f64).sqrt(),
        depth_median_um: errors.get(errors.len() / 2).copied().unwrap_or(f64::NAN),
        depth_coverage: seen as f64 / total.max(1) as f64,
        registration: registration_error(
            &encoder,
            &inspection.poses,
            &truth_poses,
            &inspection.report.registration.pairs,
            inspection.report.pipe_od_mm / 2.0,
        ),
        decode_seconds,
        inspect_seconds,
        render: rendered,
        stage_seconds,
        table1,
        helix_z_error_um: {
            let (pitch, dz) = (inspection.report.helix.pitch_mm, inspection.report.helix.z_h_mm - truth.helix_z_h_mm);
            1e3 * (dz - pitch * (dz / pitch).round())
        },
        encoder_mean_axial_offset_um: 1e3
            * encoder.iter().zip(&truth_poses).map(|(e, t)| e.axial_mm - t.axial_mm).sum::<f64>()
            / encoder.len().max(1) as f64,
    })
}

/// One of the pipeline issue's targets, read on a set of benchmark results.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TargetCheck {
    pub target: &'static str,
    pub met: bool,
    /// The worst value and where it was found.
    pub worst: String,
}

/// The pipeline issue's targets over these results: per-thread height RMS ≤ 10 µm and max ≤ 25 µm,
/// every verdict agreeing, black-crest length within 2 mm, registration within 0.02° and 5 µm
/// (after refinement; over the views and for every view), the Table 1 threads within 10 µm and the standard preset's inspection
/// within 3× its decode. A target with no case to read it on is left out.
pub fn targets(results: &[CaseResult]) -> Vec<TargetCheck> {
    let worst = |f: &dyn Fn(&CaseResult) -> f64| -> Option<(f64, &CaseResult)> {
        results.iter().map(|r| (f(r), r)).max_by(|a, b| a.0.total_cmp(&b.0))
    };
    let mut checks = Vec::new();
    let mut at_most = |target: &'static str, limit: f64, unit: &str, digits: usize, f: &dyn Fn(&CaseResult) -> f64| {
        if let Some((value, r)) = worst(f) {
            checks.push(TargetCheck {
                target,
                met: value <= limit,
                worst: format!("{value:.digits$}{unit}, {}", r.label()),
            });
        }
    };
    at_most("per-thread height RMS ≤ 10 µm", 10.0, " µm", 1, &|r| r.accuracy.height_rms_um);
    at_most("per-thread height max ≤ 25 µm", 25.0, " µm", 1, &|r| r.accuracy.height_max_um);
    at_most("black-crest length error ≤ 2 mm per thread", 2.0, " mm", 2, &|r| {
        r.accuracy.black_crest_length_max_error_mm
    });
    // The issue does not say over what registration's bound holds: over the views (RMS), or for
    // every view (its worst). Both readings are printed.
    at_most("registration ≤ 0.02° (RMS over views)", 0.02, "°", 4, &|r| r.registration.angle_rms_deg);
    at_most("registration ≤ 5 µm (RMS over views)", 5.0, " µm", 1, &|r| r.registration.axial_rms_um);
    at_most("registration ≤ 0.02° (every view)", 0.02, "°", 4, &|r| r.registration.angle_max_deg);
    at_most("registration ≤ 5 µm (every view)", 5.0, " µm", 1, &|r| r.registration.axial_max_um);
    if !results.is_empty() {
        let agree = results.iter().filter(|r| r.accuracy.verdict_agrees).count();
        checks.push(TargetCheck {
            target: "verdicts agree",
            met: agree == results.len(),
            worst: format!("{agree} of {}", results.len()),
        });
    }
    let table1: Vec<(u32, f64)> =
        results.iter().flat_map(|r| r.table1.iter().map(|(i, m, t)| (*i, 1e3 * (m - t).abs()))).collect();
    if let Some((thread, error_um)) = table1.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1)) {
        checks.push(TargetCheck {
            target: "Table 1 threads within 10 µm",
            met: error_um <= 10.0,
            worst: format!("{error_um:.1} µm, thread {thread}"),
        });
    }
    for r in results.iter().filter(|r| r.preset == "standard") {
        let ratio = r.inspect_seconds / r.decode_seconds;
        checks.push(TargetCheck {
            target: "standard inspection ≤ 3× its decode",
            met: ratio <= 3.0,
            worst: format!("{ratio:.2}×, {}", r.label()),
        });
    }
    checks
}

/// The benchmark table, markdown.
pub fn table(results: &[CaseResult]) -> String {
    let mut out = String::from(
        "| case | height RMS / max µm | bins | depth RMS / median µm, coverage | registration ° / axial µm (encoder) | black-crest length err mm | verdict | decode s | inspect s (ratio) |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let a = &r.accuracy;
        let g = &r.registration;
        out.push_str(&format!(
            "| {} (seed {}) | {:.1} / {:.1} | {} | {:.0} / {:.1}, {:.1}% | {:.4} / {:.1} ({:.2} / {:.0}) | {:.2} | {} | {:.2} | {:.2} ({:.2}×) |\n",
            r.preset,
            r.seed,
            a.height_rms_um,
            a.height_max_um,
            a.bins_compared,
            r.depth_rms_um,
            r.depth_median_um,
            100.0 * r.depth_coverage,
            g.angle_rms_deg,
            g.axial_rms_um,
            g.encoder_angle_rms_deg,
            g.encoder_axial_rms_um,
            a.black_crest_length_max_error_mm,
            if a.verdict_agrees { "agrees" } else { "DISAGREES" },
            r.decode_seconds,
            r.inspect_seconds,
            r.inspect_seconds / r.decode_seconds
        ));
    }
    for r in results.iter().filter(|r| !r.table1.is_empty()) {
        out.push_str("\nSeed Table 1 (mean of bins 0–4°): thread, measured mm, truth mm, error µm\n");
        for (i, m, t) in &r.table1 {
            out.push_str(&format!("  {i:2}  {m:.4}  {t:.4}  {:+.1}\n", 1e3 * (m - t)));
        }
    }
    if results.iter().any(|r| !r.black_crests.is_empty()) {
        out.push_str("\nBlack crests within Lc, per thread: arcs found (true arcs), length error mm\n");
        let arcs = |a: &[[f64; 2]]| -> String {
            if a.is_empty() {
                return "none".into();
            }
            a.iter().map(|[s, e]| format!("{s:.1}°–{e:.1}°")).collect::<Vec<_>>().join(", ")
        };
        for r in results.iter().filter(|r| !r.black_crests.is_empty()) {
            let rows: Vec<String> = r
                .black_crests
                .iter()
                .map(|b| {
                    format!(
                        "thread {} {} ({}) {:.2}",
                        b.thread,
                        arcs(&b.reported_arcs_deg),
                        arcs(&b.truth_arcs_deg),
                        (b.reported_mm - b.truth_mm).abs()
                    )
                })
                .collect();
            out.push_str(&format!("  {}: {}\n", r.label(), rows.join("; ")));
        }
    }
    out.push_str(
        "\nRegistration, every view and every pair: the worst view's angle ° and axial µm (after the solve), and \
         the pairs' measured shifts against the true ones, RMS along the arc / axially µm (pairs measured)\n",
    );
    for r in results {
        let g = &r.registration;
        out.push_str(&format!(
            "  {}: worst view {:.4}° / {:.1} µm; pairs {:.1} / {:.1} µm ({})\n",
            r.label(),
            g.angle_max_deg,
            g.axial_max_um,
            g.pair_arc_rms_um,
            g.pair_axial_rms_um,
            g.pairs_measured
        ));
    }
    out.push_str(
        "\nAbsolute z (overlaps cannot observe it; taken from the end face where the views show it): helix z_h \
         measured − truth, and the encoders' mean axial offset, µm\n",
    );
    for r in results {
        out.push_str(&format!(
            "  {}: {:+.1} ({:+.1})\n",
            r.label(),
            r.helix_z_error_um,
            r.encoder_mean_axial_offset_um
        ));
    }
    let checks = targets(results);
    if !checks.is_empty() {
        out.push_str("\nTargets of the pipeline issue, read on these cases (worst value, where):\n");
        for c in &checks {
            out.push_str(&format!("  {}: {} ({})\n", c.target, if c.met { "met" } else { "NOT MET" }, c.worst));
        }
    }
    let stages: Vec<String> = results
        .iter()
        .map(|r| {
            format!(
                "{}: {}",
                r.label(),
                r.stage_seconds.iter().map(|(s, t)| format!("{s} {t:.2}")).collect::<Vec<_>>().join(", ")
            )
        })
        .collect();
    out.push_str(&format!("\nStage times (s):\n  {}\n", stages.join("\n  ")));
    out.push_str("\nRenderings (this machine, when first rendered): preset, frames, MB, seconds\n");
    for r in results {
        out.push_str(&format!(
            "  {}: {} frames, {:.0} MB, {:.1} s\n",
            r.label(),
            r.render.frames,
            r.render.bytes as f64 / 1e6,
            r.render.seconds
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn suites_name_existing_presets_and_share_no_case() {
        for suite in [Suite::Accuracy, Suite::Holdout] {
            for case in suite.cases() {
                assert!(crate::sim::preset(case.preset).is_some(), "{}", case.name());
            }
        }
        for a in ACCURACY_SUITE {
            assert!(HOLDOUT_SUITE.iter().all(|h| h.name() != a.name()), "{}", a.name());
        }
        let mut names: Vec<String> = HOLDOUT_SUITE.iter().map(Case::name).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), HOLDOUT_SUITE.len());
    }

    fn result(preset: &str, height_max_um: f64, inspect_over_decode: f64) -> CaseResult {
        CaseResult {
            preset: preset.into(),
            seed: 1,
            accuracy: Accuracy {
                bins_compared: 100,
                bins_missing: 0,
                height_rms_um: 2.0,
                height_max_um,
                height_bias_um: 0.0,
                black_crest_length_max_error_mm: 0.5,
                seen_crest_deg: None,
                verdict_agrees: true,
                worst: Vec::new(),
            },
            depth_rms_um: 0.0,
            depth_median_um: 0.0,
            depth_coverage: 1.0,
            registration: RegistrationError {
                angle_rms_deg: 0.01,
                angle_max_deg: 0.02,
                axial_rms_um: 3.0,
                axial_max_um: 6.0,
                radial_rms_um: 1.0,
                encoder_angle_rms_deg: 0.6,
                encoder_axial_rms_um: 180.0,
                pair_arc_rms_um: 1.5,
                pair_axial_rms_um: 1.2,
                pairs_measured: 45,
            },
            decode_seconds: 1.0,
            inspect_seconds: inspect_over_decode,
            render: crate::sim::SimSummary {
                files: 1,
                bytes: 1,
                frames: 1,
                seconds: 1.0,
                verdict: crate::domain::rules::Verdict::Accept,
            },
            stage_seconds: Vec::new(),
            table1: Vec::new(),
            helix_z_error_um: 0.0,
            encoder_mean_axial_offset_um: 0.0,
            black_crests: Vec::new(),
        }
    }

    fn check(results: &[CaseResult], target: &str) -> Option<TargetCheck> {
        targets(results).into_iter().find(|c| c.target.starts_with(target))
    }

    #[test]
    fn targets_name_the_worst_case_and_whether_it_is_met() {
        let standard = result("standard", 7.2, 4.4);
        let mut round = result("lc-round-black", 20.3, 4.0);
        let both = [standard.clone(), round.clone()];
        let max = check(&both, "per-thread height max").unwrap();
        assert!(max.met);
        assert_eq!(max.worst, "20.3 µm, lc-round-black seed 1");
        let speed = check(&both, "standard inspection").unwrap();
        assert!(!speed.met);
        assert_eq!(speed.worst, "4.40×, standard seed 1");
        assert!(check(&both, "verdicts agree").unwrap().met);
        // No Table 1 case, no Table 1 target; no standard case, no speed target.
        assert!(check(&both, "Table 1").is_none());
        assert!(check(&both[1..], "standard inspection").is_none());

        // Limits are inclusive; just past one, the target is not met.
        round.registration.axial_rms_um = 5.0;
        assert!(check(std::slice::from_ref(&round), "registration ≤ 5 µm (RMS").unwrap().met);
        // Its worst view (6 µm) is over: read per view, the target is not met.
        let every_view = check(std::slice::from_ref(&round), "registration ≤ 5 µm (every").unwrap();
        assert_eq!((every_view.met, every_view.worst.as_str()), (false, "6.0 µm, lc-round-black seed 1"));
        round.registration.axial_rms_um = 5.01;
        round.accuracy.height_max_um = 25.1;
        round.accuracy.verdict_agrees = false;
        let both = [standard.clone(), round.clone()];
        assert!(!check(&both, "registration ≤ 5 µm (RMS").unwrap().met);
        assert!(!check(&both, "per-thread height max").unwrap().met);
        let verdicts = check(&both, "verdicts agree").unwrap();
        assert_eq!((verdicts.met, verdicts.worst.as_str()), (false, "1 of 2"));

        let mut table1 = result("seed-table1", 10.8, 5.9);
        table1.table1 = vec![(2, 0.9884, 0.9823), (10, 0.4263, 0.4207)];
        let t = check(std::slice::from_ref(&table1), "Table 1").unwrap();
        assert_eq!((t.met, t.worst.as_str()), (true, "6.1 µm, thread 2"));
        table1.table1.push((6, 0.9370, 0.9479));
        let t = check(std::slice::from_ref(&table1), "Table 1").unwrap();
        assert_eq!((t.met, t.worst.as_str()), (false, "10.9 µm, thread 6"));
    }

    #[test]
    fn pair_errors_are_read_against_the_true_corrections_difference() {
        use crate::domain::optics::ViewPose;
        let pose = |angle_deg: f64, axial_mm: f64| ViewPose { angle_deg, axial_mm, lens_radius_mm: 270.0 };
        let encoder = [pose(0.0, 10.0), pose(8.0, 10.0), pose(16.0, 10.0)];
        // True corrections (truth − encoder): +0.5°, −0.3°, +0.1° and +0.10, −0.05, 0 mm.
        let truth = [pose(0.5, 10.1), pose(7.7, 9.95), pose(16.1, 10.0)];
        let pair = |a: usize, b: usize, angle_error_deg: f64, axial_error_mm: f64| crate::pipeline::register::PairMeasure {
            a,
            b,
            shift_angle_deg: (truth[b].angle_deg - encoder[b].angle_deg) - (truth[a].angle_deg - encoder[a].angle_deg)
                + angle_error_deg,
            shift_axial_mm: (truth[b].axial_mm - encoder[b].axial_mm) - (truth[a].axial_mm - encoder[a].axial_mm)
                + axial_error_mm,
            shift_radius_mm: 0.0,
            peak_ncc: 0.5,
            overlap_cells: 5000,
            residual_angle_deg: 0.0,
            residual_axial_um: 0.0,
            residual_radius_um: 0.0,
        };
        let radius_mm = 57.15;
        // Exact pairs: no error. Errors of 3 µm of arc and 4 µm axially on one pair of two.
        let exact = [pair(0, 1, 0.0, 0.0), pair(1, 2, 0.0, 0.0)];
        let e = registration_error(&encoder, &truth, &truth, &exact, radius_mm);
        assert!(e.pair_arc_rms_um < 1e-9 && e.pair_axial_rms_um < 1e-9, "{e:?}");
        assert_eq!(e.pairs_measured, 2);
        let arc_deg = (0.003 / radius_mm).to_degrees();
        let off = [pair(0, 1, arc_deg, 0.004), pair(1, 2, 0.0, 0.0)];
        let e = registration_error(&encoder, &truth, &truth, &off, radius_mm);
        assert!((e.pair_arc_rms_um - 3.0 / 2f64.sqrt()).abs() < 1e-6, "{e:?}");
        assert!((e.pair_axial_rms_um - 4.0 / 2f64.sqrt()).abs() < 1e-6, "{e:?}");
        // No pairs: nothing to read.
        assert!(registration_error(&encoder, &truth, &truth, &[], radius_mm).pair_arc_rms_um.is_nan());
    }

    #[test]
    fn only_picks_a_preset_or_one_seed_of_it() {
        let case = Case { preset: "bc-polished", seed: 3 };
        assert!(case.matches("bc-polished"));
        assert!(case.matches("bc-polished-3"));
        assert!(!case.matches("bc-polished-30"));
        assert!(!case.matches("bc-black-2"));
        assert!(!Case { preset: "bc-black-2", seed: 1 }.matches("bc-black"));
    }
}
