-- Tenants: API keys belong to a tenant, and jobs (datasets are simulate jobs)
-- and models belong to the tenant that made them. Keys are stored as the SHA-256 of the
-- key (hex), never the key; `id` is the key's public prefix, for `otofit keys list/revoke`.
-- A revoked key stays (revoked_at set): a server that once had keys never turns keyless.
CREATE TABLE api_keys (
    id          TEXT PRIMARY KEY,
    tenant      TEXT NOT NULL,
    key_hash    TEXT NOT NULL UNIQUE,
    admin       INTEGER NOT NULL DEFAULT 0,
    created_at  TEXT NOT NULL,
    revoked_at  TEXT
);
-- Jobs made before tenants, or by a keyless server or a --api-key-hash key, are the
-- `default` tenant's.
ALTER TABLE jobs ADD COLUMN tenant TEXT NOT NULL DEFAULT 'default';
CREATE INDEX jobs_tenant_created ON jobs (tenant, created_at);
-- A model's tenant is its source job's; NULL (the default model, models registered by
-- the operator) is shared by every tenant.
ALTER TABLE models ADD COLUMN tenant TEXT;
UPDATE models SET tenant = (SELECT tenant FROM jobs WHERE jobs.id = models.source_job) WHERE source_job IS NOT NULL;
