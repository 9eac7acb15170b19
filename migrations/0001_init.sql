-- crestscan's store. Times are Unix milliseconds (UTC); the API renders them as RFC 3339.
-- Plain SQL without SQLite-only types beyond what PostgreSQL also accepts, so that the schema can move.

CREATE TABLE uploads (
    sha256      TEXT PRIMARY KEY,
    size_bytes  INTEGER NOT NULL,
    views       INTEGER NOT NULL,
    frames      INTEGER NOT NULL,
    created_at  INTEGER NOT NULL,
    -- Set when the retention sweep deleted the file (the row stays for the inspections' history).
    purged_at   INTEGER
);

CREATE TABLE inspections (
    id                TEXT PRIMARY KEY,          -- UUID v7: time-ordered, the list's cursor
    status            TEXT NOT NULL CHECK (status IN ('queued', 'running', 'succeeded', 'failed', 'canceled')),
    upload_sha256     TEXT NOT NULL REFERENCES uploads (sha256),
    serial            TEXT,
    connection        TEXT,
    client_reference  TEXT,
    options_json      TEXT NOT NULL,
    verdict           TEXT CHECK (verdict IN ('accept', 'reject')),
    created_at        INTEGER NOT NULL,
    updated_at        INTEGER NOT NULL,
    started_at        INTEGER,
    finished_at       INTEGER,
    progress_stage    TEXT,
    progress_fraction REAL,
    attempts          INTEGER NOT NULL DEFAULT 0,
    max_attempts      INTEGER NOT NULL,
    available_at      INTEGER NOT NULL,          -- not claimed before (retry back-off)
    lease_owner       TEXT,
    lease_expires_at  INTEGER,
    cancel_requested  INTEGER NOT NULL DEFAULT 0,
    error_json        TEXT,                      -- the problem object of a failed inspection
    idempotency_key   TEXT UNIQUE,
    request_sha256    TEXT NOT NULL
);
CREATE INDEX inspections_claim ON inspections (status, available_at, id);
CREATE INDEX inspections_serial ON inspections (serial, id);
CREATE INDEX inspections_client_reference ON inspections (client_reference, id);
CREATE INDEX inspections_connection ON inspections (connection, id);
CREATE INDEX inspections_upload ON inspections (upload_sha256);

CREATE TABLE reports (
    inspection_id TEXT PRIMARY KEY REFERENCES inspections (id) ON DELETE CASCADE,
    report_json   TEXT NOT NULL,
    etag          TEXT NOT NULL
);

-- Meshes and images, immutable once written.
CREATE TABLE artifacts (
    inspection_id TEXT NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    kind          TEXT NOT NULL,                 -- mesh.ply, mesh.stl, height-map.png, all-in-focus.png
    content_type  TEXT NOT NULL,
    body          BLOB NOT NULL,
    etag          TEXT NOT NULL,
    PRIMARY KEY (inspection_id, kind)
);

-- The per-thread table: one row per thread, one per thread and angle bin.
CREATE TABLE threads (
    inspection_id          TEXT NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    thread_index           INTEGER NOT NULL,
    crest_z_start_mm       REAL NOT NULL,
    crest_z_end_mm         REAL NOT NULL,
    min_height_mm          REAL,
    mean_height_mm         REAL,
    max_height_mm          REAL,
    bins_measured          INTEGER NOT NULL,
    black_crest_length_mm  REAL NOT NULL,
    black_crest_arcs_json  TEXT NOT NULL,
    PRIMARY KEY (inspection_id, thread_index)
);

CREATE TABLE thread_heights (
    inspection_id TEXT NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    thread_index  INTEGER NOT NULL,
    angle_deg     REAL NOT NULL,
    height_mm     REAL,                          -- NULL where no view covered the bin
    PRIMARY KEY (inspection_id, thread_index, angle_deg)
);

CREATE TABLE cmm_measurements (
    inspection_id TEXT PRIMARY KEY REFERENCES inspections (id) ON DELETE CASCADE,
    instrument    TEXT,
    measured_at   TEXT,
    points_json   TEXT NOT NULL,
    uploaded_at   INTEGER NOT NULL
);
