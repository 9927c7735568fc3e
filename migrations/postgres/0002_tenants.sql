-- Tenants: the same as migrations/0003_tenants.sql (SQLite).
CREATE TABLE api_keys (
    id          TEXT PRIMARY KEY,
    tenant      TEXT NOT NULL,
    key_hash    TEXT NOT NULL UNIQUE,
    admin       BIGINT NOT NULL DEFAULT 0,
    created_at  TEXT NOT NULL,
    revoked_at  TEXT
);
ALTER TABLE jobs ADD COLUMN tenant TEXT NOT NULL DEFAULT 'default';
CREATE INDEX jobs_tenant_created ON jobs (tenant, created_at);
ALTER TABLE models ADD COLUMN tenant TEXT;
UPDATE models SET tenant = (SELECT tenant FROM jobs WHERE jobs.id = models.source_job) WHERE source_job IS NOT NULL;
