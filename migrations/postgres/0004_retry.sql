-- The same as migrations/0005_retry.sql (SQLite).
ALTER TABLE jobs ADD COLUMN run_after_ms BIGINT;
