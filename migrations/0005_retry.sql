-- Retries with backoff: a failed attempt of a job with attempts left goes back
-- to the queue, claimable only from `run_after_ms` (the database clock, ms since 1970):
-- a delay that doubles with each failed attempt, capped. NULL: claimable at once.
ALTER TABLE jobs ADD COLUMN run_after_ms INTEGER;
