-- When an inspection's meshes and images were deleted by the result retention (its report and
-- thread table are kept); NULL while they are stored.
ALTER TABLE inspections ADD COLUMN artifacts_purged_at INTEGER;
