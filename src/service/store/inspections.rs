//! Inspections: submitting (with idempotency), reading, listing with filters and cursors, and
//! requesting cancellation.

use super::*;

/// An inspection as stored, joined with its upload's summary (serialised only as the change feed's
/// message between processes).
#[derive(Clone, Debug, sqlx::FromRow, Serialize, serde::Deserialize)]
pub struct InspectionRow {
    pub id: String,
    pub status: String,
    pub upload_sha256: String,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    pub options_json: String,
    pub verdict: Option<String>,
    /// Whether the result needs review; set when the inspection succeeds.
    pub review_required: Option<bool>,
    /// The ISO 14253-1 decision; set when the inspection succeeds.
    pub decision: Option<String>,
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
    /// The station the bundle was recorded at, as the manifest or the submission named it.
    pub station: Option<String>,
    pub size_bytes: i64,
    pub views: i64,
    pub frames: i64,
}

impl InspectionRow {
    pub fn status(&self) -> Status {
        self.status.parse().unwrap_or(Status::Failed)
    }
}

pub(super) const SELECT_INSPECTION: &str = "SELECT i.id, i.status, i.upload_sha256, i.serial, i.connection, i.client_reference, \
     i.options_json, i.verdict, i.review_required, i.decision, i.created_at, i.updated_at, i.started_at, i.finished_at, i.progress_stage, \
     i.progress_fraction, i.attempts, i.max_attempts, i.cancel_requested, i.error_json, i.request_sha256, \
     i.station, u.size_bytes, u.views, u.frames FROM inspections i JOIN uploads u ON u.sha256 = i.upload_sha256";

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
    pub station: Option<String>,
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
    pub review_required: Option<bool>,
    pub serial: Option<String>,
    pub connection: Option<String>,
    pub client_reference: Option<String>,
    pub station: Option<String>,
    pub created_after_ms: Option<i64>,
    pub created_before_ms: Option<i64>,
    /// Only inspections that finished (succeeded, failed or were canceled) after this time.
    pub finished_after_ms: Option<i64>,
    /// Only ids strictly older than this one (newest first).
    pub before_id: Option<String>,
    pub limit: u32,
}

impl Store {
    pub async fn inspection(&self, id: &str) -> Result<InspectionRow, StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query_as::<_, InspectionRow>(&d.sql(&format!("{SELECT_INSPECTION} WHERE i.id = ?")))
                .bind(id)
                .fetch_optional(pool)
                .await?
        })
        .ok_or(StoreError::NotFound)
    }

    pub async fn by_idempotency_key(&self, key: &str) -> Result<Option<InspectionRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as::<_, InspectionRow>(&d.sql(&format!("{SELECT_INSPECTION} WHERE i.idempotency_key = ?")))
                .bind(key)
                .fetch_optional(pool)
                .await?
        }))
    }

    /// Records an accepted upload and its queued inspection in one transaction, placing the
    /// (prepared, i.e. fsynced) upload file under its hash while the transaction holds the lock
    /// the retention sweep deletes files under (SQLite's write lock, PostgreSQL's lock on the
    /// hash): a committed row always has its file.
    pub async fn insert_inspection(
        &self,
        new: &NewInspection,
        file: tempfile::NamedTempFile,
    ) -> Result<Inserted, StoreError> {
        let now = now_ms();
        on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            if let Some(lock) = d.lock_key() {
                sqlx::query(lock).bind(&new.upload.sha256).execute(&mut *tx).await?;
            }
            // A write first, so the transaction holds the write lock before it reads the key.
            sqlx::query(&d.sql(
                "INSERT INTO uploads (sha256, size_bytes, views, frames, created_at) VALUES (?, ?, ?, ?, ?) \
                 ON CONFLICT (sha256) DO UPDATE SET purged_at = NULL",
            ))
            .bind(&new.upload.sha256)
            .bind(new.upload.size_bytes as i64)
            .bind(new.upload.views as i64)
            .bind(new.upload.frames as i64)
            .bind(now)
            .execute(&mut *tx)
            .await?;
            if let Some(key) = &new.idempotency_key {
                let existing: Option<(String, String)> =
                    sqlx::query_as(&d.sql("SELECT id, request_sha256 FROM inspections WHERE idempotency_key = ?"))
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
            self.blobs.put(&new.upload.sha256, file).await?;
            sqlx::query(&d.sql(
                "INSERT INTO inspections (id, status, upload_sha256, serial, connection, client_reference, options_json, \
                 created_at, updated_at, max_attempts, available_at, idempotency_key, request_sha256, station) \
                 VALUES (?, 'queued', ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            ))
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
            .bind(&new.station)
            .execute(&mut *tx)
            .await?;
            // Read inside the transaction: after the commit a worker may already have claimed it, and
            // the answer to the submission is the inspection as created (queued).
            let row = sqlx::query_as::<_, InspectionRow>(&d.sql(&format!("{SELECT_INSPECTION} WHERE i.id = ?")))
                .bind(&new.id)
                .fetch_one(&mut *tx)
                .await?;
            if d == Dialect::Postgres {
                // Delivered at the commit, to every process's listener: idle workers wake.
                sqlx::query("SELECT pg_notify($1, $2)").bind(QUEUE_CHANNEL).bind(&new.id).execute(&mut *tx).await?;
            }
            tx.commit().await?;
            Ok(Inserted::Created(row))
        })
    }

    pub async fn list(&self, filter: &ListFilter) -> Result<Vec<InspectionRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            let mut q = QueryBuilder::new(SELECT_INSPECTION);
            q.push(" WHERE 1 = 1");
            if let Some(s) = filter.status {
                q.push(" AND i.status = ").push_bind(s.as_str());
            }
            if let Some(v) = &filter.verdict {
                q.push(" AND i.verdict = ").push_bind(v.clone());
            }
            if let Some(v) = filter.review_required {
                q.push(" AND i.review_required = ").push_bind(v);
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
            if let Some(v) = &filter.station {
                q.push(" AND i.station = ").push_bind(v.clone());
            }
            if let Some(t) = filter.created_after_ms {
                q.push(" AND i.created_at > ").push_bind(t);
            }
            if let Some(t) = filter.created_before_ms {
                q.push(" AND i.created_at < ").push_bind(t);
            }
            if let Some(t) = filter.finished_after_ms {
                q.push(" AND i.finished_at > ").push_bind(t);
            }
            if let Some(id) = &filter.before_id {
                q.push(" AND i.id < ").push_bind(id.clone());
            }
            q.push(" ORDER BY i.id DESC LIMIT ").push_bind(filter.limit as i64);
            q.build_query_as::<InspectionRow>().fetch_all(pool).await?
        }))
    }

    /// Cancels a queued inspection at once, or asks a running one to stop (its worker sees the
    /// flag at the next heartbeat). Terminal ones are returned unchanged.
    pub async fn request_cancel(&self, id: &str) -> Result<InspectionRow, StoreError> {
        let now = now_ms();
        on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "UPDATE inspections SET status = 'canceled', finished_at = ?, updated_at = ?, lease_owner = NULL, \
                 lease_expires_at = NULL WHERE id = ? AND status = 'queued'",
            ))
            .bind(now)
            .bind(now)
            .bind(id)
            .execute(pool)
            .await?;
            sqlx::query(&d.sql(
                "UPDATE inspections SET cancel_requested = TRUE, updated_at = ? WHERE id = ? AND status = 'running'",
            ))
            .bind(now)
            .bind(id)
            .execute(pool)
            .await?;
        });
        self.publish(id).await;
        self.inspection(id).await
    }
}
