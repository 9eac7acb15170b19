//! The webhook outbox: inspections whose terminal state is not yet turned into deliveries, the
//! deliveries (claimed under a lease, attempted, completed exactly once per attempt) and their
//! attempts' record.

use super::inspections::SELECT_INSPECTION;
use super::*;

/// A delivery to write for an inspection's terminal state.
#[derive(Clone, Debug)]
pub struct NewDelivery {
    pub id: String,
    pub endpoint: String,
    pub url: String,
    pub event_type: String,
    pub payload_json: String,
}

/// A delivery as stored.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct DeliveryRow {
    pub id: String,
    pub inspection_id: String,
    pub endpoint: String,
    pub url: String,
    pub event_type: String,
    pub payload_json: String,
    pub status: String,
    pub attempts: i64,
    pub created_at: i64,
    pub next_attempt_at: i64,
    pub delivered_at: Option<i64>,
    pub last_error: Option<String>,
}

/// One attempt's record.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct AttemptRow {
    pub delivery_id: String,
    pub attempt: i64,
    pub started_at: i64,
    pub duration_ms: i64,
    pub status_code: Option<i64>,
    pub error: Option<String>,
}

/// What an attempt came to.
#[derive(Clone, Debug, PartialEq)]
pub enum AttemptOutcome {
    Delivered,
    /// Failed; tried again at this time (ms since the epoch).
    RetryAt(i64),
    /// Failed for good: out of attempts, or the destination is no longer configured or allowed.
    GaveUp,
}

#[derive(Clone, Debug, Default)]
pub struct DeliveryFilter {
    pub inspection_id: Option<String>,
    pub status: Option<String>,
    pub limit: u32,
}

const DELIVERY_COLUMNS: &str = "id, inspection_id, endpoint, url, event_type, payload_json, status, attempts, \
     created_at, next_attempt_at, delivered_at, last_error";

/// Writes one pending delivery under `inspection_id` on the transaction `$tx` of dialect `$d`
/// (once per inspection, endpoint and event: a second write of it is a no-op). A macro, so that
/// it runs inside either backend's transaction.
macro_rules! insert_delivery {
    ($tx:expr, $d:expr, $inspection_id:expr, $delivery:expr, $now:expr) => {{
        let delivery: &$crate::service::store::NewDelivery = $delivery;
        sqlx::query(&$d.sql(
            "INSERT INTO webhook_deliveries (id, inspection_id, endpoint, url, event_type, payload_json, status, \
             attempts, created_at, next_attempt_at) VALUES (?, ?, ?, ?, ?, ?, 'pending', 0, ?, ?) \
             ON CONFLICT (inspection_id, endpoint, event_type) DO NOTHING",
        ))
        .bind(&delivery.id)
        .bind($inspection_id)
        .bind(&delivery.endpoint)
        .bind(&delivery.url)
        .bind(&delivery.event_type)
        .bind(&delivery.payload_json)
        .bind($now)
        .bind($now)
        .execute($tx)
        .await?;
    }};
}
pub(super) use insert_delivery;

impl Store {
    /// Terminal inspections whose deliveries are not written yet, oldest first.
    pub async fn unannounced(&self, limit: u32) -> Result<Vec<InspectionRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as::<_, InspectionRow>(&d.sql(&format!(
                "{SELECT_INSPECTION} WHERE i.webhooks_enqueued = FALSE \
                 AND i.status IN ('succeeded', 'failed', 'canceled') ORDER BY i.id LIMIT ?"
            )))
            .bind(limit as i64)
            .fetch_all(pool)
            .await?
        }))
    }

    /// Writes an inspection's deliveries and marks it announced, in one transaction; false (and
    /// nothing written) when another process announced it first.
    pub async fn announce(&self, inspection_id: &str, deliveries: &[NewDelivery]) -> Result<bool, StoreError> {
        let now = now_ms();
        Ok(on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            let marked = sqlx::query(
                &d.sql("UPDATE inspections SET webhooks_enqueued = TRUE WHERE id = ? AND webhooks_enqueued = FALSE"),
            )
            .bind(inspection_id)
            .execute(&mut *tx)
            .await?;
            if marked.rows_affected() == 0 {
                tx.rollback().await?;
                false
            } else {
                for delivery in deliveries {
                    insert_delivery!(&mut *tx, d, inspection_id, delivery, now);
                }
                tx.commit().await?;
                true
            }
        }))
    }

    /// Claims up to `limit` due deliveries (pending, due, and not held under a live lease).
    pub async fn claim_deliveries(
        &self,
        owner: &str,
        lease: Duration,
        limit: u32,
    ) -> Result<Vec<DeliveryRow>, StoreError> {
        let now = now_ms();
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as::<_, DeliveryRow>(&d.sql(&format!(
                "UPDATE webhook_deliveries SET lease_owner = ?, lease_expires_at = ? WHERE id IN \
                 (SELECT id FROM webhook_deliveries WHERE status = 'pending' AND next_attempt_at <= ? \
                  AND (lease_expires_at IS NULL OR lease_expires_at < ?) ORDER BY next_attempt_at, id LIMIT ?{}) \
                 RETURNING {DELIVERY_COLUMNS}",
                d.skip_locked()
            )))
            .bind(owner)
            .bind(now + lease.as_millis() as i64)
            .bind(now)
            .bind(now)
            .bind(limit as i64)
            .fetch_all(pool)
            .await?
        }))
    }

    /// Records an attempt and its outcome, if `owner` still holds the delivery's lease (false when
    /// it lapsed and another process took the delivery over).
    pub async fn record_attempt(
        &self,
        owner: &str,
        attempt: &AttemptRow,
        outcome: &AttemptOutcome,
    ) -> Result<bool, StoreError> {
        let now = now_ms();
        let (status, next_at) = match outcome {
            AttemptOutcome::Delivered => ("delivered", now),
            AttemptOutcome::RetryAt(at) => ("pending", *at),
            AttemptOutcome::GaveUp => ("failed", now),
        };
        Ok(on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            let updated = sqlx::query(&d.sql(
                "UPDATE webhook_deliveries SET status = ?, attempts = ?, next_attempt_at = ?, lease_owner = NULL, \
                 lease_expires_at = NULL, delivered_at = CASE WHEN ? = 'delivered' THEN ? ELSE NULL END, \
                 last_error = ? WHERE id = ? AND lease_owner = ? AND status = 'pending'",
            ))
            .bind(status)
            .bind(attempt.attempt)
            .bind(next_at)
            .bind(status)
            .bind(now)
            .bind(&attempt.error)
            .bind(&attempt.delivery_id)
            .bind(owner)
            .execute(&mut *tx)
            .await?;
            if updated.rows_affected() == 0 {
                tx.rollback().await?;
                false
            } else {
                sqlx::query(&d.sql(
                    "INSERT INTO webhook_attempts (delivery_id, attempt, started_at, duration_ms, status_code, error) \
                     VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (delivery_id, attempt) DO NOTHING",
                ))
                .bind(&attempt.delivery_id)
                .bind(attempt.attempt)
                .bind(attempt.started_at)
                .bind(attempt.duration_ms)
                .bind(attempt.status_code)
                .bind(&attempt.error)
                .execute(&mut *tx)
                .await?;
                tx.commit().await?;
                true
            }
        }))
    }

    /// Deliveries, newest first, with every attempt of each.
    pub async fn deliveries(&self, filter: &DeliveryFilter) -> Result<Vec<(DeliveryRow, Vec<AttemptRow>)>, StoreError> {
        let (rows, attempts): (Vec<DeliveryRow>, Vec<AttemptRow>) = on_db!(self.db, |pool, d| {
            let mut q = QueryBuilder::new(format!("SELECT {DELIVERY_COLUMNS} FROM webhook_deliveries WHERE 1 = 1"));
            if let Some(id) = &filter.inspection_id {
                q.push(" AND inspection_id = ").push_bind(id);
            }
            if let Some(status) = &filter.status {
                q.push(" AND status = ").push_bind(status);
            }
            q.push(" ORDER BY created_at DESC, id DESC LIMIT ").push_bind(filter.limit as i64);
            let rows: Vec<DeliveryRow> = q.build_query_as().fetch_all(pool).await?;
            if rows.is_empty() {
                return Ok(Vec::new());
            }
            // Every listed delivery's attempts in one query (a page holds up to 1000 deliveries).
            let mut q = QueryBuilder::new(
                "SELECT delivery_id, attempt, started_at, duration_ms, status_code, error FROM webhook_attempts \
                 WHERE delivery_id IN (",
            );
            let mut ids = q.separated(", ");
            for row in &rows {
                ids.push_bind(&row.id);
            }
            q.push(") ORDER BY delivery_id, attempt");
            let attempts: Vec<AttemptRow> = q.build_query_as().fetch_all(pool).await?;
            (rows, attempts)
        });
        let mut by_delivery: std::collections::HashMap<String, Vec<AttemptRow>> = std::collections::HashMap::new();
        for a in attempts {
            by_delivery.entry(a.delivery_id.clone()).or_default().push(a);
        }
        Ok(rows
            .into_iter()
            .map(|row| {
                let attempts = by_delivery.remove(&row.id).unwrap_or_default();
                (row, attempts)
            })
            .collect())
    }
}
