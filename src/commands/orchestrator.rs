//! `wavesplat serve orchestrator`, `wavesplat worker`, `wavesplat archive submit` and
//! `wavesplat jobs list|watch|cancel|retry`. Wiring and display only: the queue and the service
//! live in `wavesplat-orchestrator`, the worker and archive scanning (which reads every volume
//! format) in `wavesplat-worker`.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use std::collections::HashSet;
use std::path::PathBuf;
use wavesplat_compressor::encode::Target;
use wavesplat_harness::console::{describe, part_label, watch};
use wavesplat_orchestrator::model;
use wavesplat_orchestrator::{JobOptions, QueueOptions, ServiceOptions, Store, TargetSpec};
use wavesplat_orchestrator_client as client;
use wavesplat_orchestrator_client::convert::state_name;
use wavesplat_proto::pb;
use wavesplat_worker::archive;

/// Arguments of `wavesplat serve orchestrator`.
#[derive(Args, Debug)]
#[command(group(clap::ArgGroup::new("store").required(true).args(["db", "queue"])))]
pub struct ServeOrchestratorArgs {
    /// Keep the queue in this directory (an embedded sled database, created if missing; one
    /// orchestrator owns it). The default store: nothing else to run.
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// Keep the queue in a PostgreSQL database instead, shared by any number of orchestrators
    /// (each stateless: give workers and clients all their URLs). `postgres://USER@HOST:PORT/DB`;
    /// the password from the URL, PGPASSWORD or ~/.pgpass; `?sslmode=require` (or
    /// `verify-full`, with `sslrootcert=FILE`) for TLS to the database. The schema is created
    /// or upgraded at start.
    #[arg(long, value_name = "URL")]
    pub queue: Option<String>,
    /// Connections to the queue database.
    #[arg(long, default_value_t = 16, requires = "queue")]
    pub queue_connections: u32,
    /// Listen address (port 0 picks a free port; the bound address is printed on stdout).
    #[arg(long, default_value = "127.0.0.1:50052")]
    pub addr: String,
    /// A lease lapses this many seconds after a worker's last heartbeat; the job is then
    /// queued again for another worker.
    #[arg(long, default_value_t = 30.0)]
    pub lease_secs: f64,
    /// Heartbeat interval asked of workers, in ms (default: a quarter of the lease).
    #[arg(long)]
    pub heartbeat_ms: Option<u64>,
    /// Attempts per job before it fails for good (permanent failures such as invalid input
    /// are not retried).
    #[arg(long, default_value_t = 3)]
    pub max_attempts: u32,
    /// Backoff before the second attempt, in ms; doubles per attempt, at most 60 s.
    #[arg(long, default_value_t = 2000)]
    pub retry_base_ms: u64,
    /// Longest an idle worker waits before asking for work again, in ms.
    #[arg(long, default_value_t = 1000)]
    pub poll_ms: u64,
    /// Largest accepted upload (`archive submit --upload`) in MiB.
    #[arg(long, default_value_t = 1024)]
    pub max_upload_mib: u64,
    /// Confirm each delivery with this cache (it must hold the job's name as the reported
    /// volume and content) before marking the job done; --ca and --token-file (a `read`
    /// token) apply to this connection.
    #[arg(long, value_name = "URL")]
    pub cache: Option<String>,
    #[command(flatten)]
    pub cache_security: super::security::ClientSecurityArgs,
    #[command(flatten)]
    pub security: super::security::ServerSecurityArgs,
}

/// Arguments of `wavesplat worker`.
#[derive(Args, Debug)]
pub struct WorkerArgs {
    /// Orchestrator URL; several, comma-separated, for orchestrators sharing one PostgreSQL
    /// queue: requests go to the first that answers and fail over to the next.
    #[arg(long, default_value = super::DEFAULT_ORCHESTRATOR_URL)]
    pub orchestrator: String,
    /// Cache URL the results are delivered to.
    #[arg(long, default_value = super::DEFAULT_CACHE_URL)]
    pub cache: String,
    /// Compression threads (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Worker identity shown in job listings (default: host name and process id).
    #[arg(long)]
    pub id: Option<String>,
    /// Exit after this many jobs.
    #[arg(long)]
    pub max_jobs: Option<usize>,
    /// Directory for temporary files (default: $TMPDIR, else /tmp): an uploaded bricked job's
    /// source is streamed there (as large as the upload; a bundle of files unpacked), a
    /// compressed source (.nii.gz) is inflated there, and a bricked job compressed here keeps
    /// its coded bricks there until its file is assembled (about the file's size). Give a disk
    /// with room when /tmp is small or in memory (tmpfs). Uploads that a killed worker left
    /// there are removed when a worker starts.
    #[arg(long, value_name = "DIR")]
    pub scratch_dir: Option<std::path::PathBuf>,
    /// Testing aid: pause this long (ms) after compressing each volume, before uploading.
    #[arg(long, default_value_t = 0, hide = true)]
    pub pause_before_upload_ms: u64,
    /// Testing aid: pause this long (ms) after computing each part of a spread job, before
    /// reporting it.
    #[arg(long, default_value_t = 0, hide = true)]
    pub pause_before_part_report_ms: u64,
    /// CA and token for both services (the token needs `worker` at the orchestrator and
    /// `ingest` at the cache).
    #[command(flatten)]
    pub security: super::security::ClientSecurityArgs,
}

/// Compressor options of submitted jobs (the same meaning as in `wavesplat compress`).
#[derive(Args, Debug, Clone)]
pub struct JobOptionArgs {
    /// Wavelet family: haar, linear, cubic.
    #[arg(long, default_value = "linear")]
    pub family: String,
    /// Decomposition depth M (default: automatic).
    #[arg(long)]
    pub levels: Option<usize>,
    /// Colour space for RGB volumes: rgb, yiq, pca.
    #[arg(long, default_value = "pca")]
    pub colorspace: String,
    /// Quantization bits P (1..=16).
    #[arg(long, default_value_t = 8)]
    pub bits: u8,
    /// Quantizer step of the sigmap coder.
    #[arg(long, default_value_t = 1.0)]
    pub step: f64,
    /// Entropy coder: sigmap, fast, range, huffman (see `compress --help`).
    #[arg(long, default_value = "sigmap")]
    pub coder: String,
    /// What to keep.
    #[command(flatten)]
    pub keep: super::TargetArgs,
    /// Tile edge in voxels (default: automatic).
    #[arg(long)]
    pub tile: Option<usize>,
    /// Quality layers (default: automatic).
    #[arg(long)]
    pub layers: Option<usize>,
    /// Each quality layer holds G times the coefficients of all layers before it (default 16;
    /// 4 streams a finer progression in file order for ~8–11 % more bytes).
    #[arg(long, value_name = "G")]
    pub layer_growth: Option<f64>,
    /// Rounds of least-squares refinement of the kept set (default 3; splines only).
    #[arg(long)]
    pub refine_rounds: Option<usize>,
    /// Send the oracle's coefficients unchanged (no least-squares refinement).
    #[arg(long)]
    pub no_refine: bool,
    /// Compress each volume as a bricked volume in bricks of at most N voxels a side
    /// (8..=1024; linear or haar): the worker reads a raw, NIfTI, NRRD or MetaImage file on
    /// shared storage brick by brick, so its memory is about one brick per thread whatever the
    /// volume's size (see `compress --brick`).
    #[arg(long, value_name = "N")]
    pub brick: Option<usize>,
    /// Of a time series (a 4D NIfTI, a DICOM cine directory): compress its time points
    /// together in groups of G (a power of two; 1: each alone), as `compress --time-group`.
    /// Default 8.
    #[arg(long, value_name = "G")]
    pub time_group: Option<usize>,
    /// Compression effort: fast, default, best (see `compress --help`).
    #[arg(long, default_value = "default")]
    pub effort: String,
}

impl JobOptionArgs {
    /// Validated job options.
    pub fn options(&self) -> Result<JobOptions> {
        let target = match self.keep.target() {
            Target::Bytes(b) => TargetSpec::Bytes(b),
            Target::Fraction(f) => TargetSpec::Fraction(f),
            Target::Coefficients(c) => TargetSpec::Coefficients(c),
            Target::QvPercent(q) => TargetSpec::QvPercent(q),
            Target::All => TargetSpec::All,
        };
        Ok(JobOptions {
            family: model::parse_family(&self.family)?,
            levels: self.levels,
            colorspace: model::parse_colorspace(&self.colorspace)?,
            bits: self.bits,
            step: self.step,
            coder: model::parse_coder(&self.coder)?,
            target,
            tile: self.tile,
            layers: self.layers,
            refine_rounds: self.refine_rounds,
            no_refine: self.no_refine,
            layer_growth: self.layer_growth,
            brick: self.brick,
            time_group: self.time_group,
            effort: model::parse_effort(&self.effort)?,
            memory_limit: None,
        }
        .validate()?)
    }
}

/// `wavesplat archive …`.
#[derive(Subcommand, Debug)]
pub enum ArchiveCommand {
    /// Submit every supported volume under DIR as one job each, then show progress until all
    /// are finished (unless --detach).
    ///
    /// Supported: DICOM (a directory of DICOM files is one volume, named by its path), NRRD
    /// (`*.nrrd`, `*.nhdr` + data file), MetaImage (`*.mha`, `*.mhd` + data file), NIfTI-1
    /// (`*.nii`, `*.nii.gz`, scalar or RGB24) and headerless raw files named
    /// `NAME_XxYxZ_DTYPE[_rgb][_be].raw` (DTYPE u8, i8, u16, i16, u32, i32, u64, i64, f32 or f64; `_rgb`: 3 channels
    /// interleaved per voxel; `_be`: big-endian; x fastest), e.g. `head_256x256x128_u16.raw`.
    /// The cache name is the relative path without extension and layout suffix (`ct/head`).
    /// Each volume's files are hashed (SHA-256); one already submitted with the same options is
    /// skipped.
    Submit(SubmitArgs),
}

/// Arguments of `wavesplat archive submit`.
#[derive(Args, Debug)]
pub struct SubmitArgs {
    /// Archive directory (scanned recursively).
    pub dir: PathBuf,
    /// Orchestrator URL; several, comma-separated, for orchestrators sharing one PostgreSQL
    /// queue: requests go to the first that answers and fail over to the next.
    #[arg(long, default_value = super::DEFAULT_ORCHESTRATOR_URL)]
    pub orchestrator: String,
    /// Stream each file's bytes to the orchestrator instead of passing its path (use when the
    /// workers do not share this machine's storage).
    #[arg(long)]
    pub upload: bool,
    /// Return after submitting instead of watching the jobs.
    #[arg(long)]
    pub detach: bool,
    /// Put this before every volume's name in the cache (e.g. `study2/`), so the same files
    /// compressed again with other options land beside the first ones instead of failing on
    /// names already taken.
    #[arg(long, default_value = "")]
    pub name_prefix: String,
    /// Put this after every volume's name in the cache (e.g. `_cubic` for `--family cubic`).
    #[arg(long, default_value = "")]
    pub name_suffix: String,
    /// A directory whose volume files are numbered time steps (`step_0000.nii.gz`,
    /// `step_0010.nii.gz`, …) is one time series, named by the directory (without this, each
    /// file is a volume of its own). 4D NIfTI files and DICOM cines are series either way.
    #[arg(long)]
    pub time_steps: bool,
    /// Each worker's memory for a job (bytes, or with a K, M or G suffix: `8G`); default: the
    /// memory available on this machine, and no limit on the workers. A volume given without
    /// --brick that would need more to compress whole (or has more voxels than one transform
    /// takes) is submitted as a bricked job instead, in the largest bricks of 256, 128, 64 or
    /// 32 a side of which one fits, as `compress` bricks a file by itself; its bricks spread
    /// over the workers when they read it on shared storage. Without it, only files larger
    /// than 1/64 of the memory available are probed. Given, the jobs carry it and their
    /// workers keep to it: a volume compressed whole that would need more fails (kind
    /// compress; refused from its header, before it is read) instead of running out of memory,
    /// and a bricked job's workers keep its bricks' top coefficients only in what one brick
    /// leaves. Part of a job's identity: the same volume submitted again with another limit is
    /// a new job. A time series is not bricked by it.
    #[arg(long, value_parser = super::parse_bytes)]
    pub memory_limit: Option<u64>,
    #[command(flatten)]
    pub security: super::security::ClientSecurityArgs,
    #[command(flatten)]
    pub options: JobOptionArgs,
}

/// `wavesplat jobs …`.
#[derive(Subcommand, Debug)]
pub enum JobsCommand {
    /// One line per job: id, state, name, attempts, progress, worker, error (the parts of
    /// bricked and time series jobs with --parts).
    List(JobsListArgs),
    /// Show progress bars until every job is finished.
    Watch(JobsUrl),
    /// Cancel a queued or running job (a running worker discards its result).
    Cancel(JobIdArgs),
    /// Queue a failed or cancelled job again with a fresh attempt budget.
    Retry(JobIdArgs),
}

/// Orchestrator address and how to reach it.
#[derive(Args, Debug)]
pub struct JobsUrl {
    /// Orchestrator URL; several, comma-separated, for orchestrators sharing one PostgreSQL
    /// queue: requests go to the first that answers and fail over to the next.
    #[arg(long, default_value = super::DEFAULT_ORCHESTRATOR_URL)]
    pub orchestrator: String,
    #[command(flatten)]
    pub security: super::security::ClientSecurityArgs,
}

/// `jobs list`.
#[derive(Args, Debug)]
pub struct JobsListArgs {
    /// List the parts of bricked and time series jobs too (one per brick, or series unit, and
    /// step, labelled with their job); without it they are counted on a last line.
    #[arg(long)]
    pub parts: bool,
    #[command(flatten)]
    pub url: JobsUrl,
}

/// A job id.
#[derive(Args, Debug)]
pub struct JobIdArgs {
    /// Job id.
    pub id: u64,
    #[command(flatten)]
    pub url: JobsUrl,
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

async fn connect(
    url: &str,
    security: &super::security::ClientSecurityArgs,
) -> Result<client::Client> {
    client::connect_with(url, &security.options()?)
        .await
        .with_context(|| format!("connecting to the orchestrator at {url}"))
}

/// `e` with what a failure at the transport means, when it does: a plaintext URL against a
/// server that speaks TLS ([`wavesplat_net::tls::explain_status`]).
async fn explain(url: &str, e: anyhow::Error) -> anyhow::Error {
    let Some(s) = e.chain().find_map(|c| c.downcast_ref::<tonic::Status>()) else {
        return e;
    };
    let explained = wavesplat_net::tls::explain_status(url, s.clone()).await;
    if explained.message() == s.message() {
        return e;
    }
    e.context(explained.message().to_string())
}

/// Runs `wavesplat serve orchestrator`.
pub fn run_serve(a: ServeOrchestratorArgs) -> Result<()> {
    if !(a.lease_secs.is_finite() && a.lease_secs > 0.0) {
        bail!("--lease-secs {} must be positive", a.lease_secs);
    }
    let lease_ms = (a.lease_secs * 1000.0).round().max(1.0) as u64;
    let config = ServiceOptions {
        queue: QueueOptions {
            lease_ms,
            heartbeat_ms: a.heartbeat_ms.unwrap_or((lease_ms / 4).max(1)),
            max_attempts: a.max_attempts,
            backoff_base_ms: a.retry_base_ms,
            backoff_max_ms: 60_000.max(a.retry_base_ms),
        }
        .validate()?,
        poll_ms: a.poll_ms.max(1),
        max_upload_bytes: a.max_upload_mib.saturating_mul(1 << 20),
    };
    let delivery_check = match &a.cache {
        Some(url) => Some(wavesplat_orchestrator::DeliveryCheck::new(
            url,
            &a.cache_security.options()?,
        )?),
        None => None,
    };
    let options = wavesplat_orchestrator::ServeOptions {
        security: a.security.security()?,
        delivery_check,
    };
    let embedded = match &a.db {
        Some(db) => {
            Some(Store::open(db).map_err(|e| super::database_error(e, db, "orchestrator"))?)
        }
        None => None,
    };
    runtime()?.block_on(async move {
        let store: wavesplat_orchestrator::Backend = match (embedded, &a.queue) {
            (Some(store), _) => store.into(),
            (None, Some(url)) => {
                let pg = wavesplat_orchestrator::PostgresQueue::connect(
                    url,
                    wavesplat_orchestrator::PostgresOptions {
                        max_connections: a.queue_connections,
                        ..Default::default()
                    },
                )
                .await
                .context("opening the queue database")?
                .with_options(config.queue);
                pg.check_clock().await?;
                pg.into()
            }
            (None, None) => bail!("give --db DIR or --queue postgres://…"),
        };
        let listener = super::bind_announced(&a.addr, &options.security).await?;
        let shutdown = super::ctrl_c();
        wavesplat_orchestrator::serve_with(listener, store, config, options, shutdown).await?;
        Ok(())
    })
}

/// Runs `wavesplat worker`.
pub fn run_worker(a: WorkerArgs) -> Result<()> {
    if let Some(dir) = &a.scratch_dir {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating the scratch directory {}", dir.display()))?;
        // Every temporary file of this process goes there (uploads, inflated sources).
        let _ = tempfile::env::override_temp_dir(dir);
    }
    let cfg = wavesplat_worker::WorkerOptions {
        orchestrator: a.orchestrator,
        cache: a.cache,
        threads: a.threads,
        id: a.id.unwrap_or_else(wavesplat_worker::default_worker_id),
        max_jobs: a.max_jobs,
        pause_before_upload_ms: a.pause_before_upload_ms,
        pause_before_part_report_ms: a.pause_before_part_report_ms,
        connect: a.security.options()?,
    };
    runtime()?.block_on(async move {
        // SIGINT or SIGTERM (what Kubernetes and batch schedulers send): finish the current
        // job, then stop.
        let shutdown = async {
            #[cfg(unix)]
            {
                use tokio::signal::unix::{signal, SignalKind};
                match signal(SignalKind::terminate()) {
                    Ok(mut term) => {
                        tokio::select! {
                            _ = tokio::signal::ctrl_c() => {}
                            _ = term.recv() => {}
                        }
                    }
                    Err(_) => {
                        let _ = tokio::signal::ctrl_c().await;
                    }
                }
            }
            #[cfg(not(unix))]
            let _ = tokio::signal::ctrl_c().await;
            tracing::info!("finishing the current job, then stopping");
        };
        wavesplat_worker::run(cfg, shutdown).await?;
        Ok(())
    })
}

/// Runs `wavesplat archive …`.
pub fn run_archive(cmd: ArchiveCommand) -> Result<()> {
    let ArchiveCommand::Submit(a) = cmd;
    // The workers keep to the limit too: the job carries it.
    let options = JobOptions {
        memory_limit: a.memory_limit,
        ..a.options.options()?
    }
    .validate()?;
    let scan = archive::scan_with(&a.dir, a.time_steps)
        .with_context(|| format!("scanning {}", a.dir.display()))?;
    for (path, why) in &scan.skipped {
        eprintln!("skipped {}: {why}", path.display());
    }
    if scan.found.is_empty() {
        bail!("no supported volumes under {}", a.dir.display());
    }
    let url = a.orchestrator.clone();
    runtime()?.block_on(async move {
        match submit_all(a, &scan, &options).await {
            Err(e) => Err(explain(&url, e).await),
            ok => ok,
        }
    })
}

/// The options the found volume `f` is submitted with: `options`, with a brick side when they
/// name none, `f` is one volume (a time series is bricked by its own rule) and compressing it
/// whole would not fit `limit` (each worker's memory; else the memory available here), as
/// `compress` bricks a file by itself (`compress::probe_file_for_bricks`, one brick at a time:
/// a worker runs one part at a time). Says so when it bricks.
fn submit_options(
    f: &archive::Found,
    options: &JobOptions,
    limit: Option<u64>,
) -> Result<JobOptions> {
    if options.brick.is_some() {
        return Ok(options.clone());
    }
    let raw = f.raw.as_ref().map(wavesplat_worker::options::raw_spec);
    if archive::is_series_source(&f.path, raw.as_ref()) {
        return Ok(options.clone());
    }
    let opts = wavesplat_compressor::encode::CompressOptions {
        memory_limit: limit,
        ..wavesplat_worker::options::compress_options(options)
    };
    // A cubic job is not bricked (the family has no bricks yet).
    if opts.family == wavesplat_codec::family::Family::Cubic {
        return Ok(options.clone());
    }
    // A file that cannot be probed is submitted as it is: its worker says what is wrong with it
    // (as for any job).
    let probed = super::compress::probe_file_for_bricks(&f.path, raw.as_ref(), f.channel, &opts, 1)
        .unwrap_or_else(|e| {
            tracing::debug!(path = %f.path.display(), "not probed for bricks: {e:#}");
            None
        });
    Ok(match probed {
        Some((side, why)) => {
            eprintln!(
                "note: {}: {why}: submitted as bricks of at most {side} voxels a side, each \
                 compressed on its own (--brick N chooses the side)",
                f.path.display()
            );
            JobOptions {
                brick: Some(side),
                ..options.clone()
            }
        }
        None => options.clone(),
    })
}

/// A source's bytes, uploaded with each job that reads it (a Zarr store's channels).
type SharedBytes = std::sync::Arc<Vec<u8>>;

async fn submit_all(a: SubmitArgs, scan: &archive::Scan, options: &JobOptions) -> Result<()> {
    let mut c = connect(&a.orchestrator, &a.security).await?;
    let mut ids = HashSet::new();
    let (mut new, mut known, mut unreadable) = (0, 0, 0);
    // The last source hashed (and its bytes, when uploaded): the channels of one Zarr store
    // follow one another, and it is listed and hashed once for all of them.
    let mut hashed: Option<(PathBuf, model::JobSpec, Option<SharedBytes>)> = None;
    for f in &scan.found {
        let f = &archive::Found {
            name: format!("{}{}{}", a.name_prefix, f.name, a.name_suffix),
            ..f.clone()
        };
        let options = &submit_options(f, options, a.memory_limit)?;
        let (spec, bytes) = match &hashed {
            Some((path, spec, bytes)) if *path == f.path && f.channel.is_some() => (
                model::JobSpec {
                    name: f.name.clone(),
                    channel: f.channel.map(|c| c as u32),
                    options: options.clone(),
                    ..spec.clone()
                },
                bytes.clone(),
            ),
            _ => match archive::job_spec(f, options, a.upload) {
                Ok((spec, bytes)) => (spec, bytes.map(std::sync::Arc::new)),
                Err(e) => {
                    // Said, and the rest submitted: one unreadable volume (a store whose files
                    // cannot be listed, a file gone) does not hold back the archive.
                    eprintln!("error: reading {}: {e}; not submitted", f.path.display());
                    unreadable += 1;
                    continue;
                }
            },
        };
        hashed = Some((f.path.clone(), spec.clone(), bytes.clone()));
        let bytes = bytes.as_deref().map(Vec::as_slice);
        let r = client::submit(&mut c, &spec, bytes)
            .await
            .with_context(|| format!("submitting {}", f.path.display()))?;
        let job = r.job.context("the orchestrator returned no job")?;
        let what = if r.existed {
            known += 1;
            "already known as"
        } else {
            new += 1;
            "submitted as"
        };
        // A channel of a store is told by its name.
        let channel = match f.channel {
            Some(_) => format!(" as {}", f.name),
            None => String::new(),
        };
        outln!(
            "{}{channel} {what} job {} ({})",
            f.path.display(),
            job.id,
            state_name(job.state)
        );
        ids.insert(job.id);
    }
    let unread = match unreadable {
        0 => String::new(),
        n => format!(", {n} not read (said above)"),
    };
    outln!("{new} submitted, {known} already known{unread}");
    let watched = if a.detach {
        Ok(())
    } else {
        watch(&mut c, Some(&ids), &mut crate::Stdout).await
    };
    if unreadable > 0 {
        watched?;
        bail!("{unreadable} volume(s) could not be read and were not submitted (said above)");
    }
    watched
}

/// Runs `wavesplat jobs …`.
pub fn run_jobs(cmd: JobsCommand) -> Result<()> {
    let url = match &cmd {
        JobsCommand::List(a) => a.url.orchestrator.clone(),
        JobsCommand::Watch(u) => u.orchestrator.clone(),
        JobsCommand::Cancel(a) | JobsCommand::Retry(a) => a.url.orchestrator.clone(),
    };
    runtime()?.block_on(async move {
        match jobs(cmd).await {
            Err(e) => Err(explain(&url, e).await),
            ok => ok,
        }
    })
}

async fn jobs(cmd: JobsCommand) -> Result<()> {
    match cmd {
        JobsCommand::List(a) => {
            let mut c = connect(&a.url.orchestrator, &a.url.security).await?;
            let mut hidden = 0usize;
            for j in client::list(&mut c).await? {
                if part_label(&j).is_some() && !a.parts {
                    hidden += 1;
                    continue;
                }
                outln!("{}", describe(&j));
            }
            if hidden > 0 {
                outln!("({hidden} parts of bricked or series jobs not listed: --parts lists them)");
            }
        }
        JobsCommand::Watch(u) => {
            let mut c = connect(&u.orchestrator, &u.security).await?;
            watch(&mut c, None, &mut crate::Stdout).await?;
        }
        JobsCommand::Cancel(a) => {
            let mut c = connect(&a.url.orchestrator, &a.url.security).await?;
            let j = c
                .cancel_job(pb::JobRef { id: a.id })
                .await
                .with_context(|| format!("cancelling job {}", a.id))?;
            outln!("{}", describe(j.get_ref()));
        }
        JobsCommand::Retry(a) => {
            let mut c = connect(&a.url.orchestrator, &a.url.security).await?;
            let j = c
                .retry_job(pb::JobRef { id: a.id })
                .await
                .with_context(|| format!("retrying job {}", a.id))?;
            outln!("{}", describe(j.get_ref()));
        }
    }
    Ok(())
}
