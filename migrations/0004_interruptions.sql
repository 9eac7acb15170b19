-- Claims that ended because the worker's process died (its lease lapsed), counted apart from
-- attempts that ended in a retryable failure: a crash is not the job's fault until it repeats.
ALTER TABLE inspections ADD COLUMN interruptions INTEGER NOT NULL DEFAULT 0;
