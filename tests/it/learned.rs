//! The learned parts through real ONNX Runtime (scripts/setup-onnxruntime puts it in place): the
//! shipped model against the framework's own output, session reuse, the pipeline with profile
//! correction, and what the CLI says when the runtime is missing.

use crate::common::ci_bundle;
use crestscan::bundle::{Bundle, OpenOptions};
use crestscan::domain::thread::ConnectionTable;
use crestscan::learned::{self, ModelRole, ModelSource};
use crestscan::pipeline::profile::Correction;
use crestscan::pipeline::{self, PipelineOptions};
use std::sync::atomic::AtomicBool;

/// The input and torch's output that training/profile_mlp.py wrote beside the shipped model.
fn framework_check() -> (Vec<f32>, Vec<f32>) {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/models/profile-mlp.check.json");
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    let flat = |key: &str| -> Vec<f32> {
        v[key]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|row| row.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32))
            .collect()
    };
    (flat("input"), flat("output"))
}

#[test]
fn the_shipped_mlp_through_onnx_runtime_equals_the_frameworks_output() {
    let (input, expected) = framework_check();
    assert!(input.len() >= 4 * learned::profile_mlp::SAMPLES && input.len() == expected.len());
    let model = learned::models().get(ModelRole::ProfileCorrection, None).expect("the shipped model");
    assert_eq!(model.identity.source, ModelSource::Shipped);
    let output = learned::profile_mlp::correct(&model, &input).expect("ONNX Runtime runs the shipped model");
    let worst = output.iter().zip(&expected).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(worst < 1e-4, "largest difference from torch's output {worst}");
    // The model corrects: its output is not its input.
    let moved = output.iter().zip(&input).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(moved > 1e-3, "{moved}");
    // The session went back to the pool and is reused.
    assert!(model.pool.idle_sessions() >= 1);
    let again = learned::profile_mlp::correct(&model, &input).unwrap();
    assert_eq!(again, output, "the same input gives the same output");
}

#[test]
fn profile_correction_changes_heights_and_the_report_names_the_model() {
    let bundle = Bundle::open(ci_bundle(), &ConnectionTable::api5b(), OpenOptions::default()).unwrap();
    let run = |options: &PipelineOptions| {
        pipeline::inspect(&bundle, options, &|_, _| {}, &AtomicBool::new(false)).unwrap().unwrap().report
    };
    let heights = |r: &pipeline::report::Report| -> Vec<Option<f64>> {
        r.threads.iter().flat_map(|t| t.height_mm.values.iter().copied()).collect()
    };
    let mut options = PipelineOptions::default();
    // The ci station's pixels are fine: `auto`, the default, leaves its heights classical.
    assert_eq!(options.profile.correction, Correction::Auto);
    let classic = run(&options);
    options.profile.correction = Correction::Off;
    assert_eq!(heights(&run(&options)), heights(&classic));
    options.profile.correction = Correction::On;
    let corrected_run = pipeline::inspect(&bundle, &options, &|_, _| {}, &AtomicBool::new(false)).unwrap().unwrap();
    let corrected = corrected_run.report.clone();
    // The threads kept for training pairs are the classical fits, whatever corrected the report.
    options.profile.correction = Correction::Off;
    let classic_run = pipeline::inspect(&bundle, &options, &|_, _| {}, &AtomicBool::new(false)).unwrap().unwrap();
    assert_eq!(corrected_run.threads, classic_run.threads);
    // An inspection drops the views' depth maps once fused: nothing after fusion reads them.
    assert!(classic_run.depth_maps.is_empty());
    options.profile.correction = Correction::On;
    let provenance = corrected.provenance.as_ref().unwrap();
    assert_eq!(provenance.models.len(), 1, "{:?}", provenance.models);
    let shipped = learned::models().shipped();
    assert_eq!(provenance.models[0], shipped[0]);
    assert_eq!(provenance.models[0].sha256.len(), 64);
    assert!(classic.provenance.as_ref().unwrap().models.is_empty());
    // The uncertainty was measured for classical heights: corrected ones take the failed path,
    // with no decision, and say so.
    let codes = |r: &pipeline::report::Report| r.quality.reasons.iter().map(|q| q.code).collect::<Vec<_>>();
    assert!(codes(&corrected).contains(&pipeline::quality::QualityCode::ProfileCorrected));
    assert!(!codes(&classic).contains(&pipeline::quality::QualityCode::ProfileCorrected));
    assert!(corrected.review_required);
    assert_eq!(corrected.decision, pipeline::uncertainty::Decision::Indeterminate);
    // The summary and the report page name the model.
    assert!(corrected.summary().contains(&format!("sha256 {}", shipped[0].sha256)), "{}", corrected.summary());
    let page = crestscan::export::html::report_page(&corrected, &Default::default());
    assert!(page.contains(&format!("profile-mlp (shipped, sha256 {})", shipped[0].sha256)));
    assert!(
        crestscan::export::html::report_page(&classic, &Default::default()).contains("none: the classical pipeline")
    );
    let (a, b) = (heights(&classic), heights(&corrected));
    assert_eq!(a.len(), b.len());
    let changed =
        a.iter().zip(&b).filter(|(x, y)| matches!((x, y), (Some(x), Some(y)) if (x - y).abs() > 1e-6)).count();
    assert!(changed > 0, "the correction changed no height");
    // Every corrected height is a height (a bounded change, not a model gone wrong).
    for (x, y) in a.iter().zip(&b) {
        if let (Some(x), Some(y)) = (x, y) {
            assert!((x - y).abs() < 0.5 * corrected.nominal_height_mm, "{x} → {y}");
        }
    }
    // An unknown model is an error that names the option.
    options.profile.correction_model = Some("no-such-model".into());
    let err = pipeline::inspect(&bundle, &options, &|_, _| {}, &AtomicBool::new(false)).err().expect("refused");
    let text = err.to_string();
    assert!(text.contains("no-such-model") && text.contains("profile-mlp"), "{text}");
}

#[test]
fn without_onnx_runtime_the_cli_says_what_is_missing_and_the_classical_path_runs() {
    let bin = env!("CARGO_BIN_EXE_crestscan");
    let run = |correction: &str| {
        std::process::Command::new(bin)
            .args(["inspect", "--quiet", "--profile-correction", correction])
            .arg(ci_bundle())
            .env("CRESTSCAN_ORT_LIB", "/nonexistent/libonnxruntime.so")
            .output()
            .unwrap()
    };
    let on = run("on");
    assert!(!on.status.success());
    let stderr = String::from_utf8_lossy(&on.stderr);
    assert!(stderr.contains("ONNX Runtime is not available"), "{stderr}");
    assert!(
        stderr.contains("/nonexistent/libonnxruntime.so") && stderr.contains("scripts/setup-onnxruntime"),
        "{stderr}"
    );
    let off = run("off");
    assert!(off.status.success(), "{}", String::from_utf8_lossy(&off.stderr));
    assert!(String::from_utf8_lossy(&off.stdout).contains("ACCEPT"));
    // `auto` with a model whose card says it helps buttress threads at every pixel: it is wanted,
    // cannot run, and the heights are the classical ones with the report saying why.
    let models = tempfile::tempdir().unwrap();
    std::fs::copy(concat!(env!("CARGO_MANIFEST_DIR"), "/models/profile-mlp.onnx"), models.path().join("helpful.onnx"))
        .unwrap();
    let card = serde_json::json!({
        "role": "profile_correction",
        "effect": {"measured_by": "this test", "entries": [{
            "family": "buttress", "object_pixel_mm": [0.0, 1.0], "cases": 3, "better_cases": 3,
            "classical_rms_um": 30.0, "corrected_rms_um": 10.0, "error_per_change": 0.5
        }]}
    });
    std::fs::write(models.path().join("helpful.json"), card.to_string()).unwrap();
    let auto = std::process::Command::new(bin)
        .args(["inspect", "--quiet", "--json", "--profile-correction", "auto", "--correction-model", "helpful"])
        .arg("--models-dir")
        .arg(models.path())
        .arg(ci_bundle())
        .env("CRESTSCAN_ORT_LIB", "/nonexistent/libonnxruntime.so")
        .output()
        .unwrap();
    assert!(auto.status.success(), "{}", String::from_utf8_lossy(&auto.stderr));
    let report: serde_json::Value = serde_json::from_slice(&auto.stdout).unwrap();
    let reasons = report["quality"]["reasons"].as_array().unwrap();
    let reason = reasons.iter().find(|r| r["code"] == "profile_correction_unavailable").expect("the reason");
    assert!(reason["message"].as_str().unwrap().contains("ONNX Runtime is not available"), "{reason}");
    assert_ne!(report["quality"]["status"], "ok");
    assert!(report["provenance"].get("models").is_none(), "{}", report["provenance"]);
    let choice = &report["profile_correction"];
    assert_eq!(choice["ran"], false, "{choice}");
    assert!(choice["why"].as_str().unwrap().contains("could not run"), "{choice}");
    // A card whose effect does not hold together is refused with what is wrong, not ignored.
    let broken = serde_json::json!({"role": "profile_correction", "effect": {"measured_by": "x", "entries": [{
        "family": "buttress", "object_pixel_mm": [0.2, 0.1], "cases": 1, "better_cases": 1,
        "classical_rms_um": 1.0, "corrected_rms_um": 1.0, "error_per_change": 1.0
    }]}});
    std::fs::write(models.path().join("helpful.json"), broken.to_string()).unwrap();
    let refused = std::process::Command::new(bin)
        .args(["inspect", "--quiet", "--profile-correction", "auto", "--correction-model", "helpful"])
        .arg("--models-dir")
        .arg(models.path())
        .arg(ci_bundle())
        .output()
        .unwrap();
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("helpful") && stderr.contains("object_pixel_mm"), "{stderr}");
}

#[test]
fn cli_pairs_answer_with_the_truth_or_a_cmm_file() {
    let bin = env!("CARGO_BIN_EXE_crestscan");
    let dir = tempfile::tempdir().unwrap();
    let read = |path: &std::path::Path| -> Vec<serde_json::Value> {
        std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
    };
    let with_truth = dir.path().join("truth.jsonl");
    let run =
        std::process::Command::new(bin).arg("pairs").arg(ci_bundle()).arg("--out").arg(&with_truth).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let pairs = read(&with_truth);
    assert!(pairs.len() >= 10, "{}", pairs.len());
    for p in &pairs {
        assert_eq!(p["input"].as_array().unwrap().len(), 256);
        assert_eq!(p["target"].as_array().unwrap().len(), 256);
        let (raw, truth) = (p["raw_height_mm"].as_f64().unwrap(), p["target_height_mm"].as_f64().unwrap());
        // The ci station measures within tens of µm: a pair far off would be a pairing error.
        assert!((raw - truth).abs() < 0.1, "{p}");
    }
    // The same bins against a CMM file (a thread's mean, without an angle, pairs with no bin).
    let (thread, angle) = (pairs[0]["thread"].as_u64().unwrap(), pairs[0]["angle_deg"].as_f64().unwrap());
    let cmm = dir.path().join("cmm.csv");
    std::fs::write(&cmm, format!("thread,angle_deg,height_mm\n{thread},{angle},1.6\n{thread},,1.5\n")).unwrap();
    let with_cmm = dir.path().join("cmm.jsonl");
    let run = std::process::Command::new(bin)
        .arg("pairs")
        .arg(ci_bundle())
        .arg("--cmm")
        .arg(&cmm)
        .arg("--out")
        .arg(&with_cmm)
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let pairs = read(&with_cmm);
    assert_eq!(pairs.len(), 1);
    assert_eq!(pairs[0]["target_height_mm"], 1.6);
    assert!(pairs[0].get("target").is_none());
}

/// The check training/depth_cnn.py wrote beside the shipped depth model: a fixed stack, its
/// planes, and torch's output.
fn depth_check() -> serde_json::Value {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/models/depth-unet.check.json");
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn floats(v: &serde_json::Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

#[test]
fn the_shipped_depth_unets_through_onnx_runtime_equal_the_frameworks_output() {
    use learned::depth_cnn;
    let check = depth_check();
    let shape: Vec<usize> =
        check["frames_shape"].as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as usize).collect();
    let (n, h, w) = (shape[0], shape[2], shape[3]);
    // The planes Rust computes from the check's offsets are those the framework was given.
    let offsets = [0.3, -0.2, 0.1, 0.0, -0.1, 0.2];
    let planes = depth_cnn::plane_matrix(&offsets);
    let expected_planes = floats(&check["planes"]);
    assert_eq!(planes.len(), expected_planes.len());
    assert!(planes.iter().zip(&expected_planes).all(|(a, b)| (a - b).abs() < 1e-6), "{planes:?}");
    let model = learned::models().get(ModelRole::Depth, None).expect("the shipped depth model");
    assert_eq!((model.identity.name.as_str(), model.identity.source), ("depth-unet", ModelSource::Shipped));
    let got = depth_cnn::run_tile(&model, floats(&check["frames"]), n, h, w, &planes).expect("ONNX Runtime runs it");
    for (name, got, want) in
        [("plane", &got.plane, floats(&check["plane"])), ("confidence", &got.confidence, floats(&check["confidence"]))]
    {
        assert_eq!(got.len(), want.len(), "{name}");
        let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{name}: largest difference from torch's output {worst}");
    }
    // Planes lie on the stack; the output varies over the tile (not a constant net).
    assert!(got.plane.iter().all(|p| (0.0..=(depth_cnn::PLANES - 1) as f32).contains(p)));
    let (lo, hi) = got.plane.iter().fold((f32::MAX, f32::MIN), |(a, b), &p| (a.min(p), b.max(p)));
    assert!(hi - lo > 0.01, "{lo}..{hi}");
}

#[test]
fn cnn_depth_measures_the_classical_pixels_near_truth_and_the_report_names_the_model() {
    use crestscan::pipeline::depth::DepthMethod;
    let bundle = Bundle::open(ci_bundle(), &ConnectionTable::api5b(), OpenOptions::default()).unwrap();
    // The depth maps are kept for the comparison (an inspection drops them once fused).
    let keep = pipeline::Substitutes { keep_depth_maps: true, ..Default::default() };
    let run = |options: &PipelineOptions| {
        pipeline::inspect_substituted(&bundle, options, crestscan::learned::models(), &keep).unwrap()
    };
    let mut options = PipelineOptions::default();
    options.profile.correction = Correction::Off;
    let classic = run(&options);
    assert_eq!(classic.depth_maps.len(), bundle.views.len());
    options.depth.method = DepthMethod::Cnn;
    let cnn = run(&options);
    // The same pixels are trusted; their depths are the nets'.
    let (mut errors, mut changed) = (Vec::new(), 0usize);
    for (v, (a, b)) in classic.depth_maps.iter().zip(&cnn.depth_maps).enumerate() {
        let truth_path = ci_bundle().join(format!("truth/{}.depth.pfm", bundle.views[v].id));
        let (_, _, truth) = crestscan::sim::pfm::read(&std::fs::read(truth_path).unwrap()).unwrap();
        for ((x, y), t) in
            a.depth_mm.iter().zip(&b.depth_mm).zip(truth.chunks_exact(a.width).step_by(a.row_step).flatten())
        {
            assert_eq!(x.is_finite(), y.is_finite());
            if x.is_finite() && t.is_finite() {
                changed += usize::from((x - y).abs() > 1e-6);
                errors.push((1e3 * (y - t)).abs());
            }
        }
    }
    assert!(changed > errors.len() / 2, "{changed} of {} changed", errors.len());
    errors.sort_by(f32::total_cmp);
    let median_um = errors[errors.len() / 2];
    // Within half a plane's spacing of truth at the median: a net that had learnt nothing (the
    // middle plane everywhere) is off by about a quarter of the stack, four planes. (The shipped
    // model's median here is about a fifth of a plane, several times the classical measure's
    // error: docs/models.md.)
    let offsets: Vec<f64> = bundle.views[0].frames.iter().map(|f| f.offset_mm).collect();
    let span_mm = offsets.iter().fold(f64::MIN, |a, &b| a.max(b)) - offsets.iter().fold(f64::MAX, |a, &b| a.min(b));
    let plane_um = 1e3 * span_mm / (learned::depth_cnn::PLANES - 1) as f64;
    assert!((median_um as f64) < 0.5 * plane_um, "median depth error {median_um} µm, planes {plane_um} µm apart");
    let models = &cnn.report.provenance.as_ref().unwrap().models;
    assert_eq!(models.len(), 1, "{models:?}");
    assert_eq!(models[0].role, ModelRole::Depth);
    assert_eq!(models[0].name, "depth-unet");
    assert!(cnn.report.timings.iter().any(|t| t.stage == pipeline::report::DEPTH_CNN));
    assert!(cnn.report.summary().contains("depth from the depth model depth-unet"), "{}", cnn.report.summary());
    // The uncertainty was measured for the classical depth: the nets' heights take the failed
    // path, with no decision, and say so.
    let codes: Vec<_> = cnn.report.quality.reasons.iter().map(|q| q.code).collect();
    assert!(codes.contains(&pipeline::quality::QualityCode::DepthLearned), "{codes:?}");
    assert_eq!(cnn.report.decision, pipeline::uncertainty::Decision::Indeterminate);
    assert!(!classic.report.quality.reasons.iter().any(|q| q.code == pipeline::quality::QualityCode::DepthLearned));
    // An unknown depth model is refused, naming its option.
    options.depth.model = Some("no-such-depth".into());
    let err = pipeline::inspect(&bundle, &options, &|_, _| {}, &AtomicBool::new(false)).err().expect("refused");
    assert!(err.to_string().contains("no-such-depth") && err.to_string().contains("depth-unet"), "{err}");
    assert_eq!(crestscan::problem::ErrorCode::culprit(&err).as_deref(), Some("depth.model"));
}

/// The bundle's frames, counting how often each is decoded.
struct Counting<'a> {
    bundle: &'a Bundle,
    reads: std::sync::Mutex<std::collections::HashMap<(usize, usize), usize>>,
}

impl crestscan::domain::frame::FrameSource for Counting<'_> {
    fn read_frame(
        &self,
        view: usize,
        frame: usize,
    ) -> Result<crestscan::domain::frame::Frame, crestscan::domain::frame::FrameError> {
        *self.reads.lock().unwrap().entry((view, frame)).or_default() += 1;
        crestscan::domain::frame::FrameSource::read_frame(self.bundle, view, frame)
    }
}

impl crestscan::domain::frame::Recording for Counting<'_> {
    fn part(&self) -> &crestscan::domain::part::Part {
        self.bundle.part()
    }
    fn optics(&self) -> &crestscan::domain::optics::Optics {
        self.bundle.optics()
    }
    fn views(&self) -> &[crestscan::domain::frame::View] {
        self.bundle.views()
    }
}

#[test]
fn every_depth_estimator_decodes_each_frame_once() {
    use crestscan::domain::frame::Recording;
    use crestscan::pipeline::depth::DepthMethod;
    let bundle = Bundle::open(ci_bundle(), &ConnectionTable::api5b(), OpenOptions::default()).unwrap();
    let frames: usize = bundle.views().iter().map(|v| v.frames.len()).sum();
    for method in [DepthMethod::Classic, DepthMethod::Cnn] {
        let counting = Counting { bundle: &bundle, reads: Default::default() };
        let mut options = PipelineOptions::default();
        options.profile.correction = Correction::Off;
        options.depth.method = method;
        let inspection = pipeline::inspect(&counting, &options, &|_, _| {}, &AtomicBool::new(false)).unwrap().unwrap();
        let reads = counting.reads.into_inner().unwrap();
        assert_eq!(reads.len(), frames, "{method:?}: every frame read");
        assert!(reads.values().all(|&n| n == 1), "{method:?}: {reads:?}");
        // The nets still ran: the report names their model.
        let models = inspection.report.provenance.as_ref().map_or(0, |p| p.models.len());
        assert_eq!(models, usize::from(method == DepthMethod::Cnn), "{method:?}");
    }
}
