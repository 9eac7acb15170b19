//! Receiving a bundle: the request body (raw zip/tar, or multipart with one `bundle` part, or a
//! `manifest` part plus frame parts named by their manifest paths) is streamed to a temporary file
//! in the data directory while it is hashed; multipart frame parts are written as a tar archive.
//! File writes run on one blocking thread fed through a bounded channel, so the async runtime never
//! blocks on the disk.

use super::problem::ApiError;
use crate::bundle::check_relative_path;
use crate::problem::Code;
use crate::service::store::files::{FileStore, HashingWriter};
use axum::body::{Body, Bytes};
use axum::extract::{FromRequest, Multipart, Request};
use axum::http::header;
use futures_util::StreamExt;
use std::io::{BufWriter, Write};
use tokio::sync::mpsc;

/// A received upload, not yet validated or committed.
pub struct Received {
    pub file: tempfile::NamedTempFile,
    pub sha256: String,
    pub size_bytes: u64,
    /// The multipart `options` part, if any (JSON).
    pub options_part: Option<Vec<u8>>,
}

enum Chunk {
    Raw(Bytes),
    Entry { path: String, data: Vec<u8> },
}

type FileWriter = HashingWriter<BufWriter<std::fs::File>>;

enum Sink {
    Empty(FileWriter),
    Raw(FileWriter),
    Tar(tar::Builder<FileWriter>),
}

/// The blocking side: owns the file, appends raw bytes or tar entries.
fn write_loop(file: std::fs::File, mut rx: mpsc::Receiver<Chunk>) -> std::io::Result<(String, u64)> {
    let mut sink = Sink::Empty(HashingWriter::new(BufWriter::with_capacity(1 << 20, file)));
    while let Some(chunk) = rx.blocking_recv() {
        sink = match (sink, chunk) {
            (Sink::Empty(mut w) | Sink::Raw(mut w), Chunk::Raw(bytes)) => {
                w.write_all(&bytes)?;
                Sink::Raw(w)
            }
            (Sink::Empty(w), chunk @ Chunk::Entry { .. }) => {
                let mut builder = tar::Builder::new(w);
                append_entry(&mut builder, chunk)?;
                Sink::Tar(builder)
            }
            (Sink::Tar(mut builder), chunk @ Chunk::Entry { .. }) => {
                append_entry(&mut builder, chunk)?;
                Sink::Tar(builder)
            }
            _ => return Err(std::io::Error::other("raw bytes and multipart entries mixed")),
        };
    }
    let writer = match sink {
        Sink::Empty(w) | Sink::Raw(w) => w,
        Sink::Tar(builder) => builder.into_inner()?,
    };
    let (buffered, sha256, size) = writer.finish();
    buffered.into_inner().map_err(|e| e.into_error())?.flush()?;
    Ok((sha256, size))
}

fn append_entry(builder: &mut tar::Builder<FileWriter>, chunk: Chunk) -> std::io::Result<()> {
    let Chunk::Entry { path, data } = chunk else { unreachable!("only entries reach here") };
    let mut header = tar::Header::new_ustar();
    header.set_size(data.len() as u64);
    header.set_mode(0o644);
    header.set_entry_type(tar::EntryType::Regular);
    builder.append_data(&mut header, &path, data.as_slice())
}

struct Upload {
    tx: mpsc::Sender<Chunk>,
    writer: tokio::task::JoinHandle<std::io::Result<(String, u64)>>,
    file: tempfile::NamedTempFile,
    received: u64,
    files: FileStore,
    /// Received bytes at which the free space is looked at next.
    next_space_check: u64,
    rules: UploadRules,
    /// This upload's place in the [`UploadGate`]: its progress is shown there, and the gate may
    /// take the place back from an upload too slow to keep it.
    slot: std::sync::Arc<UploadSlot>,
}

/// What an upload may take: its size, and how slowly it may come.
#[derive(Clone, Copy, Debug)]
pub struct UploadRules {
    pub limit: u64,
    /// The longest wait for the body's next piece.
    pub idle: std::time::Duration,
    /// Once `idle` has passed since the upload began, the average rate it must keep, bytes/s (a
    /// floor on the average, not a total timeout: a large bundle at a steady rate streams on).
    pub min_bytes_per_s: f64,
}

/// How long an upload may run before its average rate is held to the floor: long enough for a
/// connection to reach its pace, short enough that a trickle cannot hold a place for the 30 s
/// idle limit.
const RATE_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

impl UploadRules {
    /// When the rate floor starts to apply: after [`RATE_GRACE`], or the idle limit if shorter.
    fn rate_grace(&self) -> std::time::Duration {
        self.idle.min(RATE_GRACE)
    }

    pub fn of(settings: &crate::service::config::Settings) -> Self {
        Self {
            limit: settings.max_upload_bytes(),
            idle: std::time::Duration::from_secs_f64(settings.upload_idle_seconds),
            min_bytes_per_s: settings.min_upload_kib_per_s * 1024.0,
        }
    }
}

fn too_slow(detail: String) -> ApiError {
    tracing::warn!(%detail, "upload cut off");
    ApiError::new(Code::RequestTimeout, detail)
}

/// How often, in received bytes, a streaming upload checks that the disk stays above its floor.
const SPACE_CHECK_BYTES: u64 = 32 << 20;

/// 507 unless `incoming` more bytes leave the store above its free-space floor.
pub fn ensure_room(files: &FileStore, incoming: u64) -> Result<(), ApiError> {
    let (room, free) = files.has_room(incoming).map_err(ApiError::internal)?;
    if room {
        return Ok(());
    }
    tracing::warn!(free_bytes = free, floor_bytes = files.free_floor_bytes(), incoming, "upload refused: disk low");
    Err(ApiError::new(
        Code::InsufficientStorage,
        format!(
            "the server's disk cannot take this upload now: {} MiB free, {} MiB kept free (min_free_disk_mb){}; \
             retry later",
            free >> 20,
            files.free_floor_bytes() >> 20,
            if incoming > 0 { format!(", {} MiB announced", incoming >> 20) } else { String::new() }
        ),
    ))
}

/// The client-facing error of a failed upload write: 507 when the disk is full, else internal
/// (logged, with a reference).
pub fn write_failed(e: &std::io::Error) -> ApiError {
    if crate::service::store::files::is_storage_full(e) {
        tracing::warn!(error = %e, "upload failed: disk full");
        ApiError::new(Code::InsufficientStorage, "the server's disk filled while storing this upload; retry later")
    } else {
        ApiError::internal(format!("writing the upload: {e}"))
    }
}

impl Upload {
    fn start(files: &FileStore, rules: UploadRules, slot: std::sync::Arc<UploadSlot>) -> Result<Self, ApiError> {
        let file = files.temp_file().map_err(|e| write_failed(&e))?;
        let handle = file.reopen().map_err(ApiError::internal)?;
        let (tx, rx) = mpsc::channel(64);
        let writer = tokio::task::spawn_blocking(move || write_loop(handle, rx));
        Ok(Self {
            tx,
            writer,
            file,
            received: 0,
            files: files.clone(),
            next_space_check: SPACE_CHECK_BYTES,
            rules,
            slot,
        })
    }

    /// Awaits the body's next piece within the idle limit, then checks the average rate (once the
    /// grace has passed). Ends at once if the gate took this upload's place for a faster one.
    async fn paced<T>(&self, next: impl std::future::Future<Output = T>) -> Result<T, ApiError> {
        let evicted = self.slot.evicted.notified();
        tokio::pin!(evicted);
        // Registered before the flag is read, so an eviction between the two is not missed.
        evicted.as_mut().enable();
        if self.slot.is_evicted() {
            return Err(self.evicted_error());
        }
        let value = tokio::select! {
            value = tokio::time::timeout(self.rules.idle, next) => value,
            _ = &mut evicted => return Err(self.evicted_error()),
        };
        let Ok(value) = value else {
            return Err(too_slow(format!(
                "the upload sent nothing for {:.0} s (upload_idle_seconds) after {} bytes",
                self.rules.idle.as_secs_f64(),
                self.received
            )));
        };
        let elapsed = self.slot.started.elapsed();
        if elapsed > self.rules.rate_grace() {
            let rate = self.received as f64 / elapsed.as_secs_f64();
            if rate < self.rules.min_bytes_per_s {
                return Err(too_slow(format!(
                    "the upload came at {:.1} KiB/s over {:.0} s, under the {:.0} KiB/s floor (min_upload_kib_per_s)",
                    rate / 1024.0,
                    elapsed.as_secs_f64(),
                    self.rules.min_bytes_per_s / 1024.0
                )));
            }
        }
        Ok(value)
    }

    fn evicted_error(&self) -> ApiError {
        let elapsed = self.slot.started.elapsed().as_secs_f64().max(1e-3);
        too_slow(format!(
            "the upload came at {:.1} KiB/s over {elapsed:.1} s, under the {:.0} KiB/s floor (min_upload_kib_per_s), \
             while every upload place was taken: its place went to an upload that keeps the pace",
            self.received as f64 / elapsed / 1024.0,
            self.rules.min_bytes_per_s / 1024.0
        ))
    }

    fn count(&mut self, n: usize) -> Result<(), ApiError> {
        self.received += n as u64;
        self.slot.received.store(self.received, std::sync::atomic::Ordering::Relaxed);
        if self.received > self.rules.limit {
            return Err(too_large(self.rules.limit));
        }
        if self.received >= self.next_space_check {
            self.next_space_check = self.received + SPACE_CHECK_BYTES;
            ensure_room(&self.files, 0)?;
        }
        Ok(())
    }

    async fn send(&mut self, chunk: Chunk) -> Result<(), ApiError> {
        if self.tx.send(chunk).await.is_err() {
            // The writer stopped: its error says why.
            return Err(self.writer_error().await);
        }
        Ok(())
    }

    async fn writer_error(&mut self) -> ApiError {
        match (&mut self.writer).await {
            Ok(Err(e)) => write_failed(&e),
            Ok(Ok(_)) => ApiError::internal("upload writer stopped early"),
            Err(e) => ApiError::internal(format!("upload writer: {e}")),
        }
    }

    async fn finish(self, options_part: Option<Vec<u8>>) -> Result<Received, ApiError> {
        drop(self.tx);
        let (sha256, size_bytes) = self.writer.await.map_err(ApiError::internal)?.map_err(|e| write_failed(&e))?;
        Ok(Received { file: self.file, sha256, size_bytes, options_part })
    }
}

const DRAIN_BYTES: u64 = 64 << 20;

/// Reads and drops up to 64 MiB of a body that is being refused, so a client that sends it whole
/// (without `Expect: 100-continue`) reads the problem instead of a reset connection.
pub async fn drain(body: Body) {
    drain_stream(body.into_data_stream()).await
}

/// The longest a refused body is read for: a slow client is not waited on.
const DRAIN_SECONDS: u64 = 5;

async fn drain_stream(mut stream: axum::body::BodyDataStream) {
    let read = async {
        let mut seen = 0u64;
        while let Some(Ok(chunk)) = stream.next().await {
            seen += chunk.len() as u64;
            if seen > DRAIN_BYTES {
                break;
            }
        }
    };
    let _ = tokio::time::timeout(std::time::Duration::from_secs(DRAIN_SECONDS), read).await;
}

fn too_large(limit: u64) -> ApiError {
    ApiError::new(Code::BodyTooLarge, format!("the upload exceeds the {} MiB limit (max_upload_mb)", limit >> 20))
}

/// Streams the request body into the file store's temporary area.
pub async fn receive(
    request: Request,
    files: &FileStore,
    rules: UploadRules,
    slot: std::sync::Arc<UploadSlot>,
) -> Result<Received, ApiError> {
    let limit = rules.limit;
    let content_type =
        request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let length = request.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    if let Some(length) = length
        && length > limit
    {
        // Read (and drop) a moderate excess so that clients without `Expect: 100-continue` see the
        // 413 instead of a reset connection; larger bodies are cut off.
        if length <= limit.saturating_add(DRAIN_BYTES) {
            drain(request.into_body()).await;
        }
        return Err(too_large(limit));
    }
    let announced = length.unwrap_or(0);
    if let Err(e) = ensure_room(files, announced) {
        if announced <= DRAIN_BYTES {
            drain(request.into_body()).await;
        }
        return Err(e);
    }
    let essence = content_type.split(';').next().unwrap_or("").trim().to_string();
    match essence.as_str() {
        "multipart/form-data" => receive_multipart(request, files, rules, slot).await,
        "application/zip"
        | "application/x-zip-compressed"
        | "application/x-tar"
        | "application/tar"
        | "application/octet-stream"
        | "application/gzip"
        | "application/x-gzip"
        | "application/x-gtar"
        | "application/x-compressed-tar" => receive_raw(request.into_body(), files, rules, slot).await,
        other => {
            let error = ApiError::new(
            Code::UnsupportedMediaType,
            format!(
                "Content-Type {:?}: send the bundle as application/zip, application/x-tar, application/gzip (a .tar.gz), application/octet-stream or multipart/form-data",
                if other.is_empty() { "(none)" } else { other }
            ),
            )
            .with_culprit("Content-Type");
            drain(request.into_body()).await;
            Err(error)
        }
    }
}

async fn receive_raw(
    body: Body,
    files: &FileStore,
    rules: UploadRules,
    slot: std::sync::Arc<UploadSlot>,
) -> Result<Received, ApiError> {
    let mut upload = Upload::start(files, rules, slot)?;
    let mut stream = body.into_data_stream();
    while let Some(chunk) = upload.paced(stream.next()).await? {
        let chunk = chunk.map_err(|e| ApiError::new(Code::BadRequest, format!("reading the body: {e}")))?;
        if let Err(e) = upload.count(chunk.len()) {
            drain_stream(stream).await;
            return Err(e);
        }
        upload.send(Chunk::Raw(chunk)).await?;
    }
    if upload.received == 0 {
        return Err(
            ApiError::new(Code::InvalidArchive, "the body is empty: expected a zip or tar bundle").with_culprit("body")
        );
    }
    upload.finish(None).await
}

fn multipart_error(e: axum::extract::multipart::MultipartError) -> ApiError {
    if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        return ApiError::new(Code::BodyTooLarge, e.body_text());
    }
    ApiError::new(Code::InvalidMultipart, e.body_text()).with_culprit("body")
}

async fn receive_multipart(
    request: Request,
    files: &FileStore,
    rules: UploadRules,
    slot: std::sync::Arc<UploadSlot>,
) -> Result<Received, ApiError> {
    let mut multipart = Multipart::from_request(request, &())
        .await
        .map_err(|e| ApiError::new(Code::InvalidMultipart, e.body_text()).with_culprit("body"))?;
    let result = read_parts(&mut multipart, files, rules, slot).await;
    // A slow client is not waited for again.
    if result.as_ref().is_err_and(|e| e.code != Code::RequestTimeout) {
        // As for raw bodies: read (and drop) a moderate rest so the client sees the problem.
        let read = async {
            let mut seen = 0u64;
            'parts: while let Ok(Some(mut field)) = multipart.next_field().await {
                while let Ok(Some(chunk)) = field.chunk().await {
                    seen += chunk.len() as u64;
                    if seen > DRAIN_BYTES {
                        break 'parts;
                    }
                }
            }
        };
        let _ = tokio::time::timeout(std::time::Duration::from_secs(DRAIN_SECONDS), read).await;
    }
    result
}

/// Reads a whole part into memory, counted against the upload's limit; `too_big` is the refusal
/// once it passes `cap` bytes.
async fn read_part(
    field: &mut axum::extract::multipart::Field<'_>,
    upload: &mut Upload,
    cap: u64,
    too_big: impl FnOnce() -> ApiError,
) -> Result<Vec<u8>, ApiError> {
    let mut data = Vec::new();
    while let Some(chunk) = upload.paced(field.chunk()).await?.map_err(multipart_error)? {
        upload.count(chunk.len())?;
        data.extend_from_slice(&chunk);
        if data.len() as u64 > cap {
            return Err(too_big());
        }
    }
    Ok(data)
}

async fn read_parts(
    multipart: &mut Multipart,
    files: &FileStore,
    rules: UploadRules,
    slot: std::sync::Arc<UploadSlot>,
) -> Result<Received, ApiError> {
    let mut upload = Upload::start(files, rules, slot)?;
    let mut options = None;
    let (mut archive_part, mut manifest_part, mut frame_parts) = (false, false, 0usize);
    while let Some(mut field) = upload.paced(multipart.next_field()).await?.map_err(multipart_error)? {
        let name = field.name().unwrap_or("").to_string();
        match name.as_str() {
            "options" => {
                options = Some(
                    read_part(&mut field, &mut upload, 1 << 20, || {
                        ApiError::new(Code::InvalidOption, "the options part exceeds 1 MiB").with_culprit("options")
                    })
                    .await?,
                );
            }
            "bundle" => {
                if archive_part || manifest_part || frame_parts > 0 {
                    return Err(ApiError::new(
                        Code::InvalidMultipart,
                        "a `bundle` part must be the only bundle content",
                    )
                    .with_culprit("bundle"));
                }
                archive_part = true;
                while let Some(chunk) = upload.paced(field.chunk()).await?.map_err(multipart_error)? {
                    upload.count(chunk.len())?;
                    upload.send(Chunk::Raw(chunk)).await?;
                }
            }
            _ => {
                if archive_part {
                    return Err(ApiError::new(
                        Code::InvalidMultipart,
                        format!("part {name:?} next to a `bundle` part"),
                    )
                    .with_culprit(name));
                }
                let path = if name == "manifest" || name == "manifest.json" {
                    if manifest_part {
                        return Err(
                            ApiError::new(Code::InvalidMultipart, "two manifest parts").with_culprit("manifest")
                        );
                    }
                    manifest_part = true;
                    "manifest.json".to_string()
                } else {
                    // Frame parts are named by their manifest path (the part name, else its filename).
                    let path = if name.is_empty() || name == "file" || name == "frame" {
                        field.file_name().unwrap_or("").to_string()
                    } else {
                        name.clone()
                    };
                    check_relative_path(&path).map_err(|message| {
                        ApiError::new(Code::UnsafePath, format!("part {path:?}: {message}")).with_culprit(path.clone())
                    })?;
                    frame_parts += 1;
                    path
                };
                // Parts are held in memory until written as tar entries: each is capped like a
                // bundle file.
                let max_part = crate::bundle::Limits::default().max_file_bytes;
                let data = read_part(&mut field, &mut upload, max_part, || {
                    ApiError::new(
                        Code::BundleTooLarge,
                        format!("part {path:?} exceeds the per-file cap of {max_part} bytes"),
                    )
                    .with_culprit(path.clone())
                })
                .await?;
                upload.send(Chunk::Entry { path, data }).await?;
            }
        }
    }
    if !archive_part && !manifest_part {
        return Err(ApiError::new(
            Code::InvalidMultipart,
            "no bundle: send a `bundle` part (zip or tar), or a `manifest` part and one part per frame named by its manifest path",
        )
        .with_culprit("bundle"));
    }
    upload.finish(options).await
}

/// Caps on uploads received at once, over all clients and per client address. Each upload holds a
/// writer thread of the blocking pool and a temporary file while it streams, so without a cap slow
/// clients could take every thread.
///
/// The places belong to uploads that keep the pace: when every place is taken, a new upload takes
/// the place of the slowest one that has run for [`EVICT_AFTER`] and averages under the rate floor
/// (`min_upload_kib_per_s`); that one ends with 408. So however many clients trickle, a client at
/// the floor or faster still gets in (issue 48: 100 uploads at 1 byte/s held every place until
/// their 30 s timeout). With no floor (0), no place is taken back.
pub struct UploadGate {
    global: usize,
    per_client: usize,
    floor_bytes_per_s: f64,
    open: std::sync::Mutex<GateState>,
}

#[derive(Default)]
struct GateState {
    total: usize,
    by_client: std::collections::HashMap<std::net::IpAddr, usize>,
    slots: Vec<(std::net::IpAddr, std::sync::Arc<UploadSlot>)>,
}

/// How long an upload runs before the gate may judge it by its average rate.
pub const EVICT_AFTER: std::time::Duration = std::time::Duration::from_secs(1);

/// One upload's place: when it started, what it has received, and whether the gate took it back.
#[derive(Debug)]
pub struct UploadSlot {
    started: std::time::Instant,
    received: std::sync::atomic::AtomicU64,
    evicted_flag: std::sync::atomic::AtomicBool,
    evicted: tokio::sync::Notify,
}

impl UploadSlot {
    fn new() -> Self {
        Self {
            started: std::time::Instant::now(),
            received: Default::default(),
            evicted_flag: Default::default(),
            evicted: tokio::sync::Notify::new(),
        }
    }

    fn is_evicted(&self) -> bool {
        self.evicted_flag.load(std::sync::atomic::Ordering::Acquire)
    }

    /// Average bytes/s so far, once it has run [`EVICT_AFTER`]; None before.
    fn judged_rate(&self, now: std::time::Instant) -> Option<f64> {
        let age = now.saturating_duration_since(self.started);
        (age >= EVICT_AFTER)
            .then(|| self.received.load(std::sync::atomic::Ordering::Relaxed) as f64 / age.as_secs_f64())
    }
}

/// An admitted upload; leaving frees its places (unless the gate took them back already).
pub struct UploadPass<'a> {
    gate: &'a UploadGate,
    client: std::net::IpAddr,
    slot: std::sync::Arc<UploadSlot>,
}

impl UploadPass<'_> {
    pub fn slot(&self) -> std::sync::Arc<UploadSlot> {
        self.slot.clone()
    }
}

impl GateState {
    fn release(&mut self, client: std::net::IpAddr, slot: &std::sync::Arc<UploadSlot>) {
        let Some(at) = self.slots.iter().position(|(_, s)| std::sync::Arc::ptr_eq(s, slot)) else { return };
        self.slots.swap_remove(at);
        self.total -= 1;
        if let Some(n) = self.by_client.get_mut(&client) {
            *n -= 1;
            if *n == 0 {
                self.by_client.remove(&client);
            }
        }
    }

    /// The slowest upload under `floor` (of `client` only, when given) that has run long enough
    /// to be judged.
    fn slowest_under(
        &self,
        floor: f64,
        client: Option<std::net::IpAddr>,
    ) -> Option<(std::net::IpAddr, std::sync::Arc<UploadSlot>)> {
        let now = std::time::Instant::now();
        self.slots
            .iter()
            .filter(|(c, _)| client.is_none_or(|wanted| *c == wanted))
            .filter_map(|(c, s)| s.judged_rate(now).filter(|&r| r < floor).map(|r| (r, c, s)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, c, s)| (*c, s.clone()))
    }

    /// Takes a place back from a too-slow upload: it is told, and its place is free at once.
    fn evict(&mut self, client: std::net::IpAddr, slot: std::sync::Arc<UploadSlot>) {
        slot.evicted_flag.store(true, std::sync::atomic::Ordering::Release);
        slot.evicted.notify_waiters();
        tracing::warn!(%client, received = slot.received.load(std::sync::atomic::Ordering::Relaxed),
            seconds = slot.started.elapsed().as_secs_f64(), "slow upload's place given to a new upload");
        self.release(client, &slot);
    }
}

impl UploadGate {
    pub fn new(global: usize, per_client: usize, floor_bytes_per_s: f64) -> Self {
        Self { global, per_client, floor_bytes_per_s, open: Default::default() }
    }

    pub fn enter(&self, client: std::net::IpAddr) -> Result<UploadPass<'_>, ApiError> {
        let mut open = self.open.lock().expect("gate lock");
        let floor = self.floor_bytes_per_s;
        let mine = open.by_client.get(&client).copied().unwrap_or(0);
        if mine >= self.per_client {
            match (floor > 0.0).then(|| open.slowest_under(floor, Some(client))).flatten() {
                Some((c, slot)) => open.evict(c, slot),
                None => {
                    return Err(ApiError::new(
                        Code::TooManyUploads,
                        format!(
                            "{mine} uploads from {client} are already being received (max_uploads_per_client); retry when one ends"
                        ),
                    ));
                }
            }
        }
        if open.total >= self.global {
            match (floor > 0.0).then(|| open.slowest_under(floor, None)).flatten() {
                Some((c, slot)) => open.evict(c, slot),
                None => {
                    return Err(ApiError::new(
                        Code::ServerBusy,
                        format!(
                            "{} uploads are being received (max_concurrent_uploads), each at the rate floor or faster; retry shortly",
                            open.total
                        ),
                    ));
                }
            }
        }
        let slot = std::sync::Arc::new(UploadSlot::new());
        open.total += 1;
        *open.by_client.entry(client).or_insert(0) += 1;
        open.slots.push((client, slot.clone()));
        Ok(UploadPass { gate: self, client, slot })
    }
}

impl Drop for UploadPass<'_> {
    fn drop(&mut self) {
        let mut open = self.gate.open.lock().expect("gate lock");
        open.release(self.client, &self.slot);
    }
}

#[cfg(test)]
mod gate_tests {
    use super::*;

    #[test]
    fn the_gate_caps_each_client_and_all_of_them_and_frees_places_on_leaving() {
        let gate = UploadGate::new(3, 2, 64.0 * 1024.0);
        let (a, b, c): (std::net::IpAddr, std::net::IpAddr, std::net::IpAddr) =
            ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap(), "10.0.0.3".parse().unwrap());
        let a1 = gate.enter(a).unwrap();
        let _a2 = gate.enter(a).unwrap();
        assert_eq!(gate.enter(a).err().unwrap().code, Code::TooManyUploads);
        let _b1 = gate.enter(b).unwrap();
        assert_eq!(gate.enter(c).err().unwrap().code, Code::ServerBusy);
        drop(a1);
        let _c1 = gate.enter(c).unwrap();
        assert_eq!(gate.enter(b).err().unwrap().code, Code::ServerBusy);
    }

    #[test]
    fn a_full_gate_gives_the_place_of_the_slowest_trickle_to_a_new_upload() {
        let floor = 64.0 * 1024.0;
        let gate = UploadGate::new(2, 2, floor);
        let (a, b, c): (std::net::IpAddr, std::net::IpAddr, std::net::IpAddr) =
            ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap(), "10.0.0.3".parse().unwrap());
        let trickle = gate.enter(a).unwrap();
        let steady = gate.enter(a).unwrap();
        // Young uploads are not judged: the gate is simply full.
        assert_eq!(gate.enter(b).err().unwrap().code, Code::ServerBusy);
        std::thread::sleep(EVICT_AFTER + std::time::Duration::from_millis(100));
        trickle.slot().received.store(3, std::sync::atomic::Ordering::Relaxed);
        steady.slot().received.store(10 << 20, std::sync::atomic::Ordering::Relaxed);
        let newcomer = gate.enter(b).expect("the trickle's place");
        assert!(trickle.slot().is_evicted() && !steady.slot().is_evicted());
        // The steady upload keeps its place; the newcomer is too young to judge.
        assert_eq!(gate.enter(c).err().unwrap().code, Code::ServerBusy);
        // The evicted pass leaving frees nothing twice.
        drop(trickle);
        assert_eq!(gate.enter(c).err().unwrap().code, Code::ServerBusy);
        drop(newcomer);
        let _c = gate.enter(c).unwrap();
    }

    #[test]
    fn without_a_floor_no_place_is_taken_back() {
        let gate = UploadGate::new(1, 1, 0.0);
        let a: std::net::IpAddr = "10.0.0.1".parse().unwrap();
        let _slow = gate.enter(a).unwrap();
        std::thread::sleep(EVICT_AFTER + std::time::Duration::from_millis(100));
        assert_eq!(gate.enter("10.0.0.2".parse().unwrap()).err().unwrap().code, Code::ServerBusy);
    }
}
