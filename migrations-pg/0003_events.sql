-- Every status an inspection or a station takes, in the order they were committed: written by
-- triggers in the transaction that changes the status. The MQTT publisher delivers them in `seq`
-- order from its cursor. `migrate-store` sets crestscan.copying to copy the source's own events
-- instead of making new ones.
CREATE TABLE events (
    seq          BIGSERIAL PRIMARY KEY,
    subject_kind TEXT NOT NULL CHECK (subject_kind IN ('inspection', 'station')),
    subject      TEXT COLLATE "C" NOT NULL,
    status       TEXT NOT NULL,
    at           BIGINT NOT NULL
);
CREATE INDEX events_at ON events (at);

CREATE FUNCTION crestscan_inspection_event() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    IF coalesce(current_setting('crestscan.copying', true), '') <> 'on'
       AND (TG_OP = 'INSERT' OR NEW.status IS DISTINCT FROM OLD.status) THEN
        INSERT INTO events (subject_kind, subject, status, at) VALUES ('inspection', NEW.id, NEW.status, NEW.updated_at);
    END IF;
    RETURN NULL;
END $$;
CREATE TRIGGER inspection_event AFTER INSERT OR UPDATE OF status ON inspections
    FOR EACH ROW EXECUTE FUNCTION crestscan_inspection_event();

CREATE FUNCTION crestscan_station_event() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    IF coalesce(current_setting('crestscan.copying', true), '') <> 'on'
       AND (TG_OP = 'INSERT' OR NEW.status IS DISTINCT FROM OLD.status) THEN
        INSERT INTO events (subject_kind, subject, status, at) VALUES ('station', NEW.name, NEW.status, NEW.updated_at);
    END IF;
    RETURN NULL;
END $$;
CREATE TRIGGER station_event AFTER INSERT OR UPDATE OF status ON stations
    FOR EACH ROW EXECUTE FUNCTION crestscan_station_event();

CREATE TABLE mqtt_cursor (
    id               BIGINT PRIMARY KEY CHECK (id = 1),
    delivered_seq    BIGINT,
    lease_owner      TEXT,
    lease_expires_at BIGINT
);
INSERT INTO mqtt_cursor (id) VALUES (1);
