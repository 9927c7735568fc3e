//! Migrations whose comments were reworded after release. sqlx refuses to run when an
//! applied migration's checksum (SHA-384 of its text) differs from the file's, so a
//! database migrated with the old wording would no longer open. Before migrating, the
//! stored checksum of each such migration is moved from its old wording's to the new
//! one's — only when it is exactly the old wording's, so a migration changed in any
//! other way is still refused.

use super::{Pool, Store};
use sqlx::migrate::Migrator;

/// (version, SHA-384 in hex of the text as first released), SQLite tree.
pub(super) const SQLITE: [(i64, &str); 4] = [
    (2, "40688739b960fbb61afd6a6440f6ddb80e77c18bb20f85e0c0196d929943ef5543c687b8f33a03a140fadf095da6334a"),
    (3, "5e8c1ee0b5da65d3325926acc89e4766911c67f5e31a3624bc4c86d343dd555d936cfdf61a45fba893717f3c48191399"),
    (4, "826d8dfd4a80669c0eec0a8c77d17c2cf8de129d41163faf768166228ef4c662406fccdf9b85822df2e24416afb7fc47"),
    (5, "292b9d5e4aac3cdd414486c27f6b61ac5543c624b35caeadbbd6660d304aee417c4341c16227b48491b7bf85f73c8f8c"),
];

/// The same for the PostgreSQL tree.
pub(super) const POSTGRES: [(i64, &str); 1] =
    [(3, "00697cc548db7905e80717a0a46c9276848e34266ed456173b7d5081cd31548ccd9521d86ee6a9b305387fa31245eb79")];

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex constant")).collect()
}

/// (version, old checksum, new checksum) for each reworded migration of `migrator`.
fn moves(migrator: &Migrator, old: &[(i64, &str)]) -> Vec<(i64, Vec<u8>, Vec<u8>)> {
    old.iter()
        .filter_map(|&(v, hex)| {
            let now = migrator.iter().find(|m| m.version == v)?;
            Some((v, unhex(hex), now.checksum.to_vec()))
        })
        .collect()
}

/// Moves the old wordings' checksums to the new ones in the store's database, for the
/// reworded migrations `released` of `migrator`'s tree.
pub(super) async fn repair(store: &Store, migrator: &Migrator, released: &[(i64, &str)]) -> Result<(), sqlx::Error> {
    const SQLITE_TABLE: &str = "SELECT name FROM sqlite_master WHERE type = 'table' AND name = '_sqlx_migrations'";
    const POSTGRES_TABLE: &str = "SELECT table_name::text FROM information_schema.tables \
         WHERE table_schema = current_schema() AND table_name = '_sqlx_migrations'";
    let table: Option<(String,)> = match &store.pool {
        Pool::Sqlite(p) => sqlx::query_as(SQLITE_TABLE).fetch_optional(p).await?,
        Pool::Postgres(p) => sqlx::query_as(POSTGRES_TABLE).fetch_optional(p).await?,
    };
    if table.is_none() {
        return Ok(()); // a new database: nothing applied yet
    }
    const SQL: &str = "UPDATE _sqlx_migrations SET checksum = $1 WHERE version = $2 AND checksum = $3";
    for (v, old, new) in moves(migrator, released) {
        on_pool!(store, p => sqlx::query(SQL).bind(&new).bind(v).bind(&old).execute(p).await?.rows_affected());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::{POSTGRES_MIGRATIONS as POSTGRES_MIGRATOR, SQLITE_MIGRATIONS as SQLITE_MIGRATOR};
    use super::*;
    use sha2::{Digest, Sha384};

    /// The repair relies on sqlx's checksum being SHA-384 of the file's text, as the
    /// old constants were computed (`sha384sum` of the released files).
    #[test]
    fn sqlx_checksums_are_sha384_of_the_files() {
        for (m, dir) in [(&SQLITE_MIGRATOR, "migrations"), (&POSTGRES_MIGRATOR, "migrations/postgres")] {
            for mig in m.iter() {
                let name = format!("{:04}_{}.sql", mig.version, mig.description.replace(' ', "_"));
                let path = format!("{}/../../{dir}/{name}", env!("CARGO_MANIFEST_DIR"));
                let text = std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
                assert_eq!(Sha384::digest(&text).as_slice(), &*mig.checksum, "{path}");
            }
        }
    }

    #[test]
    fn every_reworded_migration_has_a_new_checksum() {
        for (m, old) in [(&SQLITE_MIGRATOR, &SQLITE[..]), (&POSTGRES_MIGRATOR, &POSTGRES[..])] {
            let moved = moves(m, old);
            assert_eq!(moved.len(), old.len(), "a reworded migration is missing from its tree");
            for (v, old, new) in moved {
                assert_ne!(old, new, "migration {v}: its old and new wordings have the same checksum");
            }
        }
    }
}

/// A database migrated with the old wordings (their checksums put back) opens, and its
/// checksums become the new ones; a checksum that is neither is still refused.
#[cfg(test)]
mod reopen {
    use super::super::SQLITE_MIGRATIONS;
    use super::*;
    use crate::store::{Pool, Store};

    /// Migrates a new database at `path`, then stores `sums` as its applied checksums.
    async fn set_checksums(path: &std::path::Path, sums: &[(i64, Vec<u8>)]) {
        let store = Store::open(path).await.unwrap();
        let Pool::Sqlite(pool) = &store.pool else { unreachable!() };
        for (v, sum) in sums {
            sqlx::query("UPDATE _sqlx_migrations SET checksum = ? WHERE version = ?")
                .bind(sum)
                .bind(v)
                .execute(pool)
                .await
                .unwrap();
        }
        pool.close().await;
    }

    async fn checksum(path: &std::path::Path, v: i64) -> Vec<u8> {
        let store = Store::open(path).await.unwrap();
        let Pool::Sqlite(pool) = &store.pool else { unreachable!() };
        let (sum,): (Vec<u8>,) = sqlx::query_as("SELECT checksum FROM _sqlx_migrations WHERE version = ?")
            .bind(v)
            .fetch_one(pool)
            .await
            .unwrap();
        pool.close().await;
        sum
    }

    #[tokio::test]
    async fn a_database_migrated_with_the_old_wording_still_opens() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("otofit.db");
        let old: Vec<_> = SQLITE.iter().map(|&(v, hex)| (v, unhex(hex))).collect();
        set_checksums(&path, &old).await;
        for (v, _) in SQLITE {
            let now = SQLITE_MIGRATIONS.iter().find(|m| m.version == v).unwrap();
            assert_eq!(checksum(&path, v).await, now.checksum.to_vec(), "migration {v}");
        }
    }

    #[tokio::test]
    async fn a_migration_changed_otherwise_is_still_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("otofit.db");
        set_checksums(&path, &[(3, vec![7u8; 48])]).await;
        let e = Store::open(&path).await.err().expect("a foreign checksum must be refused");
        assert!(e.to_string().contains('3'), "{e}");
    }
}
