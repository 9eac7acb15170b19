//! CMM measurements stored beside an inspection, every upload as a version.

use super::*;

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct CmmRow {
    pub version: i64,
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub points_json: String,
    pub uploaded_at: i64,
    pub uploaded_by: Option<String>,
}

/// One stored version without its points.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct CmmVersionRow {
    pub version: i64,
    pub instrument: Option<String>,
    pub measured_at: Option<String>,
    pub uploaded_at: i64,
    pub uploaded_by: Option<String>,
    pub points: i64,
}

impl Store {
    /// Stores an upload as the inspection's next version (earlier ones are kept); returns it.
    pub async fn put_cmm(
        &self,
        id: &str,
        cmm: &crate::eval::cmm::CmmMeasurements,
        uploaded_by: Option<&str>,
    ) -> Result<i64, StoreError> {
        // One statement, so two uploads at once cannot take the same number (the primary key
        // would refuse the second rather than overwrite).
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_scalar(&d.sql(
                "INSERT INTO cmm_versions (inspection_id, version, instrument, measured_at, points_json, uploaded_at, \
                 uploaded_by) SELECT ?1, COALESCE(MAX(version), 0) + 1, ?2, ?3, ?4, ?5, ?6 FROM cmm_versions \
                 WHERE inspection_id = ?1 RETURNING version",
            ))
            .bind(id)
            .bind(&cmm.instrument)
            .bind(&cmm.measured_at)
            .bind(serde_json::to_string(&cmm.points).expect("points serialise"))
            .bind(now_ms())
            .bind(uploaded_by)
            .fetch_one(pool)
            .await?
        }))
    }

    /// The latest version, or the one asked for.
    pub async fn cmm(&self, id: &str, version: Option<i64>) -> Result<CmmRow, StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT version, instrument, measured_at, points_json, uploaded_at, uploaded_by FROM cmm_versions \
                 WHERE inspection_id = ?1 AND (?2 IS NULL OR version = ?2) ORDER BY version DESC LIMIT 1",
            ))
            .bind(id)
            .bind(version)
            .fetch_optional(pool)
            .await?
        })
        .ok_or(StoreError::NotFound)
    }

    /// Every version, oldest first.
    pub async fn cmm_versions(&self, id: &str) -> Result<Vec<CmmVersionRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(&format!(
                "SELECT version, instrument, measured_at, uploaded_at, uploaded_by, {} AS points \
                 FROM cmm_versions WHERE inspection_id = ? ORDER BY version",
                d.json_array_length("points_json")
            )))
            .bind(id)
            .fetch_all(pool)
            .await?
        }))
    }
}
