//! `crestscan migrate-store`: a single-node data directory moved into the distributed backends,
//! so that a plant that started small keeps its history:
//! - `--to postgres://…`: its records (inspections, the queue, results, CMM data, keys, audit,
//!   webhooks, stations) copied table by table, each verified by count and digest;
//! - `--object-store s3://…`: its uploaded bundles copied, each verified by size (and with
//!   `--verify-hashes` by its bytes' sha256); with `--to` as well, its meshes and images move
//!   out of the rows into the object store on the way, each verified the same way.
//!
//! Both are resumable: what the target has already is skipped, so an interrupted run is run again.

use anyhow::{Context, Result, bail};
use clap::Args;
use crestscan::service::config::Settings;
use crestscan::service::store::blobs::{BlobStore, S3Blobs};
use crestscan::service::store::{Database, Store};
use std::path::PathBuf;

#[derive(Args)]
pub struct MigrateStoreArgs {
    /// The service's data directory (its crestscan.db and uploads/).
    #[arg(long)]
    from: PathBuf,
    /// PostgreSQL to copy the records into, postgres://user:password@host:5432/crestscan (what
    /// `serve --database-url` will be given); created and migrated if new.
    #[arg(long, env = "CRESTSCAN_DATABASE_URL", hide_env_values = true)]
    to: Option<String>,
    /// The object store to copy the uploads into, s3://bucket/prefix (what `serve --object-store`
    /// will be given).
    #[arg(long, env = "CRESTSCAN_OBJECT_STORE")]
    object_store: Option<String>,
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
        if self.to.is_none() && self.object_store.is_none() {
            bail!(
                "nothing to move: give --to postgres://… (the records), --object-store s3://… (the uploads), or both"
            );
        }
        let mut settings = Settings {
            data_dir: self.from.clone(),
            database_url: self.to.clone(),
            object_store: self.object_store.clone(),
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
        let mut flags = Vec::new();
        if let Some(url) = &self.to {
            copy_records(&store, url, &settings, self.verify_hashes).await?;
            flags.push(format!("--database-url {}", crestscan::service::store::redact_url(url)));
        }
        if let Some(url) = &self.object_store {
            copy_uploads(&store, url, &settings, self.verify_hashes).await?;
            flags.push(format!("--object-store {url}"));
        }
        println!("Start the service with {} on this data directory.", flags.join(" "));
        if self.object_store.is_some() {
            println!("The files under {} can then be deleted.", store.files.root().display());
        }
        Ok(())
    }
}

/// Copies the uploads into the object store at `url` and checks every live one is there.
async fn copy_uploads(store: &Store, url: &str, settings: &Settings, verify_hashes: bool) -> Result<()> {
    let blobs = S3Blobs::open_url(url, &settings.s3(), &settings.tmp_dir())?;
    blobs.check().await.with_context(|| format!("the object store {} does not take a write", blobs.describe()))?;
    let live = store.live_uploads().await?;
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
            Some(_) if verify_hashes => {
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
        if verify_hashes { " by size and sha256" } else { " by size" }
    );
    if !problems.is_empty() {
        bail!("{} upload(s) not in the store as recorded:\n{}", problems.len(), problems.join("\n"));
    }
    Ok(())
}

/// Copies the records into PostgreSQL at `url` and checks every table came over whole.
async fn copy_records(store: &Store, url: &str, settings: &Settings, verify_hashes: bool) -> Result<()> {
    let shown = crestscan::service::store::redact_url(url);
    let mut target = Store::connect(&Database::Postgres(url.to_string()), &settings.uploads_dir(), &settings.tmp_dir())
        .await
        .with_context(|| format!("opening {shown}"))?;
    if let Some(objects) = &settings.object_store {
        let blobs = S3Blobs::open_url(objects, &settings.s3(), &settings.tmp_dir())?;
        blobs.check().await.with_context(|| format!("the object store {} does not take a write", blobs.describe()))?;
        target.artifact_objects = Some(std::sync::Arc::new(blobs));
    }
    let copies = store
        .copy_records_into(&target, |c| {
            println!(
                "{:<20} {:>9} rows, {:>9} copied now, {:>9} in the target, {}",
                c.table,
                c.rows,
                c.inserted,
                c.target_rows,
                if c.identical { "identical" } else { "DIFFERENT" }
            )
        })
        .await
        .with_context(|| format!("copying the records into {shown}"))?;
    let (objects, problems) = target.verify_artifact_objects(verify_hashes).await?;
    target.close().await;
    if objects > 0 {
        println!(
            "{objects} meshes and images in the object store: {} verified{}",
            objects - problems.len(),
            if verify_hashes { " by sha256" } else { " by presence" }
        );
    }
    if !problems.is_empty() {
        bail!("{} artifact(s) not in the object store as recorded:\n{}", problems.len(), problems.join("\n"));
    }
    let different: Vec<&str> = copies.iter().filter(|c| !c.identical).map(|c| c.table).collect();
    if !different.is_empty() {
        bail!(
            "these tables differ between the data directory and {shown}: {} (rows the target had before that the \
             source lacks, or rows changed since a first run: a target for one data directory only)",
            different.join(", ")
        );
    }
    let rows: u64 = copies.iter().map(|c| c.rows).sum();
    println!("{} tables, {rows} rows: identical in {shown} (counted, and digested row by row)", copies.len());
    Ok(())
}
