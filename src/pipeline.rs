//! The whole inspection as one library call, used by the CLI and (later) the service's workers:
//! bundle → depth (per view, in parallel) → cloud → fuse → profile → crest → rules → report.
//! Progress is reported through a callback (stage, fraction); a cancellation flag stops it promptly
//! (checked between frames and stages).

use crate::bundle::{Bundle, BundleError};
use crate::cloud;
use crate::crest::{self, CrestOptions};
use crate::depth::{DepthMap, DepthOptions, DepthScratch, depth_from_focus_in};
use crate::fuse::{Fusion, GridSpec, UnrolledMap};
use crate::mesh::{self, MeshOptions};
use crate::optics::ViewPose;
use crate::profile::{self, ProfileOptions};
use crate::register::{self, RegisterOptions};
use crate::report::{self, HeightSeries, Report, StageTiming, ThreadReport};
use crate::rules::{self, ArcRule, RuleInput};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Instant;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PipelineOptions {
    pub depth: DepthOptions,
    pub crest: CrestOptions,
    pub register: RegisterOptions,
    pub mesh: MeshOptions,
    /// How heights are reported (options stored before this existed load with the default).
    #[serde(default)]
    pub profile: ProfileOptions,
    pub arc_rule: ArcRule,
    /// Fused-map cell size in object pixels.
    pub cell_px: f64,
    /// Take the ring's axial offset from the end face's silhouette when the views show it.
    #[serde(default = "yes")]
    pub anchor_end_face: bool,
}

fn yes() -> bool {
    true
}

impl Default for PipelineOptions {
    fn default() -> Self {
        Self {
            depth: DepthOptions::default(),
            crest: CrestOptions::default(),
            register: RegisterOptions::default(),
            mesh: MeshOptions::default(),
            profile: ProfileOptions::default(),
            arc_rule: ArcRule::PerThread,
            cell_px: 1.5,
            anchor_end_face: true,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Depth,
    Register,
    Fuse,
    Mesh,
    Profile,
    Rules,
}

impl Stage {
    pub fn as_str(self) -> &'static str {
        match self {
            Stage::Depth => "depth",
            Stage::Register => "register",
            Stage::Fuse => "fuse",
            Stage::Mesh => "mesh",
            Stage::Profile => "profile",
            Stage::Rules => "crest_and_rules",
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Bundle(#[from] BundleError),
    #[error("no view gave a usable depth map (is the part in focus anywhere in the stacks?)")]
    NoDepth,
    #[error("no thread found: the profile shows no spectrum at the {pitch_mm} mm pitch")]
    NoThread { pitch_mm: f64 },
    #[error(transparent)]
    Mesh(#[from] mesh::MeshError),
}

pub struct Inspection {
    pub report: Report,
    pub map: UnrolledMap,
    pub depth_maps: Vec<DepthMap>,
    /// The refined view poses.
    pub poses: Vec<ViewPose>,
    pub mesh: mesh::Mesh,
}

/// Runs the pipeline. Ok(None) means it was cancelled.
pub fn inspect(
    bundle: &Bundle,
    options: &PipelineOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
    cancel: &AtomicBool,
) -> Result<Option<Inspection>, PipelineError> {
    let cancelled = || cancel.load(Ordering::Relaxed);
    let mut timings = Vec::new();
    let clock = std::cell::Cell::new(Instant::now());
    let lap = |stage: Stage, timings: &mut Vec<StageTiming>| {
        timings.push(StageTiming { stage: stage.as_str().into(), seconds: clock.get().elapsed().as_secs_f64() });
        clock.set(Instant::now());
    };

    progress(Stage::Depth, 0.0);
    let done = AtomicUsize::new(0);
    let total = bundle.views.len();
    // Depth buffers are handed from view to view (one set per view in flight, not one per view).
    let scratches = std::sync::Mutex::new(Vec::<DepthScratch>::new());
    let depth_options = options.depth.for_form(&bundle.part.form);
    let depth_maps: Vec<Option<DepthMap>> = bundle
        .views
        .par_iter()
        .enumerate()
        .map(|(v, view)| {
            let mut scratch = scratches.lock().expect("no panics while held").pop().unwrap_or_default();
            let map = depth_from_focus_in(
                &mut scratch,
                &bundle.optics,
                view,
                &depth_options,
                |k| bundle.read_frame(v, k),
                &cancelled,
            );
            scratches.lock().expect("no panics while held").push(scratch);
            let map = map?;
            progress(Stage::Depth, (done.fetch_add(1, Ordering::Relaxed) + 1) as f64 / total as f64);
            Ok(map)
        })
        .collect::<Result<_, BundleError>>()?;
    if cancelled() || depth_maps.iter().any(Option::is_none) {
        return Ok(None);
    }
    drop(scratches);
    let mut depth_maps: Vec<DepthMap> = depth_maps.into_iter().flatten().collect();
    if options.depth.equalize_phase {
        let grids: Vec<Option<(f64, f64)>> = bundle
            .views
            .iter()
            .map(|v| crate::depth::even_frame_grid(&v.frames.iter().map(|f| f.offset_mm).collect::<Vec<_>>()))
            .collect();
        crate::depth::equalize_sub_frame_phase(&mut depth_maps, &grids, bundle.optics.focus_distance_mm);
    }
    let depth_coverage = depth_maps.iter().map(|d| d.coverage()).sum::<f64>() / depth_maps.len().max(1) as f64;
    if depth_coverage == 0.0 {
        return Err(PipelineError::NoDepth);
    }
    lap(Stage::Depth, &mut timings);

    progress(Stage::Register, 0.0);
    let part = &bundle.part;
    let encoder_poses: Vec<ViewPose> = bundle.views.iter().map(|v| v.pose).collect();
    // Each view's points are reduced as they are projected (to registration's grids here, to
    // fusion's bins below): no stage holds every view's cloud.
    let optics = &bundle.optics;
    let pixel_mm = bundle.optics.object_pixel_mm(bundle.optics.focus_distance_mm);
    let format = bundle.views[0].format;
    let radius_ref = part.pipe_od_mm / 2.0;
    let register_options = RegisterOptions { cell_mm: pixel_mm, ..options.register.clone() };
    let lattice = register::Lattice::new(radius_ref, register_options.cell_mm);
    let grids: Vec<register::ViewGrid> = encoder_poses
        .par_iter()
        .zip(&depth_maps)
        .map_init(register::GridScratch::default, |scratch, (pose, depth)| {
            let fill_arc_gaps = depth.row_step > 1;
            register::view_grid(
                cloud::points_of(optics, pose, depth),
                pose.angle_deg.to_radians(),
                &lattice,
                fill_arc_gaps,
                scratch,
            )
        })
        .collect();
    let registration = register::register(
        &grids,
        &encoder_poses,
        &lattice,
        (format.height as f64 * pixel_mm / 2.0 / radius_ref).to_degrees(),
        format.width as f64 * pixel_mm / 2.0,
        &register_options,
    );
    let encoder_z_ranges_mm: Vec<(f64, f64)> = grids.iter().map(|g| g.z_range_mm()).collect();
    drop(grids);
    let mut poses: Vec<ViewPose> =
        encoder_poses.iter().zip(&registration.corrections).map(|(p, c)| c.apply(p)).collect();
    // Absolute z from the end face, where the views show it.
    let end_face = options
        .anchor_end_face
        .then(|| {
            let edges: Vec<&[crate::endface::FrameEdge]> = depth_maps.iter().map(|d| d.end_edges.as_slice()).collect();
            crate::endface::anchor(&bundle.optics, &poses, &edges, format.width, format.height, 3, 20.0)
        })
        .flatten();
    if let Some(end) = &end_face {
        poses.iter_mut().for_each(|p| p.axial_mm -= end.z_offset_mm);
    }
    lap(Stage::Register, &mut timings);
    if cancelled() {
        return Ok(None);
    }

    progress(Stage::Fuse, 0.0);
    let cell_mm = options.cell_px * pixel_mm;
    // The views' z ranges at the encoder poses, moved by each view's axial correction.
    let z_range_mm = poses.iter().zip(&encoder_poses).zip(&encoder_z_ranges_mm).fold(
        (f64::MAX, f64::MIN),
        |(lo, hi), ((pose, encoder), &(view_lo, view_hi))| {
            let shift = pose.axial_mm - encoder.axial_mm;
            (lo.min(view_lo + shift), hi.max(view_hi + shift))
        },
    );
    let grid = GridSpec::spanning(z_range_mm, cell_mm, part.pipe_od_mm / 2.0).ok_or(PipelineError::NoDepth)?;
    let mut fusion = Fusion::new(grid);
    // Binning (angle and radius per point) runs per view in parallel, a few views at a time into
    // buffers reused from batch to batch; each batch is summed in view order before the next.
    let batch = 2 * rayon::current_num_threads().max(1);
    let mut buffers: Vec<Vec<crate::fuse::Binned>> = vec![Vec::new(); batch.min(total)];
    for (batch_index, views) in poses.iter().zip(&depth_maps).collect::<Vec<_>>().chunks(batch).enumerate() {
        if cancelled() {
            return Ok(None);
        }
        buffers.par_iter_mut().zip(views).for_each(|(buffer, &(pose, depth))| {
            fusion.bin_into(buffer, cloud::points_of(optics, pose, depth), pose.angle_deg.to_radians());
        });
        fusion.accumulate_all(&buffers[..views.len()]);
        // Binning is most of the work; the sums follow each batch.
        progress(Stage::Fuse, 0.9 * ((batch_index * batch + views.len()) as f64 / total as f64));
    }
    drop(buffers);
    progress(Stage::Fuse, 1.0);
    let map = fusion.finish();
    lap(Stage::Fuse, &mut timings);
    if cancelled() {
        return Ok(None);
    }

    // The mesh is an export: it runs beside the profile, which the verdict needs. Each stage's
    // own time is reported; together they take the longer of the two.
    progress(Stage::Mesh, 0.0);
    progress(Stage::Profile, 0.0);
    let form = &part.form;
    fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
        let started = Instant::now();
        let out = f();
        (out, started.elapsed().as_secs_f64())
    }
    let ((mesh, mesh_seconds), ((helix, threads), profile_seconds)) = rayon::join(
        || timed(|| mesh::build(&map, &options.mesh)),
        || {
            timed(|| {
                let helix = profile::estimate_helix(&map, form).map(|first| {
                    let threads = profile::survey_threads(&map, form, &first, &options.profile);
                    profile::refine_helix(&map, form, &first, &threads)
                });
                let threads = helix.as_ref().map(|h| profile::measure_threads(&map, form, h, &options.profile));
                (helix, threads)
            })
        },
    );
    let mesh = mesh?;
    let helix = helix.ok_or(PipelineError::NoThread { pitch_mm: form.pitch_mm })?;
    let threads = threads.expect("measured whenever the helix was found");
    timings.push(StageTiming { stage: Stage::Mesh.as_str().into(), seconds: mesh_seconds });
    timings.push(StageTiming { stage: Stage::Profile.as_str().into(), seconds: profile_seconds });
    clock.set(Instant::now());
    if cancelled() {
        return Ok(None);
    }

    progress(Stage::Rules, 0.0);
    let crest::CrestFindings { observations, machined_crest_gray, cone: crest_cone } = crest::observations(
        &threads,
        part.lc_mm,
        helix.pitch_mm,
        form.radius_slope(),
        crate::profile::crest_window_half_mm(form),
        &options.crest,
    );
    let input = RuleInput {
        family: part.family(),
        lc_mm: part.lc_mm,
        circumference_mm: part.circumference_mm(),
        nominal_height_mm: form.height_mm,
        height_tolerance_mm: form.height_tolerance_mm,
        threads: observations,
    };
    let assessment = rules::assess(&input, options.arc_rule);
    let thread_reports = threads
        .iter()
        .map(|t| {
            let values: Vec<Option<f64>> = t.bins.iter().map(|b| b.height_mm).collect();
            let measured: Vec<f64> = values.iter().flatten().copied().collect();
            let black = assessment.black_threads.iter().find(|b| b.index == t.index);
            ThreadReport {
                index: t.index,
                height_mm: HeightSeries { angles_deg: t.bins.iter().map(|b| b.angle_deg).collect(), values },
                black_crest_arcs_deg: black.map(|b| b.arcs_deg.clone()).unwrap_or_default(),
                black_crest_length_mm: black.map_or(0.0, |b| b.length_mm),
                crest_z_mm: [
                    t.bins[0].crest_z_mm - 0.5 * helix.pitch_mm / 360.0,
                    t.bins[359].crest_z_mm + 0.5 * helix.pitch_mm / 360.0,
                ],
                min_height_mm: measured.iter().copied().reduce(f64::min),
                mean_height_mm: (!measured.is_empty()).then(|| measured.iter().sum::<f64>() / measured.len() as f64),
                max_height_mm: measured.iter().copied().reduce(f64::max),
                bins_measured: measured.len(),
            }
        })
        .collect();
    lap(Stage::Rules, &mut timings);
    progress(Stage::Rules, 1.0);

    let report = Report {
        connection: part.connection.clone(),
        family: part.family(),
        pipe_od_mm: part.pipe_od_mm,
        lc_mm: part.lc_mm,
        circumference_mm: part.circumference_mm(),
        pitch_mm: form.pitch_mm,
        nominal_height_mm: form.height_mm,
        threads: thread_reports,
        verdict: assessment.verdict,
        reasons: assessment.messages(),
        serial: part.serial.clone(),
        height_tolerance_mm: form.height_tolerance_mm,
        assessment,
        helix,
        registration: registration.clone(),
        end_face,
        depth_coverage,
        map_coverage: map.coverage(),
        machined_crest_gray,
        crest_cone,
        timings,
        peak_memory_mb: report::peak_memory_mb(),
    };
    Ok(Some(Inspection { report, map, depth_maps, poses, mesh }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Jobs store their options; those stored before the profile options existed still load.
    #[test]
    fn options_stored_before_the_profile_options_existed_load_with_their_default() {
        let mut stored = serde_json::to_value(PipelineOptions::default()).unwrap();
        stored.as_object_mut().unwrap().remove("profile");
        let options: PipelineOptions = serde_json::from_value(stored).unwrap();
        assert_eq!(options.profile, ProfileOptions::default());
        assert_eq!(options.profile.height_window_half_bins, 5);
    }
}
