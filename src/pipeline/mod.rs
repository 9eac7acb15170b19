//! The pure stages, in data-flow order, and [`inspect`], the one library call behind the CLI, the
//! benchmark and the service's workers:
//!
//! | stage | in | out |
//! |---|---|---|
//! | [`depth`] | each view's focal stack | a depth map per view (and the end face's edge per frame) |
//! | [`cloud`] | a depth map and its pose | surface points, streamed |
//! | [`register`] | every view's points on one lattice | pose corrections, per-pair residuals; [`register::anchor`] the ring's absolute z from the end face |
//! | [`fuse`] | every view's points at the refined poses | the unrolled surface ([`surface`]) |
//! | [`mesh`] | the unrolled surface | a triangle mesh (an export; runs beside the profile) |
//! | [`profile`] | the unrolled surface and the thread form | the helix, per-thread heights per 1° bin |
//! | [`crest`] | the per-thread measures | black-crest observations, the crest cone |
//! | rules ([`crate::domain::rules`]) | the observations | the API 5B verdict and reasons |
//! | [`uncertainty`] | the heights, the station, registration | U (k = 2) per height; the ISO 14253-1 decision |
//! | [`report`] | all of the above | the report, with its [`quality`]: what was not measured |
//!
//! Stages never open a file: frames come through [`Recording`]. Progress, cancellation (checked
//! between frames and stages) and timings belong to a small run context ([`run`]).

// The stages in data-flow order (blank lines keep rustfmt from sorting them), then the run's
// context and options.
pub mod depth;

pub mod cloud;

pub mod register;

pub mod surface;

pub mod fuse;

pub mod gate;

pub mod mesh;

pub mod profile;

pub mod crest;

pub mod uncertainty;

pub mod qualify;
pub mod quality;

pub mod report;

pub mod memory;
pub mod options;
pub mod run;

pub use crate::domain::frame::Recording;
pub use options::PipelineOptions;
pub use run::Stage;

use crate::domain;
use crate::domain::frame::FrameError;
use crate::domain::optics::ViewPose;
use crate::domain::rules::{self, RuleInput};
use crate::problem::{Code, ErrorCode};
use depth::{DepthMap, DepthScratch};
use fuse::Fusion;
use profile::{Helix, ThreadMeasure};
use rayon::prelude::*;
use register::{EndFace, Registration};
use report::Report;
use run::{Halt, Run};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Instant;
use surface::{GridSpec, UnrolledMap};

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Frame(#[from] FrameError),
    #[error("no view gave a usable depth map (is the part in focus anywhere in the stacks?)")]
    NoDepth,
    #[error(
        "no thread found: the profile shows no spectrum at the {pitch_mm} mm pitch (the fused map covers {:.1}% of \
         the surface, {:.1}% of its cells dropped as no surface of the form: where that is little, the station's depth \
         from focus did not resolve the part)",
        100.0 * map_coverage,
        100.0 * map_implausible_share
    )]
    NoThread { pitch_mm: f64, map_coverage: f64, map_implausible_share: f64 },
    #[error(transparent)]
    Mesh(#[from] mesh::MeshError),
    #[error(transparent)]
    Option(#[from] options::OptionOutOfRange),
    #[error(transparent)]
    Learned(#[from] crate::learned::LearnedError),
}

impl From<depth::cnn::CnnDepthError> for PipelineError {
    fn from(e: depth::cnn::CnnDepthError) -> Self {
        match e {
            depth::cnn::CnnDepthError::Frame(e) => PipelineError::Frame(e),
            depth::cnn::CnnDepthError::Learned(e) => PipelineError::Learned(e),
        }
    }
}

impl ErrorCode for PipelineError {
    fn code(&self) -> Code {
        match self {
            PipelineError::Frame(e) => e.code(),
            PipelineError::NoDepth => Code::NoDepth,
            PipelineError::NoThread { .. } => Code::NoThread,
            PipelineError::Mesh(_) => Code::MeshFailed,
            PipelineError::Option(e) => e.code(),
            PipelineError::Learned(e) => e.code(),
        }
    }

    fn culprit(&self) -> Option<String> {
        match self {
            PipelineError::Frame(e) => e.culprit(),
            PipelineError::Option(e) => e.culprit(),
            PipelineError::Learned(e) => e.culprit(),
            _ => None,
        }
    }
}

pub struct Inspection {
    pub report: Report,
    pub map: UnrolledMap,
    /// The views' depth maps where a diagnosis asked for them ([`Substitutes::keep_depth_maps`]);
    /// otherwise empty: an inspection drops them once fused, before the fused map is finished.
    pub depth_maps: Vec<DepthMap>,
    /// The refined view poses.
    pub poses: Vec<ViewPose>,
    pub mesh: mesh::Mesh,
    /// The measured threads as the classical fits left them (their bins' own fits in
    /// `raw_height_mm`, before any profile correction and the uncertainty stage), for
    /// [`profile::pitch::pitch_profiles`] on the map.
    pub threads: Vec<ThreadMeasure>,
}

/// Runs the pipeline, with the process's models ([`crate::learned::models`]). Ok(None) means it
/// was cancelled.
pub fn inspect(
    recording: &dyn Recording,
    options: &PipelineOptions,
    progress: &(dyn Fn(Stage, f64) + Sync),
    cancel: &AtomicBool,
) -> Result<Option<Inspection>, PipelineError> {
    inspect_with(recording, options, crate::learned::models(), progress, cancel)
}

/// [`inspect_with`] at a named station: where `at` is a qualification the bundle matches, the
/// station's correction is applied to the classical heights (the profile MLP is not run: the
/// station's correction takes its place) and its uncertainty stands in for the method's; where
/// it is not, the quality says why and no decision is made.
pub fn inspect_at(
    recording: &dyn Recording,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    progress: &(dyn Fn(Stage, f64) + Sync),
    cancel: &AtomicBool,
    at: Option<&qualify::AtStation>,
) -> Result<Option<Inspection>, PipelineError> {
    options.check_ranges()?;
    let mut options = options.clone();
    if matches!(at, Some(qualify::AtStation::Qualified(_))) {
        options.profile.correction = profile::Correction::Off;
    }
    match run_stages(recording, &options, models, Run::new(progress, cancel), at, &Substitutes::default()) {
        Ok(inspection) => Ok(Some(inspection)),
        Err(Halt::Cancelled) => Ok(None),
        Err(Halt::Failed(e)) => Err(e),
    }
}

/// [`inspect`] with the learned models of `models` (the service's: its own models folder).
pub fn inspect_with(
    recording: &dyn Recording,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    progress: &(dyn Fn(Stage, f64) + Sync),
    cancel: &AtomicBool,
) -> Result<Option<Inspection>, PipelineError> {
    // Every caller (the service checks at submission too) meets the same bounds: an option outside
    // them can multiply a stage's memory or work without limit.
    options.check_ranges()?;
    match run_stages(recording, options, models, Run::new(progress, cancel), None, &Substitutes::default()) {
        Ok(inspection) => Ok(Some(inspection)),
        Err(Halt::Cancelled) => Ok(None),
        Err(Halt::Failed(e)) => Err(e),
    }
}

/// What a diagnosis puts in place of a stage's output, to see how much of the final error the
/// stages after it add: the error budget ([`crate::eval::budget`]) runs a bundle with the
/// simulator's true depth maps, poses or helix in turn. Nothing but a diagnosis uses it; an
/// inspection takes [`Substitutes::default`], which replaces nothing.
#[derive(Default)]
pub struct Substitutes<'a> {
    /// Rewrites view v's depth map after the depth stage (before registration).
    pub depth: Option<&'a (dyn Fn(usize, &mut DepthMap) + Sync)>,
    /// The poses fusion uses, in place of the registered ones (registration still runs and is
    /// reported).
    pub poses: Option<&'a [ViewPose]>,
    /// The helix the heights are measured on, in place of the estimated one.
    pub helix: Option<&'a (dyn Fn(&Helix) -> Helix + Sync)>,
    /// Keep the views' depth maps in [`Inspection::depth_maps`] (a diagnosis compares them with
    /// the truth); an inspection drops them once fused, so the stages after fusion and the
    /// exports run without them (docs/notebook/speed.md).
    pub keep_depth_maps: bool,
}

/// [`inspect_with`] with some stages' outputs replaced ([`Substitutes`]); never cancelled.
pub fn inspect_substituted(
    recording: &dyn Recording,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    substitutes: &Substitutes,
) -> Result<Inspection, PipelineError> {
    options.check_ranges()?;
    let cancel = AtomicBool::new(false);
    match run_stages(recording, options, models, Run::new(&|_, _| {}, &cancel), None, substitutes) {
        Ok(inspection) => Ok(inspection),
        Err(Halt::Cancelled) => Err(PipelineError::NoDepth),
        Err(Halt::Failed(e)) => Err(e),
    }
}

type Step<T> = Result<T, Halt<PipelineError>>;

fn run_stages(
    recording: &dyn Recording,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    mut run: Run,
    at: Option<&qualify::AtStation>,
    substitutes: &Substitutes,
) -> Step<Inspection> {
    let (mut depth_maps, mut depth_coverage, depth_model) = measure_depth(recording, options, models, &mut run)?;
    if let Some(replace) = substitutes.depth {
        depth_maps.par_iter_mut().enumerate().for_each(|(v, map)| replace(v, map));
        depth_coverage = depth_maps.iter().map(|d| d.coverage()).sum::<f64>() / depth_maps.len().max(1) as f64;
    }
    let mut registered = register_views(recording, options, &depth_maps, &mut run)?;
    if let Some(poses) = substitutes.poses {
        registered.poses = poses.to_vec();
    }
    let frame_noise_pct = crate::numeric::stats::median(
        &mut depth_maps.iter().filter_map(|d| d.frame_noise).map(|n| 100.0 * n).collect::<Vec<_>>(),
    );
    let depth_prefiltered_views = depth_maps.iter().filter(|d| d.prefiltered).count();
    let (map, map_implausible_share, depth_maps) = fuse_views(
        recording,
        options,
        depth_maps,
        substitutes.keep_depth_maps,
        &registered.poses,
        &registered.encoder_z_ranges_mm,
        &mut run,
    )?;
    let part = recording.part();
    let mut station = domain::station::Station::of(recording.optics(), recording.views(), part.pipe_od_mm / 2.0)
        .with_frame_noise(frame_noise_pct);
    // One view's pose error moves all its generatrices: the views' spacing is the helix phase's
    // sector, over which the windows' local phase is read and its readings count as one.
    let sector_deg = station.view_spacing_deg.unwrap_or(360.0);
    let (mesh, helix, mut threads, learned) =
        mesh_and_profile(recording, options, models, &map, map_implausible_share, sector_deg, substitutes, &mut run)?;
    // The classical fits, for the training pairs (`eval::pairs`), whether or not the MLP ran.
    let measured_threads = learned.classical.clone().unwrap_or_else(|| threads.clone());
    let (assessment, crest, rule_input) = crest_and_rules(recording, options, &helix, &threads, &mut run);
    let phase = helix.phase_uncertainty(&part.form, sector_deg);
    let qualification = at.map(|at| qualify::apply(at, &mut station, part.connection.as_deref(), &mut threads));
    let mut quality = quality::assess(
        &station,
        &registered.registration,
        recording.views(),
        &assessment,
        &quality::SurfaceFit {
            qualified_helix_fit_rms_um: qualification.as_ref().and_then(|q| q.helix_fit_rms_max_um),
            ..quality::SurfaceFit::of(&helix, part, depth_coverage, &phase)
        },
    );
    quality.flag_learned(
        depth_model.as_ref(),
        learned.correction.as_ref().filter(|c| c.run),
        learned.unavailable.as_ref(),
    );
    if let Some(reason) = qualification.as_ref().and_then(|q| q.refused.as_ref()) {
        quality.flag(
            quality::QualityStatus::Degraded,
            quality::QualityCode::StationNotQualified,
            format!("The station's qualification could not be applied, so no decision is made. {reason}."),
        );
    }
    // A learned correction's own error, as its card measured it per micrometre of change.
    let model_by_thread_mm: Vec<(u32, f64)> = learned
        .correction
        .iter()
        .filter(|c| c.run)
        .flat_map(|c| c.change_by_thread.iter().map(|t| (t.thread, 1e-3 * t.rms_um * c.error_per_change())))
        .collect();
    let (uncertainty, thread_mean_u) = uncertainty::heights(
        &mut threads,
        &uncertainty::Scales {
            station: &station,
            focus_window_radius_px: options.depth.for_form(&part.form).window_radius_px,
            pipe_radius_mm: part.pipe_od_mm / 2.0,
            form: &part.form,
            phase: &phase,
            registration: &registered.registration,
            end_face: registered.end_face.as_ref(),
            crests: &rule_input.threads,
            height_window_half_bins: options.profile.height_window_half_bins,
            station_u_mm: qualification.as_ref().and_then(|q| q.uncertainty.as_ref()).map(|u| 1e-3 * u.combined_um),
            station_noise_mm: qualification
                .as_ref()
                .filter(|q| q.applied)
                .map(|q| 1e-3 * q.noise_median_um.unwrap_or(0.0)),
            model_by_thread_mm: &model_by_thread_mm,
        },
        crest.cone.as_ref().map(|c| c.scatter_um),
        &quality,
        &options.uncertainty,
    );
    let decision = uncertainty::decide(
        &threads,
        &uncertainty::RuleContext {
            input: &rule_input,
            arc_rule: options.arc_rule,
            pitch_mm: helix.pitch_mm,
            nominal_slope: part.form.radius_slope(),
            crest_window_half_mm: profile::crest_window_half_mm(&part.form),
            crest: &options.crest,
        },
        &uncertainty,
        &quality,
        &station,
    );
    let report = Report::assemble(report::Findings {
        part,
        options,
        optics: recording.optics(),
        views: recording.views(),
        station,
        quality,
        uncertainty,
        thread_mean_uncertainty_mm: thread_mean_u,
        decision,
        helix,
        threads: &threads,
        assessment,
        machined_crest_gray: crest.machined_crest_gray,
        crest_cone: crest.cone,
        registration: registered.registration,
        end_face: registered.end_face,
        depth_coverage,
        depth_prefiltered_views,
        map_coverage: map.coverage(),
        map_implausible_share,
        models: depth_model.into_iter().chain(learned.used).collect(),
        timings: run.into_timings(),
        qualification,
        profile_correction: learned.correction,
    });
    Ok(Inspection { report, map, depth_maps, poses: registered.poses, mesh, threads: measured_threads })
}

/// Depth from focus per view, in parallel, then the views' sub-frame phases equalised; the maps
/// and their mean coverage.
fn measure_depth(
    recording: &dyn Recording,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    run: &mut Run,
) -> Step<(Vec<DepthMap>, f64, Option<crate::learned::ModelUse>)> {
    let views = recording.views();
    run.progress(Stage::Depth, 0.0);
    let estimator = depth::estimator::estimator(&options.depth, models).map_err(PipelineError::from)?;
    // The nets' share of the stage, summed over views (they run on the same workers as the
    // classical measure), for benchmarks to set against the classical stage.
    let (learned_nanos, total_nanos) = (std::sync::atomic::AtomicU64::new(0), std::sync::atomic::AtomicU64::new(0));
    let done = AtomicUsize::new(0);
    let total = views.len();
    // Depth buffers are handed from view to view (one set per view in flight, not one per view).
    let scratches = std::sync::Mutex::new(Vec::<DepthScratch>::new());
    let depth_options = options.depth.for_part(&recording.part().form, recording.optics());
    let run_ref = &*run;
    let cancelled = || run_ref.cancelled();
    let depth_maps: Vec<Option<DepthMap>> = views
        .par_iter()
        .enumerate()
        .map(|(v, view)| {
            let started = Instant::now();
            let mut scratch = scratches.lock().expect("no panics while held").pop().unwrap_or_default();
            let frame_at = |k| recording.read_frame(v, k);
            let stack = depth::estimator::ViewStack {
                optics: recording.optics(),
                view,
                options: &depth_options,
                frame_at: &frame_at,
                cancelled: &cancelled,
            };
            let estimate = estimator.estimate(&stack, &mut scratch);
            scratches.lock().expect("no panics while held").push(scratch);
            let estimate = estimate?;
            total_nanos.fetch_add(started.elapsed().as_nanos() as u64, Ordering::Relaxed);
            learned_nanos.fetch_add(estimate.as_ref().map_or(0, |e| e.learned.as_nanos() as u64), Ordering::Relaxed);
            run_ref.progress(Stage::Depth, (done.fetch_add(1, Ordering::Relaxed) + 1) as f64 / total as f64);
            Ok(estimate.map(|e| e.map))
        })
        .collect::<Result<_, PipelineError>>()?;
    if run.cancelled() || depth_maps.iter().any(Option::is_none) {
        return Err(Halt::Cancelled);
    }
    drop(scratches);
    let mut depth_maps: Vec<DepthMap> = depth_maps.into_iter().flatten().collect();
    // The sub-frame phase bias is the classical peak finder's; the nets' planes have their own.
    if options.depth.equalize_phase && estimator.model().is_none() {
        let grids: Vec<Option<(f64, f64)>> = views
            .iter()
            .map(|v| depth::even_frame_grid(&v.frames.iter().map(|f| f.offset_mm).collect::<Vec<_>>()))
            .collect();
        depth::equalize_sub_frame_phase(&mut depth_maps, &grids, recording.optics().focus_distance_mm);
    }
    let depth_coverage = depth_maps.iter().map(|d| d.coverage()).sum::<f64>() / depth_maps.len().max(1) as f64;
    if depth_coverage == 0.0 {
        return Err(PipelineError::NoDepth.into());
    }
    let stage_seconds = run.lap(Stage::Depth);
    let model = estimator.model().cloned();
    if model.is_some() {
        // The views run in parallel: the stage's wall time shared by the parts' summed times.
        let (learned, all) = (learned_nanos.into_inner() as f64, total_nanos.into_inner() as f64);
        run.record_part(report::DEPTH_CNN, stage_seconds * learned / all.max(1.0));
    }
    Ok((depth_maps, depth_coverage, model))
}

/// What registration hands on: the refined poses, what it measured, and the views' z ranges at
/// the encoder poses (fusion's grid is sized from them).
struct Registered {
    poses: Vec<ViewPose>,
    registration: Registration,
    end_face: Option<EndFace>,
    encoder_z_ranges_mm: Vec<(f64, f64)>,
}

/// Registration of the overlapping views on one lattice, then absolute z from the end face where
/// the views show it.
fn register_views(
    recording: &dyn Recording,
    options: &PipelineOptions,
    depth_maps: &[DepthMap],
    run: &mut Run,
) -> Step<Registered> {
    run.progress(Stage::Register, 0.0);
    let (part, optics, views) = (recording.part(), recording.optics(), recording.views());
    let encoder_poses: Vec<ViewPose> = views.iter().map(|v| v.pose).collect();
    // Each view's points are reduced as they are projected (to registration's grids here, to
    // fusion's bins below): no stage holds every view's cloud.
    let pixel_mm = optics.object_pixel_mm(optics.focus_distance_mm);
    let format = views[0].format;
    let radius_ref = part.pipe_od_mm / 2.0;
    let register_options = options.register.clone();
    // The overlap grids' cell is the object pixel: the texture registration correlates is
    // resolved to a pixel, and finer cells would hold no more.
    let lattice = register::Lattice::new(radius_ref, pixel_mm);
    let grids: Vec<register::ViewGrid> = encoder_poses
        .par_iter()
        .zip(depth_maps)
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
        part.form.pitch_mm,
        &register_options,
    );
    let encoder_z_ranges_mm: Vec<(f64, f64)> = grids.iter().map(|g| g.z_range_mm()).collect();
    drop(grids);
    let mut poses: Vec<ViewPose> =
        encoder_poses.iter().zip(&registration.corrections).map(|(p, c)| c.apply(p)).collect();
    let mut registration = registration;
    let mut end_face = None;
    if options.anchor_end_face {
        let edges: Vec<&[depth::FrameEdge]> = depth_maps.iter().map(|d| d.end_edges.as_slice()).collect();
        let corners = register::corners(optics, &poses, &edges, format.width, format.height);
        let ring: Vec<bool> = (0..poses.len()).map(|v| !registration.unregistered_views.contains(&v)).collect();
        end_face = register::anchor(&corners, &ring, 3, 20.0);
        let (_, axial_bound_mm) = register_options.encoder_bounds();
        for (v, pose) in poses.iter_mut().enumerate() {
            // A view no overlap placed keeps its encoder's axial error (up to the fixture's
            // bound); where it sees the end face, its own corner places it instead: the end face
            // is z = 0 by the contract.
            if let (false, Some((own_z, _))) = (ring[v], corners[v]) {
                if own_z.abs() <= axial_bound_mm {
                    pose.axial_mm -= own_z;
                    registration.placed_by_end_face.push(v);
                    continue;
                }
                // At coarse stations a corner misread by a pixel or a depth of field would move
                // the view by as much: a view with a corner so misread is left as one without.
                registration.end_face_implausible.push(v);
            }
            pose.axial_mm -= end_face.as_ref().map_or(0.0, |e| e.z_offset_mm);
        }
    }
    run.lap(Stage::Register);
    run.check()?;
    Ok(Registered { poses, registration, end_face, encoder_z_ranges_mm })
}

/// Every view's points binned at its refined pose and summed into the unrolled surface. The
/// depth maps are dropped once summed, before the map is finished (its result planes are the
/// next allocation), unless `keep_depth_maps`: then they come back.
fn fuse_views(
    recording: &dyn Recording,
    options: &PipelineOptions,
    depth_maps: Vec<DepthMap>,
    keep_depth_maps: bool,
    poses: &[ViewPose],
    encoder_z_ranges_mm: &[(f64, f64)],
    run: &mut Run,
) -> Step<(UnrolledMap, f64, Vec<DepthMap>)> {
    run.progress(Stage::Fuse, 0.0);
    let (part, optics, views) = (recording.part(), recording.optics(), recording.views());
    let total = views.len();
    let pixel_mm = optics.object_pixel_mm(optics.focus_distance_mm);
    let cell_mm = options.cell_mm(pixel_mm, &part.form);
    // The views' z ranges at the encoder poses, moved by each view's axial correction.
    let z_range_mm = poses.iter().zip(views).zip(encoder_z_ranges_mm).fold(
        (f64::MAX, f64::MIN),
        |(lo, hi), ((pose, view), &(view_lo, view_hi))| {
            let shift = pose.axial_mm - view.pose.axial_mm;
            (lo.min(view_lo + shift), hi.max(view_hi + shift))
        },
    );
    let grid = GridSpec::spanning(z_range_mm, cell_mm, part.pipe_od_mm / 2.0).ok_or(PipelineError::NoDepth)?;
    let mut fusion = Fusion::new(grid);
    // Binning (angle and radius per point) runs per view in parallel, a few views at a time into
    // buffers reused from batch to batch; each batch is summed in view order before the next.
    let batch = 2 * rayon::current_num_threads().max(1);
    let mut buffers: Vec<Vec<fuse::Binned>> = vec![Vec::new(); batch.min(total)];
    for (batch_index, views) in poses.iter().zip(&depth_maps).collect::<Vec<_>>().chunks(batch).enumerate() {
        run.check()?;
        buffers.par_iter_mut().zip(views).for_each(|(buffer, &(pose, depth))| {
            fusion.bin_into(buffer, cloud::points_of(optics, pose, depth), pose.angle_deg.to_radians());
        });
        fusion.accumulate_all(&buffers[..views.len()]);
        // Binning is most of the work; the sums follow each batch.
        run.progress(Stage::Fuse, 0.9 * ((batch_index * batch + views.len()) as f64 / total as f64));
    }
    drop(buffers);
    let depth_maps = if keep_depth_maps { depth_maps } else { Vec::new() };
    run.progress(Stage::Fuse, 1.0);
    let mut map = fusion.finish();
    let seen = map.radius_mm.iter().filter(|r| r.is_finite()).count();
    let dropped = if options.gate_implausible { gate::drop_implausible(&mut map, &part.form) } else { 0 };
    run.lap(Stage::Fuse);
    run.check()?;
    Ok((map, dropped as f64 / seen.max(1) as f64, depth_maps))
}

/// The mesh is an export: it runs beside the profile, which the verdict needs. Each stage's own
/// time is reported; together they take the longer of the two.
fn mesh_and_profile(
    recording: &dyn Recording,
    options: &PipelineOptions,
    models: &crate::learned::Models,
    map: &UnrolledMap,
    map_implausible_share: f64,
    sector_deg: f64,
    substitutes: &Substitutes,
    run: &mut Run,
) -> Step<(mesh::Mesh, Helix, Vec<ThreadMeasure>, Learned)> {
    run.progress(Stage::Mesh, 0.0);
    run.progress(Stage::Profile, 0.0);
    let form = &recording.part().form;
    // Half a view's spacing, in 1° bins, either side of a bin for its local helix phase.
    let local_phase_bins = options.profile.local_phase.then(|| (0.5 * sector_deg).round() as usize);
    fn timed<T>(f: impl FnOnce() -> T) -> (T, f64) {
        let started = Instant::now();
        let out = f();
        (out, started.elapsed().as_secs_f64())
    }
    let ((mesh, mesh_seconds), ((helix, threads), profile_seconds)) = rayon::join(
        || timed(|| mesh::build(map, &options.mesh)),
        || {
            timed(|| {
                let helix = profile::estimate_helix(map, form).map(|first| {
                    let threads = profile::survey_threads(map, form, &first, &options.profile);
                    let refined = profile::refine_helix(map, form, &first, &threads);
                    let refined = match local_phase_bins {
                        Some(bins) => refined.with_local_phase(bins),
                        None => refined,
                    };
                    match substitutes.helix {
                        Some(replace) => replace(&refined),
                        None => refined,
                    }
                });
                let threads = helix.as_ref().map(|h| profile::measure_threads(map, form, h, &options.profile));
                (helix, threads)
            })
        },
    );
    let mesh = mesh.map_err(PipelineError::from)?;
    let helix = helix.ok_or(PipelineError::NoThread {
        pitch_mm: form.pitch_mm,
        map_coverage: map.coverage(),
        map_implausible_share,
    })?;
    let mut threads = threads.expect("measured whenever the helix was found");
    // The MLP runs after mesh and profile, not beside them: it needs the profile's threads, and
    // its sessions run on the same workers.
    let started = Instant::now();
    let mut models_used = Vec::new();
    let (mut unavailable, mut classical) = (None, None);
    let optics = recording.optics();
    let pixel_mm = optics.object_pixel_mm(optics.focus_distance_mm);
    let profile_options = &options.profile;
    let choice = profile::choose_correction(profile_options, models, recording.part().family(), pixel_mm);
    let mut choice = match choice {
        Ok(choice) => choice,
        Err(e) => return Err(PipelineError::from(e).into()),
    };
    if let Some((c, model)) = choice.as_mut().and_then(|(c, m)| c.run.then_some((c, m.clone()))) {
        let corrected = {
            let mut corrected = threads.clone();
            profile::pitch::correct_heights(map, form, &helix, &mut corrected, profile_options, &model)
                .map(|_| corrected)
        };
        match corrected {
            Ok(corrected) => {
                c.change_by_thread = profile::change_by_thread(&threads, &corrected);
                classical = Some(std::mem::replace(&mut threads, corrected));
                models_used.push(model.identity.clone());
            }
            // Asked for by name or by `on`: an error. Chosen by `auto` for the station: the
            // classical heights, and the report says so.
            Err(e)
                if profile_options.correction == profile::Correction::Auto
                    && matches!(
                        e,
                        crate::learned::LearnedError::RuntimeMissing { .. }
                            | crate::learned::LearnedError::Model { .. }
                    ) =>
            {
                c.run = false;
                c.why = format!("{} It could not run: {e}", c.why);
                unavailable = Some(e)
            }
            Err(e) => return Err(PipelineError::from(e).into()),
        }
    }
    let correction_seconds = started.elapsed().as_secs_f64();
    run.record_side_by_side(&[(Stage::Mesh, mesh_seconds), (Stage::Profile, profile_seconds + correction_seconds)]);
    if !models_used.is_empty() {
        // Inside the profile stage's time, named so that benchmarks can set it against depth's.
        run.record_part(report::PROFILE_CORRECTION, correction_seconds);
    }
    run.check()?;
    let correction = choice.map(|(c, _)| c);
    Ok((mesh, helix, threads, Learned { used: models_used, unavailable, classical, correction }))
}

/// The learned models a run used, and the one `auto` wanted and could not run.
struct Learned {
    used: Vec<crate::learned::ModelUse>,
    unavailable: Option<crate::learned::LearnedError>,
    /// The classical threads, where the MLP replaced their heights.
    classical: Option<Vec<ThreadMeasure>>,
    /// Whether the profile correction ran and why, wherever it was not off.
    correction: Option<profile::CorrectionChoice>,
}

/// Black-crest observations from the per-thread measures, then the API 5B rules on them.
fn crest_and_rules(
    recording: &dyn Recording,
    options: &PipelineOptions,
    helix: &Helix,
    threads: &[ThreadMeasure],
    run: &mut Run,
) -> (rules::Assessment, crest::CrestFindings, RuleInput) {
    run.progress(Stage::Rules, 0.0);
    let part = recording.part();
    let form = &part.form;
    let mut findings = crest::observations(
        threads,
        part.lc_mm,
        helix.pitch_mm,
        form.radius_slope(),
        profile::crest_window_half_mm(form),
        &options.crest,
    );
    let input = RuleInput {
        family: part.family(),
        lc_mm: part.lc_mm,
        circumference_mm: part.circumference_mm(),
        nominal_height_mm: form.height_mm,
        height_tolerance_mm: form.height_tolerance_mm,
        threads: std::mem::take(&mut findings.observations),
    };
    let assessment = rules::assess(&input, options.arc_rule);
    run.lap(Stage::Rules);
    run.progress(Stage::Rules, 1.0);
    (assessment, findings, input)
}
