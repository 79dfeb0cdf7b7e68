//! `wavesplat serve cache` (run the coefficient cache) and `wavesplat cache ingest|list|rm`
//! (talk to one). Wiring only: the server and client live in `wavesplat-cache`.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use std::path::PathBuf;
use wavesplat_cache::{client, Limits, Store, VolumeKey};
use wavesplat_proto::pb;

/// Default cache address.
pub const DEFAULT_URL: &str = "http://127.0.0.1:50051";

/// `wavesplat serve …`: run a service.
#[derive(Subcommand, Debug)]
pub enum ServeCommand {
    /// The coefficient cache (gRPC): stores .wsp volumes, streams view-dependent refinement.
    Cache(ServeCacheArgs),
    /// The batch job orchestrator (gRPC): a durable queue of compression jobs for workers.
    Orchestrator(super::orchestrator::ServeOrchestratorArgs),
}

/// Arguments of `wavesplat serve cache`.
#[derive(Args, Debug)]
pub struct ServeCacheArgs {
    /// Database directory (created if missing).
    #[arg(long)]
    pub db: PathBuf,
    /// Listen address (port 0 picks a free port; the bound address is printed on stdout).
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub addr: String,
    /// Largest accepted upload in MiB.
    #[arg(long, default_value_t = 1024)]
    pub max_upload_mib: u64,
}

/// `wavesplat cache …`: client commands.
#[derive(Subcommand, Debug)]
pub enum CacheCommand {
    /// Upload a .wsp file.
    Ingest(IngestArgs),
    /// List stored volumes, one per line, name first.
    List(UrlArgs),
    /// Delete a volume by name.
    Rm(RmArgs),
}

/// Cache address.
#[derive(Args, Debug)]
pub struct UrlArgs {
    /// Cache URL (`http://HOST:PORT` or `HOST:PORT`).
    #[arg(long = "cache", default_value = DEFAULT_URL)]
    pub url: String,
}

/// Arguments of `wavesplat cache ingest`.
#[derive(Args, Debug)]
pub struct IngestArgs {
    /// The .wsp file.
    pub input: PathBuf,
    /// Name to store it under (default: the file stem).
    #[arg(long)]
    pub name: Option<String>,
    #[command(flatten)]
    pub url: UrlArgs,
}

/// Arguments of `wavesplat cache rm`.
#[derive(Args, Debug)]
pub struct RmArgs {
    /// Volume name.
    pub name: String,
    #[command(flatten)]
    pub url: UrlArgs,
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

fn url(u: &str) -> String {
    if u.contains("://") {
        u.to_string()
    } else {
        format!("http://{u}")
    }
}

/// Runs `wavesplat serve …`.
pub fn run_serve(cmd: ServeCommand) -> Result<()> {
    let a = match cmd {
        ServeCommand::Cache(a) => a,
        ServeCommand::Orchestrator(a) => return super::orchestrator::run_serve(a),
    };
    let limits = Limits {
        max_upload_bytes: a.max_upload_mib.saturating_mul(1 << 20),
        ..Limits::default()
    };
    let store = Store::open(&a.db, limits)
        .with_context(|| format!("opening the cache database {}", a.db.display()))?;
    runtime()?.block_on(async move {
        let listener = super::bind_announced(&a.addr).await?;
        let shutdown = super::ctrl_c();
        wavesplat_cache::serve(listener, store, shutdown).await?;
        Ok(())
    })
}

/// Runs `wavesplat cache …`.
pub fn run(cmd: CacheCommand) -> Result<()> {
    runtime()?.block_on(async move {
        match cmd {
            CacheCommand::Ingest(a) => {
                let bytes = std::fs::read(&a.input)
                    .with_context(|| format!("reading {}", a.input.display()))?;
                let name = match a.name {
                    Some(n) => n,
                    None => a
                        .input
                        .file_stem()
                        .map(|s| s.to_string_lossy().into_owned())
                        .context("the input has no file name; pass --name")?,
                };
                let mut c = connect(&a.url.url).await?;
                let r = client::ingest(&mut c, &name, &bytes)
                    .await
                    .with_context(|| format!("ingesting {}", a.input.display()))?;
                let v = r.volume.context("the cache returned no volume")?;
                let what = if r.existed {
                    "already stored as"
                } else {
                    "stored as"
                };
                outln!("{} {what} {:?} (id {})", a.input.display(), v.name, v.id);
            }
            CacheCommand::List(a) => {
                let mut c = connect(&a.url).await?;
                let list = c.list(pb::ListRequest {}).await?.into_inner();
                for v in list.volumes {
                    outln!("{}", describe(&v));
                }
            }
            CacheCommand::Rm(a) => {
                let mut c = connect(&a.url.url).await?;
                let key = VolumeKey::Name(a.name.clone());
                let r = c
                    .delete(pb::DeleteRequest {
                        volume: Some(wavesplat_cache::convert::volume_ref(&key)),
                    })
                    .await
                    .with_context(|| format!("deleting {:?}", a.name))?;
                outln!("deleted {:?} (id {})", a.name, r.into_inner().id);
            }
        }
        Ok(())
    })
}

async fn connect(u: &str) -> Result<pb::cache_client::CacheClient<tonic::transport::Channel>> {
    let u = url(u);
    if u.is_empty() {
        bail!("empty cache URL");
    }
    client::connect(&u)
        .await
        .with_context(|| format!("connecting to the cache at {u}"))
}

fn describe(v: &pb::VolumeInfo) -> String {
    let dims: Vec<String> = v.dims.iter().map(|d| d.to_string()).collect();
    format!(
        "{}\tid={}\tdims={}\tchannels={}\tfamily={}\tlevels={}\tbytes={}\tpackets={}\ttiles={}\tlayers={}\tcoefficients={}\tcreated_ms={}",
        v.name,
        v.id,
        dims.join("x"),
        v.channels,
        v.family,
        v.levels,
        v.file_bytes,
        v.packet_count,
        v.tile_count,
        v.layer_count,
        v.coefficients,
        v.created_unix_ms
    )
}
