//! The workers: claim a job from the SQLite queue, run the pipeline off the async runtime on the
//! compute pool, heartbeat the lease (publishing progress, picking up cancel requests), and
//! complete with success, retry or abort. A panic in the pipeline fails that job only.

use crate::bundle::{Bundle, OpenOptions};
use crate::domain::frame::Recording;
use crate::domain::rules::Verdict;
use crate::domain::thread::ConnectionTable;
use crate::export::{ply, png, stl};
use crate::pipeline::{self, Stage};
use crate::problem::{Code, ErrorCode, Problem};
use crate::service::config::Settings;
use crate::service::queue::JobOptions;
use crate::service::store::{Artifact, Claimed, Heartbeat, JobResults, Status, Store};
use crate::service::telemetry::Metrics;
use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{Notify, watch};

#[derive(Clone)]
pub struct WorkerContext {
    pub store: Store,
    pub table: Arc<ConnectionTable>,
    pub metrics: Arc<Metrics>,
    pub compute: Arc<rayon::ThreadPool>,
    pub settings: crate::service::config::Settings,
    /// Wakes idle workers when work arrives.
    pub wake: Arc<Notify>,
    /// Unique per process; each claim's lease token starts with it.
    pub owner: String,
    pub models: Arc<crate::learned::Models>,
}

enum Outcome {
    Succeeded(Box<JobResults>),
    Canceled,
    /// Retry later (the failure may pass: I/O).
    Retry(Problem),
    /// Fail for good (the input cannot be inspected, or the pipeline crashed on it).
    Fail(Problem),
}

/// How long a job told to stop at the end of the grace period is waited for.
const STOP_WAIT: Duration = Duration::from_secs(3);

fn problem(code: Code, detail: impl Into<String>) -> Problem {
    Problem::new(code, detail, None)
}

/// Builds the compute pool: one thread per core (or the `compute_threads` setting), each at the
/// `compute_nice` level, or SCHED_IDLE with `compute_sched_idle` (Linux; elsewhere the default
/// priority), so that request handling keeps its latency while inspections saturate the CPU.
pub fn compute_pool(settings: &Settings) -> Arc<rayon::ThreadPool> {
    let (nice, sched_idle) = (settings.compute_nice, settings.compute_sched_idle);
    let builder = rayon::ThreadPoolBuilder::new()
        .num_threads(settings.compute_threads_resolved())
        .thread_name(|i| format!("compute-{i}"))
        .start_handler(move |_| lower_priority(nice, sched_idle));
    Arc::new(builder.build().expect("compute pool starts"))
}

/// Lowers the calling thread's priority (on Linux a nice level is per thread).
fn lower_priority(nice: i32, sched_idle: bool) {
    #[cfg(target_os = "linux")]
    // SAFETY: plain syscalls on the calling thread with a valid, initialised parameter.
    unsafe {
        let param = libc::sched_param { sched_priority: 0 };
        if sched_idle && libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) == 0 {
            return;
        }
        if libc::setpriority(libc::PRIO_PROCESS, 0, nice) != 0 {
            tracing::warn!(nice, "could not lower the compute pool's priority");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (nice, sched_idle);
}

/// Runs `settings.workers` worker loops until `shutdown` turns true, then lets running jobs finish
/// within the grace period and releases the rest to the queue.
pub async fn run(ctx: WorkerContext, shutdown: watch::Receiver<bool>) {
    let mut loops = Vec::new();
    for slot in 0..ctx.settings.workers {
        let ctx = ctx.clone();
        let shutdown = shutdown.clone();
        loops.push(tokio::spawn(async move { worker_loop(ctx, slot, shutdown).await }));
    }
    for l in loops {
        let _ = l.await;
    }
}

async fn worker_loop(ctx: WorkerContext, slot: usize, mut shutdown: watch::Receiver<bool>) {
    let lease = Duration::from_secs_f64(ctx.settings.lease_seconds);
    let poll = Duration::from_millis(ctx.settings.poll_interval_ms);
    loop {
        if *shutdown.borrow() {
            return;
        }
        // Below the free-space floor a job's results could not be stored: claim nothing until space
        // returns (the jobs wait queued, not wedged in `running`).
        match ctx.store.files.has_room(0) {
            Ok((false, free)) => {
                tracing::warn!(slot, free_bytes = free, "disk under its free-space floor; not claiming");
                tokio::select! {
                    _ = tokio::time::sleep(poll.max(Duration::from_secs(1))) => {}
                    _ = shutdown.changed() => {}
                }
                continue;
            }
            Ok((true, _)) => {}
            Err(e) => tracing::warn!(slot, error = %e, "free space unknown"),
        }
        // A lease names the claim, not only the process: two slots of one process never share one.
        let lease_token = format!("{}/{}", ctx.owner, uuid::Uuid::now_v7());
        match ctx.store.claim(&lease_token, lease).await {
            Ok(Some(job)) => {
                tracing::info!(inspection = %job.id, attempt = job.attempts, interruptions = job.interruptions, slot, "claimed");
                // The run's span (trace export): the inspection, its attempt, how it ended, and
                // the pipeline's stages as its events.
                let span = tracing::info_span!(
                    "inspection",
                    otel.name = "inspection",
                    inspection.id = %job.id,
                    attempt = job.attempts,
                    outcome = tracing::field::Empty,
                );
                let run = process(&ctx, job, &lease_token, &mut shutdown);
                tracing::Instrument::instrument(run, span).await;
            }
            Ok(None) => {
                tokio::select! {
                    _ = ctx.wake.notified() => {}
                    _ = tokio::time::sleep(poll) => {}
                    _ = shutdown.changed() => {}
                }
            }
            Err(e) => {
                tracing::error!(error = %e, "claim failed; retrying");
                tokio::time::sleep(poll).await;
            }
        }
    }
}

async fn process(ctx: &WorkerContext, job: Claimed, lease_token: &str, shutdown: &mut watch::Receiver<bool>) {
    let started = Instant::now();
    let cancel = Arc::new(AtomicBool::new(false));
    let progress: Arc<Mutex<Option<(Stage, f64)>>> = Arc::new(Mutex::new(None));
    let lease = Duration::from_secs_f64(ctx.settings.lease_seconds);
    let lease_lost = Arc::new(AtomicBool::new(false));

    // The station's qualification as it stands when the job starts (a later study or suspension
    // applies to later jobs).
    let (at, master_run) = match at_station(ctx, &job.id).await {
        Ok(at) => at,
        Err(e) => {
            tracing::error!(inspection = %job.id, error = %e, "reading the inspection's station failed; the job runs as at an unqualified station would not be honest, so it is retried");
            tokio::time::sleep(Duration::from_secs(1)).await;
            return;
        }
    };
    let task = {
        let (ctx, job, cancel, progress) = (ctx.clone(), job.clone(), cancel.clone(), progress.clone());
        let runtime = tokio::runtime::Handle::current();
        tokio::task::spawn_blocking(move || {
            // The bundle as a local file: the stored one, or a download from the object store
            // (inside the task, so that the lease is renewed while a large one arrives).
            let bundle = runtime.block_on(ctx.store.blobs.fetch(&job.upload_sha256));
            let pool = ctx.compute.clone();
            pool.install(|| {
                contain(&job.id, || run_job(&ctx, &job, bundle, at.as_ref(), master_run, &cancel, &progress))
            })
        })
    };
    tokio::pin!(task);

    let mut beat = tokio::time::interval(Duration::from_secs_f64(ctx.settings.heartbeat_seconds));
    beat.tick().await;
    let mut grace_deadline: Option<tokio::time::Instant> = None;
    let outcome = loop {
        let deadline =
            grace_deadline.unwrap_or_else(|| tokio::time::Instant::now() + Duration::from_secs(86_400 * 365));
        tokio::select! {
            result = &mut task => break result,
            _ = beat.tick() => {
                let snapshot = *progress.lock().expect("progress lock");
                let stage = snapshot.map(|(s, f)| (s.as_str(), f));
                match ctx.store.heartbeat(&job.id, lease_token, lease, stage).await {
                    Ok(Heartbeat::Held { cancel_requested }) => if cancel_requested { cancel.store(true, Ordering::Relaxed) },
                    Ok(Heartbeat::Lost) => {
                        tracing::warn!(inspection = %job.id, "lease lost; stopping");
                        lease_lost.store(true, Ordering::Relaxed);
                        cancel.store(true, Ordering::Relaxed);
                    }
                    Err(e) => tracing::warn!(inspection = %job.id, error = %e, "heartbeat failed"),
                }
            }
            _ = shutdown.changed(), if grace_deadline.is_none() => {
                grace_deadline = Some(tokio::time::Instant::now() + Duration::from_secs_f64(ctx.settings.shutdown_grace_seconds));
                tracing::info!(inspection = %job.id, grace_s = ctx.settings.shutdown_grace_seconds, "shutting down: letting the job finish");
            }
            _ = tokio::time::sleep_until(deadline), if grace_deadline.is_some() => {
                tracing::info!(inspection = %job.id, "grace period over: stopping the job and releasing it");
                cancel.store(true, Ordering::Relaxed);
                // Every stage checks the flag between steps; one that does not come back within
                // this is left behind (the process is about to exit), not waited for: SIGTERM is
                // honoured whatever a job is doing.
                if tokio::time::timeout(STOP_WAIT, &mut task).await.is_err() {
                    tracing::warn!(inspection = %job.id, wait_s = STOP_WAIT.as_secs_f64(), "the job did not stop; releasing it anyway");
                }
                if let Err(e) = ctx.store.requeue(&job.id, lease_token, Duration::ZERO, None, true).await {
                    tracing::error!(inspection = %job.id, error = %e, "release failed; the lease will lapse");
                }
                tracing::Span::current().record("outcome", "released");
                return;
            }
        }
    };
    let outcome =
        outcome.unwrap_or_else(|e| Outcome::Fail(problem(Code::PipelinePanic, format!("worker task failed: {e}"))));
    if lease_lost.load(Ordering::Relaxed) {
        tracing::Span::current().record("outcome", "lease_lost");
        return;
    }
    let elapsed = started.elapsed().as_secs_f64();
    let mut finding = None;
    let (label, stored) = match outcome {
        Outcome::Succeeded(results) => {
            for t in &results.report.timings {
                ctx.metrics.observe_stage(&t.stage, t.seconds);
                tracing::debug!(stage = %t.stage, seconds = t.seconds, "stage");
            }
            let r = &results.report;
            finding = Some((r.verdict.as_str(), r.decision.as_str(), r.review_required));
            ("succeeded", ctx.store.complete_success(&job.id, lease_token, &results).await)
        }
        Outcome::Canceled => {
            ("canceled", ctx.store.complete_without_results(&job.id, lease_token, Status::Canceled, None).await)
        }
        Outcome::Fail(p) => {
            let json = serde_json::to_string(&p).expect("problem serialises");
            ("failed", ctx.store.complete_without_results(&job.id, lease_token, Status::Failed, Some(&json)).await)
        }
        Outcome::Retry(p) => {
            let json = serde_json::to_string(&p).expect("problem serialises");
            let result = if job.failed_attempts() >= job.max_attempts {
                ctx.store.complete_without_results(&job.id, lease_token, Status::Failed, Some(&json)).await
            } else {
                let backoff = Duration::from_secs((1u64 << job.failed_attempts().clamp(0, 6)).min(60));
                ctx.store.requeue(&job.id, lease_token, backoff, Some(&json), false).await
            };
            ("retry", result)
        }
    };
    tracing::Span::current().record("outcome", label);
    match stored {
        Ok(true) => {
            ctx.metrics.job_finished(label, elapsed);
            if let Some((verdict, decision, review)) = finding {
                ctx.metrics.inspection_result(verdict, decision, review);
            }
            tracing::info!(inspection = %job.id, outcome = label, seconds = elapsed, "job done");
        }
        Ok(false) => tracing::warn!(inspection = %job.id, "job was re-claimed elsewhere; result dropped"),
        Err(e) if e.is_storage_full() => {
            // The results do not fit on the disk now: back to the queue (not blamed on the job; the
            // workers claim nothing until space is over the floor again). If even that small write
            // fails, the lease lapses and the job is re-run as after a crash.
            tracing::error!(inspection = %job.id, error = %e, "disk full: results not stored; back to the queue");
            if let Err(e) = ctx.store.requeue(&job.id, lease_token, Duration::from_secs(30), None, true).await {
                tracing::error!(inspection = %job.id, error = %e, "requeue failed too; the lease will lapse");
            }
        }
        Err(e) => {
            // The records or the object store refused the results (an outage): back to the queue
            // after a wait, not blamed on the job, rather than a lapsed lease counted as an
            // interruption (five of those fail a job as poisonous). If the requeue fails too, the
            // lease lapses and the job is re-run as after a crash.
            tracing::error!(inspection = %job.id, error = %e, "could not record the outcome; back to the queue in 30 s");
            if let Err(e) = ctx.store.requeue(&job.id, lease_token, Duration::from_secs(30), None, true).await {
                tracing::error!(inspection = %job.id, error = %e, "requeue failed too; the lease will lapse");
            }
        }
    }
}

/// What the inspection's station says for it: nothing at no station or an unqualified one; its
/// qualification where it is qualified and not expired; why not where it is suspended or expired.
async fn at_station(
    ctx: &WorkerContext,
    id: &str,
) -> Result<(Option<pipeline::qualify::AtStation>, bool), crate::service::store::StoreError> {
    let row = ctx.store.inspection(id).await?;
    let Some(name) = row.station else { return Ok((None, false)) };
    // A run of one of the station's masters is what a study or a check reads: classical heights.
    let master_run = match &row.serial {
        Some(serial) => ctx.store.masters(&name).await?.iter().any(|m| &m.serial == serial),
        None => false,
    };
    Ok((qualification_at(ctx, &name).await?, master_run))
}

/// The qualification an inspection at station `name` is to apply, or why it may not.
async fn qualification_at(
    ctx: &WorkerContext,
    name: &str,
) -> Result<Option<pipeline::qualify::AtStation>, crate::service::store::StoreError> {
    use pipeline::qualify::AtStation;
    let name = name.to_string();
    let station = ctx.store.station(&name).await?;
    let refused = |reason: String| Ok(Some(AtStation::Refused { station: name.clone(), reason }));
    match (station.status.as_str(), &station.study_id) {
        ("qualified", Some(study)) => {
            let row = ctx.store.study(&name, study).await?;
            let q: crate::domain::qualification::Qualification = serde_json::from_str(&row.qualification_json)
                .map_err(|e| crate::service::store::StoreError::Io(std::io::Error::other(e)))?;
            if let Some(reason) =
                crate::service::wire::qualification_expired(&name, &q, crate::service::store::now_ms())
            {
                return refused(reason);
            }
            Ok(Some(AtStation::Qualified(q)))
        }
        ("suspended", _) => refused(format!(
            "Station {name} is suspended: {}",
            station.status_reason.as_deref().unwrap_or("no reason was given")
        )),
        _ => Ok(None),
    }
}

/// Runs a job's blocking part; a panic becomes that job's permanent failure, not the worker's end.
fn contain(id: &str, run: impl FnOnce() -> Outcome) -> Outcome {
    std::panic::catch_unwind(AssertUnwindSafe(run)).unwrap_or_else(|panic| {
        let message = panic
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| panic.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".into());
        // The panic's text names the code, not the input: it goes to the log, under a reference
        // the client sees.
        let reference = uuid::Uuid::now_v7();
        tracing::error!(inspection = %id, %message, %reference, "pipeline panicked");
        Outcome::Fail(problem(
            Code::PipelinePanic,
            format!("the pipeline crashed on this bundle; the server's log has the cause under reference {reference}"),
        ))
    })
}

/// The blocking part: open the stored bundle, run the pipeline, encode the results.
fn run_job(
    ctx: &WorkerContext,
    job: &Claimed,
    bundle: std::io::Result<crate::service::store::blobs::LocalCopy>,
    at: Option<&pipeline::qualify::AtStation>,
    master_run: bool,
    cancel: &AtomicBool,
    progress: &Mutex<Option<(Stage, f64)>>,
) -> Outcome {
    let mut options: JobOptions = match serde_json::from_str(&job.options_json) {
        Ok(o) => o,
        Err(e) => return Outcome::Fail(problem(Code::InvalidOption, format!("stored options unreadable: {e}"))),
    };
    if master_run {
        options.pipeline.profile.correction = pipeline::profile::Correction::Off;
    }
    let copy = match bundle {
        Ok(copy) => copy,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Outcome::Fail(problem(
                Code::UploadMissing,
                format!("the uploaded bundle {} is no longer in the store", job.upload_sha256),
            ));
        }
        // The store unreachable or the download cut: another attempt may succeed.
        Err(e) => {
            return Outcome::Retry(problem(
                Code::IoError,
                format!(
                    "the uploaded bundle {} could not be read from {}: {e}",
                    job.upload_sha256,
                    ctx.store.blobs.describe()
                ),
            ));
        }
    };
    let path = copy.path();
    let limits = ctx.settings.bundle_limits();
    let bundle = match Bundle::open(
        &path,
        &ctx.table,
        OpenOptions { limits, name: Some("the upload"), ..OpenOptions::default() },
    ) {
        Ok(b) => b,
        Err(e) => return failure(&e),
    };
    if let Err(e) = crate::service::queue::check_memory(&bundle, &options.pipeline, &ctx.settings) {
        return Outcome::Fail(Problem::of(&e));
    }
    let report_progress = |stage: Stage, fraction: f64| {
        *progress.lock().expect("progress lock") = Some((stage, fraction));
    };
    let mut inspection =
        match pipeline::inspect_at(&bundle, &options.pipeline, &ctx.models, &report_progress, cancel, at) {
            Ok(Some(i)) => i,
            Ok(None) => return Outcome::Canceled,
            Err(e) => return failure(&e),
        };
    if let Some(provenance) = inspection.report.provenance.as_mut() {
        provenance.inspection_id = Some(job.id.clone());
        provenance.bundle_sha256 = Some(job.upload_sha256.clone());
    }
    let optics = bundle.optics();
    let profiles = crate::eval::pairs::ProfileSet::of(
        &inspection,
        &bundle.part().form,
        optics.object_pixel_mm(optics.focus_distance_mm),
    );
    match encode_results(&inspection) {
        Ok(mut r) => {
            // Kept for the profile-correction MLP's training pairs once CMM data arrives
            // (`GET …/training-pairs`; docs/models.md).
            r.artifacts.push(Artifact {
                kind: PITCH_PROFILES,
                content_type: "application/octet-stream",
                body: profiles.encode(),
            });
            Outcome::Succeeded(Box::new(r))
        }
        Err(e) => {
            let reference = uuid::Uuid::now_v7();
            tracing::warn!(inspection = %job.id, error = %e, %reference, "encoding the results failed");
            Outcome::Retry(problem(Code::IoError, format!("encoding the results failed; log reference {reference}")))
        }
    }
}

/// A bundle that cannot be read or inspected fails for good with its own problem; a transient
/// failure (the server's storage) is retried, shown as an internal error (its path is the
/// operator's business, in the log), as the API shows it.
fn failure(e: &impl ErrorCode) -> Outcome {
    if e.code().is_transient() {
        let reference = uuid::Uuid::now_v7();
        tracing::warn!(error = %e, %reference, "transient failure; the job will be retried");
        Outcome::Retry(problem(
            Code::InternalError,
            format!("the server failed; its log has the cause under reference {reference}"),
        ))
    } else {
        Outcome::Fail(Problem::of(e))
    }
}

pub use crate::service::store::PITCH_PROFILES;

pub fn encode_results(
    inspection: &pipeline::Inspection,
) -> Result<JobResults, Box<dyn std::error::Error + Send + Sync>> {
    let report = &inspection.report;
    let mut ply = Vec::new();
    ply::write(&inspection.mesh, &mut ply)?;
    let mut stl = Vec::new();
    stl::write(&inspection.mesh, &mut stl)?;
    // The report as stored and served, its numbers rounded to their resolution; the thread tables
    // are filled from the same rounded values, so the report, the table and its CSV agree.
    let report_json = String::from_utf8(crate::export::json::to_vec(report)?)?;
    let report: crate::pipeline::report::Report = serde_json::from_str(&report_json)?;
    Ok(JobResults {
        verdict: match report.verdict {
            Verdict::Accept => "accept",
            Verdict::Reject => "reject",
        },
        report_json,
        report,
        artifacts: vec![
            Artifact { kind: "mesh.ply", content_type: "application/x-ply", body: ply },
            Artifact { kind: "mesh.stl", content_type: "model/stl", body: stl },
            Artifact { kind: "height-map.png", content_type: "image/png", body: png::height_map_png(&inspection.map)? },
            Artifact { kind: "all-in-focus.png", content_type: "image/png", body: png::mosaic_png(&inspection.map)? },
        ],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panicking_job_fails_with_a_problem_and_the_caller_goes_on() {
        let outcome = contain("job-1", || {
            let empty: Vec<u8> = Vec::new();
            Outcome::Fail(problem(Code::NoDepth, format!("{}", empty[3])))
        });
        let Outcome::Fail(p) = outcome else { panic!("a panic must fail the job") };
        assert_eq!((p.code.as_str(), p.status), ("pipeline_panic", 500));
        // The panic's text is logged, not shown.
        assert!(!p.detail.contains("index out of bounds") && p.detail.contains("reference"), "{}", p.detail);
        assert!(matches!(contain("job-2", || Outcome::Canceled), Outcome::Canceled));
    }

    #[test]
    fn io_errors_retry_and_bad_input_fails() {
        use crate::bundle::BundleError;
        let Outcome::Retry(p) = failure(&BundleError::Io { path: "x".into(), message: "EIO".into() }) else {
            panic!("I/O is retried")
        };
        assert_eq!((p.code.as_str(), p.culprit), ("internal_error", None));
        assert!(!p.detail.contains("EIO") && !p.detail.contains('/'), "no server detail shown: {}", p.detail);
        let Outcome::Fail(p) = failure(&BundleError::MissingFile { path: "a/0.png".into() }) else { panic!() };
        assert_eq!((p.code.as_str(), p.culprit.as_deref()), ("missing_file", Some("a/0.png")));
        let Outcome::Fail(p) = failure(&pipeline::PipelineError::NoDepth) else { panic!() };
        assert_eq!((p.code.as_str(), p.status), ("no_depth", 422));
    }
}
