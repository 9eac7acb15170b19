-- Each height's expanded uncertainty (k = 2), each thread's mean's and its height finding, and
-- the inspection's ISO 14253-1 decision. NULL for results stored before they were computed.
ALTER TABLE thread_heights ADD COLUMN uncertainty_mm REAL;
ALTER TABLE threads ADD COLUMN mean_height_uncertainty_mm REAL;
ALTER TABLE threads ADD COLUMN height_finding TEXT;
ALTER TABLE inspections ADD COLUMN decision TEXT
    CHECK (decision IN ('conforms', 'does_not_conform', 'indeterminate'));
