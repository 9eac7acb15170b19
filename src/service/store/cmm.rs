//! CMM measurements stored beside an inspection.

use super::*;

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct CmmRow {
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub points_json: String,
    pub uploaded_at: i64,
}

impl Store {
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
}
