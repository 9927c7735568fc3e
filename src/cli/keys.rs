//! `otofit keys add|list|revoke`: the API keys of a server's database. A key belongs to a
//! tenant; `add` prints it once and stores only its SHA-256. A server whose database holds
//! a key (revoked ones included) needs a key on every route but /health, from then on.

use super::serve::database_arg;
use crate::store::Store;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use std::path::PathBuf;

/// Arguments of `otofit keys`.
#[derive(Args, Debug)]
pub struct KeysArgs {
    /// What to do with the keys.
    #[command(subcommand)]
    pub command: KeysCommand,
    /// The server's database: `sqlite://PATH` (default: DATA_DIR/otofit.db) or
    /// `postgres://USER:PASSWORD@HOST:PORT/DB`.
    #[arg(long, env = "OTOFIT_DATABASE", global = true)]
    pub database: Option<String>,
    /// The server's data directory (where its SQLite database is by default).
    #[arg(long, default_value = "data", global = true)]
    pub data_dir: PathBuf,
}

/// The `otofit keys` subcommands.
#[derive(Subcommand, Debug)]
pub enum KeysCommand {
    /// Make a key for a tenant and print it (once: only its hash is stored).
    Add {
        /// The tenant the key speaks for: 1..=64 of A-Z a-z 0-9 _ -.
        #[arg(long)]
        tenant: String,
        /// The key sees every tenant's jobs, datasets and models (but not the measurements
        /// in other tenants' job params).
        #[arg(long)]
        admin: bool,
    },
    /// Every key: id, tenant, admin, created, revoked (never the key).
    List {
        /// As JSON.
        #[arg(long)]
        json: bool,
    },
    /// Revoke a key by its id (the one `list` shows, also the start of the key).
    Revoke {
        /// The key's id.
        id: String,
    },
}

/// Runs `otofit keys` on the server's database.
pub fn run(args: KeysArgs) -> Result<()> {
    let database = database_arg(args.database.as_deref(), &args.data_dir)?;
    if let crate::store::Database::Sqlite(_) = database {
        std::fs::create_dir_all(&args.data_dir)
            .with_context(|| format!("cannot create {}", args.data_dir.display()))?;
    }
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    rt.block_on(async move {
        let store =
            Store::connect(&database).await.with_context(|| format!("opening the database {}", database.redacted()))?;
        match args.command {
            KeysCommand::Add { tenant, admin } => {
                if !crate::jobs::is_plain_id(&tenant) {
                    bail!("--tenant: '{tenant}' is not a tenant name (1..=64 of A-Z a-z 0-9 _ -)");
                }
                let k = store.add_key(&tenant, admin).await?;
                let role = if admin { " (admin)" } else { "" };
                eprintln!("key {} for tenant '{tenant}'{role}; shown once, stored only as its SHA-256:", k.id);
                println!("{}", k.key);
            }
            KeysCommand::List { json } => {
                let keys = store.keys().await?;
                if json {
                    println!("{}", serde_json::to_string_pretty(&keys)?);
                } else {
                    println!("{:<12}  {:<20}  {:<5}  {:<24}  revoked", "id", "tenant", "admin", "created");
                    for k in keys {
                        let revoked = k.revoked_at.as_deref().unwrap_or("-");
                        println!("{:<12}  {:<20}  {:<5}  {:<24}  {revoked}", k.id, k.tenant, k.admin, k.created_at);
                    }
                }
            }
            KeysCommand::Revoke { id } => match store.revoke_key(&id).await? {
                Some(true) => eprintln!("key {id} revoked"),
                Some(false) => eprintln!("key {id} was already revoked"),
                None => bail!("no key '{id}' (otofit keys list shows them)"),
            },
        }
        Ok(())
    })
}
