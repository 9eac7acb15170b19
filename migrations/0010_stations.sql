-- Stations a plant qualifies (ISO 15530-3): the station, its masters with their certificates, the
-- studies run over the masters' inspections, and the station each inspection was recorded at.
CREATE TABLE stations (
    name               TEXT PRIMARY KEY,        -- what bundles and submissions name the station by
    description        TEXT,
    status             TEXT NOT NULL CHECK (status IN ('unqualified', 'qualified', 'suspended')),
    status_reason      TEXT,
    study_id           TEXT,                    -- the study in force (qualified) or last (suspended)
    created_at         INTEGER NOT NULL,
    updated_at         INTEGER NOT NULL
);
CREATE TABLE masters (
    station            TEXT NOT NULL REFERENCES stations (name) ON DELETE CASCADE,
    serial             TEXT NOT NULL,
    certificate_json   TEXT NOT NULL,           -- the CMM points as uploaded
    instrument         TEXT NOT NULL,
    calibrated_at      TEXT NOT NULL,
    uncertainty_mm     REAL NOT NULL,           -- the largest expanded uncertainty its points state
    uploaded_at        INTEGER NOT NULL,
    PRIMARY KEY (station, serial)
);
CREATE TABLE studies (
    id                 TEXT PRIMARY KEY,
    station            TEXT NOT NULL REFERENCES stations (name) ON DELETE CASCADE,
    inspections_json   TEXT NOT NULL,           -- the master inspections it was run over
    qualification_json TEXT NOT NULL,           -- the result: correction, U, gauge figures
    created_at         INTEGER NOT NULL
);
ALTER TABLE inspections ADD COLUMN station TEXT;
CREATE INDEX inspections_station ON inspections (station, id);
