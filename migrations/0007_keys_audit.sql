-- API keys (bearer): the secret is stored only as its SHA-256; `id` is the key's public part.
CREATE TABLE api_keys (
    id            TEXT PRIMARY KEY,
    name          TEXT NOT NULL,
    scopes        TEXT NOT NULL,                -- comma-separated: read, submit, admin
    secret_sha256 TEXT NOT NULL,
    created_at    INTEGER NOT NULL,
    revoked_at    INTEGER                       -- NULL while valid
);

-- Who did what to which inspection, and when: submissions, cancels, CMM uploads, reads of
-- results, key changes.
CREATE TABLE audit (
    seq        INTEGER PRIMARY KEY AUTOINCREMENT,
    at         INTEGER NOT NULL,
    key_id     TEXT,                            -- NULL with auth off
    key_name   TEXT,
    client     TEXT NOT NULL,                   -- the peer's address
    action     TEXT NOT NULL,                   -- method and matched route
    target     TEXT,                            -- the inspection or key id
    status     INTEGER NOT NULL
);
CREATE INDEX audit_target ON audit (target);
