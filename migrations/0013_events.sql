-- Every status an inspection or a station takes, in the order they were committed: written by
-- triggers in the transaction that changes the status, so no path can change one unrecorded.
-- The MQTT publisher (`mqtt_url`) delivers them in `seq` order from its cursor.
CREATE TABLE events (
    seq          INTEGER PRIMARY KEY AUTOINCREMENT,
    subject_kind TEXT NOT NULL CHECK (subject_kind IN ('inspection', 'station')),
    subject      TEXT NOT NULL,
    status       TEXT NOT NULL,
    at           INTEGER NOT NULL
);
CREATE INDEX events_at ON events (at);

CREATE TRIGGER inspection_created_event AFTER INSERT ON inspections BEGIN
    INSERT INTO events (subject_kind, subject, status, at) VALUES ('inspection', NEW.id, NEW.status, NEW.updated_at);
END;
CREATE TRIGGER inspection_status_event AFTER UPDATE OF status ON inspections WHEN NEW.status IS NOT OLD.status BEGIN
    INSERT INTO events (subject_kind, subject, status, at) VALUES ('inspection', NEW.id, NEW.status, NEW.updated_at);
END;
CREATE TRIGGER station_created_event AFTER INSERT ON stations BEGIN
    INSERT INTO events (subject_kind, subject, status, at) VALUES ('station', NEW.name, NEW.status, NEW.updated_at);
END;
CREATE TRIGGER station_status_event AFTER UPDATE OF status ON stations WHEN NEW.status IS NOT OLD.status BEGIN
    INSERT INTO events (subject_kind, subject, status, at) VALUES ('station', NEW.name, NEW.status, NEW.updated_at);
END;

-- The MQTT publisher's place in `events` (NULL until it first runs: it starts from then, not from
-- history) and the lease of the one process publishing.
CREATE TABLE mqtt_cursor (
    id               INTEGER PRIMARY KEY CHECK (id = 1),
    delivered_seq    INTEGER,
    lease_owner      TEXT,
    lease_expires_at INTEGER
);
INSERT INTO mqtt_cursor (id) VALUES (1);
