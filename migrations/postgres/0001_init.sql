-- PostgreSQL schema: the same tables and columns as migrations/0001_init.sql +
-- 0002_leases.sql (SQLite), so one set of queries serves both. Timestamps are RFC 3339
-- text, flags are 0/1 integers, as in SQLite.

-- Models: NPE checkpoints on (shared) disk, registered by path.
CREATE TABLE models (
    id          TEXT PRIMARY KEY,
    path        TEXT NOT NULL,
    is_default  BIGINT NOT NULL DEFAULT 0,
    created_at  TEXT NOT NULL,
    source_job  TEXT
);

-- Jobs: queued → running → succeeded | failed | cancelled.
CREATE TABLE jobs (
    id               TEXT PRIMARY KEY,
    kind             TEXT NOT NULL,
    state            TEXT NOT NULL DEFAULT 'queued'
                     CHECK (state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    params           TEXT NOT NULL,
    progress         DOUBLE PRECISION NOT NULL DEFAULT 0,
    message          TEXT NOT NULL DEFAULT '',
    attempts         BIGINT NOT NULL DEFAULT 0,
    max_attempts     BIGINT NOT NULL DEFAULT 3,
    cancel_requested BIGINT NOT NULL DEFAULT 0,
    error            TEXT,
    result           TEXT,
    created_at       TEXT NOT NULL,
    started_at       TEXT,
    finished_at      TEXT,
    lease_token      TEXT,
    lease_expires_ms BIGINT,
    worker           TEXT
);
CREATE INDEX jobs_state_created ON jobs (state, created_at);
