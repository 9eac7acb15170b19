//! `crestscan keys`: API keys in a service's data directory, from the machine it runs on (the
//! first admin key comes from here; later ones may come from `POST /v1/keys`).

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use std::path::PathBuf;

#[derive(Args)]
pub struct KeysArgs {
    #[command(subcommand)]
    command: KeysCommand,
}

#[derive(Subcommand)]
enum KeysCommand {
    /// Create a key; the key is printed alone on the last line, once (only its hash is stored).
    Create {
        #[command(flatten)]
        data: DataDir,
        /// Who or what holds it (mes-line-3, ci, ...).
        #[arg(long)]
        name: String,
        /// Comma-separated: read (results), submit (inspections, CMM data), admin (keys, audit; all).
        #[arg(long)]
        scopes: String,
    },
    /// List the keys (id, name, scopes, created, revoked); never their secrets.
    List {
        #[command(flatten)]
        data: DataDir,
    },
    /// Revoke a key by its id (the part after `csk_`); effective at the service's next request.
    Revoke {
        #[command(flatten)]
        data: DataDir,
        id: String,
    },
}

#[derive(Args)]
struct DataDir {
    /// The service's data directory (its database) [default: ./crestscan-data].
    #[arg(long, env = "CRESTSCAN_DATA_DIR")]
    data_dir: Option<PathBuf>,
    /// The service's PostgreSQL, where it keeps its records there (`serve --database-url`).
    #[arg(long, env = "CRESTSCAN_DATABASE_URL", hide_env_values = true)]
    database_url: Option<String>,
}

impl DataDir {
    async fn store(&self) -> Result<crestscan::service::store::Store> {
        let settings = crestscan::service::config::Settings {
            data_dir: self.data_dir.clone().unwrap_or_else(|| crestscan::service::config::Settings::default().data_dir),
            database_url: self.database_url.clone(),
            ..Default::default()
        };
        settings.validate()?;
        std::fs::create_dir_all(&settings.data_dir)
            .with_context(|| format!("creating {}", settings.data_dir.display()))?;
        let database = settings.database();
        crestscan::service::store::Store::connect(&database, &settings.uploads_dir(), &settings.tmp_dir())
            .await
            .with_context(|| format!("opening the database {}", database.describe()))
    }
}

impl KeysArgs {
    pub fn run(self) -> Result<()> {
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        runtime.block_on(self.command.run())
    }
}

impl KeysCommand {
    async fn run(self) -> Result<()> {
        use crestscan::service::auth;
        match self {
            KeysCommand::Create { data, name, scopes } => {
                let scopes = auth::parse_scopes(&scopes).map_err(anyhow::Error::msg).context("--scopes")?;
                let name = auth::key_name(&name).map_err(anyhow::Error::msg).context("--name")?;
                let (row, token) = data.store().await?.create_key(name, &scopes).await?;
                println!("created key {} ({}) with scopes {}; it is shown once:", row.id, row.name, row.scopes);
                println!("{token}");
            }
            KeysCommand::List { data } => {
                for k in data.store().await?.keys().await? {
                    let revoked = k.revoked_at.map_or(String::new(), |t| format!("  revoked {}", rfc3339(t)));
                    println!("{}  {}  {}  created {}{revoked}", k.id, k.name, k.scopes, rfc3339(k.created_at));
                }
            }
            KeysCommand::Revoke { data, id } => {
                let row = data.store().await?.revoke_key(&id).await.map_err(|e| match e {
                    crestscan::service::store::StoreError::NotFound => anyhow::anyhow!("no key {id}"),
                    other => other.into(),
                })?;
                println!("revoked {} ({})", row.id, row.name);
            }
        }
        Ok(())
    }
}

fn rfc3339(ms: i64) -> String {
    crestscan::service::wire::rfc3339(ms)
}
