//! `crestscan migrate-store`: a single-node data directory's uploaded bundles copied into an
//! S3-compatible object store, resumable (what is there already is skipped) and verified (every
//! live upload present with its size, and with `--verify-hashes` its bytes' sha256), so that the
//! service can then run with `--object-store` on the same data directory and keep its history.
//! The records stay in the data directory's SQLite file (PostgreSQL is not built yet).

use anyhow::{Context, Result, bail};
use clap::Args;
use crestscan::service::config::Settings;
use crestscan::service::store::blobs::{BlobStore, S3Blobs};
use std::path::PathBuf;

#[derive(Args)]
pub struct MigrateStoreArgs {
    /// The service's data directory (its crestscan.db and uploads/).
    #[arg(long)]
    from: PathBuf,
    /// The object store, s3://bucket/prefix (what `serve --object-store` will be given).
    #[arg(long, env = "CRESTSCAN_OBJECT_STORE")]
    object_store: String,
    #[command(flatten)]
    s3: super::object_store::S3Args,
    /// Also download every copied object and check its sha256 (reads the whole store back).
    #[arg(long)]
    verify_hashes: bool,
}

impl MigrateStoreArgs {
    pub fn run(self) -> Result<()> {
        tokio::runtime::Builder::new_multi_thread().enable_all().build()?.block_on(self.migrate())
    }

    async fn migrate(self) -> Result<()> {
        // The data directory and the store read as `serve` would read them, checked the same way.
        let mut settings = Settings {
            data_dir: self.from.clone(),
            object_store: Some(self.object_store.clone()),
            ..Settings::default()
        };
        self.s3.apply(&mut settings);
        settings.validate()?;
        let database = settings.database_path();
        if !database.is_file() {
            bail!("{}: no crestscan.db here; --from is a service's data directory", self.from.display());
        }
        let store = crestscan::service::store::Store::open(&database, &settings.uploads_dir(), &settings.tmp_dir())
            .await
            .with_context(|| format!("opening {}", database.display()))?;
        let blobs = S3Blobs::open_url(&self.object_store, &settings.s3(), &settings.tmp_dir())?;
        blobs.check().await.with_context(|| format!("the object store {} does not take a write", blobs.describe()))?;
        let live: Vec<(String, i64)> =
            sqlx::query_as("SELECT sha256, size_bytes FROM uploads WHERE purged_at IS NULL ORDER BY sha256")
                .fetch_all(&store.pool)
                .await?;
        let (mut copied, mut present) = (0usize, 0usize);
        for (sha, _) in &live {
            let path = store.files.path_of(sha);
            if !path.is_file() {
                // Already moved and the local copy deleted, or lost: the check below says which.
                continue;
            }
            if blobs.copy_in(sha, &path).await.with_context(|| format!("copying {}", path.display()))? {
                copied += 1;
            } else {
                present += 1;
            }
        }
        // Verified: every live upload in the store with its size (and, asked, its bytes' hash).
        let mut problems = Vec::new();
        for (sha, size) in &live {
            match blobs.size_of(sha).await? {
                None => problems.push(format!("{sha}: not in the store (and not in {})", store.files.root().display())),
                Some(stored) if stored != *size as u64 => {
                    problems.push(format!("{sha}: {stored} bytes in the store, {size} recorded"))
                }
                Some(_) if self.verify_hashes => {
                    if let Err(e) = blobs.fetch(sha).await {
                        problems.push(format!("{sha}: {e}"));
                    }
                }
                Some(_) => {}
            }
        }
        println!(
            "{} live uploads: {copied} copied, {present} already in {}; {} verified{}",
            live.len(),
            blobs.describe(),
            live.len() - problems.len(),
            if self.verify_hashes { " by size and sha256" } else { " by size" }
        );
        if !problems.is_empty() {
            bail!("{} upload(s) not in the store as recorded:\n{}", problems.len(), problems.join("\n"));
        }
        println!(
            "Start the service with --object-store {} on this data directory; the files under {} can then be deleted.",
            self.object_store,
            store.files.root().display()
        );
        Ok(())
    }
}
