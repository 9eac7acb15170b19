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

-- One function for both tables: its arguments are the subject's kind and its key column.
CREATE FUNCTION crestscan_status_event() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    IF coalesce(current_setting('crestscan.copying', true), '') <> 'on'
       AND (TG_OP = 'INSERT' OR NEW.status IS DISTINCT FROM OLD.status) THEN
        INSERT INTO events (subject_kind, subject, status, at)
        VALUES (TG_ARGV[0], to_jsonb(NEW) ->> TG_ARGV[1], NEW.status, NEW.updated_at);
    END IF;
    RETURN NULL;
END $$;
CREATE TRIGGER inspection_event AFTER INSERT OR UPDATE OF status ON inspections
    FOR EACH ROW EXECUTE FUNCTION crestscan_status_event('inspection', 'id');
CREATE TRIGGER station_event AFTER INSERT OR UPDATE OF status ON stations
    FOR EACH ROW EXECUTE FUNCTION crestscan_status_event('station', 'name');

CREATE TABLE mqtt_cursor (
    id               BIGINT PRIMARY KEY CHECK (id = 1),
    delivered_seq    BIGINT,
    lease_owner      TEXT,
    lease_expires_at BIGINT
);
INSERT INTO mqtt_cursor (id) VALUES (1);
