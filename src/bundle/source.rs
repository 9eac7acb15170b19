//! Where a bundle's files come from: a directory, a `.zip` or a `.tar`. Archives are indexed once
//! (names, sizes, types) and read lazily, so frames can be streamed; every read is capped.

use super::BundleError;
use std::collections::HashMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Component, Path, PathBuf};
use std::sync::Mutex;

/// Caps that keep a hostile or broken upload from exhausting memory or disk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Total uncompressed bytes of all files in the bundle.
    pub max_total_bytes: u64,
    /// Files (archive entries) in the bundle.
    pub max_files: usize,
    /// Bytes of one file.
    pub max_file_bytes: u64,
    /// Bytes of manifest.json: parsing holds it as a JSON tree, about ten times its size.
    pub max_manifest_bytes: u64,
    /// Views in the manifest.
    pub max_views: usize,
    /// Frames of one view.
    pub max_frames_per_view: usize,
    /// Uncompressed over compressed size of a zip entry of over 1 MiB. Frames are PNG (already
    /// deflated) or TIFF, which a zip shrinks a few times at most; a far larger ratio is a bomb that
    /// would cost the server its inflation before any other check could refuse it.
    pub max_compression_ratio: u64,
    /// Samples of one view's focal stack (frames × pixels per frame): depth from focus holds the
    /// stack's focus measure, 4 bytes a sample, and its decoded frames, 1 to 12 bytes a sample by
    /// channels and bit depth (3 for 8-bit RGB), for each view in flight.
    pub max_stack_samples: u64,
    /// Pixels of one frame of each view, summed over the views: the inspection keeps a depth map,
    /// a confidence and a colour per pixel of every view (20 bytes a pixel) until fusion.
    pub max_view_pixels: u64,
    /// Object pixels on the surface the views cover (the pipe's circumference by the z band they
    /// span, at the optics' object pixel): registration's and fusion's grids scale with it.
    pub max_surface_pixels: u64,
}

impl Default for Limits {
    fn default() -> Self {
        // The standard preset (45 views of 20 frames of 864×320) uses 5.5 M stack samples,
        // 12.4 M view pixels and 7.6 M surface pixels, and peaks at about 0.55 GB: these caps are
        // 20–50 times that, a bound against broken or hostile manifests, not a tuned capacity.
        Self {
            max_total_bytes: 16 << 30,
            max_files: 200_000,
            max_file_bytes: 512 << 20,
            // The standard preset's manifest is 60 KB (45 views of 20 frames).
            max_manifest_bytes: 16 << 20,
            max_views: 1000,
            max_frames_per_view: 500,
            max_compression_ratio: 100,
            max_stack_samples: 1 << 28,
            max_view_pixels: 1 << 28,
            max_surface_pixels: 1 << 28,
        }
    }
}

/// Checks a manifest path: relative, `/`-separated, no `..`, `.` or empty parts, no backslash.
pub fn check_relative_path(path: &str) -> Result<(), String> {
    if path.is_empty() {
        return Err("is empty".into());
    }
    if path.starts_with('/') || path.contains('\\') || path.contains(':') {
        return Err(format!("'{path}' is not a relative '/'-separated path inside the bundle"));
    }
    for part in path.split('/') {
        match part {
            "" | "." => return Err(format!("'{path}' has an empty or '.' component")),
            ".." => return Err(format!("'{path}' escapes the bundle ('..')")),
            _ => {}
        }
    }
    Ok(())
}

enum Kind {
    Dir(PathBuf),
    Zip { archive: Mutex<zip::ZipArchive<File>>, index: HashMap<String, (usize, u64)> },
    Tar { file: Mutex<File>, index: HashMap<String, TarEntry> },
}

#[derive(Clone, Copy)]
struct TarEntry {
    data_offset: u64,
    size: u64,
    regular: bool,
}

/// Zip entries smaller than this are not held to [`Limits::max_compression_ratio`]: inflating
/// them costs nothing, and a small manifest of repetitive JSON may shrink far more than a frame.
const RATIO_CHECKED_BYTES: u64 = 1 << 20;

/// Whether an archive's first bytes are a tar's: the ustar magic of its first header.
fn is_tar(head: &[u8]) -> bool {
    head.get(257..262) == Some(b"ustar".as_slice())
}

/// An opened bundle container. Paths given to it are bundle-relative (already checked).
pub struct Source {
    kind: Kind,
    /// Folder inside an archive that holds the bundle ("" at the root, else "name/").
    prefix: String,
    limits: Limits,
    display: String,
}

fn io_err(path: &str, e: impl std::fmt::Display) -> BundleError {
    BundleError::Io { path: path.to_string(), message: e.to_string() }
}

impl Source {
    /// Opens a directory, or an archive recognised by its magic bytes (zip) or ustar header (tar).
    pub fn open(path: &Path, limits: Limits, name: Option<&str>) -> Result<Self, BundleError> {
        let display = name.map_or_else(|| path.display().to_string(), str::to_string);
        let meta = std::fs::metadata(path).map_err(|e| io_err(&display, e))?;
        if meta.is_dir() {
            return Ok(Self { kind: Kind::Dir(path.to_path_buf()), prefix: String::new(), limits, display });
        }
        let mut file = File::open(path).map_err(|e| io_err(&display, e))?;
        let mut head = [0u8; 512];
        let n = read_up_to(&mut file, &mut head).map_err(|e| io_err(&display, e))?;
        file.seek(SeekFrom::Start(0)).map_err(|e| io_err(&display, e))?;
        if n >= 4 && (&head[..4] == b"PK\x03\x04" || &head[..4] == b"PK\x05\x06") {
            Self::open_zip(file, limits, display)
        } else if is_tar(&head[..n]) {
            Self::open_tar(file, limits, display)
        } else if n >= 2 && head[..2] == [0x1f, 0x8b] {
            Self::open_tar_gz(file, path, limits, display)
        } else {
            Err(BundleError::Archive {
                message: format!("{display}: neither a zip, a tar nor a gzipped tar (.tar.gz) archive"),
            })
        }
    }

    /// A gzipped tar: inflated into an unnamed temporary file beside it, held to the caps on the
    /// bundle's bytes and on the compression ratio that apply to a zip, then read as a tar.
    fn open_tar_gz(file: File, path: &Path, limits: Limits, display: String) -> Result<Self, BundleError> {
        let compressed = file.metadata().map_err(|e| io_err(&display, e))?.len();
        let beside = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let mut out =
            tempfile::tempfile_in(beside).or_else(|_| tempfile::tempfile()).map_err(|e| io_err(&display, e))?;
        // A tar adds a 512-byte header and up to 511 bytes of padding to each file.
        let cap = limits.max_total_bytes.saturating_add((limits.max_files as u64 + 2).saturating_mul(1024));
        let mut inflating = flate2::read::MultiGzDecoder::new(std::io::BufReader::new(file)).take(cap + 1);
        let inflated = std::io::copy(&mut inflating, &mut out).map_err(|e| match e.kind() {
            std::io::ErrorKind::InvalidData | std::io::ErrorKind::InvalidInput | std::io::ErrorKind::UnexpectedEof => {
                BundleError::Archive { message: format!("{display}: not a readable gzip: {e}") }
            }
            _ => io_err(&display, e),
        })?;
        if inflated > cap {
            return Err(too_many_bytes(inflated, limits));
        }
        if inflated > RATIO_CHECKED_BYTES && inflated > limits.max_compression_ratio.saturating_mul(compressed) {
            return Err(BundleError::Limit {
                culprit: None,
                message: format!(
                    "{display}: inflates from {compressed} to more than {inflated} bytes, more than \
                     max_compression_ratio ({}:1) allows",
                    limits.max_compression_ratio
                ),
            });
        }
        out.seek(SeekFrom::Start(0)).map_err(|e| io_err(&display, e))?;
        let mut head = [0u8; 512];
        let n = read_up_to(&mut out, &mut head).map_err(|e| io_err(&display, e))?;
        out.seek(SeekFrom::Start(0)).map_err(|e| io_err(&display, e))?;
        if !is_tar(&head[..n]) {
            return Err(BundleError::Archive { message: format!("{display}: a gzip that holds no tar archive") });
        }
        Self::open_tar(out, limits, display)
    }

    fn open_zip(file: File, limits: Limits, display: String) -> Result<Self, BundleError> {
        let mut archive = zip::ZipArchive::new(file)
            .map_err(|e| BundleError::Archive { message: format!("{display}: not a readable zip: {e}") })?;
        if archive.len() > limits.max_files {
            return Err(too_many_files(archive.len(), limits));
        }
        let mut index = HashMap::new();
        let mut total = 0u64;
        for i in 0..archive.len() {
            let entry = archive
                .by_index_raw(i)
                .map_err(|e| BundleError::Archive { message: format!("{display}: entry {i}: {e}") })?;
            let name = entry
                .name()
                .map_err(|e| BundleError::Archive { message: format!("{display}: entry {i}: {e}") })?
                .to_string();
            if entry.is_symlink() {
                return Err(BundleError::UnsafePath { path: name, message: "is a symbolic link".into() });
            }
            if entry.is_dir() {
                continue;
            }
            total = total.saturating_add(entry.size());
            if entry.size() > limits.max_file_bytes {
                return Err(file_too_large(&name, entry.size(), limits));
            }
            if entry.size() > RATIO_CHECKED_BYTES
                && entry.size() > limits.max_compression_ratio.saturating_mul(entry.compressed_size())
            {
                return Err(BundleError::Limit {
                    culprit: Some(name.trim_start_matches("./").to_string()),
                    message: format!(
                        "{name}: inflates from {} to {} bytes, more than max_compression_ratio ({}:1) allows",
                        entry.compressed_size(),
                        entry.size(),
                        limits.max_compression_ratio
                    ),
                });
            }
            if total > limits.max_total_bytes {
                return Err(too_many_bytes(total, limits));
            }
            index.insert(name, (i, entry.size()));
        }
        let prefix = bundle_prefix(index.keys().map(String::as_str))?;
        Ok(Self { kind: Kind::Zip { archive: Mutex::new(archive), index }, prefix, limits, display })
    }

    fn open_tar(file: File, limits: Limits, display: String) -> Result<Self, BundleError> {
        let file_len = file.metadata().map_err(|e| io_err(&display, e))?.len();
        let mut archive = tar::Archive::new(file);
        let mut index = HashMap::new();
        let mut total = 0u64;
        let entries = archive
            .entries()
            .map_err(|e| BundleError::Archive { message: format!("{display}: not a readable tar: {e}") })?;
        // An archive that ends inside an entry's data fails when the next entry is sought: that
        // entry (name, end of its data) is the damaged one.
        let mut previous: Option<(String, u64)> = None;
        for (i, entry) in entries.enumerate() {
            let entry = entry.map_err(|e| match &previous {
                Some((name, end)) if *end > file_len => {
                    damaged_entry(name, format!("the archive {display} ends inside this entry"))
                }
                _ => BundleError::Archive { message: format!("{display}: entry {i}: {e}") },
            })?;
            if index.len() >= limits.max_files {
                return Err(too_many_files(index.len() + 1, limits));
            }
            let name = entry
                .path()
                .map_err(|e| BundleError::Archive { message: format!("{display}: entry {i}: {e}") })?
                .to_string_lossy()
                .into_owned();
            let kind = entry.header().entry_type();
            if kind.is_symlink() || kind.is_hard_link() {
                return Err(BundleError::UnsafePath { path: name, message: "is a link".into() });
            }
            if kind.is_dir() || kind.is_pax_global_extensions() {
                continue;
            }
            let size = entry.size();
            if size > limits.max_file_bytes {
                return Err(file_too_large(&name, size, limits));
            }
            total = total.saturating_add(size);
            if total > limits.max_total_bytes {
                return Err(too_many_bytes(total, limits));
            }
            let name = name.trim_start_matches("./").to_string();
            previous = Some((name.clone(), entry.raw_file_position().saturating_add(size)));
            index.insert(name, TarEntry { data_offset: entry.raw_file_position(), size, regular: kind.is_file() });
        }
        let prefix = bundle_prefix(index.keys().map(String::as_str))?;
        let file = archive.into_inner();
        Ok(Self { kind: Kind::Tar { file: Mutex::new(file), index }, prefix, limits, display })
    }

    pub fn describe(&self) -> &str {
        &self.display
    }

    /// Reads a whole bundle file (path relative to the bundle root, already checked).
    pub fn read(&self, path: &str) -> Result<Vec<u8>, BundleError> {
        self.read_capped_at(path, self.limits.max_file_bytes, "the per-file cap")
    }

    /// Reads manifest.json, held to [`Limits::max_manifest_bytes`].
    pub fn read_manifest(&self) -> Result<Vec<u8>, BundleError> {
        let max = self.limits.max_manifest_bytes.min(self.limits.max_file_bytes);
        self.read_capped_at("manifest.json", max, "max_manifest_kib")
    }

    /// The first `len` bytes of a file (fewer if it is shorter): enough for a PNG's header
    /// without holding its pixels. A zip entry is still inflated to its end (into nothing), so that
    /// its CRC is checked.
    pub fn read_head(&self, path: &str, len: usize) -> Result<Vec<u8>, BundleError> {
        let full = format!("{}{}", self.prefix, path);
        let mut head = Vec::with_capacity(len);
        match &self.kind {
            Kind::Dir(root) => {
                let file_path = self.dir_path(root, path)?;
                let file = File::open(&file_path).map_err(|e| missing_or_io(path, e))?;
                file.take(len as u64).read_to_end(&mut head).map_err(|e| io_err(path, e))?;
            }
            Kind::Zip { archive, index } => {
                let &(i, _) = index.get(&full).ok_or_else(|| BundleError::MissingFile { path: path.into() })?;
                let mut archive = archive.lock().unwrap_or_else(|p| p.into_inner());
                let mut entry = archive.by_index(i).map_err(|e| damaged_entry(path, e))?;
                (&mut entry).take(len as u64).read_to_end(&mut head).map_err(|e| damaged_entry(path, e))?;
                // The rest is inflated into nothing, so the entry's CRC is checked at upload
                // (a damaged archive is refused before the 202) without holding the pixels;
                // max_compression_ratio bounds what that costs.
                std::io::copy(&mut (&mut entry).take(self.limits.max_file_bytes), &mut std::io::sink())
                    .map_err(|e| damaged_entry(path, e))?;
            }
            Kind::Tar { file, index } => {
                let entry = index.get(&full).ok_or_else(|| BundleError::MissingFile { path: path.into() })?;
                if !entry.regular {
                    return Err(BundleError::UnsafePath { path: path.into(), message: "is not a regular file".into() });
                }
                let mut file = file.lock().unwrap_or_else(|p| p.into_inner());
                file.seek(SeekFrom::Start(entry.data_offset)).map_err(|e| io_err(path, e))?;
                (&mut *file).take(entry.size.min(len as u64)).read_to_end(&mut head).map_err(|e| io_err(path, e))?;
            }
        }
        Ok(head)
    }

    fn read_capped_at(&self, path: &str, max: u64, limit: &'static str) -> Result<Vec<u8>, BundleError> {
        let full = format!("{}{}", self.prefix, path);
        match &self.kind {
            Kind::Dir(root) => {
                let file_path = self.dir_path(root, path)?;
                let mut file = File::open(&file_path).map_err(|e| missing_or_io(path, e))?;
                read_capped(&mut file, max, limit, path, io_err)
            }
            Kind::Zip { archive, index } => {
                let &(i, _) = index.get(&full).ok_or_else(|| BundleError::MissingFile { path: path.into() })?;
                let mut archive = archive.lock().unwrap_or_else(|p| p.into_inner());
                // A damaged entry (bad CRC, broken deflate stream) is the client's archive, not our I/O.
                let mut entry = archive.by_index(i).map_err(|e| damaged_entry(path, e))?;
                read_capped(&mut entry, max, limit, path, damaged_entry)
            }
            Kind::Tar { file, index } => {
                let entry = index.get(&full).ok_or_else(|| BundleError::MissingFile { path: path.into() })?;
                if !entry.regular {
                    return Err(BundleError::UnsafePath { path: path.into(), message: "is not a regular file".into() });
                }
                if entry.size > max {
                    return Err(over_cap(path, max, limit));
                }
                let mut file = file.lock().unwrap_or_else(|p| p.into_inner());
                file.seek(SeekFrom::Start(entry.data_offset)).map_err(|e| io_err(path, e))?;
                let mut bytes = vec![0u8; entry.size as usize];
                file.read_exact(&mut bytes).map_err(|e| match e.kind() {
                    std::io::ErrorKind::UnexpectedEof => damaged_entry(path, "the archive ends inside this entry"),
                    _ => io_err(path, e),
                })?;
                Ok(bytes)
            }
        }
    }

    /// Whether a bundle file exists (without reading it).
    pub fn exists(&self, path: &str) -> bool {
        let full = format!("{}{}", self.prefix, path);
        match &self.kind {
            Kind::Dir(root) => self.dir_path(root, path).map(|p| p.is_file()).unwrap_or(false),
            Kind::Zip { index, .. } => index.contains_key(&full),
            Kind::Tar { index, .. } => index.contains_key(&full),
        }
    }

    /// Resolves a path inside a directory bundle, refusing symbolic links at any level so that
    /// nothing outside the bundle can be reached.
    fn dir_path(&self, root: &Path, path: &str) -> Result<PathBuf, BundleError> {
        let mut current = root.to_path_buf();
        for component in Path::new(path).components() {
            let Component::Normal(part) = component else {
                return Err(BundleError::UnsafePath {
                    path: path.into(),
                    message: "is not a plain relative path".into(),
                });
            };
            current.push(part);
            match std::fs::symlink_metadata(&current) {
                Ok(meta) if meta.file_type().is_symlink() => {
                    return Err(BundleError::UnsafePath {
                        path: path.into(),
                        message: "is or passes through a symbolic link".into(),
                    });
                }
                Ok(_) => {}
                Err(e) => return Err(missing_or_io(path, e)),
            }
        }
        Ok(current)
    }

    /// Files in a directory bundle are counted and sized up front, like an archive's entries.
    pub fn check_dir_limits(&self) -> Result<(), BundleError> {
        let Kind::Dir(root) = &self.kind else { return Ok(()) };
        let (mut files, mut total) = (0usize, 0u64);
        let mut stack = vec![root.clone()];
        while let Some(dir) = stack.pop() {
            let entries = std::fs::read_dir(&dir).map_err(|e| io_err(&dir.display().to_string(), e))?;
            for entry in entries {
                let entry = entry.map_err(|e| io_err(&dir.display().to_string(), e))?;
                let meta = entry.metadata().map_err(|e| io_err(&entry.path().display().to_string(), e))?;
                if meta.is_dir() {
                    stack.push(entry.path());
                } else {
                    files += 1;
                    total = total.saturating_add(meta.len());
                    if files > self.limits.max_files {
                        return Err(too_many_files(files, self.limits));
                    }
                    if total > self.limits.max_total_bytes {
                        return Err(too_many_bytes(total, self.limits));
                    }
                }
            }
        }
        Ok(())
    }
}

fn missing_or_io(path: &str, e: std::io::Error) -> BundleError {
    if e.kind() == std::io::ErrorKind::NotFound {
        BundleError::MissingFile { path: path.into() }
    } else {
        io_err(path, e)
    }
}

fn read_up_to(file: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match file.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// Reads at most `max` bytes; more means the declared size lied (a bomb) or the cap is too small.
fn read_capped(
    reader: &mut impl Read,
    max: u64,
    limit: &'static str,
    path: &str,
    on_error: fn(&str, std::io::Error) -> BundleError,
) -> Result<Vec<u8>, BundleError> {
    let mut bytes = Vec::new();
    reader.take(max + 1).read_to_end(&mut bytes).map_err(|e| on_error(path, e))?;
    if bytes.len() as u64 > max {
        return Err(over_cap(path, max, limit));
    }
    Ok(bytes)
}

fn over_cap(path: &str, max: u64, limit: &'static str) -> BundleError {
    BundleError::Limit {
        culprit: Some(path.to_string()),
        message: format!("{path}: larger than {max} bytes ({limit})"),
    }
}

fn damaged_entry(path: &str, e: impl std::fmt::Display) -> BundleError {
    BundleError::Archive { message: format!("{path}: damaged archive entry: {e}") }
}

fn too_many_files(n: usize, limits: Limits) -> BundleError {
    BundleError::Limit {
        culprit: None,
        message: format!("the archive holds more than {} files ({n} seen)", limits.max_files),
    }
}

fn too_many_bytes(total: u64, limits: Limits) -> BundleError {
    BundleError::Limit {
        culprit: None,
        message: format!(
            "the uncompressed size exceeds {} bytes, the cap max_decompressed_mb sets ({total} seen)",
            limits.max_total_bytes
        ),
    }
}

fn file_too_large(name: &str, size: u64, limits: Limits) -> BundleError {
    BundleError::Limit {
        culprit: Some(name.trim_start_matches("./").to_string()),
        message: format!(
            "{name}: uncompressed size {size} exceeds the per-file cap of {} bytes",
            limits.max_file_bytes
        ),
    }
}

/// The bundle sits at the archive root, or inside exactly one top-level folder.
fn bundle_prefix<'a>(names: impl Iterator<Item = &'a str>) -> Result<String, BundleError> {
    let names: Vec<&str> = names.map(|n| n.trim_start_matches("./")).collect();
    if names.contains(&"manifest.json") {
        return Ok(String::new());
    }
    let mut tops = names.iter().filter_map(|n| n.split_once('/').map(|(top, _)| top));
    if let Some(first) = tops.next()
        && names.iter().all(|n| n.split_once('/').map(|(t, _)| t) == Some(first))
        && names.iter().any(|n| *n == format!("{first}/manifest.json"))
    {
        return Ok(format!("{first}/"));
    }
    // Deeper (an archive made from outside the bundle's folder): the folder to make it from.
    if let Some(found) = names.iter().filter(|n| n.ends_with("/manifest.json")).min_by_key(|n| n.len()) {
        let folder = found.trim_end_matches("manifest.json").trim_end_matches('/').to_string();
        return Err(BundleError::NestedBundle { found: found.to_string(), folder });
    }
    Err(BundleError::MissingFile { path: "manifest.json".into() })
}
