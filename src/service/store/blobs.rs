//! Where uploaded bundles' bytes live, content-addressed by sha256: the local directory (the
//! embedded default, [`LocalBlobs`]) or an S3-compatible object store ([`S3Blobs`],
//! `--object-store s3://bucket/prefix`). Uploads are staged in local temporary space either way
//! (hashed and checked while they arrive); [`BlobStore::put`] then makes the staged file the
//! blob before the database row that names it commits, so a committed row never points at
//! nothing. Workers read a blob through [`BlobStore::fetch`]: the file itself, or a download
//! into temporary space checked against its hash.

use super::files::FileStore;
use futures_util::future::BoxFuture;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The capability the service needs of a place for bundles' bytes.
pub trait BlobStore: Send + Sync {
    /// Makes the staged file (fsynced, its sha256 known) the blob `sha256`, durably. A blob that
    /// is already there is kept (the same content).
    fn put<'a>(&'a self, sha256: &'a str, staged: tempfile::NamedTempFile) -> BoxFuture<'a, io::Result<()>>;
    /// A local file holding the blob, for as long as the returned copy lives.
    fn fetch<'a>(&'a self, sha256: &'a str) -> BoxFuture<'a, io::Result<LocalCopy>>;
    /// Deletes the blob; one that is not there is no error.
    fn remove<'a>(&'a self, sha256: &'a str) -> BoxFuture<'a, io::Result<()>>;
    /// Every stored blob's sha256.
    fn list(&self) -> BoxFuture<'_, io::Result<Vec<String>>>;
    /// Whether a write would succeed now (readiness): a small probe written and deleted.
    fn check(&self) -> BoxFuture<'_, io::Result<()>>;
    /// Where the blobs are, for logs and readiness (`local /data/uploads`, `s3://bucket/prefix`).
    fn describe(&self) -> String;
}

/// Meshes and images held as objects (`artifacts/<inspection>/<kind>/<sha256>`), where an object
/// store is configured; the embedded default keeps them in the records instead, so that one
/// backup of the database holds them with their reports. The sha256 in the key is the body's:
/// a worker that lost its lease and uploads the same result again writes the same key, and
/// bytes that no record names are found by the orphan sweep.
pub trait ArtifactStore: Send + Sync {
    /// Stores `body`, durably, before the record that names it commits.
    fn put_artifact<'a>(&'a self, key: &'a ArtifactKey, body: Vec<u8>) -> BoxFuture<'a, io::Result<()>>;
    /// The body, checked against its sha256.
    fn get_artifact<'a>(&'a self, key: &'a ArtifactKey) -> BoxFuture<'a, io::Result<Vec<u8>>>;
    /// The stored size, bytes; None where it is not there.
    fn artifact_size<'a>(&'a self, key: &'a ArtifactKey) -> BoxFuture<'a, io::Result<Option<u64>>>;
    /// Deletes one; one that is not there is no error.
    fn remove_artifact<'a>(&'a self, key: &'a ArtifactKey) -> BoxFuture<'a, io::Result<()>>;
    /// Every stored artifact with the time it was written (ms since the epoch).
    fn list_artifacts(&self) -> BoxFuture<'_, io::Result<Vec<(ArtifactKey, i64)>>>;
    fn describe(&self) -> String;
}

/// Which artifact object: an inspection's result of one kind, by its bytes' sha256.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ArtifactKey {
    pub inspection_id: String,
    pub kind: String,
    pub sha256: String,
}

/// A blob as a local file: the stored file itself, or a download removed when this is dropped.
pub enum LocalCopy {
    InPlace(PathBuf),
    Downloaded(tempfile::TempPath),
}

impl LocalCopy {
    pub fn path(&self) -> &Path {
        match self {
            LocalCopy::InPlace(p) => p,
            LocalCopy::Downloaded(p) => p,
        }
    }
}

fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> io::Result<T> + Send + 'static,
) -> BoxFuture<'static, io::Result<T>> {
    Box::pin(async move { tokio::task::spawn_blocking(f).await.map_err(io::Error::other)? })
}

/// The data directory's `uploads/`: the embedded default.
#[derive(Clone, Debug)]
pub struct LocalBlobs {
    files: FileStore,
}

impl LocalBlobs {
    pub fn new(files: FileStore) -> Self {
        Self { files }
    }
}

impl BlobStore for LocalBlobs {
    fn put<'a>(&'a self, sha256: &'a str, staged: tempfile::NamedTempFile) -> BoxFuture<'a, io::Result<()>> {
        let (files, sha) = (self.files.clone(), sha256.to_string());
        blocking(move || files.place(staged, &sha).map(|_| ()))
    }

    fn fetch<'a>(&'a self, sha256: &'a str) -> BoxFuture<'a, io::Result<LocalCopy>> {
        let path = self.files.path_of(sha256);
        Box::pin(async move {
            match tokio::fs::metadata(&path).await {
                Ok(_) => Ok(LocalCopy::InPlace(path)),
                Err(e) => Err(io::Error::new(e.kind(), format!("{}: {e}", path.display()))),
            }
        })
    }

    fn remove<'a>(&'a self, sha256: &'a str) -> BoxFuture<'a, io::Result<()>> {
        let (files, sha) = (self.files.clone(), sha256.to_string());
        blocking(move || files.remove(&sha))
    }

    fn list(&self) -> BoxFuture<'_, io::Result<Vec<String>>> {
        let files = self.files.clone();
        blocking(move || files.stored_hashes())
    }

    fn check(&self) -> BoxFuture<'_, io::Result<()>> {
        let files = self.files.clone();
        blocking(move || files.check_writable())
    }

    fn describe(&self) -> String {
        format!("local {}", self.files.root().display())
    }
}

/// Where and how to reach an S3-compatible store: `s3://bucket/prefix`, with the endpoint, region
/// and credentials from the settings or the usual `AWS_*` environment.
#[derive(Clone, Debug, PartialEq)]
pub struct S3Location {
    pub bucket: String,
    /// Keys are `<prefix>/uploads/ab/abcdef…` (no leading or trailing slash; may be empty).
    pub prefix: String,
}

impl S3Location {
    /// Parses `s3://bucket[/prefix]`; the error says what is wrong.
    pub fn parse(url: &str) -> Result<Self, String> {
        let rest =
            url.strip_prefix("s3://").ok_or_else(|| format!("`{url}`: an object store is s3://bucket/prefix"))?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        // S3's own bucket naming rule, so that a typo is caught here, not at the first upload.
        let valid_bucket = (3..=63).contains(&bucket.len())
            && bucket.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.')
            && bucket.starts_with(|c: char| c.is_ascii_alphanumeric())
            && bucket.ends_with(|c: char| c.is_ascii_alphanumeric());
        if !valid_bucket {
            return Err(format!(
                "`{url}`: the bucket `{bucket}` is not an S3 bucket name (3–63 of a–z, 0–9, '-' and '.', \
                 starting and ending with a letter or digit)"
            ));
        }
        let prefix = prefix.trim_matches('/');
        if prefix.split('/').any(|p| p == "." || p == "..") {
            return Err(format!("`{url}`: the prefix may not hold `.` or `..`"));
        }
        Ok(Self { bucket: bucket.into(), prefix: prefix.into() })
    }
}

/// The settings an S3 store is opened with besides its location.
#[derive(Clone, Debug, Default)]
pub struct S3Settings {
    /// `http://127.0.0.1:9000` for MinIO, moto and the like (path-style requests); None: AWS.
    pub endpoint: Option<String>,
    pub region: Option<String>,
    /// An access key and its secret; None: the environment's (or the instance's role).
    pub credentials: Option<(String, String)>,
}

/// Blobs in an S3-compatible object store (the `object_store` crate's client).
pub struct S3Blobs {
    store: Arc<dyn object_store::ObjectStore>,
    location: S3Location,
    /// Downloads for the workers go here (the data directory's `tmp/`).
    tmp: PathBuf,
}

/// Parts of a multipart upload: S3 wants at least 5 MiB for every part but the last.
const PART_BYTES: usize = 8 << 20;

fn s3_error(e: object_store::Error) -> io::Error {
    match e {
        object_store::Error::NotFound { path, .. } => {
            io::Error::new(io::ErrorKind::NotFound, format!("object store: {path}: not found"))
        }
        e => io::Error::other(format!("object store: {e}")),
    }
}

impl S3Blobs {
    /// [`S3Blobs::open`] at `s3://bucket/prefix`; a malformed one is an `InvalidInput` error that
    /// says what is wrong.
    pub fn open_url(url: &str, settings: &S3Settings, tmp: &Path) -> io::Result<Self> {
        let location = S3Location::parse(url).map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        Self::open(location, settings, tmp)
    }

    /// Opens the store (no request is made: [`BlobStore::check`] is the first).
    pub fn open(location: S3Location, settings: &S3Settings, tmp: &Path) -> io::Result<Self> {
        use object_store::aws::AmazonS3Builder;
        let mut builder = AmazonS3Builder::from_env().with_bucket_name(&location.bucket);
        if let Some(region) = &settings.region {
            builder = builder.with_region(region);
        }
        if let Some((key, secret)) = &settings.credentials {
            builder = builder.with_access_key_id(key).with_secret_access_key(secret);
        }
        if let Some(endpoint) = &settings.endpoint {
            builder = builder
                .with_endpoint(endpoint)
                .with_allow_http(endpoint.starts_with("http://"))
                .with_virtual_hosted_style_request(false);
        }
        let store = builder.build().map_err(|e| io::Error::other(format!("object store: {e}")))?;
        std::fs::create_dir_all(tmp)?;
        Ok(Self { store: Arc::new(store), location, tmp: tmp.to_path_buf() })
    }

    /// `rest` under the location's prefix.
    fn under_prefix(&self, rest: &str) -> object_store::path::Path {
        if self.location.prefix.is_empty() {
            object_store::path::Path::from(rest)
        } else {
            object_store::path::Path::from(format!("{}/{rest}", self.location.prefix))
        }
    }

    fn key(&self, sha256: &str) -> object_store::path::Path {
        let shard = sha256.get(..2).unwrap_or("00");
        self.under_prefix(&format!("uploads/{shard}/{sha256}"))
    }

    /// Uploads the file at `path` as the blob `sha256` unless it is there already (true: it was
    /// uploaded). The file is left as it is: `migrate-store` copies a data directory's uploads so.
    pub async fn copy_in(&self, sha256: &str, path: &Path) -> io::Result<bool> {
        use object_store::{ObjectStore, PutPayload, WriteMultipart};
        use tokio::io::AsyncReadExt;
        let key = self.key(sha256);
        if self.size_at(&key).await?.is_some() {
            return Ok(false);
        }
        let mut file = tokio::fs::File::open(path).await?;
        let size = file.metadata().await?.len();
        // Read a part at a time: a bundle is never held whole in memory.
        let mut buffer = vec![0u8; PART_BYTES.min(size as usize + 1)];
        if size as usize <= PART_BYTES {
            let n = read_full(&mut file, &mut buffer).await?;
            buffer.truncate(n);
            self.store.put(&key, PutPayload::from(buffer)).await.map_err(s3_error)?;
            return Ok(true);
        }
        let upload = self.store.put_multipart(&key).await.map_err(s3_error)?;
        let mut writer = WriteMultipart::new_with_chunk_size(upload, PART_BYTES);
        loop {
            let n = file.read(&mut buffer).await?;
            if n == 0 {
                break;
            }
            writer.wait_for_capacity(2).await.map_err(s3_error)?;
            writer.write(&buffer[..n]);
        }
        writer.finish().await.map_err(s3_error)?;
        Ok(true)
    }

    /// The stored size of the blob `sha256`, bytes; None where it is not there.
    pub async fn size_of(&self, sha256: &str) -> io::Result<Option<u64>> {
        self.size_at(&self.key(sha256)).await
    }

    /// The size of the object at `path`, bytes; None where there is none.
    async fn size_at(&self, path: &object_store::path::Path) -> io::Result<Option<u64>> {
        use object_store::ObjectStore;
        match self.store.head(path).await {
            Ok(meta) => Ok(Some(meta.size as u64)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(s3_error(e)),
        }
    }

    /// Deletes the object at `path`; one that is not there is no error.
    async fn delete_at(&self, path: &object_store::path::Path) -> io::Result<()> {
        use object_store::ObjectStore;
        match self.store.delete(path).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(s3_error(e)),
        }
    }
}

impl BlobStore for S3Blobs {
    fn put<'a>(&'a self, sha256: &'a str, staged: tempfile::NamedTempFile) -> BoxFuture<'a, io::Result<()>> {
        Box::pin(async move { self.copy_in(sha256, staged.path()).await.map(|_| ()) })
    }

    fn fetch<'a>(&'a self, sha256: &'a str) -> BoxFuture<'a, io::Result<LocalCopy>> {
        Box::pin(async move {
            use futures_util::StreamExt;
            use object_store::ObjectStore;
            use sha2::{Digest, Sha256};
            use tokio::io::AsyncWriteExt;
            let key = self.key(sha256);
            let got = self.store.get(&key).await.map_err(s3_error)?;
            let temp = tempfile::Builder::new().prefix("fetch-").tempfile_in(&self.tmp)?;
            let (file, path) = temp.into_parts();
            let mut file = tokio::fs::File::from_std(file);
            let mut hasher = Sha256::new();
            let mut stream = got.into_stream();
            while let Some(chunk) = stream.next().await {
                let chunk = chunk.map_err(s3_error)?;
                hasher.update(&chunk);
                file.write_all(&chunk).await?;
            }
            file.flush().await?;
            let got_sha = hex::encode(hasher.finalize());
            if got_sha != sha256 {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("object store: {key} holds bytes of sha256 {got_sha}, not {sha256}"),
                ));
            }
            Ok(LocalCopy::Downloaded(path))
        })
    }

    fn remove<'a>(&'a self, sha256: &'a str) -> BoxFuture<'a, io::Result<()>> {
        Box::pin(async move { self.delete_at(&self.key(sha256)).await })
    }

    fn list(&self) -> BoxFuture<'_, io::Result<Vec<String>>> {
        Box::pin(async move {
            use futures_util::TryStreamExt;
            use object_store::ObjectStore;
            let prefix = self.under_prefix("uploads");
            let objects: Vec<object_store::ObjectMeta> =
                self.store.list(Some(&prefix)).try_collect().await.map_err(s3_error)?;
            Ok(objects
                .into_iter()
                .filter_map(|o| o.location.filename().map(String::from))
                .filter(|name| name.len() == 64 && name.bytes().all(|b| b.is_ascii_hexdigit()))
                .collect())
        })
    }

    fn check(&self) -> BoxFuture<'_, io::Result<()>> {
        Box::pin(async move {
            use object_store::{ObjectStore, PutPayload};
            let probe = self.under_prefix(&format!("probe/{}", std::process::id()));
            self.store.put(&probe, PutPayload::from_static(b"probe")).await.map_err(s3_error)?;
            self.delete_at(&probe).await
        })
    }

    fn describe(&self) -> String {
        if self.location.prefix.is_empty() {
            format!("s3://{}", self.location.bucket)
        } else {
            format!("s3://{}/{}", self.location.bucket, self.location.prefix)
        }
    }
}

impl S3Blobs {
    fn artifact_path(&self, key: &ArtifactKey) -> object_store::path::Path {
        self.under_prefix(&format!("artifacts/{}/{}/{}", key.inspection_id, key.kind, key.sha256))
    }
}

impl ArtifactStore for S3Blobs {
    fn put_artifact<'a>(&'a self, key: &'a ArtifactKey, body: Vec<u8>) -> BoxFuture<'a, io::Result<()>> {
        Box::pin(async move {
            use object_store::{ObjectStore, PutPayload};
            // Results are a few MB: one request (S3's single PUT takes up to 5 GB).
            self.store.put(&self.artifact_path(key), PutPayload::from(body)).await.map_err(s3_error)?;
            Ok(())
        })
    }

    fn get_artifact<'a>(&'a self, key: &'a ArtifactKey) -> BoxFuture<'a, io::Result<Vec<u8>>> {
        Box::pin(async move {
            use object_store::ObjectStore;
            use sha2::{Digest, Sha256};
            let path = self.artifact_path(key);
            let got = self.store.get(&path).await.map_err(s3_error)?;
            let body = got.bytes().await.map_err(s3_error)?;
            let got_sha = hex::encode(Sha256::digest(&body));
            if got_sha != key.sha256 {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!("object store: {path} holds bytes of sha256 {got_sha}, not {}", key.sha256),
                ));
            }
            Ok(body.to_vec())
        })
    }

    fn artifact_size<'a>(&'a self, key: &'a ArtifactKey) -> BoxFuture<'a, io::Result<Option<u64>>> {
        Box::pin(async move { self.size_at(&self.artifact_path(key)).await })
    }

    fn remove_artifact<'a>(&'a self, key: &'a ArtifactKey) -> BoxFuture<'a, io::Result<()>> {
        Box::pin(async move { self.delete_at(&self.artifact_path(key)).await })
    }

    fn list_artifacts(&self) -> BoxFuture<'_, io::Result<Vec<(ArtifactKey, i64)>>> {
        Box::pin(async move {
            use futures_util::TryStreamExt;
            use object_store::ObjectStore;
            let prefix = self.under_prefix("artifacts");
            let objects: Vec<object_store::ObjectMeta> =
                self.store.list(Some(&prefix)).try_collect().await.map_err(s3_error)?;
            Ok(objects
                .into_iter()
                .filter_map(|o| {
                    let parts: Vec<_> = o.location.prefix_match(&prefix)?.map(|p| p.as_ref().to_string()).collect();
                    let [id, kind, sha] = <[String; 3]>::try_from(parts).ok()?;
                    Some((ArtifactKey { inspection_id: id, kind, sha256: sha }, o.last_modified.timestamp_millis()))
                })
                .collect())
        })
    }

    fn describe(&self) -> String {
        BlobStore::describe(self)
    }
}

/// Reads until `buffer` is full or the file ends; the bytes read.
async fn read_full(file: &mut tokio::fs::File, buffer: &mut [u8]) -> io::Result<usize> {
    use tokio::io::AsyncReadExt;
    let mut n = 0;
    while n < buffer.len() {
        let got = file.read(&mut buffer[n..]).await?;
        if got == 0 {
            break;
        }
        n += got;
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_object_store_url_is_a_bucket_and_a_prefix() {
        assert_eq!(
            S3Location::parse("s3://plant-a/crestscan/").unwrap(),
            S3Location { bucket: "plant-a".into(), prefix: "crestscan".into() }
        );
        assert_eq!(S3Location::parse("s3://plant-a").unwrap().prefix, "");
        assert!(S3Location::parse("https://plant-a").unwrap_err().contains("s3://bucket/prefix"));
        assert!(S3Location::parse("s3://Plant_A/x").unwrap_err().contains("not an S3 bucket name"));
        assert!(S3Location::parse("s3://plant-a/../x").unwrap_err().contains("`..`"));
    }

    #[tokio::test]
    async fn local_blobs_put_fetch_list_and_remove() {
        let dir = tempfile::tempdir().unwrap();
        let files = FileStore::open(&dir.path().join("uploads"), &dir.path().join("tmp")).unwrap();
        let blobs = LocalBlobs::new(files.clone());
        let bytes = b"a bundle's bytes";
        let sha = super::super::files::sha256_hex(bytes);
        let mut staged = files.temp_file().unwrap();
        std::io::Write::write_all(&mut staged, bytes).unwrap();
        files.prepare(&staged).unwrap();
        blobs.put(&sha, staged).await.unwrap();
        assert_eq!(std::fs::read(blobs.fetch(&sha).await.unwrap().path()).unwrap(), bytes);
        assert_eq!(blobs.list().await.unwrap(), vec![sha.clone()]);
        blobs.check().await.unwrap();
        blobs.remove(&sha).await.unwrap();
        assert!(blobs.list().await.unwrap().is_empty());
        assert_eq!(blobs.fetch(&sha).await.err().unwrap().kind(), io::ErrorKind::NotFound);
        blobs.remove(&sha).await.unwrap();
    }
}
