//! Stations, their masters with certificates, and the qualification studies run over the masters'
//! inspections (ISO 15530-3).

use super::*;

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct StationRow {
    pub name: String,
    pub description: Option<String>,
    pub status: String,
    pub status_reason: Option<String>,
    pub study_id: Option<String>,
    pub created_at: i64,
    pub updated_at: i64,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct MasterRow {
    pub serial: String,
    pub certificate_json: String,
    pub instrument: String,
    pub calibrated_at: String,
    pub uncertainty_mm: f64,
    pub uploaded_at: i64,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct StudyRow {
    pub id: String,
    pub station: String,
    pub inspections_json: String,
    pub qualification_json: String,
    pub created_at: i64,
}

const SELECT_STATION: &str =
    "SELECT name, description, status, status_reason, study_id, created_at, updated_at FROM stations";

impl Store {
    /// Creates a station, unqualified; None when the name is taken.
    pub async fn create_station(
        &self,
        name: &str,
        description: Option<&str>,
    ) -> Result<Option<StationRow>, StoreError> {
        let now = now_ms();
        let inserted = sqlx::query(
            "INSERT INTO stations (name, description, status, created_at, updated_at) VALUES (?, ?, 'unqualified', ?, ?) \
             ON CONFLICT (name) DO NOTHING",
        )
        .bind(name)
        .bind(description)
        .bind(now)
        .bind(now)
        .execute(&self.pool)
        .await?
        .rows_affected();
        if inserted == 0 {
            return Ok(None);
        }
        self.station(name).await.map(Some)
    }

    pub async fn station(&self, name: &str) -> Result<StationRow, StoreError> {
        sqlx::query_as(&format!("{SELECT_STATION} WHERE name = ?"))
            .bind(name)
            .fetch_optional(&self.pool)
            .await?
            .ok_or(StoreError::NotFound)
    }

    pub async fn stations(&self) -> Result<Vec<StationRow>, StoreError> {
        Ok(sqlx::query_as(&format!("{SELECT_STATION} ORDER BY name LIMIT 1000")).fetch_all(&self.pool).await?)
    }

    /// Stores a master's certificate; false when the station already has a master of this serial
    /// (a certificate is not overwritten: a recalibrated master is uploaded under a new serial).
    pub async fn put_master(
        &self,
        station: &str,
        serial: &str,
        certificate_json: &str,
        instrument: &str,
        calibrated_at: &str,
        uncertainty_mm: f64,
    ) -> Result<bool, StoreError> {
        let inserted = sqlx::query(
            "INSERT INTO masters (station, serial, certificate_json, instrument, calibrated_at, uncertainty_mm, uploaded_at) \
             VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (station, serial) DO NOTHING",
        )
        .bind(station)
        .bind(serial)
        .bind(certificate_json)
        .bind(instrument)
        .bind(calibrated_at)
        .bind(uncertainty_mm)
        .bind(now_ms())
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok(inserted == 1)
    }

    pub async fn masters(&self, station: &str) -> Result<Vec<MasterRow>, StoreError> {
        Ok(sqlx::query_as(
            "SELECT serial, certificate_json, instrument, calibrated_at, uncertainty_mm, uploaded_at FROM masters \
             WHERE station = ? ORDER BY serial",
        )
        .bind(station)
        .fetch_all(&self.pool)
        .await?)
    }

    /// Stores a study and puts the station in force under it (qualified), in one transaction.
    pub async fn put_study(&self, row: &StudyRow) -> Result<(), StoreError> {
        let mut tx = self.pool.begin().await?;
        sqlx::query(
            "INSERT INTO studies (id, station, inspections_json, qualification_json, created_at) VALUES (?, ?, ?, ?, ?)",
        )
        .bind(&row.id)
        .bind(&row.station)
        .bind(&row.inspections_json)
        .bind(&row.qualification_json)
        .bind(row.created_at)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE stations SET status = 'qualified', status_reason = NULL, study_id = ?, updated_at = ? WHERE name = ?",
        )
        .bind(&row.id)
        .bind(now_ms())
        .bind(&row.station)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    pub async fn study(&self, station: &str, id: &str) -> Result<StudyRow, StoreError> {
        sqlx::query_as(
            "SELECT id, station, inspections_json, qualification_json, created_at FROM studies WHERE station = ? AND id = ?",
        )
        .bind(station)
        .bind(id)
        .fetch_optional(&self.pool)
        .await?
        .ok_or(StoreError::NotFound)
    }

    /// Suspends a station, with the reason (drift, an operator's word).
    pub async fn suspend_station(&self, station: &str, reason: &str) -> Result<(), StoreError> {
        sqlx::query("UPDATE stations SET status = 'suspended', status_reason = ?, updated_at = ? WHERE name = ?")
            .bind(reason)
            .bind(now_ms())
            .bind(station)
            .execute(&self.pool)
            .await?;
        Ok(())
    }
}
