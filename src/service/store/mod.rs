//! Persistence at the edge: SQLite (WAL) through sqlx for inspections, the job queue, results and
//! CMM data; [`files::FileStore`] for uploaded bundles. SQL stays portable (no SQLite-only
//! functions beyond `RETURNING`, which PostgreSQL shares) so the store could move later.

pub mod files;

use crate::problem::{Code, Problem};
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
    #[error("file store: {0}")]
    Io(#[from] std::io::Error),
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

/// An inspection as stored, joined with its upload's summary.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct InspectionRow {
    pub id: String,
    pub status: String,
    pub upload_sha256: String,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    pub options_json: String,
    pub verdict: Option<String>,
    pub created_at: i64,
    pub updated_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
    pub progress_stage: Option<String>,
    pub progress_fraction: Option<f64>,
    pub attempts: i64,
    pub max_attempts: i64,
    pub cancel_requested: bool,
    pub error_json: Option<String>,
    pub request_sha256: String,
    pub size_bytes: i64,
    pub views: i64,
    pub frames: i64,
}

impl InspectionRow {
    pub fn status(&self) -> Status {
        self.status.parse().unwrap_or(Status::Failed)
    }
}

const SELECT_INSPECTION: &str = "SELECT i.id, i.status, i.upload_sha256, i.serial, i.connection, i.client_reference, \
     i.options_json, i.verdict, i.created_at, i.updated_at, i.started_at, i.finished_at, i.progress_stage, \
     i.progress_fraction, i.attempts, i.max_attempts, i.cancel_requested, i.error_json, i.request_sha256, \
     u.size_bytes, u.views, u.frames FROM inspections i JOIN uploads u ON u.sha256 = i.upload_sha256";

#[derive(Clone, Debug)]
pub struct UploadInfo {
    pub sha256: String,
    pub size_bytes: u64,
    pub views: usize,
    pub frames: usize,
}

#[derive(Clone, Debug)]
pub struct NewInspection {
    pub id: String,
    pub upload: UploadInfo,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    pub options_json: String,
    pub idempotency_key: Option<String>,
    /// Hash of the upload and the options: what "the same request" means for Idempotency-Key.
    pub request_sha256: String,
    pub max_attempts: u32,
}

pub enum Inserted {
    Created(InspectionRow),
    /// Same Idempotency-Key, same request: the earlier inspection.
    Replayed(InspectionRow),
}

#[derive(Clone, Debug, Default)]
pub struct ListFilter {
    pub status: Option<Status>,
    pub verdict: Option<String>,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    pub created_after_ms: Option<i64>,
    pub created_before_ms: Option<i64>,
    /// Only ids strictly older than this one (newest first).
    pub before_id: Option<String>,
    pub limit: u32,
}

/// A claimed job.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct Claimed {
    pub id: String,
    pub upload_sha256: String,
    pub options_json: String,
    pub attempts: i64,
    pub max_attempts: i64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Heartbeat {
    Held {
        cancel_requested: bool,
    },
    /// The lease expired and another worker (or nobody) owns the job now.
    Lost,
}

/// A result file kept as a BLOB.
#[derive(Clone, Debug)]
pub struct Artifact {
    pub kind: &'static str,
    pub content_type: &'static str,
    pub body: Vec<u8>,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct StoredArtifact {
    pub content_type: String,
    pub body: Vec<u8>,
    pub etag: String,
}

#[derive(Clone, Debug)]
pub struct JobResults {
    pub verdict: &'static str,
    pub report_json: String,
    pub report: crate::pipeline::report::Report,
    pub artifacts: Vec<Artifact>,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct ThreadRow {
    pub thread_index: i64,
    pub crest_z_start_mm: f64,
    pub crest_z_end_mm: f64,
    pub min_height_mm: Option<f64>,
    pub mean_height_mm: Option<f64>,
    pub max_height_mm: Option<f64>,
    pub bins_measured: i64,
    pub black_crest_length_mm: f64,
    pub black_crest_arcs_json: String,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct HeightRow {
    pub thread_index: i64,
    pub angle_deg: f64,
    pub height_mm: Option<f64>,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct CmmRow {
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub points_json: String,
    pub uploaded_at: i64,
}

#[derive(Clone)]
pub struct Store {
    pub pool: SqlitePool,
    pub files: FileStore,
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
        let pool = SqlitePoolOptions::new().max_connections(8).connect_with(options).await?;
        MIGRATOR.run(&pool).await?;
        let files = FileStore::open(uploads, tmp)?;
        Ok(Self { pool, files })
    }

    pub async fn inspection(&self, id: &str) -> Result<InspectionRow, StoreError> {
        sqlx::query_as::<_, InspectionRow>(&format!("{SELECT_INSPECTION} WHERE i.id = ?"))
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
            .ok_or(StoreError::NotFound)
    }

    pub async fn by_idempotency_key(&self, key: &str) -> Result<Option<InspectionRow>, StoreError> {
        Ok(sqlx::query_as::<_, InspectionRow>(&format!("{SELECT_INSPECTION} WHERE i.idempotency_key = ?"))
            .bind(key)
            .fetch_optional(&self.pool)
            .await?)
    }

    /// Records an accepted upload and its queued inspection in one transaction, placing the
    /// (prepared, i.e. fsynced) upload file under its hash while the transaction holds the write
    /// lock: the retention sweep deletes files under the same lock, so a committed row always has
    /// its file.
    pub async fn insert_inspection(
        &self,
        new: &NewInspection,
        file: tempfile::NamedTempFile,
    ) -> Result<Inserted, StoreError> {
        let now = now_ms();
        let mut tx = self.pool.begin().await?;
        // A write first, so the transaction holds the write lock before it reads the key.
        sqlx::query(
            "INSERT INTO uploads (sha256, size_bytes, views, frames, created_at) VALUES (?, ?, ?, ?, ?) \
             ON CONFLICT (sha256) DO UPDATE SET purged_at = NULL",
        )
        .bind(&new.upload.sha256)
        .bind(new.upload.size_bytes as i64)
        .bind(new.upload.views as i64)
        .bind(new.upload.frames as i64)
        .bind(now)
        .execute(&mut *tx)
        .await?;
        if let Some(key) = &new.idempotency_key {
            let existing: Option<(String, String)> =
                sqlx::query_as("SELECT id, request_sha256 FROM inspections WHERE idempotency_key = ?")
                    .bind(key)
                    .fetch_optional(&mut *tx)
                    .await?;
            if let Some((id, hash)) = existing {
                tx.rollback().await?;
                return if hash == new.request_sha256 {
                    Ok(Inserted::Replayed(self.inspection(&id).await?))
                } else {
                    Err(StoreError::IdempotencyConflict { existing_id: id })
                };
            }
        }
        let files = self.files.clone();
        let sha = new.upload.sha256.clone();
        tokio::task::spawn_blocking(move || files.place(file, &sha))
            .await
            .map_err(|e| StoreError::Io(std::io::Error::other(e)))??;
        sqlx::query(
            "INSERT INTO inspections (id, status, upload_sha256, serial, connection, client_reference, options_json, \
             created_at, updated_at, max_attempts, available_at, idempotency_key, request_sha256) \
             VALUES (?, 'queued', ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(&new.id)
        .bind(&new.upload.sha256)
        .bind(&new.serial)
        .bind(&new.connection)
        .bind(&new.client_reference)
        .bind(&new.options_json)
        .bind(now)
        .bind(now)
        .bind(new.max_attempts as i64)
        .bind(now)
        .bind(&new.idempotency_key)
        .bind(&new.request_sha256)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(Inserted::Created(self.inspection(&new.id).await?))
    }

    pub async fn list(&self, filter: &ListFilter) -> Result<Vec<InspectionRow>, StoreError> {
        let mut q: QueryBuilder<Sqlite> = QueryBuilder::new(SELECT_INSPECTION);
        q.push(" WHERE 1 = 1");
        if let Some(s) = filter.status {
            q.push(" AND i.status = ").push_bind(s.as_str());
        }
        if let Some(v) = &filter.verdict {
            q.push(" AND i.verdict = ").push_bind(v.clone());
        }
        if let Some(v) = &filter.serial {
            q.push(" AND i.serial = ").push_bind(v.clone());
        }
        if let Some(v) = &filter.connection {
            q.push(" AND i.connection = ").push_bind(v.clone());
        }
        if let Some(v) = &filter.client_reference {
            q.push(" AND i.client_reference = ").push_bind(v.clone());
        }
        if let Some(t) = filter.created_after_ms {
            q.push(" AND i.created_at > ").push_bind(t);
        }
        if let Some(t) = filter.created_before_ms {
            q.push(" AND i.created_at < ").push_bind(t);
        }
        if let Some(id) = &filter.before_id {
            q.push(" AND i.id < ").push_bind(id.clone());
        }
        q.push(" ORDER BY i.id DESC LIMIT ").push_bind(filter.limit as i64);
        Ok(q.build_query_as::<InspectionRow>().fetch_all(&self.pool).await?)
    }

    /// Cancels a queued inspection at once, or asks a running one to stop (its worker sees the
    /// flag at the next heartbeat). Terminal ones are returned unchanged.
    pub async fn request_cancel(&self, id: &str) -> Result<InspectionRow, StoreError> {
        let now = now_ms();
        sqlx::query(
            "UPDATE inspections SET status = 'canceled', finished_at = ?, updated_at = ?, lease_owner = NULL, \
             lease_expires_at = NULL WHERE id = ? AND status = 'queued'",
        )
        .bind(now)
        .bind(now)
        .bind(id)
        .execute(&self.pool)
        .await?;
        sqlx::query("UPDATE inspections SET cancel_requested = 1, updated_at = ? WHERE id = ? AND status = 'running'")
            .bind(now)
            .bind(id)
            .execute(&self.pool)
            .await?;
        self.inspection(id).await
    }

    /// Atomically claims the oldest available job: queued and due, or running with a lapsed lease.
    pub async fn claim(&self, owner: &str, lease: Duration) -> Result<Option<Claimed>, StoreError> {
        let now = now_ms();
        // Jobs whose attempts are spent (they kept dying) fail instead of looping forever.
        sqlx::query(
            "UPDATE inspections SET status = 'failed', finished_at = ?, updated_at = ?, lease_owner = NULL, \
             lease_expires_at = NULL, error_json = ? \
             WHERE status = 'running' AND lease_expires_at < ? AND attempts >= max_attempts",
        )
        .bind(now)
        .bind(now)
        .bind(attempts_exhausted_problem())
        .bind(now)
        .execute(&self.pool)
        .await?;
        let claimed = sqlx::query_as::<_, Claimed>(
            "UPDATE inspections SET status = 'running', lease_owner = ?, lease_expires_at = ?, \
             attempts = attempts + 1, started_at = COALESCE(started_at, ?), updated_at = ?, \
             progress_stage = NULL, progress_fraction = NULL \
             WHERE id = (SELECT id FROM inspections WHERE cancel_requested = 0 AND \
               ((status = 'queued' AND available_at <= ?) OR (status = 'running' AND lease_expires_at < ?)) \
               ORDER BY id LIMIT 1) \
             RETURNING id, upload_sha256, options_json, attempts, max_attempts",
        )
        .bind(owner)
        .bind(now + lease.as_millis() as i64)
        .bind(now)
        .bind(now)
        .bind(now)
        .bind(now)
        .fetch_optional(&self.pool)
        .await?;
        // A running job whose worker died after a cancel request: cancel it now.
        sqlx::query(
            "UPDATE inspections SET status = 'canceled', finished_at = ?, updated_at = ?, lease_owner = NULL, \
             lease_expires_at = NULL WHERE status = 'running' AND cancel_requested = 1 AND lease_expires_at < ?",
        )
        .bind(now)
        .bind(now)
        .bind(now)
        .execute(&self.pool)
        .await?;
        Ok(claimed)
    }

    /// Renews the lease and publishes progress; tells the worker whether to stop.
    pub async fn heartbeat(
        &self,
        id: &str,
        owner: &str,
        lease: Duration,
        progress: Option<(&str, f64)>,
    ) -> Result<Heartbeat, StoreError> {
        let now = now_ms();
        let row: Option<(bool,)> = sqlx::query_as(
            "UPDATE inspections SET lease_expires_at = ?, updated_at = ?, \
             progress_stage = COALESCE(?, progress_stage), progress_fraction = COALESCE(?, progress_fraction) \
             WHERE id = ? AND lease_owner = ? AND status = 'running' RETURNING cancel_requested",
        )
        .bind(now + lease.as_millis() as i64)
        .bind(now)
        .bind(progress.map(|p| p.0))
        .bind(progress.map(|p| p.1))
        .bind(id)
        .bind(owner)
        .fetch_optional(&self.pool)
        .await?;
        Ok(match row {
            Some((cancel_requested,)) => Heartbeat::Held { cancel_requested },
            None => Heartbeat::Lost,
        })
    }

    /// Stores the results and marks the job succeeded, in one transaction, only if this worker
    /// still holds the lease (so a job finishes exactly once). Returns false when it did not.
    pub async fn complete_success(&self, id: &str, owner: &str, results: &JobResults) -> Result<bool, StoreError> {
        let now = now_ms();
        let mut tx = self.pool.begin().await?;
        let updated = sqlx::query(
            "UPDATE inspections SET status = 'succeeded', verdict = ?, finished_at = ?, updated_at = ?, \
             lease_owner = NULL, lease_expires_at = NULL, progress_fraction = 1.0, error_json = NULL \
             WHERE id = ? AND lease_owner = ? AND status = 'running'",
        )
        .bind(results.verdict)
        .bind(now)
        .bind(now)
        .bind(id)
        .bind(owner)
        .execute(&mut *tx)
        .await?;
        if updated.rows_affected() == 0 {
            tx.rollback().await?;
            return Ok(false);
        }
        sqlx::query("INSERT INTO reports (inspection_id, report_json, etag) VALUES (?, ?, ?)")
            .bind(id)
            .bind(&results.report_json)
            .bind(etag_of(results.report_json.as_bytes()))
            .execute(&mut *tx)
            .await?;
        for a in &results.artifacts {
            sqlx::query("INSERT INTO artifacts (inspection_id, kind, content_type, body, etag) VALUES (?, ?, ?, ?, ?)")
                .bind(id)
                .bind(a.kind)
                .bind(a.content_type)
                .bind(&a.body)
                .bind(etag_of(&a.body))
                .execute(&mut *tx)
                .await?;
        }
        for t in &results.report.threads {
            sqlx::query(
                "INSERT INTO threads (inspection_id, thread_index, crest_z_start_mm, crest_z_end_mm, min_height_mm, \
                 mean_height_mm, max_height_mm, bins_measured, black_crest_length_mm, black_crest_arcs_json) \
                 VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            )
            .bind(id)
            .bind(t.index as i64)
            .bind(t.crest_z_mm[0])
            .bind(t.crest_z_mm[1])
            .bind(t.min_height_mm)
            .bind(t.mean_height_mm)
            .bind(t.max_height_mm)
            .bind(t.bins_measured as i64)
            .bind(t.black_crest_length_mm)
            .bind(serde_json::to_string(&t.black_crest_arcs_deg).expect("arcs serialise"))
            .execute(&mut *tx)
            .await?;
        }
        let rows: Vec<(u32, f64, Option<f64>)> = results
            .report
            .threads
            .iter()
            .flat_map(|t| t.height_mm.angles_deg.iter().zip(&t.height_mm.values).map(|(&a, &h)| (t.index, a, h)))
            .collect();
        // 4 parameters a row; SQLite allows 32 766 per statement.
        for chunk in rows.chunks(2000) {
            let mut q: QueryBuilder<Sqlite> =
                QueryBuilder::new("INSERT INTO thread_heights (inspection_id, thread_index, angle_deg, height_mm) ");
            q.push_values(chunk, |mut b, (t, a, h)| {
                b.push_bind(id).push_bind(*t as i64).push_bind(*a).push_bind(*h);
            });
            q.build().execute(&mut *tx).await?;
        }
        tx.commit().await?;
        Ok(true)
    }

    /// Ends a job without results: failed (with its problem object) or canceled.
    pub async fn complete_without_results(
        &self,
        id: &str,
        owner: &str,
        status: Status,
        problem_json: Option<&str>,
    ) -> Result<bool, StoreError> {
        let now = now_ms();
        let updated = sqlx::query(
            "UPDATE inspections SET status = ?, finished_at = ?, updated_at = ?, lease_owner = NULL, \
             lease_expires_at = NULL, error_json = ? WHERE id = ? AND lease_owner = ? AND status = 'running'",
        )
        .bind(status.as_str())
        .bind(now)
        .bind(now)
        .bind(problem_json)
        .bind(id)
        .bind(owner)
        .execute(&self.pool)
        .await?;
        Ok(updated.rows_affected() == 1)
    }

    /// Puts a job back in the queue: a retryable failure (after `delay`, error kept for the
    /// record) or a release at shutdown (delay zero, attempt not counted). A job whose cancel was
    /// requested is canceled instead (claims skip it, so queued it would wait forever).
    pub async fn requeue(
        &self,
        id: &str,
        owner: &str,
        delay: Duration,
        problem_json: Option<&str>,
        refund_attempt: bool,
    ) -> Result<bool, StoreError> {
        let now = now_ms();
        let updated = sqlx::query(
            "UPDATE inspections SET status = CASE WHEN cancel_requested = 1 THEN 'canceled' ELSE 'queued' END, \
             finished_at = CASE WHEN cancel_requested = 1 THEN ? ELSE NULL END, available_at = ?, updated_at = ?, \
             lease_owner = NULL, lease_expires_at = NULL, error_json = COALESCE(?, error_json), attempts = attempts - ?, \
             progress_stage = NULL, progress_fraction = NULL WHERE id = ? AND lease_owner = ? AND status = 'running'",
        )
        .bind(now)
        .bind(now + delay.as_millis() as i64)
        .bind(now)
        .bind(problem_json)
        .bind(refund_attempt as i64)
        .bind(id)
        .bind(owner)
        .execute(&self.pool)
        .await?;
        Ok(updated.rows_affected() == 1)
    }

    pub async fn report(&self, id: &str) -> Result<(String, String), StoreError> {
        sqlx::query_as("SELECT report_json, etag FROM reports WHERE inspection_id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
            .ok_or(StoreError::NotFound)
    }

    pub async fn artifact(&self, id: &str, kind: &str) -> Result<StoredArtifact, StoreError> {
        sqlx::query_as("SELECT content_type, body, etag FROM artifacts WHERE inspection_id = ? AND kind = ?")
            .bind(id)
            .bind(kind)
            .fetch_optional(&self.pool)
            .await?
            .ok_or(StoreError::NotFound)
    }

    pub async fn threads(&self, id: &str) -> Result<(Vec<ThreadRow>, Vec<HeightRow>), StoreError> {
        let threads = sqlx::query_as::<_, ThreadRow>(
            "SELECT thread_index, crest_z_start_mm, crest_z_end_mm, min_height_mm, mean_height_mm, max_height_mm, \
             bins_measured, black_crest_length_mm, black_crest_arcs_json FROM threads WHERE inspection_id = ? \
             ORDER BY thread_index",
        )
        .bind(id)
        .fetch_all(&self.pool)
        .await?;
        let heights = sqlx::query_as::<_, HeightRow>(
            "SELECT thread_index, angle_deg, height_mm FROM thread_heights WHERE inspection_id = ? \
             ORDER BY thread_index, angle_deg",
        )
        .bind(id)
        .fetch_all(&self.pool)
        .await?;
        Ok((threads, heights))
    }

    pub async fn put_cmm(&self, id: &str, cmm: &crate::eval::cmm::CmmMeasurements) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO cmm_measurements (inspection_id, instrument, measured_at, points_json, uploaded_at) \
             VALUES (?, ?, ?, ?, ?) ON CONFLICT (inspection_id) DO UPDATE SET instrument = excluded.instrument, \
             measured_at = excluded.measured_at, points_json = excluded.points_json, uploaded_at = excluded.uploaded_at",
        )
        .bind(id)
        .bind(&cmm.instrument)
        .bind(&cmm.measured_at)
        .bind(serde_json::to_string(&cmm.points).expect("points serialise"))
        .bind(now_ms())
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    pub async fn cmm(&self, id: &str) -> Result<CmmRow, StoreError> {
        sqlx::query_as(
            "SELECT instrument, measured_at, points_json, uploaded_at FROM cmm_measurements WHERE inspection_id = ?",
        )
        .bind(id)
        .fetch_optional(&self.pool)
        .await?
        .ok_or(StoreError::NotFound)
    }

    /// Jobs waiting (queued) and running.
    pub async fn queue_depth(&self) -> Result<(i64, i64), StoreError> {
        Ok(sqlx::query_as(
            "SELECT COALESCE(SUM(status = 'queued'), 0), COALESCE(SUM(status = 'running'), 0) FROM inspections \
             WHERE status IN ('queued', 'running')",
        )
        .fetch_one(&self.pool)
        .await?)
    }

    /// Deletes uploaded bundles whose inspections all finished before `cutoff_ms`.
    pub async fn purge_uploads(&self, cutoff_ms: i64) -> Result<usize, StoreError> {
        let due: Vec<(String,)> = sqlx::query_as(
            "SELECT u.sha256 FROM uploads u WHERE u.purged_at IS NULL AND NOT EXISTS (SELECT 1 FROM inspections i \
             WHERE i.upload_sha256 = u.sha256 AND (i.finished_at IS NULL OR i.finished_at >= ?))",
        )
        .bind(cutoff_ms)
        .fetch_all(&self.pool)
        .await?;
        let mut purged = 0;
        for (sha,) in &due {
            // Re-checked and deleted under the write lock: an upload of the same bundle accepted
            // since the SELECT keeps its file (it places it under the same lock).
            let mut tx = self.pool.begin().await?;
            let marked = sqlx::query(
                "UPDATE uploads SET purged_at = ? WHERE sha256 = ? AND purged_at IS NULL AND NOT EXISTS (SELECT 1 \
                 FROM inspections i WHERE i.upload_sha256 = uploads.sha256 AND (i.finished_at IS NULL OR i.finished_at >= ?))",
            )
            .bind(now_ms())
            .bind(sha)
            .bind(cutoff_ms)
            .execute(&mut *tx)
            .await?;
            if marked.rows_affected() == 1 {
                self.files.remove(sha)?;
                purged += 1;
            }
            tx.commit().await?;
        }
        Ok(purged)
    }

    pub async fn ping(&self) -> Result<(), StoreError> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }
}

/// A strong ETag: the quoted sha256 of the bytes.
pub fn etag_of(bytes: &[u8]) -> String {
    format!("\"{}\"", files::sha256_hex(bytes))
}

fn attempts_exhausted_problem() -> String {
    let problem = Problem::new(
        Code::AttemptsExhausted,
        "the job's worker stopped (crash or kill) on every attempt; it was not retried again",
        None,
    );
    serde_json::to_string(&problem).expect("a problem serialises")
}
