-- crestscan's records in PostgreSQL: the tables of migrations/0001–0011 (SQLite) as they stand
-- after the last of them, in PostgreSQL's types. Integers are BIGINT (the store reads them as
-- i64), flags BOOLEAN, reals DOUBLE PRECISION, bodies BYTEA; keys that are ordered or compared
-- (ids, hashes, names) use the "C" collation, so that they sort as bytes, as SQLite's do, and a
-- list's cursor means the same on either backend.

CREATE TABLE uploads (
    sha256      TEXT COLLATE "C" PRIMARY KEY,
    size_bytes  BIGINT NOT NULL,
    views       BIGINT NOT NULL,
    frames      BIGINT NOT NULL,
    created_at  BIGINT NOT NULL,
    purged_at   BIGINT
);

CREATE TABLE inspections (
    id                  TEXT COLLATE "C" PRIMARY KEY,
    status              TEXT NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'canceled')),
    upload_sha256       TEXT COLLATE "C" NOT NULL REFERENCES uploads (sha256),
    serial              TEXT COLLATE "C",
    connection          TEXT COLLATE "C",
    client_reference    TEXT COLLATE "C",
    options_json        TEXT NOT NULL,
    verdict             TEXT CHECK (verdict IN ('accept', 'reject')),
    created_at          BIGINT NOT NULL,
    updated_at          BIGINT NOT NULL,
    started_at          BIGINT,
    finished_at         BIGINT,
    progress_stage      TEXT,
    progress_fraction   DOUBLE PRECISION,
    attempts            BIGINT NOT NULL DEFAULT 0,
    max_attempts        BIGINT NOT NULL,
    available_at        BIGINT NOT NULL,
    lease_owner         TEXT,
    lease_expires_at    BIGINT,
    cancel_requested    BOOLEAN NOT NULL DEFAULT FALSE,
    error_json          TEXT,
    idempotency_key     TEXT UNIQUE,
    request_sha256      TEXT NOT NULL,
    review_required     BOOLEAN,
    decision            TEXT CHECK (decision IN ('conforms', 'does_not_conform', 'indeterminate')),
    interruptions       BIGINT NOT NULL DEFAULT 0,
    artifacts_purged_at BIGINT,
    webhooks_enqueued   BOOLEAN NOT NULL DEFAULT FALSE,
    station             TEXT COLLATE "C"
);
CREATE INDEX inspections_claim ON inspections (status, available_at, id);
CREATE INDEX inspections_serial ON inspections (serial, id);
CREATE INDEX inspections_client_reference ON inspections (client_reference, id);
CREATE INDEX inspections_connection ON inspections (connection, id);
CREATE INDEX inspections_upload ON inspections (upload_sha256);
CREATE INDEX inspections_review_required ON inspections (review_required, id);
CREATE INDEX inspections_webhooks_pending ON inspections (webhooks_enqueued, status);
CREATE INDEX inspections_station ON inspections (station, id);

CREATE TABLE reports (
    inspection_id TEXT COLLATE "C" PRIMARY KEY REFERENCES inspections (id) ON DELETE CASCADE,
    report_json   TEXT NOT NULL,
    etag          TEXT NOT NULL
);

CREATE TABLE artifacts (
    inspection_id TEXT COLLATE "C" NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    kind          TEXT COLLATE "C" NOT NULL,
    content_type  TEXT NOT NULL,
    body          BYTEA NOT NULL,
    etag          TEXT NOT NULL,
    PRIMARY KEY (inspection_id, kind)
);
-- Meshes and PNGs: kept out of line without compression (PNG is compressed already; compressing
-- a few MB each cost a finishing job about 100 ms).
ALTER TABLE artifacts ALTER COLUMN body SET STORAGE EXTERNAL;

CREATE TABLE threads (
    inspection_id              TEXT COLLATE "C" NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    thread_index               BIGINT NOT NULL,
    crest_z_start_mm           DOUBLE PRECISION NOT NULL,
    crest_z_end_mm             DOUBLE PRECISION NOT NULL,
    min_height_mm              DOUBLE PRECISION,
    mean_height_mm             DOUBLE PRECISION,
    max_height_mm              DOUBLE PRECISION,
    bins_measured              BIGINT NOT NULL,
    black_crest_length_mm      DOUBLE PRECISION NOT NULL,
    black_crest_arcs_json      TEXT NOT NULL,
    mean_height_uncertainty_mm DOUBLE PRECISION,
    height_finding             TEXT,
    PRIMARY KEY (inspection_id, thread_index)
);

CREATE TABLE thread_heights (
    inspection_id  TEXT COLLATE "C" NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    thread_index   BIGINT NOT NULL,
    angle_deg      DOUBLE PRECISION NOT NULL,
    height_mm      DOUBLE PRECISION,
    uncertainty_mm DOUBLE PRECISION,
    PRIMARY KEY (inspection_id, thread_index, angle_deg)
);

CREATE TABLE cmm_versions (
    inspection_id TEXT COLLATE "C" NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    version       BIGINT NOT NULL,
    instrument    TEXT,
    measured_at   TEXT,
    points_json   TEXT NOT NULL,
    uploaded_at   BIGINT NOT NULL,
    uploaded_by   TEXT,
    PRIMARY KEY (inspection_id, version)
);

CREATE TABLE api_keys (
    id            TEXT COLLATE "C" PRIMARY KEY,
    name          TEXT NOT NULL,
    scopes        TEXT NOT NULL,
    secret_sha256 TEXT NOT NULL,
    created_at    BIGINT NOT NULL,
    revoked_at    BIGINT
);

CREATE TABLE audit (
    seq        BIGINT GENERATED BY DEFAULT AS IDENTITY PRIMARY KEY,
    at         BIGINT NOT NULL,
    key_id     TEXT,
    key_name   TEXT,
    client     TEXT NOT NULL,
    action     TEXT NOT NULL,
    target     TEXT COLLATE "C",
    status     BIGINT NOT NULL
);
CREATE INDEX audit_target ON audit (target);

CREATE TABLE webhook_deliveries (
    id               TEXT COLLATE "C" PRIMARY KEY,
    inspection_id    TEXT COLLATE "C" NOT NULL,
    endpoint         TEXT COLLATE "C" NOT NULL,
    url              TEXT NOT NULL,
    event_type       TEXT COLLATE "C" NOT NULL,
    payload_json     TEXT NOT NULL,
    status           TEXT NOT NULL CHECK (status IN ('pending', 'delivered', 'failed')),
    attempts         BIGINT NOT NULL DEFAULT 0,
    created_at       BIGINT NOT NULL,
    next_attempt_at  BIGINT NOT NULL,
    lease_owner      TEXT,
    lease_expires_at BIGINT,
    delivered_at     BIGINT,
    last_error       TEXT,
    UNIQUE (inspection_id, endpoint, event_type)
);
CREATE INDEX webhook_deliveries_due ON webhook_deliveries (status, next_attempt_at);

CREATE TABLE webhook_attempts (
    delivery_id  TEXT COLLATE "C" NOT NULL REFERENCES webhook_deliveries (id) ON DELETE CASCADE,
    attempt      BIGINT NOT NULL,
    started_at   BIGINT NOT NULL,
    duration_ms  BIGINT NOT NULL,
    status_code  BIGINT,
    error        TEXT,
    PRIMARY KEY (delivery_id, attempt)
);

CREATE TABLE write_probe (
    id  BIGINT PRIMARY KEY CHECK (id = 1),
    at  BIGINT NOT NULL
);

CREATE TABLE stations (
    name          TEXT COLLATE "C" PRIMARY KEY,
    description   TEXT,
    status        TEXT NOT NULL CHECK (status IN ('unqualified', 'qualified', 'suspended')),
    status_reason TEXT,
    study_id      TEXT COLLATE "C",
    created_at    BIGINT NOT NULL,
    updated_at    BIGINT NOT NULL
);

CREATE TABLE masters (
    station          TEXT COLLATE "C" NOT NULL REFERENCES stations (name) ON DELETE CASCADE,
    serial           TEXT COLLATE "C" NOT NULL,
    certificate_json TEXT NOT NULL,
    instrument       TEXT NOT NULL,
    calibrated_at    TEXT NOT NULL,
    uncertainty_mm   DOUBLE PRECISION NOT NULL,
    uploaded_at      BIGINT NOT NULL,
    PRIMARY KEY (station, serial)
);

CREATE TABLE studies (
    id                 TEXT COLLATE "C" PRIMARY KEY,
    station            TEXT COLLATE "C" NOT NULL REFERENCES stations (name) ON DELETE CASCADE,
    inspections_json   TEXT NOT NULL,
    qualification_json TEXT NOT NULL,
    created_at         BIGINT NOT NULL
);

CREATE TABLE checks (
    station        TEXT COLLATE "C" NOT NULL REFERENCES stations (name) ON DELETE CASCADE,
    study_id       TEXT COLLATE "C" NOT NULL,
    seq            BIGINT NOT NULL,
    inspection_id  TEXT COLLATE "C" NOT NULL,
    master         TEXT NOT NULL,
    points_json    TEXT NOT NULL,
    violation_json TEXT,
    created_at     BIGINT NOT NULL,
    PRIMARY KEY (station, study_id, seq),
    UNIQUE (station, study_id, inspection_id)
);
