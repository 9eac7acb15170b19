//! API keys and the audit log.

use super::*;
use crate::service::auth::{NewKey, Scope, parse_scopes, scopes_text};

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct KeyRow {
    pub id: String,
    pub name: String,
    pub scopes: String,
    pub secret_sha256: String,
    pub created_at: i64,
    pub revoked_at: Option<i64>,
}

impl KeyRow {
    pub fn scopes(&self) -> Vec<Scope> {
        parse_scopes(&self.scopes).unwrap_or_default()
    }
}

/// One audit entry to write.
#[derive(Clone, Debug)]
pub struct AuditEntry {
    pub key_id: Option<String>,
    pub key_name: Option<String>,
    pub client: String,
    pub action: String,
    pub target: Option<String>,
    pub status: u16,
}

#[derive(Clone, Debug, sqlx::FromRow)]
pub struct AuditRow {
    pub seq: i64,
    pub at: i64,
    pub key_id: Option<String>,
    pub key_name: Option<String>,
    pub client: String,
    pub action: String,
    pub target: Option<String>,
    pub status: i64,
}

impl Store {
    /// Creates a key; returns its row and the token, which is not stored and cannot be shown again.
    pub async fn create_key(&self, name: &str, scopes: &[Scope]) -> Result<(KeyRow, String), StoreError> {
        let key = NewKey::generate().map_err(|e| StoreError::Io(std::io::Error::other(e.to_string())))?;
        let row = KeyRow {
            id: key.id,
            name: name.to_string(),
            scopes: scopes_text(scopes),
            secret_sha256: key.secret_sha256,
            created_at: now_ms(),
            revoked_at: None,
        };
        on_db!(self.db, |pool, d| {
            sqlx::query(
                &d.sql("INSERT INTO api_keys (id, name, scopes, secret_sha256, created_at) VALUES (?, ?, ?, ?, ?)"),
            )
            .bind(&row.id)
            .bind(&row.name)
            .bind(&row.scopes)
            .bind(&row.secret_sha256)
            .bind(row.created_at)
            .execute(pool)
            .await?;
        });
        Ok((row, key.token))
    }

    pub async fn key(&self, id: &str) -> Result<KeyRow, StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query_as(
                &d.sql("SELECT id, name, scopes, secret_sha256, created_at, revoked_at FROM api_keys WHERE id = ?"),
            )
            .bind(id)
            .fetch_optional(pool)
            .await?
        })
        .ok_or(StoreError::NotFound)
    }

    /// The live key a presented token (`csk_<id>_<secret>`) names, None where the token is
    /// malformed, unknown, revoked or its secret does not match: the one check every interface
    /// that takes API keys makes.
    pub async fn key_for_token(&self, token: &str) -> Result<Option<KeyRow>, StoreError> {
        let Some((id, secret)) = crate::service::auth::split_token(token) else { return Ok(None) };
        let row = match self.key(id).await {
            Ok(row) => row,
            Err(StoreError::NotFound) => return Ok(None),
            Err(e) => return Err(e),
        };
        let live = row.revoked_at.is_none() && crate::service::auth::secret_matches(secret, &row.secret_sha256);
        Ok(live.then_some(row))
    }

    /// Every key, oldest first (revoked ones too).
    pub async fn keys(&self) -> Result<Vec<KeyRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(
                "SELECT id, name, scopes, secret_sha256, created_at, revoked_at FROM api_keys ORDER BY created_at, id",
            )
            .fetch_all(pool)
            .await?
        }))
    }

    /// Revokes a key (a revoked key stays listed); NotFound when there is none.
    pub async fn revoke_key(&self, id: &str) -> Result<KeyRow, StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql("UPDATE api_keys SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL"))
                .bind(now_ms())
                .bind(id)
                .execute(pool)
                .await?;
        });
        self.key(id).await
    }

    pub async fn audit(&self, e: &AuditEntry) -> Result<(), StoreError> {
        on_db!(self.db, |pool, d| {
            sqlx::query(&d.sql(
                "INSERT INTO audit (at, key_id, key_name, client, action, target, status) VALUES (?, ?, ?, ?, ?, ?, ?)",
            ))
            .bind(now_ms())
            .bind(&e.key_id)
            .bind(&e.key_name)
            .bind(&e.client)
            .bind(&e.action)
            .bind(&e.target)
            .bind(e.status as i64)
            .execute(pool)
            .await?;
        });
        Ok(())
    }

    /// The audit log, newest first: at most `limit` entries before `before_seq`, of `target` if given.
    pub async fn audit_log(
        &self,
        limit: i64,
        before_seq: Option<i64>,
        target: Option<&str>,
    ) -> Result<Vec<AuditRow>, StoreError> {
        Ok(on_db!(self.db, |pool, d| {
            sqlx::query_as(&d.sql(
                "SELECT seq, at, key_id, key_name, client, action, target, status FROM audit \
                 WHERE (?1 IS NULL OR seq < ?1) AND (?2 IS NULL OR target = ?2) ORDER BY seq DESC LIMIT ?3",
            ))
            .bind(before_seq)
            .bind(target)
            .bind(limit)
            .fetch_all(pool)
            .await?
        }))
    }
}
