-- Drift control: check runs of a station's masters, charted against the limits of the study in
-- force when they were made (Western Electric rules). A check that breaks a rule suspends the
-- station in the same transaction as it is recorded, and writes the station.suspended webhook
-- deliveries (keyed by the check's inspection).
CREATE TABLE checks (
    station        TEXT NOT NULL REFERENCES stations (name) ON DELETE CASCADE,
    study_id       TEXT NOT NULL,
    seq            INTEGER NOT NULL,            -- 1, 2, … within the study
    inspection_id  TEXT NOT NULL,
    master         TEXT NOT NULL,
    points_json    TEXT NOT NULL,               -- each statistic's value and z
    violation_json TEXT,                        -- the rule it broke; NULL in control
    created_at     INTEGER NOT NULL,
    PRIMARY KEY (station, study_id, seq),
    UNIQUE (station, study_id, inspection_id)
);
