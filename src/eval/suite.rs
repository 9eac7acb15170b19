//! The benchmark suites: their cases, and running one (render once, cached; decode as the yardstick;
//! inspect; compare with truth).

use crate::eval::truth::{Accuracy, BlackCrest, RegistrationError, black_crests, compare, registration_error};
use crate::sim::Truth;
use serde::Serialize;

/// A benchmark case: a preset rendered with one seed, at its own station or at a random one.
#[derive(Clone, Copy, Debug)]
pub struct Case {
    pub preset: &'static str,
    pub seed: u64,
    /// The seed of the random station the preset's part is recorded at
    /// ([`crate::sim::station::random`]); None: the preset's own station.
    pub station_seed: Option<u64>,
}

impl Case {
    pub const fn at(preset: &'static str, seed: u64) -> Self {
        Self { preset, seed, station_seed: None }
    }
}

/// The accuracy suite: the standard preset, the defects that decide verdicts, and the seed's
/// Table 1, each with a seed of its own that no test uses. Its role as it is: the targets are read
/// on it, and the black-crest and registration thresholds were chosen while looking at it, so it
/// is a tuning set too; the held-out suite is where its numbers are checked.
pub const ACCURACY_SUITE: &[Case] = &[
    Case::at("standard", 9001),
    Case::at("bc-black-2", 9002),
    Case::at("bc-arc-over-25", 9003),
    Case::at("lc-round-black", 9004),
    Case::at("bc-polished", 9005),
    Case::at("seed-table1", 9006),
];

/// The held-out suite: the defect presets rendered again with other seeds, none of which chose a
/// setting. Seeds rendered only to check a change joined it after that change; the seeds that
/// chose something are in [`TUNING_SUITE`] instead (the history: docs/notebook/accuracy.md).
pub const HOLDOUT_SUITE: &[Case] = &[
    Case::at("lc-round-black", 4),
    Case::at("lc-round-black", 5),
    Case::at("lc-round-black", 6),
    Case::at("lc-accept", 1),
    Case::at("bc-black-1", 1),
    Case::at("bc-black-1", 2),
    Case::at("bc-black-2", 1),
    Case::at("bc-black-2", 2),
    Case::at("bc-black-3", 1),
    Case::at("bc-arc-over-25", 1),
    Case::at("bc-arc-over-25", 2),
    Case::at("bc-arc-over-25", 3),
    Case::at("bc-polished", 1),
    Case::at("bc-polished", 2),
    Case::at("bc-polished", 3),
    Case::at("bc-polished", 4),
    Case::at("bc-polished", 5),
    Case::at("bc-polished", 6),
    Case::at("bc-polished", 7),
    Case::at("bc-polished", 8),
    Case::at("bc-polished", 13),
    Case::at("bc-polished", 14),
    Case::at("bc-polished", 15),
    Case::at("bc-polished", 16),
    Case::at("bc-polished-long", 4),
    Case::at("bc-polished-end", 1),
    Case::at("bc-polished-end", 2),
    Case::at("bc-polished-end", 3),
    Case::at("lc-round-black", 7),
    Case::at("bc-polished-long", 5),
    Case::at("bc-polished-long", 6),
    Case::at("bc-polished-end", 4),
    Case::at("bc-polished-end", 5),
];

/// The held-out seeds that chose a setting, kept as the tuning set they became: round seeds 1–3
/// chose the width of the height window (seed 2 showed the faint end bin a dark run now bridges);
/// polished seeds 9–12 chose how the polished crest's ends are fitted (seed 9 had a wrong verdict
/// after the steep-edge depth change); polished-long seeds 1–3 chose where the harmonic arch fit
/// takes over (`HARMONIC_ARCH_DEG`).
pub const TUNING_SUITE: &[Case] = &[
    Case::at("lc-round-black", 1),
    Case::at("lc-round-black", 2),
    Case::at("lc-round-black", 3),
    Case::at("bc-polished", 9),
    Case::at("bc-polished", 10),
    Case::at("bc-polished", 11),
    Case::at("bc-polished", 12),
    Case::at("bc-polished-long", 1),
    Case::at("bc-polished-long", 2),
    Case::at("bc-polished-long", 3),
];

/// The defect presets a random station records, in turn: every thread family and defect kind.
pub const STATION_PRESETS: &[&str] = &[
    "standard",
    "bc-black-1",
    "bc-black-2",
    "bc-black-3",
    "bc-arc-over-25",
    "lc-round-black",
    "lc-accept",
    "bc-polished",
    "bc-polished-long",
    "bc-polished-end",
    "seed-table1",
];

/// Station seeds of the tuning stations: settings are chosen on these.
pub const STATION_TUNING_SEEDS: std::ops::Range<u64> = 1..13;
/// Station seeds of the station benchmark: rendered after every setting was chosen, used to
/// choose none.
pub const STATION_BENCH_SEEDS: std::ops::Range<u64> = 101..141;
/// Station seeds of a second check set, rendered after the settings of 2026-12-04 were chosen on
/// the tuning stations: where a setting chosen since is checked besides the benchmark.
pub const STATION_CHECK_SEEDS: std::ops::Range<u64> = 151..181;

fn station_cases(seeds: std::ops::Range<u64>) -> Vec<Case> {
    seeds
        .map(|seed| Case {
            preset: STATION_PRESETS[(seed as usize) % STATION_PRESETS.len()],
            seed,
            station_seed: Some(seed),
        })
        .collect()
}

/// A named benchmark suite.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Suite {
    Accuracy,
    Holdout,
    /// The held-out seeds that chose a setting ([`TUNING_SUITE`]).
    Tuning,
    /// The defect presets at random stations ([`STATION_BENCH_SEEDS`]).
    Stations,
    /// The same at the tuning stations ([`STATION_TUNING_SEEDS`]).
    StationsTuning,
    /// The same at the check stations ([`STATION_CHECK_SEEDS`]).
    StationsCheck,
}

impl Suite {
    pub fn name(self) -> &'static str {
        match self {
            Suite::Accuracy => "accuracy",
            Suite::Holdout => "holdout",
            Suite::Tuning => "tuning",
            Suite::Stations => "stations",
            Suite::StationsTuning => "stations-tuning",
            Suite::StationsCheck => "stations-check",
        }
    }

    pub fn cases(self) -> Vec<Case> {
        match self {
            Suite::Accuracy => ACCURACY_SUITE.to_vec(),
            Suite::Holdout => HOLDOUT_SUITE.to_vec(),
            Suite::Tuning => TUNING_SUITE.to_vec(),
            Suite::Stations => station_cases(STATION_BENCH_SEEDS),
            Suite::StationsTuning => station_cases(STATION_TUNING_SEEDS),
            Suite::StationsCheck => station_cases(STATION_CHECK_SEEDS),
        }
    }

    /// Where its renderings are cached unless `--work` says otherwise.
    pub fn default_work_dir(self) -> &'static str {
        match self {
            Suite::Accuracy => "out/bench",
            Suite::Holdout | Suite::Tuning => "out/holdout",
            Suite::Stations | Suite::StationsTuning | Suite::StationsCheck => "out/stations",
        }
    }
}

impl Case {
    /// The case's folder under the work directory, and its name for `--only`.
    pub fn name(&self) -> String {
        match self.station_seed {
            None => format!("{}-{}", self.preset, self.seed),
            Some(station) => format!("{}@station{}-{}", self.preset, station, self.seed),
        }
    }

    /// The case's simulation: the preset, moved to its random station when it has one.
    pub fn spec(&self) -> Option<crate::sim::SimSpec> {
        let spec = crate::sim::preset(self.preset)?;
        Some(match self.station_seed {
            None => spec,
            Some(seed) => {
                use crate::sim::station;
                let s = station::random(seed, spec.part.pipe_od_mm / 2.0, station::z_span_mm(&spec));
                station::at_station(&spec, &s)
            }
        })
    }

    /// `--only` picks a case by its preset (every seed) or by `preset-seed`.
    pub fn matches(&self, only: &str) -> bool {
        only == self.preset || only == self.name()
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CaseResult {
    pub preset: String,
    pub seed: u64,
    /// The random station's seed, when the case is at one, and the station as the report read it.
    pub station_seed: Option<u64>,
    pub station: Option<crate::domain::station::Station>,
    /// The arc a random station's views cover when it is a sector of the ring, degrees.
    pub sector_deg: Option<f64>,
    pub verdict: crate::domain::rules::Verdict,
    pub truth_verdict: crate::domain::rules::Verdict,
    pub quality: crate::pipeline::quality::QualityStatus,
    pub quality_codes: Vec<crate::pipeline::quality::QualityCode>,
    pub pairs_expected: usize,
    pub pairs_measured: usize,
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
    /// The inspection's report (`bench --reports` writes it), not in the results' JSON.
    #[serde(skip)]
    pub report: Option<Box<crate::pipeline::report::Report>>,
}

impl CaseResult {
    /// How the benchmark's blocks name the case: "preset seed N".
    pub fn label(&self) -> String {
        match self.station_seed {
            None => format!("{} seed {}", self.preset, self.seed),
            Some(station) => format!("{} at station {} (seed {})", self.preset, station, self.seed),
        }
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
    let spec = case.spec().ok_or_else(|| BenchError::Preset(case.preset.into()))?;
    let dir = work.join(case.name());
    let rendered = render_once(&spec, case.seed, &dir)?;
    // Truth is rewritten every run (it is cheap, the frames are not): a cached rendering keeps its
    // pixels, but the verdict and black-crest arcs must follow the current rule engine.
    let truth: Truth = crate::sim::write_truth(&spec, case.seed, &dir)?;
    let table = crate::domain::thread::ConnectionTable::api5b();
    let bundle = Bundle::open(&dir, &table, OpenOptions::default())?;
    let timed = timed_runs(&bundle, options, repeat)?;
    let inspection = &timed.inspection;
    let accuracy = compare(&inspection.report, &truth);
    let depth = depth_error(&bundle, &dir, &inspection.depth_maps)?;
    let truth_poses = truth.poses_of(&bundle.views).map_err(BenchError::Other)?;
    let encoder: Vec<_> = bundle.views.iter().map(|v| v.pose).collect();
    let table1 = if case.preset == "seed-table1" { table1_rows(&inspection.report, &truth) } else { Vec::new() };
    let mut result = CaseResult {
        black_crests: black_crests(&inspection.report, &truth),
        preset: case.preset.into(),
        seed: case.seed,
        station_seed: case.station_seed,
        station: inspection.report.station.clone(),
        sector_deg: spec
            .station
            .as_ref()
            .filter(|s| s.views_rendered < s.views_around)
            .map(|s| s.views_rendered as f64 * 360.0 / s.views_around as f64),
        verdict: inspection.report.verdict,
        truth_verdict: truth.verdict,
        quality: inspection.report.quality.status,
        quality_codes: inspection.report.quality.reasons.iter().map(|r| r.code).collect(),
        pairs_expected: inspection.report.registration.pairs_expected,
        pairs_measured: inspection.report.registration.pairs_measured,
        accuracy,
        depth_rms_um: depth.rms_um,
        depth_median_um: depth.median_um,
        depth_coverage: depth.coverage,
        registration: registration_error(
            &encoder,
            &inspection.poses,
            &truth_poses,
            &inspection.report.registration.pairs,
            inspection.report.pipe_od_mm / 2.0,
        ),
        decode_seconds: timed.decode_seconds,
        inspect_seconds: timed.inspect_seconds,
        render: rendered,
        stage_seconds: timed.stage_seconds,
        table1,
        helix_z_error_um: {
            let (pitch, dz) = (inspection.report.helix.pitch_mm, inspection.report.helix.z_h_mm - truth.helix_z_h_mm);
            1e3 * (dz - pitch * (dz / pitch).round())
        },
        report: None,
        encoder_mean_axial_offset_um: 1e3
            * encoder.iter().zip(&truth_poses).map(|(e, t)| e.axial_mm - t.axial_mm).sum::<f64>()
            / encoder.len().max(1) as f64,
    };
    // Moved, not copied: most runs never write it.
    result.report = Some(Box::new(timed.inspection.report));
    Ok(result)
}

/// Renders the case into `dir` unless a finished rendering is there: it leaves its summary
/// (render time, size) beside the bundle.
fn render_once(
    spec: &crate::sim::SimSpec,
    seed: u64,
    dir: &std::path::Path,
) -> Result<crate::sim::SimSummary, BenchError> {
    let done = dir.join("render-summary.json");
    if let Some(summary) = std::fs::read(&done).ok().and_then(|b| serde_json::from_slice(&b).ok()) {
        return Ok(summary);
    }
    let _ = std::fs::remove_dir_all(dir);
    let summary = crate::sim::simulate(spec, seed, dir)?;
    std::fs::write(&done, serde_json::to_vec(&summary).expect("serialises"))
        .map_err(|e| BenchError::Other(e.to_string()))?;
    Ok(summary)
}

/// The last inspection of `repeat` runs, and the medians of the runs' decode and inspection times.
struct TimedRuns {
    inspection: crate::pipeline::Inspection,
    decode_seconds: f64,
    inspect_seconds: f64,
    /// Stage times of the run whose inspection time is the median.
    stage_seconds: Vec<(String, f64)>,
}

/// Yardstick: decode every frame once, with the pipeline's parallelism (views across cores).
/// Decode and inspection alternate `repeat` times and each time is the median of its runs: on a
/// shared 2-core machine one run of either can be 30% off.
fn timed_runs(
    bundle: &crate::bundle::Bundle,
    options: &crate::pipeline::PipelineOptions,
    repeat: usize,
) -> Result<TimedRuns, BenchError> {
    use rayon::prelude::*;
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
    // (decode s, inspect s, stage times) per run; the results are the same every run, so only
    // the last inspection is kept.
    let mut runs = Vec::new();
    let mut last = None;
    for _ in 0..repeat.max(1) {
        let decode_seconds = decode()?;
        drop(last.take()); // the previous run's maps are not held while this one runs
        let started = std::time::Instant::now();
        // The depth maps are kept for the depth error against the truth (an inspection drops
        // them once fused).
        let keep = crate::pipeline::Substitutes { keep_depth_maps: true, ..Default::default() };
        let inspection = crate::pipeline::inspect_substituted(bundle, options, crate::learned::models(), &keep)?;
        let stages: Vec<(String, f64)> =
            inspection.report.timings.iter().map(|t| (t.stage.clone(), t.seconds)).collect();
        runs.push((decode_seconds, started.elapsed().as_secs_f64(), stages));
        last = Some(inspection);
    }
    let inspection = last.expect("at least one run");
    let median_of = |mut v: Vec<f64>| crate::numeric::stats::median(&mut v).expect("at least one run");
    let decode_seconds = median_of(runs.iter().map(|r| r.0).collect());
    let inspect_seconds = median_of(runs.iter().map(|r| r.1).collect());
    let stage_seconds = runs
        .into_iter()
        .min_by(|a, b| (a.1 - inspect_seconds).abs().total_cmp(&(b.1 - inspect_seconds).abs()))
        .expect("at least one run")
        .2;
    Ok(TimedRuns { inspection, decode_seconds, inspect_seconds, stage_seconds })
}

/// Depth error over every pixel truth has a depth for: RMS and median of the trusted ones (µm),
/// and the share trusted.
struct DepthError {
    rms_um: f64,
    median_um: f64,
    coverage: f64,
}

fn depth_error(
    bundle: &crate::bundle::Bundle,
    dir: &std::path::Path,
    depth_maps: &[crate::pipeline::depth::DepthMap],
) -> Result<DepthError, BenchError> {
    let (mut sq, mut errors, mut seen, mut total) = (0.0, Vec::new(), 0usize, 0usize);
    for (view, depth) in bundle.views.iter().zip(depth_maps) {
        let t = crate::sim::read_true_depth(dir, &view.id).map_err(BenchError::Other)?;
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
    Ok(DepthError {
        rms_um: (sq / seen.max(1) as f64).sqrt(),
        median_um: errors.get(errors.len() / 2).copied().unwrap_or(f64::NAN),
        coverage: seen as f64 / total.max(1) as f64,
    })
}

/// The seed's Table 1: each thread's mean height over bins 0–4°, measured and true.
fn table1_rows(report: &crate::pipeline::report::Report, truth: &Truth) -> Vec<(u32, f64, f64)> {
    (1..=10u32)
        .filter_map(|i| {
            let r = report.threads.iter().find(|t| t.index == i)?;
            let t = truth.threads.iter().find(|t| t.index == i)?;
            let bins: Vec<(f64, f64)> =
                (0..5).filter_map(|k| Some((r.height_mm.values[k]?, t.height_mm.values[k]?))).collect();
            (!bins.is_empty()).then(|| {
                let n = bins.len() as f64;
                (i, bins.iter().map(|b| b.0).sum::<f64>() / n, bins.iter().map(|b| b.1).sum::<f64>() / n)
            })
        })
        .collect()
}
