-- Readiness (issue 48): `/readyz` writes one small row in a transaction of its own, so that a
-- database that can be read but not written (its disk full, its write lock held) reads as not
-- ready. One row, overwritten each time.
CREATE TABLE write_probe (
    id  INTEGER PRIMARY KEY CHECK (id = 1),
    at  INTEGER NOT NULL
);
