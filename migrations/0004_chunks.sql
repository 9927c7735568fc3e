-- Chunked simulate jobs: a simulate job of n rows is split into
-- chunks planned once, at its first attempt; any worker may claim a chunk of a running
-- job (a lease per chunk, like a job's), writes it as a part file of the dataset and
-- marks it done. A re-claimed job resumes from the finished parts. Rows are kept after
-- the job ends: who simulated what, for operators.
CREATE TABLE job_chunks (
    id               TEXT PRIMARY KEY,  -- '<job id>:<idx, 5 digits>'
    job_id           TEXT NOT NULL,
    idx              INTEGER NOT NULL,
    first_row        INTEGER NOT NULL,
    n_rows           INTEGER NOT NULL,
    state            TEXT NOT NULL DEFAULT 'queued' CHECK (state IN ('queued', 'running', 'done')),
    lease_token      TEXT,
    lease_expires_ms INTEGER,
    worker           TEXT,
    attempts         INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX job_chunks_job ON job_chunks (job_id, idx);
