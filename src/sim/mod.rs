//! Focal-stack simulator: writes a bundle per docs/bundle.md with exact ground truth.
//!
//! `simulate(&spec, seed, out)` renders every frame of every view (see [`render`]), writes
//! manifest.json, the frames as PNG, and truth/ (truth.json and one depth PFM per view). The same
//! spec and seed give byte-identical files.

pub mod appearance;
pub mod part;
pub mod pfm;
pub(crate) mod presets;
pub mod render;
pub mod station;

pub use presets::{PRESETS, PresetInfo, SEED_TABLE1_HEIGHTS_MM, preset};

use crate::bundle::{FORMAT_V1, FrameEntry, Manifest, PartManifest, ViewManifest};
use crate::domain::optics::{Optics, ViewPose};
use crate::domain::rules::{self, ArcRule, Assessment};
use appearance::Appearance;
use part::{PartModel, ThreadTruth};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use render::{Camera, Sensor, Tracer};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A view as planned by the fixture: where the encoders say the camera is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewPlan {
    pub id: String,
    pub pose: ViewPose,
}

/// Encoder error bounds (uniform): the true pose differs from the planned one by up to these.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseJitter {
    pub angle_deg: f64,
    pub axial_mm: f64,
    pub lens_radius_mm: f64,
}

/// Everything a simulated bundle is made from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimSpec {
    pub name: String,
    pub description: String,
    /// What the manifest says about the part.
    pub part_manifest: PartManifest,
    pub part: PartModel,
    pub optics: Optics,
    pub width: u32,
    pub height: u32,
    pub views: Vec<ViewPlan>,
    /// Frame offsets, the same for every view, growing near → far.
    pub offsets_mm: Vec<f64>,
    pub jitter: PoseJitter,
    /// Truth heights are given for crest points up to this z (the inspected length).
    pub truth_z_end_mm: f64,
    pub appearance: Appearance,
    pub sensor: Sensor,
    /// The station the preset was moved to, when it was ([`station::at_station`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub station: Option<station::StationSpec>,
    /// A refocus the manifest does not know of, mm: every frame is rendered this much further along
    /// the camera's axis than its declared offset (a station that drifted after its study).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub focus_drift_mm: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    pub connection: Option<String>,
    pub family: crate::domain::thread::Family,
    pub pipe_od_mm: f64,
    pub lc_mm: f64,
    pub circumference_mm: f64,
    pub pitch_mm: f64,
    pub nominal_height_mm: f64,
    pub threads: Vec<ThreadTruth>,
    pub verdict: rules::Verdict,
    pub reasons: Vec<String>,
    // Extras.
    pub preset: String,
    pub seed: u64,
    /// The seed of the placement (poses and sensor noise) where it is not `seed`: a repeat run of
    /// the same part (same texture) placed again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub placement_seed: Option<u64>,
    pub helix_z_h_mm: f64,
    pub taper_on_diameter: f64,
    pub height_tolerance_mm: f64,
    pub assessment: Assessment,
    pub true_poses: BTreeMap<String, ViewPose>,
    pub part_model: PartModel,
    pub depth_of_field_mm: f64,
    pub notes: Vec<String>,
}

impl Truth {
    /// The true poses of `views`, in their order; Err names the first view truth has none for.
    pub fn poses_of(&self, views: &[crate::domain::frame::View]) -> Result<Vec<ViewPose>, String> {
        views
            .iter()
            .map(|v| self.true_poses.get(&v.id).copied().ok_or_else(|| format!("truth lacks the pose of {}", v.id)))
            .collect()
    }
}

/// Where a rendered bundle keeps view `view_id`'s true depth map (PFM; NaN off the part).
pub fn true_depth_path(bundle_dir: &Path, view_id: &str) -> PathBuf {
    bundle_dir.join("truth").join(format!("{view_id}.depth.pfm"))
}

/// View `view_id`'s true depth map at full resolution, row-major; Err names the file.
pub fn read_true_depth(bundle_dir: &Path, view_id: &str) -> Result<Vec<f32>, String> {
    let path = true_depth_path(bundle_dir, view_id);
    let bytes = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    pfm::read(&bytes).map(|(_, _, depth)| depth).map_err(|e| format!("{}: {e}", path.display()))
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimSummary {
    pub files: usize,
    pub bytes: u64,
    pub frames: usize,
    pub seconds: f64,
    pub verdict: rules::Verdict,
}

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: {message}")]
    Encode { path: String, message: String },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SimError + '_ {
    move |source| SimError::Io { path: path.display().to_string(), source }
}

impl SimSpec {
    /// True poses: the plan moved by seeded encoder errors.
    pub fn true_poses(&self, seed: u64) -> Vec<ViewPose> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x7035_E5EE_D000_0001);
        let j = self.jitter;
        let mut uniform = |bound: f64| if bound > 0.0 { rng.random_range(-bound..=bound) } else { 0.0 };
        self.views
            .iter()
            .map(|v| ViewPose {
                angle_deg: v.pose.angle_deg + uniform(j.angle_deg),
                axial_mm: v.pose.axial_mm + uniform(j.axial_mm),
                lens_radius_mm: v.pose.lens_radius_mm + uniform(j.lens_radius_mm),
            })
            .collect()
    }

    pub fn manifest(&self) -> Manifest {
        Manifest {
            station: None,
            format: FORMAT_V1.to_string(),
            part: self.part_manifest.clone(),
            optics: self.optics.clone(),
            views: self
                .views
                .iter()
                .map(|v| ViewManifest {
                    id: v.id.clone(),
                    pose: v.pose,
                    frames: (0..self.offsets_mm.len())
                        .map(|k| FrameEntry { file: frame_path(&v.id, k), offset_mm: self.offsets_mm[k] })
                        .collect(),
                })
                .collect(),
        }
    }

    pub fn truth(&self, seed: u64) -> Truth {
        self.truth_placed(seed, seed)
    }

    /// The truth of the part `seed` renders, placed on the station as `placement` draws it (the
    /// encoders' errors): a repeat run of the same part has another placement.
    pub fn truth_placed(&self, seed: u64, placement: u64) -> Truth {
        let (threads, input) = self.part.thread_truth(self.truth_z_end_mm);
        let assessment = rules::assess(&input, ArcRule::PerThread);
        let poses = self.true_poses(placement);
        let dof = self.optics.depth_of_field_mm(1.0);
        Truth {
            connection: self.part_manifest.connection.clone(),
            family: self.part.form.family,
            pipe_od_mm: self.part.pipe_od_mm,
            lc_mm: self.part.lc_mm,
            circumference_mm: self.part.circumference_mm(),
            pitch_mm: self.part.form.pitch_mm,
            nominal_height_mm: self.part.form.height_mm,
            threads,
            verdict: assessment.verdict,
            reasons: assessment.messages(),
            preset: self.name.clone(),
            seed,
            placement_seed: (placement != seed).then_some(placement),
            helix_z_h_mm: self.part.helix_z_h_mm,
            taper_on_diameter: self.part.form.taper_on_diameter,
            height_tolerance_mm: self.part.form.height_tolerance_mm,
            assessment,
            true_poses: self.views.iter().zip(poses).map(|(v, p)| (v.id.clone(), p)).collect(),
            part_model: self.part.clone(),
            depth_of_field_mm: dof,
            notes: vec![
                format!(
                    "depth of field (blur circle ≤ 1 px) {:.3} mm against a thread height of {:.3} mm",
                    dof, self.part.form.height_mm
                ),
                format!(
                    "object pixel {:.1} µm at focus; frame step {:.3} mm",
                    1e3 * self.optics.object_pixel_mm(self.optics.focus_distance_mm),
                    self.offsets_mm.get(1).map_or(0.0, |o| o - self.offsets_mm[0])
                ),
                "depth maps: camera at offset 0, true pose; heights per the bundle contract".into(),
            ]
            .into_iter()
            .chain(self.station.as_ref().map(|s| s.summary()))
            .collect(),
        }
    }

    /// Bytes of raw pixels the bundle holds.
    pub fn raw_bytes(&self) -> u64 {
        let bytes_per_sample = if self.sensor.bit_depth > 8 { 2 } else { 1 };
        let channels = if self.sensor.monochrome { 1 } else { 3 };
        self.views.len() as u64
            * self.offsets_mm.len() as u64
            * self.width as u64
            * self.height as u64
            * channels
            * bytes_per_sample
    }
}

pub fn frame_path(view_id: &str, k: usize) -> String {
    format!("{view_id}/{k:03}.png")
}

fn mix(seed: u64, a: u64, b: u64) -> u64 {
    let mut x = seed ^ a.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ b.wrapping_mul(0xD6E8_FEB8_6659_FD93);
    x ^= x >> 32;
    x = x.wrapping_mul(0xD6E8_FEB8_6659_FD93);
    x ^ (x >> 29)
}

/// Writes truth/truth.json only (no rendering): for designing presets and for quick checks.
pub fn write_truth(spec: &SimSpec, seed: u64, out: &Path) -> Result<Truth, SimError> {
    write_truth_placed(spec, seed, seed, out)
}

/// [`write_truth`] for the part `seed` renders at the placement `placement` draws.
pub fn write_truth_placed(spec: &SimSpec, seed: u64, placement: u64, out: &Path) -> Result<Truth, SimError> {
    let truth = spec.truth_placed(seed, placement);
    let dir = out.join("truth");
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let path = dir.join("truth.json");
    let json = serde_json::to_vec_pretty(&truth).expect("truth serialises");
    std::fs::write(&path, json).map_err(io(&path))?;
    Ok(truth)
}

/// Renders the whole bundle into `out` (created if needed).
pub fn simulate(spec: &SimSpec, seed: u64, out: &Path) -> Result<SimSummary, SimError> {
    simulate_with_progress(spec, seed, out, &|_| {})
}

/// [`simulate`], calling `progress` with the number of frames written so far after each frame
/// (from the rendering threads, in no particular order).
pub fn simulate_with_progress(
    spec: &SimSpec,
    seed: u64,
    out: &Path,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<SimSummary, SimError> {
    simulate_placed(spec, seed, seed, out, progress)
}

/// [`simulate_with_progress`] of the part `seed` renders (its texture), placed as `placement`
/// draws it: the encoders' errors and the sensor's noise. The same `seed` with another
/// `placement` is the same part measured again after being repositioned.
pub fn simulate_placed(
    spec: &SimSpec,
    seed: u64,
    placement: u64,
    out: &Path,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<SimSummary, SimError> {
    let started = Instant::now();
    let written = std::sync::atomic::AtomicUsize::new(0);
    std::fs::create_dir_all(out).map_err(io(out))?;
    let truth = write_truth_placed(spec, seed, placement, out)?;
    let manifest_path = out.join("manifest.json");
    let manifest = serde_json::to_vec_pretty(&spec.manifest()).expect("manifest serialises");
    std::fs::write(&manifest_path, manifest).map_err(io(&manifest_path))?;

    let tracer = Tracer::new(&spec.part);
    let poses = spec.true_poses(placement);
    // Truth depth per view.
    let cameras: Vec<Camera> = poses
        .par_iter()
        .zip(&spec.views)
        .map(|(pose, view)| {
            let mut camera = Camera {
                optics: &spec.optics,
                pose: pose.camera_to_pipe(),
                width: spec.width,
                height: spec.height,
                depth_map_cached: Vec::new(),
            };
            let depth = camera.depth_map(&tracer);
            let path = true_depth_path(out, &view.id);
            let mut bytes = Vec::new();
            pfm::write(&mut bytes, spec.width as usize, spec.height as usize, &depth).map_err(io(&path))?;
            std::fs::write(&path, bytes).map_err(io(&path))?;
            camera.depth_map_cached = depth;
            Ok(camera)
        })
        .collect::<Result<_, SimError>>()?;

    // Frames, each independent (own noise stream), so parallel order cannot change a byte.
    for view in &spec.views {
        let dir = out.join(&view.id);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    }
    let texture_seed = mix(seed, 0xC0FFEE, 0);
    let jobs: Vec<(usize, usize)> =
        (0..spec.views.len()).flat_map(|v| (0..spec.offsets_mm.len()).map(move |k| (v, k))).collect();
    jobs.par_iter().try_for_each(|&(v, k)| {
        let samples = render::render_frame(
            &cameras[v],
            &tracer,
            &spec.appearance,
            &spec.sensor,
            spec.offsets_mm[k] + spec.focus_drift_mm,
            texture_seed,
            mix(placement, v as u64 + 1, k as u64 + 1),
        );
        let path = out.join(frame_path(&spec.views[v].id, k));
        write_png(&path, spec.width, spec.height, &spec.sensor, &samples)?;
        progress(written.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1);
        Ok(())
    })?;

    let (files, bytes) = dir_size(out).map_err(io(out))?;
    Ok(SimSummary {
        files,
        bytes,
        frames: jobs.len(),
        seconds: started.elapsed().as_secs_f64(),
        verdict: truth.verdict,
    })
}

fn write_png(path: &Path, width: u32, height: u32, sensor: &Sensor, samples: &[u16]) -> Result<(), SimError> {
    use image::ImageEncoder;
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let mut bytes = Vec::new();
    let encoder = PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, FilterType::Adaptive);
    use image::ExtendedColorType::{L8, L16, Rgb8, Rgb16};
    let result = if sensor.bit_depth > 8 {
        let raw: Vec<u8> = samples.iter().flat_map(|v| v.to_ne_bytes()).collect();
        encoder.write_image(&raw, width, height, if sensor.monochrome { L16 } else { Rgb16 })
    } else {
        let raw: Vec<u8> = samples.iter().map(|&v| v as u8).collect();
        encoder.write_image(&raw, width, height, if sensor.monochrome { L8 } else { Rgb8 })
    };
    result.map_err(|e| SimError::Encode { path: path.display().to_string(), message: e.to_string() })?;
    std::fs::write(path, bytes).map_err(io(path))
}

fn dir_size(dir: &Path) -> std::io::Result<(usize, u64)> {
    let (mut files, mut bytes) = (0, 0);
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let meta = entry.metadata()?;
        if meta.is_dir() {
            let (f, b) = dir_size(&entry.path())?;
            files += f;
            bytes += b;
        } else {
            files += 1;
            bytes += meta.len();
        }
    }
    Ok((files, bytes))
}

/// A master's calibration certificate written from its truth, in the CMM JSON format
/// (docs/bundle.md, "CMM measurements"): every thread's height at every 1° bin the truth holds,
/// each with seeded normal noise of standard deviation `expanded_uncertainty_mm / 2` (k = 2), the
/// stated uncertainty, an instrument and a calibration date.
pub fn certificate(truth: &Truth, expanded_uncertainty_mm: f64, seed: u64) -> serde_json::Value {
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = ChaCha8Rng::seed_from_u64(mix(seed, 0xCE27_1F1C, 0));
    let sigma_mm = expanded_uncertainty_mm / 2.0;
    let mut points = Vec::new();
    for t in &truth.threads {
        for (angle, value) in t.height_mm.angles_deg.iter().zip(&t.height_mm.values) {
            if let Some(h) = value {
                let noise: f64 = StandardNormal.sample(&mut rng);
                // Rounded as a CMM's report is: 0.1 µm.
                let height = ((h + sigma_mm * noise) * 1e4).round() / 1e4;
                points.push(serde_json::json!({ "thread": t.index, "angle_deg": angle, "height_mm": height }));
            }
        }
    }
    serde_json::json!({
        "instrument": format!("simulated CMM (crestscan simulate, {} seed {seed})", truth.preset),
        "measured_at": "2026-01-05T08:00:00Z",
        "uncertainty_mm": expanded_uncertainty_mm,
        "points": points,
    })
}
