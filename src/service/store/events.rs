//! The status events the triggers record (migration `events`), and the MQTT publisher's cursor
//! over them: one process at a time publishes, under a lease on the cursor's row.

use super::*;

/// One status an inspection or a station took.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct EventRow {
    pub seq: i64,
    /// `inspection` or `station`.
    pub subject_kind: String,
    /// The inspection's id or the station's name.
    pub subject: String,
    pub status: String,
    pub at: i64,
}

impl Store {
    /// The events after `seq`, oldest first, at most `limit`.
    pub async fn events_after(&self, seq: i64, limit: i64) -> Result<Vec<EventRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(
                &d.sql("SELECT seq, subject_kind, subject, status, at FROM events WHERE seq > ? ORDER BY seq LIMIT ?"),
            )
            .bind(seq)
            .bind(limit)
            .fetch_all(pool)
            .await?
        }))
    }

    /// Takes (or renews) the publisher's lease for `owner`; its delivered position when this
    /// process holds it, None while another does. A cursor never set starts at the events' end:
    /// a publisher turned on later does not replay history.
    pub async fn mqtt_lease(&self, owner: &str, lease: Duration) -> Result<Option<i64>, StoreError> {
        let now = now_ms();
        let held: Option<(Option<i64>,)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "UPDATE mqtt_cursor SET lease_owner = ?, lease_expires_at = ?, \
                 delivered_seq = COALESCE(delivered_seq, (SELECT COALESCE(MAX(seq), 0) FROM events)) \
                 WHERE id = 1 AND (lease_owner IS NULL OR lease_owner = ? OR lease_expires_at < ?) \
                 RETURNING delivered_seq",
            ))
            .bind(owner)
            .bind(now + lease.as_millis() as i64)
            .bind(owner)
            .bind(now)
            .fetch_optional(pool)
            .await?
        });
        Ok(held.map(|(seq,)| seq.unwrap_or(0)))
    }

    /// Sets a cursor never set to the events' end, now: a publisher turned on starts from the
    /// moment its process starts (before it serves), not from history, and not from whenever its
    /// task first runs.
    pub async fn mqtt_start_cursor(&self) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query(
                "UPDATE mqtt_cursor SET delivered_seq = (SELECT COALESCE(MAX(seq), 0) FROM events) \
                 WHERE id = 1 AND delivered_seq IS NULL",
            )
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// Records that every event up to `seq` was delivered (acknowledged by the broker); false
    /// where `owner` no longer holds the lease.
    pub async fn mqtt_delivered(&self, owner: &str, seq: i64) -> Result<bool, StoreError> {
        let updated = on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql("UPDATE mqtt_cursor SET delivered_seq = ? WHERE id = 1 AND lease_owner = ?"))
                .bind(seq)
                .bind(owner)
                .execute(pool)
                .await?
                .rows_affected()
        });
        Ok(updated == 1)
    }

    /// Gives the lease up (a stopping process), so another publishes at once.
    pub async fn mqtt_release(&self, owner: &str) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query(
                &d.sql("UPDATE mqtt_cursor SET lease_owner = NULL, lease_expires_at = NULL WHERE lease_owner = ?"),
            )
            .bind(owner)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// Deletes events recorded before `before_ms` that the publisher has delivered (all of them
    /// where no publisher ever ran); how many.
    pub async fn purge_events(&self, before_ms: i64) -> Result<u64, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "DELETE FROM events WHERE at < ? AND seq <= COALESCE((SELECT delivered_seq FROM mqtt_cursor \
                 WHERE id = 1), seq)",
            ))
            .bind(before_ms)
            .execute(pool)
            .await?
            .rows_affected()
        }))
    }
}
