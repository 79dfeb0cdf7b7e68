//! `wavesplat serve cache` (run the coefficient cache) and `wavesplat cache
//! ingest|list|show|rm` (talk to one). Wiring only: the server lives in `wavesplat-cache`, the
//! client in `wavesplat-client`.

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use std::path::PathBuf;
use wavesplat_cache::{Limits, Store};
use wavesplat_client::blocking::CacheClient;
use wavesplat_client::{VolumeInfo, VolumeKey};

/// Arguments of `wavesplat serve cache`.
#[derive(Args, Debug)]
pub struct ServeCacheArgs {
    /// Database directory (created if missing). With `--store`, only this node's own state:
    /// uploads in progress.
    #[arg(long)]
    pub db: PathBuf,
    /// Keep volumes in an object store shared by any number of cache nodes instead of in
    /// `--db`: `s3://BUCKET/PREFIX` (S3 or a compatible store; endpoint, region and credentials
    /// from the standard variables: AWS_ENDPOINT_URL, AWS_REGION, AWS_ACCESS_KEY_ID,
    /// AWS_SECRET_ACCESS_KEY, and AWS_ALLOW_HTTP=true for a plain-http endpoint) or
    /// `file:///PATH` (a shared file system). Nodes over one store serve the same volumes and
    /// hold nothing another node needs.
    #[arg(long, value_name = "URL")]
    pub store: Option<String>,
    /// With `--store`: memory this node may use to keep packets it read from the store, in MiB.
    #[arg(long, default_value_t = 256, value_name = "MIB")]
    pub read_cache_mib: u64,
    /// Listen address (port 0 picks a free port; the bound address is printed on stdout).
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub addr: String,
    /// Largest accepted upload in MiB.
    #[arg(long, default_value_t = 1024)]
    pub max_upload_mib: u64,
    /// Refinement streams one caller (token identity, or address) may have open at once.
    #[arg(long, default_value_t = 64)]
    pub max_streams_per_caller: usize,
    #[command(flatten)]
    pub security: super::security::ServerSecurityArgs,
}

/// `wavesplat cache …`: client commands.
#[derive(Subcommand, Debug)]
pub enum CacheCommand {
    /// Upload a .wsp file.
    Ingest(IngestArgs),
    /// List stored volumes, one per line, name first.
    List(UrlArgs),
    /// Show a stored volume: its header, size and packet table.
    Show(ShowArgs),
    /// Delete a volume by name.
    Rm(RmArgs),
}

/// Cache address and how to reach it.
#[derive(Args, Debug)]
pub struct UrlArgs {
    /// Cache URL (`http://HOST:PORT`, `https://HOST:PORT` or `HOST:PORT`).
    #[arg(long = "cache", default_value = super::DEFAULT_CACHE_URL)]
    pub url: String,
    #[command(flatten)]
    pub security: super::security::ClientSecurityArgs,
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

/// Arguments of `wavesplat cache show`.
#[derive(Args, Debug)]
pub struct ShowArgs {
    /// Volume name.
    pub name: String,
    /// Print only the first N rows of the packet table (0: none).
    #[arg(long, default_value_t = usize::MAX, hide_default_value = true)]
    pub packets: usize,
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

/// Runs `wavesplat serve cache`.
pub fn run_serve(a: ServeCacheArgs) -> Result<()> {
    let limits = Limits {
        max_upload_bytes: a.max_upload_mib.saturating_mul(1 << 20),
        ..Limits::default()
    };
    let options = wavesplat_cache::ServeOptions {
        security: a.security.security()?,
        fairness: wavesplat_cache::service::Fairness {
            max_streams_per_caller: a.max_streams_per_caller.max(1),
            ..Default::default()
        },
    };
    let rt = runtime()?;
    let store = match &a.store {
        None => Store::open(&a.db, limits).map_err(|e| super::database_error(e, &a.db, "cache"))?,
        Some(url) => rt
            .block_on(Store::open_bucket(
                &a.db,
                url,
                limits,
                a.read_cache_mib.saturating_mul(1 << 20),
            ))
            .with_context(|| format!("opening the object store {url}"))?,
    };
    rt.block_on(async move {
        let listener = super::bind_announced(&a.addr, &options.security).await?;
        let shutdown = super::ctrl_c();
        wavesplat_cache::serve_with(listener, store, options, shutdown).await?;
        Ok(())
    })
}

/// `path` opened, when it is a file that starts as a `.wsp` does.
fn open_plain_wsp(path: &std::path::Path) -> Result<Option<std::fs::File>> {
    use std::io::Read;
    if path.is_dir() {
        return Ok(None);
    }
    let mut file =
        std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut first = [0u8; 4];
    match file.read_exact(&mut first) {
        Ok(()) => Ok((&first == wavesplat_codec::format::MAGIC).then_some(file)),
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Ok(None),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

/// Runs `wavesplat cache …`.
pub fn run(cmd: CacheCommand) -> Result<()> {
    match cmd {
        CacheCommand::Ingest(a) => {
            let name = match a.name {
                Some(n) => n,
                None => a
                    .input
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .context("the input has no file name; pass --name")?,
            };
            // A `.wsp` (or a bricked or series container) is sent from disk as it is read;
            // anything else (an indexed layout to convert, or not a `.wsp` at all) goes through
            // `read_wsp`, which converts it or says what it is. Both before connecting, so that
            // a bad file is reported as such.
            enum Source {
                File(std::fs::File),
                Converted(Vec<u8>),
            }
            let source = match open_plain_wsp(&a.input)? {
                Some(file) => Source::File(file),
                None => Source::Converted(super::read_wsp(&a.input)?),
            };
            let mut cache = connect(&a.url)?;
            let r = match source {
                Source::File(file) => cache.ingest_file(&name, file),
                Source::Converted(bytes) => cache.ingest_owned(&name, bytes),
            }
            .with_context(|| format!("ingesting {}", a.input.display()))?;
            let what = if r.existed {
                "already stored as"
            } else {
                "stored as"
            };
            outln!(
                "{} {what} {:?} (id {})",
                a.input.display(),
                r.volume.name,
                r.volume.id
            );
        }
        CacheCommand::List(a) => {
            for v in connect(&a)?.list().context("listing the cache")? {
                outln!("{}", describe(&v));
            }
        }
        CacheCommand::Show(a) => {
            let mut c = connect(&a.url)?;
            let key = VolumeKey::Name(a.name.clone());
            let h = c
                .header(&key)
                .with_context(|| format!("reading the header of {:?}", a.name))?;
            let table = c
                .packet_table(&key)
                .with_context(|| format!("reading the packet table of {:?}", a.name))?;
            let v = &h.info;
            outln!(
                "volume      {:?} (id {}, sha256 {})",
                v.name,
                v.id,
                v.sha256
            );
            outln!(
                "size        {} bytes: header {} + directory {} + packets {}",
                v.file_bytes,
                v.header_bytes,
                v.file_bytes
                    .saturating_sub(v.header_bytes)
                    .saturating_sub(v.packet_bytes),
                v.packet_bytes
            );
            super::info::print_header(&h.header);
            if let Some(first) = h.bricks.first() {
                outln!(
                    "bricks      {} (the first at {:?}, {}x{}x{} voxels, {} levels); the header \
                     above is the whole's",
                    h.bricks.len(),
                    first.origin,
                    first.header.geometry.dims[0],
                    first.header.geometry.dims[1],
                    first.header.geometry.dims[2],
                    first.header.geometry.levels
                );
            }
            outln!(
                "packets     {} holding {} coefficients",
                v.packet_count,
                v.coefficients
            );
            if a.packets > 0 && !table.is_empty() {
                outln!("packet   tile  layer     bytes     energy");
                for (i, p) in table.iter().enumerate().take(a.packets) {
                    outln!(
                        "{i:6} {:6} {:6} {:9} {:10.3e}",
                        p.tile,
                        p.layer,
                        p.bytes,
                        p.energy
                    );
                }
            }
        }
        CacheCommand::Rm(a) => {
            let id = connect(&a.url)?
                .delete(&VolumeKey::Name(a.name.clone()))
                .with_context(|| format!("deleting {:?}", a.name))?;
            outln!("deleted {:?} (id {id})", a.name);
        }
    }
    Ok(())
}

/// Connects to the cache at `url` (`http://HOST:PORT`, `https://HOST:PORT` or `HOST:PORT`),
/// with the CA and token of `--ca` / `--token-file` or their environment variables.
pub fn connect(url: &UrlArgs) -> Result<CacheClient> {
    let options = url.security.options()?;
    CacheClient::connect_with(&url.url, &options)
        .with_context(|| format!("connecting to the cache at {}", url.url))
}

fn describe(v: &VolumeInfo) -> String {
    let dims: Vec<String> = v.dims.iter().map(|d| d.to_string()).collect();
    format!(
        "{}\tid={}\tdims={}\tchannels={}\tfamily={}\tlevels={}\tbytes={}\tpackets={}\ttiles={}\tlayers={}\tcoefficients={}\tcreated={}",
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
        created(v.created_unix_ms)
    )
}

/// A volume's creation time for people: UTC to the second (RFC 3339).
fn created(unix_ms: u64) -> String {
    let t = std::time::UNIX_EPOCH + std::time::Duration::from_millis(unix_ms);
    humantime::format_rfc3339_seconds(t).to_string()
}
