-- Webhooks (issue 29): a transactional outbox. An inspection whose state became terminal is picked
-- up by the dispatcher, which writes one delivery per endpoint that wants the event and marks the
-- inspection enqueued in the same transaction; deliveries are then attempted until delivered or
-- out of attempts, across restarts. Inspections finished before this migration are not notified.
ALTER TABLE inspections ADD COLUMN webhooks_enqueued INTEGER NOT NULL DEFAULT 0;
UPDATE inspections SET webhooks_enqueued = 1 WHERE status IN ('succeeded', 'failed', 'canceled');
CREATE INDEX inspections_webhooks_pending ON inspections (webhooks_enqueued, status);

CREATE TABLE webhook_deliveries (
    id               TEXT PRIMARY KEY,          -- the webhook-id header: msg_<uuid v7>, the same on every attempt
    inspection_id    TEXT NOT NULL,             -- no foreign key: the record outlives a deleted inspection
    endpoint         TEXT NOT NULL,             -- a configured endpoint's name, or 'callback' (the submission's callback_url)
    url              TEXT NOT NULL,
    event_type       TEXT NOT NULL,             -- inspection.succeeded, inspection.failed, inspection.canceled
    payload_json     TEXT NOT NULL,             -- the body, fixed when enqueued
    status           TEXT NOT NULL CHECK (status IN ('pending', 'delivered', 'failed')),
    attempts         INTEGER NOT NULL DEFAULT 0,
    created_at       INTEGER NOT NULL,
    next_attempt_at  INTEGER NOT NULL,
    lease_owner      TEXT,                      -- the process attempting it now
    lease_expires_at INTEGER,
    delivered_at     INTEGER,
    last_error       TEXT,
    UNIQUE (inspection_id, endpoint, event_type)
);
CREATE INDEX webhook_deliveries_due ON webhook_deliveries (status, next_attempt_at);

CREATE TABLE webhook_attempts (
    delivery_id  TEXT NOT NULL REFERENCES webhook_deliveries (id) ON DELETE CASCADE,
    attempt      INTEGER NOT NULL,              -- 1, 2, ...
    started_at   INTEGER NOT NULL,
    duration_ms  INTEGER NOT NULL,
    status_code  INTEGER,                       -- NULL when no answer came (refused, timed out)
    error        TEXT,                          -- NULL when delivered
    PRIMARY KEY (delivery_id, attempt)
);
