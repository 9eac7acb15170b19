//! Results: the report, the per-thread table, the stored artifacts (meshes, images), and the
//! retention of finished uploads.

use super::*;

/// The artifact holding an inspection's pitch profiles ([`crate::eval::pairs::ProfileSet`]): the
/// worker writes it, the CMM routes read it.
pub const PITCH_PROFILES: &str = "pitch-profiles";

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
    pub mean_height_uncertainty_mm: Option<f64>,
    pub height_finding: Option<String>,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct HeightRow {
    pub thread_index: i64,
    pub angle_deg: f64,
    pub height_mm: Option<f64>,
    pub uncertainty_mm: Option<f64>,
}

impl Store {
    pub async fn report(&self, id: &str) -> Result<(String, String), StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql("SELECT report_json, etag FROM reports WHERE inspection_id = ?"))
                .bind(id)
                .fetch_optional(pool)
                .await?
        })
        .ok_or(StoreError::NotFound)
    }

    pub async fn artifact(&self, id: &str, kind: &str) -> Result<StoredArtifact, StoreError> {
        let row: Option<(String, Vec<u8>, String, Option<String>)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT content_type, body, etag, object_sha256 FROM artifacts WHERE inspection_id = ? AND kind = ?",
            ))
            .bind(id)
            .bind(kind)
            .fetch_optional(pool)
            .await?
        });
        let (content_type, body, etag, object_sha256) = row.ok_or(StoreError::NotFound)?;
        let Some(sha256) = object_sha256 else { return Ok(StoredArtifact { content_type, body, etag }) };
        let objects = self.artifact_objects.as_ref().ok_or_else(|| {
            StoreError::Io(std::io::Error::other(format!(
                "the {kind} of {id} is kept in an object store, and this process has none configured \
                 (start it with the --object-store the workers have)"
            )))
        })?;
        let key = blobs::ArtifactKey { inspection_id: id.into(), kind: kind.into(), sha256 };
        let body = objects.get_artifact(&key).await?;
        Ok(StoredArtifact { content_type, body, etag })
    }

    pub async fn threads(&self, id: &str) -> Result<(Vec<ThreadRow>, Vec<HeightRow>), StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            let threads = sqlx::query_as::<_, ThreadRow>(&d.sql(
                "SELECT thread_index, crest_z_start_mm, crest_z_end_mm, min_height_mm, mean_height_mm, max_height_mm, \
                 bins_measured, black_crest_length_mm, black_crest_arcs_json, mean_height_uncertainty_mm, height_finding \
                 FROM threads WHERE inspection_id = ? \
                 ORDER BY thread_index",
            ))
            .bind(id)
            .fetch_all(pool)
            .await?;
            let heights = sqlx::query_as::<_, HeightRow>(&d.sql(
                "SELECT thread_index, angle_deg, height_mm, uncertainty_mm FROM thread_heights WHERE inspection_id = ? \
                 ORDER BY thread_index, angle_deg",
            ))
            .bind(id)
            .fetch_all(pool)
            .await?;
            (threads, heights)
        }))
    }

    /// Deletes the meshes and images of inspections that finished before `cutoff_ms`, keeping
    /// their reports and thread tables; returns how many inspections lost theirs. SQLite reuses
    /// the freed pages for new results, so the database stops growing by them (the file itself
    /// shrinks only with VACUUM).
    pub async fn purge_artifacts(&self, cutoff_ms: i64) -> Result<usize, StoreError> {
        let (purged, objects): (usize, Vec<blobs::ArtifactKey>) = on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            // A write first: a transaction that read first could not take the write lock if another
            // connection wrote in between (SQLite answers "database is locked" at once, whatever the
            // busy timeout).
            let due: Vec<(String,)> = sqlx::query_as(&d.sql(
                "UPDATE inspections SET artifacts_purged_at = ? WHERE finished_at < ? AND artifacts_purged_at IS NULL \
                 AND EXISTS (SELECT 1 FROM artifacts a WHERE a.inspection_id = inspections.id) RETURNING id",
            ))
            .bind(now_ms())
            .bind(cutoff_ms)
            .fetch_all(&mut *tx)
            .await?;
            let mut objects = Vec::new();
            for (id,) in &due {
                let gone: Vec<(String, Option<String>)> = sqlx::query_as(
                    &d.sql("DELETE FROM artifacts WHERE inspection_id = ? RETURNING kind, object_sha256"),
                )
                .bind(id)
                .fetch_all(&mut *tx)
                .await?;
                objects.extend(gone.into_iter().filter_map(|(kind, sha)| {
                    sha.map(|sha256| blobs::ArtifactKey { inspection_id: id.clone(), kind, sha256 })
                }));
            }
            tx.commit().await?;
            (due.len(), objects)
        });
        // After the commit: an object whose deletion fails here is one no record names, which
        // the orphan sweep deletes on its next pass.
        if let Some(store) = &self.artifact_objects {
            for key in &objects {
                if let Err(e) = store.remove_artifact(key).await {
                    tracing::warn!(error = %e, inspection = %key.inspection_id, "deleting a purged artifact's object");
                }
            }
        }
        Ok(purged)
    }

    /// Deletes artifact objects that no record names and that were written before `written_before_ms`:
    /// a worker's results whose completion did not commit (its lease lost, its process killed
    /// between upload and commit), or a purge's deletion that failed. The objects are listed
    /// before the records are read, so an object whose record commits meanwhile is either seen
    /// named or younger than the cutoff (its upload came just before its commit).
    pub async fn remove_orphan_artifacts(&self, written_before_ms: i64) -> Result<usize, StoreError> {
        let Some(store) = &self.artifact_objects else { return Ok(0) };
        let stored = store.list_artifacts().await?;
        if stored.is_empty() {
            return Ok(0);
        }
        let named: std::collections::HashSet<(String, String, String)> = on_db!(self.db, |pool, d| {
            sqlx::query_as("SELECT inspection_id, kind, object_sha256 FROM artifacts WHERE object_sha256 IS NOT NULL")
                .fetch_all(pool)
                .await?
        })
        .into_iter()
        .collect();
        let mut removed = 0;
        for (key, written_ms) in stored {
            let is_named = named.contains(&(key.inspection_id.clone(), key.kind.clone(), key.sha256.clone()));
            if !is_named && written_ms < written_before_ms {
                store.remove_artifact(&key).await?;
                removed += 1;
            }
        }
        Ok(removed)
    }

    /// When the retention deleted this inspection's meshes and images, if it did.
    pub async fn artifacts_purged_at(&self, id: &str) -> Result<Option<i64>, StoreError> {
        let row: Option<(Option<i64>,)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql("SELECT artifacts_purged_at FROM inspections WHERE id = ?"))
                .bind(id)
                .fetch_optional(pool)
                .await?
        });
        Ok(row.and_then(|r| r.0))
    }

    /// Every upload whose bytes are kept (not purged), by hash: its sha256 and size.
    pub async fn live_uploads(&self) -> Result<Vec<(String, i64)>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as("SELECT sha256, size_bytes FROM uploads WHERE purged_at IS NULL ORDER BY sha256")
                .fetch_all(pool)
                .await?
        }))
    }

    /// Deletes uploaded bundles whose inspections all finished before `cutoff_ms`.
    pub async fn purge_uploads(&self, cutoff_ms: i64) -> Result<usize, StoreError> {
        let due: Vec<(String,)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT u.sha256 FROM uploads u WHERE u.purged_at IS NULL AND NOT EXISTS (SELECT 1 FROM inspections i \
                 WHERE i.upload_sha256 = u.sha256 AND (i.finished_at IS NULL OR i.finished_at >= ?))",
            ))
            .bind(cutoff_ms)
            .fetch_all(pool)
            .await?
        });
        let mut purged = 0;
        for (sha,) in &due {
            // Re-checked and deleted under the lock a submission places its file under (SQLite's
            // write lock, PostgreSQL's lock on the hash): an upload of the same bundle accepted
            // since the SELECT keeps its file.
            purged += on_db!(self.db, |pool, d| {
                let mut tx = pool.begin_with(d.begin_write()).await?;
                if let Some(lock) = d.lock_key() {
                    sqlx::query(lock).bind(sha).execute(&mut *tx).await?;
                }
                let marked = sqlx::query(&d.sql(
                    "UPDATE uploads SET purged_at = ? WHERE sha256 = ? AND purged_at IS NULL AND NOT EXISTS (SELECT 1 \
                     FROM inspections i WHERE i.upload_sha256 = uploads.sha256 AND (i.finished_at IS NULL OR \
                     i.finished_at >= ?))",
                ))
                .bind(now_ms())
                .bind(sha)
                .bind(cutoff_ms)
                .execute(&mut *tx)
                .await?
                .rows_affected()
                    == 1;
                if marked {
                    self.blobs.remove(sha).await?;
                }
                tx.commit().await?;
                usize::from(marked)
            });
        }
        Ok(purged)
    }
}
