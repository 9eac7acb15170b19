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
}

impl FileStore {
    pub fn open(root: &Path, tmp: &Path) -> io::Result<Self> {
        std::fs::create_dir_all(root)?;
        std::fs::create_dir_all(tmp)?;
        Ok(Self { root: root.to_path_buf(), tmp: tmp.to_path_buf() })
    }

    /// A temporary file beside the store (deleted on drop unless committed).
    pub fn temp_file(&self) -> io::Result<tempfile::NamedTempFile> {
        tempfile::Builder::new().prefix("upload-").tempfile_in(&self.tmp)
    }

    /// A temporary directory beside the store.
    pub fn temp_dir(&self) -> io::Result<tempfile::TempDir> {
        tempfile::Builder::new().prefix("work-").tempdir_in(&self.tmp)
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

    /// Deletes leftovers of uploads interrupted by a crash: temporaries untouched for `age` (another
    /// process on the same data directory may be writing younger ones right now).
    pub fn clear_temporaries(&self, age: std::time::Duration) -> io::Result<usize> {
        let mut n = 0;
        for entry in std::fs::read_dir(&self.tmp)? {
            let entry = entry?;
            let modified = entry.metadata()?.modified()?;
            if modified.elapsed().map_or(true, |e| e < age) {
                continue;
            }
            let path = entry.path();
            let removed = if path.is_dir() { std::fs::remove_dir_all(&path) } else { std::fs::remove_file(&path) };
            n += removed.is_ok() as usize;
        }
        Ok(n)
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
}
