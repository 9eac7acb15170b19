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
    started: std::time::Instant,
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

impl UploadRules {
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
    fn start(files: &FileStore, rules: UploadRules) -> Result<Self, ApiError> {
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
            started: std::time::Instant::now(),
        })
    }

    /// Awaits the body's next piece within the idle limit, then checks the average rate.
    async fn paced<T>(&self, next: impl std::future::Future<Output = T>) -> Result<T, ApiError> {
        let Ok(value) = tokio::time::timeout(self.rules.idle, next).await else {
            return Err(too_slow(format!(
                "the upload sent nothing for {:.0} s (upload_idle_seconds) after {} bytes",
                self.rules.idle.as_secs_f64(),
                self.received
            )));
        };
        let elapsed = self.started.elapsed();
        if elapsed > self.rules.idle {
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

    fn count(&mut self, n: usize) -> Result<(), ApiError> {
        self.received += n as u64;
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
pub async fn receive(request: Request, files: &FileStore, rules: UploadRules) -> Result<Received, ApiError> {
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
        "multipart/form-data" => receive_multipart(request, files, rules).await,
        "application/zip"
        | "application/x-zip-compressed"
        | "application/x-tar"
        | "application/tar"
        | "application/octet-stream" => receive_raw(request.into_body(), files, rules).await,
        other => {
            let error = ApiError::new(
            Code::UnsupportedMediaType,
            format!(
                "Content-Type {:?}: send the bundle as application/zip, application/x-tar, application/octet-stream or multipart/form-data",
                if other.is_empty() { "(none)" } else { other }
            ),
            )
            .with_culprit("Content-Type");
            drain(request.into_body()).await;
            Err(error)
        }
    }
}

async fn receive_raw(body: Body, files: &FileStore, rules: UploadRules) -> Result<Received, ApiError> {
    let mut upload = Upload::start(files, rules)?;
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
        return Err(ApiError::new(Code::InvalidArchive, "the body is empty: expected a zip or tar bundle"));
    }
    upload.finish(None).await
}

fn multipart_error(e: axum::extract::multipart::MultipartError) -> ApiError {
    if e.status() == axum::http::StatusCode::PAYLOAD_TOO_LARGE {
        return ApiError::new(Code::BodyTooLarge, e.body_text());
    }
    ApiError::new(Code::InvalidMultipart, e.body_text())
}

async fn receive_multipart(request: Request, files: &FileStore, rules: UploadRules) -> Result<Received, ApiError> {
    let mut multipart = Multipart::from_request(request, &())
        .await
        .map_err(|e| ApiError::new(Code::InvalidMultipart, e.body_text()))?;
    let result = read_parts(&mut multipart, files, rules).await;
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

async fn read_parts(multipart: &mut Multipart, files: &FileStore, rules: UploadRules) -> Result<Received, ApiError> {
    let mut upload = Upload::start(files, rules)?;
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
        ));
    }
    upload.finish(options).await
}

/// Caps on uploads received at once, over all clients and per client address. Each upload holds a
/// writer thread of the blocking pool and a temporary file while it streams, so without a cap slow
/// clients could take every thread.
pub struct UploadGate {
    global: usize,
    per_client: usize,
    open: std::sync::Mutex<(usize, std::collections::HashMap<std::net::IpAddr, usize>)>,
}

/// An admitted upload; leaving frees its places.
pub struct UploadPass<'a> {
    gate: &'a UploadGate,
    client: std::net::IpAddr,
}

impl UploadGate {
    pub fn new(global: usize, per_client: usize) -> Self {
        Self { global, per_client, open: Default::default() }
    }

    pub fn enter(&self, client: std::net::IpAddr) -> Result<UploadPass<'_>, ApiError> {
        let mut open = self.open.lock().expect("gate lock");
        let (total, by_client) = &mut *open;
        let mine = by_client.get(&client).copied().unwrap_or(0);
        if mine >= self.per_client {
            return Err(ApiError::new(
                Code::TooManyUploads,
                format!(
                    "{mine} uploads from {client} are already being received (max_uploads_per_client); retry when one ends"
                ),
            ));
        }
        if *total >= self.global {
            return Err(ApiError::new(
                Code::ServerBusy,
                format!("{total} uploads are being received (max_concurrent_uploads); retry shortly"),
            ));
        }
        *total += 1;
        *by_client.entry(client).or_insert(0) += 1;
        Ok(UploadPass { gate: self, client })
    }
}

impl Drop for UploadPass<'_> {
    fn drop(&mut self) {
        let mut open = self.gate.open.lock().expect("gate lock");
        let (total, by_client) = &mut *open;
        *total -= 1;
        if let Some(n) = by_client.get_mut(&self.client) {
            *n -= 1;
            if *n == 0 {
                by_client.remove(&self.client);
            }
        }
    }
}

#[cfg(test)]
mod gate_tests {
    use super::*;

    #[test]
    fn the_gate_caps_each_client_and_all_of_them_and_frees_places_on_leaving() {
        let gate = UploadGate::new(3, 2);
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
}
