//! Persistence at the edge: the records (inspections, the job queue, results, CMM data, keys,
//! audit, webhooks, stations) in SQLite (WAL, the embedded default) or PostgreSQL through sqlx;
//! uploaded bundles' bytes behind [`blobs::BlobStore`]. Each method's SQL is written once in the
//! dialect both share (`?` placeholders, rewritten to `$n` for PostgreSQL by [`Dialect::sql`]) and
//! runs on whichever pool the store holds ([`on_db!`]); where the two differ (claiming under
//! concurrent workers, locks, JSON) the [`Dialect`] says what each needs. Each backend has its own
//! migrations (`migrations/`, `migrations-pg/`).

pub mod blobs;
mod cmm;
pub mod copy;
mod events;
pub mod files;
mod inspections;
mod keys;
mod queue;
mod results;
mod stations;
mod webhooks;

pub use cmm::{CmmRow, CmmVersionRow};
pub use events::EventRow;
pub use inspections::{Inserted, InspectionRow, ListFilter, NewInspection, UploadInfo};
pub use keys::{AuditEntry, AuditRow, KeyRow};
pub use queue::{Claimed, Heartbeat};
pub use results::{Artifact, HeightRow, JobResults, PITCH_PROFILES, StoredArtifact, ThreadRow};
pub use stations::{CheckJudgement, CheckRecorded, CheckRow, MasterRow, StationRow, StudyRow};
pub use webhooks::{AttemptOutcome, AttemptRow, DeliveryFilter, DeliveryRow, NewDelivery};

use crate::problem::{Code, ErrorCode, Problem};
use files::FileStore;
use serde::Serialize;
use sqlx::postgres::{PgConnectOptions, PgPool, PgPoolOptions};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{QueryBuilder, SqlitePool};
use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Duration;

pub static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("./migrations");
/// PostgreSQL's schema: the same tables as SQLite's, in its types (BIGINT, DOUBLE PRECISION,
/// BOOLEAN, BYTEA), keys in the "C" collation so that ids order as bytes, as in SQLite.
pub static MIGRATOR_PG: sqlx::migrate::Migrator = sqlx::migrate!("./migrations-pg");

/// PostgreSQL's channel for inspections' changes (payload: the row as JSON, or its id).
const CHANGES_CHANNEL: &str = "crestscan_changes";
/// PostgreSQL's channel for newly queued inspections (payload: the id).
const QUEUE_CHANNEL: &str = "crestscan_queue";

/// Where the records live.
#[derive(Clone, Debug, PartialEq)]
pub enum Database {
    /// The embedded default: one SQLite file.
    Sqlite(PathBuf),
    /// A PostgreSQL server, by its `postgres://` URL (shared by API and worker processes).
    Postgres(String),
}

impl Database {
    /// The location without its password, for logs and `/readyz`.
    pub fn describe(&self) -> String {
        match self {
            Database::Sqlite(path) => format!("sqlite:{}", path.display()),
            Database::Postgres(url) => redact_url(url),
        }
    }
}

/// `url` with its password (if any, in its user part or as a `password` parameter) as `***`.
pub fn redact_url(url: &str) -> String {
    let Ok(mut u) = reqwest::Url::parse(url) else { return "(an unparsable URL)".into() };
    if u.password().is_some() {
        let _ = u.set_password(Some("***"));
    }
    if u.query_pairs().any(|(k, _)| k == "password") {
        let pairs: Vec<(String, String)> = u
            .query_pairs()
            .map(|(k, v)| {
                let v = if k == "password" { "***".to_string() } else { v.into_owned() };
                (k.into_owned(), v)
            })
            .collect();
        u.query_pairs_mut().clear().extend_pairs(pairs);
    }
    u.to_string()
}

/// A pool of either backend.
#[derive(Clone)]
pub enum Db {
    Sqlite(SqlitePool),
    Postgres(PgPool),
}

impl Db {
    pub async fn close(&self) {
        match self {
            Db::Sqlite(p) => p.close().await,
            Db::Postgres(p) => p.close().await,
        }
    }
}

/// What SQL the backend at hand needs where the two differ.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dialect {
    Sqlite,
    Postgres,
}

impl Dialect {
    /// `sql` with its `?` and `?n` placeholders as the backend numbers them (PostgreSQL: `$n`).
    pub fn sql(self, sql: &str) -> Cow<'_, str> {
        match self {
            Dialect::Sqlite => Cow::Borrowed(sql),
            Dialect::Postgres => Cow::Owned(numbered_placeholders(sql)),
        }
    }

    /// The statement that opens a transaction which writes: SQLite takes its write lock at once
    /// (a transaction that read first could not take it later: "database is locked"); PostgreSQL
    /// locks rows (`FOR UPDATE`) or keys ([`Dialect::lock_key`]) where a method needs it.
    pub fn begin_write(self) -> &'static str {
        match self {
            Dialect::Sqlite => "BEGIN IMMEDIATE",
            Dialect::Postgres => "BEGIN",
        }
    }

    /// Appended to the subquery that picks rows to claim: under PostgreSQL concurrent claimers
    /// skip each other's rows instead of both taking one (SQLite's write lock serialises them).
    pub fn skip_locked(self) -> &'static str {
        match self {
            Dialect::Sqlite => "",
            Dialect::Postgres => " FOR UPDATE SKIP LOCKED",
        }
    }

    /// Appended to a SELECT whose row the transaction goes on to change on what it read.
    pub fn for_update(self) -> &'static str {
        match self {
            Dialect::Sqlite => "",
            Dialect::Postgres => " FOR UPDATE",
        }
    }

    /// A statement that holds, until the transaction ends, a lock on `?` (a text key) among
    /// transactions that take the same one (PostgreSQL's advisory locks); none under SQLite, whose
    /// write transactions exclude each other already.
    pub fn lock_key(self) -> Option<&'static str> {
        match self {
            Dialect::Sqlite => None,
            Dialect::Postgres => Some("SELECT pg_advisory_xact_lock(hashtextextended($1, 0))"),
        }
    }

    /// The length of the JSON array in text column `column`.
    pub fn json_array_length(self, column: &str) -> String {
        match self {
            Dialect::Sqlite => format!("json_array_length({column})"),
            Dialect::Postgres => format!("json_array_length({column}::json)::BIGINT"),
        }
    }
}

/// Rewrites `?` (numbered in order) and `?n` placeholders to `$n`, outside quoted text.
fn numbered_placeholders(sql: &str) -> String {
    let mut out = String::with_capacity(sql.len() + 16);
    let (mut next, mut quoted) = (0, false);
    let mut chars = sql.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '\'' => {
                quoted = !quoted;
                out.push(c);
            }
            '?' if !quoted => {
                out.push('$');
                if chars.peek().is_some_and(|d| d.is_ascii_digit()) {
                    while let Some(d) = chars.next_if(|d| d.is_ascii_digit()) {
                        out.push(d);
                    }
                } else {
                    next += 1;
                    out.push_str(&next.to_string());
                }
            }
            _ => out.push(c),
        }
    }
    out
}

/// Runs `$body` on the store's pool, whichever backend: `$pool` is the pool (a `SqlitePool` or a
/// `PgPool`, so the body compiles once for each) and `$d` its [`Dialect`].
macro_rules! on_db {
    ($db:expr, |$pool:ident, $d:ident| $body:expr) => {
        match &$db {
            $crate::service::store::Db::Sqlite($pool) => {
                #[allow(unused_variables)]
                let $d = $crate::service::store::Dialect::Sqlite;
                $body
            }
            $crate::service::store::Db::Postgres($pool) => {
                #[allow(unused_variables)]
                let $d = $crate::service::store::Dialect::Postgres;
                $body
            }
        }
    };
}
pub(crate) use on_db;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("not found")]
    NotFound,
    #[error("the Idempotency-Key was used for another request (inspection {existing_id})")]
    IdempotencyConflict { existing_id: String },
    #[error("database: {0}")]
    Db(#[from] sqlx::Error),
    #[error("migrations: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error(
        "the database {database} was written by a newer crestscan: it has schema version {found}, this binary knows up \
         to {known}. Run that newer version (or restore the backup taken before the upgrade); an older binary would \
         misread it"
    )]
    SchemaNewer { database: String, found: i64, known: i64 },
    #[error("file store: {0}")]
    Io(#[from] std::io::Error),
}

impl ErrorCode for StoreError {
    fn code(&self) -> Code {
        match self {
            StoreError::NotFound => Code::NotFound,
            StoreError::IdempotencyConflict { .. } => Code::IdempotencyKeyReused,
            _ if self.is_storage_full() => Code::InsufficientStorage,
            StoreError::Db(_) | StoreError::Migrate(_) | StoreError::Io(_) | StoreError::SchemaNewer { .. } => {
                Code::InternalError
            }
        }
    }

    fn culprit(&self) -> Option<String> {
        matches!(self, StoreError::IdempotencyConflict { .. }).then(|| "Idempotency-Key".into())
    }
}

impl StoreError {
    /// The database or the file store found its disk full (SQLITE_FULL, ENOSPC, a quota).
    pub fn is_storage_full(&self) -> bool {
        match self {
            StoreError::Io(e) => files::is_storage_full(e),
            // SQLITE_FULL is 13; extended codes keep it in their low byte.
            // PostgreSQL's disk_full is SQLSTATE 53100.
            StoreError::Db(sqlx::Error::Database(db)) => db
                .code()
                .is_some_and(|c| c == "53100" || (c.len() < 5 && c.parse::<u32>().is_ok_and(|c| c & 0xff == 13))),
            StoreError::Db(sqlx::Error::Io(e)) => files::is_storage_full(e),
            _ => false,
        }
    }
}

pub fn now_ms() -> i64 {
    (time::OffsetDateTime::now_utc().unix_timestamp_nanos() / 1_000_000) as i64
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Queued,
    Running,
    Succeeded,
    Failed,
    Canceled,
}

impl Status {
    pub const ALL: [Status; 5] = [Status::Queued, Status::Running, Status::Succeeded, Status::Failed, Status::Canceled];

    pub fn as_str(self) -> &'static str {
        match self {
            Status::Queued => "queued",
            Status::Running => "running",
            Status::Succeeded => "succeeded",
            Status::Failed => "failed",
            Status::Canceled => "canceled",
        }
    }

    pub fn is_terminal(self) -> bool {
        matches!(self, Status::Succeeded | Status::Failed | Status::Canceled)
    }
}

impl FromStr for Status {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "queued" => Status::Queued,
            "running" => Status::Running,
            "succeeded" => Status::Succeeded,
            "failed" => Status::Failed,
            "canceled" => Status::Canceled,
            other => return Err(format!("unknown status {other:?} (queued, running, succeeded, failed, canceled)")),
        })
    }
}

#[derive(Clone)]
pub struct Store {
    /// The records' pool; only the store's own modules run SQL on it.
    pub(crate) db: Db,
    /// Where the records live (for readiness and logs).
    pub database: Database,
    /// Local staging for uploads (temporaries, the free-space floor) and, in the embedded
    /// default, the blobs' own directory.
    pub files: FileStore,
    /// Where uploaded bundles' bytes live ([`blobs::LocalBlobs`] over `files`, or an object store).
    pub blobs: std::sync::Arc<dyn blobs::BlobStore>,
    /// Where meshes and images go when an object store is configured; None: in the records.
    pub artifact_objects: Option<std::sync::Arc<dyn blobs::ArtifactStore>>,
    /// Deaths of the worker's process while running one job before that job is failed as
    /// poisonous ([`queue`]).
    pub max_interruptions: i64,
    /// Each change this process writes to an inspection's status or progress, as the row reads
    /// right after it: event streams see every state in order, however short, where a reading of
    /// the database every so often could miss one. Changes written by other processes reach
    /// them through the database only.
    pub changes: tokio::sync::broadcast::Sender<std::sync::Arc<InspectionRow>>,
}

impl Store {
    /// Opens (creating) the SQLite database, runs the migrations and opens the file store.
    pub async fn open(database: &Path, uploads: &Path, tmp: &Path) -> Result<Self, StoreError> {
        Self::connect(&Database::Sqlite(database.to_path_buf()), uploads, tmp).await
    }

    /// Opens the records at `database` (creating a SQLite file, or a PostgreSQL database the
    /// server lacks), runs its migrations, refusing a schema newer than this binary's, and opens
    /// the file store.
    pub async fn connect(database: &Database, uploads: &Path, tmp: &Path) -> Result<Self, StoreError> {
        let db = match database {
            Database::Sqlite(path) => Db::Sqlite(open_sqlite(path).await?),
            Database::Postgres(url) => Db::Postgres(open_postgres(url).await?),
        };
        // A schema a newer binary wrote is refused by name before the migrator's own complaint.
        let migrator = match db {
            Db::Sqlite(_) => &MIGRATOR,
            Db::Postgres(_) => &MIGRATOR_PG,
        };
        let known = migrator.iter().map(|m| m.version).max().unwrap_or(0);
        let applied: Option<i64> = on_db!(db, |pool, d| {
            sqlx::query_scalar("SELECT MAX(version) FROM _sqlx_migrations WHERE success").fetch_one(pool).await
        })
        .unwrap_or(None);
        if let Some(found) = applied.filter(|&v| v > known) {
            db.close().await;
            return Err(StoreError::SchemaNewer { database: database.describe(), found, known });
        }
        on_db!(db, |pool, d| migrator.run(pool).await)?;
        let files = FileStore::open(uploads, tmp)?;
        let (changes, _) = tokio::sync::broadcast::channel(256);
        let blobs = std::sync::Arc::new(blobs::LocalBlobs::new(files.clone()));
        Ok(Self { db, database: database.clone(), files, blobs, artifact_objects: None, max_interruptions: 5, changes })
    }

    /// Which backend holds the records.
    pub fn dialect(&self) -> Dialect {
        match self.db {
            Db::Sqlite(_) => Dialect::Sqlite,
            Db::Postgres(_) => Dialect::Postgres,
        }
    }

    /// The embedded backend's pool, for checks of SQLite's own behaviour (its pages, its locks);
    /// None under PostgreSQL.
    pub fn sqlite_pool(&self) -> Option<&SqlitePool> {
        match &self.db {
            Db::Sqlite(pool) => Some(pool),
            Db::Postgres(_) => None,
        }
    }

    /// One integer a read-only query over the records answers (`SELECT COUNT(*) …`), in the
    /// dialect both backends share: for tests and tools that check the records' consistency.
    pub async fn count(&self, sql: &str) -> Result<i64, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            let mut tx = pool.begin().await?;
            if d == Dialect::Postgres {
                sqlx::query("SET TRANSACTION READ ONLY").execute(&mut *tx).await?;
            }
            let n: i64 = sqlx::query_scalar(sql).fetch_one(&mut *tx).await?;
            tx.rollback().await?;
            n
        }))
    }

    /// Closes the records' pool (tests, tools that end).
    pub async fn close(&self) {
        self.db.close().await
    }

    /// Sends the inspection's row as it now reads to the change feed: under SQLite straight to
    /// this process's listeners (when there are any); under PostgreSQL as a NOTIFY, which every
    /// process's [`Store::listen`] (this one's included) passes to its listeners.
    pub async fn publish(&self, id: &str) {
        match &self.db {
            Db::Sqlite(_) => {
                if self.changes.receiver_count() == 0 {
                    return;
                }
                if let Ok(row) = self.inspection(id).await {
                    let _ = self.changes.send(std::sync::Arc::new(row));
                }
            }
            Db::Postgres(pool) => {
                let Ok(row) = self.inspection(id).await else { return };
                // A NOTIFY payload holds under 8000 bytes: a larger row travels as its id and is
                // read by each listener.
                let mut payload = serde_json::to_string(&row).expect("a row serialises");
                if payload.len() > 7900 {
                    payload = row.id.clone();
                }
                if let Err(e) =
                    sqlx::query("SELECT pg_notify($1, $2)").bind(CHANGES_CHANNEL).bind(&payload).execute(pool).await
                {
                    tracing::warn!(inspection = %id, error = %e, "could not publish a change (NOTIFY)");
                }
            }
        }
    }

    /// Under PostgreSQL, until `stop`: passes other processes' changes (and this one's) to
    /// [`Store::changes`] and wakes `wake` when an upload is queued. Returns at once under SQLite,
    /// where both happen inside the one process. A lost connection is reopened; what was sent
    /// meanwhile is caught by the waiters' own reads of the database.
    pub async fn listen(
        &self,
        wake: std::sync::Arc<tokio::sync::Notify>,
        mut stop: tokio::sync::watch::Receiver<bool>,
    ) {
        let Db::Postgres(pool) = &self.db else { return };
        let mut listener = loop {
            match sqlx::postgres::PgListener::connect_with(pool).await {
                Ok(mut l) => match l.listen_all([CHANGES_CHANNEL, QUEUE_CHANNEL]).await {
                    Ok(()) => break l,
                    Err(e) => tracing::warn!(error = %e, "LISTEN failed; retrying"),
                },
                Err(e) => tracing::warn!(error = %e, "LISTEN connection failed; retrying"),
            }
            tokio::select! {
                _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                _ = stop.changed() => return,
            }
        };
        loop {
            let notification = tokio::select! {
                n = listener.recv() => n,
                _ = stop.changed() => return,
            };
            match notification {
                Ok(n) if n.channel() == QUEUE_CHANNEL => wake.notify_one(),
                Ok(n) => {
                    let row = match serde_json::from_str::<InspectionRow>(n.payload()) {
                        Ok(row) => Some(row),
                        Err(_) => self.inspection(n.payload()).await.ok(),
                    };
                    if let Some(row) = row {
                        let _ = self.changes.send(std::sync::Arc::new(row));
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, "LISTEN connection lost; reconnecting");
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
            }
        }
    }

    pub async fn ping(&self) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| sqlx::query("SELECT 1").execute(pool).await.map(|_| ()))?;
        Ok(())
    }

    /// Whether the database reads and takes a write, else why not (as `/readyz` and the OPC UA
    /// state say it). The write is bounded well under the store's 10 s busy timeout, so a stuck
    /// lock answers promptly.
    pub async fn database_ready(&self) -> Result<(), String> {
        self.ping().await.map_err(|e| format!("database: {e}"))?;
        match tokio::time::timeout(std::time::Duration::from_secs(2), self.probe_write()).await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(format!("database does not take writes: {e}")),
            Err(_) => Err("database does not take writes: no write lock within 2 s".into()),
        }
    }

    /// Writes and commits one small row: fails where the database reads but cannot take a write
    /// (its disk full, its write lock held by a stuck connection).
    pub async fn probe_write(&self) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query(
                &d.sql(
                    "INSERT INTO write_probe (id, at) VALUES (1, ?) ON CONFLICT (id) DO UPDATE SET at = excluded.at",
                ),
            )
            .bind(now_ms())
            .execute(pool)
            .await
            .map(|_| ())
        })?;
        Ok(())
    }

    /// Deletes upload files that no live upload row names: left behind when the transaction that
    /// placed one failed to commit (a full disk). The live rows are read once; each file without
    /// one is checked again and deleted under the lock a submission holds while it places its
    /// file (SQLite's write lock, PostgreSQL's lock on the hash), so a file being accepted right
    /// now is never taken.
    pub async fn remove_orphan_uploads(&self) -> Result<usize, StoreError> {
        let stored = self.blobs.list().await?;
        let live: std::collections::HashSet<String> = on_db!(self.db, |pool, d| {
            sqlx::query_scalar("SELECT sha256 FROM uploads WHERE purged_at IS NULL").fetch_all(pool).await
        })?
        .into_iter()
        .collect();
        let mut removed = 0;
        for sha in stored.into_iter().filter(|sha| !live.contains(sha)) {
            removed += on_db!(self.db, |pool, d| {
                let mut tx = pool.begin_with(d.begin_write()).await?;
                if let Some(lock) = d.lock_key() {
                    sqlx::query(lock).bind(&sha).execute(&mut *tx).await?;
                }
                let live: Option<(i64,)> =
                    sqlx::query_as(&d.sql("SELECT 1 FROM uploads WHERE sha256 = ? AND purged_at IS NULL"))
                        .bind(&sha)
                        .fetch_optional(&mut *tx)
                        .await?;
                if live.is_none() {
                    self.blobs.remove(&sha).await?;
                }
                tx.commit().await?;
                usize::from(live.is_none())
            });
        }
        Ok(removed)
    }
}

async fn open_sqlite(database: &Path) -> Result<SqlitePool, StoreError> {
    if let Some(dir) = database.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let options = SqliteConnectOptions::new()
        .filename(database)
        .create_if_missing(true)
        .journal_mode(SqliteJournalMode::Wal)
        // FULL: an acknowledged upload survives power loss, not only a process crash.
        .synchronous(SqliteSynchronous::Full)
        .foreign_keys(true)
        .busy_timeout(Duration::from_secs(10));
    Ok(SqlitePoolOptions::new()
        .max_connections(8)
        .after_release(|conn, _| Box::pin(clean_on_release(conn)))
        .connect_with(options)
        .await?)
}

/// Connects to PostgreSQL, creating the database when the server has none of that name (as the
/// SQLite file is created), so a fresh server needs no step of its own.
async fn open_postgres(url: &str) -> Result<PgPool, StoreError> {
    use sqlx::migrate::MigrateDatabase;
    let options = PgConnectOptions::from_str(url)?;
    // Checked through the server's maintenance database; a role that may not read it connects
    // straight to its own database, which must then exist.
    match sqlx::Postgres::database_exists(url).await {
        Ok(true) => {}
        Ok(false) => match sqlx::Postgres::create_database(url).await {
            Ok(()) => tracing::info!(database = %redact_url(url), "created the PostgreSQL database"),
            // Another process created it in between.
            Err(sqlx::Error::Database(e)) if e.code().as_deref() == Some("42P04") => {}
            Err(e) => return Err(e.into()),
        },
        Err(e) => tracing::debug!(error = %e, "could not check whether the database exists; connecting to it"),
    }
    Ok(PgPoolOptions::new().max_connections(16).acquire_timeout(Duration::from_secs(10)).connect_with(options).await?)
}

/// Whether a connection coming back to the pool is clean: no transaction open, neither in SQLite
/// nor in sqlx's count of them. A connection that is not is closed (which rolls back whatever it
/// held) instead of being handed to the next caller.
///
/// Why: when a COMMIT fails with SQLITE_FULL, SQLite rolls the transaction back itself, but sqlx
/// 0.8's count stays at one (its ROLLBACK on drop then fails with "no transaction is active").
/// The next `begin()` on that connection issued a SAVEPOINT instead of BEGIN; a later `ROLLBACK
/// TO` of it left a transaction open holding the write lock: every other connection then got
/// "database is locked", and this one's "commits" were RELEASEs inside a transaction never
/// committed (an accepted upload answered 202 and then 404; issue 48).
async fn clean_on_release(conn: &mut sqlx::SqliteConnection) -> Result<bool, sqlx::Error> {
    use sqlx::Connection;
    // Queued behind any rollback a dropped transaction sent, so that it has run.
    let mut handle = conn.lock_handle().await?;
    // SAFETY: the handle is locked out from sqlx's worker thread while it lives;
    // sqlite3_get_autocommit only reads the connection's flag.
    let autocommit = unsafe { libsqlite3_sys::sqlite3_get_autocommit(handle.as_raw_handle().as_ptr()) } != 0;
    drop(handle);
    let clean = autocommit && !conn.is_in_transaction();
    if !clean {
        tracing::warn!(
            sqlite_in_transaction = !autocommit,
            sqlx_in_transaction = conn.is_in_transaction(),
            "a database connection came back with a transaction open (a failed commit?); closed, not reused"
        );
    }
    Ok(clean)
}

/// A strong ETag: the quoted sha256 of the bytes.
pub fn etag_of(bytes: &[u8]) -> String {
    format!("\"{}\"", files::sha256_hex(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placeholders_are_numbered_for_postgres_outside_quoted_text() {
        assert_eq!(numbered_placeholders("a = ? AND b = '?' AND c = ?"), "a = $1 AND b = '?' AND c = $2");
        assert_eq!(
            numbered_placeholders("x = ?1 OR (?2 IS NULL OR y = ?2) LIMIT ?3"),
            "x = $1 OR ($2 IS NULL OR y = $2) LIMIT $3"
        );
        assert_eq!(Dialect::Sqlite.sql("a = ?"), "a = ?");
        assert_eq!(Dialect::Postgres.sql("a = ? AND b = ?"), "a = $1 AND b = $2");
    }

    #[test]
    fn a_password_never_reaches_the_logs() {
        let d = Database::Postgres("postgres://crest:s3cret@db:5432/crestscan".into());
        assert_eq!(d.describe(), "postgres://crest:***@db:5432/crestscan");
        assert_eq!(
            redact_url("postgres://u@h/x?sslmode=require&password=p"),
            "postgres://u@h/x?sslmode=require&password=***"
        );
    }
}
