//! API keys: the token format, scopes, and checking a presented token against the stored hash.
//!
//! A key reads `csk_<id>_<secret>`: `id` (12 hex digits) is its public name in the key list and
//! the audit; `secret` (64 hex digits, 256 random bits from the operating system) is stored only as
//! its SHA-256 and compared in constant time.

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

/// What a key may do. `admin` includes the other two.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Scope {
    /// Results, lists, the report pages, metrics.
    Read,
    /// Create inspections, cancel them, upload CMM data.
    Submit,
    /// Keys, the audit log (and everything else).
    Admin,
}

impl Scope {
    pub const ALL: [Scope; 3] = [Scope::Read, Scope::Submit, Scope::Admin];

    pub fn as_str(self) -> &'static str {
        match self {
            Scope::Read => "read",
            Scope::Submit => "submit",
            Scope::Admin => "admin",
        }
    }

    pub fn parse(text: &str) -> Option<Scope> {
        Scope::ALL.into_iter().find(|s| s.as_str() == text.trim())
    }
}

/// A comma-separated scope list (`read,submit`), as the CLI and the store write it.
pub fn parse_scopes(text: &str) -> Result<Vec<Scope>, String> {
    let scopes = text
        .split(',')
        .filter(|p| !p.trim().is_empty())
        .map(|part| {
            Scope::parse(part)
                .ok_or_else(|| format!("unknown scope {:?}: the scopes are read, submit and admin", part.trim()))
        })
        .collect::<Result<Vec<_>, _>>()?;
    scope_set(scopes)
}

/// A key's scopes, each once and in order; at least one.
pub fn scope_set(mut scopes: Vec<Scope>) -> Result<Vec<Scope>, String> {
    scopes.sort();
    scopes.dedup();
    if scopes.is_empty() {
        return Err("a key needs at least one scope (read, submit, admin)".into());
    }
    Ok(scopes)
}

/// A key's name, trimmed: 1 to 100 characters.
pub fn key_name(name: &str) -> Result<&str, String> {
    let name = name.trim();
    if name.is_empty() || name.chars().count() > crate::domain::text::KEY_NAME_CHARS {
        return Err("a key's name has 1 to 100 characters".into());
    }
    Ok(name)
}

pub fn scopes_text(scopes: &[Scope]) -> String {
    scopes.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(",")
}

/// Whether a key holding `held` may do what needs `needed`.
pub fn allows(held: &[Scope], needed: Scope) -> bool {
    held.contains(&needed) || held.contains(&Scope::Admin)
}

/// A new key: its id, the whole token (shown once), and the secret's hash (stored).
pub struct NewKey {
    pub id: String,
    pub token: String,
    pub secret_sha256: String,
}

impl NewKey {
    pub fn generate() -> Result<NewKey, getrandom::Error> {
        let mut id = [0u8; 6];
        let mut secret = [0u8; 32];
        getrandom::fill(&mut id)?;
        getrandom::fill(&mut secret)?;
        let (id, secret) = (hex::encode(id), hex::encode(secret));
        Ok(NewKey { token: format!("csk_{id}_{secret}"), secret_sha256: hash_secret(&secret), id })
    }
}

fn hash_secret(secret: &str) -> String {
    hex::encode(Sha256::digest(secret.as_bytes()))
}

/// The (id, secret) of a presented token, or None when it is not shaped like a key.
pub fn split_token(token: &str) -> Option<(&str, &str)> {
    let rest = token.strip_prefix("csk_")?;
    let (id, secret) = rest.split_once('_')?;
    let hex_of = |s: &str, n: usize| s.len() == n && s.bytes().all(|b| b.is_ascii_hexdigit());
    (hex_of(id, 12) && hex_of(secret, 64)).then_some((id, secret))
}

/// Whether `secret` hashes to `stored_sha256`, compared in constant time.
pub fn secret_matches(secret: &str, stored_sha256: &str) -> bool {
    hash_secret(secret).as_bytes().ct_eq(stored_sha256.as_bytes()).into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_generated_token_splits_and_matches_only_its_own_hash() {
        let key = NewKey::generate().unwrap();
        let (id, secret) = split_token(&key.token).unwrap();
        assert_eq!(id, key.id);
        assert!(secret_matches(secret, &key.secret_sha256));
        let other = NewKey::generate().unwrap();
        assert_ne!(other.id, key.id);
        assert!(!secret_matches(secret, &other.secret_sha256));
        let mut flipped = secret.to_string();
        flipped.replace_range(0..1, if secret.starts_with('0') { "1" } else { "0" });
        assert!(!secret_matches(&flipped, &key.secret_sha256));
        for bad in ["", "csk_", "Bearer x", &key.token[..key.token.len() - 1], &key.token.replace("csk_", "sk_")] {
            assert!(split_token(bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn scopes_parse_sort_and_admin_includes_the_others() {
        assert_eq!(parse_scopes("submit, read,read").unwrap(), [Scope::Read, Scope::Submit]);
        assert!(parse_scopes("read,write").unwrap_err().contains("\"write\""));
        assert!(parse_scopes(" , ").is_err());
        assert!(allows(&[Scope::Admin], Scope::Submit));
        assert!(allows(&[Scope::Read, Scope::Submit], Scope::Submit));
        assert!(!allows(&[Scope::Read], Scope::Submit));
        assert!(!allows(&[Scope::Submit], Scope::Admin));
    }
}
