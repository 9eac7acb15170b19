-- Every CMM upload kept as a version (who, when) instead of overwriting the last; the latest is
-- what the comparison and the training pairs use unless a version is asked for.
CREATE TABLE cmm_versions (
    inspection_id TEXT NOT NULL REFERENCES inspections (id) ON DELETE CASCADE,
    version       INTEGER NOT NULL,             -- 1, 2, ... per inspection
    instrument    TEXT,
    measured_at   TEXT,
    points_json   TEXT NOT NULL,
    uploaded_at   INTEGER NOT NULL,
    uploaded_by   TEXT,                         -- the client's address; NULL for uploads before versions
    PRIMARY KEY (inspection_id, version)
);
INSERT INTO cmm_versions (inspection_id, version, instrument, measured_at, points_json, uploaded_at, uploaded_by)
    SELECT inspection_id, 1, instrument, measured_at, points_json, uploaded_at, NULL FROM cmm_measurements;
DROP TABLE cmm_measurements;
