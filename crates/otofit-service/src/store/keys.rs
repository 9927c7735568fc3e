//! API keys (the `api_keys` table): each belongs to a tenant and may be an admin key.
//! Only the SHA-256 of a key is stored; the key itself is shown once, when it is made.
//! Keys are revoked, never deleted, so a server that once had keys never turns keyless.

use super::{Cols, Pool, Store, now};
use serde::Serialize;

/// A key as `otofit keys list` shows it: never the key, nor its hash.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct ApiKey {
    /// The key's public id, also the start of the key (`otofit_<id>_…`).
    pub id: String,
    /// The tenant the key speaks for.
    pub tenant: String,
    /// Whether the key may manage other tenants' jobs and models.
    pub admin: bool,
    /// When the key was made (RFC 3339).
    pub created_at: String,
    /// When the key was revoked; `None` while it is valid.
    pub revoked_at: Option<String>,
}

/// Who a valid key speaks for.
#[derive(Clone, Debug, PartialEq)]
pub struct KeyOwner {
    /// The tenant whose jobs and models the request may see.
    pub tenant: String,
    /// Whether the request may act for every tenant.
    pub admin: bool,
}

/// A key just made: `key` is shown to the operator once and stored nowhere.
#[derive(Debug)]
pub struct NewKey {
    /// The key's public id (the start of the key).
    pub id: String,
    /// The whole secret key, `otofit_<id>_<secret>`.
    pub key: String,
}

/// The SHA-256 of a key, as stored.
pub fn key_hash(key: &str) -> [u8; 32] {
    use sha2::Digest;
    sha2::Sha256::digest(key.trim().as_bytes()).into()
}

impl Store {
    /// Makes a key for `tenant` (a plain id, checked by the caller): 256 random bits after
    /// a 48-bit public id. Returns the key, which is not stored.
    pub async fn add_key(&self, tenant: &str, admin: bool) -> Result<NewKey, sqlx::Error> {
        use rand::Rng;
        const SQL: &str = "INSERT INTO api_keys (id, tenant, key_hash, admin, created_at) VALUES ($1, $2, $3, $4, $5)";
        let mut rng = rand::rng();
        let id = format!("{:012x}", rng.random::<u64>() & 0xffff_ffff_ffff);
        let key = format!("otofit_{id}_{}", hex::encode(rng.random::<[u8; 32]>()));
        let (hash, ts) = (hex::encode(key_hash(&key)), now());
        on_pool!(self, p => sqlx::query(SQL)
            .bind(&id)
            .bind(tenant)
            .bind(&hash)
            .bind(admin as i64)
            .bind(&ts)
            .execute(p)
            .await?
            .rows_affected());
        Ok(NewKey { id, key })
    }

    /// Every key, revoked ones included, oldest first.
    pub async fn keys(&self) -> Result<Vec<ApiKey>, sqlx::Error> {
        const SQL: &str = "SELECT id, tenant, admin, created_at, revoked_at FROM api_keys ORDER BY created_at, id";
        Ok(on_pool!(self, p => sqlx::query(SQL).fetch_all(p).await?.iter().map(key_from).collect::<Result<_, _>>()?))
    }

    /// Revokes key `id`: `None` if there is no such key, else whether it was active.
    pub async fn revoke_key(&self, id: &str) -> Result<Option<bool>, sqlx::Error> {
        const SQL: &str = "UPDATE api_keys SET revoked_at = $1 WHERE id = $2 AND revoked_at IS NULL";
        let ts = now();
        let n = on_pool!(self, p => sqlx::query(SQL).bind(&ts).bind(id).execute(p).await?.rows_affected());
        if n == 1 {
            return Ok(Some(true));
        }
        Ok(self.keys().await?.iter().any(|k| k.id == id).then_some(false))
    }

    /// The owner of the active key whose SHA-256 is `hash`.
    pub async fn key_owner(&self, hash: &[u8; 32]) -> Result<Option<KeyOwner>, sqlx::Error> {
        const SQL: &str = "SELECT tenant, admin FROM api_keys WHERE key_hash = $1 AND revoked_at IS NULL";
        let hash = hex::encode(hash);
        Ok(on_pool!(self, p => sqlx::query(SQL)
            .bind(&hash)
            .fetch_optional(p)
            .await?
            .map(|r| Ok::<_, sqlx::Error>(KeyOwner { tenant: r.text("tenant")?, admin: r.int("admin")? != 0 }))
            .transpose()?))
    }

    /// Whether any key was ever made (revoked ones count).
    pub async fn has_keys(&self) -> Result<bool, sqlx::Error> {
        const SQL: &str = "SELECT COUNT(*) FROM api_keys";
        let n: i64 = on_pool!(self, p => sqlx::query_scalar(SQL).fetch_one(p).await?);
        Ok(n > 0)
    }
}

fn key_from(r: &impl Cols) -> Result<ApiKey, sqlx::Error> {
    Ok(ApiKey {
        id: r.text("id")?,
        tenant: r.text("tenant")?,
        admin: r.int("admin")? != 0,
        created_at: r.text("created_at")?,
        revoked_at: r.opt_text("revoked_at")?,
    })
}
