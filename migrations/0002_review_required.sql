-- Whether a succeeded inspection's result needs review (its report's quality is not ok), so that
-- the list can be filtered by it. NULL until the inspection succeeds, and for inspections that
-- succeeded before this column existed (their reports carry no quality).
ALTER TABLE inspections ADD COLUMN review_required INTEGER CHECK (review_required IN (0, 1));
CREATE INDEX inspections_review_required ON inspections (review_required, id);
