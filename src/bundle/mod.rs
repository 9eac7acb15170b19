//! Bundle v1 reader (docs/bundle.md): a directory, `.zip` or `.tar` holding manifest.json
//! and focal-stack frames. [`Bundle::open`] validates everything it can before any work starts
//! (manifest, optics, offsets, paths, every frame's header, size caps) and names the field or file in
//! every error; frames are then decoded one at a time with [`Bundle::read_frame`].

mod decode;
mod manifest;
mod source;
mod validate;

pub use crate::domain::frame::FrameEntry;
pub use decode::decode;
pub use manifest::{
    CustomThread, FORMAT_V1, KNOWN_FIELDS, Manifest, PartManifest, UnknownField, ViewManifest, unknown_fields,
};
pub use source::{Limits, Source, check_relative_path};
pub use validate::resolve_part;

use decode::probe;
use validate::{check_station, check_work, validate_views};

use crate::domain::frame::{Frame, FrameError, FrameFormat, FrameSource, Recording, Samples, View};
use crate::domain::optics::Optics;
use crate::domain::part::Part;
use crate::domain::thread::{ConnectionTable, Family, FormError, ProfileShape, ThreadForm};
use crate::problem::{Code, ErrorCode};
use image::ImageDecoder;
use std::collections::HashSet;
use std::io::Cursor;
use std::path::Path;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BundleError {
    #[error("manifest.json: format: unsupported format version {found:?}; this reader takes \"{FORMAT_V1}\"")]
    FormatVersion { found: String },
    #[error("manifest.json: {field}: {message}")]
    Manifest { field: String, message: String },
    #[error("manifest.json: optics.{field}: {message}")]
    Optics { field: String, message: String },
    #[error(
        "manifest.json: part.connection: unknown connection {designation:?}; see `crestscan connections` (tubing and premium threads need part.thread)"
    )]
    UnknownConnection { designation: String },
    #[error("manifest.json: part.thread.{field}: {message}")]
    Thread { field: String, message: String },
    #[error("manifest.json: {field}: {count} frame(s); a focal stack needs at least {MIN_FRAMES}")]
    TooFewFrames { field: String, count: usize },
    #[error("manifest.json: {field}: {message}")]
    Offsets { field: String, message: String },
    #[error("{path}: file not found in the bundle")]
    MissingFile { path: String },
    /// The archive holds the bundle deeper than the contract allows (`tar -cf x.tar out/ci`).
    #[error(
        "manifest.json: not at the archive's root nor in one top-level folder, but at {found}: make the archive \
         from inside the bundle's folder, e.g. `tar -C {folder} -cf bundle.tar .`"
    )]
    NestedBundle { found: String, folder: String },
    #[error("{path}: unreadable frame: {message}")]
    UnreadableFrame { path: String, message: String },
    #[error("{path}: {message}")]
    InconsistentFrames { path: String, message: String },
    #[error("{path}: unsafe path: {message}")]
    UnsafePath { path: String, message: String },
    /// Over one of the [`Limits`]; `culprit` is the bundle file at fault, where one is.
    #[error("bundle too large: {message}")]
    Limit { culprit: Option<String>, message: String },
    /// A well-formed bundle whose inspection would need more memory than the caps allow
    /// ([`Limits::max_stack_samples`] and the two after it); `field` is what makes it large.
    #[error("manifest.json: {field}: {message}")]
    InspectionTooLarge { field: String, message: String },
    /// A station the method cannot measure at (its pixel too coarse for the thread, its focal
    /// stack too sparse or too short); `field` is the manifest parameter that puts it there.
    #[error("manifest.json: {field}: {message}")]
    StationOutOfRange { field: String, message: String },
    #[error("{message}")]
    Archive { message: String },
    #[error("{path}: {message}")]
    Io { path: String, message: String },
}

impl ErrorCode for BundleError {
    fn code(&self) -> Code {
        match self {
            BundleError::FormatVersion { .. } => Code::UnsupportedFormatVersion,
            BundleError::Manifest { .. } => Code::InvalidManifest,
            BundleError::Optics { .. } => Code::InvalidOptics,
            BundleError::UnknownConnection { .. } => Code::UnknownConnection,
            BundleError::Thread { .. } => Code::InvalidThread,
            BundleError::TooFewFrames { .. } => Code::TooFewFrames,
            BundleError::Offsets { .. } => Code::InvalidOffsets,
            BundleError::MissingFile { .. } => Code::MissingFile,
            BundleError::UnreadableFrame { .. } => Code::UnreadableFrame,
            BundleError::InconsistentFrames { .. } => Code::InconsistentFrames,
            BundleError::UnsafePath { .. } => Code::UnsafePath,
            BundleError::Limit { .. } => Code::BundleTooLarge,
            BundleError::InspectionTooLarge { .. } => Code::InspectionTooLarge,
            BundleError::StationOutOfRange { .. } => Code::StationOutOfRange,
            BundleError::Archive { .. } => Code::InvalidArchive,
            BundleError::NestedBundle { .. } => Code::MissingFile,
            BundleError::Io { .. } => Code::IoError,
        }
    }

    /// The manifest field or the bundle file at fault.
    fn culprit(&self) -> Option<String> {
        match self {
            BundleError::FormatVersion { .. } => Some("manifest.json: format".to_string()),
            BundleError::Manifest { field, .. }
            | BundleError::TooFewFrames { field, .. }
            | BundleError::Offsets { field, .. }
            | BundleError::InspectionTooLarge { field, .. }
            | BundleError::StationOutOfRange { field, .. } => Some(format!("manifest.json: {field}")),
            BundleError::Optics { field, .. } => Some(format!("manifest.json: optics.{field}")),
            BundleError::Thread { field, .. } => Some(format!("manifest.json: part.thread.{field}")),
            BundleError::UnknownConnection { .. } => Some("manifest.json: part.connection".into()),
            BundleError::NestedBundle { .. } => Some("manifest.json".into()),
            BundleError::MissingFile { path }
            | BundleError::UnreadableFrame { path, .. }
            | BundleError::InconsistentFrames { path, .. }
            | BundleError::UnsafePath { path, .. } => Some(path.clone()),
            BundleError::Limit { culprit, .. } => culprit.clone(),
            // The archive as a whole: the bundle sent.
            BundleError::Archive { .. } => Some("bundle".into()),
            // The server's own file; not the client's business.
            BundleError::Io { .. } => None,
        }
    }
}

pub const MIN_FRAMES: usize = 3;

/// How thoroughly [`Bundle::open`] checks the frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum FrameCheck {
    /// Read every frame's header (size, bit depth, colour type). Corrupt pixel data after a good
    /// header is reported, by file name, when the frame is decoded.
    #[default]
    Headers,
    /// Decode every frame completely.
    Decode,
}

#[derive(Clone, Copy, Debug, Default)]
pub struct OpenOptions {
    pub limits: Limits,
    pub frame_check: FrameCheck,
    /// How errors name the archive (default: its path). The service says "the upload": its
    /// temporary file's path is the server's business.
    pub name: Option<&'static str>,
}

pub struct Bundle {
    pub manifest: Manifest,
    pub part: Part,
    pub optics: Optics,
    pub views: Vec<View>,
    /// Manifest fields this reader does not know and read past (the contract lets a newer writer
    /// add optional fields; a near miss of a known one is refused instead): their paths.
    pub unread_fields: Vec<String>,
    source: Source,
}

impl std::fmt::Debug for Bundle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bundle").field("source", &self.source.describe()).field("views", &self.views.len()).finish()
    }
}

impl Bundle {
    pub fn open(path: &Path, table: &ConnectionTable, options: OpenOptions) -> Result<Self, BundleError> {
        let source = Source::open(path, options.limits, options.name)?;
        source.check_dir_limits()?;
        let manifest_bytes = source.read_manifest()?;
        let (manifest, unread_fields) = parse_manifest_noting(&manifest_bytes)?;
        drop(manifest_bytes);
        check_counts(&manifest, options.limits)?;
        check_texts(&manifest)?;
        let part = resolve_part(&manifest.part, table)?;
        manifest.optics.validate().map_err(|(field, message)| BundleError::Optics { field: field.into(), message })?;
        let views = validate_views(&manifest, &source, options.frame_check)?;
        check_work(&part, &manifest.optics, &views, options.limits)?;
        check_station(&part, &manifest.optics, &views)?;
        let optics = manifest.optics.clone();
        Ok(Self { manifest, part, optics, views, unread_fields, source })
    }

    pub fn frame_count(&self) -> usize {
        self.views.iter().map(|v| v.frames.len()).sum()
    }

    /// Decodes one frame, checking it still matches its view's format.
    pub fn read_frame(&self, view: usize, frame: usize) -> Result<Frame, BundleError> {
        let v = &self.views[view];
        let entry = &v.frames[frame];
        let bytes = self.source.read(&entry.file)?;
        let decoded = decode(&entry.file, &bytes)?;
        if (decoded.width, decoded.height, decoded.channels) != (v.format.width, v.format.height, v.format.channels) {
            return Err(BundleError::InconsistentFrames {
                path: entry.file.clone(),
                message: "frame changed since the bundle was validated".into(),
            });
        }
        Ok(decoded)
    }

    /// Raw bytes of a bundle file (used to copy bundles and to hash uploads).
    pub fn read_file(&self, path: &str) -> Result<Vec<u8>, BundleError> {
        check_relative_path(path).map_err(|message| BundleError::UnsafePath { path: path.into(), message })?;
        self.source.read(path)
    }
}

impl Recording for Bundle {
    fn part(&self) -> &Part {
        &self.part
    }
    fn optics(&self) -> &Optics {
        &self.optics
    }
    fn views(&self) -> &[View] {
        &self.views
    }
}

impl FrameSource for Bundle {
    fn read_frame(&self, view: usize, frame: usize) -> Result<Frame, FrameError> {
        Bundle::read_frame(self, view, frame).map_err(|e| FrameError::of(&e))
    }
}

/// Refuses more views, or frames in a view, than the limits allow, before any frame is read.
fn check_counts(manifest: &Manifest, limits: Limits) -> Result<(), BundleError> {
    let culprit = |field: String, message: String| BundleError::Limit {
        culprit: Some(format!("manifest.json: {field}")),
        message: format!("manifest.json: {field}: {message}"),
    };
    if manifest.views.len() > limits.max_views {
        return Err(culprit(
            "views".into(),
            format!("{} views, more than max_views ({})", manifest.views.len(), limits.max_views),
        ));
    }
    if let Some((i, view)) =
        manifest.views.iter().enumerate().find(|(_, v)| v.frames.len() > limits.max_frames_per_view)
    {
        return Err(culprit(
            format!("views[{i}].frames"),
            format!("{} frames, more than max_frames_per_view ({})", view.frames.len(), limits.max_frames_per_view),
        ));
    }
    Ok(())
}

/// A message of at most 300 characters (a parser's, which may quote a long value whole).
fn shortened(message: &str) -> String {
    const MAX: usize = 300;
    match message.char_indices().nth(MAX) {
        Some((at, _)) => format!("{}…", &message[..at]),
        None => message.to_string(),
    }
}

/// Every free text of the manifest within its cap (domain::text), checked before any of it is
/// used, stored or quoted.
fn check_texts(manifest: &Manifest) -> Result<(), BundleError> {
    use crate::domain::text::{self, CONNECTION_CHARS, FRAME_PATH_CHARS, SERIAL_CHARS, VIEW_ID_CHARS};
    let fail = |field: String, e: text::TextError| BundleError::Manifest { field, message: e.to_string() };
    if let Some(serial) = &manifest.part.serial {
        text::check(serial, SERIAL_CHARS).map_err(|e| fail("part.serial".into(), e))?;
    }
    if let Some(connection) = &manifest.part.connection {
        text::check(connection, CONNECTION_CHARS).map_err(|e| fail("part.connection".into(), e))?;
    }
    if let Some(station) = &manifest.station {
        text::check_station_name(station)
            .map_err(|message| BundleError::Manifest { field: "station".into(), message })?;
    }
    for (i, view) in manifest.views.iter().enumerate() {
        text::check(&view.id, VIEW_ID_CHARS).map_err(|e| fail(format!("views[{i}].id"), e))?;
        for (j, frame) in view.frames.iter().enumerate() {
            text::check(&frame.file, FRAME_PATH_CHARS).map_err(|e| fail(format!("views[{i}].frames[{j}].file"), e))?;
        }
    }
    Ok(())
}

pub fn parse_manifest(bytes: &[u8]) -> Result<Manifest, BundleError> {
    parse_manifest_noting(bytes).map(|(manifest, _)| manifest)
}

/// The manifest, and the paths of the fields it has that this reader does not know. A field that
/// nearly spells a known one absent from its object (`part.serail`) is refused, naming the field
/// meant: a typo would otherwise drop the value silently.
pub fn parse_manifest_noting(bytes: &[u8]) -> Result<(Manifest, Vec<String>), BundleError> {
    let value: serde_json::Value = serde_json::from_slice(bytes).map_err(|e| BundleError::Manifest {
        field: format!("line {} column {}", e.line(), e.column()),
        message: format!("not valid JSON: {e}"),
    })?;
    let unknown = manifest::unknown_fields(&value);
    if let Some(typo) = unknown.iter().find(|u| u.did_you_mean.is_some()) {
        let meant = typo.did_you_mean.unwrap_or_default();
        let meant_path = match typo.path.rsplit_once('.') {
            Some((parent, _)) => format!("{parent}.{meant}"),
            None => meant.to_string(),
        };
        return Err(BundleError::Manifest {
            field: typo.path.clone(),
            message: format!("unknown field: did you mean `{meant_path}`?"),
        });
    }
    let unread = unknown.into_iter().map(|u| u.path).collect();
    parse_manifest_value(value).map(|manifest| (manifest, unread))
}

fn parse_manifest_value(value: serde_json::Value) -> Result<Manifest, BundleError> {
    // The version decides the shape, so it is checked before the typed parse.
    match value.get("format") {
        Some(serde_json::Value::String(s)) if s == FORMAT_V1 => {}
        Some(serde_json::Value::String(s)) => {
            return Err(BundleError::FormatVersion { found: crate::domain::text::preview(s) });
        }
        Some(other) => {
            return Err(BundleError::FormatVersion { found: crate::domain::text::preview(&other.to_string()) });
        }
        None => {
            return Err(BundleError::Manifest { field: "format".into(), message: "is missing".into() });
        }
    }
    serde_path_to_error::deserialize::<_, Manifest>(value).map_err(|e| {
        let path = e.path().to_string();
        // serde quotes the value it could not take (an unknown variant): a long one is cut.
        let message = shortened(&e.into_inner().to_string());
        if let Some(field) = path.strip_prefix("optics.") {
            BundleError::Optics { field: field.into(), message }
        } else {
            BundleError::Manifest { field: path, message }
        }
    })
}
