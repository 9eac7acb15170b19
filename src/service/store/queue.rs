//! The job queue: claim the oldest due job (or one whose lease lapsed), heartbeat the lease, and
//! complete exactly once (success with results, failure, cancellation, or back to the queue).

use super::*;

/// A claimed job.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct Claimed {
    pub id: String,
    pub upload_sha256: String,
    pub options_json: String,
    pub attempts: i64,
    pub max_attempts: i64,
    /// Claims of this job that ended with its worker's process dying.
    pub interruptions: i64,
}

impl Claimed {
    /// Attempts that ended in a retryable failure (or this one): claims less interruptions. A
    /// crash of the process is not counted against the job.
    pub fn failed_attempts(&self) -> i64 {
        self.attempts - self.interruptions
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Heartbeat {
    Held {
        cancel_requested: bool,
    },
    /// The lease expired and another worker (or nobody) owns the job now.
    Lost,
}

fn poisonous_problem(interruptions: i64) -> String {
    let problem = Problem::new(
        Code::JobPoisonous,
        format!(
            "the worker's process died while running this job {interruptions} times; it is not run again \
             (max_interruptions)"
        ),
        None,
    );
    serde_json::to_string(&problem).expect("a problem serialises")
}

impl Store {
    /// Atomically claims the oldest available job: queued and due, or running with a lapsed lease.
    pub async fn claim(&self, owner: &str, lease: Duration) -> Result<Option<Claimed>, StoreError> {
        let now = now_ms();
        // A lapsed lease means the process running the job died. That is counted as an interruption
        // (not an attempt); a job whose process died `max_interruptions` times is failed as
        // poisonous instead of taking the node down again.
        let poisonous: Vec<(String, i64)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT id, interruptions + 1 FROM inspections \
                 WHERE status = 'running' AND cancel_requested = FALSE AND lease_expires_at < ? \
                 AND interruptions + 1 >= ?",
            ))
            .bind(now)
            .bind(self.max_interruptions)
            .fetch_all(pool)
            .await?
        });
        for (id, interruptions) in poisonous {
            on_db!(self.db, |pool, d| {
                sqlx::query(&d.sql(
                    "UPDATE inspections SET status = 'failed', finished_at = ?, updated_at = ?, lease_owner = NULL, \
                     lease_expires_at = NULL, interruptions = ?, error_json = ? \
                     WHERE id = ? AND status = 'running' AND lease_expires_at < ?",
                ))
                .bind(now)
                .bind(now)
                .bind(interruptions)
                .bind(poisonous_problem(interruptions))
                .bind(&id)
                .bind(now)
                .execute(pool)
                .await?;
            });
            self.publish(&id).await;
        }
        // Under PostgreSQL the pick skips rows another claimer holds: without it two workers
        // could pick one job and the second, re-reading only its id, take it again.
        let claimed = on_db!(self.db, |pool, d| {
            sqlx::query_as::<_, Claimed>(&d.sql(&format!(
                "UPDATE inspections SET interruptions = interruptions + CASE WHEN status = 'running' THEN 1 ELSE 0 END, \
                 status = 'running', lease_owner = ?, lease_expires_at = ?, \
                 attempts = attempts + 1, started_at = COALESCE(started_at, ?), updated_at = ?, \
                 progress_stage = NULL, progress_fraction = NULL \
                 WHERE id = (SELECT id FROM inspections WHERE cancel_requested = FALSE AND \
                   ((status = 'queued' AND available_at <= ?) OR (status = 'running' AND lease_expires_at < ?)) \
                   ORDER BY id LIMIT 1{}) \
                 RETURNING id, upload_sha256, options_json, attempts, max_attempts, interruptions",
                d.skip_locked()
            )))
            .bind(owner)
            .bind(now + lease.as_millis() as i64)
            .bind(now)
            .bind(now)
            .bind(now)
            .bind(now)
            .fetch_optional(pool)
            .await?
        });
        // A running job whose worker died after a cancel request: cancel it now.
        let canceled: Vec<(String,)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "UPDATE inspections SET status = 'canceled', finished_at = ?, updated_at = ?, lease_owner = NULL, \
                 lease_expires_at = NULL WHERE status = 'running' AND cancel_requested = TRUE AND lease_expires_at < ? \
                 RETURNING id",
            ))
            .bind(now)
            .bind(now)
            .bind(now)
            .fetch_all(pool)
            .await?
        });
        for (id,) in canceled {
            self.publish(&id).await;
        }
        if let Some(job) = &claimed {
            self.publish(&job.id).await;
        }
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
        let row: Option<(bool,)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "UPDATE inspections SET lease_expires_at = ?, updated_at = ?, \
                 progress_stage = COALESCE(?, progress_stage), progress_fraction = COALESCE(?, progress_fraction) \
                 WHERE id = ? AND lease_owner = ? AND status = 'running' RETURNING cancel_requested",
            ))
            .bind(now + lease.as_millis() as i64)
            .bind(now)
            .bind(progress.map(|p| p.0))
            .bind(progress.map(|p| p.1))
            .bind(id)
            .bind(owner)
            .fetch_optional(pool)
            .await?
        });
        if row.is_some() && progress.is_some() {
            self.publish(id).await;
        }
        Ok(match row {
            Some((cancel_requested,)) => Heartbeat::Held { cancel_requested },
            None => Heartbeat::Lost,
        })
    }

    /// Stores the results and marks the job succeeded, in one transaction, only if this worker
    /// still holds the lease (so a job finishes exactly once). Returns false when it did not.
    pub async fn complete_success(&self, id: &str, owner: &str, results: &JobResults) -> Result<bool, StoreError> {
        let now = now_ms();
        let rows: Vec<(u32, f64, Option<f64>, Option<f64>)> = results
            .report
            .threads
            .iter()
            .flat_map(|t| {
                let h = &t.height_mm;
                (0..h.angles_deg.len())
                    .map(move |k| (t.index, h.angles_deg[k], h.values[k], h.uncertainty_mm.get(k).copied().flatten()))
            })
            .collect();
        // Where an object store holds meshes and images, they are uploaded before the commit that
        // names them, so that a committed row never points at nothing; an upload whose commit
        // does not follow is an orphan the retention pass deletes.
        let mut object_sha256 = vec![None; results.artifacts.len()];
        if let Some(store) = &self.artifact_objects {
            for (a, sha) in results.artifacts.iter().zip(&mut object_sha256) {
                let key = blobs::ArtifactKey {
                    inspection_id: id.into(),
                    kind: a.kind.into(),
                    sha256: super::files::sha256_hex(&a.body),
                };
                store.put_artifact(&key, a.body.clone()).await?;
                *sha = Some(key.sha256);
            }
        }
        let done = on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            let updated = sqlx::query(&d.sql(
                "UPDATE inspections SET status = 'succeeded', verdict = ?, review_required = ?, decision = ?, \
                 finished_at = ?, updated_at = ?, lease_owner = NULL, lease_expires_at = NULL, progress_fraction = 1.0, \
                 error_json = NULL WHERE id = ? AND lease_owner = ? AND status = 'running'",
            ))
            .bind(results.verdict)
            .bind(results.report.review_required)
            .bind(results.report.decision.as_str())
            .bind(now)
            .bind(now)
            .bind(id)
            .bind(owner)
            .execute(&mut *tx)
            .await?;
            if updated.rows_affected() == 0 {
                tx.rollback().await?;
                false
            } else {
                sqlx::query(&d.sql("INSERT INTO reports (inspection_id, report_json, etag) VALUES (?, ?, ?)"))
                    .bind(id)
                    .bind(&results.report_json)
                    .bind(etag_of(results.report_json.as_bytes()))
                    .execute(&mut *tx)
                    .await?;
                for (a, sha) in results.artifacts.iter().zip(&object_sha256) {
                    sqlx::query(&d.sql(
                        "INSERT INTO artifacts (inspection_id, kind, content_type, body, etag, object_sha256) \
                         VALUES (?, ?, ?, ?, ?, ?)",
                    ))
                    .bind(id)
                    .bind(a.kind)
                    .bind(a.content_type)
                    .bind(if sha.is_some() { &[][..] } else { &a.body[..] })
                    .bind(etag_of(&a.body))
                    .bind(sha.as_deref())
                    .execute(&mut *tx)
                    .await?;
                }
                for t in &results.report.threads {
                    sqlx::query(&d.sql(
                        "INSERT INTO threads (inspection_id, thread_index, crest_z_start_mm, crest_z_end_mm, \
                         min_height_mm, mean_height_mm, max_height_mm, bins_measured, black_crest_length_mm, \
                         black_crest_arcs_json, mean_height_uncertainty_mm, height_finding) \
                         VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    ))
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
                    .bind(t.height_finding.as_ref().and_then(|f| f.uncertainty_mm))
                    .bind(t.height_finding.as_ref().map(|f| f.finding.as_str()))
                    .execute(&mut *tx)
                    .await?;
                }
                tx.insert_heights(id, &rows).await?;
                tx.commit().await?;
                true
            }
        });
        if done {
            self.publish(id).await;
        }
        Ok(done)
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
        let updated = on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "UPDATE inspections SET status = ?, finished_at = ?, updated_at = ?, lease_owner = NULL, \
                 lease_expires_at = NULL, error_json = ? WHERE id = ? AND lease_owner = ? AND status = 'running'",
            ))
            .bind(status.as_str())
            .bind(now)
            .bind(now)
            .bind(problem_json)
            .bind(id)
            .bind(owner)
            .execute(pool)
            .await?
            .rows_affected()
        });
        if updated == 1 {
            self.publish(id).await;
        }
        Ok(updated == 1)
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
        let updated = on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "UPDATE inspections SET status = CASE WHEN cancel_requested THEN 'canceled' ELSE 'queued' END, \
                 finished_at = CASE WHEN cancel_requested THEN ? ELSE NULL END, available_at = ?, updated_at = ?, \
                 lease_owner = NULL, lease_expires_at = NULL, error_json = COALESCE(?, error_json), attempts = attempts - ?, \
                 progress_stage = NULL, progress_fraction = NULL WHERE id = ? AND lease_owner = ? AND status = 'running'",
            ))
            .bind(now)
            .bind(now + delay.as_millis() as i64)
            .bind(now)
            .bind(problem_json)
            .bind(refund_attempt as i64)
            .bind(id)
            .bind(owner)
            .execute(pool)
            .await?
            .rows_affected()
        });
        if updated == 1 {
            self.publish(id).await;
        }
        Ok(updated == 1)
    }

    /// Jobs waiting (queued) and running.
    pub async fn queue_depth(&self) -> Result<(i64, i64), StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(
                "SELECT COUNT(CASE WHEN status = 'queued' THEN 1 END), COUNT(CASE WHEN status = 'running' THEN 1 END) \
                 FROM inspections WHERE status IN ('queued', 'running')",
            )
            .fetch_one(pool)
            .await?
        }))
    }
}

/// One inspection's per-bin heights (thread, angle, height, uncertainty), inserted as each backend
/// takes them fastest.
trait InsertHeights {
    async fn insert_heights(
        &mut self,
        id: &str,
        rows: &[(u32, f64, Option<f64>, Option<f64>)],
    ) -> Result<(), sqlx::Error>;
}

impl InsertHeights for sqlx::Transaction<'_, sqlx::Sqlite> {
    async fn insert_heights(
        &mut self,
        id: &str,
        rows: &[(u32, f64, Option<f64>, Option<f64>)],
    ) -> Result<(), sqlx::Error> {
        // 5 parameters a row; SQLite allows 32 766 per statement.
        for chunk in rows.chunks(2000) {
            let mut q = QueryBuilder::<sqlx::Sqlite>::new(
                "INSERT INTO thread_heights (inspection_id, thread_index, angle_deg, height_mm, uncertainty_mm) ",
            );
            q.push_values(chunk, |mut b, (t, a, h, u)| {
                b.push_bind(id).push_bind(*t as i64).push_bind(*a).push_bind(*h).push_bind(*u);
            });
            q.build().execute(&mut **self).await?;
        }
        Ok(())
    }
}

impl InsertHeights for sqlx::Transaction<'_, sqlx::Postgres> {
    async fn insert_heights(
        &mut self,
        id: &str,
        rows: &[(u32, f64, Option<f64>, Option<f64>)],
    ) -> Result<(), sqlx::Error> {
        // One statement of four arrays: a statement of thousands of parameters cost PostgreSQL
        // tens of ms to parse and plan, each time.
        sqlx::query(
            "INSERT INTO thread_heights (inspection_id, thread_index, angle_deg, height_mm, uncertainty_mm) \
             SELECT $1, * FROM UNNEST($2::BIGINT[], $3::DOUBLE PRECISION[], $4::DOUBLE PRECISION[], \
             $5::DOUBLE PRECISION[])",
        )
        .bind(id)
        .bind(rows.iter().map(|r| r.0 as i64).collect::<Vec<i64>>())
        .bind(rows.iter().map(|r| r.1).collect::<Vec<f64>>())
        .bind(rows.iter().map(|r| r.2).collect::<Vec<Option<f64>>>())
        .bind(rows.iter().map(|r| r.3).collect::<Vec<Option<f64>>>())
        .execute(&mut **self)
        .await?;
        Ok(())
    }
}
