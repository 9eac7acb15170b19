//! Persistence at the edge: SQLite (WAL) through sqlx for inspections, the job queue, results and
//! CMM data; [`files::FileStore`] for uploaded bundles. SQL stays portable (no SQLite-only
//! functions beyond `RETURNING`, which PostgreSQL shares) so the store could move later.

pub mod blobs;
mod cmm;
pub mod files;
mod inspections;
mod keys;
mod queue;
mod results;
mod stations;
mod webhooks;

pub use cmm::{CmmRow, CmmVersionRow};
pub use inspections::{Inserted, InspectionRow, ListFilter, NewInspection, UploadInfo};
pub use keys::{AuditEntry, AuditRow, KeyRow};
pub use queue::{Claimed, Heartbeat};
pub use results::{Artifact, HeightRow, JobResults, PITCH_PROFILES, StoredArtifact, ThreadRow};
pub use stations::{CheckJudgement, CheckRecorded, CheckRow, MasterRow, StationRow, StudyRow};
pub use webhooks::{AttemptOutcome, AttemptRow, DeliveryFilter, DeliveryRow, NewDelivery};

use crate::problem::{Code, ErrorCode, Problem};
use files::FileStore;
use serde::Serialize;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{QueryBuilder, Sqlite, SqlitePool};
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

pub static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("./migrations");

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("not found")]
    NotFound,
    #[error("the Idempotency-Key was used for another request (inspection {existing_id})")]
    IdempotencyConflict { existing_id: String },
    #[error("database: {0}")]
    Db(#[from] sqlx::Error),
    #[error("migrations: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error(
        "the database {database} was written by a newer crestscan: it has schema version {found}, this binary knows up \
         to {known}. Run that newer version (or restore the backup taken before the upgrade); an older binary would \
         misread it"
    )]
    SchemaNewer { database: String, found: i64, known: i64 },
    #[error("file store: {0}")]
    Io(#[from] std::io::Error),
}

impl ErrorCode for StoreError {
    fn code(&self) -> Code {
        match self {
            StoreError::NotFound => Code::NotFound,
            StoreError::IdempotencyConflict { .. } => Code::IdempotencyKeyReused,
            _ if self.is_storage_full() => Code::InsufficientStorage,
            StoreError::Db(_) | StoreError::Migrate(_) | StoreError::Io(_) | StoreError::SchemaNewer { .. } => {
                Code::InternalError
            }
        }
    }

    fn culprit(&self) -> Option<String> {
        matches!(self, StoreError::IdempotencyConflict { .. }).then(|| "Idempotency-Key".into())
    }
}

impl StoreError {
    /// The database or the file store found its disk full (SQLITE_FULL, ENOSPC, a quota).
    pub fn is_storage_full(&self) -> bool {
        match self {
            StoreError::Io(e) => files::is_storage_full(e),
            // SQLITE_FULL is 13; extended codes keep it in their low byte.
            StoreError::Db(sqlx::Error::Database(db)) => {
                db.code().and_then(|c| c.parse::<u32>().ok()).is_some_and(|c| c & 0xff == 13)
            }
            StoreError::Db(sqlx::Error::Io(e)) => files::is_storage_full(e),
            _ => false,
        }
    }
}

pub fn now_ms() -> i64 {
    (time::OffsetDateTime::now_utc().unix_timestamp_nanos() / 1_000_000) as i64
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Queued,
    Running,
    Succeeded,
    Failed,
    Canceled,
}

impl Status {
    pub const ALL: [Status; 5] = [Status::Queued, Status::Running, Status::Succeeded, Status::Failed, Status::Canceled];

    pub fn as_str(self) -> &'static str {
        match self {
            Status::Queued => "queued",
            Status::Running => "running",
            Status::Succeeded => "succeeded",
            Status::Failed => "failed",
            Status::Canceled => "canceled",
        }
    }

    pub fn is_terminal(self) -> bool {
        matches!(self, Status::Succeeded | Status::Failed | Status::Canceled)
    }
}

impl FromStr for Status {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "queued" => Status::Queued,
            "running" => Status::Running,
            "succeeded" => Status::Succeeded,
            "failed" => Status::Failed,
            "canceled" => Status::Canceled,
            other => return Err(format!("unknown status {other:?} (queued, running, succeeded, failed, canceled)")),
        })
    }
}

#[derive(Clone)]
pub struct Store {
    pub pool: SqlitePool,
    /// Local staging for uploads (temporaries, the free-space floor) and, in the embedded
    /// default, the blobs' own directory.
    pub files: FileStore,
    /// Where uploaded bundles' bytes live ([`blobs::LocalBlobs`] over `files`, or an object store).
    pub blobs: std::sync::Arc<dyn blobs::BlobStore>,
    /// Deaths of the worker's process while running one job before that job is failed as
    /// poisonous ([`queue`]).
    pub max_interruptions: i64,
    /// Each change this process writes to an inspection's status or progress, as the row reads
    /// right after it: event streams see every state in order, however short, where a reading of
    /// the database every so often could miss one. Changes written by other processes reach
    /// them through the database only.
    pub changes: tokio::sync::broadcast::Sender<std::sync::Arc<InspectionRow>>,
}

impl Store {
    /// Opens (creating) the database, runs the migrations and opens the file store.
    pub async fn open(database: &Path, uploads: &Path, tmp: &Path) -> Result<Self, StoreError> {
        if let Some(dir) = database.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let options = SqliteConnectOptions::new()
            .filename(database)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            // FULL: an acknowledged upload survives power loss, not only a process crash.
            .synchronous(SqliteSynchronous::Full)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .after_release(|conn, _| Box::pin(clean_on_release(conn)))
            .connect_with(options)
            .await?;
        // A schema a newer binary wrote is refused by name before the migrator's own complaint.
        let known = MIGRATOR.iter().map(|m| m.version).max().unwrap_or(0);
        let applied: Option<i64> = sqlx::query_scalar("SELECT MAX(version) FROM _sqlx_migrations WHERE success")
            .fetch_one(&pool)
            .await
            .unwrap_or(None);
        if let Some(found) = applied.filter(|&v| v > known) {
            return Err(StoreError::SchemaNewer { database: database.display().to_string(), found, known });
        }
        MIGRATOR.run(&pool).await?;
        let files = FileStore::open(uploads, tmp)?;
        let (changes, _) = tokio::sync::broadcast::channel(256);
        let blobs = std::sync::Arc::new(blobs::LocalBlobs::new(files.clone()));
        Ok(Self { pool, files, blobs, max_interruptions: 5, changes })
    }

    /// Sends the inspection's row as it now reads to the change feed, when anyone listens.
    pub async fn publish(&self, id: &str) {
        if self.changes.receiver_count() == 0 {
            return;
        }
        if let Ok(row) = self.inspection(id).await {
            let _ = self.changes.send(std::sync::Arc::new(row));
        }
    }

    pub async fn ping(&self) -> Result<(), StoreError> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    /// Writes and commits one small row: fails where the database reads but cannot take a write
    /// (its disk full, its write lock held by a stuck connection).
    pub async fn probe_write(&self) -> Result<(), StoreError> {
        sqlx::query("INSERT INTO write_probe (id, at) VALUES (1, ?) ON CONFLICT (id) DO UPDATE SET at = excluded.at")
            .bind(now_ms())
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Deletes upload files that no live upload row names: left behind when the transaction that
    /// placed one failed to commit (a full disk). The live rows are read once; each file without
    /// one is checked again and deleted under the database's write lock, which a submission holds
    /// while it places its file, so a file being accepted right now is never taken.
    pub async fn remove_orphan_uploads(&self) -> Result<usize, StoreError> {
        let stored = self.blobs.list().await?;
        let live: std::collections::HashSet<String> =
            sqlx::query_scalar("SELECT sha256 FROM uploads WHERE purged_at IS NULL")
                .fetch_all(&self.pool)
                .await?
                .into_iter()
                .collect();
        let mut removed = 0;
        for sha in stored.into_iter().filter(|sha| !live.contains(sha)) {
            let mut tx = self.pool.begin_with("BEGIN IMMEDIATE").await?;
            let live: Option<(i64,)> = sqlx::query_as("SELECT 1 FROM uploads WHERE sha256 = ? AND purged_at IS NULL")
                .bind(&sha)
                .fetch_optional(&mut *tx)
                .await?;
            if live.is_none() {
                self.blobs.remove(&sha).await?;
                removed += 1;
            }
            tx.commit().await?;
        }
        Ok(removed)
    }
}

/// Whether a connection coming back to the pool is clean: no transaction open, neither in SQLite
/// nor in sqlx's count of them. A connection that is not is closed (which rolls back whatever it
/// held) instead of being handed to the next caller.
///
/// Why: when a COMMIT fails with SQLITE_FULL, SQLite rolls the transaction back itself, but sqlx
/// 0.8's count stays at one (its ROLLBACK on drop then fails with "no transaction is active").
/// The next `begin()` on that connection issued a SAVEPOINT instead of BEGIN; a later `ROLLBACK
/// TO` of it left a transaction open holding the write lock: every other connection then got
/// "database is locked", and this one's "commits" were RELEASEs inside a transaction never
/// committed (an accepted upload answered 202 and then 404; issue 48).
async fn clean_on_release(conn: &mut sqlx::SqliteConnection) -> Result<bool, sqlx::Error> {
    use sqlx::Connection;
    // Queued behind any rollback a dropped transaction sent, so that it has run.
    let mut handle = conn.lock_handle().await?;
    // SAFETY: the handle is locked out from sqlx's worker thread while it lives;
    // sqlite3_get_autocommit only reads the connection's flag.
    let autocommit = unsafe { libsqlite3_sys::sqlite3_get_autocommit(handle.as_raw_handle().as_ptr()) } != 0;
    drop(handle);
    let clean = autocommit && !conn.is_in_transaction();
    if !clean {
        tracing::warn!(
            sqlite_in_transaction = !autocommit,
            sqlx_in_transaction = conn.is_in_transaction(),
            "a database connection came back with a transaction open (a failed commit?); closed, not reused"
        );
    }
    Ok(clean)
}

/// A strong ETag: the quoted sha256 of the bytes.
pub fn etag_of(bytes: &[u8]) -> String {
    format!("\"{}\"", files::sha256_hex(bytes))
}
