-- Meshes and images kept in an object store (`--object-store`): the row keeps the metadata with
-- an empty body and names the object by its bytes' sha256. NULL: the body is the row's own.
ALTER TABLE artifacts ADD COLUMN object_sha256 TEXT;
