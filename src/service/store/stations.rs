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

/// A check run as charted.
#[derive(Clone, Debug, sqlx::FromRow)]
pub struct CheckRow {
    pub station: String,
    pub study_id: String,
    pub seq: i64,
    pub inspection_id: String,
    pub master: String,
    pub points_json: String,
    pub violation_json: Option<String>,
    pub created_at: i64,
}

/// What recording a check came to.
#[derive(Clone, Debug)]
pub enum CheckRecorded {
    /// Charted; `suspended` when its violation suspended the station.
    Charted { row: CheckRow, suspended: bool },
    /// This inspection is charted under this study already.
    Exists,
    /// The station's study in force is no longer the one the check was judged against.
    StudyChanged,
}

/// What the caller judges a new check with, inside the transaction that records it: the earlier
/// checks under the same study, oldest first.
pub struct CheckJudgement {
    pub points_json: String,
    /// The violation (JSON) and the suspension reason, if the check broke a rule.
    pub violation: Option<(String, String)>,
}

const SELECT_CHECK: &str =
    "SELECT station, study_id, seq, inspection_id, master, points_json, violation_json, created_at FROM checks";

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
        let inserted = on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "INSERT INTO stations (name, description, status, created_at, updated_at) \
                 VALUES (?, ?, 'unqualified', ?, ?) ON CONFLICT (name) DO NOTHING",
            ))
            .bind(name)
            .bind(description)
            .bind(now)
            .bind(now)
            .execute(pool)
            .await?
            .rows_affected()
        });
        if inserted == 0 {
            return Ok(None);
        }
        self.station(name).await.map(Some)
    }

    pub async fn station(&self, name: &str) -> Result<StationRow, StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(&format!("{SELECT_STATION} WHERE name = ?"))).bind(name).fetch_optional(pool).await?
        })
        .ok_or(StoreError::NotFound)
    }

    pub async fn stations(&self) -> Result<Vec<StationRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(&format!("{SELECT_STATION} ORDER BY name LIMIT 1000")).fetch_all(pool).await?
        }))
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
        let inserted = on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "INSERT INTO masters (station, serial, certificate_json, instrument, calibrated_at, uncertainty_mm, \
                 uploaded_at) VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (station, serial) DO NOTHING",
            ))
            .bind(station)
            .bind(serial)
            .bind(certificate_json)
            .bind(instrument)
            .bind(calibrated_at)
            .bind(uncertainty_mm)
            .bind(now_ms())
            .execute(pool)
            .await?
            .rows_affected()
        });
        Ok(inserted == 1)
    }

    pub async fn masters(&self, station: &str) -> Result<Vec<MasterRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT serial, certificate_json, instrument, calibrated_at, uncertainty_mm, uploaded_at FROM masters \
                 WHERE station = ? ORDER BY serial",
            ))
            .bind(station)
            .fetch_all(pool)
            .await?
        }))
    }

    /// Stores a study and puts the station in force under it (qualified), in one transaction.
    pub async fn put_study(&self, row: &StudyRow) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            sqlx::query(&d.sql(
                "INSERT INTO studies (id, station, inspections_json, qualification_json, created_at) \
                 VALUES (?, ?, ?, ?, ?)",
            ))
            .bind(&row.id)
            .bind(&row.station)
            .bind(&row.inspections_json)
            .bind(&row.qualification_json)
            .bind(row.created_at)
            .execute(&mut *tx)
            .await?;
            sqlx::query(&d.sql(
                "UPDATE stations SET status = 'qualified', status_reason = NULL, study_id = ?, updated_at = ? \
                 WHERE name = ?",
            ))
            .bind(&row.id)
            .bind(now_ms())
            .bind(&row.station)
            .execute(&mut *tx)
            .await?;
            tx.commit().await?;
        });
        Ok(())
    }

    pub async fn study(&self, station: &str, id: &str) -> Result<StudyRow, StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT id, station, inspections_json, qualification_json, created_at FROM studies \
                 WHERE station = ? AND id = ?",
            ))
            .bind(station)
            .bind(id)
            .fetch_optional(pool)
            .await?
        })
        .ok_or(StoreError::NotFound)
    }

    /// Suspends a station, with the reason (drift, an operator's word).
    pub async fn suspend_station(&self, station: &str, reason: &str) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query(
                &d.sql("UPDATE stations SET status = 'suspended', status_reason = ?, updated_at = ? WHERE name = ?"),
            )
            .bind(reason)
            .bind(now_ms())
            .bind(station)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// The checks charted under `study`, oldest first.
    pub async fn checks(&self, station: &str, study: &str) -> Result<Vec<CheckRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(&format!("{SELECT_CHECK} WHERE station = ? AND study_id = ? ORDER BY seq")))
                .bind(station)
                .bind(study)
                .fetch_all(pool)
                .await?
        }))
    }

    /// Records a check under `study` in one write transaction: `judge` sees the study's earlier
    /// checks and says what the new one reads and whether it broke a rule; a violation suspends
    /// the station (if still qualified under `study`) and writes `deliveries(reason)` to the
    /// webhook outbox under the check's inspection, all or nothing. Checks of one station are
    /// charted one at a time (SQLite's write lock; PostgreSQL's lock on the station's row).
    pub async fn add_check(
        &self,
        station: &str,
        study: &str,
        inspection_id: &str,
        master: &str,
        judge: impl FnOnce(&[CheckRow]) -> CheckJudgement,
        deliveries: impl FnOnce(&str) -> Vec<super::NewDelivery>,
    ) -> Result<CheckRecorded, StoreError> {
        let now = now_ms();
        on_db!(self.db, |pool, d| {
            let mut tx = pool.begin_with(d.begin_write()).await?;
            let in_force: Option<(Option<String>,)> =
                sqlx::query_as(&d.sql(&format!("SELECT study_id FROM stations WHERE name = ?{}", d.for_update())))
                    .bind(station)
                    .fetch_optional(&mut *tx)
                    .await?;
            if in_force.and_then(|r| r.0).as_deref() != Some(study) {
                return Ok(CheckRecorded::StudyChanged);
            }
            let earlier: Vec<CheckRow> =
                sqlx::query_as(&d.sql(&format!("{SELECT_CHECK} WHERE station = ? AND study_id = ? ORDER BY seq")))
                    .bind(station)
                    .bind(study)
                    .fetch_all(&mut *tx)
                    .await?;
            if earlier.iter().any(|c| c.inspection_id == inspection_id) {
                return Ok(CheckRecorded::Exists);
            }
            let judgement = judge(&earlier);
            let row = CheckRow {
                station: station.into(),
                study_id: study.into(),
                seq: earlier.last().map_or(1, |c| c.seq + 1),
                inspection_id: inspection_id.into(),
                master: master.into(),
                points_json: judgement.points_json,
                violation_json: judgement.violation.as_ref().map(|v| v.0.clone()),
                created_at: now,
            };
            sqlx::query(&d.sql(
                "INSERT INTO checks (station, study_id, seq, inspection_id, master, points_json, violation_json, \
                 created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            ))
            .bind(&row.station)
            .bind(&row.study_id)
            .bind(row.seq)
            .bind(&row.inspection_id)
            .bind(&row.master)
            .bind(&row.points_json)
            .bind(&row.violation_json)
            .bind(row.created_at)
            .execute(&mut *tx)
            .await?;
            let mut suspended = false;
            if let Some((_, reason)) = &judgement.violation {
                suspended = sqlx::query(&d.sql(
                    "UPDATE stations SET status = 'suspended', status_reason = ?, updated_at = ? \
                     WHERE name = ? AND study_id = ? AND status = 'qualified'",
                ))
                .bind(reason)
                .bind(now)
                .bind(station)
                .bind(study)
                .execute(&mut *tx)
                .await?
                .rows_affected()
                    == 1;
                if suspended {
                    for delivery in deliveries(reason) {
                        super::webhooks::insert_delivery!(&mut *tx, d, inspection_id, &delivery, now);
                    }
                }
            }
            tx.commit().await?;
            Ok(CheckRecorded::Charted { row, suspended })
        })
    }
}
