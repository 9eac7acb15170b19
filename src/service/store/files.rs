//! The upload file store: content-addressed by sha256 (`uploads/ab/abcdef…`). A file is written to
//! a temporary file in the same file system, fsynced, renamed into place and its directory fsynced
//! before the database row that refers to it commits, so a committed row never points at nothing.

use sha2::{Digest, Sha256};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug)]
pub struct FileStore {
    root: PathBuf,
    tmp: PathBuf,
    /// Free bytes below which the store takes no new upload ([`FileStore::has_room`]).
    free_floor_bytes: u64,
}

/// Whether an I/O error means the file system is full (or the quota spent).
pub fn is_storage_full(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::StorageFull
        || e.kind() == io::ErrorKind::QuotaExceeded
        || matches!(e.raw_os_error(), Some(libc::ENOSPC) | Some(libc::EDQUOT))
}

/// The prefix of this process's temporaries: the host and the process id, so that a start-up can
/// tell its own node's leftovers (whose writer is gone) from another live process's.
fn temp_prefix(kind: &str) -> String {
    format!("{kind}-{}-{}-", host_name(), std::process::id())
}

/// This host's name, read once (every upload's temporary is named with it).
fn host_name() -> &'static str {
    static NAME: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    NAME.get_or_init(|| {
        std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().replace(|c: char| !c.is_ascii_alphanumeric(), "_"))
            .unwrap_or_else(|_| "host".into())
    })
}

/// Whether a process with this id runs on this host.
fn process_alive(pid: u32) -> bool {
    #[cfg(unix)]
    {
        // SAFETY: signal 0 only checks that the process exists; nothing is delivered.
        let r = unsafe { libc::kill(pid as libc::pid_t, 0) };
        r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
    }
    #[cfg(not(unix))]
    {
        let _ = pid;
        true
    }
}

impl FileStore {
    pub fn open(root: &Path, tmp: &Path) -> io::Result<Self> {
        std::fs::create_dir_all(root)?;
        std::fs::create_dir_all(tmp)?;
        Ok(Self { root: root.to_path_buf(), tmp: tmp.to_path_buf(), free_floor_bytes: 0 })
    }

    /// The store with a free-space floor: below it, uploads are refused before they are written.
    pub fn with_free_floor(mut self, bytes: u64) -> Self {
        self.free_floor_bytes = bytes;
        self
    }

    pub fn free_floor_bytes(&self) -> u64 {
        self.free_floor_bytes
    }

    /// Bytes an unprivileged writer may still put on the store's file system.
    pub fn free_bytes(&self) -> io::Result<u64> {
        #[cfg(unix)]
        {
            use std::os::unix::ffi::OsStrExt;
            let path = std::ffi::CString::new(self.tmp.as_os_str().as_bytes()).map_err(io::Error::other)?;
            // SAFETY: statvfs writes into the zeroed struct it is given; the path is NUL-terminated.
            let mut stat: libc::statvfs = unsafe { std::mem::zeroed() };
            if unsafe { libc::statvfs(path.as_ptr(), &mut stat) } != 0 {
                return Err(io::Error::last_os_error());
            }
            Ok((stat.f_bavail as u64).saturating_mul(stat.f_frsize as u64))
        }
        #[cfg(not(unix))]
        {
            Ok(u64::MAX)
        }
    }

    /// Whether `incoming` more bytes leave the file system above the floor; the free bytes with it.
    pub fn has_room(&self, incoming: u64) -> io::Result<(bool, u64)> {
        let free = self.free_bytes()?;
        Ok((free >= self.free_floor_bytes.saturating_add(incoming), free))
    }

    /// A temporary file beside the store (deleted on drop unless committed).
    pub fn temp_file(&self) -> io::Result<tempfile::NamedTempFile> {
        tempfile::Builder::new().prefix(&temp_prefix("upload")).tempfile_in(&self.tmp)
    }

    /// A temporary directory beside the store.
    pub fn temp_dir(&self) -> io::Result<tempfile::TempDir> {
        tempfile::Builder::new().prefix(&temp_prefix("work")).tempdir_in(&self.tmp)
    }

    /// The directory the placed files live under.
    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn path_of(&self, sha256: &str) -> PathBuf {
        self.root.join(&sha256[..2]).join(sha256)
    }

    pub fn exists(&self, sha256: &str) -> bool {
        self.path_of(sha256).is_file()
    }

    /// Makes the temporary file's contents durable (fsync); slow for big uploads, so done before
    /// the database transaction that [`FileStore::place`]s it.
    pub fn prepare(&self, file: &tempfile::NamedTempFile) -> io::Result<()> {
        file.as_file().sync_all()
    }

    /// Renames a prepared temporary file under its hash and fsyncs the directory. Idempotent: an
    /// existing file of the same hash is kept and the temporary one discarded. Callers hold the
    /// database's write lock, which serialises this with the retention sweep's deletion.
    pub fn place(&self, file: tempfile::NamedTempFile, sha256: &str) -> io::Result<PathBuf> {
        let target = self.path_of(sha256);
        if target.is_file() {
            return Ok(target);
        }
        let dir = target.parent().expect("hash paths have a parent");
        std::fs::create_dir_all(dir)?;
        file.persist(&target).map_err(|e| e.error)?;
        std::fs::File::open(dir)?.sync_all()?;
        Ok(target)
    }

    pub fn remove(&self, sha256: &str) -> io::Result<()> {
        match std::fs::remove_file(self.path_of(sha256)) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// Deletes leftovers of uploads interrupted by a crash: this host's temporaries whose process is
    /// gone, at once, and any temporary untouched for `age` (another host sharing the data
    /// directory may be writing younger ones right now).
    pub fn clear_temporaries(&self, age: std::time::Duration) -> io::Result<usize> {
        let host = host_name();
        let mut n = 0;
        for entry in std::fs::read_dir(&self.tmp)? {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy().into_owned();
            // `{kind}-{host}-{pid}-{random}`; hosts' names have no '-' (replaced by '_').
            let mut parts = name.splitn(4, '-');
            let (_, entry_host, pid) = (parts.next(), parts.next(), parts.next().and_then(|p| p.parse::<u32>().ok()));
            let orphaned = entry_host == Some(host) && pid.is_some_and(|pid| !process_alive(pid));
            let stale = entry.metadata()?.modified()?.elapsed().is_ok_and(|e| e >= age);
            if !(orphaned || stale) {
                continue;
            }
            let path = entry.path();
            let removed = if path.is_dir() { std::fs::remove_dir_all(&path) } else { std::fs::remove_file(&path) };
            n += removed.is_ok() as usize;
        }
        Ok(n)
    }

    /// The hashes of the upload files stored (`ab/abcdef…`); names of any other shape are not ours
    /// and are left out.
    pub fn stored_hashes(&self) -> io::Result<Vec<String>> {
        let mut hashes = Vec::new();
        for dir in std::fs::read_dir(&self.root)? {
            let dir = dir?;
            let prefix = dir.file_name().to_string_lossy().into_owned();
            if prefix.len() != 2 || !dir.file_type()?.is_dir() {
                continue;
            }
            for file in std::fs::read_dir(dir.path())? {
                let name = file?.file_name().to_string_lossy().into_owned();
                if name.len() == 64 && name.starts_with(&prefix) && name.bytes().all(|b| b.is_ascii_hexdigit()) {
                    hashes.push(name);
                }
            }
        }
        hashes.sort();
        Ok(hashes)
    }

    /// Whether the data directory accepts writes (for `/readyz`).
    pub fn check_writable(&self) -> io::Result<()> {
        let mut f = self.temp_file()?;
        f.write_all(b"ok")?;
        f.flush()
    }
}

/// A writer that hashes (sha256) and counts what passes through it.
pub struct HashingWriter<W> {
    inner: W,
    hasher: Sha256,
    bytes: u64,
}

impl<W: Write> HashingWriter<W> {
    pub fn new(inner: W) -> Self {
        Self { inner, hasher: Sha256::new(), bytes: 0 }
    }

    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// The inner writer, the hex digest and the byte count.
    pub fn finish(self) -> (W, String, u64) {
        (self.inner, hex::encode(self.hasher.finalize()), self.bytes)
    }
}

impl<W: Write> Write for HashingWriter<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placing_is_content_addressed_and_idempotent() {
        let dir = tempfile::tempdir().unwrap();
        let store = FileStore::open(&dir.path().join("uploads"), &dir.path().join("tmp")).unwrap();
        let mut w = HashingWriter::new(store.temp_file().unwrap());
        w.write_all(b"focal stack").unwrap();
        let (file, sha, n) = w.finish();
        assert_eq!((sha.as_str(), n), (sha256_hex(b"focal stack").as_str(), 11));
        store.prepare(&file).unwrap();
        let path = store.place(file, &sha).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"focal stack");
        assert!(path.starts_with(dir.path().join("uploads").join(&sha[..2])));
        let again = store.temp_file().unwrap();
        store.prepare(&again).unwrap();
        assert_eq!(store.place(again, &sha).unwrap(), path);
        assert_eq!(std::fs::read_dir(dir.path().join("tmp")).unwrap().count(), 0, "temporaries are cleaned");
        store.remove(&sha).unwrap();
        assert!(!store.exists(&sha));
    }

    /// A real ENOSPC: /dev/full refuses every write with it.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_full_device_is_storage_full_and_other_errors_are_not() {
        let mut full = std::fs::OpenOptions::new().write(true).open("/dev/full").unwrap();
        let e = full.write_all(&[0u8; 4096]).and_then(|_| full.flush()).unwrap_err();
        assert!(is_storage_full(&e), "{e:?}");
        assert!(!is_storage_full(&io::Error::from(io::ErrorKind::PermissionDenied)));
    }

    #[test]
    fn the_floor_is_measured_against_the_free_space() {
        let dir = tempfile::tempdir().unwrap();
        let store = FileStore::open(&dir.path().join("u"), &dir.path().join("t")).unwrap();
        let free = store.free_bytes().unwrap();
        assert!(free > 0);
        assert!(store.has_room(0).unwrap().0);
        assert!(!store.clone().with_free_floor(u64::MAX).has_room(0).unwrap().0);
        assert!(!store.has_room(u64::MAX).unwrap().0, "an announced upload larger than the disk");
    }

    #[test]
    fn temporaries_of_a_dead_process_on_this_host_go_at_once_and_live_ones_stay() {
        let dir = tempfile::tempdir().unwrap();
        let store = FileStore::open(&dir.path().join("u"), &dir.path().join("t")).unwrap();
        let live = store.temp_file().unwrap();
        // Process ids are below 2^22 on Linux: this one runs nowhere.
        let dead = dir.path().join("t").join(format!("upload-{}-4194999-abc", host_name()));
        std::fs::write(&dead, b"partial").unwrap();
        let other_host = dir.path().join("t").join("upload-elsewhere-4194999-abc");
        std::fs::write(&other_host, b"partial").unwrap();
        assert_eq!(store.clear_temporaries(std::time::Duration::from_secs(3600)).unwrap(), 1);
        assert!(!dead.exists() && other_host.exists() && live.path().exists());
    }
}
