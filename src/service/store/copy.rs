//! Moving a single node's records into PostgreSQL (`crestscan migrate-store --to`): every table,
//! in the order its foreign keys need, row by row as the target's schema types them; resumable
//! (a row the target has already is left alone) and verified (each table's rows counted and
//! digested on both sides, independent of order). Where the target has an object store, meshes
//! and images move out of the rows into it on the way ([`canonical`] digests a row alike either
//! way).

use super::*;
use futures_util::TryStreamExt;
use sha2::{Digest, Sha256};
use sqlx::Row;

/// The tables in the order their foreign keys allow. A table of the target's schema missing here
/// is refused by name, so a new table cannot be left behind silently.
pub const TABLES: &[&str] = &[
    "uploads",
    "inspections",
    "reports",
    "artifacts",
    "threads",
    "thread_heights",
    "cmm_versions",
    "api_keys",
    "audit",
    "webhook_deliveries",
    "webhook_attempts",
    "stations",
    "masters",
    "studies",
    "checks",
    "events",
    "mqtt_cursor",
];

/// Rows a batch inserts: columns × rows stays under PostgreSQL's 65 535 parameters, and a batch
/// of artifacts (meshes of a few MB) stays a few hundred MB at most.
const BATCH_ROWS: usize = 100;

/// One table's copy, as counted and digested after it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TableCopy {
    pub table: &'static str,
    /// Rows in the source.
    pub rows: u64,
    /// Rows the target lacked and took now (a resumed copy takes fewer).
    pub inserted: u64,
    /// Rows in the target after the copy.
    pub target_rows: u64,
    /// Whether the source's and the target's rows digest alike (order aside).
    pub identical: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Text,
    Int,
    Real,
    Bool,
    Bytes,
}

#[derive(Clone, Debug, PartialEq)]
enum Value {
    Text(Option<String>),
    Int(Option<i64>),
    Real(Option<f64>),
    Bool(Option<bool>),
    Bytes(Option<Vec<u8>>),
}

impl Value {
    fn read<R: Row>(row: &R, i: usize, kind: Kind) -> Result<Value, sqlx::Error>
    where
        usize: sqlx::ColumnIndex<R>,
        for<'r> Option<String>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
        for<'r> Option<i64>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
        for<'r> Option<f64>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
        for<'r> Option<bool>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
        for<'r> Option<Vec<u8>>: sqlx::Decode<'r, R::Database> + sqlx::Type<R::Database>,
    {
        Ok(match kind {
            Kind::Text => Value::Text(row.try_get(i)?),
            Kind::Int => Value::Int(row.try_get(i)?),
            Kind::Real => Value::Real(row.try_get(i)?),
            Kind::Bool => Value::Bool(row.try_get(i)?),
            Kind::Bytes => Value::Bytes(row.try_get(i)?),
        })
    }

    /// A canonical encoding for the digest: a tag, then the value's bytes.
    fn digest_into(&self, h: &mut Sha256) {
        fn tagged(h: &mut Sha256, tag: u8, bytes: Option<&[u8]>) {
            match bytes {
                None => h.update([0]),
                Some(b) => {
                    h.update([tag]);
                    h.update((b.len() as u64).to_le_bytes());
                    h.update(b);
                }
            }
        }
        match self {
            Value::Text(v) => tagged(h, 1, v.as_deref().map(str::as_bytes)),
            Value::Int(v) => tagged(h, 2, v.map(i64::to_le_bytes).as_ref().map(|b| &b[..])),
            Value::Real(v) => tagged(h, 3, v.map(|x| x.to_bits().to_le_bytes()).as_ref().map(|b| &b[..])),
            Value::Bool(v) => tagged(h, 4, v.map(|x| [x as u8]).as_ref().map(|b| &b[..])),
            Value::Bytes(v) => tagged(h, 5, v.as_deref()),
        }
    }
}

/// An order-independent digest of a table's rows: the count and the wrapping sum of each row's
/// sha256 (its first 16 bytes), so both sides can be read in whatever order each returns.
#[derive(Default, PartialEq, Eq, Debug)]
struct RowsDigest {
    rows: u64,
    sum: u128,
}

impl RowsDigest {
    fn add(&mut self, row: &[Value]) {
        let mut h = Sha256::new();
        for v in row {
            v.digest_into(&mut h);
        }
        let d = h.finalize();
        self.rows += 1;
        self.sum = self.sum.wrapping_add(u128::from_le_bytes(d[..16].try_into().expect("16 bytes")));
    }
}

impl Store {
    /// Copies every record of this (SQLite) store into `target` (PostgreSQL, migrated), table by
    /// table; a row the target has already (by its key) is skipped, so an interrupted copy is run
    /// again to finish. Each table is then counted and digested on both sides.
    pub async fn copy_records_into(
        &self,
        target: &Store,
        mut progress: impl FnMut(&TableCopy),
    ) -> Result<Vec<TableCopy>, StoreError> {
        let (Db::Sqlite(source), Db::Postgres(pg)) = (&self.db, &target.db) else {
            return Err(StoreError::Io(std::io::Error::other("records are copied from SQLite into PostgreSQL")));
        };
        let tables: Vec<String> = sqlx::query_scalar(
            "SELECT table_name::TEXT FROM information_schema.tables WHERE table_schema = current_schema() \
             AND table_type = 'BASE TABLE' AND table_name NOT LIKE '\\_sqlx%' AND table_name <> 'write_probe'",
        )
        .fetch_all(pg)
        .await?;
        if let Some(unknown) = tables.iter().find(|t| !TABLES.contains(&t.as_str())) {
            return Err(StoreError::Io(std::io::Error::other(format!(
                "the target has table {unknown}, which this copy does not know: a newer schema? (copy with the \
                 binary that wrote it)"
            ))));
        }
        let mut copies = Vec::new();
        for &table in TABLES {
            // The MQTT publisher's place is the deployment's own: the target starts from its events'
            // end when its publisher first runs, rather than publishing the source's history.
            if table == "mqtt_cursor" {
                continue;
            }
            let columns: Vec<(String, String)> = sqlx::query_as(
                "SELECT column_name::TEXT, data_type::TEXT FROM information_schema.columns \
                 WHERE table_schema = current_schema() AND table_name = $1 ORDER BY ordinal_position",
            )
            .bind(table)
            .fetch_all(pg)
            .await?;
            let kinds: Vec<Kind> = columns
                .iter()
                .map(|(name, ty)| match ty.as_str() {
                    "text" => Ok(Kind::Text),
                    "bigint" => Ok(Kind::Int),
                    "double precision" => Ok(Kind::Real),
                    "boolean" => Ok(Kind::Bool),
                    "bytea" => Ok(Kind::Bytes),
                    other => Err(StoreError::Io(std::io::Error::other(format!("{table}.{name}: type {other}")))),
                })
                .collect::<Result<_, _>>()?;
            let names = columns.iter().map(|c| c.0.as_str()).collect::<Vec<_>>().join(", ");
            let select = format!("SELECT {names} FROM {table}");

            let moving = table == "artifacts" && target.artifact_objects.is_some();
            // A resumed copy uploads again only what the target lacks.
            let present: std::collections::HashSet<(String, String)> = if moving {
                sqlx::query_as("SELECT inspection_id, kind FROM artifacts").fetch_all(pg).await?.into_iter().collect()
            } else {
                Default::default()
            };
            let mut source_digest = RowsDigest::default();
            let mut inserted = 0u64;
            let mut batch: Vec<Vec<Value>> = Vec::with_capacity(BATCH_ROWS);
            let mut rows = sqlx::query(&select).fetch(source);
            loop {
                let next = rows.try_next().await?;
                if let Some(row) = &next {
                    let mut values = kinds
                        .iter()
                        .enumerate()
                        .map(|(i, k)| Value::read(row, i, *k))
                        .collect::<Result<Vec<_>, _>>()?;
                    source_digest.add(&canonical(table, &columns, &values));
                    if moving {
                        target.move_out_of_row(&columns, &mut values, &present).await?;
                    }
                    batch.push(values);
                }
                if batch.len() == BATCH_ROWS || (next.is_none() && !batch.is_empty()) {
                    inserted += insert_batch(pg, table, &names, &batch).await?;
                    batch.clear();
                }
                if next.is_none() {
                    break;
                }
            }
            drop(rows);
            if table == "audit" || table == "events" {
                // Copied with their numbers: the target's own numbering goes on after them.
                sqlx::query(&format!(
                    "SELECT setval(pg_get_serial_sequence('{table}', 'seq'), COALESCE((SELECT MAX(seq) FROM {table}), 0) \
                     + 1, false)"
                ))
                .execute(pg)
                .await?;
            }
            let mut target_digest = RowsDigest::default();
            let mut rows = sqlx::query(&select).fetch(pg);
            while let Some(row) = rows.try_next().await? {
                let values =
                    kinds.iter().enumerate().map(|(i, k)| Value::read(&row, i, *k)).collect::<Result<Vec<_>, _>>()?;
                target_digest.add(&canonical(table, &columns, &values));
            }
            let copy = TableCopy {
                table,
                rows: source_digest.rows,
                inserted,
                target_rows: target_digest.rows,
                identical: source_digest == target_digest,
            };
            progress(&copy);
            copies.push(copy);
        }
        Ok(copies)
    }
}

impl Store {
    /// An artifact row's body uploaded to this store's object store, the row left naming it
    /// (an empty body and its sha256), unless it names an object already or the target holds
    /// the row (`present`: a resumed copy).
    async fn move_out_of_row(
        &self,
        columns: &[(String, String)],
        values: &mut [Value],
        present: &std::collections::HashSet<(String, String)>,
    ) -> Result<(), StoreError> {
        let at = |name: &str| columns.iter().position(|c| c.0 == name).expect("the artifacts table's columns");
        let (id, kind, body, sha) = (at("inspection_id"), at("kind"), at("body"), at("object_sha256"));
        let (Value::Text(Some(id)), Value::Text(Some(kind))) = (&values[id], &values[kind]) else { return Ok(()) };
        let (Value::Bytes(Some(bytes)), Value::Text(None)) = (&values[body], &values[sha]) else { return Ok(()) };
        let key = blobs::ArtifactKey {
            inspection_id: id.clone(),
            kind: kind.clone(),
            sha256: super::files::sha256_hex(bytes),
        };
        if !present.contains(&(key.inspection_id.clone(), key.kind.clone())) {
            let objects = self.artifact_objects.as_ref().expect("moving only with an object store");
            objects.put_artifact(&key, bytes.clone()).await?;
        }
        values[body] = Value::Bytes(Some(Vec::new()));
        values[sha] = Value::Text(Some(key.sha256));
        Ok(())
    }

    /// Every artifact row that names an object, checked against the object store: there with its
    /// size (the body's length is not kept, so: there and non-empty), and with `hashes` its bytes'
    /// sha256. The problems found, one line each.
    pub async fn verify_artifact_objects(&self, hashes: bool) -> Result<(usize, Vec<String>), StoreError> {
        let Some(objects) = &self.artifact_objects else { return Ok((0, Vec::new())) };
        let named: Vec<(String, String, String)> = on_db!(self.db, |pool, d| {
            sqlx::query_as(
                "SELECT inspection_id, kind, object_sha256 FROM artifacts WHERE object_sha256 IS NOT NULL \
                 ORDER BY inspection_id, kind",
            )
            .fetch_all(pool)
            .await?
        });
        let mut problems = Vec::new();
        for (inspection_id, kind, sha256) in &named {
            let key =
                blobs::ArtifactKey { inspection_id: inspection_id.clone(), kind: kind.clone(), sha256: sha256.clone() };
            let found = if hashes {
                objects.get_artifact(&key).await.map(|b| Some(b.len() as u64))
            } else {
                objects.artifact_size(&key).await
            };
            match found {
                Ok(Some(n)) if n > 0 => {}
                Ok(Some(_)) => problems.push(format!("{inspection_id} {kind}: an empty object")),
                Ok(None) => problems.push(format!("{inspection_id} {kind}: not in {}", objects.describe())),
                Err(e) => problems.push(format!("{inspection_id} {kind}: {e}")),
            }
        }
        Ok((named.len(), problems))
    }
}

/// A row as it is digested: an artifact's body as its sha256, whether the row holds the bytes or
/// names their object, so a copy that moved them compares equal to its source.
fn canonical(table: &str, columns: &[(String, String)], values: &[Value]) -> Vec<Value> {
    let mut values = values.to_vec();
    if table == "artifacts" {
        let at = |name: &str| columns.iter().position(|c| c.0 == name);
        if let (Some(body), Some(sha)) = (at("body"), at("object_sha256")) {
            if let (Value::Bytes(Some(bytes)), Value::Text(None)) = (&values[body], &values[sha]) {
                values[sha] = Value::Text(Some(super::files::sha256_hex(bytes)));
            }
            values[body] = Value::Bytes(None);
        }
    }
    values
}

/// Inserts `batch` into `table` (columns `names`), skipping rows whose key the table has; how
/// many it took.
async fn insert_batch(pg: &PgPool, table: &str, names: &str, batch: &[Vec<Value>]) -> Result<u64, StoreError> {
    let mut q: QueryBuilder<sqlx::Postgres> = QueryBuilder::new(format!("INSERT INTO {table} ({names}) "));
    q.push_values(batch, |mut b, row| {
        for v in row {
            match v.clone() {
                Value::Text(x) => b.push_bind(x),
                Value::Int(x) => b.push_bind(x),
                Value::Real(x) => b.push_bind(x),
                Value::Bool(x) => b.push_bind(x),
                Value::Bytes(x) => b.push_bind(x),
            };
        }
    });
    q.push(" ON CONFLICT DO NOTHING");
    // The source's status events are copied as they are: the triggers that record new ones stand
    // aside for the copy's own transaction.
    let mut tx = pg.begin().await?;
    sqlx::query("SET LOCAL crestscan.copying = 'on'").execute(&mut *tx).await?;
    let inserted = q.build().execute(&mut *tx).await?.rows_affected();
    tx.commit().await?;
    Ok(inserted)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_digest_ignores_order_and_sees_every_value() {
        let a = vec![Value::Text(Some("a".into())), Value::Int(Some(1))];
        let b = vec![Value::Text(Some("b".into())), Value::Int(None)];
        let (mut x, mut y) = (RowsDigest::default(), RowsDigest::default());
        x.add(&a);
        x.add(&b);
        y.add(&b);
        y.add(&a);
        assert_eq!(x, y);
        let mut z = RowsDigest::default();
        z.add(&a);
        z.add(&[Value::Text(Some("b".into())), Value::Int(Some(0))]);
        assert_ne!(x, z, "NULL and 0 differ");
        let mut w = RowsDigest::default();
        w.add(&[Value::Text(Some("ab".into())), Value::Text(Some("".into()))]);
        let mut v = RowsDigest::default();
        v.add(&[Value::Text(Some("a".into())), Value::Text(Some("b".into()))]);
        assert_ne!(w, v, "values are delimited");
    }
}
